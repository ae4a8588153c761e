//! Fisher information of a PSF stack: the 3×3 matrix over (x, y, z) of S3 with the noise floor
//! of S25, the precision loss L_prec = log Tr(I⁻¹) and the per-depth information I(z) (S25).
//!
//! Model: pixel mean μ = N·PSF (N = photon or electron budget per plane), variance
//! μ + σ² (Poisson shot noise plus Gaussian read noise folded in, as S25). Spatial gradients
//! are central differences over one pixel (zero on the border rows/columns), the depth
//! gradient the central difference across neighbouring planes (one-sided at the stack's ends).
//! Floors (documented in docs/fisher.md): the variance gets `min_var` so that dark, noiseless
//! pixels never divide by zero; I is regularized to I + λ·Id, λ = floor_abs + floor_rel·tr(I)/3,
//! so log Tr((I+λ)⁻¹) is finite for a singular I (zero or constant PSF).

#![allow(clippy::needless_range_loop)] // 3×3 index loops read like the formulas.

use crate::DesignLoss;
use crate::error::{FisherError, check_nonneg, check_positive};
use crate::stack::{PsfStack, StackGrad};

/// Photon budget, noise and numerical floors of the Fisher computations.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FisherNoise {
    /// Expected photons (or electrons) per unit PSF value: μ = photons · PSF.
    pub photons: f64,
    /// Additive noise variance σ² per pixel (read noise², same unit as μ).
    pub noise_var: f64,
    /// Variance floor added to μ + σ² (same unit as μ).
    pub min_var: f64,
    /// Absolute Fisher floor λ_abs, m⁻² (a CRLB of 1 m: inactive for any real PSF).
    pub floor_abs: f64,
    /// Relative Fisher floor: λ includes floor_rel · tr(I)/3 (caps the condition number).
    pub floor_rel: f64,
}

impl Default for FisherNoise {
    fn default() -> Self {
        FisherNoise {
            photons: 1e4,
            noise_var: 0.0,
            min_var: 1e-9,
            floor_abs: 1.0,
            floor_rel: 1e-9,
        }
    }
}

impl FisherNoise {
    fn validate(&self) -> Result<(), FisherError> {
        check_positive("photons", self.photons)?;
        check_nonneg("noise_var", self.noise_var)?;
        check_positive("min_var", self.min_var)?;
        check_positive("floor_abs", self.floor_abs)?;
        check_nonneg("floor_rel", self.floor_rel)
    }
}

type M3 = [[f64; 3]; 3];

/// Per-pixel gradient vector g = N ∇PSF (x, y, z) and variance d of plane `k` at pixel (r, c).
#[inline]
fn pixel(
    s: &PsfStack,
    k: usize,
    r: usize,
    c: usize,
    st: (usize, usize, f64),
    n: &FisherNoise,
) -> ([f64; 3], f64) {
    let rows = s.rows();
    let p = c * rows + r;
    let pl = s.plane(k);
    let h = 0.5 / s.pitch();
    let gx = if c > 0 && c + 1 < s.cols() {
        n.photons * (pl[p + rows] - pl[p - rows]) * h
    } else {
        0.0
    };
    let gy = if r > 0 && r + 1 < rows {
        n.photons * (pl[p + 1] - pl[p - 1]) * h
    } else {
        0.0
    };
    let gz = n.photons * (s.plane(st.1)[p] - s.plane(st.0)[p]) * st.2;
    ([gx, gy, gz], n.photons * pl[p] + n.noise_var + n.min_var)
}

fn stencil(s: &PsfStack, k: usize) -> Result<(usize, usize, f64), FisherError> {
    s.dz_stencil(k).ok_or(FisherError::Shape {
        name: "planes",
        why: "the depth derivative needs at least 2 planes".into(),
    })
}

/// Fisher matrix (S3 with the S25 noise floor) of plane `k` over (x, y, z), in m⁻².
pub fn fisher_matrix(s: &PsfStack, k: usize, noise: &FisherNoise) -> Result<M3, FisherError> {
    noise.validate()?;
    if k >= s.len() {
        return Err(FisherError::InvalidParameter {
            name: "plane",
            value: k as f64,
            why: "index out of range",
        });
    }
    let st = stencil(s, k)?;
    let mut m = [[0.0; 3]; 3];
    for c in 0..s.cols() {
        for r in 0..s.rows() {
            let (g, d) = pixel(s, k, r, c, st, noise);
            if g == [0.0; 3] {
                continue;
            }
            for i in 0..3 {
                for j in i..3 {
                    m[i][j] += g[i] * g[j] / d;
                }
            }
        }
    }
    for i in 0..3 {
        for j in 0..i {
            m[i][j] = m[j][i];
        }
    }
    Ok(m)
}

/// Backpropagates ∂L/∂I (`gi`, symmetric) of plane `k` into the plane gradients `out`.
fn backprop(
    s: &PsfStack,
    k: usize,
    noise: &FisherNoise,
    gi: &M3,
    out: &mut [Vec<f64>],
) -> Result<(), FisherError> {
    let st = stencil(s, k)?;
    let rows = s.rows();
    let h = 0.5 / s.pitch();
    let nph = noise.photons;
    let spatial =
        gi[0][0] != 0.0 || gi[1][1] != 0.0 || gi[0][1] != 0.0 || gi[0][2] != 0.0 || gi[1][2] != 0.0;
    for c in 0..s.cols() {
        for r in 0..rows {
            let (g, d) = pixel(s, k, r, c, st, noise);
            if g == [0.0; 3] {
                continue;
            }
            let p = c * rows + r;
            let mut gb = [0.0; 3];
            let mut q = 0.0;
            for i in 0..3 {
                let row: f64 = (0..3).map(|j| gi[i][j] * g[j]).sum();
                gb[i] = 2.0 * row / d;
                q += g[i] * row;
            }
            out[k][p] += nph * (-q / (d * d));
            if spatial {
                if c > 0 && c + 1 < s.cols() {
                    out[k][p + rows] += nph * gb[0] * h;
                    out[k][p - rows] -= nph * gb[0] * h;
                }
                if r > 0 && r + 1 < rows {
                    out[k][p + 1] += nph * gb[1] * h;
                    out[k][p - 1] -= nph * gb[1] * h;
                }
            }
            out[st.1][p] += nph * gb[2] * st.2;
            out[st.0][p] -= nph * gb[2] * st.2;
        }
    }
    Ok(())
}

/// Cholesky factor of a symmetric positive-definite 3×3 matrix (None if not SPD).
fn chol3(a: &M3) -> Option<M3> {
    let mut l = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..=i {
            let s: f64 = (0..j).map(|k| l[i][k] * l[j][k]).sum();
            if i == j {
                let v = a[i][i] - s;
                if v.is_nan() || v <= 0.0 {
                    return None;
                }
                l[i][i] = v.sqrt();
            } else {
                l[i][j] = (a[i][j] - s) / l[j][j];
            }
        }
    }
    Some(l)
}

/// Inverse of an SPD 3×3 matrix through its Cholesky factor (symmetric solve).
fn spd_inverse(a: &M3) -> Option<M3> {
    let l = chol3(a)?;
    let mut inv = [[0.0; 3]; 3];
    for col in 0..3 {
        let mut y = [0.0; 3];
        for i in 0..3 {
            let b = if i == col { 1.0 } else { 0.0 };
            y[i] = (b - (0..i).map(|k| l[i][k] * y[k]).sum::<f64>()) / l[i][i];
        }
        let mut x = [0.0; 3];
        for i in (0..3).rev() {
            x[i] = (y[i] - (i + 1..3).map(|k| l[k][i] * x[k]).sum::<f64>()) / l[i][i];
        }
        for i in 0..3 {
            inv[i][col] = x[i];
        }
    }
    Some(inv)
}

/// log Tr((I + λ Id)⁻¹) with λ = floor_abs + floor_rel·tr(I)/3, and its gradient w.r.t. I.
/// Finite for every finite symmetric positive-semidefinite I, singular ones included.
pub fn log_trace_inverse(
    i_mat: &M3,
    floor_abs: f64,
    floor_rel: f64,
) -> Result<(f64, M3), FisherError> {
    check_positive("floor_abs", floor_abs)?;
    check_nonneg("floor_rel", floor_rel)?;
    let tr = i_mat[0][0] + i_mat[1][1] + i_mat[2][2];
    if !tr.is_finite() || i_mat.iter().flatten().any(|v| !v.is_finite()) {
        return Err(FisherError::InvalidParameter {
            name: "fisher_matrix",
            value: tr,
            why: "the Fisher matrix is not finite (photon budget too large?)",
        });
    }
    let lambda = floor_abs + floor_rel * tr / 3.0;
    // Scale to unit mean eigenvalue before the solve: log Tr(A⁻¹) = log Tr(Â⁻¹) − log σ.
    let sigma = (tr + 3.0 * lambda) / 3.0;
    let mut a = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            let sym = 0.5 * (i_mat[i][j] + i_mat[j][i]);
            a[i][j] = (sym + if i == j { lambda } else { 0.0 }) / sigma;
        }
    }
    let inv = spd_inverse(&a).ok_or(FisherError::InvalidParameter {
        name: "fisher_matrix",
        value: tr,
        why: "the regularized Fisher matrix is not positive definite (negative eigenvalue)",
    })?;
    let t = inv[0][0] + inv[1][1] + inv[2][2];
    let value = t.ln() - sigma.ln();
    // dL/dA = −A⁻²/Tr(A⁻¹) with A = σ Â ⇒ A⁻¹ = Â⁻¹/σ; the σ cancels in the ratio up to 1/σ.
    let mut g = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            let s: f64 = (0..3).map(|k| inv[i][k] * inv[k][j]).sum();
            g[i][j] = -s / (t * sigma);
        }
    }
    let trg = g[0][0] + g[1][1] + g[2][2];
    for (i, row) in g.iter_mut().enumerate() {
        row[i] += floor_rel / 3.0 * trg;
    }
    Ok((value, g))
}

/// Precision loss (S3): mean over planes of log Tr(I_k⁻¹), I_k the (x, y, z) Fisher matrix.
#[derive(Clone, Debug, Default)]
pub struct Precision {
    /// Photon budget, noise and floors.
    pub noise: FisherNoise,
}

impl DesignLoss for Precision {
    fn value_and_grad(&self, s: &PsfStack) -> Result<(f64, StackGrad), FisherError> {
        let mut out = vec![vec![0.0; s.rows() * s.cols()]; s.len()];
        let mut total = 0.0;
        let w = 1.0 / s.len() as f64;
        for k in 0..s.len() {
            let m = fisher_matrix(s, k, &self.noise)?;
            let (v, mut g) = log_trace_inverse(&m, self.noise.floor_abs, self.noise.floor_rel)?;
            total += w * v;
            g.iter_mut().flatten().for_each(|x| *x *= w);
            backprop(s, k, &self.noise, &g, &mut out)?;
        }
        Ok((total, s.grad_from_buffers(out)))
    }
}

/// Fisher information about depth per plane (S25), m⁻²: Σ (∂μ/∂z)²/(μ + σ²).
pub fn depth_fisher(s: &PsfStack, noise: &FisherNoise) -> Result<Vec<f64>, FisherError> {
    noise.validate()?;
    let mut v = Vec::with_capacity(s.len());
    for k in 0..s.len() {
        let st = stencil(s, k)?;
        let rows = s.rows();
        let (lo, hi) = (s.plane(st.0), s.plane(st.1));
        let pl = s.plane(k);
        let mut acc = 0.0;
        for p in 0..rows * s.cols() {
            let g = noise.photons * (hi[p] - lo[p]) * st.2;
            if g != 0.0 {
                acc += g * g / (noise.photons * pl[p] + noise.noise_var + noise.min_var);
            }
        }
        v.push(acc);
    }
    Ok(v)
}

/// Depth-information loss: −ln(Σ_k I(z_k) + floor_abs) with I(z) of S25 (maximizes the
/// information summed over the depth range).
#[derive(Clone, Debug, Default)]
pub struct DepthFisher {
    /// Photon budget, noise and floors.
    pub noise: FisherNoise,
}

impl DesignLoss for DepthFisher {
    fn value_and_grad(&self, s: &PsfStack) -> Result<(f64, StackGrad), FisherError> {
        let per = depth_fisher(s, &self.noise)?;
        let total: f64 = per.iter().sum::<f64>() + self.noise.floor_abs;
        let mut out = vec![vec![0.0; s.rows() * s.cols()]; s.len()];
        let mut g = [[0.0; 3]; 3];
        g[2][2] = -1.0 / total;
        for k in 0..s.len() {
            backprop(s, k, &self.noise, &g, &mut out)?;
        }
        Ok((-total.ln(), s.grad_from_buffers(out)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn log_trace_inverse_matches_diagonal_closed_form_and_fd() {
        let m = [[4.0, 1.0, 0.5], [1.0, 3.0, 0.2], [0.5, 0.2, 2.0]];
        let (v, g) = log_trace_inverse(&m, 1e-12, 0.0).unwrap();
        let d = [[2.0, 0.0, 0.0], [0.0, 4.0, 0.0], [0.0, 0.0, 8.0]];
        let (vd, _) = log_trace_inverse(&d, 1e-12, 0.0).unwrap();
        assert!((vd - (0.5f64 + 0.25 + 0.125).ln()).abs() < 1e-9);
        for i in 0..3 {
            for j in 0..3 {
                let h = 1e-6;
                let mut p = m;
                let mut q = m;
                p[i][j] += h;
                q[i][j] -= h;
                let fd = (log_trace_inverse(&p, 1e-12, 0.0).unwrap().0
                    - log_trace_inverse(&q, 1e-12, 0.0).unwrap().0)
                    / (2.0 * h);
                assert!((fd - g[i][j]).abs() < 1e-6, "{i}{j}: {fd} vs {}", g[i][j]);
            }
        }
        assert!(v.is_finite());
    }

    #[test]
    fn singular_fisher_matrix_is_finite() {
        let (v, g) = log_trace_inverse(&[[0.0; 3]; 3], 1.0, 1e-9).unwrap();
        assert!((v - 3f64.ln()).abs() < 1e-12);
        assert!(g.iter().flatten().all(|x| x.is_finite()));
        let (v, _) = log_trace_inverse(
            &[[1e20, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]],
            1.0,
            1e-9,
        )
        .unwrap();
        assert!(v.is_finite());
    }
}

//! Optical-embedding terms of Sec. A.5 (S15) from an image triplet: a reference image I₀ and
//! images I₁, I₂ with motion parameter i perturbed by h_i. Sensitivity fields are
//! noise-whitened finite differences J_i = (I_i − I₀)/(h_i √(I₀ + σ² + v₀)), so F_ij = J_i·J_j
//! is the Fisher matrix of the two parameters; cos φ = F₁₂/√(F₁₁F₂₂).
//! Loss terms (our reading of main-paper Eq. 6, which the supplement does not print):
//! sensitivity L_sens = −½[ln(F₁₁ + f) + ln(F₂₂ + f)] and orthogonality L_orth = cos²φ,
//! with the floor f keeping both finite for vanishing sensitivity.

use crate::error::{FisherError, check_nonneg, check_positive};
use faer::Mat;

/// S15 quantities of one triplet.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct EmbeddingTerms {
    /// F₁₁ = ‖J₁‖².
    pub f11: f64,
    /// F₂₂ = ‖J₂‖².
    pub f22: f64,
    /// F₁₂ = J₁·J₂.
    pub f12: f64,
    /// cos φ = F₁₂/√((F₁₁+f)(F₂₂+f)).
    pub cos_phi: f64,
    /// Sensitivity term.
    pub l_sens: f64,
    /// Orthogonality term.
    pub l_orth: f64,
}

/// Gradient of w_sens·L_sens + w_orth·L_orth w.r.t. the three images.
#[derive(Clone, Debug)]
pub struct EmbeddingGrad {
    /// ∂L/∂I₀.
    pub d_i0: Mat<f64>,
    /// ∂L/∂I₁.
    pub d_i1: Mat<f64>,
    /// ∂L/∂I₂.
    pub d_i2: Mat<f64>,
}

/// Computes the S15 terms and the gradient of `w_sens·L_sens + w_orth·L_orth`.
/// Images in photons (or e⁻), steps `h` in the parameters' units, `noise_var` σ².
#[allow(clippy::too_many_arguments)]
pub fn optical_embedding(
    i0: &Mat<f32>,
    i1: &Mat<f32>,
    i2: &Mat<f32>,
    h: [f64; 2],
    noise_var: f64,
    floor: f64,
    w_sens: f64,
    w_orth: f64,
) -> Result<(EmbeddingTerms, EmbeddingGrad), FisherError> {
    let shape = (i0.nrows(), i0.ncols());
    for (name, m) in [("i1", i1), ("i2", i2)] {
        if (m.nrows(), m.ncols()) != shape {
            return Err(FisherError::Shape {
                name,
                why: format!("{}x{} vs {}x{}", m.nrows(), m.ncols(), shape.0, shape.1),
            });
        }
    }
    for (k, m) in [i0, i1, i2].iter().enumerate() {
        for c in 0..shape.1 {
            for r in 0..shape.0 {
                let v = m[(r, c)];
                if !v.is_finite() || v < 0.0 {
                    return Err(FisherError::InvalidPlane {
                        plane: k,
                        row: r,
                        col: c,
                    });
                }
            }
        }
    }
    for (name, v) in [("h1", h[0]), ("h2", h[1])] {
        if !(v.is_finite() && v != 0.0) {
            return Err(FisherError::InvalidParameter {
                name,
                value: v,
                why: "step must be finite and nonzero",
            });
        }
    }
    check_nonneg("noise_var", noise_var)?;
    check_positive("floor", floor)?;
    const V0: f64 = 1e-9;
    let (nr, nc) = shape;
    let w = |r: usize, c: usize| 1.0 / (f64::from(i0[(r, c)]) + noise_var + V0).sqrt();
    let (mut f11, mut f22, mut f12) = (0.0, 0.0, 0.0);
    for c in 0..nc {
        for r in 0..nr {
            let b = f64::from(i0[(r, c)]);
            let j1 = (f64::from(i1[(r, c)]) - b) * w(r, c) / h[0];
            let j2 = (f64::from(i2[(r, c)]) - b) * w(r, c) / h[1];
            f11 += j1 * j1;
            f22 += j2 * j2;
            f12 += j1 * j2;
        }
    }
    let (fa, fb) = (f11 + floor, f22 + floor);
    let root = (fa * fb).sqrt();
    let cos = f12 / root;
    let terms = EmbeddingTerms {
        f11,
        f22,
        f12,
        cos_phi: cos,
        l_sens: -0.5 * (fa.ln() + fb.ln()),
        l_orth: cos * cos,
    };
    let g11 = w_sens * (-0.5 / fa) + w_orth * (-cos * cos / fa);
    let g22 = w_sens * (-0.5 / fb) + w_orth * (-cos * cos / fb);
    let g12 = w_orth * 2.0 * cos / root;
    let mut d0 = Mat::<f64>::zeros(nr, nc);
    let mut d1 = Mat::<f64>::zeros(nr, nc);
    let mut d2 = Mat::<f64>::zeros(nr, nc);
    for c in 0..nc {
        for r in 0..nr {
            let b = f64::from(i0[(r, c)]);
            let wv = w(r, c);
            let (e1, e2) = (f64::from(i1[(r, c)]) - b, f64::from(i2[(r, c)]) - b);
            let (j1, j2) = (e1 * wv / h[0], e2 * wv / h[1]);
            let jb1 = 2.0 * g11 * j1 + g12 * j2;
            let jb2 = 2.0 * g22 * j2 + g12 * j1;
            let db1 = jb1 * wv / h[0];
            let db2 = jb2 * wv / h[1];
            let wb = jb1 * e1 / h[0] + jb2 * e2 / h[1];
            d1[(r, c)] = db1;
            d2[(r, c)] = db2;
            d0[(r, c)] = -db1 - db2 - 0.5 * wv * wv * wv * wb;
        }
    }
    Ok((
        terms,
        EmbeddingGrad {
            d_i0: d0,
            d_i1: d1,
            d_i2: d2,
        },
    ))
}

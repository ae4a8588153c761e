//! Chirp-z (Bluestein) evaluation of the sensor-window DFT.
//!
//! A window DFT row y_j = Σ_b df·e^{i2π df m_b (y₀ + j δ)} x_b, with consecutive band indices
//! m_b and sub-pixel spacing δ, is a linear convolution between chirps
//! (2 m j = m² + j² − (j − m)²). By FFT it costs two transforms of length ≈ N_b + W q per row
//! instead of the N_b·W q multiply–adds of a dense matrix product, and it is exact up to
//! rounding: no approximation enters.

use crate::psf::fast_fft_size;
use faer::c64;
use nanoeye_fft::{Fft, Planner};
use std::f64::consts::{PI, TAU};
use std::sync::Arc;

/// Vectors transformed per batched FFT call (bounds the buffer to CHUNK·len values).
const CHUNK: usize = 16;

/// The linear map y = A x, A[j, i] = post_j · k(j − i) · pre_i (j < n_out, i < n_in), applied
/// as a cyclic convolution of length `len ≥ n_in + n_out − 1`.
pub(crate) struct ChirpOp {
    pre: Vec<c64>,
    post: Vec<c64>,
    /// FFT of the kernel laid out cyclically, divided by `len` (rustfft is unnormalized).
    kernel_hat: Vec<c64>,
    fft: Arc<dyn Fft<f64>>,
    ifft: Arc<dyn Fft<f64>>,
}

impl ChirpOp {
    /// Builds the map from its pre- and post-multipliers and kernel k(t), t = j − i.
    pub(crate) fn new(
        planner: &mut Planner<f64>,
        pre: Vec<c64>,
        post: Vec<c64>,
        k: impl Fn(i64) -> c64,
    ) -> Self {
        let (n_in, n_out) = (pre.len(), post.len());
        let len = fast_fft_size(n_in + n_out - 1);
        let fft = planner.plan_fft_forward(len);
        let ifft = planner.plan_fft_inverse(len);
        let mut kernel = vec![c64::new(0.0, 0.0); len];
        for t in -(n_in as i64 - 1)..=(n_out as i64 - 1) {
            kernel[t.rem_euclid(len as i64) as usize] = k(t);
        }
        fft.process(&mut kernel);
        let inv = 1.0 / len as f64;
        kernel.iter_mut().for_each(|v| *v *= inv);
        Self {
            pre,
            post,
            kernel_hat: kernel,
            fft,
            ifft,
        }
    }

    /// The window DFT E[j, b] = df·e^{i2π df m_b (y₀ + j δ)} for m_b = m₀ + b, b < n_band,
    /// j < n_out, and its adjoint Eᴴ, both as chirp maps.
    pub(crate) fn window_dft(
        planner: &mut Planner<f64>,
        m0: i64,
        n_band: usize,
        n_out: usize,
        df: f64,
        y0: f64,
        delta: f64,
    ) -> (Self, Self) {
        let alpha = df * delta;
        // α n² reaches 10³–10⁴; reducing it mod 2 keeps the sin/cos arguments below 2π.
        let chirp = |a: f64, n: i64| {
            let n2 = (n as i128 * n as i128) as f64;
            c64::from_polar(1.0, PI * (a * n2).rem_euclid(2.0))
        };
        let pre: Vec<c64> = (0..n_band as i64)
            .map(|b| {
                let m = m0 + b;
                let lin = c64::from_polar(1.0, TAU * (df * m as f64 * y0).rem_euclid(1.0));
                lin * chirp(alpha, m)
            })
            .collect();
        let post: Vec<c64> = (0..n_out as i64).map(|j| chirp(alpha, j) * df).collect();
        // j − m_b = t − m₀ with t = j − b.
        let k = |t: i64| chirp(alpha, t - m0).conj();
        let adj_pre: Vec<c64> = post.iter().map(|v| v.conj()).collect();
        let adj_post: Vec<c64> = pre.iter().map(|v| v.conj()).collect();
        let fwd = Self::new(planner, pre, post, k);
        let adj = Self::new(planner, adj_pre, adj_post, |t| k(-t).conj());
        (fwd, adj)
    }

    /// Convolution length.
    pub(crate) fn len(&self) -> usize {
        self.kernel_hat.len()
    }

    /// Buffer length `apply` needs.
    pub(crate) fn buf_len(&self) -> usize {
        CHUNK * self.len()
    }

    /// Scratch length `apply` needs.
    pub(crate) fn scratch_len(&self) -> usize {
        self.fft
            .get_inplace_scratch_len()
            .max(self.ifft.get_inplace_scratch_len())
    }

    /// The pre-multipliers (one per input element).
    pub(crate) fn pre(&self) -> &[c64] {
        &self.pre
    }

    /// The post-multipliers (one per output element).
    pub(crate) fn post(&self) -> &[c64] {
        &self.post
    }

    /// Applies the bare convolution y = K x of the map y = diag(post)·K·diag(pre) x to `count`
    /// vectors: element i of input v is `get(v, i)`, element j of output v is passed to
    /// `set(v, j, y)`; `buf` and `scratch` have at least [`Self::buf_len`] and
    /// [`Self::scratch_len`] values. Callers fold the diagonals [`Self::pre`], [`Self::post`]
    /// into neighbouring operators (the PSF folds the window DFT's pre-multipliers into the
    /// transfer function and drops its unit-modulus post-multipliers, which |·|² does not see).
    pub(crate) fn apply_conv(
        &self,
        count: usize,
        buf: &mut [c64],
        scratch: &mut [c64],
        get: impl Fn(usize, usize) -> c64,
        mut set: impl FnMut(usize, usize, c64),
    ) {
        let len = self.len();
        let (n_in, n_out) = (self.pre.len(), self.post.len());
        let zero = c64::new(0.0, 0.0);
        let mut first = 0;
        while first < count {
            let nv = CHUNK.min(count - first);
            let buf = &mut buf[..nv * len];
            for (v, row) in buf.chunks_exact_mut(len).enumerate() {
                for (i, r) in row[..n_in].iter_mut().enumerate() {
                    *r = get(first + v, i);
                }
                row[n_in..].fill(zero);
            }
            self.convolve(buf, scratch);
            for (v, row) in buf.chunks_exact(len).enumerate() {
                for (j, r) in row[..n_out].iter().enumerate() {
                    set(first + v, j, *r);
                }
            }
            first += nv;
        }
    }

    /// The bare convolution in place on whole vectors of [`Self::len`] values each: input i
    /// of a vector at its index i (< n_in), zeros after; output j at index j (< n_out).
    pub(crate) fn convolve(&self, buf: &mut [c64], scratch: &mut [c64]) {
        self.fft.process_with_scratch(buf, scratch);
        for row in buf.chunks_exact_mut(self.len()) {
            row.iter_mut()
                .zip(&self.kernel_hat)
                .for_each(|(r, k)| *r *= k);
        }
        self.ifft.process_with_scratch(buf, scratch);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn dense(m0: i64, nb: usize, nout: usize, df: f64, y0: f64, delta: f64) -> Vec<Vec<c64>> {
        (0..nout)
            .map(|j| {
                (0..nb)
                    .map(|b| {
                        let m = (m0 + b as i64) as f64;
                        c64::from_polar(df, TAU * df * m * (y0 + j as f64 * delta))
                    })
                    .collect()
            })
            .collect()
    }

    /// The whole map diag(post)·K·diag(pre) applied to one vector.
    fn apply1(op: &ChirpOp, x: &[c64], n_out: usize) -> Vec<c64> {
        let mut buf = vec![c64::new(0.0, 0.0); op.buf_len()];
        let mut scratch = vec![c64::new(0.0, 0.0); op.scratch_len()];
        let mut y = vec![c64::new(0.0, 0.0); n_out];
        op.apply_conv(
            1,
            &mut buf,
            &mut scratch,
            |_, i| x[i] * op.pre()[i],
            |_, j, v| y[j] = v * op.post()[j],
        );
        y
    }

    #[test]
    fn chirp_z_equals_the_dense_window_dft_and_its_adjoint() {
        // A PSF-like case: band −60..=60 at df = 1/1.2 mm, 96 outputs at 0.75 µm, offset window.
        let (m0, nb, nout) = (-60_i64, 121_usize, 96_usize);
        let (df, y0, delta) = (1.0 / 1.2e-3, -3.7e-5 + 0.6e-3, 0.75e-6);
        let mut planner = Planner::new();
        let (fwd, adj) = ChirpOp::window_dft(&mut planner, m0, nb, nout, df, y0, delta);
        let e = dense(m0, nb, nout, df, y0, delta);
        let x: Vec<c64> = (0..nb)
            .map(|b| c64::new((b as f64 * 0.37).sin(), (b as f64 * 0.11).cos()))
            .collect();
        let y = apply1(&fwd, &x, nout);
        let scale: f64 = x.iter().map(|v| v.norm()).sum::<f64>() * df;
        for j in 0..nout {
            let d: c64 = (0..nb).map(|b| e[j][b] * x[b]).sum();
            assert!((d - y[j]).norm() < 1e-12 * scale, "j {j}: {d} vs {}", y[j]);
        }
        let g: Vec<c64> = (0..nout)
            .map(|j| c64::new((j as f64 * 0.23).cos(), (j as f64 * 0.71).sin()))
            .collect();
        let xa = apply1(&adj, &g, nb);
        let scale: f64 = g.iter().map(|v| v.norm()).sum::<f64>() * df;
        for b in 0..nb {
            let d: c64 = (0..nout).map(|j| e[j][b].conj() * g[j]).sum();
            assert!(
                (d - xa[b]).norm() < 1e-12 * scale,
                "b {b}: {d} vs {}",
                xa[b]
            );
        }
    }

    /// A second geometry; and the post-multipliers have modulus df, which the PSF relies on
    /// when it drops them from the field.
    #[test]
    fn bare_convolution_with_the_diagonals_applied_outside_equals_the_map() {
        let mut planner = Planner::new();
        let (m0, nb, nout, df) = (-11_i64, 23usize, 17usize, 1.0 / 173e-6);
        let (y0, delta) = (-41e-6, 0.37e-6);
        let (op, _) = ChirpOp::window_dft(&mut planner, m0, nb, nout, df, y0, delta);
        let x: Vec<c64> = (0..nb)
            .map(|b| c64::new((b as f64 * 0.29).cos(), (b as f64 * 0.53).sin()))
            .collect();
        let e = dense(m0, nb, nout, df, y0, delta);
        let y: Vec<c64> = e
            .iter()
            .map(|row| row.iter().zip(&x).map(|(a, b)| a * b).sum())
            .collect();
        let xp: Vec<c64> = x.iter().zip(op.pre()).map(|(a, p)| a * p).collect();
        let mut buf = vec![c64::new(0.0, 0.0); op.buf_len()];
        let mut scratch = vec![c64::new(0.0, 0.0); op.scratch_len()];
        let mut yc = vec![c64::new(0.0, 0.0); nout];
        op.apply_conv(1, &mut buf, &mut scratch, |_, i| xp[i], |_, j, v| yc[j] = v);
        let scale: f64 = x.iter().map(|v| v.norm()).sum::<f64>() * df;
        for j in 0..nout {
            let d = yc[j] * op.post()[j];
            assert!((d - y[j]).norm() < 1e-12 * scale, "j {j}: {d} vs {}", y[j]);
            assert!(
                (op.post()[j].norm() - df).abs() < 1e-12 * df,
                "post modulus"
            );
        }
    }
}

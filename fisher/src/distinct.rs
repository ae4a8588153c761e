//! Distinctness loss (S4): Σ_{i≠j} |z_i − z_j| · cos(PSF(z_i), PSF(z_j)), ordered pairs,
//! depths in metres. A plane's norm is √(‖P‖² + eps_norm) so an all-zero plane gives a
//! cosine of 0 and a finite gradient.

use crate::DesignLoss;
use crate::error::{FisherError, check_positive};
use crate::stack::{PsfStack, StackGrad};

/// S4 with the norm floor `eps_norm` (in PSF-value², default 1e-24).
#[derive(Clone, Debug)]
pub struct Distinctness {
    /// Added to ‖P‖² before the square root.
    pub eps_norm: f64,
}

impl Default for Distinctness {
    fn default() -> Self {
        Distinctness { eps_norm: 1e-24 }
    }
}

impl DesignLoss for Distinctness {
    fn value_and_grad(&self, s: &PsfStack) -> Result<(f64, StackGrad), FisherError> {
        check_positive("eps_norm", self.eps_norm)?;
        let k = s.len();
        let n = s.rows() * s.cols();
        let norms: Vec<f64> = (0..k)
            .map(|i| (s.plane(i).iter().map(|v| v * v).sum::<f64>() + self.eps_norm).sqrt())
            .collect();
        let mut out = vec![vec![0.0; n]; k];
        let mut total = 0.0;
        let z = s.depths();
        for i in 0..k {
            for j in i + 1..k {
                let (pi, pj) = (s.plane(i), s.plane(j));
                let dot: f64 = pi.iter().zip(pj).map(|(a, b)| a * b).sum();
                let cos = dot / (norms[i] * norms[j]);
                // Both ordered pairs (i, j) and (j, i) contribute.
                let w = 2.0 * (z[j] - z[i]).abs();
                total += w * cos;
                let (ai, bi) = (w / (norms[i] * norms[j]), w * cos / (norms[i] * norms[i]));
                let (aj, bj) = (ai, w * cos / (norms[j] * norms[j]));
                for p in 0..n {
                    out[i][p] += ai * pj[p] - bi * pi[p];
                    out[j][p] += aj * pi[p] - bj * pj[p];
                }
            }
        }
        Ok((total, s.grad_from_buffers(out)))
    }
}

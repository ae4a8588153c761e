//! Compactness loss (S5): mean over planes of the Shannon entropy −Σ P̂ log(P̂ + ε) of the
//! plane normalized to a probability mass function P̂ = P/(ΣP + eps_sum).

use crate::DesignLoss;
use crate::error::{FisherError, check_positive};
use crate::stack::{PsfStack, StackGrad};

/// S5 with the log floor `eps` (default 1e-12) and sum floor `eps_sum` (default 1e-30).
#[derive(Clone, Debug)]
pub struct Compactness {
    /// ε inside the logarithm.
    pub eps: f64,
    /// Added to the plane's sum before normalizing (zero planes stay finite).
    pub eps_sum: f64,
}

impl Default for Compactness {
    fn default() -> Self {
        Compactness {
            eps: 1e-12,
            eps_sum: 1e-30,
        }
    }
}

impl DesignLoss for Compactness {
    fn value_and_grad(&self, s: &PsfStack) -> Result<(f64, StackGrad), FisherError> {
        check_positive("eps", self.eps)?;
        check_positive("eps_sum", self.eps_sum)?;
        let n = s.rows() * s.cols();
        let w = 1.0 / s.len() as f64;
        let mut out = vec![vec![0.0; n]; s.len()];
        let mut total = 0.0;
        for (k, o) in out.iter_mut().enumerate() {
            let pl = s.plane(k);
            let sum = pl.iter().sum::<f64>() + self.eps_sum;
            // dH/dP̂_p = −(log(P̂+ε) + P̂/(P̂+ε)); dP̂_q/dP_p = (δ_pq − P̂_q)/S.
            let mut h = 0.0;
            let mut gdot = 0.0;
            for (p, &v) in pl.iter().enumerate() {
                let q = v / sum;
                let l = (q + self.eps).ln();
                h -= q * l;
                let g = -(l + q / (q + self.eps));
                o[p] = g;
                gdot += g * q;
            }
            total += w * h;
            for g in o.iter_mut() {
                *g = w * (*g - gdot) / sum;
            }
        }
        Ok((total, s.grad_from_buffers(out)))
    }
}

//! L_init of Sec. A.2: precision (S3), distinctness (S4) and compactness (S5) combined by the
//! auto-balanced composite (S6) with learnable log-variances s_k.

use crate::DesignLoss;
use crate::balance::kendall;
use crate::compact::Compactness;
use crate::distinct::Distinctness;
use crate::error::FisherError;
use crate::precision::Precision;
use crate::stack::{PsfStack, StackGrad};

/// Unit (m²) in which S6 sees L_prec = log Tr(I⁻¹): 1 µm².
///
/// S6's balancing needs L_k > 0 (its optimum over s_k is e^{s_k} = L_k). In m², log Tr(I⁻¹)
/// of a useful PSF is ≈ −22 (a 20 µm CRLB), so s_prec runs to its clamp and the composite
/// diverges to −∞ with L_prec weighted 10¹³ times the others. In µm² the same PSF gives ≈ +6
/// and stays positive down to a 1 µm CRLB; the change is a constant, so ∂L_prec/∂PSF is the same.
pub const PREC_UNIT_M2: f64 = 1e-12;

/// The three initialization losses, in the order (prec, dist, comp) of `log_vars`.
#[derive(Clone, Debug, Default)]
pub struct InitLoss {
    /// S3 term.
    pub precision: Precision,
    /// S4 term.
    pub distinct: Distinctness,
    /// S5 term.
    pub compact: Compactness,
}

/// One evaluation of L_init.
#[derive(Clone, Debug)]
pub struct InitEval {
    /// L_init (S6).
    pub value: f64,
    /// (L_prec in units of [`PREC_UNIT_M2`], L_dist, L_comp).
    pub terms: [f64; 3],
    /// ∂L_init/∂s_k.
    pub d_log_vars: [f64; 3],
    /// ∂L_init/∂PSF per plane.
    pub grad: StackGrad,
}

impl InitLoss {
    /// Evaluates L_init and its gradients at log-variances `log_vars` (s_k = log σ_k²).
    pub fn evaluate(&self, s: &PsfStack, log_vars: &[f64; 3]) -> Result<InitEval, FisherError> {
        let parts: [&dyn DesignLoss; 3] = [&self.precision, &self.distinct, &self.compact];
        let mut terms = [0.0; 3];
        let mut grads = Vec::with_capacity(3);
        for (k, l) in parts.iter().enumerate() {
            let (v, g) = l.value_and_grad(s)?;
            terms[k] = if k == 0 { v - PREC_UNIT_M2.ln() } else { v };
            grads.push(g);
        }
        let kd = kendall(&terms, log_vars)?;
        let mut grad = grads.pop().expect("three terms");
        for (kp, p) in grad.planes.iter_mut().enumerate() {
            for j in 0..p.ncols() {
                for i in 0..p.nrows() {
                    let mut v = kd.d_losses[2] * p[(i, j)];
                    for (k, g) in grads.iter().enumerate() {
                        v += kd.d_losses[k] * g.planes[kp][(i, j)];
                    }
                    p[(i, j)] = v;
                }
            }
        }
        Ok(InitEval {
            value: kd.value,
            terms,
            d_log_vars: [kd.d_log_vars[0], kd.d_log_vars[1], kd.d_log_vars[2]],
            grad,
        })
    }
}

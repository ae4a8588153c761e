//! Auto-balanced composite (S6) in the log-variance form of Kendall, Gal & Cipolla (CVPR 2018):
//! with s_k = log σ_k², L = Σ_k ½ e^{−s_k} L_k + ½ s_k, which equals S6 and is minimized over
//! s_k at e^{s_k} = L_k for L_k > 0. s_k is clamped to ±[`KENDALL_S_LIMIT`]: for a loss that
//! is ≤ 0 (log Tr I⁻¹ in m² is negative for good PSFs) the unconstrained optimum does not
//! exist, and the clamp keeps the composite bounded (that term then gets the largest weight).

use crate::error::FisherError;

/// Bound on |s_k|.
pub const KENDALL_S_LIMIT: f64 = 30.0;

/// Value and gradients of the Kendall composite.
#[derive(Clone, Debug, PartialEq)]
pub struct Kendall {
    /// L_init.
    pub value: f64,
    /// ∂L/∂L_k = ½ e^{−s_k}.
    pub d_losses: Vec<f64>,
    /// ∂L/∂s_k = ½ − ½ e^{−s_k} L_k (0 where s_k sits on the clamp and pushes outwards).
    pub d_log_vars: Vec<f64>,
}

/// Evaluates L = Σ ½ e^{−s_k} L_k + ½ s_k (S6) with s_k clamped to ±KENDALL_S_LIMIT.
pub fn kendall(losses: &[f64], log_vars: &[f64]) -> Result<Kendall, FisherError> {
    if losses.len() != log_vars.len() {
        return Err(FisherError::Shape {
            name: "log_vars",
            why: format!(
                "{} losses but {} log-variances",
                losses.len(),
                log_vars.len()
            ),
        });
    }
    if let Some(v) = losses.iter().chain(log_vars).find(|v| !v.is_finite()) {
        return Err(FisherError::InvalidParameter {
            name: "losses",
            value: *v,
            why: "must be finite",
        });
    }
    let mut value = 0.0;
    let mut d_losses = Vec::with_capacity(losses.len());
    let mut d_log_vars = Vec::with_capacity(losses.len());
    for (&l, &s0) in losses.iter().zip(log_vars) {
        let s = s0.clamp(-KENDALL_S_LIMIT, KENDALL_S_LIMIT);
        let e = (-s).exp();
        value += 0.5 * e * l + 0.5 * s;
        d_losses.push(0.5 * e);
        let ds = 0.5 - 0.5 * e * l;
        let pinned = (s0 <= -KENDALL_S_LIMIT && ds > 0.0) || (s0 >= KENDALL_S_LIMIT && ds < 0.0);
        d_log_vars.push(if pinned { 0.0 } else { ds });
    }
    Ok(Kendall {
        value,
        d_losses,
        d_log_vars,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn optimum_is_at_exp_s_equal_loss() {
        // Minimize over s by Newton steps (∂²L/∂s² = ½ e^{−s} L > 0): e^{s*} = L_k.
        let losses = [0.37, 2.5, 140.0];
        let mut s = vec![0.0; 3];
        for _ in 0..100 {
            let k = kendall(&losses, &s).unwrap();
            for i in 0..3 {
                let h = 0.5 * (-s[i]).exp() * losses[i];
                s[i] -= k.d_log_vars[i] / h;
            }
        }
        for i in 0..3 {
            assert!(
                (s[i].exp() - losses[i]).abs() < 1e-9 * losses[i],
                "{} vs {}",
                s[i].exp(),
                losses[i]
            );
        }
        // And it is a minimum: nudging s either way increases L.
        let v0 = kendall(&losses, &s).unwrap().value;
        for i in 0..3 {
            for d in [-1e-3, 1e-3] {
                let mut t = s.clone();
                t[i] += d;
                assert!(kendall(&losses, &t).unwrap().value > v0);
            }
        }
    }

    #[test]
    fn gradients_match_finite_differences() {
        let losses = [1.3, -0.7];
        let s = [0.4, -1.1];
        let k = kendall(&losses, &s).unwrap();
        let h = 1e-6;
        for i in 0..2 {
            let mut a = losses;
            let mut b = losses;
            a[i] += h;
            b[i] -= h;
            let fd = (kendall(&a, &s).unwrap().value - kendall(&b, &s).unwrap().value) / (2.0 * h);
            assert!((fd - k.d_losses[i]).abs() < 1e-8);
            let mut a = s;
            let mut b = s;
            a[i] += h;
            b[i] -= h;
            let fd = (kendall(&losses, &a).unwrap().value - kendall(&losses, &b).unwrap().value)
                / (2.0 * h);
            assert!((fd - k.d_log_vars[i]).abs() < 1e-8);
        }
    }
}

//! Task losses of A.3: Dice (S7) on sigmoid mask probabilities, MSE (S8) on slippage, and
//! their sum L_task = L_seg + λ_slip·L_calib. Losses are accumulated in f64.

use crate::error::{NetsError, Result};
use crate::tensor::Tensor;

/// Dice smoothing ε of S7.
pub const DICE_EPS: f64 = 1.0;

fn sigmoid(x: f32) -> f64 {
    1.0 / (1.0 + (-(x as f64)).exp())
}

/// Per image of a Dice batch: its logits, its target, I = Σ M·M* and den = Σ (M + M*) + ε
/// (f64), after the shape checks S7's loss and its target gradient share.
fn dice_images<'a>(
    logits: &'a Tensor,
    target: &'a Tensor,
) -> Result<impl Iterator<Item = (&'a [f32], &'a [f32], f64, f64)>> {
    logits.check_same(target, "dice target")?;
    if logits.n == 0 {
        return Err(NetsError::Shape("dice loss of an empty batch".into()));
    }
    let per = logits.c * logits.plane();
    Ok((0..logits.n).map(move |n| {
        let l = &logits.data[n * per..][..per];
        let t = &target.data[n * per..][..per];
        let (mut inter, mut sum) = (0.0f64, 0.0f64);
        for (&lv, &tv) in l.iter().zip(t) {
            let m = sigmoid(lv);
            inter += m * tv as f64;
            sum += m + tv as f64;
        }
        (l, t, inter, sum + DICE_EPS)
    }))
}

/// Mean over images of S7 with M = σ(logits); returns (loss, dL/dlogits).
pub fn dice_loss(logits: &Tensor, target: &Tensor) -> Result<(f64, Tensor)> {
    let mut grad = Tensor::zeros(logits.n, logits.c, logits.h, logits.w);
    let per = logits.c * logits.plane();
    let mut total = 0.0f64;
    for (n, (l, t, inter, den)) in dice_images(logits, target)?.enumerate() {
        total += 1.0 - 2.0 * inter / den;
        let g = &mut grad.data[n * per..][..per];
        for ((gv, &lv), &tv) in g.iter_mut().zip(l).zip(t) {
            let m = sigmoid(lv);
            let dm = -2.0 * tv as f64 / den + 2.0 * inter / (den * den);
            *gv = (dm * m * (1.0 - m) / logits.n as f64) as f32;
        }
    }
    Ok((total / logits.n as f64, grad))
}

/// ∂(S7 mean over images)/∂target for M = σ(logits): the Dice loss's gradient w.r.t. a soft
/// target M* that itself depends on a parameter (the mask averaged onto the p̂ grid).
pub fn dice_target_grad(logits: &Tensor, target: &Tensor) -> Result<Tensor> {
    let mut grad = Tensor::zeros(logits.n, logits.c, logits.h, logits.w);
    let per = logits.c * logits.plane();
    for (n, (l, _, inter, den)) in dice_images(logits, target)?.enumerate() {
        // L = 1 − 2I/den with ∂I/∂t = m and ∂den/∂t = 1.
        let g = &mut grad.data[n * per..][..per];
        for (gv, &lv) in g.iter_mut().zip(l) {
            let m = sigmoid(lv);
            *gv = ((-2.0 * m / den + 2.0 * inter / (den * den)) / logits.n as f64) as f32;
        }
    }
    Ok(grad)
}

/// Mean over images of S8, ‖Δt − Δt*‖²; `pred`, `target` are (N, 3, 1, 1). Returns (loss, dL/dpred).
pub fn slip_mse(pred: &Tensor, target: &Tensor) -> Result<(f64, Tensor)> {
    pred.check_same(target, "slippage target")?;
    if pred.n == 0 {
        return Err(NetsError::Shape("slippage loss of an empty batch".into()));
    }
    let nb = pred.n as f64;
    let mut grad = Tensor::zeros(pred.n, pred.c, pred.h, pred.w);
    let mut total = 0.0f64;
    for ((g, &p), &t) in grad.data.iter_mut().zip(&pred.data).zip(&target.data) {
        let d = p as f64 - t as f64;
        total += d * d;
        *g = (2.0 * d / nb) as f32;
    }
    Ok((total / nb, grad))
}

/// Hard Dice 2|A∩B|/(|A|+|B|) of the thresholded mask (logit > 0) against a {0,1} target,
/// averaged over images (1 when both are empty).
pub fn hard_dice(logits: &Tensor, target: &Tensor) -> Result<f64> {
    logits.check_same(target, "dice target")?;
    let per = logits.c * logits.plane();
    let mut total = 0.0;
    for n in 0..logits.n {
        let (mut i, mut s) = (0.0f64, 0.0f64);
        for (&l, &t) in logits.data[n * per..][..per]
            .iter()
            .zip(&target.data[n * per..][..per])
        {
            let p = if l > 0.0 { 1.0 } else { 0.0 };
            let t = if t > 0.5 { 1.0 } else { 0.0 };
            i += p * t;
            s += p + t;
        }
        total += if s == 0.0 { 1.0 } else { 2.0 * i / s };
    }
    Ok(total / logits.n.max(1) as f64)
}

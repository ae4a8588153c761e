//! The task loss of A.3 through the supernet: L_task = L_seg (Dice, S7) + λ_slip·L_calib (slip
//! MSE, S8, in mm²) summed over the subnets of a step (S22), with ∂L/∂input for the camera chain.
//! Slippage targets and predictions are in millimetres so L_calib is O(1) (docs/chain.md).

use crate::error::{Result, param};
use nanoeye_nets::loss::{dice_loss, slip_mse};
use nanoeye_nets::{Arch, BnMode, Supernet, Tensor};

/// Loss parts summed over subnets.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct TaskLoss {
    /// Σ over subnets of L_seg + λ_slip·L_calib.
    pub total: f64,
    /// Σ L_seg (Dice loss, dimensionless).
    pub seg: f64,
    /// Σ L_calib (mm²).
    pub calib: f64,
}

/// Forward and backward of every subnet in `archs` on `input` with targets `mask`
/// (N, 1, H, W) and `slip_mm` (N, 3, 1, 1). Parameter gradients accumulate in `net` (the caller
/// zeroes them); returns the loss and ∂L/∂input summed over subnets.
pub fn task_loss(
    net: &mut Supernet,
    archs: &[Arch],
    input: &Tensor,
    mask: &Tensor,
    slip_mm: &Tensor,
    lambda_slip: f64,
    mode: BnMode,
) -> Result<(TaskLoss, Tensor)> {
    if archs.is_empty() {
        return Err(param("subnets", "need at least one subnet"));
    }
    if !(lambda_slip.is_finite() && lambda_slip >= 0.0) {
        return Err(param(
            "lambda_slip",
            format!("must be finite and ≥ 0, got {lambda_slip}"),
        ));
    }
    let mut out = TaskLoss::default();
    let mut dx = Tensor::zeros(input.n, input.c, input.h, input.w);
    for a in archs {
        let o = net.forward(a, input, mode)?;
        let (seg, d_logits) = dice_loss(&o.mask_logits, mask)?;
        let (calib, mut d_slip) = slip_mse(&o.slip, slip_mm)?;
        d_slip
            .data
            .iter_mut()
            .for_each(|v| *v *= lambda_slip as f32);
        let g = net.backward(&d_logits, &d_slip)?;
        dx.add_assign(&g);
        out.seg += seg;
        out.calib += calib;
        out.total += seg + lambda_slip * calib;
    }
    Ok((out, dx))
}

//! The task loss of A.3 through the supernet: L_task = L_seg (Dice, S7) + λ_slip·L_calib (slip
//! MSE, S8, in mm²) summed over the subnets of a step (S22), with ∂L/∂input for the camera chain.
//! Slippage targets and predictions are in millimetres so L_calib is O(1) (docs/chain.md).
//! λ_slip may differ per axis (x, y, z): the loss is then Σ_a λ_a·mean_n (Δt_a − Δt*_a)².

use crate::error::{Result, param};
use nanoeye_nets::loss::{dice_loss, dice_target_grad, slip_mse};
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

/// Gradients of [`task_loss`] w.r.t. the chain's outputs, summed over subnets.
#[derive(Clone, Debug)]
pub struct TaskGrads {
    /// ∂L/∂input (N, 1, H, W).
    pub input: Tensor,
    /// ∂L/∂mask (N, 1, H, W): the segmentation target is the pupil mask averaged onto the p̂
    /// grid, so it moves with p̂ ([`crate::CameraChain::target_backward`]).
    pub mask: Tensor,
}

/// Forward and backward of every subnet in `archs` on `input` with targets `mask`
/// (N, 1, H, W) and `slip_mm` (N, 3, 1, 1), λ_slip per axis (x, y, z; per mm²). Parameter
/// gradients accumulate in `net` (the caller zeroes them); returns the loss and its gradients
/// w.r.t. the input and the mask target, summed over subnets.
pub fn task_loss(
    net: &mut Supernet,
    archs: &[Arch],
    input: &Tensor,
    mask: &Tensor,
    slip_mm: &Tensor,
    lambda_slip: [f64; 3],
    mode: BnMode,
) -> Result<(TaskLoss, TaskGrads)> {
    if archs.is_empty() {
        return Err(param("subnets", "need at least one subnet"));
    }
    // At most `TrainConfig`'s largest weight times its largest axis weight.
    if !lambda_slip.iter().all(|l| (0.0..=1e6).contains(l)) {
        return Err(param(
            "lambda_slip",
            format!("must lie in [0, 1e6] on every axis, got {lambda_slip:?}"),
        ));
    }
    if slip_mm.c != 3 || slip_mm.plane() != 1 {
        return Err(param(
            "slip_mm",
            format!("need (N, 3, 1, 1) targets, got {:?}", slip_mm.shape()),
        ));
    }
    let mut out = TaskLoss::default();
    let mut dx = Tensor::zeros(input.n, input.c, input.h, input.w);
    let mut dm = Tensor::zeros(mask.n, mask.c, mask.h, mask.w);
    for a in archs {
        let o = net.forward(a, input, mode)?;
        let (seg, d_logits) = dice_loss(&o.mask_logits, mask)?;
        dm.add_assign(&dice_target_grad(&o.mask_logits, mask)?);
        let (calib, mut d_slip) = slip_mse(&o.slip, slip_mm)?;
        // (N, 3, 1, 1): element i is axis i mod 3.
        for (i, v) in d_slip.data.iter_mut().enumerate() {
            *v *= lambda_slip[i % 3] as f32;
        }
        let g = net.backward(&d_logits, &d_slip)?;
        dx.add_assign(&g);
        out.seg += seg;
        out.calib += calib;
        out.total += seg + weighted_calib(&o.slip, slip_mm, calib, lambda_slip);
    }
    Ok((
        out,
        TaskGrads {
            input: dx,
            mask: dm,
        },
    ))
}

/// Σ_a λ_a·mean_n (Δt_a − Δt*_a)²; with one λ for all axes, λ·`calib` (the same value in the
/// same rounding as before the weights were per axis, so training histories stay bit-identical).
fn weighted_calib(pred: &Tensor, target: &Tensor, calib: f64, lambda: [f64; 3]) -> f64 {
    if lambda[0] == lambda[1] && lambda[1] == lambda[2] {
        return lambda[0] * calib;
    }
    let n = pred.n.max(1) as f64;
    pred.data
        .iter()
        .zip(&target.data)
        .enumerate()
        .map(|(i, (&p, &t))| lambda[i % 3] * (p as f64 - t as f64).powi(2))
        .sum::<f64>()
        / n
}

#[cfg(test)]
mod tests {
    use super::*;
    use nanoeye_nets::SupernetConfig;

    fn setup() -> (Supernet, Tensor, Tensor, Tensor) {
        let cfg = SupernetConfig {
            head_expand: 16,
            head_hidden: 8,
            ..SupernetConfig::default()
        };
        let net = Supernet::new(cfg, 3).unwrap();
        let (n, h, w) = (2, 32, 32);
        let input = Tensor::from_vec(
            n,
            1,
            h,
            w,
            (0..n * h * w)
                .map(|i| ((i * 37) % 101) as f32 / 101.0)
                .collect(),
        )
        .unwrap();
        let mask = Tensor::from_vec(
            n,
            1,
            h,
            w,
            (0..n * h * w)
                .map(|i| {
                    if (i % w) > 12 && (i % w) < 20 {
                        1.0
                    } else {
                        0.0
                    }
                })
                .collect(),
        )
        .unwrap();
        let slip = Tensor::from_vec(n, 3, 1, 1, vec![1.0, -2.0, 0.5, -0.5, 3.0, -1.0]).unwrap();
        (net, input, mask, slip)
    }

    fn run(lambda: [f64; 3], slip: &Tensor) -> (TaskLoss, Tensor, Vec<f32>) {
        let (mut net, input, mask, _) = setup();
        net.zero_grad();
        let (l, dx) = task_loss(
            &mut net,
            &[Arch::min()],
            &input,
            &mask,
            slip,
            lambda,
            BnMode::Train,
        )
        .unwrap();
        let mut grads = Vec::new();
        net.visit(&mut |_, p| grads.extend_from_slice(&p.grad));
        (l, dx.input, grads)
    }

    /// An axis weighted 0 drops out of the loss: moving its target changes neither the loss nor
    /// any gradient, while the same move on a weighted axis does; and the weighted loss is
    /// Σ_a λ_a·MSE_a of the unweighted errors.
    #[test]
    fn per_axis_weights_weigh_each_axis_alone() {
        let (_, _, _, slip) = setup();
        let lambda = [0.0, 0.3, 1.2];
        let (l0, dx0, g0) = run(lambda, &slip);
        let mut moved = slip.clone();
        moved.data[0] += 5.0;
        moved.data[3] -= 2.0;
        let (l1, dx1, g1) = run(lambda, &moved);
        assert_eq!(l0.total, l1.total);
        assert_eq!(dx0.data, dx1.data);
        assert_eq!(g0, g1);
        assert!(l1.calib > l0.calib, "the reported MSE stays unweighted");
        let (l2, dx2, _) = run([1.0, 0.3, 1.2], &moved);
        assert!(l2.total > l1.total && dx2.data != dx1.data);
        // Σ_a λ_a·MSE_a against the same predictions (the weights do not change the forward).
        let (mut net, input, _, _) = setup();
        let pred = net
            .forward(&Arch::min(), &input, BnMode::Train)
            .unwrap()
            .slip;
        let mut by_axis = [0.0f64; 3];
        for (i, (&p, &t)) in pred.data.iter().zip(&moved.data).enumerate() {
            by_axis[i % 3] += (p as f64 - t as f64).powi(2) / 2.0;
        }
        let want: f64 = lambda.iter().zip(&by_axis).map(|(l, m)| l * m).sum();
        assert!(
            (l1.total - l1.seg - want).abs() <= 1e-9 * want.max(1.0),
            "{} vs {want}",
            l1.total - l1.seg
        );
    }

    /// Equal weights are the scalar λ bit for bit (training histories of earlier builds hold).
    #[test]
    fn equal_weights_are_the_scalar_lambda() {
        let (_, _, _, slip) = setup();
        let (l, _, _) = run([0.3; 3], &slip);
        assert_eq!(l.total, l.seg + 0.3 * l.calib);
    }

    #[test]
    fn a_negative_or_nan_axis_weight_is_refused() {
        let (mut net, input, mask, slip) = setup();
        for bad in [[0.1, -1.0, 0.1], [f64::NAN, 0.1, 0.1]] {
            let e = task_loss(
                &mut net,
                &[Arch::min()],
                &input,
                &mask,
                &slip,
                bad,
                BnMode::Train,
            )
            .unwrap_err();
            assert!(e.to_string().contains("lambda_slip"), "{e}");
        }
    }
}

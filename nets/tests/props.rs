//! Numerical-stability properties under extreme but legal inputs.

use nanoeye_nets::Tensor;
use nanoeye_nets::act::Act;
use nanoeye_nets::loss::{dice_loss, hard_dice, slip_mse};
use nanoeye_nets::norm::{BatchNorm, BnMode};
use nanoeye_nets::resize::bilinear_forward;
use proptest::prelude::*;

proptest! {
    #![proptest_config(ProptestConfig::with_cases(32))]

    /// Constant channels (zero variance) and huge offsets still normalize to finite values.
    #[test]
    fn batchnorm_constant_and_huge_inputs_stay_finite(v in -1e6f32..1e6, spread in 0.0f32..1e-3) {
        let data: Vec<f32> = (0..2 * 3 * 4).map(|i| v + spread * (i % 5) as f32).collect();
        let x = Tensor::from_vec(2, 3, 2, 2, data).unwrap();
        let mut bn = BatchNorm::new(3);
        let y = bn.forward(&x, BnMode::Train).unwrap();
        prop_assert!(y.data.iter().all(|a| a.is_finite() && a.abs() < 1e4));
        let dx = bn.backward(&Tensor { data: vec![1.0; 24], ..y }).unwrap();
        prop_assert!(dx.data.iter().all(|a| a.is_finite()));
    }

    /// Saturated logits give a finite Dice loss in [0, 1] and finite gradients.
    #[test]
    fn dice_saturated_logits_are_finite(l in prop::collection::vec(-1e30f32..1e30, 16), bits in 0u16..) {
        let logits = Tensor::from_vec(1, 1, 4, 4, l).unwrap();
        let target = Tensor::from_vec(1, 1, 4, 4, (0..16).map(|i| ((bits >> i) & 1) as f32).collect()).unwrap();
        let (loss, g) = dice_loss(&logits, &target).unwrap();
        prop_assert!((0.0..=1.0).contains(&loss));
        prop_assert!(g.data.iter().all(|v| v.is_finite()));
        let d = hard_dice(&logits, &target).unwrap();
        prop_assert!((0.0..=1.0).contains(&d));
    }

    /// Activations are finite and bounded by their closed-form envelopes everywhere.
    #[test]
    fn activations_bounded(x in -1e30f32..1e30) {
        prop_assert!((0.0..=1.0).contains(&Act::HSigmoid.apply(x)));
        let hs = Act::HSwish.apply(x);
        prop_assert!(hs.is_finite() && hs >= -0.375 && (hs <= x.max(0.0)));
    }

    /// Bilinear resampling is a convex combination: output within the input's range.
    #[test]
    fn bilinear_within_range(h in 1usize..9, w in 1usize..9, oh in 1usize..40, ow in 1usize..40, s in -1e20f32..1e20) {
        let x = Tensor::from_vec(1, 1, h, w, (0..h * w).map(|i| s * ((i * 37 % 11) as f32 - 5.0)).collect()).unwrap();
        let (lo, hi) = x.data.iter().fold((f32::MAX, f32::MIN), |(a, b), &v| (a.min(v), b.max(v)));
        let y = bilinear_forward(&x, oh, ow);
        let tol = 1e-5 * hi.abs().max(lo.abs()).max(1.0);
        prop_assert!(y.data.iter().all(|&v| v >= lo - tol && v <= hi + tol));
    }
}

#[test]
fn losses_reject_mismatched_shapes() {
    let a = Tensor::zeros(1, 1, 4, 4);
    let b = Tensor::zeros(1, 1, 4, 5);
    assert!(dice_loss(&a, &b).is_err());
    assert!(slip_mse(&Tensor::zeros(2, 3, 1, 1), &Tensor::zeros(1, 3, 1, 1)).is_err());
    assert!(Tensor::from_vec(1, 1, 2, 2, vec![0.0; 3]).is_err());
}

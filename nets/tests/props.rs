//! Numerical-stability properties under extreme but legal inputs.

use nanoeye_nets::Tensor;
use nanoeye_nets::act::Act;
use nanoeye_nets::conv::{depthwise_forward, depthwise_vjp, out_size};
use nanoeye_nets::loss::{dice_loss, hard_dice, slip_mse};
use nanoeye_nets::norm::{BatchNorm, BnMode};
use nanoeye_nets::resize::bilinear_forward;
use nanoeye_nets::{Arch, Inference, Supernet, SupernetConfig};
use proptest::prelude::*;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Largest |a − b| over two equally long slices.
fn maxdiff(a: &[f32], b: &[f32]) -> f32 {
    a.iter()
        .zip(b)
        .fold(0.0f32, |m, (p, q)| m.max((p - q).abs()))
}

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

    /// The compiled batch-1 path computes the supernet's eval-mode function for any input size
    /// and subnet, down to one-pixel planes (depthwise windows clipped on every side, resizes
    /// to and from a single pixel), within a few times what two-ulp changes of the parameters
    /// and the input move the reference.
    #[test]
    fn inference_matches_the_supernet_for_any_size_and_subnet(
        h in 1usize..40,
        w in 1usize..40,
        seed in 0u64..1 << 20,
    ) {
        inference_matches_the_supernet(h, w, seed)?;
    }

    /// Depthwise forward and backward at any scale up to where k²·|x|·|w| nears f32's range,
    /// on any plane size, stride and channel count (so both the plane path and the
    /// eight-channel blocks): finite and within rounding of the f64 definition.
    #[test]
    fn depthwise_any_scale_matches_the_definition(
        h in 1usize..20,
        w in 1usize..20,
        kc in 0usize..4,
        s in 1usize..3,
        blocks in 1usize..3,
        odd in any::<bool>(),
        scale in -30i32..17,
        seed in 0u64..1 << 20,
    ) {
        let (k, c) = ([1, 3, 5, 7][kc], 8 * blocks + usize::from(odd));
        let a = 10f32.powi(scale);
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut draw = |n: usize| -> Vec<f32> { (0..n).map(|_| a * rng.random_range(-1.0f32..1.0)).collect() };
        let (ho, wo) = (out_size(h, k, s), out_size(w, k, s));
        let x = Tensor::from_vec(2, c, h, w, draw(2 * c * h * w)).unwrap();
        let wt = draw(c * k * k);
        let dy = Tensor::from_vec(2, c, ho, wo, draw(2 * c * ho * wo)).unwrap();
        let y = depthwise_forward(&x, &wt, k, s).unwrap();
        let mut dw = vec![0.0f32; c * k * k];
        let dx = depthwise_vjp(&x, &wt, k, s, &dy, &mut dw).unwrap();
        let p = (k / 2) as isize;
        let (mut y0, mut dx0, mut dw0) = (vec![0.0f64; y.len()], vec![0.0f64; x.len()], vec![0.0f64; dw.len()]);
        // The sums of magnitudes of each value's terms, which bound its rounding error.
        let (mut ym, mut dxm, mut dwm) = (vec![0.0f64; y.len()], vec![0.0f64; x.len()], vec![0.0f64; dw.len()]);
        for n in 0..2 {
            for ch in 0..c {
                for oy in 0..ho {
                    for ox in 0..wo {
                        for ky in 0..k {
                            for kx in 0..k {
                                let (iy, ix) = ((oy * s + ky) as isize - p, (ox * s + kx) as isize - p);
                                if iy < 0 || ix < 0 || iy >= h as isize || ix >= w as isize {
                                    continue;
                                }
                                let xi = ((n * c + ch) * h + iy as usize) * w + ix as usize;
                                let yi = ((n * c + ch) * ho + oy) * wo + ox;
                                let t = ch * k * k + ky * k + kx;
                                let (xv, wv, gv) = (x.data[xi] as f64, wt[t] as f64, dy.data[yi] as f64);
                                y0[yi] += wv * xv;
                                ym[yi] += (wv * xv).abs();
                                dx0[xi] += wv * gv;
                                dxm[xi] += (wv * gv).abs();
                                dw0[t] += xv * gv;
                                dwm[t] += (xv * gv).abs();
                            }
                        }
                    }
                }
            }
        }
        // Terms per value: k² for y and dL/dx, all outputs of both images for dL/dw.
        let checks = [
            ("y", &y.data, &y0, &ym, k * k),
            ("dx", &dx.data, &dx0, &dxm, k * k),
            ("dw", &dw, &dw0, &dwm, 2 * ho * wo + 1),
        ];
        for (what, got, want, mag, terms) in checks {
            for (i, ((&g, &v), &m)) in got.iter().zip(want.iter()).zip(mag.iter()).enumerate() {
                prop_assert!(g.is_finite(), "{what}[{i}] = {g}");
                // A recursive f32 sum of n terms (inputs exact in f64) errs by at most
                // (n + 1)·2⁻²⁴ of the sum of magnitudes, plus what rounding products below
                // f32's normal range can lose.
                let tol = (terms + 1) as f64 * 2f64.powi(-24) * m + 1e-37;
                prop_assert!((g as f64 - v).abs() <= tol, "{what}[{i}] {g} vs {v} (|terms| {m}) k {k} s {s} c {c} {h}x{w}");
            }
        }
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

/// The property above for one input size (`h` × `w` pixels) and network/subnet/image `seed`.
fn inference_matches_the_supernet(h: usize, w: usize, seed: u64) -> Result<(), TestCaseError> {
    let cfg = SupernetConfig {
        head_expand: 48,
        head_hidden: 32,
        ..SupernetConfig::default()
    };
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let arch = Arch::sample(&mut rng);
    let mut img = || -> Vec<f32> { (0..h * w).map(|_| rng.random_range(0.0..1.0)).collect() };
    // Eight images, so that even the 1-pixel planes of the deep stages get BN statistics
    // from more than a couple of samples (with two, an untrained net's logits reach 1e14
    // and the comparison measures f32 chaos, not the compiled path).
    let calib: Vec<f32> = (0..8).flat_map(|_| img()).collect();
    let calib = Tensor::from_vec(8, 1, h, w, calib).unwrap();
    let x = img();
    let mut net = Supernet::new(cfg, seed).unwrap();
    net.recalibrate_bn(&arch, &[calib]).unwrap();
    // Every parameter and BN statistic, in visiting order, to restore after each probe.
    let mut saved = Vec::new();
    net.visit(&mut |_, p| saved.extend_from_slice(&p.value));
    net.visit_bn(&mut |_, bn| {
        saved.extend_from_slice(&bn.running_mean);
        saved.extend_from_slice(&bn.running_var);
    });
    // The network's output with every parameter, BN statistic and input value v changed to
    // v·(1 + sign·r·2⁻²²), r = ±1 drawn from the generator seeded by `flip` (about 2 ulp),
    // or left as they are without one; the network is restored afterwards.
    let mut probe = |flip: Option<(u64, f32)>| {
        let mut r = flip.map(|(s, sign)| (ChaCha8Rng::seed_from_u64(s), sign));
        let mut ulp2 = |v: &mut f32| {
            if let Some((r, sign)) = &mut r {
                *v *= 1.0 + if r.random::<bool>() { *sign } else { -*sign } * 2f32.powi(-22);
            }
        };
        net.visit(&mut |_, p| p.value.iter_mut().for_each(&mut ulp2));
        net.visit_bn(&mut |_, bn| {
            bn.running_mean.iter_mut().for_each(&mut ulp2);
            bn.running_var.iter_mut().for_each(&mut ulp2);
        });
        let mut xp = x.clone();
        xp.iter_mut().for_each(&mut ulp2);
        let out = net
            .forward(
                &arch,
                &Tensor::from_vec(1, 1, h, w, xp).unwrap(),
                BnMode::Eval,
            )
            .unwrap();
        let mut it = saved.iter();
        let mut put = |v: &mut f32| *v = *it.next().unwrap();
        net.visit(&mut |_, p| p.value.iter_mut().for_each(&mut put));
        net.visit_bn(&mut |_, bn| {
            bn.running_mean.iter_mut().for_each(&mut put);
            bn.running_var.iter_mut().for_each(&mut put);
        });
        out
    };
    let want = probe(None);
    // How far f32 rounding alone moves the reference here: networks and inputs with every
    // value changed by ±2 ulp. Rounding enters at every layer (the compiled path folds BN into
    // the weights and sums in other orders), so the parameters are perturbed as well as the
    // input. And the changes come in opposite pairs: an untrained net can sit at a kink (ReLU,
    // clamp) with a huge one-sided gain, where only one sign of a change moves it. An
    // input-only probe of three independent draws missed such a case (h = 28, w = 25, seed =
    // 119321: half of all 2-ulp changes move its logits by 7 %, as much as the compiled path
    // does, the others by 10⁻⁴; 13 of 15 opposite pairs catch it). Untrained nets with BN
    // statistics from a few pixels amplify changes by up to ~10³ through 20 blocks even away
    // from kinks; the compiled path must stay within a few of them.
    let (mut near_logits, mut near_slip) = (0.0f32, 0.0f32);
    for trial in 1..=3u64 {
        for sign in [1.0, -1.0] {
            let near = probe(Some((seed ^ (trial << 40), sign)));
            near_logits = near_logits.max(maxdiff(&near.mask_logits.data, &want.mask_logits.data));
            near_slip = near_slip.max(maxdiff(&near.slip.data, &want.slip.data));
        }
    }
    let scale = want
        .mask_logits
        .data
        .iter()
        .fold(1.0f32, |m, v| m.max(v.abs()));
    let slip_scale = want.slip.data.iter().fold(1.0f32, |m, v| m.max(v.abs()));
    // Where ±2 ulp already move an output by more than 0.1 % of its range, the function is
    // not determined at f32 (a tiny image with BN statistics of a few samples per channel):
    // no implementation can be compared with another there.
    prop_assume!(near_logits < 1e-3 * scale && near_slip < 1e-3 * slip_scale);
    let tol = 1e-6 * scale + 16.0 * near_logits;
    let slip_tol = 1e-6 * slip_scale + 16.0 * near_slip;
    let mut inf = Inference::new(&net, &arch, h, w).unwrap();
    let got = inf.run(&x).unwrap();
    let err = maxdiff(got.mask_logits, &want.mask_logits.data);
    prop_assert!(
        err <= tol,
        "logits differ by {} (tolerance {}) for {:?}",
        err,
        tol,
        arch
    );
    let err = maxdiff(&got.slip, &want.slip.data);
    // Plus what the calibration head's half-precision hidden layer may move Δt (docs/nets.md).
    let slip_tol = slip_tol + inf.slip_rounding_bound();
    prop_assert!(
        err <= slip_tol,
        "slip differs by {} (tolerance {})",
        err,
        slip_tol
    );
    Ok(())
}

/// A case the property once failed (logits 1253 apart, tolerance 38.5; CI on 340c4ed): 2-ulp
/// parameter changes alone move this untrained net's logits by 7 %, so its function is not
/// determined at f32, and the probe must say so instead of comparing.
#[test]
fn a_case_that_f32_does_not_determine_is_recognised() {
    let r = inference_matches_the_supernet(28, 25, 119321);
    assert!(
        matches!(r, Err(TestCaseError::Reject(_))),
        "expected the case to be rejected as not determined at f32, got {r:?}"
    );
}

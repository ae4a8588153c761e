//! Finite-difference checks of every layer's VJP (central differences, loss ⟨r, y⟩ in f64).

use nanoeye_nets::Tensor;
use nanoeye_nets::act::Act;
use nanoeye_nets::conv::*;
use nanoeye_nets::loss::{dice_loss, dice_target_grad, slip_mse};
use nanoeye_nets::norm::{BatchNorm, BnMode};
use nanoeye_nets::pool::{gap_forward, gap_vjp};
use nanoeye_nets::resize::{bilinear_forward, bilinear_vjp};
use nanoeye_nets::se::{SeGrads, SeWeights, se_forward, se_vjp};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn rnd(rng: &mut ChaCha8Rng, n: usize) -> Vec<f32> {
    (0..n).map(|_| rng.random_range(-1.0f32..1.0)).collect()
}

fn t(rng: &mut ChaCha8Rng, s: [usize; 4]) -> Tensor {
    Tensor::from_vec(s[0], s[1], s[2], s[3], rnd(rng, s.iter().product())).unwrap()
}

fn dot(a: &[f32], b: &[f32]) -> f64 {
    a.iter().zip(b).map(|(x, y)| *x as f64 * *y as f64).sum()
}

/// Compares `analytic` with central differences of x ↦ ⟨r, f(x)⟩ at `x0`.
fn fd_check(
    name: &str,
    x0: &[f32],
    analytic: &[f32],
    r: &[f32],
    h: f32,
    tol: f64,
    mut f: impl FnMut(&[f32]) -> Vec<f32>,
) {
    let scale = analytic.iter().fold(1e-3f64, |m, v| m.max(v.abs() as f64));
    let mut x = x0.to_vec();
    for i in 0..x0.len() {
        x[i] = x0[i] + h;
        let lp = dot(r, &f(&x));
        x[i] = x0[i] - h;
        let lm = dot(r, &f(&x));
        x[i] = x0[i];
        let fd = (lp - lm) / (2.0 * h as f64);
        let err = (fd - analytic[i] as f64).abs();
        assert!(
            err <= tol * scale,
            "{name}[{i}]: fd {fd} vs analytic {} (scale {scale})",
            analytic[i]
        );
    }
}

#[test]
fn conv2d_vjp_matches_fd() {
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    for (k, s) in [(3, 2), (3, 1), (5, 2)] {
        let x = t(&mut rng, [2, 2, 5, 6]);
        let w = rnd(&mut rng, 3 * 2 * k * k);
        let y = conv2d_forward(&x, &w, 3, k, s).unwrap();
        let r = rnd(&mut rng, y.len());
        let dy = Tensor {
            data: r.clone(),
            ..y.clone()
        };
        let mut dw = vec![0.0; w.len()];
        let dx = conv2d_vjp(&x, &w, 3, k, s, &dy, &mut dw).unwrap();
        fd_check("conv dx", &x.data, &dx.data, &r, 1e-2, 1e-3, |v| {
            conv2d_forward(
                &Tensor {
                    data: v.to_vec(),
                    ..x.clone()
                },
                &w,
                3,
                k,
                s,
            )
            .unwrap()
            .data
        });
        fd_check("conv dw", &w, &dw, &r, 1e-2, 1e-3, |v| {
            conv2d_forward(&x, v, 3, k, s).unwrap().data
        });
    }
}

#[test]
fn depthwise_vjp_matches_fd() {
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    for (k, s) in [(3, 1), (5, 2), (7, 1), (7, 2)] {
        let x = t(&mut rng, [2, 3, 6, 7]);
        let w = rnd(&mut rng, 3 * k * k);
        let y = depthwise_forward(&x, &w, k, s).unwrap();
        assert_eq!([y.h, y.w], [out_size(6, k, s), out_size(7, k, s)]);
        let r = rnd(&mut rng, y.len());
        let dy = Tensor {
            data: r.clone(),
            ..y.clone()
        };
        let mut dw = vec![0.0; w.len()];
        let dx = depthwise_vjp(&x, &w, k, s, &dy, &mut dw).unwrap();
        fd_check("dw dx", &x.data, &dx.data, &r, 1e-2, 1e-3, |v| {
            depthwise_forward(
                &Tensor {
                    data: v.to_vec(),
                    ..x.clone()
                },
                &w,
                k,
                s,
            )
            .unwrap()
            .data
        });
        fd_check("dw dw", &w, &dw, &r, 1e-2, 1e-3, |v| {
            depthwise_forward(&x, v, k, s).unwrap().data
        });
    }
}

#[test]
fn depthwise_identity_kernel_is_identity() {
    // A centred delta kernel must reproduce the input exactly at stride 1 (same padding).
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let x = t(&mut rng, [1, 2, 5, 4]);
    let mut w = vec![0.0; 2 * 25];
    w[12] = 1.0;
    w[25 + 12] = 1.0;
    assert_eq!(depthwise_forward(&x, &w, 5, 1).unwrap(), x);
}

#[test]
fn pointwise_vjp_matches_fd_and_dense_reference() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let x = t(&mut rng, [2, 5, 3, 4]);
    let w = rnd(&mut rng, 4 * 5);
    let b = rnd(&mut rng, 4);
    let y = pointwise_forward(&x, &w, 4, Some(&b)).unwrap();
    // Dense reference: a 1×1 dense conv plus bias.
    let yr = conv2d_forward(&x, &w, 4, 1, 1).unwrap();
    for (i, (a, c)) in y.data.iter().zip(&yr.data).enumerate() {
        let o = (i / 12) % 4;
        assert!((a - c - b[o]).abs() < 1e-5);
    }
    let r = rnd(&mut rng, y.len());
    let dy = Tensor {
        data: r.clone(),
        ..y.clone()
    };
    let (mut dw, mut db) = (vec![0.0; w.len()], vec![0.0; 4]);
    let dx = pointwise_vjp(&x, &w, 4, &dy, &mut dw, Some(&mut db)).unwrap();
    fd_check("pw dx", &x.data, &dx.data, &r, 1e-2, 1e-3, |v| {
        pointwise_forward(
            &Tensor {
                data: v.to_vec(),
                ..x.clone()
            },
            &w,
            4,
            Some(&b),
        )
        .unwrap()
        .data
    });
    fd_check("pw dw", &w, &dw, &r, 1e-2, 1e-3, |v| {
        pointwise_forward(&x, v, 4, Some(&b)).unwrap().data
    });
    fd_check("pw db", &b, &db, &r, 1e-2, 1e-3, |v| {
        pointwise_forward(&x, &w, 4, Some(v)).unwrap().data
    });
}

/// One-pixel planes (the heads after pooling) take the batched-GEMM path: check it against the
/// dense reference and central differences with more output rows than one parallel block, that
/// the weight gradient is added to what `dw` held, and that the result does not depend on the
/// thread count.
#[test]
fn pointwise_on_one_pixel_planes_matches_reference_fd_and_thread_counts() {
    check_batched_pointwise(31, [3, 70, 1, 1], 130);
}

/// Small planes (≤ 64 pixels, the deep stages) run as one GEMM over the batch's N·HW columns:
/// the same checks, with more columns than one parallel column block (9 · 35 > 256) and more
/// weight-gradient rows than one row block.
#[test]
fn pointwise_on_small_planes_matches_reference_fd_and_thread_counts() {
    check_batched_pointwise(32, [9, 20, 7, 5], 70);
    check_batched_pointwise(33, [2, 3, 8, 8], 5);
}

fn check_batched_pointwise(seed: u64, shape: [usize; 4], cout: usize) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let cin = shape[1];
    let hw = shape[2] * shape[3];
    let x = t(&mut rng, shape);
    let w = rnd(&mut rng, cout * cin);
    let b = rnd(&mut rng, cout);
    let y = pointwise_forward(&x, &w, cout, Some(&b)).unwrap();
    let yr = conv2d_forward(&x, &w, cout, 1, 1).unwrap();
    for (i, (a, c)) in y.data.iter().zip(&yr.data).enumerate() {
        let o = (i / hw) % cout;
        assert!((a - c - b[o]).abs() < 1e-5, "y[{i}]: {a} vs {}", c + b[o]);
    }
    let r = rnd(&mut rng, y.len());
    let dy = Tensor {
        data: r.clone(),
        ..y.clone()
    };
    let held = rnd(&mut rng, w.len());
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let (mut dw, mut db) = (held.clone(), vec![0.0; cout]);
            let dx = pointwise_vjp(&x, &w, cout, &dy, &mut dw, Some(&mut db)).unwrap();
            (dx, dw, db)
        })
    };
    let (dx, dw_acc, db) = run(2);
    let (dx1, dw1, db1) = run(1);
    assert_eq!(dx.data, dx1.data);
    assert_eq!(dw_acc, dw1);
    assert_eq!(db, db1);
    let dw: Vec<f32> = dw_acc.iter().zip(&held).map(|(a, h)| a - h).collect();
    fd_check("pw1 dx", &x.data, &dx.data, &r, 1e-2, 1e-3, |v| {
        pointwise_forward(
            &Tensor {
                data: v.to_vec(),
                ..x.clone()
            },
            &w,
            cout,
            Some(&b),
        )
        .unwrap()
        .data
    });
    fd_check("pw1 dw", &w, &dw, &r, 1e-2, 1e-3, |v| {
        pointwise_forward(&x, v, cout, Some(&b)).unwrap().data
    });
    fd_check("pw1 db", &b, &db, &r, 1e-2, 1e-3, |v| {
        pointwise_forward(&x, &w, cout, Some(v)).unwrap().data
    });
}

#[test]
fn batchnorm_vjp_matches_fd_train_and_eval() {
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    let x = t(&mut rng, [3, 2, 2, 3]);
    for mode in [BnMode::Train, BnMode::Eval] {
        let mut bn = BatchNorm::new(4);
        bn.gamma.value = vec![1.3, -0.7, 2.0, 1.0];
        bn.beta.value = vec![0.1, 0.2, 0.3, 0.4];
        bn.running_mean = vec![0.2, -0.1, 0.0, 0.0];
        bn.running_var = vec![0.5, 2.0, 1.0, 1.0];
        let y = bn.forward(&x, mode).unwrap();
        let r = rnd(&mut rng, y.len());
        let dx = bn
            .backward(&Tensor {
                data: r.clone(),
                ..y.clone()
            })
            .unwrap();
        let probe = bn.clone();
        fd_check("bn dx", &x.data, &dx.data, &r, 1e-2, 2e-3, |v| {
            probe
                .clone()
                .forward(
                    &Tensor {
                        data: v.to_vec(),
                        ..x.clone()
                    },
                    BnMode::Eval.max_mode(mode),
                )
                .unwrap()
                .data
        });
        let g0 = bn.gamma.value.clone();
        fd_check(
            "bn dgamma",
            &g0[..2],
            &bn.gamma.grad[..2],
            &r,
            1e-2,
            1e-3,
            |v| {
                let mut b = probe.clone();
                b.gamma.value[..2].copy_from_slice(v);
                b.forward(&x, BnMode::Eval.max_mode(mode)).unwrap().data
            },
        );
        let b0 = bn.beta.value.clone();
        fd_check(
            "bn dbeta",
            &b0[..2],
            &bn.beta.grad[..2],
            &r,
            1e-2,
            1e-3,
            |v| {
                let mut b = probe.clone();
                b.beta.value[..2].copy_from_slice(v);
                b.forward(&x, BnMode::Eval.max_mode(mode)).unwrap().data
            },
        );
    }
}

/// Train-mode forwards in the FD probes must not depend on running statistics; Eval ones must
/// not update them: this helper picks the probe mode.
trait ProbeMode {
    fn max_mode(self, m: BnMode) -> BnMode;
}
impl ProbeMode for BnMode {
    fn max_mode(self, m: BnMode) -> BnMode {
        if m == BnMode::Train {
            BnMode::Recalibrate
        } else {
            BnMode::Eval
        }
    }
}

#[test]
fn batchnorm_train_output_is_standardized() {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let x = t(&mut rng, [4, 3, 5, 5]);
    let mut bn = BatchNorm::new(3);
    let y = bn.forward(&x, BnMode::Train).unwrap();
    for c in 0..3 {
        let v: Vec<f64> = (0..4)
            .flat_map(|n| y.data[(n * 3 + c) * 25..][..25].iter().map(|&a| a as f64))
            .collect();
        let m = v.iter().sum::<f64>() / v.len() as f64;
        let var = v.iter().map(|a| (a - m).powi(2)).sum::<f64>() / v.len() as f64;
        assert!(
            m.abs() < 1e-5 && (var - 1.0).abs() < 1e-3,
            "channel {c}: mean {m}, var {var}"
        );
    }
}

#[test]
fn batchnorm_recalibration_is_exact_pooled_statistics() {
    let mut rng = ChaCha8Rng::seed_from_u64(6);
    let batches: Vec<Tensor> = (0..3).map(|_| t(&mut rng, [2, 2, 3, 3])).collect();
    let mut bn = BatchNorm::new(2);
    bn.begin_recalibration();
    for b in &batches {
        bn.forward(b, BnMode::Recalibrate).unwrap();
    }
    bn.finish_recalibration();
    for c in 0..2 {
        let v: Vec<f64> = batches
            .iter()
            .flat_map(|b| {
                (0..2).flat_map(move |n| b.data[(n * 2 + c) * 9..][..9].iter().map(|&a| a as f64))
            })
            .collect();
        let m = v.iter().sum::<f64>() / v.len() as f64;
        let var = v.iter().map(|a| (a - m).powi(2)).sum::<f64>() / v.len() as f64;
        assert!((bn.running_mean[c] as f64 - m).abs() < 1e-6);
        assert!((bn.running_var[c] as f64 - var).abs() < 1e-6);
    }
}

#[test]
fn activations_derivatives_match_fd() {
    let xs: Vec<f32> = vec![-4.5, -2.9, -1.3, -0.4, 0.3, 1.1, 2.2, 2.9, 3.4, 5.0];
    for act in [Act::Relu, Act::HSwish, Act::HSigmoid, Act::Identity] {
        let r = vec![1.0; xs.len()];
        let g = act.vjp(&xs, &r);
        for (i, &x) in xs.iter().enumerate() {
            let fd = (act.apply(x + 1e-3) as f64 - act.apply(x - 1e-3) as f64) / 2e-3;
            assert!(
                (fd - g[i] as f64).abs() < 1e-3,
                "{act:?} at {x}: {fd} vs {}",
                g[i]
            );
        }
    }
    // Closed forms: h-swish(1) = 1·4/6, h-sigmoid(0) = ½, h-swish saturates to x beyond 3.
    assert!((Act::HSwish.apply(1.0) - 4.0 / 6.0).abs() < 1e-7);
    assert_eq!(Act::HSigmoid.apply(0.0), 0.5);
    assert_eq!(Act::HSwish.apply(7.0), 7.0);
}

#[test]
fn se_vjp_matches_fd() {
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let (c, m) = (4, 2);
    let x = t(&mut rng, [2, c, 3, 3]);
    let w1 = rnd(&mut rng, m * c);
    let b1 = vec![0.3, 0.2];
    let w2 = rnd(&mut rng, c * m);
    let b2 = rnd(&mut rng, c);
    let wt = SeWeights {
        w1: &w1,
        b1: &b1,
        w2: &w2,
        b2: &b2,
    };
    let (y, cache) = se_forward(&x, &wt).unwrap();
    let r = rnd(&mut rng, y.len());
    let (mut g1, mut gb1, mut g2, mut gb2) = (
        vec![0.0; m * c],
        vec![0.0; m],
        vec![0.0; c * m],
        vec![0.0; c],
    );
    let dx = se_vjp(
        &x,
        &wt,
        &cache,
        &Tensor {
            data: r.clone(),
            ..y.clone()
        },
        SeGrads {
            w1: &mut g1,
            b1: &mut gb1,
            w2: &mut g2,
            b2: &mut gb2,
        },
    )
    .unwrap();
    let run = |x: &Tensor, w1: &[f32], b1: &[f32], w2: &[f32], b2: &[f32]| {
        se_forward(x, &SeWeights { w1, b1, w2, b2 }).unwrap().0.data
    };
    let h = 1e-3;
    fd_check("se dx", &x.data, &dx.data, &r, h, 5e-3, |v| {
        run(
            &Tensor {
                data: v.to_vec(),
                ..x.clone()
            },
            &w1,
            &b1,
            &w2,
            &b2,
        )
    });
    fd_check("se dw1", &w1, &g1, &r, h, 5e-3, |v| {
        run(&x, v, &b1, &w2, &b2)
    });
    fd_check("se db1", &b1, &gb1, &r, h, 5e-3, |v| {
        run(&x, &w1, v, &w2, &b2)
    });
    fd_check("se dw2", &w2, &g2, &r, h, 5e-3, |v| {
        run(&x, &w1, &b1, v, &b2)
    });
    fd_check("se db2", &b2, &gb2, &r, h, 5e-3, |v| {
        run(&x, &w1, &b1, &w2, v)
    });
    // Gradient buffers of another size than the weights' are refused, not indexed past.
    let mut long = vec![0.0; m * c + 1];
    let e = se_vjp(
        &x,
        &wt,
        &cache,
        &y,
        SeGrads {
            w1: &mut long,
            b1: &mut gb1,
            w2: &mut g2,
            b2: &mut gb2,
        },
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("SE gradients"), "{e}");
}

#[test]
fn pooling_and_bilinear_are_adjoint_pairs() {
    let mut rng = ChaCha8Rng::seed_from_u64(8);
    let x = t(&mut rng, [2, 3, 5, 7]);
    let g = t(&mut rng, [2, 3, 1, 1]);
    assert!(
        (dot(&gap_forward(&x).data, &g.data) - dot(&x.data, &gap_vjp(x.shape(), &g).data)).abs()
            < 1e-5
    );
    for (h, w) in [(11, 3), (2, 14), (5, 7), (1, 1)] {
        let y = bilinear_forward(&x, h, w);
        let gy = t(&mut rng, [2, 3, h, w]);
        let lhs = dot(&y.data, &gy.data);
        let rhs = dot(&x.data, &bilinear_vjp(x.shape(), &gy).data);
        assert!(
            (lhs - rhs).abs() < 1e-4 * lhs.abs().max(1.0),
            "({h},{w}): {lhs} vs {rhs}"
        );
    }
    // Same size resampling is the identity; a constant image stays constant.
    assert_eq!(bilinear_forward(&x, 5, 7), x);
    let ones = Tensor::from_vec(1, 1, 3, 4, vec![2.5; 12]).unwrap();
    assert!(
        bilinear_forward(&ones, 7, 9)
            .data
            .iter()
            .all(|&v| (v - 2.5).abs() < 1e-6)
    );
}

#[test]
fn losses_gradients_match_fd() {
    let mut rng = ChaCha8Rng::seed_from_u64(10);
    let l = t(&mut rng, [2, 1, 3, 3]);
    let m = Tensor {
        data: l
            .data
            .iter()
            .map(|_| if rng.random_bool(0.4) { 1.0 } else { 0.0 })
            .collect(),
        ..l.clone()
    };
    let (_, g) = dice_loss(&l, &m).unwrap();
    let one = vec![1.0];
    fd_check("dice", &l.data, &g.data, &one, 1e-2, 2e-3, |v| {
        vec![
            dice_loss(
                &Tensor {
                    data: v.to_vec(),
                    ..l.clone()
                },
                &m,
            )
            .unwrap()
            .0 as f32,
        ]
    });
    // W.r.t. a soft target (the mask averaged onto the p̂ grid depends on p̂).
    let soft = Tensor {
        data: m.data.iter().map(|&v| 0.2 + 0.6 * v).collect(),
        ..m.clone()
    };
    let gt = dice_target_grad(&l, &soft).unwrap();
    fd_check("dice target", &soft.data, &gt.data, &one, 1e-2, 2e-3, |v| {
        vec![
            dice_loss(
                &l,
                &Tensor {
                    data: v.to_vec(),
                    ..l.clone()
                },
            )
            .unwrap()
            .0 as f32,
        ]
    });
    // Perfect, confident prediction of a non-empty mask → Dice loss ≈ ε/(2Σ M* + ε).
    let perfect = Tensor {
        data: m
            .data
            .iter()
            .map(|&v| if v > 0.5 { 30.0 } else { -30.0 })
            .collect(),
        ..m.clone()
    };
    let (lp, _) = dice_loss(&perfect, &m).unwrap();
    let s: Vec<f64> = (0..2)
        .map(|n| m.data[n * 9..][..9].iter().map(|&v| v as f64).sum())
        .collect();
    let want = s
        .iter()
        .map(|&s| 1.0 - 2.0 * s / (2.0 * s + 1.0))
        .sum::<f64>()
        / 2.0;
    assert!((lp - want).abs() < 1e-9);
    let p = t(&mut rng, [2, 3, 1, 1]);
    let q = t(&mut rng, [2, 3, 1, 1]);
    let (lm, gm) = slip_mse(&p, &q).unwrap();
    let direct = p
        .data
        .iter()
        .zip(&q.data)
        .map(|(a, b)| ((a - b) as f64).powi(2))
        .sum::<f64>()
        / 2.0;
    assert!((lm - direct).abs() < 1e-9);
    fd_check("mse", &p.data, &gm.data, &one, 1e-2, 1e-3, |v| {
        vec![
            slip_mse(
                &Tensor {
                    data: v.to_vec(),
                    ..p.clone()
                },
                &q,
            )
            .unwrap()
            .0 as f32,
        ]
    });
}

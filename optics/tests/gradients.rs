//! Every VJP against central finite differences (directional derivatives along random
//! directions, relative error ≤ 1e-3), and proptests of numerical robustness.

use faer::Mat;
use nanoeye_optics::psf::PsfModel;
use nanoeye_optics::{ApertureGrid, AsmPsf, Layer, LayeredImager, PhaseMap, PsfConfig};
use proptest::prelude::*;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn rand_mat(rng: &mut ChaCha8Rng, r: usize, c: usize, lo: f64, hi: f64) -> Mat<f64> {
    Mat::from_fn(r, c, |_, _| rng.random_range(lo..hi))
}

fn dot(a: &Mat<f64>, b: &Mat<f64>) -> f64 {
    let mut s = 0.0;
    for j in 0..a.ncols() {
        for i in 0..a.nrows() {
            s += a[(i, j)] * b[(i, j)];
        }
    }
    s
}

/// Small rig (D = 40 µm, Δ = 2 µm, s = 100 µm, 8×8 window at 1 µm): a lens with a random
/// aberration so every pixel depends on the phase.
fn small_model() -> (AsmPsf, PhaseMap, Vec<f64>) {
    small_model_with_period(None)
}

/// [`small_model`] with the spectrum period `period_m` (default: D + W p + margin).
fn small_model_with_period(period_m: Option<f64>) -> (AsmPsf, PhaseMap, Vec<f64>) {
    let grid = ApertureGrid::new(40e-6, 2e-6).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let k = std::f64::consts::TAU / 940e-9;
    let phase = Mat::from_fn(grid.n, grid.n, |i, j| {
        let (y, x) = (grid.coord(i), grid.coord(j));
        let r2 = x * x + y * y;
        -k * r2 / (2.0 * 90e-6) + rng.random_range(-0.5..0.5)
    });
    let amp = rand_mat(&mut rng, grid.n, grid.n, 0.5, 1.0);
    let map = PhaseMap::new(grid, phase, amp).unwrap();
    let cfg = PsfConfig {
        sensor_distance_m: 100e-6,
        pitch_m: 1e-6,
        window_px: 8,
        period_m,
        ..PsfConfig::default()
    };
    (
        AsmPsf::new(cfg, grid).unwrap(),
        map,
        vec![0.8e-3, 1.0e-3, 1.3e-3],
    )
}

/// The VJP right after the stack at the same map reuses the stack's fields (`AsmPsf`'s
/// memo): its gradient must be the fresh model's bit for bit, with some depths inactive in the
/// stack (their fields computed afresh), and after a stack at another map (no reuse).
#[test]
fn psf_vjp_after_the_stack_reuses_its_fields_bit_for_bit() {
    let (model, map, depths) = small_model();
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let gp: Vec<Mat<f64>> = depths
        .iter()
        .map(|_| rand_mat(&mut rng, 8, 8, -1.0, 1.0))
        .collect();
    let bits = |g: &nanoeye_optics::psf::PhaseMapGrad| {
        let mut v = Vec::new();
        for m in [&g.phase_rad, &g.amplitude] {
            for j in 0..m.ncols() {
                v.extend(m.col(j).iter().map(|x| x.to_bits()));
            }
        }
        v
    };
    let (fresh, _, _) = small_model();
    let want = bits(&fresh.vjp(&map, &depths, &gp, None).unwrap());
    model
        .planes_f64(&map, &depths, Some(&[true, false, true]))
        .unwrap();
    assert_eq!(bits(&model.vjp(&map, &depths, &gp, None).unwrap()), want);
    let other = PhaseMap::new(
        map.grid,
        Mat::from_fn(map.grid.n, map.grid.n, |i, j| map.phase_rad[(i, j)] + 0.3),
        map.amplitude.clone(),
    )
    .unwrap();
    model.planes_f64(&other, &depths, None).unwrap();
    assert_eq!(bits(&model.vjp(&map, &depths, &gp, None).unwrap()), want);
    // And the other map's VJP, with its fields kept, is its fresh one's.
    let (fresh2, _, _) = small_model();
    let want2 = bits(&fresh2.vjp(&other, &depths, &gp, None).unwrap());
    model.planes_f64(&other, &depths, None).unwrap();
    assert_eq!(bits(&model.vjp(&other, &depths, &gp, None).unwrap()), want2);
    assert_ne!(want, want2);
}

#[test]
fn psf_vjp_matches_finite_differences() {
    psf_vjp_matches_finite_differences_at(None);
}

/// A period shorter than the aperture (26 µm for D = 40 µm) folds several aperture rows onto
/// one row of the spectral grid: the samples are then reordered by fold row and streamed a
/// block of rows at a time, forward and adjoint alike.
#[test]
fn psf_vjp_matches_finite_differences_when_the_period_folds_the_aperture() {
    psf_vjp_matches_finite_differences_at(Some(26e-6));
}

fn psf_vjp_matches_finite_differences_at(period_m: Option<f64>) {
    let (model, map, depths) = small_model_with_period(period_m);
    if let Some(p) = period_m {
        assert!(
            model.sizes().0 < map.grid.n,
            "period {p} does not fold the aperture"
        );
    }
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let gp: Vec<Mat<f64>> = depths
        .iter()
        .map(|_| rand_mat(&mut rng, 8, 8, -1.0, 1.0))
        .collect();
    // ∂/∂z weights scaled so both terms of the loss are comparable.
    let gd: Vec<Mat<f64>> = depths
        .iter()
        .map(|_| rand_mat(&mut rng, 8, 8, -1e-4, 1e-4))
        .collect();
    let loss = |m: &PhaseMap| {
        let planes = model.planes_f64(m, &depths, None).unwrap();
        let dz = nanoeye_optics::psf::depth_derivative(&depths, &planes);
        (0..depths.len())
            .map(|k| {
                dot(&gp[k], planes[k].as_ref().unwrap()) + dot(&gd[k], dz[k].as_ref().unwrap())
            })
            .sum::<f64>()
    };
    let g = model.vjp(&map, &depths, &gp, Some(&gd)).unwrap();
    let n = map.grid.n;
    let w = map.grid.aperture_weights();
    for which in ["phase", "amplitude"] {
        let dir = Mat::from_fn(n, n, |i, j| {
            if w[(i, j)] > 0.0 {
                rng.random_range(-1.0..1.0)
            } else {
                0.0
            }
        });
        let h = 1e-5;
        let shifted = |sgn: f64| {
            let mut m = map.clone();
            let t = if which == "phase" {
                &mut m.phase_rad
            } else {
                &mut m.amplitude
            };
            for i in 0..n {
                for j in 0..n {
                    t[(i, j)] += sgn * h * dir[(i, j)];
                }
            }
            m
        };
        let fd = (loss(&shifted(1.0)) - loss(&shifted(-1.0))) / (2.0 * h);
        let an = dot(
            if which == "phase" {
                &g.phase_rad
            } else {
                &g.amplitude
            },
            &dir,
        );
        assert!(
            (fd - an).abs() <= 1e-3 * fd.abs().max(1e-12),
            "{which}: fd {fd} vjp {an}"
        );
    }
}

/// The PSF VJP is its per-depth terms added in increasing depth from zero, whatever the
/// thread count and whichever depths a term is computed with: shares of the depths computed
/// on several processes (`vjp_terms`) and summed in that order give `vjp`'s bits.
#[test]
fn psf_vjp_is_its_depth_terms_summed_in_order_on_any_thread_count() {
    let (model, map, _) = small_model();
    let depths = vec![0.7e-3, 0.8e-3, 1.0e-3, 1.3e-3, 1.6e-3];
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let mut gp: Vec<Mat<f64>> = depths
        .iter()
        .map(|_| rand_mat(&mut rng, 8, 8, -1.0, 1.0))
        .collect();
    gp[2] = Mat::zeros(8, 8);
    let with = nanoeye_optics::psf::depths_with_gradient(&gp);
    assert_eq!(with, [0, 1, 3, 4]);
    let on = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| model.vjp(&map, &depths, &gp, None).unwrap())
    };
    let bits = |m: &Mat<f64>| {
        (0..m.ncols())
            .flat_map(|j| (0..m.nrows()).map(move |i| (i, j)))
            .map(|ij| m[ij].to_bits())
            .collect::<Vec<_>>()
    };
    let (g1, g3) = (on(1), on(3));
    assert_eq!(bits(&g1.phase_rad), bits(&g3.phase_rad));
    assert_eq!(bits(&g1.amplitude), bits(&g3.amplitude));
    // Two "processes": depths 0, 3 on one, 1, 4 on the other, added back in depth order.
    let a = model.vjp_terms(&map, &depths, &gp, &[0, 3]).unwrap();
    let b = model.vjp_terms(&map, &depths, &gp, &[1, 4]).unwrap();
    let mut sum = nanoeye_optics::PhaseMapGrad::zeros(map.grid.n);
    for t in [&a[0], &b[0], &a[1], &b[1]] {
        sum.add(t);
    }
    assert_eq!(bits(&sum.phase_rad), bits(&g1.phase_rad));
    assert_eq!(bits(&sum.amplitude), bits(&g1.amplitude));
    // A term that is not zero, and an index beyond the stack refused.
    assert!(a[0].phase_rad.norm_l2() > 0.0);
    assert!(model.vjp_terms(&map, &depths, &gp, &[5]).is_err());
}

fn layers_fixture(rng: &mut ChaCha8Rng, n: usize) -> Vec<(Mat<f32>, Mat<f32>, Mat<f32>)> {
    (0..n)
        .map(|_| {
            let l = Mat::from_fn(12, 10, |_, _| rng.random_range(0.0..2.0f32));
            let a = Mat::from_fn(12, 10, |_, _| rng.random_range(0.0..1.0f32));
            let p = Mat::from_fn(5, 5, |_, _| rng.random_range(0.0..0.08f32));
            (l, a, p)
        })
        .collect()
}

fn as_layers(v: &[(Mat<f32>, Mat<f32>, Mat<f32>)]) -> Vec<Layer<'_>> {
    v.iter()
        .map(|(l, a, p)| Layer {
            radiance: l,
            alpha: a,
            psf: p,
        })
        .collect()
}

#[test]
fn layered_vjp_matches_finite_differences() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let base = layers_fixture(&mut rng, 3);
    let imager = LayeredImager::new(12, 10, 5).unwrap();
    let g = rand_mat(&mut rng, 12, 10, -1.0, 1.0);
    let loss = |v: &[(Mat<f32>, Mat<f32>, Mat<f32>)]| {
        dot(&g, &imager.forward_f64_image(&as_layers(v)).unwrap())
    };
    let grads = imager.vjp(&as_layers(&base), &g).unwrap();
    for which in 0..3 {
        for k in 0..3 {
            let (r, c) = if which == 2 { (5, 5) } else { (12, 10) };
            let dir = rand_mat(&mut rng, r, c, -1.0, 1.0);
            let h = 1e-3;
            let shifted = |sgn: f64| {
                let mut v = base.clone();
                let t = match which {
                    0 => &mut v[k].0,
                    1 => &mut v[k].1,
                    _ => &mut v[k].2,
                };
                for i in 0..r {
                    for j in 0..c {
                        t[(i, j)] += (sgn * h * dir[(i, j)]) as f32;
                    }
                }
                v
            };
            let (plus, minus) = (shifted(1.0), shifted(-1.0));
            let fd = (loss(&plus) - loss(&minus)) / (2.0 * h);
            // The perturbation actually applied after rounding to f32.
            let pick = |v: &[(Mat<f32>, Mat<f32>, Mat<f32>)]| match which {
                0 => v[k].0.clone(),
                1 => v[k].1.clone(),
                _ => v[k].2.clone(),
            };
            let (tp, tm) = (pick(&plus), pick(&minus));
            let dir = Mat::from_fn(r, c, |i, j| {
                (tp[(i, j)] as f64 - tm[(i, j)] as f64) / (2.0 * h)
            });
            let gm = match which {
                0 => &grads.radiance[k],
                1 => &grads.alpha[k],
                _ => &grads.psf[k],
            };
            let an = dot(gm, &dir);
            assert!(
                (fd - an).abs() <= 1e-3 * fd.abs().max(1e-6),
                "input {which} layer {k}: fd {fd} vjp {an}"
            );
        }
    }
}

#[test]
fn layered_occlusion_with_delta_psfs() {
    let delta = Mat::from_fn(3, 3, |i, j| if i == 1 && j == 1 { 1.0f32 } else { 0.0 });
    let back = Mat::from_fn(6, 6, |_, _| 2.0f32);
    let ones = Mat::from_fn(6, 6, |_, _| 1.0f32);
    let front = Mat::from_fn(6, 6, |i, _| i as f32);
    let half = Mat::from_fn(6, 6, |_, j| if j < 3 { 1.0f32 } else { 0.0 });
    let empty = Mat::<f32>::zeros(6, 6);
    let imager = LayeredImager::new(6, 6, 3).unwrap();
    let layers = [
        Layer {
            radiance: &back,
            alpha: &ones,
            psf: &delta,
        },
        Layer {
            radiance: &front,
            alpha: &empty,
            psf: &delta,
        },
        Layer {
            radiance: &front,
            alpha: &half,
            psf: &delta,
        },
    ];
    let img = imager.forward(&layers).unwrap();
    for i in 0..6 {
        for j in 0..6 {
            let want = if j < 3 { i as f32 } else { 2.0 };
            assert!(
                (img[(i, j)] - want).abs() < 1e-5,
                "({i},{j}) {} vs {want}",
                img[(i, j)]
            );
        }
    }
    // The α ≡ 0 layer changes nothing and receives no gradient.
    let without = imager.forward(&[layers[0], layers[2]]).unwrap();
    assert_eq!(img, without);
    let g = imager
        .vjp(&layers, &Mat::from_fn(6, 6, |_, _| 1.0))
        .unwrap();
    assert!(
        g.radiance[1]
            .col_iter()
            .all(|c| c.iter().all(|&v| v == 0.0))
    );
    // Energy of a blurred, fully opaque single layer inside the image: the kernel sums to 1.
    let blur = Mat::from_fn(3, 3, |_, _| 1.0f32 / 9.0);
    let img = imager
        .forward(&[Layer {
            radiance: &back,
            alpha: &ones,
            psf: &blur,
        }])
        .unwrap();
    assert!((img[(2, 2)] - 2.0).abs() < 1e-5);
    assert!(
        (img[(0, 0)] - 2.0 * 4.0 / 9.0).abs() < 1e-5,
        "corner {}",
        img[(0, 0)]
    );
    assert!(
        imager
            .forward(&[Layer {
                radiance: &back,
                alpha: &ones,
                psf: &back
            }])
            .is_err()
    );
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]

    /// Random (even wildly varying) phase maps and amplitudes in [0, 1] give finite,
    /// non-negative PSFs that never hold more energy than the aperture transmits.
    #[test]
    fn random_phase_maps_give_finite_nonnegative_psfs(seed in 0u64..1_000_000, scale in 1e-3f64..1e4, z in 1e-4f64..1.0) {
        let grid = ApertureGrid::new(20e-6, 1e-6).unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let phase = rand_mat(&mut rng, grid.n, grid.n, -scale, scale);
        let amp = rand_mat(&mut rng, grid.n, grid.n, 0.0, 1.0);
        let map = PhaseMap::new(grid, phase, amp).unwrap();
        let cfg = PsfConfig { sensor_distance_m: 50e-6, pitch_m: 1e-6, window_px: 8, ..PsfConfig::default() };
        let model = AsmPsf::new(cfg, grid).unwrap();
        let s = model.forward(&map, &[z], None).unwrap();
        let mut e = 0.0f64;
        for c in s.planes[0].col_iter() {
            for &v in c.iter() {
                prop_assert!(v.is_finite() && v >= 0.0);
                e += v as f64;
            }
        }
        prop_assert!(e <= 1.0 + 1e-6, "energy {}", e);
    }

    /// Layered images of non-negative layers with α ∈ [0, 1] and normalized PSFs stay finite,
    /// non-negative and below the brightest radiance.
    #[test]
    fn layered_images_are_bounded(seed in 0u64..1_000_000, big in 1e-6f32..1e6) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut v = layers_fixture(&mut rng, 3);
        let mut lmax = 0.0f32;
        for (l, _, p) in v.iter_mut() {
            let s: f32 = p.col_iter().map(|c| c.iter().sum::<f32>()).sum();
            for j in 0..5 { for i in 0..5 { p[(i, j)] /= s; } }
            for j in 0..10 { for i in 0..12 { l[(i, j)] *= big; lmax = lmax.max(l[(i, j)]); } }
        }
        let imager = LayeredImager::new(12, 10, 5).unwrap();
        let img = imager.forward(&as_layers(&v)).unwrap();
        for c in img.col_iter() {
            for &x in c.iter() {
                prop_assert!(x.is_finite() && x >= -1e-5 * lmax && x <= lmax * (1.0 + 1e-4));
            }
        }
    }
}

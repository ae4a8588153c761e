//! The spectral S1 path (kernel spectra shared across frames, ∂loss/∂P accumulated in the
//! frequency domain) against the reference `LayeredImager::forward`/`vjp`.

// Kernel index k selects both the accumulator slot and the reference layers that use it.
#![allow(clippy::needless_range_loop)]

use faer::Mat;
use nanoeye_optics::{Layer, LayeredImager, SpectralLayer};

fn img(h: usize, w: usize, s: usize) -> Mat<f32> {
    Mat::from_fn(h, w, |i, j| (((i * 7 + j * 13 + s * 5) % 17) as f32) / 17.0)
}

fn alpha(h: usize, w: usize, s: usize) -> Mat<f32> {
    Mat::from_fn(h, w, |i, j| {
        let v = ((i * 3 + j * 11 + s) % 9) as f32 / 8.0;
        if (i + j + s) % 5 == 0 { 0.0 } else { v }
    })
}

#[test]
fn spectral_path_matches_the_reference_forward_and_psf_gradient() {
    let (h, w, wp) = (23, 31, 7);
    let im = LayeredImager::new(h, w, wp).unwrap();
    let psfs: Vec<Mat<f32>> = (0..3)
        .map(|s| Mat::from_fn(wp, wp, |i, j| 1.0 / (1.0 + ((i + s) * (j + 1)) as f32)))
        .collect();
    let rad: Vec<Mat<f32>> = (0..3).map(|s| img(h, w, s)).collect();
    let al: Vec<Mat<f32>> = (0..3).map(|s| alpha(h, w, s)).collect();
    let empty = Mat::<f32>::zeros(h, w);
    // Back to front, with an empty layer in the middle; layer 2 reuses kernel 0.
    let order = [(0usize, 0usize), (1, 1), (9, 1), (2, 0)];
    let reference: Vec<Layer> = order
        .iter()
        .map(|&(l, k)| Layer {
            radiance: if l == 9 { &empty } else { &rad[l] },
            alpha: if l == 9 { &empty } else { &al[l] },
            psf: &psfs[k],
        })
        .collect();
    let spectral: Vec<SpectralLayer> = order
        .iter()
        .map(|&(l, k)| SpectralLayer {
            radiance: if l == 9 { &empty } else { &rad[l] },
            alpha: if l == 9 { &empty } else { &al[l] },
            kernel: k,
        })
        .collect();
    let ks = im
        .kernel_spectra(&[Some(&psfs[0]), Some(&psfs[1]), None])
        .unwrap();
    let want = im.forward_f64_image(&reference).unwrap();
    let (got, tape) = im.forward_spectral(&spectral, &ks).unwrap();
    for i in 0..h {
        for j in 0..w {
            assert!((got[(i, j)] as f64 - want[(i, j)]).abs() < 1e-5 * (1.0 + want[(i, j)].abs()));
        }
    }
    let g = Mat::from_fn(h, w, |i, j| ((i * 5 + j * 3) % 7) as f64 - 3.0);
    let lg = im.vjp(&reference, &g).unwrap();
    let mut acc = im.kernel_grad_accumulator(3);
    im.vjp_kernels(&spectral, &tape, &g, &mut acc).unwrap();
    let scale = acc.radiance_scale.clone();
    let kg = im.kernel_grads(acc);
    for k in 0..2 {
        for i in 0..wp {
            for j in 0..wp {
                let want: f64 = order
                    .iter()
                    .enumerate()
                    .filter(|(_, o)| o.1 == k)
                    .map(|(n, _)| lg.psf[n][(i, j)])
                    .sum();
                assert!(
                    (kg[k][(i, j)] - want).abs() < 1e-4 * (1.0 + want.abs()),
                    "kernel {k} ({i},{j}): {} vs {want}",
                    kg[k][(i, j)]
                );
            }
        }
    }
    assert!(kg[2].col_iter().all(|c| c.iter().all(|&v| v == 0.0)));
    // ∂/∂(scale s_k on layer radiance) = Σ ∂L/∂L_k · L_k, from the reference VJP.
    for k in 0..2 {
        let want: f64 = order
            .iter()
            .enumerate()
            .filter(|(_, o)| o.1 == k && o.0 != 9)
            .map(|(n, o)| {
                let (gr, r) = (&lg.radiance[n], &rad[o.0]);
                (0..h)
                    .flat_map(|i| (0..w).map(move |j| (i, j)))
                    .map(|(i, j)| gr[(i, j)] * r[(i, j)] as f64)
                    .sum::<f64>()
            })
            .sum();
        assert!(
            (scale[k] - want).abs() < 1e-4 * (1.0 + want.abs()),
            "{} vs {want}",
            scale[k]
        );
    }
}

#[test]
fn absurd_sizes_are_refused_before_any_integer_conversion() {
    use nanoeye_optics::{ApertureGrid, AsmPsf, PsfConfig};
    let grid = ApertureGrid::new(0.1e-3, 2e-6).unwrap();
    let cfg = PsfConfig {
        window_px: 16,
        ..PsfConfig::default()
    };
    for (period, pitch) in [(Some(1e17), 3e-6), (None, 6.9359757717147935e19)] {
        let c = PsfConfig {
            period_m: period,
            pitch_m: pitch,
            ..cfg
        };
        assert!(AsmPsf::new(c, grid).is_err(), "{period:?} {pitch}");
    }
}

#[test]
fn saving_over_a_symlink_is_refused() {
    use nanoeye_optics::{ApertureGrid, AsmPsf, Hyperbolic, PhaseProfile, PsfConfig, PsfModel};
    let d = tempfile::tempdir().unwrap();
    let target = d.path().join("elsewhere");
    let link = d.path().join("psf.npy");
    std::os::unix::fs::symlink(&target, &link).unwrap();
    let grid = ApertureGrid::new(0.1e-3, 2e-6).unwrap();
    let m = AsmPsf::new(
        PsfConfig {
            window_px: 8,
            ..PsfConfig::default()
        },
        grid,
    )
    .unwrap();
    let map = Hyperbolic::default().phase_map(&grid).unwrap();
    let stack = m.forward(&map, &[20e-3], None).unwrap();
    assert!(nanoeye_optics::io::save_stack_npy(&stack, &link).is_err());
    assert!(!target.exists());
}

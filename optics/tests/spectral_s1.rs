//! The spectral S1 path (kernel spectra shared across frames, ∂loss/∂P accumulated in the
//! frequency domain) against the reference `LayeredImager::forward`/`vjp`.

// Kernel index k selects both the accumulator slot and the reference layers that use it.
#![allow(clippy::needless_range_loop)]

use faer::Mat;
use nanoeye_optics::{KernelSpectra, Layer, LayerSpectra, LayeredImager, SpectralLayer};
use proptest::prelude::*;

fn img(h: usize, w: usize, s: usize) -> Mat<f32> {
    Mat::from_fn(h, w, |i, j| (((i * 7 + j * 13 + s * 5) % 17) as f32) / 17.0)
}

fn alpha(h: usize, w: usize, s: usize) -> Mat<f32> {
    Mat::from_fn(h, w, |i, j| {
        let v = ((i * 3 + j * 11 + s) % 9) as f32 / 8.0;
        if (i + j + s).is_multiple_of(5) {
            0.0
        } else {
            v
        }
    })
}

/// The spectral path's f32 image within 1e-5 (relative, or absolute below 1) of the f64
/// reference's, pixel by pixel.
fn assert_image_close(got: &Mat<f32>, want: &Mat<f64>) {
    for i in 0..want.nrows() {
        for j in 0..want.ncols() {
            assert!(
                (got[(i, j)] as f64 - want[(i, j)]).abs() < 1e-5 * (1.0 + want[(i, j)].abs()),
                "({i},{j}): {} vs {}",
                got[(i, j)],
                want[(i, j)]
            );
        }
    }
}

#[test]
fn spectral_path_matches_the_reference_forward_and_psf_gradient() {
    // On the whole padded grid, then on tiles.
    for tile in [None, Some(4), Some(9)] {
        spectral_path_matches_the_reference_forward_and_psf_gradient_on(tile);
    }
}

fn spectral_path_matches_the_reference_forward_and_psf_gradient_on(tile: Option<usize>) {
    let (h, w, wp) = (23, 31, 7);
    let im = LayeredImager::with_tiles(h, w, wp, tile).unwrap();
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
        .map(|&(l, k)| {
            SpectralLayer::new(
                if l == 9 {
                    empty.as_ref()
                } else {
                    rad[l].as_ref()
                },
                if l == 9 {
                    empty.as_ref()
                } else {
                    al[l].as_ref()
                },
                k,
            )
        })
        .collect();
    let ks = im
        .kernel_spectra(&[Some(&psfs[0]), Some(&psfs[1]), None])
        .unwrap();
    let want = im.forward_f64_image(&reference).unwrap();
    let (got, tape) = im.forward_spectral(&spectral, &ks, None).unwrap();
    assert_image_close(&got, &want);
    let g = Mat::from_fn(h, w, |i, j| ((i * 5 + j * 3) % 7) as f64 - 3.0);
    let lg = im.vjp(&reference, &g).unwrap();
    let mut acc = im.kernel_grad_accumulator(3);
    im.vjp_kernels(&spectral, &tape, &g, &mut acc, None)
        .unwrap();
    let scale = acc.radiance_scale.clone();
    let kg = im.kernel_grads(acc);
    // The sensor's gradient comes in f32: the same values give the same bits.
    let g32 = Mat::from_fn(h, w, |i, j| g[(i, j)] as f32);
    let mut acc32 = im.kernel_grad_accumulator(3);
    im.vjp_kernels(&spectral, &tape, &g32, &mut acc32, None)
        .unwrap();
    assert_eq!(acc32.radiance_scale, scale);
    assert!(im.kernel_grads(acc32) == kg, "f32 and f64 gradients differ");
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

/// A layer whose α is zero outside `rows` and on every row `r` with `r % gap == 0`.
fn banded_alpha(h: usize, w: usize, rows: std::ops::Range<usize>, gap: usize) -> Mat<f32> {
    Mat::from_fn(h, w, |i, j| {
        if rows.contains(&i) && i % gap != 0 {
            0.2 + ((i * 3 + j * 7) % 5) as f32 / 8.0
        } else {
            0.0
        }
    })
}

/// Forward image and ∂loss/∂P of the spectral path; the same bits (asserted) when the
/// layers' spectra are computed beforehand and given, when the VJP uses those the forward
/// recorded on its tape, and when it computes them again (taken off the tape).
fn spectral_run(
    im: &LayeredImager,
    layers: &[SpectralLayer],
    psfs: &[Mat<f32>],
    g: &Mat<f64>,
) -> (Mat<f32>, Vec<Mat<f64>>, Vec<f64>) {
    let ks = im
        .kernel_spectra(&psfs.iter().map(Some).collect::<Vec<_>>())
        .unwrap();
    let spectra = im.layer_spectra(layers).unwrap();
    let covered = layers
        .iter()
        .filter(|l| l.alpha.col_iter().any(|c| c.iter().any(|&a| a != 0.0)))
        .count();
    // On the whole grid a covered layer holds one grid; on tiles, at most every tile.
    match im.tile() {
        None => assert_eq!(spectra.bytes(), covered * LayerSpectra::layer_bytes(im)),
        Some(_) => assert!(spectra.bytes() <= covered * LayerSpectra::layer_bytes(im)),
    }
    // `given`: spectra passed in; else the tape's, taken off it when `!on_tape`.
    let run = |given: Option<&LayerSpectra>, on_tape: bool| {
        let (img, mut tape) = im.forward_spectral(layers, &ks, given).unwrap();
        assert!(im.image_spectral(layers, &ks, given).unwrap() == img);
        match given {
            Some(_) => assert_eq!(tape.spectra_bytes(), 0, "nothing recorded when given"),
            None => assert_eq!(tape.spectra_bytes(), spectra.bytes()),
        }
        if !on_tape {
            let recorded = tape.take_spectra();
            assert!(given.is_some() || recorded.as_ref() == Some(&spectra));
        }
        let mut acc = im.kernel_grad_accumulator(psfs.len());
        im.vjp_kernels(layers, &tape, g, &mut acc, given).unwrap();
        // A second frame merged in, as a batch does: the merged spectra are reused.
        let mut other = im.kernel_grad_accumulator(psfs.len());
        im.vjp_kernels(layers, &tape, g, &mut other, given).unwrap();
        im.merge_kernel_grads(&mut acc, other);
        let scale = acc.radiance_scale.clone();
        (img, im.kernel_grads(acc), scale)
    };
    let computed = run(None, false);
    for other in [run(None, true), run(Some(&spectra), true)] {
        assert!(other.0 == computed.0, "images differ");
        assert!(other.1 == computed.1, "PSF gradients differ");
        assert_eq!(other.2, computed.2);
    }
    // Spectra of other layers (a count that differs) are refused, not used.
    assert!(
        im.forward_spectral(&layers[..layers.len() - 1], &ks, Some(&spectra))
            .is_err()
    );
    computed
}

#[test]
fn rows_without_data_are_skipped_and_reused_work_spaces_change_nothing() {
    // On the whole padded grid, then on tiles.
    for tile in [None, Some(16)] {
        rows_without_data_are_skipped_and_reused_work_spaces_change_nothing_on(tile);
    }
}

fn rows_without_data_are_skipped_and_reused_work_spaces_change_nothing_on(tile: Option<usize>) {
    // 300 rows: three 128-row packing bands, the last one partial; data in a few rows of
    // each layer only, one layer's rows crossing two band edges.
    let (h, w, wp) = (300, 19, 5);
    let im = LayeredImager::with_tiles(h, w, wp, tile).unwrap();
    let psfs: Vec<Mat<f32>> = (0..2)
        .map(|s| Mat::from_fn(wp, wp, |i, j| 1.0 / (1.0 + ((i + s) * (j + 2)) as f32)))
        .collect();
    let rad: Vec<Mat<f32>> = (0..3).map(|s| img(h, w, s)).collect();
    let al = [
        banded_alpha(h, w, 3..9, 100),
        banded_alpha(h, w, 120..290, 5),
        banded_alpha(h, w, 200..202, 100),
    ];
    let kernel = [0usize, 1, 0];
    let g = Mat::from_fn(h, w, |i, j| ((i * 5 + j * 3) % 7) as f64 - 3.0);
    let spectral: Vec<SpectralLayer> = (0..3)
        .map(|l| SpectralLayer::new(rad[l].as_ref(), al[l].as_ref(), kernel[l]))
        .collect();
    let reference: Vec<Layer> = (0..3)
        .map(|l| Layer {
            radiance: &rad[l],
            alpha: &al[l],
            psf: &psfs[kernel[l]],
        })
        .collect();
    // Dense layers first, so that the sparse run below gets work spaces full of their data.
    let dense_al: Vec<Mat<f32>> = (0..3).map(|s| alpha(h, w, s)).collect();
    let dense: Vec<SpectralLayer> = (0..3)
        .map(|l| SpectralLayer::new(rad[l].as_ref(), dense_al[l].as_ref(), kernel[l]))
        .collect();
    spectral_run(&im, &dense, &psfs, &g);
    let (got, kg, scale) = spectral_run(&im, &spectral, &psfs, &g);
    let want = im.forward_f64_image(&reference).unwrap();
    assert_image_close(&got, &want);
    let lg = im.vjp(&reference, &g).unwrap();
    for k in 0..2 {
        for i in 0..wp {
            for j in 0..wp {
                // Two frames of the same layers were merged.
                let want: f64 = 2.0
                    * (0..3)
                        .filter(|&l| kernel[l] == k)
                        .map(|l| lg.psf[l][(i, j)])
                        .sum::<f64>();
                assert!(
                    (kg[k][(i, j)] - want).abs() < 1e-4 * (1.0 + want.abs()),
                    "kernel {k} ({i},{j}): {} vs {want}",
                    kg[k][(i, j)]
                );
            }
        }
    }
    // The same calls again on the imager's reused work spaces: the same bits.
    let (got2, kg2, scale2) = spectral_run(&im, &spectral, &psfs, &g);
    assert_eq!(got, got2);
    assert_eq!(kg, kg2);
    assert_eq!(scale, scale2);
    // And on a fresh imager, whose work spaces are new.
    let fresh = LayeredImager::with_tiles(h, w, wp, tile).unwrap();
    let (got3, kg3, _) = spectral_run(&fresh, &spectral, &psfs, &g);
    assert_eq!(got, got3);
    assert_eq!(kg, kg3);
}

/// Row-major planes (transposes of owned matrices, as `search` keeps a dataset's layers) give
/// the column-major path's bits: the image, the radiance scales and the PSF gradient, with the
/// VJP packing the layers again; planes of two layouts in one layer are refused.
#[test]
fn row_major_layers_give_the_column_major_bits() {
    // On the whole padded grid, then on tiles.
    for tile in [None, Some(10)] {
        row_major_layers_give_the_column_major_bits_on(tile);
    }
}

fn row_major_layers_give_the_column_major_bits_on(tile: Option<usize>) {
    let (h, w, wp) = (131, 37, 5);
    let im = LayeredImager::with_tiles(h, w, wp, tile).unwrap();
    let psfs: Vec<Mat<f32>> = (0..2)
        .map(|k| Mat::from_fn(wp, wp, |i, j| 1.0 / (1.0 + (i * j + k) as f32)))
        .collect();
    let ks = im
        .kernel_spectra(&[Some(&psfs[0]), Some(&psfs[1])])
        .unwrap();
    let rad: Vec<Mat<f32>> = (0..2).map(|s| img(h, w, s)).collect();
    let al: Vec<Mat<f32>> = (0..2).map(|s| alpha(h, w, s + 3)).collect();
    let weight = Mat::from_fn(h, w, |i, j| 0.5 + ((i * 3 + j) % 7) as f32 / 3.0);
    // W×H matrices whose transposes are the planes: rows contiguous.
    let t = |m: &Mat<f32>| m.transpose().to_owned();
    let (rad_t, al_t, weight_t): (Vec<_>, Vec<_>, _) = (
        rad.iter().map(t).collect(),
        al.iter().map(t).collect(),
        t(&weight),
    );
    let layers = |rows: bool| -> Vec<SpectralLayer> {
        (0..2)
            .map(|l| match rows {
                true => SpectralLayer {
                    gain: 1.5,
                    weight: Some(weight_t.transpose()),
                    ..SpectralLayer::new(rad_t[l].transpose(), al_t[l].transpose(), l)
                },
                false => SpectralLayer {
                    gain: 1.5,
                    weight: Some(weight.as_ref()),
                    ..SpectralLayer::new(rad[l].as_ref(), al[l].as_ref(), l)
                },
            })
            .collect()
    };
    let g = Mat::from_fn(h, w, |i, j| ((i * 5 + j * 3) % 7) as f64 - 3.0);
    let run = |layers: &[SpectralLayer]| {
        let (image, mut tape) = im.forward_spectral(layers, &ks, None).unwrap();
        assert!(tape.take_spectra().is_some());
        let mut acc = im.kernel_grad_accumulator(2);
        im.vjp_kernels(layers, &tape, &g, &mut acc, None).unwrap();
        let scale = acc.radiance_scale.clone();
        (image, scale, im.kernel_grads(acc))
    };
    let (cols, rows) = (layers(false), layers(true));
    assert_eq!(rows[0].alpha.col_stride(), 1);
    let (a, b) = (run(&cols), run(&rows));
    assert!(a.0 == b.0, "images differ");
    assert_eq!(a.1, b.1);
    assert!(a.2 == b.2, "PSF gradients differ");
    assert!(im.image_spectral(&rows, &ks, None).unwrap() == a.0);
    let mixed = SpectralLayer {
        weight: Some(weight.as_ref()),
        ..rows[0]
    };
    let err = im
        .forward_spectral(&[mixed], &ks, None)
        .err()
        .expect("refused");
    assert!(err.to_string().contains("memory layout"), "{err}");
    // The VJP packs the layers again: the same refusal, not a panic.
    let (_, mut tape) = im.forward_spectral(&rows[..1], &ks, None).unwrap();
    tape.take_spectra();
    let mut acc = im.kernel_grad_accumulator(2);
    let err = im
        .vjp_kernels(&[mixed], &tape, &g, &mut acc, None)
        .expect_err("refused");
    assert!(err.to_string().contains("memory layout"), "{err}");
}

/// A layer's gain and weight are the caller's pre-scaled radiance, bit for bit (image, tape
/// and PSF gradient), and what they make non-finite is refused like a non-finite radiance.
#[test]
fn gain_scales_the_convolution_weight_is_the_prescaled_radiance_and_overflow_is_refused() {
    // On the whole padded grid, then on tiles.
    for tile in [None, Some(6)] {
        gain_scales_the_convolution_weight_is_the_prescaled_radiance_and_overflow_is_refused_on(
            tile,
        );
    }
}

fn gain_scales_the_convolution_weight_is_the_prescaled_radiance_and_overflow_is_refused_on(
    tile: Option<usize>,
) {
    let (h, w, wp) = (19, 26, 5);
    let im = LayeredImager::with_tiles(h, w, wp, tile).unwrap();
    let psf = Mat::from_fn(wp, wp, |i, j| 1.0 / (1.0 + (i * j) as f32));
    let ks = im.kernel_spectra(&[Some(&psf)]).unwrap();
    let rad: Vec<Mat<f32>> = (0..2).map(|s| img(h, w, s)).collect();
    let al: Vec<Mat<f32>> = (0..2).map(|s| alpha(h, w, s + 3)).collect();
    let weight = Mat::from_fn(h, w, |i, j| 0.5 + ((i * 3 + j) % 7) as f32 / 3.0);
    let gain = [3.7f32, 0.011];
    let weighted: Vec<Mat<f32>> = (0..2)
        .map(|l| Mat::from_fn(h, w, |i, j| weight[(i, j)] * rad[l][(i, j)]))
        .collect();
    let pre: Vec<SpectralLayer> = (0..2)
        .map(|l| SpectralLayer {
            gain: gain[l],
            ..SpectralLayer::new(weighted[l].as_ref(), al[l].as_ref(), 0)
        })
        .collect();
    let on_the_fly: Vec<SpectralLayer> = (0..2)
        .map(|l| SpectralLayer {
            gain: gain[l],
            weight: Some(weight.as_ref()),
            ..SpectralLayer::new(rad[l].as_ref(), al[l].as_ref(), 0)
        })
        .collect();
    let g = Mat::from_fn(h, w, |i, j| ((i * 5 + j * 3) % 7) as f64 - 3.0);
    let run = |layers: &[SpectralLayer]| {
        let (image, tape) = im.forward_spectral(layers, &ks, None).unwrap();
        let mut acc = im.kernel_grad_accumulator(1);
        im.vjp_kernels(layers, &tape, &g, &mut acc, None).unwrap();
        let scale = acc.radiance_scale.clone();
        (image, scale, im.kernel_grads(acc))
    };
    let (a, b) = (run(&pre), run(&on_the_fly));
    assert!(a.0 == b.0, "images differ");
    // Without the tape: the same image.
    assert!(im.image_spectral(&on_the_fly, &ks, None).unwrap() == a.0);
    assert_eq!(a.1, b.1);
    assert!(a.2[0] == b.2[0], "PSF gradients differ");
    // The gain on the convolution is the gain on the radiance, up to round-off: the image
    // of radiance gain · w · L with gain 1 (S1 is linear in the radiance channel).
    let scaled: Vec<Mat<f32>> = (0..2)
        .map(|l| Mat::from_fn(h, w, |i, j| gain[l] * weighted[l][(i, j)]))
        .collect();
    let plain: Vec<SpectralLayer> = (0..2)
        .map(|l| SpectralLayer::new(scaled[l].as_ref(), al[l].as_ref(), 0))
        .collect();
    let c = run(&plain);
    // S1's spectral path transforms in f32, whose round-off is relative to the grid's norm,
    // not to each pixel: up to the image's peak.
    let peak =
        c.0.col_iter()
            .flat_map(|c| c.iter().map(|v| v.abs()))
            .fold(0.0, f32::max);
    let mut worst = 0.0f32;
    for j in 0..w {
        for i in 0..h {
            let (x, y) = (c.0[(i, j)], a.0[(i, j)]);
            worst = worst.max((x - y).abs() / peak);
        }
    }
    assert!(worst <= 1e-6, "{worst}");
    // (The prescaled radiance is rounded to f32: 6e-8 of each value.)
    for (x, y) in c.1.iter().zip(&a.1) {
        assert!((x - y).abs() <= 1e-6 * x.abs().max(1.0), "{x} vs {y}");
    }

    // A weight of 4 on f32::MAX overflows to ∞ as it is packed: refused, naming the layers.
    let big = Mat::from_fn(h, w, |_, _| f32::MAX);
    let four = Mat::from_fn(h, w, |_, _| 4.0f32);
    let overflow = SpectralLayer {
        weight: Some(four.as_ref()),
        ..SpectralLayer::new(big.as_ref(), al[0].as_ref(), 0)
    };
    let err = im
        .forward_spectral(&[overflow], &ks, None)
        .err()
        .expect("refused");
    assert!(err.to_string().contains("non-finite"), "{err}");
    // A gain of 4 on it overflows the image, which is refused too.
    let loud = SpectralLayer {
        gain: 4.0,
        ..SpectralLayer::new(big.as_ref(), al[0].as_ref(), 0)
    };
    let err = im
        .forward_spectral(&[loud], &ks, None)
        .err()
        .expect("refused");
    assert!(err.to_string().contains("exceeds"), "{err}");
    assert!(im.image_spectral(&[loud], &ks, None).is_err());
    // A layer without coverage is skipped, but a NaN in it is still refused.
    let empty = Mat::<f32>::zeros(h, w);
    let nan = Mat::from_fn(h, w, |i, j| if i == 3 && j == 4 { f32::NAN } else { 1.0 });
    let uncovered = SpectralLayer::new(nan.as_ref(), empty.as_ref(), 0);
    assert!(
        im.forward_spectral(&[pre[0], uncovered], &ks, None)
            .is_err()
    );
    // A non-finite gain or a weight of the wrong shape: refused before any work.
    let inf_gain = SpectralLayer {
        gain: f32::INFINITY,
        ..pre[0]
    };
    assert!(im.forward_spectral(&[inf_gain], &ks, None).is_err());
    let small = Mat::<f32>::zeros(h - 1, w);
    let bad_weight = SpectralLayer {
        weight: Some(small.as_ref()),
        ..pre[0]
    };
    let err = im
        .forward_spectral(&[bad_weight], &ks, None)
        .err()
        .expect("refused");
    assert!(err.to_string().contains("weight"), "{err}");
}

/// S1's spectral path transforms αL and α in one f32 FFT; a radiance in the thousands must
/// not put its round-off into α∗P, which multiplies every layer behind: the image and ∂L/∂P
/// stay within f32 round-off of the f64 reference, relative to their peaks, when every layer
/// is bright.
#[test]
fn bright_layers_keep_the_occlusion_at_f32_precision() {
    // On the whole padded grid, then on tiles.
    for tile in [None, Some(12)] {
        bright_layers_keep_the_occlusion_at_f32_precision_on(tile);
    }
}

fn bright_layers_keep_the_occlusion_at_f32_precision_on(tile: Option<usize>) {
    let (h, w, wp) = (40, 56, 9);
    let im = LayeredImager::with_tiles(h, w, wp, tile).unwrap();
    let psf = Mat::from_fn(wp, wp, |i, j| {
        let (y, x) = (i as f32 - 4.0, j as f32 - 4.0);
        (-(x * x + y * y) / 6.0).exp() / 18.85
    });
    let ks = im.kernel_spectra(&[Some(&psf)]).unwrap();
    let far_l = Mat::from_fn(h, w, |i, j| 3.0e4 + 50.0 * ((i * 5 + j * 3) % 11) as f32);
    let ones = Mat::from_fn(h, w, |_, _| 1.0f32);
    let near_l = Mat::from_fn(h, w, |i, j| 2.0e4 + 30.0 * ((i + j * 7) % 13) as f32);
    // An opaque disc in front, soft-edged.
    let near_a = Mat::from_fn(h, w, |i, j| {
        let r = ((i as f32 - 20.0).powi(2) + (j as f32 - 28.0).powi(2)).sqrt();
        (12.0 - r).clamp(0.0, 1.0)
    });
    let reference = [
        Layer {
            radiance: &far_l,
            alpha: &ones,
            psf: &psf,
        },
        Layer {
            radiance: &near_l,
            alpha: &near_a,
            psf: &psf,
        },
    ];
    let spectral = [
        SpectralLayer::new(far_l.as_ref(), ones.as_ref(), 0),
        SpectralLayer::new(near_l.as_ref(), near_a.as_ref(), 0),
    ];
    let want = im.forward_f64_image(&reference).unwrap();
    let (got, tape) = im.forward_spectral(&spectral, &ks, None).unwrap();
    let peak = want
        .col_iter()
        .flat_map(|c| c.iter().map(|v| v.abs()))
        .fold(0.0, f64::max);
    let worst = (0..h)
        .flat_map(|i| (0..w).map(move |j| (i, j)))
        .map(|(i, j)| (got[(i, j)] as f64 - want[(i, j)]).abs() / peak)
        .fold(0.0, f64::max);
    assert!(worst < 2e-6, "image: {worst:e} of the peak {peak}");
    let g = Mat::from_fn(h, w, |i, j| ((i * 5 + j * 3) % 7) as f64 - 3.0);
    let mut acc = im.kernel_grad_accumulator(1);
    im.vjp_kernels(&spectral, &tape, &g, &mut acc, None)
        .unwrap();
    let kg = im.kernel_grads(acc);
    let rg = im.vjp(&reference, &g).unwrap();
    let want_kg = Mat::from_fn(wp, wp, |i, j| rg.psf[0][(i, j)] + rg.psf[1][(i, j)]);
    let kpeak = want_kg
        .col_iter()
        .flat_map(|c| c.iter().map(|v| v.abs()))
        .fold(0.0, f64::max);
    let kworst = (0..wp)
        .flat_map(|i| (0..wp).map(move |j| (i, j)))
        .map(|(i, j)| (kg[0][(i, j)] - want_kg[(i, j)]).abs() / kpeak)
        .fold(0.0, f64::max);
    assert!(kworst < 1e-5, "∂L/∂P: {kworst:e} of the peak {kpeak}");
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    /// Any plane size (one row or one column included), kernel width, radiance magnitude and
    /// tile side (or the whole grid): row-major planes give the column-major path's result bit for bit, or the same refusal
    /// (an image beyond f32's range).
    #[test]
    fn row_and_column_major_layers_agree(
        h in 1usize..24,
        w in 1usize..24,
        half in 0usize..3,
        seed in 0usize..1000,
        mag in -30i32..30,
        tile in prop::option::of(1usize..12),
    ) {
        let wp = 2 * half + 1;
        let im = LayeredImager::with_tiles(h, w, wp, tile.map(|t| t.min(h.max(w)))).unwrap();
        let psf = Mat::from_fn(wp, wp, |i, j| 1.0 / (1.0 + (i + 2 * j + seed % 3) as f32));
        let ks = im.kernel_spectra(&[Some(&psf)]).unwrap();
        let big = 10f32.powi(mag);
        let rad: Vec<Mat<f32>> = (0..2)
            .map(|s| Mat::from_fn(h, w, |i, j| big * img(h, w, seed + s)[(i, j)]))
            .collect();
        let al: Vec<Mat<f32>> = (0..2).map(|s| alpha(h, w, seed + s + 1)).collect();
        let weight = Mat::from_fn(h, w, |i, j| 0.25 + ((i + 3 * j + seed) % 5) as f32);
        let t = |m: &Mat<f32>| m.transpose().to_owned();
        let (rad_t, al_t, weight_t): (Vec<_>, Vec<_>, _) =
            (rad.iter().map(t).collect(), al.iter().map(t).collect(), t(&weight));
        let cols: Vec<SpectralLayer> = (0..2)
            .map(|l| SpectralLayer {
                weight: Some(weight.as_ref()),
                ..SpectralLayer::new(rad[l].as_ref(), al[l].as_ref(), 0)
            })
            .collect();
        let rows: Vec<SpectralLayer> = (0..2)
            .map(|l| SpectralLayer {
                weight: Some(weight_t.transpose()),
                ..SpectralLayer::new(rad_t[l].transpose(), al_t[l].transpose(), 0)
            })
            .collect();
        match (im.image_spectral(&cols, &ks, None), im.image_spectral(&rows, &ks, None)) {
            (Ok(a), Ok(b)) => {
                prop_assert!(a == b, "images differ");
                prop_assert!(a.col_iter().all(|c| c.iter().all(|v| v.is_finite())));
            }
            (Err(a), Err(b)) => prop_assert_eq!(a.to_string(), b.to_string()),
            (a, b) => prop_assert!(false, "{:?} against {:?}", a.is_ok(), b.is_ok()),
        }
    }
}

/// A 40×44 imager on tiles of 12 (16² grids) with a 5×5 kernel, its kernel spectra, a radiance,
/// full coverage and a 3×3 patch of coverage.
struct TileScene {
    size: (usize, usize, usize),
    im: LayeredImager,
    psf: Mat<f32>,
    ks: KernelSpectra,
    rad: Mat<f32>,
    ones: Mat<f32>,
    patch: Mat<f32>,
}

fn tile_scene() -> TileScene {
    let (h, w, wp) = (40, 44, 5);
    let im = LayeredImager::with_tiles(h, w, wp, Some(12)).unwrap();
    let psf = Mat::from_fn(wp, wp, |i, j| 1.0 / (1.0 + (i * 2 + j) as f32));
    let ks = im.kernel_spectra(&[Some(&psf)]).unwrap();
    // A 3×3 patch inside tile (1, 2), against its right edge: its blur crosses into (1, 3).
    let patch = Mat::from_fn(h, w, |i, j| {
        if (14..17).contains(&i) && (33..36).contains(&j) {
            0.8
        } else {
            0.0
        }
    });
    TileScene {
        size: (h, w, wp),
        im,
        psf,
        ks,
        rad: img(h, w, 1),
        ones: Mat::from_fn(h, w, |_, _| 1.0f32),
        patch,
    }
}

/// On tiles, a layer costs only the tiles its α touches: one covered tile holds one tile
/// grid of spectrum, the image and ∂L/∂P still match the f64 reference, a tile whose α is
/// zero but whose neighbour's light reaches it gets that light, and spectra or kernel spectra
/// of the whole-grid imager are refused rather than read on the wrong grid.
#[test]
fn tiles_without_coverage_are_skipped() {
    let TileScene {
        size: (h, w, wp),
        im,
        psf,
        ks,
        rad,
        ones,
        patch,
    } = tile_scene();
    // 12 + 5 − 1 = 16, a fast size: tiles of 12, 4 × 4 of them.
    assert_eq!(im.tile(), Some(12));
    let layers = [
        SpectralLayer::new(rad.as_ref(), ones.as_ref(), 0),
        SpectralLayer::new(rad.as_ref(), patch.as_ref(), 0),
    ];
    let spectra = im.layer_spectra(&layers).unwrap();
    let tile_bytes = 16 * 16 * 8;
    assert_eq!(spectra.bytes(), (16 + 1) * tile_bytes);
    let reference = [
        Layer {
            radiance: &rad,
            alpha: &ones,
            psf: &psf,
        },
        Layer {
            radiance: &rad,
            alpha: &patch,
            psf: &psf,
        },
    ];
    let want = im.forward_f64_image(&reference).unwrap();
    let (got, tape) = im.forward_spectral(&layers, &ks, None).unwrap();
    assert_image_close(&got, &want);
    // The patch's blur reaches column 37, in tile (1, 3), which it does not cover.
    assert!((got[(15, 37)] as f64 - want[(15, 37)]).abs() < 1e-5 * want[(15, 37)].abs());
    let g = Mat::from_fn(h, w, |i, j| ((i * 5 + j * 3) % 7) as f64 - 3.0);
    let mut acc = im.kernel_grad_accumulator(1);
    im.vjp_kernels(&layers, &tape, &g, &mut acc, None).unwrap();
    let scale = acc.radiance_scale[0];
    let kg = im.kernel_grads(acc);
    let lg = im.vjp(&reference, &g).unwrap();
    // ∂/∂(radiance scale) = Σ_k Σ ∂L/∂L_k · L_k: the full layer's term reads the image below
    // the patch's layer over the patch's reach, which the tape keeps alone.
    let want: f64 = (0..2)
        .flat_map(|k| (0..h).flat_map(move |i| (0..w).map(move |j| (k, i, j))))
        .map(|(k, i, j)| lg.radiance[k][(i, j)] * rad[(i, j)] as f64)
        .sum();
    assert!(
        (scale - want).abs() < 1e-4 * (1.0 + want.abs()),
        "radiance scale: {scale} vs {want}"
    );
    for i in 0..wp {
        for j in 0..wp {
            let want = lg.psf[0][(i, j)] + lg.psf[1][(i, j)];
            assert!(
                (kg[0][(i, j)] - want).abs() < 1e-4 * (1.0 + want.abs()),
                "({i},{j}): {} vs {want}",
                kg[0][(i, j)]
            );
        }
    }
    let whole = LayeredImager::with_tiles(h, w, wp, None).unwrap();
    assert_eq!(whole.tile(), None);
    // The tape holds each layer's planes over the tiles it imaged: another imager's backward
    // refuses it, and so does this one given spectra of other tiles (another frame's patch),
    // rather than reading them against planes that do not cover them.
    let mut acc = whole.kernel_grad_accumulator(1);
    let err = whole.vjp_kernels(&layers, &tape, &g, &mut acc, None).err();
    let err = err.expect("refused").to_string();
    assert!(err.contains("another imager"), "{err}");
    let moved = Mat::from_fn(h, w, |i, j| if i < 3 && j < 3 { 0.8 } else { 0.0 });
    let other = im
        .layer_spectra(&[
            SpectralLayer::new(rad.as_ref(), ones.as_ref(), 0),
            SpectralLayer::new(rad.as_ref(), moved.as_ref(), 0),
        ])
        .unwrap();
    let mut acc = im.kernel_grad_accumulator(1);
    let err = im
        .vjp_kernels(&layers, &tape, &g, &mut acc, Some(&other))
        .err();
    let err = err.expect("refused").to_string();
    assert!(err.contains("other tiles"), "{err}");
    // The forward pass's refusal of other spectra, as text.
    let refused = |ks: &KernelSpectra, spectra: Option<&LayerSpectra>| {
        let err = im.forward_spectral(&layers, ks, spectra).err();
        err.expect("refused").to_string()
    };
    let whole_spectra = whole.layer_spectra(&layers).unwrap();
    let err = refused(&ks, Some(&whole_spectra));
    assert!(err.contains("tiles of"), "{err}");
    let whole_ks = whole.kernel_spectra(&[Some(&psf)]).unwrap();
    let err = refused(&whole_ks, None);
    assert!(err.contains("another imager"), "{err}");
    // Spectra of a tiled imager of another image size (the same tiles and grids): refused,
    // not read out of its tiles' range.
    let taller = LayeredImager::with_tiles(h + 40, w, wp, Some(12)).unwrap();
    let (tr, ta) = (img(h + 40, w, 1), alpha(h + 40, w, 1));
    let tall = [SpectralLayer::new(tr.as_ref(), ta.as_ref(), 0); 2];
    let tall_spectra = taller.layer_spectra(&tall).unwrap();
    let err = refused(&ks, Some(&tall_spectra));
    assert!(err.contains("of 80×44"), "{err}");
    assert!(LayeredImager::with_tiles(h, w, wp, Some(0)).is_err());
    assert!(LayeredImager::with_tiles(h, w, wp, Some(45)).is_err());
    assert!(LayeredImager::with_tiles(h, w, wp, Some(44)).is_ok());
}

/// A layer cover computed once (the tiles each layer reaches and its radiance scale) gives the
/// forward the bits it gets from its own pass over the planes — image, recorded spectra and
/// the PSF gradient through its tape — and is what the forward uses (another frame's cover
/// changes the image); an untiled imager has none, a cover of another number of layers is
/// refused, and a plane the forward would refuse is refused by `layer_cover` too.
#[test]
fn a_kept_layer_cover_gives_the_forward_its_bits() {
    let TileScene {
        size: (h, w, wp),
        im,
        psf,
        ks,
        rad,
        ones,
        patch,
    } = tile_scene();
    let zeros = Mat::<f32>::zeros(h, w);
    let layers = [
        SpectralLayer::new(rad.as_ref(), ones.as_ref(), 0),
        SpectralLayer::new(rad.as_ref(), zeros.as_ref(), 0),
        SpectralLayer::new(rad.as_ref(), patch.as_ref(), 0),
    ];
    let cover = im.layer_cover(&layers).unwrap().expect("a tiled imager");
    // Three layers' slots and the 16 + 0 + 1 tiles they reach, four bytes each.
    let slot = std::mem::size_of::<Option<(Vec<u32>, f32)>>();
    assert_eq!(cover.bytes(), 3 * slot + 4 * 17);
    let (a, mut ta) = im.forward_spectral(&layers, &ks, None).unwrap();
    let (b, mut tb) = im
        .forward_spectral_covered(&layers, &ks, None, Some(&cover))
        .unwrap();
    assert!(a == b, "the image");
    let g = Mat::from_fn(h, w, |i, j| ((i * 5 + j * 3) % 7) as f64 - 3.0);
    let (mut acc_a, mut acc_b) = (im.kernel_grad_accumulator(1), im.kernel_grad_accumulator(1));
    im.vjp_kernels(&layers, &ta, &g, &mut acc_a, None).unwrap();
    im.vjp_kernels(&layers, &tb, &g, &mut acc_b, None).unwrap();
    assert!(im.kernel_grads(acc_a) == im.kernel_grads(acc_b), "∂L/∂P");
    assert_eq!(ta.take_spectra(), tb.take_spectra(), "the recorded spectra");
    // Another frame's cover (the layers in another order): the forward follows it.
    let other = im
        .layer_cover(&[layers[2], layers[1], layers[0]])
        .unwrap()
        .unwrap();
    let (c, _) = im
        .forward_spectral_covered(&layers, &ks, None, Some(&other))
        .unwrap();
    assert!(c != a);
    let err = im
        .forward_spectral_covered(&layers[..2], &ks, None, Some(&cover))
        .err()
        .expect("refused")
        .to_string();
    assert!(err.contains("a cover of 3 layers for 2 layers"), "{err}");
    let whole = LayeredImager::with_tiles(h, w, wp, None).unwrap();
    assert!(whole.layer_cover(&layers).unwrap().is_none());
    // The cover of another imager — untiled, or tiled otherwise with in-range tile indices —
    // is refused, not read.
    let whole_ks = whole.kernel_spectra(&[Some(&psf)]).unwrap();
    let err = whole
        .forward_spectral_covered(&layers, &whole_ks, None, Some(&cover))
        .err()
        .expect("refused")
        .to_string();
    assert!(err.contains("for this imager of 40×44 (no tiles)"), "{err}");
    let finer = LayeredImager::with_tiles(h, w, wp, Some(8)).unwrap();
    let finer_ks = finer.kernel_spectra(&[Some(&psf)]).unwrap();
    let err = finer
        .forward_spectral_covered(&layers, &finer_ks, None, Some(&cover))
        .err()
        .expect("refused")
        .to_string();
    assert!(err.contains("on tiles of 12 (16² grids)"), "{err}");
    let mut bad = ones.clone();
    bad[(3, 4)] = f32::NAN;
    let nan = [SpectralLayer::new(rad.as_ref(), bad.as_ref(), 0)];
    assert!(im.layer_cover(&nan).is_err());
    assert!(im.forward_spectral(&nan, &ks, None).is_err());
}

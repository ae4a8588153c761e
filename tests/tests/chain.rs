//! The camera chain end to end (issue: the simulated camera): datasets round-trip, one geometry
//! for every p̂, S1 against a direct convolution, photon conservation across pitches, opaque
//! occlusion, and the end-to-end gradient against central finite differences.

use faer::Mat;
use nanoeye_datagen::render::{
    Batcher, Dataset, DatasetOptions, LayerInfo, LayerSpec, RenderSet, SceneSource, StoredFrame,
    StoredLayer, dataset::plan, dataset::render_planned, dataset::rig_at_size, write_dataset,
};
use nanoeye_gaze::{GazeSolver, Rig, SphereSolver};
use nanoeye_nets::loss::{dice_loss, dice_target_grad};
use nanoeye_nets::{Arch, BnMode, Supernet, SupernetConfig, Tensor};
use nanoeye_optics::PhaseMap;
use nanoeye_optics::PsfModel;
use nanoeye_search::{
    CameraChain, ChainConfig, ChainFrame, DepthSplit, LensSpec, NativeGrid, SlipTarget, StepPsfs,
    task_loss,
};
use nanoeye_sensor::{BoxIntegrator, NoiseMode};
use proptest::prelude::*;
use std::path::Path;

const W: usize = 80;
const H: usize = 50;

fn opts(dir: &Path, seed: u64) -> DatasetOptions {
    DatasetOptions {
        set: RenderSet::Ambiguity,
        n: 1,
        seed,
        width_px: W,
        height_px: H,
        spp: 2,
        out_dir: dir.to_path_buf(),
        rig: Rig::default(),
        source: SceneSource::Procedural,
        progress: false,
        layers: LayerSpec::default(),
        blink_fraction: 0.0,
        protocol_grid: nanoeye_datagen::states::PROTOCOL_GRID,
    }
}

fn tiny_dataset() -> (tempfile::TempDir, Dataset) {
    let dir = tempfile::tempdir().unwrap();
    write_dataset(&opts(dir.path(), 3)).unwrap();
    let ds = Dataset::open(dir.path()).unwrap();
    (dir, ds)
}

/// Coarse but fast: a 10 µm metasurface grid (the chain's consistency, not the lens's
/// convergence, is under test).
fn test_cfg() -> ChainConfig {
    let mut c = ChainConfig {
        aperture_step_m: 10e-6,
        ..ChainConfig::default()
    };
    c.sensor.base_pitch = 48e-6;
    // 48 µm pixels collect 256× the light of 3 µm ones: keep the signal below full well.
    c.radiometry.exposure_s = 0.1e-3 / 256.0;
    c
}

fn chain_for(ds: &Dataset) -> CameraChain {
    CameraChain::for_dataset(ds, test_cfg()).unwrap()
}

fn hyperbolic(chain: &CameraChain) -> PhaseMap {
    LensSpec::Hyperbolic
        .phase_map(chain.aperture_grid(), 940e-9, 2e-3)
        .unwrap()
}

fn frame_with(ds: &Dataset, layers: Vec<StoredLayer>) -> ChainFrame {
    ChainFrame {
        id: 0,
        source: None,
        data: StoredFrame {
            layers,
            mask_visible_pupil: Mat::zeros(H, W),
            mask_pupil: Mat::zeros(H, W),
        },
        record: ds.records[0].clone(),
    }
}

fn layer(k: usize, radiance: Mat<f32>, alpha: Mat<f32>) -> StoredLayer {
    let s = LayerSpec::default();
    let dz = (s.far_m - s.near_m) / s.count as f64;
    let info = LayerInfo {
        index: k,
        near_m: s.near_m + dz * k as f64,
        far_m: s.near_m + dz * (k + 1) as f64,
    };
    StoredLayer::new(info, radiance.as_ref(), alpha.as_ref())
}

fn sum(m: &Mat<f32>) -> f64 {
    m.col_iter()
        .map(|c| c.iter().map(|&v| v as f64).sum::<f64>())
        .sum()
}

#[test]
fn datasets_round_trip_exactly() {
    let (dir, ds) = tiny_dataset();
    assert_eq!(ds.len(), 3);
    let o = opts(dir.path(), 3);
    let rig = rig_at_size(&o.rig, W, H).unwrap();
    let planned = plan(o.set, &rig, &o.source, o.n, o.seed, o.protocol_grid).unwrap();
    for (i, f) in planned.iter().enumerate() {
        let pixel_seed = o.seed ^ (i as u64).wrapping_mul(0xA076_1D64_78BD_642F);
        let (frame, _) = render_planned(&rig, &o.source, f, o.spp, pixel_seed, o.layers).unwrap();
        let back = ds.load(i).unwrap();
        let kept: Vec<_> = frame.layers.layers.iter().filter(|l| !l.empty).collect();
        assert_eq!(kept.len(), back.layers.len());
        for (a, b) in kept.iter().zip(&back.layers) {
            assert_eq!(a.radiance.as_ref(), b.radiance());
            assert_eq!(a.alpha.as_ref(), b.alpha());
            assert_eq!((a.near_m, a.far_m), (b.info.near_m, b.info.far_m));
        }
        assert_eq!(frame.mask_visible_pupil, back.mask_visible_pupil);
        assert_eq!(frame.mask_pupil, back.mask_pupil);
        assert_eq!(ds.records[i].state, f.state);
    }
}

#[test]
fn resume_with_other_parameters_is_refused() {
    let (dir, _) = tiny_dataset();
    let mut o = opts(dir.path(), 4);
    let err = write_dataset(&o).unwrap_err().to_string();
    assert!(err.contains("seed"), "{err}");
    o.seed = 3;
    o.spp = 3;
    let err = write_dataset(&o).unwrap_err().to_string();
    assert!(err.contains("spp"), "{err}");
    o.spp = 2;
    let s = write_dataset(&o).unwrap();
    assert_eq!((s.written, s.skipped), (0, 3));
}

#[test]
fn batcher_is_a_seeded_permutation() {
    let b = Batcher::new(&[5, 3], 3, 7).unwrap();
    assert_eq!(b.batches_per_epoch(), 3);
    let e0 = b.epoch(0);
    let mut sorted = e0.clone();
    sorted.sort();
    let all: Vec<_> = (0..5)
        .map(|i| (0, i))
        .chain((0..3).map(|i| (1, i)))
        .collect();
    assert_eq!(sorted, all);
    assert_eq!(e0, Batcher::new(&[5, 3], 3, 7).unwrap().epoch(0));
    assert_ne!(e0, b.epoch(1));
    let cat: Vec<_> = (0..3).flat_map(|s| b.batch(s)).collect();
    assert_eq!(cat, e0);
    assert_eq!(b.batch(3), b.epoch(1)[..3].to_vec());
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]
    /// For any native sensor and p̂ (integer or not), the sensor's output grid, the camera at
    /// p̂ and the gaze solver's mask check agree, and the downsampled mask's centroid is the
    /// native centroid mapped through the camera.
    #[test]
    fn one_geometry_for_every_pitch(
        w in 40usize..1400, aspect in 0.4f64..1.0, base_um in 1.0f64..6.0, ratio in 1.0f64..4.0,
    ) {
        let h = ((w as f64 * aspect) as usize).max(10);
        let mut rig = Rig::default();
        rig.camera = rig.camera.with_pitch(rig.camera.pixel_pitch_m).unwrap();
        rig.camera.width_px = w;
        rig.camera.height_px = h;
        rig.camera.cx_px = w as f64 / 2.0;
        rig.camera.cy_px = h as f64 / 2.0;
        rig.camera.pixel_pitch_m = base_um * 1e-6;
        rig.camera.fx_px = rig.camera.focal_length_m / rig.camera.pixel_pitch_m;
        rig.camera.fy_px = rig.camera.fx_px;
        let native = NativeGrid::new(rig.camera.clone()).unwrap();
        let p_hat = base_um * 1e-6 * ratio;
        let Ok(grid) = native.at(p_hat) else {
            // Only an effective pixel larger than the sensor may be refused.
            prop_assert!(ratio > w.min(h) as f64);
            return Ok(());
        };
        let integ = BoxIntegrator::new(h, w, base_um * 1e-6, p_hat, base_um * 1e-6).unwrap();
        prop_assert_eq!(integ.out_shape(), grid.shape());
        let (oh, ow) = grid.shape();
        prop_assert!((grid.camera.cx_px - ow as f64 / 2.0).abs() < 1e-9);
        prop_assert!((grid.camera.cy_px - oh as f64 / 2.0).abs() < 1e-9);
        // A disc mask near the centre: downsample it and solve on the p̂ camera.
        // Binning moves a centroid by a fraction of an output pixel (a box sum keeps the mass,
        // not the first moment): a disc at least 4 output pixels in radius, inside the
        // covered area, keeps it within 0.1 px.
        let r = h as f64 * 0.3;
        prop_assume!(r / ratio >= 4.0);
        let (u0, v0) = (w as f64 * 0.5 - 0.3 * r, h as f64 * 0.5 + 0.1 * r);
        let m = Mat::from_fn(h, w, |i, j| {
            let (du, dv) = (j as f64 + 0.5 - u0, i as f64 + 0.5 - v0);
            if du * du + dv * dv < r * r { 1.0f32 } else { 0.0 }
        });
        let md = grid.downsample_mask(&m).unwrap();
        let mut prig = rig.clone();
        prig.camera = grid.camera.clone();
        let solver = SphereSolver::new(&prig).unwrap();
        let c = solver.mask_centroid(md.as_ref()).unwrap();
        prop_assert_eq!(c.scale, 1.0);
        // Native centroid mapped to p̂ pixels: u' = cx' + (u − cx)·k.
        let (mut m0, mut mu, mut mv) = (0.0, 0.0, 0.0);
        for i in 0..h { for j in 0..w { let x = m[(i, j)] as f64; m0 += x; mu += x * (j as f64 + 0.5); mv += x * (i as f64 + 0.5); } }
        let k = 1.0 / ratio;
        let up = grid.camera.cx_px + (mu / m0 - w as f64 / 2.0) * k;
        let vp = grid.camera.cy_px + (mv / m0 - h as f64 / 2.0) * k;
        prop_assert!((c.px[0] - up).abs() < 0.1 && (c.px[1] - vp).abs() < 0.1,
            "{:?} vs ({up}, {vp})", c.px);
        prop_assert!(solver.solve_mask(md.as_ref(), [0.0; 3]).is_ok()
            || solver.solve_pixel(c.px, [0.0; 3]).is_err());
    }
}

/// Direct "same" convolution with the kernel centred at (wp/2, wp/2).
fn convolve(img: &Mat<f32>, k: &Mat<f32>) -> Mat<f64> {
    let (h, w, wp) = (img.nrows(), img.ncols(), k.nrows());
    let c = (wp / 2) as isize;
    Mat::from_fn(h, w, |i, j| {
        let mut s = 0.0;
        for a in 0..wp {
            for b in 0..wp {
                let (y, x) = (i as isize - (a as isize - c), j as isize - (b as isize - c));
                if y >= 0 && x >= 0 && (y as usize) < h && (x as usize) < w {
                    s += k[(a, b)] as f64 * img[(y as usize, x as usize)] as f64;
                }
            }
        }
        s
    })
}

fn disc(cy: f64, cx: f64, r: f64, v: f32) -> Mat<f32> {
    Mat::from_fn(H, W, |i, j| {
        let (dy, dx) = (i as f64 + 0.5 - cy, j as f64 + 0.5 - cx);
        if dy * dy + dx * dx < r * r { v } else { 0.0 }
    })
}

fn all_slabs_psfs(chain: &CameraChain, map: &PhaseMap) -> std::sync::Arc<StepPsfs> {
    chain.psfs(map, &[true; 8]).unwrap()
}

/// The stack's normalised planes and powers as bits, for exact comparison.
fn psf_bits(p: &StepPsfs) -> (Vec<u32>, Vec<u64>) {
    let planes = p
        .unit
        .iter()
        .flat_map(|m| {
            let (r, c) = (m.nrows(), m.ncols());
            (0..r * c).map(move |i| m[(i / c, i % c)].to_bits())
        })
        .collect();
    (planes, p.eta.iter().map(|e| e.to_bits()).collect())
}

/// A fixed lens asks for the same stack once per batch, so the chain keeps the last one: it
/// holds the bits a fresh chain computes, the same map and slabs get it back, and a map that
/// differs in one sample, or another set of slabs, gets a stack of its own.
#[test]
fn the_last_psf_stack_is_reused_only_for_the_same_map_and_slabs() {
    use std::sync::Arc;
    let (_d, ds) = tiny_dataset();
    let chain = chain_for(&ds);
    let map = hyperbolic(&chain);
    let all = [true; 8];
    let a = chain.psfs(&map, &all).unwrap();
    assert!(Arc::ptr_eq(&a, &chain.psfs(&map, &all).unwrap()));
    let fresh = chain_for(&ds).psfs(&map, &all).unwrap();
    assert_eq!(psf_bits(&a), psf_bits(&fresh));

    let mut other = map.clone();
    let n = other.phase_rad.nrows();
    other.phase_rad[(n / 2, n / 2 + 3)] += 1.0;
    let b = chain.psfs(&other, &all).unwrap();
    assert!(!Arc::ptr_eq(&a, &b));
    assert_ne!(
        psf_bits(&a),
        psf_bits(&b),
        "one phase sample moved no PSF value"
    );
    let again = chain.psfs(&map, &all).unwrap();
    assert!(!Arc::ptr_eq(&b, &again));
    assert_eq!(psf_bits(&a), psf_bits(&again));

    let mut some = all;
    some[0] = false;
    let c = chain.psfs(&map, &some).unwrap();
    assert!(!Arc::ptr_eq(&again, &c));
    assert_eq!(c.eta[0], 0.0);
    assert_eq!(c.eta[1..], a.eta[1..]);
}

#[test]
fn a_bright_disc_images_to_its_psf_convolution() {
    let (_d, ds) = tiny_dataset();
    let chain = chain_for(&ds);
    let map = hyperbolic(&chain);
    let psfs = all_slabs_psfs(&chain, &map);
    let k = 2;
    let l = disc(25.0, 40.0, 3.0, 0.5);
    let a = disc(25.0, 40.0, 3.0, 1.0);
    let f = frame_with(&ds, vec![layer(k, l.clone(), a)]);
    let fwd = chain
        .forward(std::slice::from_ref(&f), &psfs, 48e-6, NoiseMode::None, 0)
        .unwrap();
    // Expected: (scale·L) ∗ P_k (the raw PSF: η_k P̂_k), pitch = native, κ = 1, × QE.
    let cfg = test_cfg();
    let mut cam = ds.manifest.rig.camera.clone();
    cam.pixel_pitch_m = cfg.sensor.base_pitch;
    let light_d = {
        let light = nanoeye_datagen::render::Light::near_camera(&cam.nominal_pose());
        let apex = [
            0.0,
            0.0,
            nanoeye_datagen::render::Subject::default().cornea_apex_m,
        ];
        nanoeye_gaze::geom::norm(nanoeye_gaze::geom::sub(light.position_m, apex))
    };
    let scale = cfg
        .radiometry
        .scale_map(&cam, ds.manifest.light_intensity_w_per_sr, light_d)
        .unwrap();
    let src = Mat::from_fn(H, W, |i, j| scale[(i, j)] * l[(i, j)]);
    let expect = convolve(&src, &psfs.stack.planes[k]);
    let qe = cfg.sensor.quantum_efficiency;
    let got = &fwd.electrons[0];
    let peak = (0..H)
        .flat_map(|i| (0..W).map(move |j| (i, j)))
        .map(|(i, j)| expect[(i, j)])
        .fold(0.0, f64::max);
    assert!(peak > 0.0);
    for i in 0..H {
        for j in 0..W {
            let e = qe * expect[(i, j)];
            assert!(
                (got[(i, j)] as f64 - e).abs() < 1e-4 * qe * peak,
                "({i},{j}): {} vs {e}",
                got[(i, j)]
            );
        }
    }
}

#[test]
fn electrons_are_conserved_across_pitches() {
    let (_d, ds) = tiny_dataset();
    let chain = chain_for(&ds);
    let map = hyperbolic(&chain);
    let psfs = all_slabs_psfs(&chain, &map);
    // Light well inside the 78×48 area the 3× grid covers (W, H not multiples of 3).
    let l = disc(24.0, 39.0, 6.0, 1.0);
    let f = frame_with(&ds, vec![layer(3, l.clone(), disc(24.0, 39.0, 6.0, 1.0))]);
    let one = chain
        .forward(std::slice::from_ref(&f), &psfs, 48e-6, NoiseMode::None, 0)
        .unwrap();
    let three = chain
        .forward(std::slice::from_ref(&f), &psfs, 144e-6, NoiseMode::None, 0)
        .unwrap();
    assert_eq!(three.grid.shape(), (16, 26));
    let (a, b) = (sum(&one.electrons[0]), sum(&three.electrons[0]));
    assert!(a > 0.0);
    assert!((a - b).abs() < 1e-5 * a, "{a} vs {b}");
}

#[test]
fn an_opaque_near_layer_hides_what_is_behind_it() {
    let (_d, ds) = tiny_dataset();
    let chain = chain_for(&ds);
    let map = hyperbolic(&chain);
    let psfs = all_slabs_psfs(&chain, &map);
    let ones = Mat::from_fn(H, W, |_, _| 1.0f32);
    let block = Mat::from_fn(H, W, |i, j| {
        if (10..40).contains(&i) && (20..60).contains(&j) {
            1.0f32
        } else {
            0.0
        }
    });
    let far = layer(6, ones.clone(), ones.clone());
    let near = layer(1, Mat::zeros(H, W), block);
    let f = frame_with(&ds, vec![near, far]);
    let fwd = chain
        .forward(std::slice::from_ref(&f), &psfs, 48e-6, NoiseMode::None, 0)
        .unwrap();
    let e = &fwd.electrons[0];
    let r = chain.psf_px() / 2;
    let open = e[(2, 2)] as f64;
    assert!(open > 1.0, "background must be lit: {open}");
    // Up to S1's f32 transforms: 1 − α∗P of an opaque pixel is zero to ~1e-6 (the round-off
    // of α∗P ≈ 1), so 1e-5 of the light behind (1e-6 until S1 moved to f32, 2026-12-01).
    for i in 10 + r..40 - r {
        for j in 20 + r..60 - r {
            assert!(
                (e[(i, j)] as f64) < 1e-5 * open,
                "({i},{j}) leaks {} of {open}",
                e[(i, j)]
            );
        }
    }
}

/// Loss on the chain's output, for FD checks: a fixed linear functional of the network input
/// (`net` None) or the task loss of a full-resolution min subnet.
struct Rig1 {
    _d: Option<tempfile::TempDir>,
    ds: Dataset,
    chain: CameraChain,
}

fn loss_at(
    r: &Rig1,
    map: &PhaseMap,
    p_hat: f64,
    net: Option<&mut Supernet>,
) -> (f64, nanoeye_search::ChainGrad) {
    let frames = r.chain.load(&r.ds, &[0, 1, 2]).unwrap();
    let psfs = r.chain.psfs(map, &r.chain.active(&frames)).unwrap();
    let fwd = r
        .chain
        .forward(&frames, &psfs, p_hat, NoiseMode::Gaussian, 11)
        .unwrap();
    // The linear loss ⟨r, input⟩ has no target; the task loss's mask target moves with p̂.
    let (l, dx, d_mask) = match net {
        Some(net) => {
            net.zero_grad();
            let arch = Arch {
                resolution_scale: 1.0,
                ..Arch::min()
            };
            let (l, g) = task_loss(
                net,
                &[arch],
                &fwd.input,
                &fwd.mask,
                &fwd.slip_mm,
                [0.1; 3],
                BnMode::Train,
            )
            .unwrap();
            (l.total, g.input, Some(g.mask))
        }
        None => {
            let mut dx = fwd.input.clone();
            for (i, v) in dx.data.iter_mut().enumerate() {
                *v = ((i * 7919) % 13) as f32 / 13.0 - 0.4;
            }
            let l = dx
                .data
                .iter()
                .zip(&fwd.input.data)
                .map(|(a, b)| *a as f64 * *b as f64)
                .sum();
            (l, dx, None)
        }
    };
    let mut acc = r.chain.accumulator();
    r.chain
        .backward(&frames, &psfs, &fwd, &dx, &mut acc)
        .unwrap();
    if let Some(dm) = &d_mask {
        r.chain
            .target_backward(&frames, &fwd, dm, &mut acc)
            .unwrap();
    }
    (l, r.chain.finish(map, &psfs, acc).unwrap())
}

fn smooth_dir(n: usize, t: usize, seed: f64) -> Mat<f64> {
    Mat::from_fn(n, n, |i, j| {
        ((i as f64 * 0.07 * seed).sin() + (j as f64 * 0.05 + t as f64).cos()) * 0.5
    })
}

fn shifted(map: &PhaseMap, dir: &Mat<f64>, s: f64) -> PhaseMap {
    let n = map.grid.n;
    let ph = Mat::from_fn(n, n, |i, j| map.phase_rad[(i, j)] + s * dir[(i, j)]);
    PhaseMap::new(map.grid, ph, map.amplitude.clone()).unwrap()
}

fn dot(a: &Mat<f64>, b: &Mat<f64>) -> f64 {
    (0..a.nrows())
        .flat_map(|i| (0..a.ncols()).map(move |j| (i, j)))
        .map(|(i, j)| a[(i, j)] * b[(i, j)])
        .sum()
}

fn rig1() -> Rig1 {
    let (d, ds) = tiny_dataset();
    let chain = chain_for(&ds);
    Rig1 {
        _d: Some(d),
        ds,
        chain,
    }
}

#[test]
fn chain_gradient_matches_central_differences() {
    let r = rig1();
    let map = hyperbolic(&r.chain);
    // Inside one output size: at 100 µm the 50-px side holds exactly 24 pixels, and the grid
    // loses one (and re-centres) just above, a jump the loss really has.
    let p_hat = 103e-6;
    let (l0, g) = loss_at(&r, &map, p_hat, None);
    assert!(l0.is_finite());
    // Deterministic for fixed seeds.
    assert_eq!(loss_at(&r, &map, p_hat, None).0, l0);
    let n = map.grid.n;
    for (t, seed) in [(0usize, 1.3f64), (1, 2.9)] {
        let dir = smooth_dir(n, t, seed);
        let an = dot(&g.phase_rad, &dir);
        let eps = 1e-2;
        let lp = loss_at(&r, &shifted(&map, &dir, eps), p_hat, None).0;
        let lm = loss_at(&r, &shifted(&map, &dir, -eps), p_hat, None).0;
        let fd = (lp - lm) / (2.0 * eps);
        assert!(
            (fd - an).abs() < 0.02 * fd.abs().max(an.abs()),
            "φ direction {t}: FD {fd:e} vs VJP {an:e}"
        );
    }
    // p̂ (the box weights are piecewise linear: a small step stays on one piece).
    let h = 1e-8;
    let fd =
        (loss_at(&r, &map, p_hat + h, None).0 - loss_at(&r, &map, p_hat - h, None).0) / (2.0 * h);
    assert!(
        (fd - g.p_hat).abs() < 0.02 * fd.abs().max(g.p_hat.abs()),
        "p̂: FD {fd:e} vs VJP {:e}",
        g.p_hat
    );
}

/// A fixed lens's backward (`pitch_accumulator`) skips S1's PSF adjoint but gives ∂L/∂p̂ bit for
/// bit as the full backward does; the PSF VJP refuses such an accumulator.
#[test]
fn a_fixed_lens_gets_the_same_pitch_gradient_without_the_psf_adjoint() {
    let r = rig1();
    let map = hyperbolic(&r.chain);
    let frames = r.chain.load(&r.ds, &[0, 1, 2]).unwrap();
    let psfs = r.chain.psfs(&map, &r.chain.active(&frames)).unwrap();
    let fwd = r
        .chain
        .forward(&frames, &psfs, 103e-6, NoiseMode::Gaussian, 5)
        .unwrap();
    let mut dx = fwd.input.clone();
    for (i, v) in dx.data.iter_mut().enumerate() {
        *v = ((i * 7919) % 13) as f32 / 13.0 - 0.4;
    }
    let (mut full, mut pitch) = (r.chain.accumulator(), r.chain.pitch_accumulator());
    for acc in [&mut full, &mut pitch] {
        r.chain.backward(&frames, &psfs, &fwd, &dx, acc).unwrap();
    }
    assert!(full.p_hat() != 0.0);
    assert_eq!(full.p_hat().to_bits(), pitch.p_hat().to_bits());
    let err = r.chain.finish(&map, &psfs, pitch).expect_err("refused");
    assert!(err.to_string().contains("pitch_accumulator"), "{err}");
    assert!(r.chain.finish(&map, &psfs, full).is_ok());
}

/// A forward that keeps no S1 tape takes a frame's S1 image from the chain's cache when the
/// frame (by dataset and index) was imaged under the same PSF stack: the same bits as a fresh
/// forward, another dataset's frame of the same index not confused with it, the cache emptied
/// for another stack, and a backward to the PSFs refused.
#[test]
fn a_frame_seen_again_under_the_same_stack_skips_s1_with_the_same_bits() {
    let r = rig1();
    let (_d2, other) = {
        let dir = tempfile::tempdir().unwrap();
        write_dataset(&opts(dir.path(), 17)).unwrap();
        let ds = Dataset::open(dir.path()).unwrap();
        (dir, ds)
    };
    let map = hyperbolic(&r.chain);
    let frames = r.chain.load(&r.ds, &[0, 1]).unwrap();
    let others = r.chain.load(&other, &[0, 1]).unwrap();
    let psfs = r.chain.psfs(&map, &r.chain.active(&frames)).unwrap();
    let run = |fr: &[nanoeye_search::ChainFrame], grad: bool| {
        r.chain
            .forward_with(fr, &psfs, 103e-6, NoiseMode::Gaussian, 3, grad)
            .unwrap()
    };
    let fresh = run(&frames, true);
    let fresh_other = run(&others, true);
    assert_eq!(
        r.chain.cached_s1_images(),
        0,
        "a forward with a tape fills no cache"
    );
    let first = run(&frames, false);
    assert_eq!(r.chain.cached_s1_images(), 2);
    let again = run(&frames, false);
    let other_again = run(&others, false);
    assert_eq!(r.chain.cached_s1_images(), 4, "other dataset, other keys");
    for (a, b) in [
        (&fresh, &first),
        (&fresh, &again),
        (&fresh_other, &other_again),
    ] {
        assert!(a.input.data == b.input.data, "network input differs");
        assert!(a.electrons == b.electrons);
    }
    assert!(fresh.input.data != fresh_other.input.data);
    // Only ∂L/∂p̂ can flow back through a forward without a tape.
    let dx = again.input.clone();
    let mut acc = r.chain.accumulator();
    let err = r
        .chain
        .backward(&frames, &psfs, &again, &dx, &mut acc)
        .expect_err("no S1 tape");
    assert!(err.to_string().contains("pitch_accumulator"), "{err}");
    let mut pitch = r.chain.pitch_accumulator();
    r.chain
        .backward(&frames, &psfs, &again, &dx, &mut pitch)
        .unwrap();
    // Another lens: another stack, the cache emptied and refilled with its images.
    let flat = LensSpec::Flat
        .phase_map(r.chain.aperture_grid(), 940e-9, 2e-3)
        .unwrap();
    let psfs2 = r.chain.psfs(&flat, &r.chain.active(&frames)).unwrap();
    let b = r
        .chain
        .forward_with(&frames, &psfs2, 103e-6, NoiseMode::Gaussian, 3, false)
        .unwrap();
    assert_eq!(r.chain.cached_s1_images(), 2);
    assert!(b.input.data != fresh.input.data);
}

/// With the S1 image cache off (`sim`: each frame imaged once) a tape-less forward keeps no
/// image and gives the bits of one with the cache on.
#[test]
fn a_chain_without_the_s1_image_cache_keeps_no_images_and_the_same_bits() {
    let mut r = rig1();
    let map = hyperbolic(&r.chain);
    let frames = r.chain.load(&r.ds, &[0, 1]).unwrap();
    let psfs = r.chain.psfs(&map, &r.chain.active(&frames)).unwrap();
    let on = r
        .chain
        .forward_with(&frames, &psfs, 103e-6, NoiseMode::Gaussian, 3, false)
        .unwrap();
    assert_eq!(r.chain.cached_s1_images(), 2);
    r.chain.set_s1_cache(false);
    assert_eq!(r.chain.cached_s1_images(), 0, "turning it off empties it");
    let off = r
        .chain
        .forward_with(&frames, &psfs, 103e-6, NoiseMode::Gaussian, 3, false)
        .unwrap();
    assert_eq!(r.chain.cached_s1_images(), 0);
    assert!(on.input.data == off.input.data && on.electrons == off.electrons);
}

/// A frame's layer spectra do not depend on the lens: computed once, kept from one PSF
/// stack to the next and shared with another chain over the same data, and the forward and
/// the backward through them give the bits of frames imaged without them.
#[test]
fn layer_spectra_are_kept_across_lenses_with_the_same_bits() {
    let r = rig1();
    let frames = r.chain.load(&r.ds, &[0, 1]).unwrap();
    // Built in memory as far as the chain knows: never given kept spectra.
    let bare: Vec<ChainFrame> = frames.iter().map(ChainFrame::unkeyed).collect();
    let flat = LensSpec::Flat
        .phase_map(r.chain.aperture_grid(), 940e-9, 2e-3)
        .unwrap();
    let run = |fr: &[ChainFrame], map: &PhaseMap| {
        let psfs = r.chain.psfs(map, &r.chain.active(fr)).unwrap();
        let fwd = r
            .chain
            .forward(fr, &psfs, 103e-6, NoiseMode::Gaussian, 3)
            .unwrap();
        let dx = fwd.input.clone();
        let mut acc = r.chain.accumulator();
        r.chain.backward(fr, &psfs, &fwd, &dx, &mut acc).unwrap();
        (fwd.input.data, r.chain.finish(map, &psfs, acc).unwrap())
    };
    let before = r.chain.cached_layer_spectra();
    let mut inputs = vec![];
    for map in [hyperbolic(&r.chain), flat] {
        let want = run(&bare, &map);
        let got = run(&frames, &map);
        assert!(got.0 == want.0, "network input differs");
        assert!(got.1.phase_rad == want.1.phase_rad, "∂L/∂φ differs");
        assert_eq!(got.1.p_hat.to_bits(), want.1.p_hat.to_bits());
        inputs.push(got.0);
    }
    assert!(inputs[0] != inputs[1], "two lenses, two images");
    assert!(r.chain.cached_layer_spectra() >= before + 2);
    assert!(nanoeye_search::spectra::layer_spectra_bytes() > 0);
    let again = CameraChain::for_dataset(&r.ds, test_cfg()).unwrap();
    assert!(
        again.cached_layer_spectra() >= 2,
        "a chain over the same data shares the kept spectra"
    );
}

/// A layer that is not finite is refused with the frame and the depth slab it belongs to
/// named (S1 numbers its layers back to front, the slab is its kernel), with and without
/// S1's tape.
#[test]
fn a_non_finite_layer_is_refused_naming_the_frame() {
    let (_d, ds) = tiny_dataset();
    let chain = chain_for(&ds);
    let map = hyperbolic(&chain);
    let psfs = all_slabs_psfs(&chain, &map);
    let mut l = disc(24.0, 39.0, 6.0, 1.0);
    l[(24, 39)] = f32::NAN;
    let near = layer(1, disc(20.0, 30.0, 4.0, 1.0), disc(20.0, 30.0, 4.0, 1.0));
    let mut f = frame_with(&ds, vec![near, layer(3, l, disc(24.0, 39.0, 6.0, 1.0))]);
    f.id = 7;
    for grad in [true, false] {
        let err = chain
            .forward_with(
                std::slice::from_ref(&f),
                &psfs,
                48e-6,
                NoiseMode::None,
                0,
                grad,
            )
            .err()
            .expect("refused");
        let msg = err.to_string();
        assert!(
            msg.contains("frame 7") && msg.contains("(kernel 3)") && msg.contains("non-finite"),
            "{msg}"
        );
    }
}

/// Threads standing in for the processes of a distributed run: `all_gather` swaps the shares
/// through shared slots between two barriers.
struct Exchange {
    barrier: std::sync::Barrier,
    slots: std::sync::Mutex<Vec<Vec<f64>>>,
}

struct ThreadSplit {
    ex: std::sync::Arc<Exchange>,
    parts: usize,
    part: usize,
    /// Values this part contributed, per gather.
    sent: std::sync::Mutex<Vec<usize>>,
}

impl DepthSplit for ThreadSplit {
    fn parts(&self) -> usize {
        self.parts
    }
    fn part(&self) -> usize {
        self.part
    }
    fn all_gather(&self, values: Vec<f64>) -> nanoeye_search::Result<Vec<Vec<f64>>> {
        self.sent.lock().unwrap().push(values.len());
        self.ex.slots.lock().unwrap()[self.part] = values;
        self.ex.barrier.wait();
        let all = self.ex.slots.lock().unwrap().clone();
        // Nobody overwrites a slot before every part has read this round.
        self.ex.barrier.wait();
        Ok(all)
    }
}

fn mat_bits(m: &Mat<f64>) -> Vec<u64> {
    (0..m.ncols())
        .flat_map(|j| (0..m.nrows()).map(move |i| (i, j)))
        .map(|ij| m[ij].to_bits())
        .collect()
}

/// A step's PSF stack and PSF VJP split over three "processes" (each computes every third
/// depth, then all-gathers) hold one process's bits: the planes, the loss and ∂L/∂φ, ∂L/∂p̂.
#[test]
fn a_chain_split_over_three_processes_gives_one_process_bits() {
    let r = rig1();
    let map = hyperbolic(&r.chain);
    let p_hat = 103e-6;
    let (l1, g1) = loss_at(&r, &map, p_hat, None);
    let frames = r.chain.load(&r.ds, &[0, 1, 2]).unwrap();
    let active = r.chain.active(&frames);
    let one = r.chain.psfs(&map, &active).unwrap();
    // The stack the PSF model gives directly.
    let direct = r
        .chain
        .psf_model()
        .forward(&map, r.chain.depths_m(), Some(&active))
        .unwrap();
    let active_n = active.iter().filter(|&&a| a).count();
    assert!(active_n >= 3, "{active:?}: the split needs depths to share");
    let parts = 3;
    let ex = std::sync::Arc::new(Exchange {
        barrier: std::sync::Barrier::new(parts),
        slots: std::sync::Mutex::new(vec![Vec::new(); parts]),
    });
    let results: Vec<_> = std::thread::scope(|s| {
        let hs: Vec<_> = (0..parts)
            .map(|part| {
                let ex = ex.clone();
                let ds = &r.ds;
                let map = &map;
                s.spawn(move || {
                    let split = std::sync::Arc::new(ThreadSplit {
                        ex,
                        parts,
                        part,
                        sent: Default::default(),
                    });
                    let mut chain = chain_for(ds);
                    chain.set_split(split.clone());
                    let frames = chain.load(ds, &[0, 1, 2]).unwrap();
                    let psfs = chain.psfs(map, &chain.active(&frames)).unwrap();
                    let planes = psfs.stack.planes.clone();
                    let rig = Rig1 {
                        _d: None,
                        ds: Dataset::open(&ds.dir).unwrap(),
                        chain,
                    };
                    let (l, g) = loss_at(&rig, map, p_hat, None);
                    let sent = split.sent.lock().unwrap().clone();
                    (planes, l, g, sent)
                })
            })
            .collect();
        hs.into_iter().map(|h| h.join().unwrap()).collect()
    });
    let wp = r.chain.psf_px();
    let n = map.grid.n;
    for (part, (planes, l, g, sent)) in results.iter().enumerate() {
        for (k, p) in planes.iter().enumerate() {
            let f = |m: &Mat<f32>| {
                (0..wp * wp)
                    .map(|x| m[(x % wp, x / wp)].to_bits())
                    .collect::<Vec<_>>()
            };
            assert_eq!(f(p), f(&one.stack.planes[k]), "part {part}: plane {k}");
            assert_eq!(
                f(&one.stack.planes[k]),
                f(&direct.planes[k]),
                "plane {k} differs from the model's"
            );
        }
        assert_eq!(l.to_bits(), l1.to_bits(), "part {part}: loss");
        assert_eq!(g.p_hat.to_bits(), g1.p_hat.to_bits(), "part {part}: ∂L/∂p̂");
        assert_eq!(
            mat_bits(&g.phase_rad),
            mat_bits(&g1.phase_rad),
            "part {part}: ∂L/∂φ"
        );
        // Each part computed its share only: every third active depth, planes then terms
        // (the step's stack once — `psfs` above; `loss_at` asks for the same map and slabs and
        // gets the chain's kept stack without another exchange — then the VJP).
        let mine =
            nanoeye_search::split::share(&(0..active_n).collect::<Vec<_>>(), parts, part).len();
        assert_eq!(sent[0], mine * wp * wp, "part {part}: {sent:?}");
        assert_eq!(sent.len(), 2, "part {part}: {sent:?}");
        assert!(sent[1] % (n * n) == 0 && sent[1] <= mine * n * n);
    }
    // The single-process chain's ∂L/∂φ is the PSF model's own VJP of the same upstream
    // gradient (checked against finite differences above): the split changes no bit of it.
    assert!(g1.phase_rad.norm_l2() > 0.0);
}

#[test]
fn end_to_end_gradient_through_the_network_matches_central_differences() {
    let r = rig1();
    let map = hyperbolic(&r.chain);
    let cfg = SupernetConfig {
        head_expand: 32,
        head_hidden: 16,
        ..SupernetConfig::default()
    };
    let mut net = Supernet::new(cfg, 5).unwrap();
    let p_hat = 50e-6;
    let (l0, g) = loss_at(&r, &map, p_hat, Some(&mut net));
    assert!(l0.is_finite());
    let n = map.grid.n;
    let dir = smooth_dir(n, 0, 1.7);
    let an = dot(&g.phase_rad, &dir);
    let eps = 5e-3;
    let lp = loss_at(&r, &shifted(&map, &dir, eps), p_hat, Some(&mut net)).0;
    let lm = loss_at(&r, &shifted(&map, &dir, -eps), p_hat, Some(&mut net)).0;
    let fd = (lp - lm) / (2.0 * eps);
    // 10 %: the network runs in f32 with ReLU/h-swish kinks and batch-statistics BN over a
    // 3-frame batch, so central differences carry a few per cent of curvature and rounding;
    // the chain alone is held to 2 % above.
    assert!(
        (fd - an).abs() < 0.10 * fd.abs().max(an.abs()),
        "φ: FD {fd:e} vs VJP {an:e} (loss {l0})"
    );
    // A few network weights.
    let _ = loss_at(&r, &map, p_hat, Some(&mut net));
    let mut picks = Vec::new();
    net.visit(&mut |name, p| {
        if picks.len() < 3 && p.grad.iter().any(|&v| v != 0.0) {
            let i = p
                .grad
                .iter()
                .enumerate()
                .max_by(|a, b| a.1.abs().total_cmp(&b.1.abs()))
                .map(|x| x.0)
                .unwrap();
            picks.push((name.to_string(), i, p.grad[i] as f64));
        }
    });
    assert!(!picks.is_empty());
    for (name, i, an) in picks {
        let bump = |net: &mut Supernet, d: f32| {
            net.visit(&mut |nm, p| {
                if nm == name {
                    p.value[i] += d;
                }
            })
        };
        let e = 1e-3f32;
        bump(&mut net, e);
        let lp = loss_at(&r, &map, p_hat, Some(&mut net)).0;
        bump(&mut net, -2.0 * e);
        let lm = loss_at(&r, &map, p_hat, Some(&mut net)).0;
        bump(&mut net, e);
        let fd = (lp - lm) / (2.0 * e as f64);
        assert!(
            (fd - an).abs() < 0.10 * fd.abs().max(an.abs()),
            "{name}[{i}]: FD {fd:e} vs {an:e}"
        );
    }
    // The lens matters: another phase map gives another loss.
    let dh = LensSpec::DoubleHelix
        .phase_map(r.chain.aperture_grid(), 940e-9, 2e-3)
        .unwrap();
    assert_ne!(loss_at(&r, &dh, p_hat, Some(&mut net)).0, l0);
}

/// ∂L/∂p̂ through the segmentation target (the pupil mask averaged onto the p̂ grid moves
/// with p̂, as the network input does): for fixed mask logits, `target_backward` of the Dice
/// loss's target gradient matches central differences of that loss in p̂. (Through the
/// network the loss in p̂ has kinks every few nm — ReLU/h-swish and box edges crossing
/// samples — so the p̂ check there is split: the chain's input part above, this part here,
/// the network's ∂L/∂input in nets' own checks.)
#[test]
fn the_mask_targets_pitch_gradient_matches_central_differences() {
    let r = rig1();
    let map = hyperbolic(&r.chain);
    let frames = r.chain.load(&r.ds, &[0, 1, 2]).unwrap();
    let psfs = r.chain.psfs(&map, &r.chain.active(&frames)).unwrap();
    let mask_at = |p: f64| {
        r.chain
            .forward(&frames, &psfs, p, NoiseMode::None, 11)
            .unwrap()
    };
    // Not at 50 or 51.2 µm, where the 80 × 50 px sensor of 48 µm pixels holds whole pixels.
    let p = 51.3e-6;
    let f0 = mask_at(p);
    let m = &f0.mask;
    let logits = Tensor::from_vec(
        m.n,
        1,
        m.h,
        m.w,
        (0..m.data.len())
            .map(|i| ((i * 37) % 23) as f32 / 4.0 - 2.5)
            .collect(),
    )
    .unwrap();
    let dm = dice_target_grad(&logits, m).unwrap();
    let mut acc = r.chain.pitch_accumulator();
    r.chain
        .target_backward(&frames, &f0, &dm, &mut acc)
        .unwrap();
    let an = acc.p_hat();
    let h = 1e-9;
    let fd = (dice_loss(&logits, &mask_at(p + h).mask).unwrap().0
        - dice_loss(&logits, &mask_at(p - h).mask).unwrap().0)
        / (2.0 * h);
    assert!(
        an.abs() > 0.0 && (fd - an).abs() < 1e-4 * fd.abs(),
        "FD {fd:e} vs VJP {an:e}"
    );
    // A wrongly shaped gradient is refused.
    let bad = Tensor::zeros(m.n, 1, m.h + 1, m.w);
    assert!(
        r.chain
            .target_backward(&frames, &f0, &bad, &mut acc)
            .is_err()
    );
}

/// A chain built and run on one thread gives the bits of one built and run on three: the
/// ranks of a distributed run use one thread each, a single process all its cores. (The PSF's
/// pixel quadrature came from faer's pooled SVD, whose last bits followed the pool's size
/// and reached every ∂L/∂φ.)
#[test]
fn chain_gradients_do_not_depend_on_the_thread_count() {
    let (_d, ds) = tiny_dataset();
    let run = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| {
                let r = Rig1 {
                    _d: None,
                    ds: Dataset::open(&ds.dir).unwrap(),
                    chain: chain_for(&ds),
                };
                let map = hyperbolic(&r.chain);
                let (l, g) = loss_at(&r, &map, 60e-6, None);
                (l.to_bits(), g.p_hat.to_bits(), mat_bits(&g.phase_rad))
            })
    };
    let (a, b) = (run(1), run(3));
    assert_eq!(a.0, b.0, "loss");
    assert_eq!(a.1, b.1, "∂L/∂p̂");
    assert!(a.2 == b.2, "∂L/∂φ");
}

/// The calibration head's targets are the frames' translations in mm by default and the
/// eye-equivalent translations with `SlipTarget::EyeEquivalent`; the rendered cameras turned,
/// so the two differ.
#[test]
fn slip_targets_follow_the_configured_definition() {
    let (_dir, ds) = tiny_dataset();
    let ids: Vec<usize> = (0..ds.len()).collect();
    let targets = |t: SlipTarget| {
        let chain = CameraChain::for_dataset(
            &ds,
            ChainConfig {
                slip_target: t,
                ..test_cfg()
            },
        )
        .unwrap();
        let frames = chain.load(&ds, &ids).unwrap();
        let map = hyperbolic(&chain);
        let psfs = chain.psfs(&map, &chain.active(&frames)).unwrap();
        let fwd = chain
            .forward(&frames, &psfs, 48e-6, NoiseMode::None, 0)
            .unwrap();
        fwd.slip_mm.data
    };
    let (tr, eq) = (
        targets(SlipTarget::Translation),
        targets(SlipTarget::EyeEquivalent),
    );
    let cam = &ds.manifest.rig.camera;
    let mut turned = 0;
    for (b, r) in ds.records.iter().enumerate() {
        let e = cam.eye_equivalent_slip(r.state.slip_m, r.state.cam_rot_rad);
        for a in 0..3 {
            assert_eq!(tr[b * 3 + a], (r.state.slip_m[a] * 1e3) as f32);
            assert_eq!(eq[b * 3 + a], (e[a] * 1e3) as f32);
        }
        turned += usize::from(r.state.cam_rot_rad != [0.0; 3]);
    }
    assert!(turned > 0, "no rendered camera turned");
    assert_ne!(tr, eq);
}

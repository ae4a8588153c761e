//! Criterion benches of the camera chain on a 320×200 (12 µm) render of one ambiguity pair:
//! the PSF stack of a step, forward (S1 + sensor) and backward per batch of 3 frames — with
//! the frames' layer spectra kept (a dataset's frames seen again) and computed in each call —
//! and the backward with the step's PSF VJP. Full-sensor numbers: docs/bench/chain.md.

use criterion::{Criterion, criterion_group, criterion_main};
use nanoeye_datagen::render::{
    Dataset, DatasetOptions, LayerSpec, RenderSet, SceneSource, write_dataset,
};
use nanoeye_gaze::Rig;
use nanoeye_nets::Tensor;
use nanoeye_search::{CameraChain, ChainConfig, ChainFrame, LensSpec};
use nanoeye_sensor::NoiseMode;
use std::hint::black_box;

fn bench(c: &mut Criterion) {
    let dir = tempfile::tempdir().expect("tempdir");
    write_dataset(&DatasetOptions {
        set: RenderSet::Ambiguity,
        n: 1,
        seed: 0,
        width_px: 320,
        height_px: 200,
        spp: 1,
        out_dir: dir.path().to_path_buf(),
        rig: Rig::default(),
        source: SceneSource::Procedural,
        progress: false,
        layers: LayerSpec::default(),
        blink_fraction: 0.0,
        protocol_grid: nanoeye_datagen::states::PROTOCOL_GRID,
    })
    .expect("render");
    let ds = Dataset::open(dir.path()).expect("dataset");
    let chain = CameraChain::for_dataset(&ds, ChainConfig::default()).expect("chain");
    let map = LensSpec::Hyperbolic
        .phase_map(chain.aperture_grid(), 940e-9, 2e-3)
        .expect("lens");
    let frames = chain.load(&ds, &[0, 1, 2]).expect("load");
    let active = chain.active(&frames);
    let p_hat = 14.5e-6;
    let mut g = c.benchmark_group("chain_320x200");
    g.sample_size(10);
    // Two maps in turn: the chain keeps the last stack it computed and would hand it back
    // for the same map, which is a lookup, not a stack.
    let nudged = {
        let mut ph = map.phase_rad.clone();
        ph[(0, 0)] += 1e-3;
        nanoeye_optics::PhaseMap::new(map.grid, ph, map.amplitude.clone()).expect("map")
    };
    let mut turn = false;
    g.bench_function("psf_stack", |b| {
        b.iter(|| {
            turn = !turn;
            let m = if turn { &nudged } else { &map };
            chain.psfs(black_box(m), &active).expect("psfs")
        })
    });
    let psfs = chain.psfs(&map, &active).expect("psfs");
    // After the first call the frames' layer spectra are kept (crate::spectra).
    g.bench_function("forward_3_frames", |b| {
        b.iter(|| {
            chain
                .forward(black_box(&frames), &psfs, p_hat, NoiseMode::Gaussian, 0)
                .expect("forward")
        })
    });
    // The same frames as if built in memory: never given kept spectra (as frames beyond
    // the spectra's budget); S1 computes them and records them on its tape.
    let bare: Vec<ChainFrame> = frames.iter().map(ChainFrame::unkeyed).collect();
    g.bench_function("forward_3_frames_spectra_computed", |b| {
        b.iter(|| {
            chain
                .forward(black_box(&bare), &psfs, p_hat, NoiseMode::Gaussian, 0)
                .expect("forward")
        })
    });
    // Without S1's tape (a fixed lens, evaluation): after the first call every frame's S1
    // image comes from the chain's cache, so this is the sensor and the targets alone.
    g.bench_function("forward_3_frames_s1_cached", |b| {
        b.iter(|| {
            chain
                .forward_with(
                    black_box(&frames),
                    &psfs,
                    p_hat,
                    NoiseMode::Gaussian,
                    0,
                    false,
                )
                .expect("forward")
        })
    });
    let fwd = chain
        .forward(&frames, &psfs, p_hat, NoiseMode::Gaussian, 0)
        .expect("forward");
    let mut dx = Tensor::zeros(fwd.input.n, 1, fwd.input.h, fwd.input.w);
    dx.data
        .iter_mut()
        .enumerate()
        .for_each(|(i, v)| *v = (i % 7) as f32 - 3.0);
    g.bench_function("backward_3_frames", |b| {
        b.iter(|| {
            let mut acc = chain.accumulator();
            chain
                .backward(&frames, &psfs, &fwd, black_box(&dx), &mut acc)
                .expect("backward");
            acc
        })
    });
    // Frames beyond the budget: the spectra their forward computed, read from its tape.
    let fwd_bare = chain
        .forward(&bare, &psfs, p_hat, NoiseMode::Gaussian, 0)
        .expect("forward");
    g.bench_function("backward_3_frames_spectra_on_tape", |b| {
        b.iter(|| {
            let mut acc = chain.accumulator();
            chain
                .backward(&bare, &psfs, &fwd_bare, black_box(&dx), &mut acc)
                .expect("backward");
            acc
        })
    });
    g.bench_function("backward_3_frames_pitch_only", |b| {
        b.iter(|| {
            let mut acc = chain.pitch_accumulator();
            chain
                .backward(&frames, &psfs, &fwd, black_box(&dx), &mut acc)
                .expect("backward");
            acc
        })
    });
    g.bench_function("backward_3_frames_and_psf_vjp", |b| {
        b.iter(|| {
            let mut acc = chain.accumulator();
            chain
                .backward(&frames, &psfs, &fwd, black_box(&dx), &mut acc)
                .expect("backward");
            chain.finish(&map, &psfs, acc).expect("vjp")
        })
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);

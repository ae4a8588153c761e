//! Where one sandwich step's time goes (S22): the PSF stack, the chain forward (S1 + sensor),
//! the network forward + backward of N_max, N_min and n random subnets, the chain backward and
//! the one PSF VJP — the parts of `Trainer::train_step`, timed apart. Usage:
//! `cargo run --release -p nanoeye-search --example step_time -- DATASET [PITCH_UM] [BATCH]
//! [N_RANDOM] [REPS] [learned|fixed] [sandwich|min] [WARMUP]` (docs/bench/chain.md, "Sandwich
//! step and REA candidate: default and paper sizes"; `min`: the smallest subnet alone, issue
//! 13's batch through optics + sensor + N_min; WARMUP untimed passes first, 1 by default as in
//! earlier sessions' figures: at paper size the second pass still faults in ~30,000 pages that later steps reuse,
//! each costly on a VM whose memory is fresh, docs/bench/chain.md). With
//! `learned` (the default) the phase map moves by a small step each pass, as the learned
//! lens's does in training, so the chain's kept PSF stack is never reused; with `fixed` it is
//! (a fixed lens's training), and the chain's backward is the sensor's alone (no PSF adjoint,
//! no PSF VJP), as in a fixed lens's training.

use nanoeye_datagen::render::Dataset;
use nanoeye_nets::{Arch, BnMode, Supernet, SupernetConfig};
use nanoeye_search::{CameraChain, ChainConfig, LensSpec, task_loss};
use nanoeye_sensor::NoiseMode;
use rand::SeedableRng;
use std::time::Instant;

/// Argument `i` (`name` in messages), `default` when absent; a value that does not parse is
/// refused (exit 2) rather than replaced by the default, so a typo cannot time another run.
fn arg<T: std::str::FromStr>(args: &[String], i: usize, name: &str, default: T) -> T {
    match args.get(i) {
        None => default,
        Some(s) => s.parse().unwrap_or_else(|_| {
            eprintln!("step_time: {name} must be a non-negative number in range, got {s:?}");
            std::process::exit(2);
        }),
    }
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let Some(dir) = args.get(1) else {
        eprintln!(
            "usage: step_time DATASET [PITCH_UM] [BATCH] [N_RANDOM] [REPS] [learned|fixed] [sandwich|min] [WARMUP]"
        );
        std::process::exit(2);
    };
    let pitch_um: f64 = arg(&args, 2, "PITCH_UM", 14.0);
    let batch: usize = arg(&args, 3, "BATCH", 4);
    let n_random: usize = arg(&args, 4, "N_RANDOM", 2);
    let reps: usize = arg(&args, 5, "REPS", 3);
    let warmup: usize = arg(&args, 8, "WARMUP", 1);
    if reps == 0 {
        eprintln!("step_time: REPS must be at least 1 (the passes timed)");
        std::process::exit(2);
    }
    if !(pitch_um.is_finite() && pitch_um > 0.0) || batch == 0 {
        eprintln!("step_time: PITCH_UM must be a positive number and BATCH at least 1");
        std::process::exit(2);
    }
    // The binary's allocator and its settings, so these times are the CLI's.
    nanoeye_alloc::like_cli();
    let learned = args.get(6).is_none_or(|s| s != "fixed");
    let ds = Dataset::open(std::path::Path::new(dir)).expect("dataset");
    let chain = CameraChain::for_dataset(&ds, ChainConfig::default()).expect("chain");
    let mut map = LensSpec::Hyperbolic
        .phase_map(chain.aperture_grid(), 940e-9, 2e-3)
        .expect("lens");
    let ids: Vec<usize> = (0..batch).map(|i| i % ds.len()).collect();
    let mut net = Supernet::new(SupernetConfig::default(), 0).expect("supernet");
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
    let min_only = args.get(7).is_some_and(|s| s == "min");
    let archs: Vec<Arch> = if min_only {
        vec![Arch::min()]
    } else {
        [Arch::max(), Arch::min()]
            .into_iter()
            .chain((0..n_random).map(|_| Arch::sample(&mut rng)))
            .collect()
    };
    // [load, psf stack, chain forward, network, chain backward, psf vjp]
    let mut t = [0.0f64; 6];
    let mut shape = (0, 0);
    for rep in 0..warmup + reps {
        let mut lap = [0.0f64; 6];
        let mut clock = Instant::now();
        let mut tick = |k: usize, clock: &mut Instant| {
            lap[k] = clock.elapsed().as_secs_f64();
            *clock = Instant::now();
        };
        if learned {
            // An optimizer step moves every phase sample.
            map.phase_rad
                .col_iter_mut()
                .for_each(|c| c.iter_mut().for_each(|v| *v += 1e-3));
        }
        let frames = chain.load(&ds, &ids).expect("load");
        tick(0, &mut clock);
        let psfs = chain.psfs(&map, &chain.active(&frames)).expect("psfs");
        tick(1, &mut clock);
        let fwd = chain
            .forward(&frames, &psfs, pitch_um * 1e-6, NoiseMode::Gaussian, 7)
            .expect("forward");
        shape = (fwd.input.h, fwd.input.w);
        tick(2, &mut clock);
        net.zero_grad();
        let mut dx = nanoeye_nets::Tensor::zeros(fwd.input.n, 1, fwd.input.h, fwd.input.w);
        let mut dm = dx.clone();
        for a in &archs {
            let (_, g) = task_loss(
                &mut net,
                std::slice::from_ref(a),
                &fwd.input,
                &fwd.mask,
                &fwd.slip_mm,
                [0.1; 3],
                BnMode::Train,
            )
            .expect("task loss");
            dx.add_assign(&g.input);
            dm.add_assign(&g.mask);
        }
        tick(3, &mut clock);
        // As in training: a fixed lens needs ∂L/∂p̂ only, and no PSF VJP.
        let mut acc = if learned {
            chain.accumulator()
        } else {
            chain.pitch_accumulator()
        };
        chain
            .backward(&frames, &psfs, &fwd, &dx, &mut acc)
            .expect("backward");
        chain
            .target_backward(&frames, &fwd, &dm, &mut acc)
            .expect("target backward");
        tick(4, &mut clock);
        if learned {
            let g = chain.finish(&map, &psfs, acc).expect("finish");
            std::hint::black_box(g);
        }
        tick(5, &mut clock);
        // The first passes warm caches, plans and the process's pages.
        if rep >= warmup {
            t.iter_mut()
                .zip(lap)
                .for_each(|(a, b)| *a += b / reps as f64);
        }
    }
    let (h, w) = chain.native().shape();
    let total: f64 = t.iter().sum();
    println!(
        "native {w}x{h} at {:.1} um, p_hat {pitch_um} um -> network input {}x{}, batch {batch}, \
         {} subnets, {} depth slabs, {} lens, mean of {reps} passes after {warmup} untimed",
        chain.native().pitch_m() * 1e6,
        shape.1,
        shape.0,
        archs.len(),
        chain.depths_m().len(),
        if learned { "learned" } else { "fixed" }
    );
    let names = [
        "load layers",
        "PSF stack",
        "chain forward (S1 + sensor)",
        "network fwd + bwd",
        "chain backward",
        "PSF VJP",
    ];
    for (n, s) in names.iter().zip(t) {
        println!("{n:<28} {s:>8.3} s  {:>5.1} %", 100.0 * s / total);
    }
    println!("{:<28} {total:>8.3} s per step", "sandwich step");
}

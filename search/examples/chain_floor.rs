//! Time of the camera chain's optics part per frame against its FFT floor, and the PSF stack
//! and its VJP per step. Usage: `RAYON_NUM_THREADS=1 cargo run --release -p nanoeye-search
//! --example chain_floor -- DATASET [PITCH_UM] [FRAMES] [REPS]` (docs/bench/chain.md). Allocator as in
//! the CLI.

use nanoeye_datagen::render::Dataset;
use nanoeye_nets::Tensor;
use nanoeye_search::{CameraChain, ChainConfig, ChainForward, ChainFrame, LensSpec};
use nanoeye_sensor::NoiseMode;
use std::time::Instant;

fn main() {
    // The binary's allocator and its settings, so these times are the CLI's.
    nanoeye_alloc::like_cli();
    let args: Vec<String> = std::env::args().collect();
    let Some(dir) = args.get(1) else {
        eprintln!("usage: chain_floor DATASET [PITCH_UM] [FRAMES]");
        std::process::exit(2);
    };
    let pitch_um: f64 = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(9.5);
    let nf: usize = args.get(3).and_then(|s| s.parse().ok()).unwrap_or(1);
    let ds = Dataset::open(std::path::Path::new(dir)).expect("dataset");
    let chain = CameraChain::for_dataset(&ds, ChainConfig::default()).expect("chain");
    let map = LensSpec::Hyperbolic
        .phase_map(chain.aperture_grid(), 940e-9, 2e-3)
        .expect("lens");
    let ids: Vec<usize> = (0..nf.min(ds.len())).collect();
    let frames = chain.load(&ds, &ids).expect("load");
    let active = chain.active(&frames);
    let layers: usize = frames.iter().map(|f| f.data.layers.len()).sum();
    let reps: usize = args.get(4).and_then(|s| s.parse().ok()).unwrap_or(5).max(1);
    // Floor: one bare 2-D FFT of S1's padded grid (batched rows, then batched columns of the
    // transpose; no copies, no allocation), in S1's spectral precision (f32) and, for
    // comparison with the figures of the f64 path before 2026-12-01, in f64; timed here back
    // to back (its grid then stays in cache) and below between the chain's calls, which the
    // ratios use (docs/bench/chain.md).
    let (h, w) = chain.native().shape();
    let (ny, nx) = (
        nanoeye_optics::psf::fast_fft_size(h + chain.psf_px() - 1),
        nanoeye_optics::psf::fast_fft_size(w + chain.psf_px() - 1),
    );
    let mut fft32 = bare_fft2::<f32>(ny, nx);
    let mut fft_t = fft2_transposed(ny, nx);
    let t_fft = time(10 * reps, &mut fft32);
    let t_fft64 = time(10 * reps, &mut bare_fft2::<f64>(ny, nx));
    let t_fft_t = time(10 * reps, &mut fft_t);
    // On tiles (docs/optics.md), the floor is a bare 2-D FFT of a tile's N×N grid per covered
    // tile (α ≠ 0 somewhere in it); its 0.4 MB grid stays in cache, so it is timed back to
    // back.
    let tiles = chain.s1_tile().map(|t| {
        let n = nanoeye_optics::psf::fast_fft_size(t + chain.psf_px() - 1);
        let covered: usize = frames
            .iter()
            .flat_map(|f| &f.data.layers)
            .map(|l| {
                let a = l.alpha();
                let mut hit = vec![false; h.div_ceil(t) * w.div_ceil(t)];
                for r in 0..h {
                    for c in 0..w {
                        if a[(r, c)] != 0.0 {
                            hit[(r / t) * w.div_ceil(t) + c / t] = true;
                        }
                    }
                }
                hit.iter().filter(|&&x| x).count()
            })
            .sum();
        (t, n, covered, time(10 * reps, &mut bare_fft2::<f32>(n, n)))
    });
    let mut psfs = None;
    let t_psf = time(reps, &mut || {
        psfs = Some(chain.psfs(&map, &active).expect("psfs"))
    });
    let psfs = psfs.expect("set");
    let p_hat = pitch_um * 1e-6;
    // The same frames as if built in memory: the chain never keeps their layer spectra, so
    // S1 computes them in every forward and records them on its tape for the backward (as
    // for frames beyond the kept spectra's budget).
    let bare: Vec<ChainFrame> = frames.iter().map(ChainFrame::unkeyed).collect();
    let t = Instant::now();
    drop(
        chain
            .forward(&frames, &psfs, p_hat, NoiseMode::Gaussian, 0)
            .expect("forward"),
    );
    let t_first = t.elapsed().as_secs_f64();
    let g = |fwd: &ChainForward| {
        let mut g = Tensor::zeros(fwd.input.n, 1, fwd.input.h, fwd.input.w);
        g.data
            .iter_mut()
            .enumerate()
            .for_each(|(i, v)| *v = (i % 7) as f32 - 3.0);
        g
    };
    let n = frames.len() as f64;
    let per = layers as f64 / n;
    println!(
        "native {h}x{w}, PSF window {} px, {} frames, {per:.1} layers/frame, p_hat {pitch_um} um, \
         {reps} timed calls (minimum, median)",
        chain.psf_px(),
        frames.len(),
    );
    println!(
        "one bare 2-D FFT of S1's {ny}x{nx} grid, back to back (in cache; the ratios below \
         time it between the chain's calls): {:.2}, {:.2} ms in f32; {:.2}, {:.2} ms in f64",
        t_fft.0 * 1e3,
        t_fft.1 * 1e3,
        t_fft64.0 * 1e3,
        t_fft64.1 * 1e3
    );
    println!(
        "one 2-D FFT with its transposition (rows, a tiled transpose, then the columns; f32): \
         {:.2}, {:.2} ms",
        t_fft_t.0 * 1e3,
        t_fft_t.1 * 1e3
    );
    // A dataset whose frames' spectra would not all fit the budget keeps none
    // (search/src/spectra.rs): its "kept" rows below then compute them too, with two FFTs
    // per layer (or covered tile) forward, and their floor counts one.
    let kept = chain.cached_layer_spectra();
    println!(
        "first forward of the frames (computes their layer spectra, keeps them where the \
         dataset's fit the budget): {:.1} ms per frame; frames with kept spectra: {kept} of {}",
        t_first / n * 1e3,
        frames.len()
    );
    if kept < frames.len() {
        println!(
            "NOTE: not every frame's spectra are kept (the dataset's exceed the budget): the \
             \"kept\" rows below compute them in each forward (two FFTs per layer or tile)"
        );
    }
    if let Some((t, nt, covered, tf)) = tiles {
        println!(
            "S1 on tiles of {t} px ({nt}x{nt} grids): {:.1} covered tiles per frame; one bare \
             2-D FFT of a tile's grid {:.3}, {:.3} ms",
            covered as f64 / n,
            tf.0 * 1e3,
            tf.1 * 1e3
        );
    }
    // With kept spectra each covered tile's spectrum (N² complex f32, 0.4 MB at N = 224) is
    // read from memory once per forward: that read, timed alone with the caches evicted
    // first, is what the FFT floor leaves out (docs/bench/chain.md). Summed as 64-bit words
    // with wrapping adds, which vectorise: a complex f32 sum is one chain of dependent adds
    // and would time the adds (6.3 M of them, about twice as long as the read), not memory.
    let stream = tiles
        .filter(|_| kept == frames.len())
        .map(|(_, nt, covered, _)| {
            let len = (covered as f64 / n).round() as usize * nt * nt;
            let words = vec![1u64; len];
            let mut evict = vec![0u8; 96 << 20];
            let mut read = || {
                evict.iter_mut().for_each(|v| *v = v.wrapping_add(1));
                std::hint::black_box(&evict);
                clock(&mut || {
                    let s = words.iter().fold(0u64, |a, &w| a.wrapping_add(w));
                    std::hint::black_box(s);
                })
            };
            // One untimed read first, as `time` makes one untimed call.
            read();
            let (min, med) = min_median((0..reps).map(|_| read()).collect());
            (len as f64 * 8e-6, min, med)
        });
    if let Some((mb, a, b)) = stream {
        println!(
            "a frame's kept spectra ({mb:.0} MB) read once from memory, caches evicted first: \
             {:.1}, {:.1} ms",
            a * 1e3,
            b * 1e3
        );
    }
    // The kept-spectra backward, which the PSF VJP's time below is taken against.
    let mut t_bwd_kept = None;
    // Kept spectra: forward one inverse FFT per layer, backward the gradient's spectrum per
    // layer. Not kept: the forward computes the layer's spectrum on top, the backward reads
    // it from the tape.
    for (what, fr, ffts, reads) in [
        ("kept layer spectra", &frames, [1.0, 1.0], true),
        (
            "layer spectra computed in each forward (on its tape for the backward)",
            &bare,
            [2.0, 1.0],
            false,
        ),
    ] {
        let mut fwd = None;
        let t_fwd = paired(
            reps,
            &mut || {
                // The previous frame's result is dropped first, as a training step drops it,
                // so the timed calls reuse its memory instead of faulting in a second set.
                fwd = None;
                fwd = Some(
                    chain
                        .forward(fr, &psfs, p_hat, NoiseMode::Gaussian, 0)
                        .expect("forward"),
                )
            },
            [&mut fft32, &mut fft_t],
        );
        let fwd = fwd.expect("set");
        let t_opt = time(reps, &mut || {
            for f in fr.iter() {
                std::hint::black_box(chain.optical_image(f, &psfs).expect("s1"));
            }
        });
        let g = g(&fwd);
        let t_bwd = paired(
            reps,
            &mut || {
                let mut acc = chain.accumulator();
                chain
                    .backward(fr, &psfs, &fwd, &g, &mut acc)
                    .expect("backward");
            },
            [&mut fft32, &mut fft_t],
        );
        t_bwd_kept.get_or_insert(t_bwd[0]);
        println!("{what}:");
        println!(
            "  optical_image only per frame: {:.1}, {:.1} ms",
            t_opt.0 / n * 1e3,
            t_opt.1 / n * 1e3
        );
        // Frames whose spectra are kept (`stream` is timed only where all are): against one
        // inverse FFT per covered tile plus the spectra's read.
        if let (Some((_, _, covered, tf)), Some((_, sa, sb)), true) = (tiles, stream, reads) {
            let floor = |t: f64, s: f64| covered as f64 / n * t + s;
            println!(
                "    on tiles: against the FFT floor plus the kept spectra's read ({:.1}, {:.1} \
                 ms): ratio {:.2}, {:.2}",
                floor(tf.0, sa) * 1e3,
                floor(tf.1, sb) * 1e3,
                t_opt.0 / n / floor(tf.0, sa),
                t_opt.1 / n / floor(tf.1, sb)
            );
        }
        for (dir, [t, bare, tr], ffts) in
            [("forward", t_fwd, ffts[0]), ("backward", t_bwd, ffts[1])]
        {
            let floor = |t: f64| ffts * per * t;
            println!(
                "  chain {dir} per frame: {:.1}, {:.1} ms; FFT floor ({ffts} per layer, timed \
                 between its calls) {:.1}, {:.1} ms; ratio {:.2}, {:.2}; against as many 2-D \
                 FFTs with their transposition {:.2}, {:.2}",
                t.0 / n * 1e3,
                t.1 / n * 1e3,
                floor(bare.0) * 1e3,
                floor(bare.1) * 1e3,
                t.0 / n / floor(bare.0),
                t.1 / n / floor(bare.1),
                t.0 / n / floor(tr.0),
                t.1 / n / floor(tr.1)
            );
            if let Some((_, _, covered, tf)) = tiles {
                let floor = |t: f64| ffts * covered as f64 / n * t;
                println!(
                    "    on tiles: FFT floor ({ffts} per covered tile) {:.1}, {:.1} ms; ratio \
                     {:.2}, {:.2}",
                    floor(tf.0) * 1e3,
                    floor(tf.1) * 1e3,
                    t.0 / n / floor(tf.0),
                    t.1 / n / floor(tf.1)
                );
            }
        }
    }
    let fwd = chain
        .forward(&frames, &psfs, p_hat, NoiseMode::Gaussian, 0)
        .expect("forward");
    let g = g(&fwd);
    let t_vjp = time(reps, &mut || {
        let mut acc = chain.accumulator();
        chain
            .backward(&frames, &psfs, &fwd, &g, &mut acc)
            .expect("backward");
        chain.finish(&map, &psfs, acc).expect("vjp");
    });
    println!(
        "per step: PSF stack ({} depths) {:.1} ms, PSF VJP + kernel inverse FFTs {:.1} ms (medians)",
        active.iter().filter(|&&a| a).count(),
        t_psf.1 * 1e3,
        (t_vjp.1 - t_bwd_kept.expect("timed").1) * 1e3
    );
}

/// (minimum, median) seconds of `reps` calls of `f`, each timed on its own after one untimed
/// call: this VM's speed moves by ±20 % between seconds.
fn time(reps: usize, f: &mut dyn FnMut()) -> (f64, f64) {
    f();
    min_median((0..reps).map(|_| clock(f)).collect())
}

/// (minimum, median) of a non-empty list of times.
fn min_median(mut t: Vec<f64>) -> (f64, f64) {
    t.sort_by(f64::total_cmp);
    (t[0], t[t.len() / 2])
}

/// (minimum, median) seconds of `reps` calls of `f` and, timed before each of them, of one
/// call of each floor: a floor timed back to back keeps its grid in the last-level cache,
/// which the chain's grids never are, and this VM's speed moves by up to 2× within a minute.
fn paired(reps: usize, f: &mut dyn FnMut(), mut floors: [&mut dyn FnMut(); 2]) -> [(f64, f64); 3] {
    f();
    floors.iter_mut().for_each(|g| g());
    let mut t = [(); 3].map(|_| Vec::with_capacity(reps));
    for _ in 0..reps {
        for (i, g) in floors.iter_mut().enumerate() {
            t[1 + i].push(clock(*g));
        }
        t[0].push(clock(f));
    }
    t.map(min_median)
}

/// Seconds of one call of `g`.
fn clock(g: &mut dyn FnMut()) -> f64 {
    let t = Instant::now();
    g();
    t.elapsed().as_secs_f64()
}

/// One 2-D FFT of an ny × nx grid in precision `T` per call: the rows, then the second axis
/// as contiguous runs of ny (no transposition, no copies, no allocation).
fn bare_fft2<T: nanoeye_fft::Float>(ny: usize, nx: usize) -> impl FnMut() {
    let (fx, fy, mut buf, mut scratch) = plans::<T>(ny, nx);
    move || {
        fx.process_with_scratch(&mut buf, &mut scratch);
        fy.process_with_scratch(&mut buf, &mut scratch);
    }
}

/// A planned FFT.
type Plan<T> = std::sync::Arc<dyn nanoeye_fft::Fft<T>>;
/// A complex grid or buffer.
type Grid<T> = Vec<nanoeye_fft::num_complex::Complex<T>>;

/// The two forward plans of a ny × nx grid (rows of nx, columns of ny), a grid of ones (1 + i)
/// and a scratch buffer either plan can use.
fn plans<T: nanoeye_fft::Float>(ny: usize, nx: usize) -> (Plan<T>, Plan<T>, Grid<T>, Grid<T>) {
    let mut planner = nanoeye_fft::Planner::<T>::new();
    let (fx, fy) = (planner.plan_fft_forward(nx), planner.plan_fft_forward(ny));
    let z = nanoeye_fft::num_complex::Complex::new(T::zero(), T::zero());
    let buf = vec![nanoeye_fft::num_complex::Complex::new(T::one(), T::one()); ny * nx];
    let scratch = vec![
        z;
        fx.get_inplace_scratch_len()
            .max(fy.get_inplace_scratch_len())
    ];
    (fx, fy, buf, scratch)
}

/// One f32 2-D FFT of a row-major ny × nx grid per call, done as a grid in memory needs it:
/// the rows, a transposition into a second buffer (32 × 32 tiles), then the columns, now
/// contiguous; the result left column-major, as S1 keeps its spectra. [`bare_fft2`] leaves
/// the transposition out, so it bounds the transforms alone.
fn fft2_transposed(ny: usize, nx: usize) -> impl FnMut() {
    use nanoeye_fft::num_complex::Complex;
    const TILE: usize = 32;
    let (fx, fy, mut buf, mut scratch) = plans::<f32>(ny, nx);
    let mut cols = vec![Complex::new(0.0f32, 0.0); ny * nx];
    move || {
        fx.process_with_scratch(&mut buf, &mut scratch);
        for r0 in (0..ny).step_by(TILE) {
            for c0 in (0..nx).step_by(TILE) {
                for c in c0..(c0 + TILE).min(nx) {
                    for r in r0..(r0 + TILE).min(ny) {
                        cols[c * ny + r] = buf[r * nx + c];
                    }
                }
            }
        }
        fy.process_with_scratch(&mut cols, &mut scratch);
    }
}

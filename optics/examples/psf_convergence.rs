//! Time-vs-error table of the PSF model (docs/bench/optics.md):
//! `cargo run --release -p nanoeye-optics --example psf_convergence`.
//! Reference: Δ = 0.75 µm, L = 2 mm. Error: max |PSF − ref| / max ref over depths 17, 20, 23, 26 mm.

use nanoeye_fft::Planner;
use nanoeye_optics::{ApertureGrid, AsmPsf, Hyperbolic, PhaseProfile, PsfConfig};
use num_complex::Complex64;
use std::time::Instant;

fn stack(
    dx: f64,
    period: Option<f64>,
    depths: &[f64],
) -> (Vec<faer::Mat<f64>>, f64, (usize, usize)) {
    let grid = ApertureGrid::new(1e-3, dx).unwrap();
    let map = Hyperbolic::default().phase_map(&grid).unwrap();
    let model = AsmPsf::new(
        PsfConfig {
            period_m: period,
            ..PsfConfig::default()
        },
        grid,
    )
    .unwrap();
    let t = Instant::now();
    let planes = model.planes_f64(&map, depths, None).unwrap();
    let dt = t.elapsed().as_secs_f64() / depths.len() as f64;
    (
        planes.into_iter().map(Option::unwrap).collect(),
        dt,
        model.sizes(),
    )
}

fn fft2_time(n: usize) -> f64 {
    let fft = Planner::<f64>::new().plan_fft_forward(n);
    let mut buf = vec![Complex64::new(1.0, 0.5); n * n];
    let mut col = vec![Complex64::new(0.0, 0.0); n];
    let t = Instant::now();
    let reps = 3;
    for _ in 0..reps {
        fft.process(&mut buf);
        for c in 0..n {
            for (r, v) in col.iter_mut().enumerate() {
                *v = buf[r * n + c];
            }
            fft.process(&mut col);
            for (r, v) in col.iter().enumerate() {
                buf[r * n + c] = *v;
            }
        }
    }
    t.elapsed().as_secs_f64() / reps as f64
}

/// Time (s, one thread) of the bare FFTs one plane runs: `rows` row and N_b column transforms
/// of length N_L on the folded grid, and 2(N_b + W q) chirp-z transforms of length `lc`.
fn plane_fft_floor(nl: usize, rows: usize, nb: usize, lc: usize, wq: usize) -> f64 {
    let mut planner = Planner::<f64>::new();
    let (fft, cfft) = (planner.plan_fft_forward(nl), planner.plan_fft_forward(lc));
    let mut buf = vec![Complex64::new(1.0, 0.5); nl * rows];
    let mut cols = vec![Complex64::new(1.0, 0.5); nl * nb];
    let mut chirp = vec![Complex64::new(1.0, 0.5); lc * 2 * (nb + wq)];
    let reps = 5;
    let t = Instant::now();
    for _ in 0..reps {
        fft.process(&mut buf);
        fft.process(&mut cols);
        cfft.process(&mut chirp);
    }
    t.elapsed().as_secs_f64() / reps as f64
}

fn main() {
    let depths: Vec<f64> = (0..4).map(|i| 17e-3 + i as f64 * 3e-3).collect();
    let (reference, _, _) = stack(0.75e-6, Some(2e-3), &depths);
    println!("| Δ (µm) | L (mm) | N_L | N_b | ms/plane | rel. max error | energy err |");
    println!("|---|---|---|---|---|---|---|");
    for dx in [3e-6, 2e-6, 1.5e-6, 1e-6] {
        for period in [Some(0.25e-3), Some(0.5e-3), None, Some(2e-3)] {
            let (planes, dt, (nl, nb)) = stack(dx, period, &depths);
            let (mut err, mut eerr) = (0.0f64, 0.0f64);
            for (p, r) in planes.iter().zip(&reference) {
                let (mut m, mut peak, mut e, mut er) = (0.0f64, 0.0f64, 0.0, 0.0);
                for j in 0..r.ncols() {
                    for i in 0..r.nrows() {
                        m = m.max((p[(i, j)] - r[(i, j)]).abs());
                        peak = peak.max(r[(i, j)]);
                        e += p[(i, j)];
                        er += r[(i, j)];
                    }
                }
                err = err.max(m / peak);
                eerr = eerr.max((e - er).abs());
            }
            let lbl = period.map_or("1.192 (default)".to_string(), |p| format!("{}", p * 1e3));
            println!(
                "| {} | {lbl} | {nl} | {nb} | {:.1} | {err:.2e} | {eerr:.1e} |",
                dx * 1e6,
                dt * 1e3
            );
        }
    }
    // Floors: the bare FFTs of one plane, and the 2-D FFTs of a conventional 2×-padded ASM grid.
    let grid = ApertureGrid::new(1e-3, 1.5e-6).unwrap();
    let model = AsmPsf::new(PsfConfig::default(), grid).unwrap();
    let (nl, nb) = model.sizes();
    let wq = model.field_points();
    let lc = model.chirp_len();
    let map = Hyperbolic::default().phase_map(&grid).unwrap();
    // Per-plane cost inside a stack on one thread (aperture sampling and buffers amortized).
    let d16: Vec<f64> = (0..16).map(|i| 17e-3 + i as f64 * 0.6e-3).collect();
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    let t = Instant::now();
    pool.install(|| model.planes_f64(&map, &d16, None).unwrap());
    let t_plane = t.elapsed().as_secs_f64() / d16.len() as f64;
    let rows = grid.n.min(nl);
    let floor = plane_fft_floor(nl, rows, nb, lc, wq);
    println!(
        "\none plane (16-depth stack on 1 thread, per plane): {:.1} ms; its bare FFTs ({rows} + {nb} of length {nl}, {} chirp-z of length {lc}): {:.1} ms; ratio {:.2}",
        t_plane * 1e3,
        2 * (nb + wq),
        floor * 1e3,
        t_plane / floor
    );
    let pad = nanoeye_optics::psf::fast_fft_size(2 * grid.n);
    println!(
        "conventional ASM, 2 FFTs of {pad}²: {:.1} ms",
        2.0 * fft2_time(pad) * 1e3
    );
    let d256: Vec<f64> = (0..256).map(|i| 17e-3 + i as f64 * 9e-3 / 255.0).collect();
    use nanoeye_optics::PsfModel;
    let t = Instant::now();
    let s = model.forward(&map, &d256, None).unwrap();
    println!(
        "256-depth stack (Δ = 1.5 µm, default L, 64×64 at 3 µm, {} threads): {:.2} s ({} planes)",
        rayon::current_num_threads(),
        t.elapsed().as_secs_f64(),
        s.planes.len()
    );
}

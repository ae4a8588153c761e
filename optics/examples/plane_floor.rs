//! One PSF plane against its FFT floor in one process, alternating nothing: the criterion
//! bench's stack of 8 depths on one thread (default rig, hyperbolic lens, Δ = 1.5 µm) and the
//! bare FFTs the plane cannot avoid, timed one after the other in each of REPS rounds (so a drift of
//! the machine's speed meets both alike); prints the minimum and median per
//! plane and their ratio, and a checksum of the planes (equal checksums = same PSF bits, to
//! the printed digits). On a VM whose speed drifts, the minima are the stable statistic.
//!
//! `cargo run --release -p nanoeye-optics --example plane_floor -- [REPS]` (default 20).

use nanoeye_optics::{ApertureGrid, AsmPsf, Hyperbolic, PhaseProfile, PsfConfig, PsfModel};
use num_complex::Complex64;
use std::time::Instant;

fn main() {
    let reps: usize = std::env::args()
        .nth(1)
        .map_or(20, |s| s.parse().expect("REPS: a positive integer"))
        .max(1);
    let grid = ApertureGrid::new(1e-3, 1.5e-6).expect("grid");
    let map = Hyperbolic::default().phase_map(&grid).expect("map");
    let rows = grid.n;
    let model = AsmPsf::new(PsfConfig::default(), grid).expect("model");
    let depths: Vec<f64> = (0..8).map(|i| 17e-3 + i as f64 * 1.2e-3).collect();
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .expect("pool");
    // The floor: the same FFTs as benches/psf.rs's `floor_ffts_of_one_plane`.
    let (nl, nb) = model.sizes();
    let (wq, lc) = (model.field_points(), model.chirp_len());
    let mut planner = nanoeye_fft::Planner::<f64>::new();
    let fft = planner.plan_fft_forward(nl);
    let cfft = planner.plan_fft_forward(lc);
    let one = Complex64::new(1.0, 0.0);
    let mut buf = vec![one; nl * rows.min(nl)];
    let mut cols = vec![one; nl * nb];
    let mut chirp = vec![one; lc * 2 * (nb + wq)];
    let (mut plane, mut floor, mut checksum) = (Vec::new(), Vec::new(), 0.0);
    for _ in 0..reps {
        let t0 = Instant::now();
        let stack = pool.install(|| model.forward(&map, &depths, None).expect("psf"));
        plane.push(t0.elapsed().as_secs_f64() * 1e3 / depths.len() as f64);
        let t0 = Instant::now();
        fft.process(&mut buf);
        fft.process(&mut cols);
        cfft.process(&mut chirp);
        floor.push(t0.elapsed().as_secs_f64() * 1e3);
        checksum = stack
            .planes
            .iter()
            .flat_map(|p| p.col_iter())
            .flat_map(|c| c.iter().map(|&v| v as f64))
            .sum::<f64>();
    }
    plane.sort_by(f64::total_cmp);
    floor.sort_by(f64::total_cmp);
    let (p0, pm, f0, fm) = (plane[0], plane[reps / 2], floor[0], floor[reps / 2]);
    println!(
        "ms/plane min {p0:.2} med {pm:.2}  floor min {f0:.2} med {fm:.2}  \
         ratio min {:.3} med {:.3}  checksum {checksum:.15e}",
        p0 / f0,
        pm / fm
    );
}

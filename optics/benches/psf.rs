//! Criterion benches: one PSF plane on the default rig (1 mm aperture, 64×64 window at 3 µm)
//! against the bare FFTs the plane needs on the same grids (the floor): min(n, N_L) row and N_b column
//! FFTs of the folded grid, and 2(N_b + W q + 2T) chirp-z FFTs of the window DFT.

use criterion::{Criterion, criterion_group, criterion_main};
use nanoeye_fft::Planner;
use nanoeye_optics::{ApertureGrid, AsmPsf, Hyperbolic, PhaseProfile, PsfConfig, PsfModel};
use num_complex::Complex64;

fn bench(c: &mut Criterion) {
    let grid = ApertureGrid::new(1e-3, 1.5e-6).expect("grid");
    let map = Hyperbolic::default().phase_map(&grid).expect("map");
    let model = AsmPsf::new(PsfConfig::default(), grid).expect("model");
    let mut g = c.benchmark_group("psf");
    g.sample_size(10);
    // Eight depths per call so the per-call aperture sampling is amortized as in a stack.
    let depths: Vec<f64> = (0..8).map(|i| 17e-3 + i as f64 * 1.2e-3).collect();
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .expect("pool");
    g.bench_function("stack8_1thread_1mm_d1.5um_64px_3um", |b| {
        b.iter(|| pool.install(|| model.forward(&map, &depths, None).expect("psf")))
    });
    let (nl, nb) = model.sizes();
    let wq = model.field_points();
    let lc = model.chirp_len();
    let mut planner = Planner::<f64>::new();
    let fft = planner.plan_fft_forward(nl);
    let cfft = planner.plan_fft_forward(lc);
    let rows = grid.n.min(nl);
    let mut buf = vec![Complex64::new(1.0, 0.0); nl * rows];
    let mut cols = vec![Complex64::new(1.0, 0.0); nl * nb];
    let mut chirp = vec![Complex64::new(1.0, 0.0); lc * 2 * (nb + wq)];
    g.bench_function("floor_ffts_of_one_plane", |b| {
        b.iter(|| {
            fft.process(&mut buf);
            fft.process(&mut cols);
            cfft.process(&mut chirp);
        })
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);

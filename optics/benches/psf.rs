//! Criterion benches: one PSF plane on the default rig (1 mm aperture, 64×64 window at 3 µm)
//! against the bare FFTs of the same folded grid (the floor).

use criterion::{Criterion, criterion_group, criterion_main};
use nanoeye_optics::{ApertureGrid, AsmPsf, Hyperbolic, PhaseProfile, PsfConfig, PsfModel};
use num_complex::Complex64;
use rustfft::FftPlanner;

fn bench(c: &mut Criterion) {
    let grid = ApertureGrid::new(1e-3, 1.5e-6).expect("grid");
    let map = Hyperbolic::default().phase_map(&grid).expect("map");
    let model = AsmPsf::new(PsfConfig::default(), grid).expect("model");
    let mut g = c.benchmark_group("psf");
    g.sample_size(10);
    g.bench_function("plane_1mm_d1.5um_64px_3um", |b| {
        b.iter(|| model.forward(&map, &[21e-3], None).expect("psf"))
    });
    let (nl, _) = model.sizes();
    let fft = FftPlanner::<f64>::new().plan_fft_forward(nl);
    let mut buf = vec![Complex64::new(1.0, 0.0); nl * nl];
    g.bench_function("floor_fft2d_folded_grid", |b| {
        b.iter(|| {
            fft.process(&mut buf);
            let mut col = vec![Complex64::new(0.0, 0.0); nl];
            for cidx in 0..nl {
                for (r, v) in col.iter_mut().enumerate() {
                    *v = buf[r * nl + cidx];
                }
                fft.process(&mut col);
            }
        })
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);

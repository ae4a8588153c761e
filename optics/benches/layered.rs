//! Criterion benches: the spectral S1 path on the 3 µm default sensor (800×1280, 65-px PSF
//! window), one thread, per layer: forward (`forward_spectral`) and the PSF adjoint
//! (`vjp_kernels`), against the floor of two bare 2-D FFTs of the padded grid per layer
//! (rows, then the second axis as contiguous rows: no transpose, no copies) in f32, the
//! path's precision, and in f64, its precision until 2026-12-01. Allocator as in the CLI.

use criterion::{Criterion, criterion_group, criterion_main};
use faer::Mat;
use nanoeye_fft::{Float, Planner};
use nanoeye_optics::psf::fast_fft_size;
use nanoeye_optics::{LayeredImager, SpectralLayer};
use num_complex::Complex;

fn bench(c: &mut Criterion) {
    // The binary's allocator and its settings, so these times are the CLI's.
    nanoeye_alloc::like_cli();
    let (h, w, wp) = (800, 1280, 65);
    let im = LayeredImager::new(h, w, wp).expect("imager");
    let psf = Mat::from_fn(wp, wp, |r, c| {
        let (y, x) = (r as f32 - 32.0, c as f32 - 32.0);
        (-(x * x + y * y) / 200.0).exp()
    });
    let ks = im.kernel_spectra(&[Some(&psf)]).expect("spectra");
    let rad = Mat::from_fn(h, w, |r, c| ((r * 7 + c * 13) % 17) as f32 / 17.0);
    let alpha = Mat::from_fn(
        h,
        w,
        |r, c| if (r / 40 + c / 40) % 3 == 0 { 0.0 } else { 1.0 },
    );
    let layers = [SpectralLayer::new(rad.as_ref(), alpha.as_ref(), 0)];
    let grad = Mat::from_fn(h, w, |r, c| ((r * 5 + c * 3) % 7) as f64 - 3.0);
    let mut g = c.benchmark_group("layered");
    g.sample_size(10);
    g.bench_function("forward_1layer_800x1280_65px", |b| {
        b.iter(|| im.forward_spectral(&layers, &ks, None).expect("forward"))
    });
    let (_, tape) = im.forward_spectral(&layers, &ks, None).expect("forward");
    g.bench_function("vjp_kernels_1layer_800x1280_65px", |b| {
        b.iter(|| {
            let mut acc = im.kernel_grad_accumulator(1);
            im.vjp_kernels(&layers, &tape, &grad, &mut acc, None)
                .expect("vjp");
            acc
        })
    });
    let (ny, nx) = (fast_fft_size(h + wp - 1), fast_fft_size(w + wp - 1));
    floor::<f32>(&mut g, "floor_two_f32_ffts_800x1280_65px", ny, nx);
    floor::<f64>(&mut g, "floor_two_f64_ffts_800x1280_65px", ny, nx);
    g.finish();
}

/// Two bare 2-D FFTs of an ny × nx grid in precision `T`.
fn floor<T: Float>(
    g: &mut criterion::BenchmarkGroup<criterion::measurement::WallTime>,
    name: &str,
    ny: usize,
    nx: usize,
) {
    let mut planner = Planner::<T>::new();
    let (fx, fy) = (planner.plan_fft_forward(nx), planner.plan_fft_forward(ny));
    // Unit values; the transforms' growth reaches ∞ after a few calls, which costs no time.
    let mut buf = vec![Complex::new(T::one(), T::one()); ny * nx];
    g.bench_function(name, |b| {
        b.iter(|| {
            for _ in 0..2 {
                fx.process(&mut buf);
                fy.process(&mut buf);
            }
        })
    });
}

criterion_group!(benches, bench);
criterion_main!(benches);

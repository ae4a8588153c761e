//! Solver throughput: pixel input (sphere and refraction-aware), 64×64 mask input, and the pixel VJP.

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use faer::Mat;
use nanoeye_gaze::{GazeSolver, PupilCentre, RefractiveSolver, Rig, SphereSolver};
use std::hint::black_box;

fn bench(c: &mut Criterion) {
    let rig = Rig::default();
    let solver = SphereSolver::new(&rig).unwrap();
    // 1000 pixels over the part of the image where the eye is.
    let pixels: Vec<[f64; 2]> = (0..1000)
        .map(|i| [120.0 + (i % 40) as f64 * 2.0, 30.0 + (i / 40) as f64 * 2.0])
        .collect();
    let slip = [0.5e-3, -1e-3, 0.3e-3];
    let mut g = c.benchmark_group("gaze");
    g.throughput(Throughput::Elements(pixels.len() as u64));
    g.bench_function("solve_pixel_x1000", |b| {
        b.iter(|| {
            let mut acc = 0.0;
            for &px in &pixels {
                if let Ok(s) = solver.solve_pixel(black_box(px), slip) {
                    acc += s.gaze[2];
                }
            }
            acc
        })
    });
    let refractive = RefractiveSolver::new(&rig).unwrap();
    g.bench_function("refractive_solve_pixel_x1000", |b| {
        b.iter(|| {
            let mut acc = 0.0;
            for &px in &pixels {
                if let Ok(s) = refractive.solve_pixel(black_box(px), slip) {
                    acc += s.gaze[2];
                }
            }
            acc
        })
    });
    g.bench_function("vjp_pixel_x1000", |b| {
        b.iter(|| {
            let mut acc = 0.0;
            for &px in &pixels {
                if let Ok(v) = solver.vjp_pixel(black_box(px), slip, [0.0, 0.0, 1.0]) {
                    acc += v.pupil_px[0];
                }
            }
            acc
        })
    });
    g.throughput(Throughput::Elements(1));
    // 64×64 soft disc, a 5× downscale of a 320×320 camera.
    let mut sq = rig.clone();
    sq.camera = sq.camera.with_pitch(12e-6).unwrap();
    sq.camera.width_px = 320;
    sq.camera.height_px = 320;
    let solver_sq = SphereSolver::new(&sq).unwrap();
    let mask = Mat::<f32>::from_fn(64, 64, |i, j| {
        let r = ((i as f32 - 14.0).powi(2) + (j as f32 - 34.0).powi(2)).sqrt();
        1.0 / (1.0 + (r - 6.0).exp())
    });
    g.bench_function("solve_mask_64x64", |b| {
        b.iter(|| solver_sq.solve_mask(black_box(mask.as_ref()), slip))
    });
    // A whole pupil under the cut-aware centre: S9 and a look at the mask's edges.
    g.bench_function("solve_mask_64x64_ellipse_if_cut", |b| {
        b.iter(|| {
            solver_sq.solve_mask_with(black_box(mask.as_ref()), slip, PupilCentre::EllipseIfCut)
        })
    });
    // The same disc with its centre 2 px below the top edge: a third of it out of view.
    let (ci, cj) = (2.0f32, 34.0f32);
    let cut = Mat::<f32>::from_fn(64, 64, |i, j| {
        let r = ((i as f32 + 0.5 - ci).powi(2) + (j as f32 + 0.5 - cj).powi(2)).sqrt();
        1.0 / (1.0 + (r - 6.0).exp())
    });
    for how in [PupilCentre::Centroid, PupilCentre::EllipseIfCut] {
        let c = solver_sq.mask_centre(cut.as_ref(), how).unwrap();
        // Camera pixels are 5 per mask pixel.
        let off =
            ((c.px[0] / 5.0 - cj as f64).powi(2) + (c.px[1] / 5.0 - ci as f64).powi(2)).sqrt();
        eprintln!(
            "cut disc, {}: centre {off:.3} mask px from the truth",
            how.name()
        );
        g.bench_function(format!("solve_mask_cut_64x64_{}", how.name()), |b| {
            b.iter(|| solver_sq.solve_mask_with(black_box(cut.as_ref()), slip, how))
        });
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);

//! Criterion benches: loss value + gradient per PSF plane (64×64 and 21×21 planes, 7 depths).

use criterion::{Criterion, criterion_group, criterion_main};
use faer::Mat;
use nanoeye_fisher::{
    Compactness, DepthFisher, DesignLoss, Distinctness, FisherNoise, InitLoss, Precision, PsfStack,
};
use std::hint::black_box;

fn stack(w: usize, pitch: f64) -> PsfStack {
    let planes: Vec<Mat<f64>> = (0..7)
        .map(|k| {
            let s = 2.0 + 0.7 * k as f64;
            let c = w as f64 / 2.0;
            Mat::from_fn(w, w, |i, j| {
                let (x, y) = (j as f64 - c, i as f64 - c);
                1e-3 * (-(x * x + y * y) / (2.0 * s * s)).exp()
            })
        })
        .collect();
    let depths: Vec<f64> = (0..7).map(|k| 0.017 + 1.5e-3 * k as f64).collect();
    PsfStack::from_f64(&planes, &depths, pitch).unwrap()
}

fn bench(c: &mut Criterion) {
    let noise = FisherNoise {
        photons: 1e5,
        noise_var: 16.0,
        ..FisherNoise::default()
    };
    for (w, pitch) in [(64usize, 3e-6), (21, 9e-6)] {
        let s = stack(w, pitch);
        let losses: Vec<(&str, Box<dyn DesignLoss>)> = vec![
            ("precision", Box::new(Precision { noise })),
            ("depth_fisher", Box::new(DepthFisher { noise })),
            ("distinctness", Box::new(Distinctness::default())),
            ("compactness", Box::new(Compactness::default())),
        ];
        for (name, l) in &losses {
            c.bench_function(&format!("{name}_grad_7x{w}x{w}"), |b| {
                b.iter(|| l.value_and_grad(black_box(&s)).unwrap())
            });
        }
        let init = InitLoss {
            precision: Precision { noise },
            ..InitLoss::default()
        };
        c.bench_function(&format!("init_loss_grad_7x{w}x{w}"), |b| {
            b.iter(|| init.evaluate(black_box(&s), &[0.0; 3]).unwrap())
        });
    }
}

criterion_group!(benches, bench);
criterion_main!(benches);

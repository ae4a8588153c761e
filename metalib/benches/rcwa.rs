//! Criterion benchmarks: one (pitch, diameter) eigen-solve and one height evaluation at
//! h = 700 nm, s = 530 nm, d = 200 nm for both rules and several truncations.
use criterion::{Criterion, criterion_group, criterion_main};
use nanoeye_metalib::material::Materials;
use nanoeye_metalib::rcwa::{CellSpec, LayerModes, Rule};
use std::hint::black_box;

fn bench(c: &mut Criterion) {
    faer::set_global_parallelism(faer::Par::Seq);
    for rule in [Rule::Laurent, Rule::Nv] {
        for n in [4usize, 7, 10] {
            let spec = CellSpec {
                wavelength_m: 940e-9,
                pitch_m: 530e-9,
                diameter_m: 200e-9,
                materials: Materials::default(),
                harmonics: n,
                rule,
            };
            c.bench_function(&format!("modes_{}_N{n}", rule.name()), |b| {
                b.iter(|| LayerModes::new(black_box(&spec)).unwrap())
            });
            let modes = LayerModes::new(&spec).unwrap();
            c.bench_function(&format!("height_{}_N{n}", rule.name()), |b| {
                b.iter(|| modes.transmission_at(black_box(700e-9)).unwrap())
            });
        }
    }
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(10);
    targets = bench
}
criterion_main!(benches);

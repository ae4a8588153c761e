//! Sampler throughput: TRUNCNORM in the body and deep tail, and each state set per item.

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use nanoeye_datagen::states::sets::item_rng;
use nanoeye_datagen::states::{self, Protocol, TruncNormal};
use nanoeye_gaze::Rig;
use std::hint::black_box;

fn bench(c: &mut Criterion) {
    let mut g = c.benchmark_group("truncnorm");
    g.throughput(Throughput::Elements(1000));
    for (name, a, b) in [
        ("body_-2.3_3", -35.0 / 15.0, 3.0),
        ("tail_8_9", 8.0, 9.0),
        ("tail_30_inf", 30.0, f64::INFINITY),
    ] {
        let d = TruncNormal::new(0.0, 1.0, a, b).unwrap();
        let mut rng = item_rng(0, 0, 0);
        g.bench_function(name, |bch| {
            bch.iter(|| (0..1000).map(|_| d.sample(&mut rng)).sum::<f64>())
        });
    }
    g.finish();

    let rig = Rig::default();
    let mut g = c.benchmark_group("sets");
    g.sample_size(20);
    g.throughput(Throughput::Elements(1000));
    g.bench_function("ambiguity_1000_pairs", |b| {
        b.iter(|| states::ambiguity(&rig, 1000, black_box(1)).unwrap().len())
    });
    g.bench_function("variational_1000_triplets", |b| {
        b.iter(|| states::variational(&rig, 1000, black_box(1)).unwrap().len())
    });
    g.throughput(Throughput::Elements(343 * 3));
    g.bench_function("protocol_3_subjects", |b| {
        b.iter(|| {
            states::protocol(&rig, &Protocol::default(), 3, black_box(1))
                .unwrap()
                .len()
        })
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);

//! Criterion benches: supernet forward and forward+backward (min / max subnet, 64² and 128²,
//! batch 16), per-layer-kind throughput, and the 1×1 convolution against faer's GEMM on the
//! same shape. MACs per pass come from the cost model and are printed once per case.

use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use faer::linalg::matmul::matmul;
use faer::{Accum, Mat, Par};
use nanoeye_nets::arch::{Arch, SupernetConfig};
use nanoeye_nets::conv::{depthwise_forward, pointwise_forward};
use nanoeye_nets::cost::subnet_cost;
use nanoeye_nets::se::{SeWeights, se_forward};
use nanoeye_nets::{BnMode, Supernet, Tensor};
use std::hint::black_box;
use std::time::Duration;

const BATCH: usize = 16;

fn image(n: usize, c: usize, h: usize, w: usize) -> Tensor {
    let data = (0..n * c * h * w)
        .map(|i| ((i * 7919) % 1000) as f32 / 1000.0 - 0.5)
        .collect();
    Tensor::from_vec(n, c, h, w, data).expect("shape")
}

fn supernet(c: &mut Criterion) {
    let cfg = SupernetConfig::default();
    let mut g = c.benchmark_group("supernet");
    g.sample_size(10)
        .measurement_time(Duration::from_secs(4))
        .warm_up_time(Duration::from_secs(1));
    for (name, arch) in [("min", Arch::min()), ("max", Arch::max())] {
        for size in [64usize, 128] {
            let macs = subnet_cost(&cfg, &arch, size, size).expect("cost").macs;
            eprintln!(
                "{name} {size}x{size}: {:.2} M MACs per image",
                macs as f64 / 1e6
            );
            let mut net = Supernet::new(cfg.clone(), 1).expect("net");
            let x = image(BATCH, 1, size, size);
            g.throughput(Throughput::Elements(BATCH as u64));
            g.bench_function(BenchmarkId::new(format!("forward/{name}"), size), |b| {
                b.iter(|| black_box(net.forward(&arch, &x, BnMode::Train).expect("fwd")))
            });
            g.bench_function(
                BenchmarkId::new(format!("forward_backward/{name}"), size),
                |b| {
                    b.iter(|| {
                        let out = net.forward(&arch, &x, BnMode::Train).expect("fwd");
                        let dl = Tensor {
                            data: vec![1e-3; out.mask_logits.len()],
                            ..out.mask_logits.clone()
                        };
                        let ds = Tensor {
                            data: vec![1e-3; out.slip.len()],
                            ..out.slip.clone()
                        };
                        black_box(net.backward(&dl, &ds).expect("bwd"))
                    })
                },
            );
        }
    }
    g.finish();
}

fn layers(c: &mut Criterion) {
    let mut g = c.benchmark_group("layers");
    g.sample_size(10)
        .measurement_time(Duration::from_secs(2))
        .warm_up_time(Duration::from_millis(500));
    // Typical stage-2/3 shapes at 128² input, batch 16: 16 × C × 16 × 16.
    for (cin, cout) in [(40usize, 240usize), (240, 40), (80, 480), (480, 80)] {
        let x = image(BATCH, cin, 16, 16);
        let w = vec![0.01f32; cin * cout];
        let macs = (BATCH * 256 * cin * cout) as u64;
        g.throughput(Throughput::Elements(macs));
        g.bench_function(
            BenchmarkId::new("pointwise", format!("{cin}x{cout}")),
            |b| b.iter(|| black_box(pointwise_forward(&x, &w, cout, None).expect("pw"))),
        );
        // Same MACs as one faer GEMM (cout × cin)·(cin × 16·256), all cores: the peak reference.
        let a = Mat::<f32>::from_fn(cout, cin, |i, j| ((i + j) % 7) as f32 * 0.01);
        let bm = Mat::<f32>::from_fn(cin, BATCH * 256, |i, j| ((i * j) % 5) as f32 * 0.01);
        let mut cm = Mat::<f32>::zeros(cout, BATCH * 256);
        g.bench_function(
            BenchmarkId::new("faer_gemm", format!("{cin}x{cout}")),
            |b| {
                b.iter(|| {
                    matmul(
                        cm.as_mut(),
                        Accum::Replace,
                        a.as_ref(),
                        bm.as_ref(),
                        1.0f32,
                        Par::rayon(0),
                    )
                })
            },
        );
    }
    for k in [3usize, 5, 7] {
        let x = image(BATCH, 240, 16, 16);
        let w = vec![0.01f32; 240 * k * k];
        g.throughput(Throughput::Elements((BATCH * 240 * 256 * k * k) as u64));
        g.bench_function(BenchmarkId::new("depthwise", k), |b| {
            b.iter(|| black_box(depthwise_forward(&x, &w, k, 1).expect("dw")))
        });
    }
    let x = image(BATCH, 240, 16, 16);
    let (w1, b1, w2, b2) = (
        vec![0.01f32; 64 * 240],
        vec![0.0f32; 64],
        vec![0.01f32; 240 * 64],
        vec![0.0f32; 240],
    );
    g.throughput(Throughput::Elements((BATCH * 2 * 240 * 64) as u64));
    g.bench_function("se/240", |b| {
        b.iter(|| {
            black_box(
                se_forward(
                    &x,
                    &SeWeights {
                        w1: &w1,
                        b1: &b1,
                        w2: &w2,
                        b2: &b2,
                    },
                )
                .expect("se"),
            )
        })
    });
    g.finish();
}

criterion_group!(benches, supernet, layers);
criterion_main!(benches);

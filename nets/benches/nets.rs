//! Criterion benches: supernet forward and forward+backward (min / max subnet, 64², 128² and
//! 320×200, batch 16), per-layer-kind throughput (depthwise forward and backward at strides 1
//! and 2, beside the memory roofline of each shape: a pass that only streams the bytes a depthwise
//! pass must move), batch-1 inference (compiled, one thread) against the supernet's eval pass, the 1×1 convolution against faer's GEMM on the same shape, and the min subnet's ends (stem, resizes). MACs per pass come from the cost model and are printed once per case.

use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use faer::linalg::matmul::matmul;
use faer::{Accum, Mat, Par};
use nanoeye_nets::arch::{Arch, SupernetConfig};
use nanoeye_nets::conv::{
    conv2d_forward, conv2d_vjp, depthwise_forward, depthwise_vjp, out_size, pointwise_forward,
};
use nanoeye_nets::cost::subnet_cost;
use nanoeye_nets::resize::{bilinear_forward, bilinear_vjp};
use nanoeye_nets::se::{SeWeights, se_forward};
use nanoeye_nets::{BnMode, Inference, Supernet, Tensor};
use rayon::prelude::*;
use std::hint::black_box;
use std::time::Duration;

const BATCH: usize = 16;

/// Planes per rayon task in the roofline passes: enough that a task's bookkeeping is small
/// beside its bytes (16 planes of 8×8 are 4 KB), few enough that both cores share the work.
const STREAM_PLANES: usize = 16;

/// Sum of `x` over 32 independent lanes, so that the reduction streams at load speed: a
/// one-accumulator fold (the roofline before) waits on each operation's latency, one value
/// per cycle, and timed that chain instead of the memory.
fn lane_sum_portable(x: &[f32]) -> f32 {
    let mut acc = [0.0f32; 32];
    let mut it = x.chunks_exact(32);
    for c in &mut it {
        for (a, &v) in acc.iter_mut().zip(c) {
            *a += v;
        }
    }
    acc.iter().sum::<f32>() + it.remainder().iter().sum::<f32>()
}

/// [`lane_sum_portable`] compiled for AVX2: 256-bit loads, as the depthwise kernels use.
///
/// # Safety
/// The CPU has AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn lane_sum_avx2(x: &[f32]) -> f32 {
    lane_sum_portable(x)
}

/// Sum of `x`, with the widest loads this CPU has.
fn lane_sum(x: &[f32]) -> f32 {
    #[cfg(target_arch = "x86_64")]
    if std::is_x86_feature_detected!("avx2") {
        // SAFETY: AVX2 was detected just above.
        return unsafe { lane_sum_avx2(x) };
    }
    lane_sum_portable(x)
}

fn image(n: usize, c: usize, h: usize, w: usize) -> Tensor {
    let data = (0..n * c * h * w)
        .map(|i| ((i * 7919) % 1000) as f32 / 1000.0 - 0.5)
        .collect();
    Tensor::from_vec(n, c, h, w, data).expect("shape")
}

fn supernet(c: &mut Criterion) {
    // The binary's allocator and its settings, so these times are the CLI's.
    nanoeye_alloc::like_cli();
    let cfg = SupernetConfig::default();
    let mut g = c.benchmark_group("supernet");
    g.sample_size(10)
        .measurement_time(Duration::from_secs(4))
        .warm_up_time(Duration::from_secs(1));
    for (name, arch) in [("min", Arch::min()), ("max", Arch::max())] {
        // 320×200: the default run's native render, the size the camera chain feeds.
        for (hh, ww) in [(64usize, 64usize), (128, 128), (200, 320)] {
            let size = format!("{ww}x{hh}");
            let macs = subnet_cost(&cfg, &arch, hh, ww).expect("cost").macs;
            eprintln!("{name} {size}: {:.2} M MACs per image", macs as f64 / 1e6);
            let mut net = Supernet::new(cfg.clone(), 1).expect("net");
            let x = image(BATCH, 1, hh, ww);
            g.throughput(Throughput::Elements(BATCH as u64));
            g.bench_function(BenchmarkId::new(format!("forward/{name}"), &size), |b| {
                b.iter(|| black_box(net.forward(&arch, &x, BnMode::Train).expect("fwd")))
            });
            g.bench_function(
                BenchmarkId::new(format!("forward_backward/{name}"), &size),
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

/// Batch-1 inference (the tracker's path: compiled subnet, one thread) at the default run's
/// sensor grid (278×174 at p̂ ≈ 13.8 µm) and at 320×200, against the supernet's own forward
/// pass in eval mode on one image.
fn inference(c: &mut Criterion) {
    nanoeye_alloc::like_cli();
    let cfg = SupernetConfig::default();
    let mut g = c.benchmark_group("inference");
    g.sample_size(20)
        .measurement_time(Duration::from_secs(4))
        .warm_up_time(Duration::from_secs(1));
    let mut net = Supernet::new(cfg.clone(), 1).expect("net");
    for (name, arch) in [("min", Arch::min()), ("max", Arch::max())] {
        for (hh, ww) in [(174usize, 278usize), (200, 320)] {
            let size = format!("{ww}x{hh}");
            let macs = subnet_cost(&cfg, &arch, hh, ww).expect("cost").macs;
            eprintln!("inference {name} {size}: {:.2} M MACs", macs as f64 / 1e6);
            let x = image(1, 1, hh, ww);
            let mut inf = Inference::new(&net, &arch, hh, ww).expect("compile");
            g.throughput(Throughput::Elements(1));
            g.bench_function(BenchmarkId::new(format!("compiled/{name}"), &size), |b| {
                b.iter(|| black_box(inf.run(&x.data).expect("run").slip))
            });
            g.bench_function(
                BenchmarkId::new(format!("supernet_eval/{name}"), &size),
                |b| b.iter(|| black_box(net.forward(&arch, &x, BnMode::Eval).expect("fwd"))),
            );
        }
    }
    g.finish();
}

fn layers(c: &mut Criterion) {
    nanoeye_alloc::like_cli();
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
    // Stage-2/3 maps (16², 240 channels), a stage-1 map at the default render (100×160,
    // 24 channels), and the stride-4 and stride-8 maps of the main job's 278×174 network input
    // (widths 70 and 35: rows that end in a partial register block) and the stride-2 layer that
    // reads the 44×70 map; stride 2 halves the output, so its MACs are a quarter. The 8×8
    // maps are the min subnet's last stages at 128² (output planes of 64 and 16 values: the
    // channel-block path). The stride-2 layers reading the 22×35 and 32×32 maps have output
    // planes of 198 and 256 values: the channel blocks' largest, where their transposes of
    // four input pixels per output cost the most. The stride-2 layer reading the 87×139 map
    // (the first of stage 1 at expansion 3, in subnets at full resolution): 46 MB of x and y
    // at batch 16, far past the last-level cache. The stride-2 layer reading the 11×18 map
    // (the main job's 6×9 output planes, 336 channels): channel blocks on rows of 18.
    for (c, h, w, s) in [
        (240usize, 16usize, 16usize, 1usize),
        (240, 16, 16, 2),
        (480, 8, 8, 1),
        (480, 8, 8, 2),
        (24, 100, 160, 1),
        (96, 44, 70, 1),
        (96, 44, 70, 2),
        (192, 22, 35, 1),
        (192, 22, 35, 2),
        (96, 32, 32, 2),
        (48, 87, 139, 2),
        (336, 11, 18, 2),
    ] {
        // The memory roofline of the shape: the least any depthwise pass must move, streamed
        // on both cores (forward: read x, write y; backward: read x and dL/dy, write dL/dx),
        // into outputs allocated once: a fresh zeroed output per call is the layer's own
        // overhead, not the memory's floor (docs/bench/nets.md, fifty-sixth session).
        {
            let x = image(BATCH, c, h, w);
            let (ho, wo) = (out_size(h, 3, s), out_size(w, 3, s));
            let dy = image(BATCH, c, ho, wo);
            let mut y = vec![0.0f32; dy.data.len()];
            let mut dx = vec![0.0f32; x.data.len()];
            let shape = format!("{c}x{h}x{w}/s{s}");
            g.throughput(Throughput::Bytes(
                (4 * (x.data.len() + dy.data.len())) as u64,
            ));
            g.bench_function(BenchmarkId::new("roofline_fwd", &shape), |b| {
                b.iter(|| {
                    y.par_chunks_mut(ho * wo)
                        .zip(x.data.par_chunks(h * w))
                        .with_min_len(STREAM_PLANES)
                        .for_each(|(y, x)| y.fill(lane_sum(x)));
                    black_box(&mut y);
                })
            });
            g.throughput(Throughput::Bytes(
                (4 * (2 * x.data.len() + dy.data.len())) as u64,
            ));
            g.bench_function(BenchmarkId::new("roofline_bwd", &shape), |b| {
                b.iter(|| {
                    dx.par_chunks_mut(h * w)
                        .zip(x.data.par_chunks(h * w))
                        .zip(dy.data.par_chunks(ho * wo))
                        .with_min_len(STREAM_PLANES)
                        .for_each(|((dx, x), dy)| {
                            let m = lane_sum(dy);
                            for (d, &v) in dx.iter_mut().zip(x) {
                                *d = v * m;
                            }
                        });
                    black_box(&mut dx);
                })
            });
        }
        for k in [3usize, 5, 7] {
            let x = image(BATCH, c, h, w);
            let wt = vec![0.01f32; c * k * k];
            let (ho, wo) = (out_size(h, k, s), out_size(w, k, s));
            let macs = (BATCH * c * ho * wo * k * k) as u64;
            let shape = format!("{c}x{h}x{w}/s{s}/k{k}");
            g.throughput(Throughput::Elements(macs));
            g.bench_function(BenchmarkId::new("depthwise", &shape), |b| {
                b.iter(|| black_box(depthwise_forward(&x, &wt, k, s).expect("dw")))
            });
            let dy = image(BATCH, c, ho, wo);
            let mut dw = vec![0.0f32; c * k * k];
            // Backward does two products per forward MAC (dL/dx and dL/dw): MACs counted 2×.
            g.throughput(Throughput::Elements(2 * macs));
            g.bench_function(BenchmarkId::new("depthwise_vjp", &shape), |b| {
                b.iter(|| black_box(depthwise_vjp(&x, &wt, k, s, &dy, &mut dw).expect("dw")))
            });
        }
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

/// The min subnet's ends at a 320×200 input, batch 16: the stem (3×3, stride 2, 1 → 16
/// channels at resolution scale 0.3, 60×96) and the bilinear resizes of the input and of the
/// mask logits, each way.
fn ends(c: &mut Criterion) {
    nanoeye_alloc::like_cli();
    let mut g = c.benchmark_group("ends");
    g.sample_size(20);
    let xr = image(BATCH, 1, 60, 96);
    let w: Vec<f32> = (0..16 * 9).map(|i| (i % 7) as f32 * 0.1 - 0.3).collect();
    let dy = image(BATCH, 16, 30, 48);
    g.bench_function("stem/forward", |b| {
        b.iter(|| black_box(conv2d_forward(&xr, &w, 16, 3, 2).expect("stem")))
    });
    g.bench_function("stem/vjp", |b| {
        let mut dw = vec![0.0f32; w.len()];
        b.iter(|| black_box(conv2d_vjp(&xr, &w, 16, 3, 2, &dy, &mut dw).expect("stem")))
    });
    let full = image(BATCH, 1, 200, 320);
    let lo = image(BATCH, 1, 30, 48);
    g.bench_function("resize/input_200x320_to_60x96", |b| {
        b.iter(|| black_box(bilinear_forward(&full, 60, 96)))
    });
    g.bench_function("resize/logits_30x48_to_200x320", |b| {
        b.iter(|| black_box(bilinear_forward(&lo, 200, 320)))
    });
    g.bench_function("resize_vjp/logits_200x320_to_30x48", |b| {
        b.iter(|| black_box(bilinear_vjp([BATCH, 1, 30, 48], &full)))
    });
    g.bench_function("resize_vjp/input_60x96_to_200x320", |b| {
        b.iter(|| black_box(bilinear_vjp([BATCH, 1, 200, 320], &xr)))
    });
    g.finish();
}

criterion_group!(benches, supernet, inference, layers, ends);
criterion_main!(benches);

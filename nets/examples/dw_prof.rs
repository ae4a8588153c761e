//! Depthwise convolution forward and backward (dL/dx and dL/dw) at batch 16 (or BATCH) on the
//! shapes of the nets bench and the small maps of the min subnet, under the CLI's allocator
//! settings: the fastest of N runs and its GMAC/s (the backward counts two MACs per forward
//! MAC). A smaller batch shows whether a layer is bound by memory (its data then fit in L2).
//!
//! Usage: `cargo run --release -p nanoeye-nets --example dw_prof -- [N] [CxHxW/sS/kK|all]
//! [BATCH]`; a CxHxW/sS/kK off the list runs that shape alone.

use nanoeye_nets::Tensor;
use nanoeye_nets::conv::{depthwise_forward, depthwise_vjp, out_size};
use std::hint::black_box;
use std::time::Instant;

/// Channels, input height and width, stride.
const SHAPES: [(usize, usize, usize, usize); 16] = [
    (240, 16, 16, 1),
    (240, 16, 16, 2),
    (480, 8, 8, 1),
    (480, 8, 8, 2),
    (672, 4, 4, 1),
    (24, 100, 160, 1),
    (96, 44, 70, 1),
    (96, 44, 70, 2),
    (192, 22, 35, 1),
    (192, 22, 35, 2),
    (96, 32, 32, 1),
    (96, 32, 32, 2),
    // The main job's 174×278 input at strides 16 and 32: rows of 18 and 9 outputs, the last
    // two and one past a register of eight.
    (336, 11, 18, 1),
    (336, 11, 18, 2),
    (480, 6, 9, 1),
    // The 87×139 map at stride 2 (stage 1's first layer at expansion 3, full resolution):
    // its planes come from memory at batch 16.
    (48, 87, 139, 2),
];

fn main() {
    let mut args = std::env::args().skip(1);
    let reps: usize = args.next().map_or(30, |s| s.parse().expect("N"));
    let only = args.next().filter(|s| s != "all");
    let batch: usize = args.next().map_or(16, |s| s.parse().expect("BATCH"));
    assert!(batch > 0, "BATCH: at least one image");
    // The binary's allocator and its settings, so these times are the CLI's.
    nanoeye_alloc::like_cli();
    // Inside the pool, as the supernet runs its passes.
    rayon::scope(|_| run(reps, only.as_deref(), batch));
}

/// The shape `CxHxW/sS/kK` as (channels, height, width, stride, kernel).
fn parse(name: &str) -> Option<(usize, usize, usize, usize, usize)> {
    let (dims, rest) = name.split_once("/s")?;
    let (s, k) = rest.split_once("/k")?;
    let d: Vec<usize> = dims
        .split('x')
        .map(|v| v.parse().ok())
        .collect::<Option<_>>()?;
    let [c, h, w] = d[..] else { return None };
    Some((c, h, w, s.parse().ok()?, k.parse().ok()?))
}

fn run(reps: usize, only: Option<&str>, n: usize) {
    let mut cases: Vec<(usize, usize, usize, usize, usize)> = SHAPES
        .iter()
        .flat_map(|&(c, h, w, s)| [3, 5, 7].map(|k| (c, h, w, s, k)))
        .collect();
    if let Some(o) = only {
        let shape = parse(o).unwrap_or_else(|| panic!("shape {o}: expected CxHxW/sS/kK or all"));
        cases.retain(|&v| v == shape);
        if cases.is_empty() {
            cases.push(shape);
        }
    }
    for (c, h, w, s, k) in cases {
        let name = format!("{c}x{h}x{w}/s{s}/k{k}");
        let len = n * c * h * w;
        let values = (0..len)
            .map(|i| ((i * 7919) % 1000) as f32 * 1e-3)
            .collect();
        let x = Tensor::from_vec(n, c, h, w, values).expect("shape");
        let wt = vec![0.01f32; c * k * k];
        let (ho, wo) = (out_size(h, k, s), out_size(w, k, s));
        let dy = Tensor::from_vec(n, c, ho, wo, vec![0.5; n * c * ho * wo]).expect("shape");
        let mut dw = vec![0.0f32; c * k * k];
        let macs = (n * c * ho * wo * k * k) as f64;
        let (mut tf, mut tb) = (f64::MAX, f64::MAX);
        for _ in 0..reps {
            let t = Instant::now();
            black_box(depthwise_forward(&x, &wt, k, s).expect("forward"));
            tf = tf.min(t.elapsed().as_secs_f64());
            let t = Instant::now();
            black_box(depthwise_vjp(&x, &wt, k, s, &dy, &mut dw).expect("backward"));
            tb = tb.min(t.elapsed().as_secs_f64());
        }
        println!(
            "{name}: forward {:.1} µs ({:.1} GMAC/s), backward {:.1} µs ({:.1} GMAC/s), batch {n}",
            tf * 1e6,
            macs / tf * 1e-9,
            tb * 1e6,
            2.0 * macs / tb * 1e-9
        );
    }
}

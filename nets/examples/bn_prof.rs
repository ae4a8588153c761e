//! Batch norm with its activation, training mode, forward and backward on the min subnet's
//! shapes at a 128×128 input, batch 16 (or with `large`, one shape per plane size of at least
//! 128 values of the max subnet at the main job's 137×220 input, batch 4, all with h-swish),
//! under the CLI's allocator settings: ns per value of each pass.
//!
//! Usage: `cargo run --release -p nanoeye-nets --example bn_prof -- [N] [large]`

use nanoeye_nets::act::Act;
use nanoeye_nets::norm::BatchNorm;
use nanoeye_nets::{BnMode, Tensor};

fn main() {
    let usage = "usage: bn_prof [N] [large]";
    let (mut n, mut large) = (200, false);
    for (i, a) in std::env::args().skip(1).enumerate() {
        match (i, a.as_str()) {
            (_, "large") => large = true,
            (0, s) => match s.parse() {
                Ok(k) if k > 0 => n = k,
                _ => panic!("N: {s:?}, a count of at least 1; {usage}"),
            },
            (_, s) => panic!("unknown argument {s:?}; {usage}"),
        }
    }
    // The binary's allocator and its settings, so these times are the CLI's.
    nanoeye_alloc::like_cli();
    // Inside the pool, as the supernet runs its passes (a pass from outside waits on a lock).
    rayon::scope(|_| run(n, large));
}

fn run(n: usize, large: bool) {
    let large_shapes = [
        (4, 16, 69, 110, Act::HSwish),
        (4, 96, 69, 110, Act::HSwish),
        (4, 144, 35, 55, Act::HSwish),
        (4, 240, 18, 28, Act::HSwish),
    ];
    let small_shapes = [
        (16, 16, 19, 19, Act::HSwish),
        (16, 48, 19, 19, Act::Relu),
        (16, 72, 10, 10, Act::Relu),
        (16, 120, 5, 5, Act::Relu),
        (16, 240, 3, 3, Act::HSwish),
        (16, 336, 3, 3, Act::HSwish),
        (16, 80, 3, 3, Act::Identity),
        (16, 480, 2, 2, Act::HSwish),
        (16, 960, 2, 2, Act::HSwish),
    ];
    let shapes: &[_] = if large { &large_shapes } else { &small_shapes };
    let (mut tf, mut tb) = (0.0, 0.0);
    for &(b, c, h, w, act) in shapes {
        let len = b * c * h * w;
        let x = Tensor::from_vec(
            b,
            c,
            h,
            w,
            (0..len)
                .map(|i| ((i * 7919) % 1000) as f32 / 100.0 - 5.0)
                .collect(),
        )
        .expect("shape");
        let dy = x.like((0..len).map(|i| ((i * 31) % 17) as f32 - 8.0).collect());
        let mut bn = BatchNorm::new(c);
        let (mut f, mut g) = (0.0, 0.0);
        for _ in 0..n {
            let t = std::time::Instant::now();
            let y = bn.forward_act(x.clone(), BnMode::Train, act).expect("fwd");
            f += t.elapsed().as_secs_f64();
            std::hint::black_box(y);
            let d = dy.clone();
            let t = std::time::Instant::now();
            let dx = bn.backward_owned(d).expect("bwd");
            g += t.elapsed().as_secs_f64();
            std::hint::black_box(dx);
        }
        let per = |s: f64| s / n as f64 * 1e9 / len as f64;
        println!(
            "{b}x{c}x{h}x{w} {act:?}: forward {:.2} ns/value, backward {:.2} ns/value ({:.1} / {:.1} µs)",
            per(f),
            per(g),
            f / n as f64 * 1e6,
            g / n as f64 * 1e6
        );
        tf += f / n as f64;
        tb += g / n as f64;
    }
    println!(
        "all: forward {:.1} µs, backward {:.1} µs",
        tf * 1e6,
        tb * 1e6
    );
}

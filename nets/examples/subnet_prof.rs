//! Profiling harness for `perf record`: min or max subnet forward + backward at batch B
//! (default 16), train-mode BN, under the CLI's allocator settings, N times; prints the mean
//! time.
//!
//! Usage: `cargo run --release -p nanoeye-nets --example subnet_prof -- min|max H W [N] [B]
//! [fwd]` (`fwd`: the training-mode forward pass alone).

use nanoeye_nets::arch::{Arch, SupernetConfig};
use nanoeye_nets::{BnMode, Supernet, Tensor};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let which = args.get(1).map_or("min", |s| s.as_str());
    let h: usize = args.get(2).map_or(64, |s| s.parse().expect("H"));
    let w: usize = args.get(3).map_or(64, |s| s.parse().expect("W"));
    let n: usize = args.get(4).map_or(50, |s| s.parse().expect("N"));
    // The binary's allocator and its settings, so these times are the CLI's.
    nanoeye_alloc::like_cli();
    let arch = if which == "max" {
        Arch::max()
    } else {
        Arch::min()
    };
    let mut net = Supernet::new(SupernetConfig::default(), 1).expect("net");
    let b: usize = args.get(5).map_or(16, |s| s.parse().expect("B"));
    let data = (0..b * h * w)
        .map(|i| ((i * 7919) % 1000) as f32 / 1000.0 - 0.5)
        .collect();
    let x = Tensor::from_vec(b, 1, h, w, data).expect("shape");
    let fwd_only = args.get(6).is_some_and(|s| s == "fwd");
    let mut step = || {
        let out = net.forward(&arch, &x, BnMode::Train).expect("fwd");
        if fwd_only {
            std::hint::black_box(out);
            return;
        }
        let dl = Tensor {
            data: vec![1e-3; out.mask_logits.len()],
            ..out.mask_logits.clone()
        };
        let ds = Tensor {
            data: vec![1e-3; out.slip.len()],
            ..out.slip.clone()
        };
        std::hint::black_box(net.backward(&dl, &ds).expect("bwd"));
    };
    step();
    let t = std::time::Instant::now();
    for _ in 0..n {
        step();
    }
    eprintln!(
        "{which} {h}x{w} batch {b} {}: {:.2} ms",
        if fwd_only { "fwd" } else { "fwd+bwd" },
        t.elapsed().as_secs_f64() * 1e3 / n as f64
    );
}

//! Runs the compiled batch-1 inference (`Inference`, the tracker's path) of the min or max
//! subnet many times on one thread, for `perf record`; prints the median time per image.
//!
//! `cargo run --release -p nanoeye-nets --example infer_prof -- min|max H W RUNS`

use nanoeye_nets::{Arch, Inference, Supernet, SupernetConfig};
use std::time::Instant;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let arg = |i: usize, d: usize| args.get(i).and_then(|s| s.parse().ok()).unwrap_or(d);
    let arch = match args.get(1).map(String::as_str) {
        Some("max") => Arch::max(),
        _ => Arch::min(),
    };
    let (h, w, runs) = (arg(2, 174), arg(3, 278), arg(4, 2000).max(1));
    let net = Supernet::new(SupernetConfig::default(), 1).expect("net");
    let mut inf = Inference::new(&net, &arch, h, w).unwrap_or_else(|e| {
        eprintln!("infer_prof: H and W: {e}");
        std::process::exit(2)
    });
    let x: Vec<f32> = (0..h * w)
        .map(|i| ((i * 7919) % 1000) as f32 / 1000.0)
        .collect();
    let mut times = Vec::with_capacity(runs);
    let mut sink = 0.0f32;
    for _ in 0..runs {
        let t = Instant::now();
        sink += inf.run(&x).expect("run").slip[0];
        times.push(t.elapsed().as_secs_f64());
    }
    times.sort_by(f64::total_cmp);
    println!(
        "{h}x{w}: median {:.3} ms, p10 {:.3} ms over {runs} runs (checksum {sink:e})",
        times[runs / 2] * 1e3,
        times[runs / 10] * 1e3
    );
}

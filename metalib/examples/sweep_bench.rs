//! Times the sweep on a sub-grid: `cargo run -p nanoeye-metalib --example sweep_bench -- OUT_DIR
//! PITCH_START_NM PITCH_STOP_NM` (all heights 100–1500 nm step 10, fractions 0.10–0.90 step
//! 0.005, default rule and harmonics), printing cells, seconds and cells per second.
use nanoeye_metalib::sweep::{Range, SweepConfig, run_sweep_with_progress};

fn main() {
    let a: Vec<String> = std::env::args().skip(1).collect();
    let out = a
        .first()
        .cloned()
        .unwrap_or_else(|| "/tmp/metalib_sweep_bench".into());
    let p0: f64 = a.get(1).and_then(|v| v.parse().ok()).unwrap_or(530.0);
    let p1: f64 = a.get(2).and_then(|v| v.parse().ok()).unwrap_or(p0);
    let harmonics: usize = a
        .get(3)
        .and_then(|v| v.parse().ok())
        .unwrap_or(nanoeye_metalib::rcwa::DEFAULT_HARMONICS);
    let cfg = SweepConfig {
        pitches_m: Range {
            start: p0 * 1e-9,
            stop: p1 * 1e-9,
            step: 10e-9,
        },
        harmonics,
        ..Default::default()
    };
    let t = std::time::Instant::now();
    match run_sweep_with_progress(&cfg, std::path::Path::new(&out)) {
        Ok(m) => {
            let cells: usize = m.shape.iter().product();
            let s = t.elapsed().as_secs_f64();
            println!(
                "cells {cells} shape {:?} harmonics {} rule {:?} seconds {s:.1} cells/s {:.0} failed {}",
                m.shape,
                harmonics,
                cfg.rule,
                cells as f64 / s,
                m.failed_cells
            );
        }
        Err(e) => {
            eprintln!("error: {e}");
            std::process::exit(1);
        }
    }
}

//! Trains the smallest (and optionally the largest) subnet on the toy disk-mask task:
//! `cargo run --release -p nanoeye-nets --example fit_toy -- STEPS [min|both] [SIZE]`.
use nanoeye_nets::Arch;
use nanoeye_nets::toy::{ToyConfig, fit_toy};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let steps = args.get(1).map(|s| s.parse()).transpose()?.unwrap_or(300);
    let both = args.get(2).is_some_and(|s| s == "both");
    let size = args.get(3).map(|s| s.parse()).transpose()?.unwrap_or(64);
    let cfg = ToyConfig {
        steps,
        size,
        ..ToyConfig::default()
    };
    let r = fit_toy(&Arch::min(), &cfg)?;
    println!("min: {}", serde_json::to_string(&r)?);
    if both {
        let r = fit_toy(&Arch::max(), &cfg)?;
        println!("max: {}", serde_json::to_string(&r)?);
    }
    Ok(())
}

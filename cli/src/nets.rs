//! `nanoeye nets …`: MAC/parameter counts of subnets (S23) and a toy training run.

use crate::util::print_json;
use anyhow::{Context, Result, bail};
use clap::{Args, Subcommand};
use nanoeye_nets::arch::{Arch, SupernetConfig};
use nanoeye_nets::cost::{
    Cost, MAX_IN_CHANNELS, MAX_RESOLUTION, mobilenet_v3_large, mobilenet_v3_small, subnet_cost,
};
use nanoeye_nets::toy::{
    MAX_TOY_BATCH_PIXELS, MAX_TOY_LR, MAX_TOY_SIZE, ToyConfig, fit_toy_with_progress,
};
use nanoeye_search::train::MAX_STEPS;
use serde::Serialize;
use std::time::Instant;

/// Networks: cost model and toy training.
#[derive(Subcommand)]
pub enum NetsCmd {
    /// MACs and parameters of a network at a resolution (MobileNetV3 or a supernet subnet).
    Macs(MacsArgs),
    /// Train the smallest and largest subnet on synthetic disk masks; report held-out metrics.
    FitToy(FitToyArgs),
}

/// Arguments of `nets macs`.
#[derive(Args)]
pub struct MacsArgs {
    /// large | small (torchvision MobileNetV3 with its 1000-class head) | max | min |
    /// file:ARCH.json (supernet subnet with both heads).
    #[arg(long)]
    arch: String,
    /// Input image side in pixels (a subnet sees it scaled by its resolution scale).
    #[arg(long, default_value_t = 224)]
    resolution: usize,
    /// Image channels of the supernet stem (1 = NIR eye images), for max, min and file: only
    /// [default: 1].
    #[arg(long)]
    in_channels: Option<usize>,
    /// Print JSON.
    #[arg(long)]
    json: bool,
}

/// Arguments of `nets fit-toy`.
#[derive(Args)]
pub struct FitToyArgs {
    /// Training steps per subnet.
    #[arg(long, default_value_t = 300)]
    steps: usize,
    /// Images per step.
    #[arg(long, default_value_t = 16)]
    batch: usize,
    /// Image side in pixels.
    #[arg(long, default_value_t = 64)]
    size_px: usize,
    /// Peak Adam learning rate.
    #[arg(long, default_value_t = 3e-3)]
    lr: f64,
    /// Seed of weights and data.
    #[arg(long, default_value_t = 7)]
    seed: u64,
    /// Only train the smallest subnet.
    #[arg(long)]
    min_only: bool,
    /// Print JSON.
    #[arg(long)]
    json: bool,
}

/// Runs one `nets` subcommand.
pub fn run(cmd: NetsCmd) -> Result<()> {
    match cmd {
        NetsCmd::Macs(a) => macs(a),
        NetsCmd::FitToy(a) => fit(a),
    }
}

fn macs(a: MacsArgs) -> Result<()> {
    if a.resolution == 0 || a.resolution > MAX_RESOLUTION {
        bail!(
            "--resolution: must lie in 1..={MAX_RESOLUTION}, got {}",
            a.resolution
        );
    }
    // A flag the chosen network does not take would be ignored: refuse it.
    if a.in_channels.is_some() && matches!(a.arch.as_str(), "large" | "small") {
        bail!(
            "--in-channels: shapes the supernet's stem (max, min, file:) only; MobileNetV3 {} is \
             counted as torchvision builds it, for 3-channel images",
            a.arch
        );
    }
    let in_channels = a.in_channels.unwrap_or(1);
    if in_channels == 0 || in_channels > MAX_IN_CHANNELS {
        bail!("--in-channels: must lie in 1..={MAX_IN_CHANNELS}, got {in_channels}");
    }
    let cfg = SupernetConfig {
        in_channels,
        ..SupernetConfig::default()
    };
    let cost: Cost = match a.arch.as_str() {
        "large" => mobilenet_v3_large(a.resolution),
        "small" => mobilenet_v3_small(a.resolution),
        "max" => {
            subnet_cost(&cfg, &Arch::max(), a.resolution, a.resolution).context("--arch max")?
        }
        "min" => {
            subnet_cost(&cfg, &Arch::min(), a.resolution, a.resolution).context("--arch min")?
        }
        other => {
            let Some(path) = other.strip_prefix("file:") else {
                bail!("--arch: '{other}' is not large, small, max, min or file:PATH");
            };
            let text = crate::util::read_small_text(
                std::path::Path::new(path),
                crate::util::MAX_ARCH_BYTES,
            )
            .context("--arch")?;
            crate::util::arch_layout(&text).with_context(|| format!("--arch: '{path}'"))?;
            let arch: Arch = serde_json::from_str(&text)
                .with_context(|| format!("--arch: '{path}' is not an Arch JSON"))?;
            subnet_cost(&cfg, &arch, a.resolution, a.resolution)
                .with_context(|| format!("--arch {path}"))?
        }
    };
    if a.json {
        print_json(&cost)?;
    } else {
        println!(
            "{}: {:.2} M MACs, {} parameters (pointwise {:.2} M, depthwise {:.2} M, SE {:.2} M, other {:.2} M)",
            a.arch,
            cost.macs as f64 / 1e6,
            cost.params,
            cost.per_kind.pointwise as f64 / 1e6,
            cost.per_kind.depthwise as f64 / 1e6,
            cost.per_kind.se as f64 / 1e6,
            cost.per_kind.other as f64 / 1e6
        );
    }
    Ok(())
}

#[derive(Serialize)]
struct Metrics {
    dice: f64,
    slip_mse: f64,
    seconds: f64,
}

#[derive(Serialize)]
struct FitReport {
    min: Metrics,
    #[serde(skip_serializing_if = "Option::is_none")]
    max: Option<Metrics>,
    seconds: f64,
}

fn fit(a: FitToyArgs) -> Result<()> {
    // The bound `search train` has on its steps.
    if a.steps == 0 || a.steps > MAX_STEPS {
        bail!(
            "--steps: must be 1..={:e}, got {}",
            MAX_STEPS as f64,
            a.steps
        );
    }
    if a.batch < 2 {
        bail!(
            "--batch: need at least 2 images per step (the head's batch norm), got {}",
            a.batch
        );
    }
    if !(8..=MAX_TOY_SIZE).contains(&a.size_px) {
        bail!(
            "--size-px: must lie in 8..={MAX_TOY_SIZE}, got {}",
            a.size_px
        );
    }
    if a.batch.saturating_mul(a.size_px * a.size_px) > MAX_TOY_BATCH_PIXELS {
        bail!(
            "--batch/--size-px: {} images of {}² px exceed {MAX_TOY_BATCH_PIXELS} input pixels \
             per step (≈8 GiB of training memory)",
            a.batch,
            a.size_px
        );
    }
    if !(a.lr.is_finite() && a.lr > 0.0 && a.lr <= MAX_TOY_LR) {
        bail!("--lr: must lie in (0, {MAX_TOY_LR}], got {}", a.lr);
    }
    let cfg = ToyConfig {
        size: a.size_px,
        steps: a.steps,
        batch: a.batch,
        lr: a.lr,
        seed: a.seed,
        ..ToyConfig::default()
    };
    let t0 = Instant::now();
    let run = |arch: &Arch, name: &str| -> Result<Metrics> {
        let t = Instant::now();
        let r = fit_toy_with_progress(arch, &cfg, &mut |done, loss| {
            let per = t.elapsed().as_secs_f64() / done as f64;
            eprint!(
                "\rfit-toy {name}: step {done:>5}/{}  L_task {loss:.4}  {per:.2} s/step, ETA {:.0} s   ",
                cfg.steps,
                per * (cfg.steps - done) as f64
            );
        })
        .map_err(|e| match e.to_string() {
            m if m.contains("lr:") => anyhow::anyhow!("--lr: {e}"),
            _ => anyhow::anyhow!(e),
        })?;
        eprintln!();
        Ok(Metrics {
            dice: r.dice,
            slip_mse: r.slip_mse,
            seconds: r.seconds,
        })
    };
    let min = run(&Arch::min(), "min")?;
    let max = if a.min_only {
        None
    } else {
        Some(run(&Arch::max(), "max")?)
    };
    let rep = FitReport {
        min,
        max,
        seconds: t0.elapsed().as_secs_f64(),
    };
    if a.json {
        print_json(&rep)?;
    } else {
        println!(
            "min subnet: held-out Dice {:.4}, slip MSE {:.4} ({:.1} s)",
            rep.min.dice, rep.min.slip_mse, rep.min.seconds
        );
        if let Some(m) = &rep.max {
            println!(
                "max subnet: held-out Dice {:.4}, slip MSE {:.4} ({:.1} s)",
                m.dice, m.slip_mse, m.seconds
            );
        }
    }
    Ok(())
}

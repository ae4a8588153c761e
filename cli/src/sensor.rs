//! `nanoeye sensor …`: the sensor model of S2 (photon-transfer check).

use crate::util::print_json;
use anyhow::{Result, bail};
use clap::{Args, Subcommand};
use nanoeye_sensor::{MAX_PTC_LEVELS, SensorConfig, SensorError, photon_transfer};

/// Sensor commands.
#[derive(Subcommand)]
pub enum Cmd {
    /// Photon-transfer check on flat fields: variance vs mean (DN) has slope g (DN/e⁻) and
    /// intercept (g·σ_read)² (+1/12 DN² of ADC rounding when quantizing).
    Ptc(PtcArgs),
}

/// Arguments of `sensor ptc`.
#[derive(Args)]
pub struct PtcArgs {
    /// Number of flat-field levels from dark to 60 % of full well.
    #[arg(long, default_value_t = 16)]
    levels: usize,
    /// Side of each flat field in pixels.
    #[arg(long, default_value_t = 256)]
    side_px: usize,
    /// Seed of the noise streams.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Read noise override (electrons rms).
    #[arg(long)]
    read_noise_e: Option<f64>,
    /// Conversion gain override (DN per electron).
    #[arg(long)]
    gain_dn_per_e: Option<f64>,
    /// Disable ADC rounding (the intercept is then exactly (g·σ_read)²).
    #[arg(long)]
    no_quantize: bool,
    /// Print one line of JSON: {"slope","slope_expected","intercept","intercept_expected"}.
    #[arg(long)]
    json: bool,
}

/// Runs a sensor command.
pub fn run(cmd: Cmd) -> Result<()> {
    match cmd {
        Cmd::Ptc(a) => ptc(a),
    }
}

fn ptc(a: PtcArgs) -> Result<()> {
    let mut cfg = SensorConfig {
        quantize: !a.no_quantize,
        ..SensorConfig::default()
    };
    if let Some(r) = a.read_noise_e {
        if !(r.is_finite() && r >= 0.0) {
            bail!("--read-noise-e: must be finite and >= 0, got {r}");
        }
        cfg.read_noise_e = r;
    }
    if let Some(g) = a.gain_dn_per_e {
        if !(g.is_finite() && g > 0.0) {
            bail!("--gain-dn-per-e: must be finite and > 0, got {g}");
        }
        cfg.gain_dn_per_e = g;
    }
    if a.levels < 3 {
        bail!("--levels: need at least 3, got {}", a.levels);
    }
    if a.side_px < 8 || a.side_px > 4096 {
        bail!("--side-px: must lie in 8..=4096, got {}", a.side_px);
    }
    if a.levels > MAX_PTC_LEVELS {
        bail!("--levels: at most {MAX_PTC_LEVELS}, got {}", a.levels);
    }
    let r = photon_transfer(&cfg, a.levels, a.side_px, a.seed).map_err(|e| {
        let flag = match &e {
            SensorError::InvalidParameter { name, .. } => match *name {
                "levels" => "--levels",
                "side" => "--side-px",
                "gain_dn_per_e" => "--gain-dn-per-e",
                "read_noise_e" => "--read-noise-e",
                // No level below saturation: the noise (mean + 6σ) or the gain reaches the
                // well or the ADC's top. The well is not a flag: name the two that are, with
                // the figures they meet.
                "full_well_e" => {
                    return anyhow::anyhow!(
                        "--read-noise-e/--gain-dn-per-e: with read noise {} e- rms and gain {} \
                         DN/e-, fewer than 3 flat-field levels stay below saturation (mean + 6σ \
                         under the {} e- full well and the ADC's {} DN); give a smaller read \
                         noise or gain",
                        cfg.read_noise_e,
                        cfg.gain_dn_per_e,
                        cfg.full_well_e,
                        cfg.max_dn()
                    );
                }
                _ => "sensor",
            },
            _ => "sensor",
        };
        anyhow::anyhow!("{flag}: {e}")
    })?;
    if a.json {
        print_json(&serde_json::json!({
            "slope": r.slope,
            "slope_expected": r.slope_expected,
            "intercept": r.intercept,
            "intercept_expected": r.intercept_expected,
        }))
    } else {
        println!(
            "photon transfer ({} levels, {}x{} px):",
            r.points.len(),
            a.side_px,
            a.side_px
        );
        println!(
            "  slope     {:.6} ± {:.6} DN/e-  (expected g = {:.6})",
            r.slope, r.slope_se, r.slope_expected
        );
        println!(
            "  intercept {:.4} ± {:.4} DN²    (expected (g·σ_read)²{} = {:.4})",
            r.intercept,
            r.intercept_se,
            if cfg.quantize { " + 1/12" } else { "" },
            r.intercept_expected
        );
        Ok(())
    }
}

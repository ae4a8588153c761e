//! `nanoeye safety`: the largest eye-safe LED radiant intensity for a glint illuminator
//! (D.5): IEC 62471's exempt group limits the total corneal IR irradiance (780–3000 nm,
//! t > 1000 s) to 10 mW/cm², ambient included, so I_max = (E_limit − E_ambient)·d².

use crate::util;
use anyhow::{Result, bail};
use clap::Args;

/// IEC 62471 exempt-group corneal IR irradiance limit for t > 1000 s (mW/cm²).
pub const E_LIMIT_MW_CM2: f64 = 10.0;

/// `nanoeye safety` options.
#[derive(Debug, Args)]
pub struct SafetyArgs {
    /// Ambient IR irradiance at the cornea (mW/cm²): 0 indoors, ≈ 4 on a sunny day (D.5).
    #[arg(long, default_value_t = 0.0)]
    ambient_mw_cm2: f64,
    /// Eye relief, LED to cornea (cm).
    #[arg(long, default_value_t = 1.6)]
    eye_relief_cm: f64,
    /// Print JSON.
    #[arg(long)]
    json: bool,
}

/// I_max (mW/sr) for ambient irradiance `ambient` (mW/cm²) at eye relief `d` (cm).
pub fn max_intensity_mw_sr(ambient: f64, d: f64) -> Result<f64> {
    if !(ambient.is_finite() && ambient >= 0.0) {
        bail!("--ambient-mw-cm2: must be finite and ≥ 0, got {ambient}");
    }
    if ambient >= E_LIMIT_MW_CM2 {
        bail!(
            "--ambient-mw-cm2: {ambient} mW/cm² already reaches the {E_LIMIT_MW_CM2} mW/cm² limit; no LED power is eye-safe"
        );
    }
    if !(d.is_finite() && d > 0.0 && d <= 1000.0) {
        bail!("--eye-relief-cm: must lie in (0, 1000], got {d}");
    }
    Ok((E_LIMIT_MW_CM2 - ambient) * d * d)
}

/// Runs `nanoeye safety`.
pub fn run(a: SafetyArgs) -> Result<()> {
    let i = max_intensity_mw_sr(a.ambient_mw_cm2, a.eye_relief_cm)?;
    let out = serde_json::json!({
        "e_limit_mw_cm2": E_LIMIT_MW_CM2,
        "ambient_mw_cm2": a.ambient_mw_cm2,
        "led_budget_mw_cm2": E_LIMIT_MW_CM2 - a.ambient_mw_cm2,
        "eye_relief_cm": a.eye_relief_cm,
        "i_max_mw_sr": i,
    });
    if a.json {
        return util::print_json(&out);
    }
    println!(
        "I_max = ({E_LIMIT_MW_CM2} − {}) mW/cm² × ({} cm)² = {i:.2} mW/sr",
        a.ambient_mw_cm2, a.eye_relief_cm
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reproduces_the_papers_indoor_and_outdoor_limits() {
        // D.5: 25.6 mW/sr indoors, 15.36 mW/sr with 4 mW/cm² of sun, at 1.6 cm.
        assert!((max_intensity_mw_sr(0.0, 1.6).unwrap() - 25.6).abs() < 1e-12);
        assert!((max_intensity_mw_sr(4.0, 1.6).unwrap() - 15.36).abs() < 1e-12);
        assert!(max_intensity_mw_sr(10.0, 1.6).is_err());
        assert!(max_intensity_mw_sr(f64::NAN, 1.6).is_err());
        assert!(max_intensity_mw_sr(1.0, 0.0).is_err());
    }
}

//! Photon-transfer check: on flat fields below saturation, variance vs mean (DN above the
//! black level) is a line of slope g (DN/e⁻) and intercept (g σ_read)² + Δ²/12, the last term
//! being the ADC's rounding variance (Δ = 1 DN; 0 when `quantize` is off).

use crate::Sensor;
use crate::cmos::{CmosSensor, SensorConfig};
use crate::error::SensorError;
use faer::Mat;

/// Result of [`photon_transfer`]; variances in DN², means in DN above black.
#[derive(Clone, Debug, serde::Serialize)]
pub struct PtcResult {
    /// Fitted slope, DN per electron.
    pub slope: f64,
    /// Expected slope: the conversion gain g.
    pub slope_expected: f64,
    /// Fitted intercept, DN².
    pub intercept: f64,
    /// Expected intercept: (g σ_read)² + (1/12 if quantized).
    pub intercept_expected: f64,
    /// Standard error of the slope (weighted least squares).
    pub slope_se: f64,
    /// Standard error of the intercept.
    pub intercept_se: f64,
    /// (mean, variance) per flat-field level.
    pub points: Vec<(f64, f64)>,
}

/// Most flat-field levels of one photon-transfer run.
pub const MAX_PTC_LEVELS: usize = 4096;
/// Largest side (px) of a photon-transfer flat field.
pub const MAX_PTC_SIDE: usize = 4096;
/// Most pixels simulated over all levels (levels × side²): a few seconds of work, and the
/// bound that keeps a request from running for days.
pub const MAX_PTC_PIXELS: usize = 1 << 30;

/// Least noise before ADC rounding (DN rms) of a level the quantized line is fitted on: from
/// here Δ²/12 is the rounding's variance to within 0.2 % of it.
pub const MIN_ROUNDED_NOISE_DN: f64 = 0.7;

/// Runs the photon-transfer measurement on `levels` flat fields of `side`×`side` pixels,
/// from dark to 60 % of full well (quadratic spacing to pin the intercept), seeded by `seed`.
pub fn photon_transfer(
    cfg: &SensorConfig,
    levels: usize,
    side: usize,
    seed: u64,
) -> Result<PtcResult, SensorError> {
    if levels < 3 {
        return Err(SensorError::InvalidParameter {
            name: "levels",
            value: levels as f64,
            why: "need at least 3 flat-field levels",
        });
    }
    if side < 8 {
        return Err(SensorError::InvalidParameter {
            name: "side",
            value: side as f64,
            why: "need at least 8×8 pixels per flat field",
        });
    }
    if levels > MAX_PTC_LEVELS {
        return Err(SensorError::InvalidParameter {
            name: "levels",
            value: levels as f64,
            why: "at most MAX_PTC_LEVELS (4096) flat-field levels",
        });
    }
    if side > MAX_PTC_SIDE {
        return Err(SensorError::InvalidParameter {
            name: "side",
            value: side as f64,
            why: "at most MAX_PTC_SIDE (4096) pixels per side",
        });
    }
    if levels * side * side > MAX_PTC_PIXELS {
        return Err(SensorError::InvalidParameter {
            name: "levels",
            value: levels as f64,
            why: "levels × side² exceeds MAX_PTC_PIXELS (2^30 simulated pixels)",
        });
    }
    let sensor = CmosSensor::new(cfg.clone())?;
    let g = cfg.gain_dn_per_e;
    let mut points = Vec::with_capacity(levels);
    let mut unresolved = 0;
    for l in 0..levels {
        let frac = (l as f64 / (levels - 1) as f64).powi(2);
        let mu_e = 0.6 * cfg.full_well_e * frac;
        // Stay below saturation of both the well and the ADC (mean + 6σ).
        let sd = (mu_e + cfg.read_noise_e.powi(2)).sqrt();
        if mu_e + 6.0 * sd >= cfg.full_well_e
            || cfg.black_level_dn + g * (mu_e + 6.0 * sd) >= cfg.max_dn()
        {
            continue;
        }
        // Rounding adds Δ²/12 only where the noise before it spans the step (Sheppard's
        // correction): off by up to 0.0079 DN² (a tenth of Δ²/12) at σ = Δ/2, depending on
        // where the mean falls between two codes, 0.00013 DN² at σ = 0.7 Δ (the Gaussian's
        // rounded variance, worst offset). A narrower noise rounds to a variance of 0 at most
        // levels of a small gain, which drew the fit to a slope of 0 with an error of 0.
        if cfg.quantize && g * sd < MIN_ROUNDED_NOISE_DN {
            unresolved += 1;
            continue;
        }
        let photons = (mu_e / cfg.quantum_efficiency) as f32;
        let img = Mat::from_fn(side, side, |_, _| photons);
        let (dn, _) = sensor.forward(&img, cfg.base_pitch, cfg.base_pitch, seed, l as u64)?;
        let n = (side * side) as f64;
        let mut s = 0.0;
        let mut s2 = 0.0;
        for j in 0..side {
            for i in 0..side {
                let v = f64::from(dn[(i, j)]) - cfg.black_level_dn;
                s += v;
                s2 += v * v;
            }
        }
        let mean = s / n;
        let var = (s2 - n * mean * mean) / (n - 1.0);
        points.push((mean, var));
    }
    if points.len() < 3 && points.len() + unresolved >= 3 {
        // Some levels resolved: more of them may be enough (3 levels at the default sensor
        // keep 2); none: the gain and read noise are too small for the ADC step.
        return Err(if points.is_empty() {
            SensorError::InvalidParameter {
                name: "gain_dn_per_e",
                value: g,
                why: "with ADC rounding, no flat-field level has noise of at least 0.7 DN \
                      before rounding, where the photon-transfer line holds: a larger gain or \
                      read noise, or no rounding",
            }
        } else {
            SensorError::InvalidParameter {
                name: "levels",
                value: levels as f64,
                why: "with ADC rounding, fewer than 3 flat-field levels have noise of at least \
                      0.7 DN before rounding, where the photon-transfer line holds: more \
                      levels, a larger gain or read noise, or no rounding",
            }
        });
    }
    if points.len() < 3 {
        return Err(SensorError::InvalidParameter {
            name: "full_well_e",
            value: cfg.full_well_e,
            why: "fewer than 3 flat-field levels lie below saturation",
        });
    }
    // Weighted least squares, Var(sample variance) ≈ 2 var²/(n−1).
    let n = (side * side) as f64;
    let (mut sw, mut sx, mut sy, mut sxx, mut sxy) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for &(x, y) in &points {
        let w = (n - 1.0) / (2.0 * y.max(1e-12).powi(2));
        sw += w;
        sx += w * x;
        sy += w * y;
        sxx += w * x * x;
        sxy += w * x * y;
    }
    let det = sw * sxx - sx * sx;
    let slope = (sw * sxy - sx * sy) / det;
    let intercept = (sxx * sy - sx * sxy) / det;
    let q = if cfg.quantize { 1.0 / 12.0 } else { 0.0 };
    let slope_se = (sw / det).sqrt();
    let intercept_se = (sxx / det).sqrt();
    if !(det > 0.0
        && [slope, intercept, slope_se, intercept_se]
            .iter()
            .all(|v| v.is_finite()))
    {
        // All flat fields read the same DN (the gain is too small for the ADC step to see any
        // shot noise, or the signal is too weak): the line is not determined.
        // Without rounding no ADC step is to blame: the DN carry too little of the noise
        // (the message named the ADC step under --no-quantize; a helper's audit).
        return Err(SensorError::InvalidParameter {
            name: "gain_dn_per_e",
            value: g,
            why: if cfg.quantize {
                "the flat fields show no measurable variance in DN, so the photon-transfer \
                 line is undetermined (gain too small for the ADC step)"
            } else {
                "the flat fields show no measurable variance in DN, so the photon-transfer \
                 line is undetermined (gain too small for the noise to show in the f32 DN)"
            },
        });
    }
    Ok(PtcResult {
        slope,
        slope_expected: g,
        intercept,
        intercept_expected: (g * cfg.read_noise_e).powi(2) + q,
        slope_se,
        intercept_se,
        points,
    })
}

#[cfg(test)]
mod bad_input_tests {
    use super::*;

    fn name_of(e: SensorError) -> &'static str {
        match e {
            SensorError::InvalidParameter { name, .. } => name,
            other => panic!("expected InvalidParameter, got {other:?}"),
        }
    }

    #[test]
    fn huge_counts_are_refused_before_allocating() {
        let cfg = SensorConfig::default();
        let e = photon_transfer(&cfg, usize::MAX, 8, 1).unwrap_err();
        assert_eq!(name_of(e), "levels");
        let e = photon_transfer(&cfg, 1_000_000_000_000, 8, 1).unwrap_err();
        assert_eq!(name_of(e), "levels");
        let e = photon_transfer(&cfg, 16, 1 << 20, 1).unwrap_err();
        assert_eq!(name_of(e), "side");
    }

    /// A helper's audit: with rounding on, a gain of 1e-3 DN/e⁻ fitted a slope of −7e-23 and
    /// read noise 0.5 e⁻ an intercept of 0 ± 0, exit 0. Levels whose noise does not span the
    /// ADC step are left out: the line is refused, or fitted on the levels where it holds.
    #[test]
    fn levels_below_the_adc_step_are_left_out_of_the_line() {
        let small = SensorConfig {
            gain_dn_per_e: 1e-3,
            ..SensorConfig::default()
        };
        assert_eq!(
            name_of(photon_transfer(&small, 16, 64, 1).unwrap_err()),
            "gain_dn_per_e"
        );
        // Three levels of the default sensor: the dark one is left out, two remain — more
        // levels would do (the property test's case named the gain).
        let e = photon_transfer(&SensorConfig::default(), 3, 8, 1).unwrap_err();
        assert_eq!(name_of(e), "levels");
        for (gain, read) in [(0.02, 4.0), (SensorConfig::default().gain_dn_per_e, 0.5)] {
            let cfg = SensorConfig {
                gain_dn_per_e: gain,
                read_noise_e: read,
                ..SensorConfig::default()
            };
            let r = photon_transfer(&cfg, 16, 128, 1).unwrap();
            assert!(r.points.len() < 16 && r.points.len() >= 3);
            assert!(
                (r.slope - gain).abs() < 4.0 * r.slope_se && r.slope_se < 0.05 * gain,
                "gain {gain}: slope {} ± {}",
                r.slope,
                r.slope_se
            );
            assert!(
                (r.intercept - r.intercept_expected).abs() < 4.0 * r.intercept_se,
                "gain {gain}: intercept {} ± {} against {}",
                r.intercept,
                r.intercept_se,
                r.intercept_expected
            );
        }
    }

    #[test]
    fn a_gain_too_small_to_measure_is_an_error_not_a_nan() {
        let cfg = SensorConfig {
            gain_dn_per_e: 1e-10,
            ..SensorConfig::default()
        };
        let e = photon_transfer(&cfg, 8, 8, 1).unwrap_err();
        assert_eq!(name_of(e), "gain_dn_per_e");
    }
}

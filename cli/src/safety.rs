//! `nanoeye safety`: the largest eye-safe LED radiant intensity for a glint illuminator
//! (D.5): IEC 62471's exempt group limits the total corneal IR irradiance (780–3000 nm,
//! t > 1000 s) to 10 mW/cm², ambient included, so I_max = (E_limit − E_ambient)·d².

use crate::util;
use anyhow::{Result, bail};
use clap::Args;
use nanoeye_datagen::render::{Light, Subject};
use nanoeye_gaze::{Rig, geom};
use nanoeye_search::Radiometry;
use nanoeye_sensor::SensorConfig;

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
    /// Exposure of the glint camera (ms); the chain's default.
    #[arg(long, default_value_t = 0.1)]
    exposure_ms: f64,
    /// Fraction of the ambient IR irradiance inside the camera's spectral band (1: no band-pass
    /// filter in front of a sensor that sees the whole 780–3000 nm range, the worst case).
    #[arg(long, default_value_t = 1.0)]
    ambient_band_fraction: f64,
    /// Outdoor ambient IR at the cornea (mW/cm²) of the glint comparison (D.5: ≈ 4 on a sunny
    /// day); `--ambient-mw-cm2` sets the I_max line.
    #[arg(long, default_value_t = 4.0)]
    outdoor_mw_cm2: f64,
    /// Print JSON.
    #[arg(long)]
    json: bool,
}

/// Shortest eye relief (cm) the point-source model takes: 1 mm.
pub const MIN_EYE_RELIEF_CM: f64 = 0.1;

/// I_max (mW/sr) for ambient irradiance `ambient` (mW/cm²) at eye relief `d` (cm).
pub fn max_intensity_mw_sr(ambient: f64, d: f64) -> Result<f64> {
    check_ambient("--ambient-mw-cm2", ambient)?;
    // From 1 mm: I/d² treats the LED as a point, which an emitter of a few hundred µm is not
    // closer; at 1e-300 cm I_max printed as 0 beside a saturating glint (a helper's audit).
    if !(d.is_finite() && (MIN_EYE_RELIEF_CM..=1000.0).contains(&d)) {
        bail!("--eye-relief-cm: must lie in [{MIN_EYE_RELIEF_CM}, 1000], got {d}");
    }
    Ok((E_LIMIT_MW_CM2 - ambient) * d * d)
}

/// An ambient irradiance (mW/cm²) below the exposure limit, named `flag` in the error.
fn check_ambient(flag: &str, ambient: f64) -> Result<()> {
    if !(ambient.is_finite() && ambient >= 0.0) {
        bail!("{flag}: must be finite and ≥ 0, got {ambient}");
    }
    if ambient >= E_LIMIT_MW_CM2 {
        bail!(
            "{flag}: {ambient} mW/cm² already reaches the {E_LIMIT_MW_CM2} mW/cm² limit; no LED power is eye-safe"
        );
    }
    Ok(())
}

/// Glint visibility at one ambient level (photo-electrons per 3 µm sensor pixel).
#[derive(Debug, Clone, Copy, serde::Serialize)]
pub struct GlintSnr {
    /// Ambient IR irradiance at the cornea (mW/cm²).
    pub ambient_mw_cm2: f64,
    /// LED radiant intensity at the eye-safe limit (mW/sr).
    pub led_mw_sr: f64,
    /// Photo-electrons of the glint in each pixel of its image (above the background).
    pub glint_e: f64,
    /// Pixels the glint's image covers (the LED's virtual image in the corneal mirror).
    pub glint_px: f64,
    /// Background photo-electrons per pixel from the LED (diffuse iris behind the glint).
    pub led_background_e: f64,
    /// Background photo-electrons per pixel from the ambient IR (diffuse iris).
    pub ambient_background_e: f64,
    /// Whether the glint pixels reach the full well (then the signal is clipped to it).
    pub saturated: bool,
    /// SNR = glint / √(glint + background + read²) per pixel, after clipping at the full well.
    pub snr: f64,
    /// Contrast glint / background per pixel, after clipping.
    pub contrast: f64,
    /// Glint over background per pixel before clipping (what a sensor with a deeper well or
    /// a shorter exposure would see).
    pub glint_to_background: f64,
}

/// The glint of the default rig at primary gaze with the LED (a disc of the renderer's emitter
/// radius beside the camera) at the eye-safe limit for `ambient` (mW/cm²) at eye relief `d`
/// (cm). The cornea is a convex mirror of radius R: its specular reflection of an irradiance E
/// is isotropic with radiant intensity ρ·E·R²/4 (ρ: Fresnel reflectance at normal incidence),
/// spread over the LED's virtual image (magnification (R/2)/(d + R/2)) as the camera images
/// it; the iris behind it is Lambertian, lit by the LED and by `band` of the ambient.
pub fn glint_snr(ambient: f64, d: f64, exposure_s: f64, band: f64) -> Result<GlintSnr> {
    let i_max = max_intensity_mw_sr(ambient, d)?;
    if !(band.is_finite() && (0.0..=1.0).contains(&band)) {
        bail!("--ambient-band-fraction: must lie in [0, 1], got {band}");
    }
    if !(exposure_s.is_finite() && exposure_s > 0.0 && exposure_s <= 1.0) {
        bail!(
            "--exposure-ms: must lie in (0, 1000], got {}",
            exposure_s * 1e3
        );
    }
    let rig = Rig::default();
    let subject = Subject::default();
    let sensor = SensorConfig::default();
    let radio = Radiometry {
        exposure_s,
        ..Radiometry::default()
    };
    let r_c = subject.cornea_radius_m;
    let n = subject.cornea_index;
    let rho = ((n - 1.0) / (n + 1.0)).powi(2);
    let e_led = (E_LIMIT_MW_CM2 - ambient) * 10.0; // W/m²
    let e_amb = ambient * 10.0 * band;
    let apex = [0.0, 0.0, subject.cornea_apex_m];
    let d_cam = geom::norm(geom::sub(rig.camera.position_m, apex));
    let area = std::f64::consts::PI * 0.25 * radio.aperture_m * radio.aperture_m;
    let s = radio.sensor_distance_m;
    let p = sensor.base_pitch;
    let to_e = exposure_s / radio.photon_energy_j() * sensor.quantum_efficiency;
    // Glint: total power into the aperture, over its image on the sensor.
    let i_glint = rho * e_led * r_c * r_c / 4.0;
    let glint_total_w = i_glint * area / (d_cam * d_cam);
    let glint_total_e = glint_total_w * to_e;
    let r_led = Light::near_camera(&rig.camera.nominal_pose()).radius_m;
    let mag = 0.5 * r_c / (d * 1e-2 + 0.5 * r_c);
    let r_img = r_led * mag * s / d_cam;
    let glint_px = (std::f64::consts::PI * r_img * r_img / (p * p)).max(1.0);
    let glint_e = glint_total_e / glint_px;
    // Lambertian iris: radiance ρ_iris·E/π into the pixel's étendue A·p²/s².
    let etendue = area * p * p / (s * s);
    let per_radiance = etendue * to_e;
    let led_bg = subject.iris_albedo * e_led / std::f64::consts::PI * per_radiance;
    let amb_bg = subject.iris_albedo * e_amb / std::f64::consts::PI * per_radiance;
    let fw = sensor.full_well_e;
    // Glint over background per pixel without the exposure's factor, which both carry: at
    // 1e-308 ms the background underflowed and the ratio read 0.02 against 132 at 0.1 ms. The
    // background is never 0 (the LED's irradiance is positive below the limit).
    let ratio = (glint_total_w / glint_px)
        / (subject.iris_albedo * (e_led + e_amb) / std::f64::consts::PI * etendue);
    let saturated = glint_e + led_bg + amb_bg >= fw;
    let signal = (glint_e + led_bg + amb_bg).min(fw) - (led_bg + amb_bg).min(fw);
    let noise = ((signal + led_bg + amb_bg).min(fw) + sensor.read_noise_e.powi(2)).sqrt();
    Ok(GlintSnr {
        ambient_mw_cm2: ambient,
        led_mw_sr: i_max,
        glint_e,
        glint_px,
        led_background_e: led_bg,
        ambient_background_e: amb_bg,
        saturated,
        snr: signal / noise,
        contrast: if saturated {
            signal / (led_bg + amb_bg)
        } else {
            ratio
        },
        glint_to_background: ratio,
    })
}

/// Runs `nanoeye safety`.
pub fn run(a: SafetyArgs) -> Result<()> {
    let i = max_intensity_mw_sr(a.ambient_mw_cm2, a.eye_relief_cm)?;
    check_ambient("--outdoor-mw-cm2", a.outdoor_mw_cm2)?;
    let exposure_s = a.exposure_ms * 1e-3;
    let indoor = glint_snr(0.0, a.eye_relief_cm, exposure_s, a.ambient_band_fraction)?;
    let outdoor = glint_snr(
        a.outdoor_mw_cm2,
        a.eye_relief_cm,
        exposure_s,
        a.ambient_band_fraction,
    )?;
    let out = serde_json::json!({
        "e_limit_mw_cm2": E_LIMIT_MW_CM2,
        "ambient_mw_cm2": a.ambient_mw_cm2,
        "led_budget_mw_cm2": E_LIMIT_MW_CM2 - a.ambient_mw_cm2,
        "eye_relief_cm": a.eye_relief_cm,
        "i_max_mw_sr": i,
        "glint": {
            "exposure_ms": a.exposure_ms,
            "ambient_band_fraction": a.ambient_band_fraction,
            "indoor": indoor,
            "outdoor": outdoor,
        },
    });
    if a.json {
        return util::print_json(&out);
    }
    println!(
        "I_max = ({E_LIMIT_MW_CM2} − {}) mW/cm² × ({} cm)² = {i:.2} mW/sr",
        a.ambient_mw_cm2, a.eye_relief_cm
    );
    println!(
        "glint of the default rig at primary gaze, per 3 µm pixel ({} ms exposure, {:.0} % of the ambient in band):",
        a.exposure_ms,
        a.ambient_band_fraction * 100.0
    );
    println!(
        "{:<10} {:>9} {:>10} {:>8} {:>10} {:>10} {:>9} {:>8} {:>9}",
        "",
        "LED mW/sr",
        "glint e⁻",
        "glint px",
        "LED bg e⁻",
        "sun bg e⁻",
        "glint/bg",
        "SNR",
        "contrast"
    );
    for (name, g) in [("indoor", indoor), ("outdoor", outdoor)] {
        println!(
            "{name:<10} {:>9.2} {:>10.0} {:>8.1} {:>10.0} {:>10.0} {:>9.1} {:>8.1} {:>9.2}{}",
            g.led_mw_sr,
            g.glint_e,
            g.glint_px,
            g.led_background_e,
            g.ambient_background_e,
            g.glint_to_background,
            g.snr,
            g.contrast,
            if g.saturated { " (saturated)" } else { "" }
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Glint and background both scale with the exposure: their ratio does not (a helper's
    /// audit: 1e-308 ms read 0.02 against 132 at 0.1 ms, the background floored at 1e-300).
    #[test]
    fn the_glint_to_background_ratio_does_not_depend_on_the_exposure() {
        for (ambient, band) in [(0.0, 1.0), (4.0, 1.0), (4.0, 0.1)] {
            let at = |t: f64| glint_snr(ambient, 1.6, t, band).unwrap();
            let (one, tiny) = (at(1e-4), at(1e-311));
            let rel = (tiny.glint_to_background / one.glint_to_background - 1.0).abs();
            assert!(
                rel < 1e-12,
                "{} vs {}",
                tiny.glint_to_background,
                one.glint_to_background
            );
            // Unclipped, the contrast is that ratio; at 0.1 ms indoors the glint saturates.
            assert!(!tiny.saturated && tiny.contrast == tiny.glint_to_background);
            let direct = one.glint_e / (one.led_background_e + one.ambient_background_e);
            assert!((one.glint_to_background / direct - 1.0).abs() < 1e-12);
        }
    }

    #[test]
    fn reproduces_the_papers_indoor_and_outdoor_limits() {
        // D.5: 25.6 mW/sr indoors, 15.36 mW/sr with 4 mW/cm² of sun, at 1.6 cm.
        assert!((max_intensity_mw_sr(0.0, 1.6).unwrap() - 25.6).abs() < 1e-12);
        assert!((max_intensity_mw_sr(4.0, 1.6).unwrap() - 15.36).abs() < 1e-12);
        assert!(max_intensity_mw_sr(10.0, 1.6).is_err());
        assert!(max_intensity_mw_sr(f64::NAN, 1.6).is_err());
        assert!(max_intensity_mw_sr(1.0, 0.0).is_err());
        // Closer than 1 mm the LED is no point source (1e-300 cm printed I_max 0 beside a
        // saturating glint); 1 mm itself is taken.
        assert!(max_intensity_mw_sr(0.0, 1e-300).is_err());
        assert!(max_intensity_mw_sr(0.0, 0.099).is_err());
        assert!((max_intensity_mw_sr(0.0, 0.1).unwrap() - 0.1).abs() < 1e-12);
    }

    /// Glint signal scales with the LED's intensity (linear radiometry); with the whole
    /// ambient in band the background is the same indoors and out, since the limit fixes the
    /// total corneal irradiance; so the glint-to-background ratio falls by exactly the LED's
    /// budget ratio, 6/10.
    #[test]
    fn sunlight_throttles_the_glint() {
        let a = glint_snr(0.0, 1.6, 1e-4, 1.0).unwrap();
        let b = glint_snr(4.0, 1.6, 1e-4, 1.0).unwrap();
        assert!(a.glint_e > 0.0 && a.snr.is_finite() && a.glint_px >= 1.0);
        assert!(((b.glint_e / a.glint_e) - 0.6).abs() < 1e-12, "{a:?} {b:?}");
        assert_eq!(a.ambient_background_e, 0.0);
        let bg = |g: &GlintSnr| g.led_background_e + g.ambient_background_e;
        assert!((bg(&a) - bg(&b)).abs() < 1e-9 * bg(&a));
        assert!((b.glint_to_background / a.glint_to_background - 0.6).abs() < 1e-12);
        // Electrons grow linearly with exposure.
        let c = glint_snr(0.0, 1.6, 2e-4, 1.0).unwrap();
        assert!((c.glint_e / a.glint_e - 2.0).abs() < 1e-12);
        assert!(glint_snr(0.0, 1.6, 1e-4, 2.0).is_err());
    }
}

//! Scene radiance → photons per native pixel at the sensor, for an illuminator at the eye-safe
//! limit (D.5). Étendue: the power a scene patch seen by one native pixel sends into the
//! aperture is L·A·Ω_pix·cos θ = L·A·p²cos⁴θ/s², A = πD²/4 the aperture area, s the lens–sensor
//! distance, θ the field angle; photons = power · t_exp · λ/(hc). The PSF then spreads that
//! power as fractions over sensor pixels (S1). Rendered radiance scales linearly with the
//! renderer's illuminator, so it is rescaled by I_LED / I_render.

use crate::error::{Result, param, positive};
use faer::Mat;
use nanoeye_gaze::Camera;
use serde::{Deserialize, Serialize};

/// Planck constant (J s).
pub const PLANCK_J_S: f64 = 6.626_070_15e-34;
/// Speed of light (m/s).
pub const LIGHT_M_S: f64 = 299_792_458.0;
/// IEC 62471 exempt-group limit on corneal IR irradiance for t > 1000 s (W/m², = 10 mW/cm²).
pub const IEC62471_EXEMPT_W_M2: f64 = 100.0;

/// Radiometric parameters of the camera and illuminator (SI units).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Radiometry {
    /// Wavelength λ (m).
    pub wavelength_m: f64,
    /// Aperture diameter D (m).
    pub aperture_m: f64,
    /// Lens-to-sensor distance s (m).
    pub sensor_distance_m: f64,
    /// Exposure time (s).
    pub exposure_s: f64,
    /// Corneal irradiance of the illuminator (W/m²); default the exempt limit, 10 mW/cm².
    pub corneal_irradiance_w_m2: f64,
    /// Illuminator–cornea distance d (m): I_LED = E·d². `None`: the distance of the
    /// renderer's illuminator from the corneal apex at primary gaze, so the rendered scene is
    /// lit at exactly `corneal_irradiance_w_m2`.
    pub led_distance_m: Option<f64>,
}

impl Default for Radiometry {
    /// 940 nm, D = 1 mm, s = 2 mm, 0.1 ms exposure, the renderer's illuminator driven to the
    /// exempt limit at the cornea.
    fn default() -> Self {
        Radiometry {
            wavelength_m: 940e-9,
            aperture_m: 1e-3,
            sensor_distance_m: 2e-3,
            exposure_s: 0.1e-3,
            corneal_irradiance_w_m2: IEC62471_EXEMPT_W_M2,
            led_distance_m: None,
        }
    }
}

impl Radiometry {
    /// Checks every field.
    pub fn validate(&self) -> Result<()> {
        positive("wavelength_m", self.wavelength_m)?;
        positive("aperture_m", self.aperture_m)?;
        positive("sensor_distance_m", self.sensor_distance_m)?;
        positive("exposure_s", self.exposure_s)?;
        if let Some(d) = self.led_distance_m {
            positive("led_distance_m", d)?;
        }
        let e = self.corneal_irradiance_w_m2;
        if !(0.0..=IEC62471_EXEMPT_W_M2 * (1.0 + 1e-12)).contains(&e) {
            return Err(param(
                "corneal_irradiance_w_m2",
                format!("must lie in [0, {IEC62471_EXEMPT_W_M2}] W/m² (IEC 62471 exempt), got {e}"),
            ));
        }
        if self.exposure_s > 1.0 {
            return Err(param("exposure_s", "must be at most 1 s"));
        }
        Ok(())
    }

    /// Radiant intensity of the illuminator (W/sr) for an illuminator `render_distance_m` from
    /// the cornea when `led_distance_m` is `None`.
    pub fn led_intensity_w_per_sr(&self, render_distance_m: f64) -> f64 {
        let d = self.led_distance_m.unwrap_or(render_distance_m);
        self.corneal_irradiance_w_m2 * d * d
    }

    /// Photon energy hc/λ (J).
    pub fn photon_energy_j(&self) -> f64 {
        PLANCK_J_S * LIGHT_M_S / self.wavelength_m
    }

    /// Photons per pixel of `camera`'s pitch per unit of *rendered* radiance, per pixel of
    /// `camera` (cos⁴θ included), for a dataset rendered with an illuminator of
    /// `render_w_per_sr` at `render_distance_m` from the cornea.
    pub fn scale_map(
        &self,
        camera: &Camera,
        render_w_per_sr: f64,
        render_distance_m: f64,
    ) -> Result<Mat<f32>> {
        self.validate()?;
        positive("light_intensity_w_per_sr", render_w_per_sr)?;
        positive("render_distance_m", render_distance_m)?;
        let area = std::f64::consts::PI * 0.25 * self.aperture_m * self.aperture_m;
        let p = camera.pixel_pitch_m;
        let s = self.sensor_distance_m;
        let k = self.led_intensity_w_per_sr(render_distance_m) / render_w_per_sr * area * p * p
            / (s * s)
            * self.exposure_s
            / self.photon_energy_j();
        Ok(Mat::from_fn(camera.height_px, camera.width_px, |i, j| {
            let x = (j as f64 + 0.5 - camera.cx_px) / camera.fx_px;
            let y = (i as f64 + 0.5 - camera.cy_px) / camera.fy_px;
            let c2 = 1.0 / (1.0 + x * x + y * y);
            (k * c2 * c2) as f32
        }))
    }
}

//! The CMOS sensor of S2: κ-scaled box integration, shot noise (Poisson in electrons), read
//! noise (Gaussian), full-well clipping and ADC (gain, black level, bit depth).
//!
//! Gradient through the noise (documented reparameterization): a shot-noise draw is written
//! e = μ + √μ·ξ with ξ the standardized residual of the draw (exact for `NoiseMode::Gaussian`,
//! where ξ ~ N(0,1) is drawn from the seed; for `NoiseMode::Poisson` ξ = (k − μ)/√μ of the
//! realized count k). Holding ξ fixed gives ∂e/∂μ = 1 + ξ/(2√μ). Read noise is additive
//! (∂/∂μ = 1). Saturated pixels (full well, ADC range) pass no gradient; rounding in the ADC
//! is passed straight through (∂round(x)/∂x := 1).

use crate::Sensor;
use crate::binning::BoxIntegrator;
use crate::error::{SensorError, check_image, check_positive};
use crate::rng::{poisson, standard_normal, stream_rng};
use faer::Mat;
use rayon::prelude::*;

/// How the sensor draws noise.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum NoiseMode {
    /// Noise-free: expected electrons, no read noise.
    None,
    /// Poisson shot noise and Gaussian read noise (physical model).
    Poisson,
    /// Gaussian shot noise μ + √μ ξ and Gaussian read noise (smooth reparameterized model).
    Gaussian,
}

/// Sensor parameters (units in the field names' docs); defaults: docs/sensor.md.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SensorConfig {
    /// Native pixel pitch p_base in metres (κ = (p̂/p_base)²).
    pub base_pitch: f64,
    /// Quantum efficiency at the working wavelength (electrons per photon, 0–1].
    pub quantum_efficiency: f64,
    /// Read noise, electrons rms.
    pub read_noise_e: f64,
    /// Full-well capacity, electrons.
    pub full_well_e: f64,
    /// Conversion gain, DN per electron.
    pub gain_dn_per_e: f64,
    /// ADC black level (pedestal), DN.
    pub black_level_dn: f64,
    /// ADC bit depth.
    pub bit_depth: u32,
    /// Noise model.
    pub noise: NoiseMode,
    /// Round to integer DN (off for finite-difference checks of the VJP).
    pub quantize: bool,
}

impl Default for SensorConfig {
    /// A 3 µm global-shutter NIR sensor modelled on the OmniVision OV9281 (docs/sensor.md).
    fn default() -> Self {
        let full_well_e = 8000.0;
        let black_level_dn = 16.0;
        let bit_depth = 10;
        SensorConfig {
            base_pitch: 3e-6,
            quantum_efficiency: 0.20,
            read_noise_e: 4.0,
            full_well_e,
            // The ADC range above the black level spans the full well at unity analog gain.
            gain_dn_per_e: (f64::from((1u32 << bit_depth) - 1) - black_level_dn) / full_well_e,
            black_level_dn,
            bit_depth,
            noise: NoiseMode::Poisson,
            quantize: true,
        }
    }
}

impl SensorConfig {
    /// Checks every parameter's range.
    pub fn validate(&self) -> Result<(), SensorError> {
        check_positive("base_pitch", self.base_pitch)?;
        check_positive("full_well_e", self.full_well_e)?;
        check_positive("gain_dn_per_e", self.gain_dn_per_e)?;
        if !(self.quantum_efficiency > 0.0 && self.quantum_efficiency <= 1.0) {
            return Err(SensorError::InvalidParameter {
                name: "quantum_efficiency",
                value: self.quantum_efficiency,
                why: "must lie in (0, 1]",
            });
        }
        if !(self.read_noise_e.is_finite() && self.read_noise_e >= 0.0) {
            return Err(SensorError::InvalidParameter {
                name: "read_noise_e",
                value: self.read_noise_e,
                why: "must be finite and >= 0",
            });
        }
        if !(1..=24).contains(&self.bit_depth) {
            return Err(SensorError::InvalidParameter {
                name: "bit_depth",
                value: f64::from(self.bit_depth),
                why: "must lie in 1..=24",
            });
        }
        if !(self.black_level_dn.is_finite() && self.black_level_dn >= 0.0)
            || self.black_level_dn >= self.max_dn()
        {
            return Err(SensorError::InvalidParameter {
                name: "black_level_dn",
                value: self.black_level_dn,
                why: "must lie in [0, 2^bit_depth - 1)",
            });
        }
        Ok(())
    }

    /// Largest digital number, 2^bits − 1.
    pub fn max_dn(&self) -> f64 {
        f64::from((1u32 << self.bit_depth.min(31)) - 1)
    }
}

/// What the VJP needs from a forward pass.
#[derive(Clone, Debug)]
pub struct SensorTape {
    integrator: BoxIntegrator,
    image: Mat<f32>,
    /// ∂DN/∂photons per effective pixel (gain · QE · ∂e/∂μ · masks).
    ddn_dphot: Mat<f32>,
    /// Mean photo-electrons per effective pixel, before noise.
    mean_e: Mat<f32>,
}

impl SensorTape {
    /// Mean photo-electrons per effective pixel of the forward pass (QE · box-integrated
    /// photons, before noise), so a caller that reports them need not integrate again.
    pub fn mean_electrons(&self) -> &Mat<f32> {
        &self.mean_e
    }
}

/// Gradients w.r.t. the sensor inputs.
#[derive(Clone, Debug)]
pub struct SensorGrad {
    /// Gradient w.r.t. the input image (per photon per base-pixel area).
    pub d_image: Mat<f32>,
    /// Gradient w.r.t. the effective pitch p̂ (per metre).
    pub d_p_hat: f64,
}

/// The S2 sensor with the parameters of a [`SensorConfig`].
#[derive(Clone, Debug)]
pub struct CmosSensor {
    cfg: SensorConfig,
}

impl CmosSensor {
    /// Validates `cfg` and builds the sensor.
    pub fn new(cfg: SensorConfig) -> Result<CmosSensor, SensorError> {
        cfg.validate()?;
        Ok(CmosSensor { cfg })
    }

    /// The parameters.
    pub fn config(&self) -> &SensorConfig {
        &self.cfg
    }

    /// Digitizes expected electrons per pixel (`mu_e`), drawing noise from (seed, index).
    /// Returns DN and ∂DN/∂μ_e per pixel.
    pub fn digitize(&self, mu_e: &Mat<f32>, seed: u64, index: u64) -> (Mat<f32>, Mat<f32>) {
        let c = &self.cfg;
        let (mr, mc) = (mu_e.nrows(), mu_e.ncols());
        let cols: Vec<(Vec<f32>, Vec<f32>)> = (0..mc)
            .into_par_iter()
            .map(|j| {
                let mut rng = stream_rng(seed, index, j as u64);
                let mut dn = Vec::with_capacity(mr);
                let mut dd = Vec::with_capacity(mr);
                for i in 0..mr {
                    let mu = f64::from(mu_e[(i, j)]).max(0.0);
                    // Shot noise and its pathwise derivative ∂e/∂μ at fixed ξ.
                    let (e_shot, de) = match c.noise {
                        NoiseMode::None => (mu, 1.0),
                        NoiseMode::Poisson => {
                            let k = poisson(&mut rng, mu);
                            // Below 1e-6 e⁻ the √μ derivative is undefined; use 1.
                            let d = if mu > 1e-6 {
                                1.0 + (k - mu) / (2.0 * mu)
                            } else {
                                1.0
                            };
                            (k, d)
                        }
                        NoiseMode::Gaussian => {
                            let xi = standard_normal(&mut rng);
                            let s = mu.sqrt();
                            let d = if mu > 1e-6 { 1.0 + xi / (2.0 * s) } else { 1.0 };
                            (mu + s * xi, d)
                        }
                    };
                    let (e_sat, de) = if e_shot >= c.full_well_e {
                        (c.full_well_e, 0.0)
                    } else {
                        (e_shot, de)
                    };
                    let read = if c.noise == NoiseMode::None {
                        0.0
                    } else {
                        c.read_noise_e * standard_normal(&mut rng)
                    };
                    let mut v = c.black_level_dn + c.gain_dn_per_e * (e_sat + read);
                    if c.quantize {
                        v = v.round();
                    }
                    let (v, pass) = if v <= 0.0 {
                        (0.0, 0.0)
                    } else if v >= c.max_dn() {
                        (c.max_dn(), 0.0)
                    } else {
                        (v, 1.0)
                    };
                    dn.push(v as f32);
                    dd.push((c.gain_dn_per_e * de * pass) as f32);
                }
                (dn, dd)
            })
            .collect();
        let dn = Mat::from_fn(mr, mc, |i, j| cols[j].0[i]);
        let dd = Mat::from_fn(mr, mc, |i, j| cols[j].1[i]);
        (dn, dd)
    }

    /// ∂L/∂p̂ alone (per metre): [`Sensor::vjp`]'s `d_p_hat`, without the image gradient a
    /// fixed lens's training does not use.
    pub fn pitch_vjp(&self, tape: &SensorTape, grad_dn: &Mat<f32>) -> Result<f64, SensorError> {
        let g = Self::photon_grad(tape, grad_dn)?;
        tape.integrator.pitch_vjp(&tape.image, &g)
    }

    /// ∂L/∂photons per effective pixel for ∂L/∂DN `grad_dn` (shape and values checked).
    fn photon_grad(tape: &SensorTape, grad_dn: &Mat<f32>) -> Result<Mat<f32>, SensorError> {
        let shape = (tape.ddn_dphot.nrows(), tape.ddn_dphot.ncols());
        if (grad_dn.nrows(), grad_dn.ncols()) != shape {
            return Err(SensorError::Shape {
                name: "grad_dn",
                expected: shape,
                got: (grad_dn.nrows(), grad_dn.ncols()),
            });
        }
        check_image("grad_dn", grad_dn, true)?;
        Ok(Mat::from_fn(shape.0, shape.1, |i, j| {
            grad_dn[(i, j)] * tape.ddn_dphot[(i, j)]
        }))
    }
}

impl Sensor for CmosSensor {
    fn forward(
        &self,
        image: &Mat<f32>,
        sample_pitch: f64,
        p_hat: f64,
        seed: u64,
        index: u64,
    ) -> Result<(Mat<f32>, SensorTape), SensorError> {
        check_image("image", image, false)?;
        let integ = BoxIntegrator::new(
            image.nrows(),
            image.ncols(),
            sample_pitch,
            p_hat,
            self.cfg.base_pitch,
        )?;
        let photons = integ.forward(image)?;
        let qe = self.cfg.quantum_efficiency as f32;
        let mu_e = Mat::from_fn(photons.nrows(), photons.ncols(), |i, j| {
            qe * photons[(i, j)]
        });
        let (dn, mut dd) = self.digitize(&mu_e, seed, index);
        for j in 0..dd.ncols() {
            for i in 0..dd.nrows() {
                dd[(i, j)] *= qe;
            }
        }
        Ok((
            dn,
            SensorTape {
                integrator: integ,
                image: image.clone(),
                ddn_dphot: dd,
                mean_e: mu_e,
            },
        ))
    }

    fn vjp(&self, tape: &SensorTape, grad_dn: &Mat<f32>) -> Result<SensorGrad, SensorError> {
        let g = Self::photon_grad(tape, grad_dn)?;
        let r = tape.integrator.vjp(&tape.image, &g)?;
        Ok(SensorGrad {
            d_image: r.d_image,
            d_p_hat: r.d_p_hat,
        })
    }
}

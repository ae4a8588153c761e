//! Sensor model (S2, S24): box integration with a learnable effective pitch p̂, downsampling,
//! κ = (p̂/p_base)², shot and read noise, full-well clipping and ADC. Main trait: `Sensor`.
//!
//! Units: pitches in metres, signals in photons / electrons (e⁻), digital numbers (DN).
//! The input image is the photon count per *base-pixel area* p_base², sampled on a grid of
//! spacing `sample_pitch`; the output of the envelope + downsampling + κ is the photon count
//! collected by each effective pixel of width p̂ (see docs/sensor.md).

mod binning;
mod cmos;
mod error;
mod ptc;
mod rng;

pub use binning::{BoxIntegrator, IntegratorGrad};
pub use cmos::{CmosSensor, NoiseMode, SensorConfig, SensorGrad, SensorTape};
pub use error::SensorError;
pub use ptc::{
    MAX_PTC_LEVELS, MAX_PTC_PIXELS, MAX_PTC_SIDE, MIN_ROUNDED_NOISE_DN, PtcResult, photon_transfer,
};
pub use rng::{standard_normal, stream_rng};

use faer::Mat;

/// A differentiable sensor: irradiance image → digital image, with a VJP for image and pitch.
pub trait Sensor {
    /// Simulates one exposure: `image` in photons per base-pixel area sampled every
    /// `sample_pitch` metres, effective pitch `p_hat` in metres; noise drawn from the stream
    /// (`seed`, `index`). Returns the image in DN and the tape the VJP needs.
    fn forward(
        &self,
        image: &Mat<f32>,
        sample_pitch: f64,
        p_hat: f64,
        seed: u64,
        index: u64,
    ) -> Result<(Mat<f32>, SensorTape), SensorError>;

    /// Vector–Jacobian product: upstream gradient w.r.t. the DN image → gradients w.r.t. the
    /// input image (per photon) and p̂ (per metre).
    fn vjp(&self, tape: &SensorTape, grad_dn: &Mat<f32>) -> Result<SensorGrad, SensorError>;
}

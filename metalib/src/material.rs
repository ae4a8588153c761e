//! Optical constants of the pillar, the layer background and the substrate.

use crate::error::MetalibError;
use num_complex::Complex64;

/// Default wavelength (m): the 940 nm near-infrared illumination.
pub const DEFAULT_WAVELENGTH_M: f64 = 940e-9;
/// Fused silica at 940 nm (Malitson 1965 Sellmeier, as given in oracles.md), dimensionless.
pub const FUSED_SILICA_N_940: f64 = 1.4512;
/// Amorphous silicon refractive index at 940 nm: D. T. Pierce and W. E. Spicer,
/// Phys. Rev. B 5, 3017 (1972), interpolated to 940 nm (value as given in oracles.md).
pub const A_SI_N_940: f64 = 3.70;
/// Amorphous silicon extinction coefficient at 940 nm (same source as [`A_SI_N_940`]).
pub const A_SI_K_940: f64 = 0.008;

/// Materials of a unit cell: complex indices n + ik (time convention e^{-iωt}, so k ≥ 0 is loss).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Materials {
    /// Pillar index real part.
    pub n_pillar: f64,
    /// Pillar extinction coefficient (≥ 0).
    pub k_pillar: f64,
    /// Index of the medium surrounding the pillars inside the layer (default air, 1).
    pub n_background: f64,
    /// Substrate index (real, ≥ 1 recommended; semi-infinite below the layer).
    pub n_substrate: f64,
    /// Superstrate (incidence side) index, default air.
    pub n_superstrate: f64,
}

impl Default for Materials {
    fn default() -> Self {
        Self {
            n_pillar: A_SI_N_940,
            k_pillar: A_SI_K_940,
            n_background: 1.0,
            n_substrate: FUSED_SILICA_N_940,
            n_superstrate: 1.0,
        }
    }
}

impl Materials {
    /// Checks that every index is finite, real parts positive and losses non-negative.
    pub fn validate(&self) -> Result<(), MetalibError> {
        let pos = |name: &'static str, v: f64| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(MetalibError::param(
                    name,
                    format!("must be finite and > 0, got {v}"),
                ))
            }
        };
        pos("n_pillar", self.n_pillar)?;
        pos("n_background", self.n_background)?;
        pos("n_substrate", self.n_substrate)?;
        pos("n_superstrate", self.n_superstrate)?;
        if !(self.k_pillar.is_finite() && self.k_pillar >= 0.0) {
            return Err(MetalibError::param(
                "k_pillar",
                format!("must be finite and >= 0 (no gain), got {}", self.k_pillar),
            ));
        }
        Ok(())
    }

    /// Relative permittivity of the pillar, (n + ik)².
    pub fn eps_pillar(&self) -> Complex64 {
        let n = Complex64::new(self.n_pillar, self.k_pillar);
        n * n
    }

    /// Relative permittivity of the layer background.
    pub fn eps_background(&self) -> Complex64 {
        Complex64::new(self.n_background * self.n_background, 0.0)
    }
}

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

/// Largest accepted n or k. Far beyond any optical material (metals in the far infrared reach
/// a few hundred), and (n + ik)² stays far inside f64: an index of 7e239 made the permittivity
/// infinite and the solve fail without naming the index.
pub const MAX_INDEX: f64 = 1e3;
/// Smallest accepted real index: below any optical material (silver's n is ~0.03 in the
/// visible); 1/ε stays finite (a background index of 3e-124 made the inverse-permittivity
/// matrix infinite).
pub const MIN_INDEX: f64 = 1e-3;

impl Materials {
    /// Checks that every real part lies in [[`MIN_INDEX`], [`MAX_INDEX`]] and the loss in
    /// [0, [`MAX_INDEX`]].
    pub fn validate(&self) -> Result<(), MetalibError> {
        let pos = |name: &'static str, v: f64| {
            if (MIN_INDEX..=MAX_INDEX).contains(&v) {
                Ok(())
            } else {
                Err(MetalibError::param(
                    name,
                    format!("must lie in [{MIN_INDEX}, {MAX_INDEX}], got {v}"),
                ))
            }
        };
        pos("n_pillar", self.n_pillar)?;
        pos("n_background", self.n_background)?;
        pos("n_substrate", self.n_substrate)?;
        pos("n_superstrate", self.n_superstrate)?;
        if !(self.k_pillar.is_finite() && self.k_pillar >= 0.0 && self.k_pillar <= MAX_INDEX) {
            return Err(MetalibError::param(
                "k_pillar",
                format!(
                    "must lie in [0, {MAX_INDEX}] (no gain), got {}",
                    self.k_pillar
                ),
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn indices_outside_the_bounds_are_refused_by_name() {
        let ok = Materials::default();
        assert!(ok.validate().is_ok());
        let at_bound = Materials {
            n_pillar: MAX_INDEX,
            k_pillar: MAX_INDEX,
            n_background: MIN_INDEX,
            ..ok
        };
        assert!(at_bound.validate().is_ok());
        for (m, name) in [
            (
                Materials {
                    n_pillar: 7e239,
                    ..ok
                },
                "n_pillar",
            ),
            (
                Materials {
                    k_pillar: 1e300,
                    ..ok
                },
                "k_pillar",
            ),
            (
                Materials {
                    n_substrate: MAX_INDEX * 1.01,
                    ..ok
                },
                "n_substrate",
            ),
            (
                Materials {
                    n_background: 3e-124,
                    ..ok
                },
                "n_background",
            ),
            (
                Materials {
                    n_superstrate: 0.0,
                    ..ok
                },
                "n_superstrate",
            ),
        ] {
            let e = m.validate().unwrap_err().to_string();
            assert!(e.contains(name), "{e}");
        }
    }
}

//! Which lens a run uses: the hyperbolic and double-helix baselines or a phase map from an NPY
//! file, realised on the chain's aperture grid.

use crate::error::{Result, param};
use nanoeye_optics::{ApertureGrid, DoubleHelix, Hyperbolic, PhaseMap, PhaseProfile};
use std::path::PathBuf;

/// A lens choice, parsed from `hyperbolic`, `double-helix`, `flat` or `file:PATH.npy`.
#[derive(Clone, Debug, PartialEq)]
pub enum LensSpec {
    /// Hyperbolic lens focused at 25 mm (the default rig).
    Hyperbolic,
    /// Double-helix (rotating two-lobe) lens over 17–26 mm.
    DoubleHelix,
    /// No lens: zero phase over the aperture (a bare pinhole-less aperture, no depth cue:
    /// the control of the co-design claim).
    Flat,
    /// A phase map (rad, n×n on the aperture grid) from an NPY file.
    File(PathBuf),
}

impl std::str::FromStr for LensSpec {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "hyperbolic" => Ok(LensSpec::Hyperbolic),
            "double-helix" => Ok(LensSpec::DoubleHelix),
            "flat" => Ok(LensSpec::Flat),
            _ => match s.strip_prefix("file:") {
                Some(p) if !p.is_empty() => Ok(LensSpec::File(PathBuf::from(p))),
                _ => Err(format!(
                    "'{s}' is not a lens: use hyperbolic, double-helix, flat or file:PATH.npy"
                )),
            },
        }
    }
}

/// The name [`LensSpec`]'s parser reads back (a file as `file:PATH`).
impl std::fmt::Display for LensSpec {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            LensSpec::Hyperbolic => f.write_str("hyperbolic"),
            LensSpec::DoubleHelix => f.write_str("double-helix"),
            LensSpec::Flat => f.write_str("flat"),
            LensSpec::File(p) => write!(f, "file:{}", p.display()),
        }
    }
}

impl LensSpec {
    /// The phase map on `grid` (λ and s from the caller for the built-in lenses).
    pub fn phase_map(
        &self,
        grid: &ApertureGrid,
        wavelength_m: f64,
        sensor_distance_m: f64,
    ) -> Result<PhaseMap> {
        let hyp = Hyperbolic {
            wavelength_m,
            image_distance_m: sensor_distance_m,
            ..Hyperbolic::default()
        };
        match self {
            LensSpec::Hyperbolic => Ok(hyp.phase_map(grid)?),
            LensSpec::DoubleHelix => Ok(DoubleHelix {
                lens: Hyperbolic {
                    wavelength_m,
                    image_distance_m: sensor_distance_m,
                    ..DoubleHelix::default().lens
                },
                ..DoubleHelix::default()
            }
            .phase_map(grid)?),
            LensSpec::Flat => Ok(PhaseMap::phase_only(
                *grid,
                faer::Mat::zeros(grid.n, grid.n),
            )?),
            LensSpec::File(p) => {
                let phi = nanoeye_optics::io::read_phase_npy(p)?;
                if phi.nrows() != grid.n {
                    return Err(param(
                        "lens",
                        format!(
                            "{} is {}×{} but the aperture grid is {}×{} (Δ = {} µm over {} mm)",
                            p.display(),
                            phi.nrows(),
                            phi.ncols(),
                            grid.n,
                            grid.n,
                            grid.pitch_m * 1e6,
                            grid.diameter_m * 1e3
                        ),
                    ));
                }
                Ok(PhaseMap::phase_only(*grid, phi)?)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn flat_is_zero_phase_and_every_name_parses() {
        let grid = ApertureGrid::new(1e-3, 20e-6).unwrap();
        let m = "flat"
            .parse::<LensSpec>()
            .unwrap()
            .phase_map(&grid, 940e-9, 2e-3)
            .unwrap();
        assert!(
            (0..grid.n).all(|i| (0..grid.n).all(|j| m.phase_rad[(i, j)] == 0.0)),
            "a flat lens bends nothing"
        );
        for s in [
            "hyperbolic",
            "double-helix",
            "flat",
            "file:x.npy",
            "file:d/e f.npy",
        ] {
            assert_eq!(s.parse::<LensSpec>().unwrap().to_string(), s);
        }
        let e = "fresnel".parse::<LensSpec>().unwrap_err();
        assert!(e.contains("flat"), "{e}");
    }
}

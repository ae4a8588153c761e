//! Metasurface phase profiles sampled on an [`ApertureGrid`]: hyperbolic lens, double-helix lens
//! (zone construction), free-form map and pillar-quantized realization.

use crate::error::{OpticsError, Result, positive};
use crate::grid::ApertureGrid;
use faer::Mat;
use nanoeye_metalib::PillarLibrary;
use std::f64::consts::{PI, TAU};

/// A metasurface sampled on an aperture grid: phase delay φ (rad) and field-amplitude
/// transmission a (dimensionless, 1 for a lossless phase-only surface) per sample. The pupil
/// (circular aperture) is applied by the PSF model, not stored here.
#[derive(Clone, Debug)]
pub struct PhaseMap {
    /// The grid the maps are sampled on.
    pub grid: ApertureGrid,
    /// Phase delay φ (rad), n×n, rows along y.
    pub phase_rad: Mat<f64>,
    /// Field-amplitude transmission a (dimensionless), n×n.
    pub amplitude: Mat<f64>,
}

impl PhaseMap {
    /// Phase-only map (a ≡ 1); fails when the phase is not n×n for the grid or not finite.
    pub fn phase_only(grid: ApertureGrid, phase_rad: Mat<f64>) -> Result<Self> {
        let n = grid.n;
        Self::new(grid, phase_rad, Mat::from_fn(n, n, |_, _| 1.0))
    }

    /// Map from phase (rad) and amplitude; validates shapes and finiteness (amplitude ≥ 0).
    pub fn new(grid: ApertureGrid, phase_rad: Mat<f64>, amplitude: Mat<f64>) -> Result<Self> {
        let n = grid.n;
        for (name, m) in [("phase_rad", &phase_rad), ("amplitude", &amplitude)] {
            if m.nrows() != n || m.ncols() != n {
                return Err(OpticsError::Shape(format!(
                    "{name} is {}×{}, the aperture grid is {n}×{n}",
                    m.nrows(),
                    m.ncols()
                )));
            }
        }
        for j in 0..n {
            for i in 0..n {
                let (p, a) = (phase_rad[(i, j)], amplitude[(i, j)]);
                if !p.is_finite() {
                    return Err(OpticsError::param(
                        "phase_rad",
                        format!("non-finite at ({i},{j})"),
                    ));
                }
                if !(a.is_finite() && a >= 0.0) {
                    return Err(OpticsError::param(
                        "amplitude",
                        format!("must be finite and ≥ 0, got {a} at ({i},{j})"),
                    ));
                }
            }
        }
        Ok(Self {
            grid,
            phase_rad,
            amplitude,
        })
    }
}

/// Something that yields a metasurface [`PhaseMap`] on a given aperture grid.
pub trait PhaseProfile: Send + Sync {
    /// Samples the profile on `grid`.
    fn phase_map(&self, grid: &ApertureGrid) -> Result<PhaseMap>;
}

/// Ideal (hyperbolic) lens imaging an on-axis point at `object_distance_m` onto the sensor at
/// `image_distance_m`: φ(ρ) = −k(√(ρ²+z_f²) − z_f) − k(√(ρ²+s²) − s), exact for that conjugate pair.
#[derive(Clone, Copy, Debug)]
pub struct Hyperbolic {
    /// Design wavelength λ (m).
    pub wavelength_m: f64,
    /// Object distance in focus z_f (m).
    pub object_distance_m: f64,
    /// Lens-to-sensor distance s (m).
    pub image_distance_m: f64,
}

impl Default for Hyperbolic {
    /// λ = 940 nm, z_f = 25 mm, s = 2 mm (the default rig).
    fn default() -> Self {
        Self {
            wavelength_m: 940e-9,
            object_distance_m: 25e-3,
            image_distance_m: 2e-3,
        }
    }
}

/// k(√(ρ²+z²) − z) without cancellation (rad).
#[inline]
pub(crate) fn sag_phase(k: f64, rho2: f64, z: f64) -> f64 {
    k * rho2 / ((rho2 + z * z).sqrt() + z)
}

impl Hyperbolic {
    fn validate(&self) -> Result<f64> {
        let lam = positive("wavelength_m", self.wavelength_m)?;
        positive("object_distance_m", self.object_distance_m)?;
        positive("image_distance_m", self.image_distance_m)?;
        Ok(TAU / lam)
    }

    /// Phase (rad) at radius² `rho2` (m²).
    fn phase_at(&self, k: f64, rho2: f64) -> f64 {
        -sag_phase(k, rho2, self.object_distance_m) - sag_phase(k, rho2, self.image_distance_m)
    }
}

impl PhaseProfile for Hyperbolic {
    fn phase_map(&self, grid: &ApertureGrid) -> Result<PhaseMap> {
        let k = self.validate()?;
        let phase = Mat::from_fn(grid.n, grid.n, |i, j| {
            let (y, x) = (grid.coord(i), grid.coord(j));
            self.phase_at(k, x * x + y * y)
        });
        PhaseMap::phase_only(*grid, phase)
    }
}

/// Double-helix lens by the zone construction (Prasad 2013): a hyperbolic lens focused at
/// `focus_object_distance_m` plus `zones` annular zones of equal area, zone l (l = 1…L) carrying
/// the vortex phase (2l − 1)·ϑ. Neighbouring zones differ in charge by 2, so the PSF has two
/// lobes; defocus shifts the zones' mean quadratic phase by 2π W020/(λL) per zone, which turns
/// the lobe pair by −π W020/(λ L): about π·ΔW020/(λL) over a depth range.
#[derive(Clone, Copy, Debug)]
pub struct DoubleHelix {
    /// Underlying focusing lens (its `object_distance_m` is the mid-range focus).
    pub lens: Hyperbolic,
    /// Number of annular zones L (≥ 2).
    pub zones: usize,
}

impl Default for DoubleHelix {
    /// Focus at the harmonic mid-point of 17–26 mm (1/z_c = (1/17 + 1/26)/2 mm⁻¹ → 20.56 mm),
    /// L = 4 zones: W020 spans ±1.35 λ over 17–26 mm for D = 1 mm, a total turn of ≈ 0.68π.
    fn default() -> Self {
        let zc = 2.0 / (1.0 / 17e-3 + 1.0 / 26e-3);
        Self {
            lens: Hyperbolic {
                object_distance_m: zc,
                ..Hyperbolic::default()
            },
            zones: 4,
        }
    }
}

impl PhaseProfile for DoubleHelix {
    fn phase_map(&self, grid: &ApertureGrid) -> Result<PhaseMap> {
        let k = self.lens.validate()?;
        if self.zones < 2 || self.zones > 64 {
            return Err(OpticsError::param(
                "zones",
                format!("must be in 2..=64, got {}", self.zones),
            ));
        }
        let a2 = (grid.diameter_m * 0.5).powi(2);
        let l_f = self.zones as f64;
        let phase = Mat::from_fn(grid.n, grid.n, |i, j| {
            let (y, x) = (grid.coord(i), grid.coord(j));
            let rho2 = x * x + y * y;
            let zone = ((rho2 / a2 * l_f).floor() as usize).min(self.zones - 1) + 1;
            let charge = (2 * zone - 1) as f64;
            let theta = y.atan2(x);
            self.lens.phase_at(k, rho2) + (charge * theta).rem_euclid(TAU)
        });
        PhaseMap::phase_only(*grid, phase)
    }
}

/// Free-form phase map (rad) on a fixed grid, e.g. the co-designed lens read from NPY.
#[derive(Clone, Debug)]
pub struct FreeForm {
    /// The map; its grid must equal the grid it is asked for.
    pub map: PhaseMap,
}

impl PhaseProfile for FreeForm {
    fn phase_map(&self, grid: &ApertureGrid) -> Result<PhaseMap> {
        let g = &self.map.grid;
        if g.n != grid.n || (g.pitch_m - grid.pitch_m).abs() > 1e-12 * grid.pitch_m.max(1e-30) {
            return Err(OpticsError::Shape(format!(
                "free-form map is {n}×{n} at pitch {p} m, asked for {m}×{m} at {q} m (resample it first)",
                n = g.n,
                p = g.pitch_m,
                m = grid.n,
                q = grid.pitch_m
            )));
        }
        Ok(PhaseMap {
            grid: *grid,
            ..self.map.clone()
        })
    }
}

/// A target profile realized with the nearest pillar of a library: per sample, the target phase
/// (mod 2π) → diameter → realized phase arg t(d) and amplitude √τ(d). Each aperture sample is
/// treated as one pillar, so the grid pitch should equal the library's lattice pitch.
pub struct PillarQuantized<'a> {
    /// Target profile.
    pub target: &'a dyn PhaseProfile,
    /// Pillar library that realizes it.
    pub library: &'a dyn PillarLibrary,
}

impl PillarQuantized<'_> {
    /// Realized map together with the chosen diameter (m) of every sample.
    pub fn realize(&self, grid: &ApertureGrid) -> Result<(PhaseMap, Mat<f64>)> {
        let target = self.target.phase_map(grid)?;
        let n = grid.n;
        let mut diam = Mat::<f64>::zeros(n, n);
        let mut phase = Mat::<f64>::zeros(n, n);
        let mut amp = Mat::<f64>::zeros(n, n);
        for j in 0..n {
            for i in 0..n {
                let p = target.phase_rad[(i, j)].rem_euclid(TAU);
                let d = self.library.diameter_for_phase(p)?;
                let t = self.library.response(d)?;
                let tau = self.library.transmittance(d)?;
                if !(t.re.is_finite() && t.im.is_finite() && tau.is_finite() && tau >= 0.0) {
                    return Err(OpticsError::param(
                        "library",
                        format!("non-finite response at diameter {d} m"),
                    ));
                }
                diam[(i, j)] = d;
                phase[(i, j)] = t.arg();
                amp[(i, j)] = tau.sqrt() * target.amplitude[(i, j)];
            }
        }
        Ok((PhaseMap::new(*grid, phase, amp)?, diam))
    }
}

impl PhaseProfile for PillarQuantized<'_> {
    fn phase_map(&self, grid: &ApertureGrid) -> Result<PhaseMap> {
        Ok(self.realize(grid)?.0)
    }
}

/// Wraps a phase (rad) into (−π, π].
pub fn wrap_phase(p: f64) -> f64 {
    let w = (p + PI).rem_euclid(TAU) - PI;
    if w <= -PI { w + TAU } else { w }
}

//! Pillar libraries: phase → diameter and diameter → complex response maps.

use crate::error::MetalibError;

/// A tabulated nanopillar library at fixed height, pitch and wavelength (SI units throughout).
pub trait PillarLibrary: Send + Sync {
    /// Pillar height (m) and lattice pitch (m) the library was computed for.
    fn height_m(&self) -> f64;
    /// Lattice pitch (m).
    fn pitch_m(&self) -> f64;
    /// Wavelength (m).
    fn wavelength_m(&self) -> f64;
    /// Usable diameter range (m), inclusive.
    fn diameter_range_m(&self) -> (f64, f64);
    /// Diameter (m) whose phase is closest to `phase_rad` (taken modulo 2π onto the library's covered range).
    fn diameter_for_phase(&self, phase_rad: f64) -> Result<f64, MetalibError>;
    /// Complex zero-order transmission coefficient t of a pillar of diameter `diameter_m` (m); arg t is the phase, |t|^2 scaled by the media gives τ.
    fn response(&self, diameter_m: f64) -> Result<num_complex::Complex64, MetalibError>;
    /// Power transmittance τ at `diameter_m`.
    fn transmittance(&self, diameter_m: f64) -> Result<f64, MetalibError>;
}

use num_complex::Complex64;
use std::f64::consts::PI;

/// A library tabulated on ascending diameters with strictly monotonic unwrapped phase;
/// piecewise-linear (hence monotone) interpolation in diameter for phase and |t|.
#[derive(Debug, Clone, PartialEq)]
pub struct TabulatedLibrary {
    height_m: f64,
    pitch_m: f64,
    wavelength_m: f64,
    diameters_m: Vec<f64>,
    phase_unwrapped: Vec<f64>,
    amplitude: Vec<f64>,
    /// τ / |t|² (= Re n_sub / n_sup), so τ = tau_per_t2·|t|².
    tau_per_t2: f64,
}

/// Largest |phase| (rad) a library row may hold: a cell's phase spans a few 2π.
pub const MAX_LIBRARY_PHASE_RAD: f64 = 1e3;

impl TabulatedLibrary {
    /// Builds a library from (diameter m, phase rad, |t|) samples; the phase is unwrapped
    /// along d and must then be strictly monotonic; diameters strictly ascending.
    pub fn new(
        height_m: f64,
        pitch_m: f64,
        wavelength_m: f64,
        diameters_m: Vec<f64>,
        phase_rad: &[f64],
        amplitude: Vec<f64>,
        tau_per_t2: f64,
    ) -> Result<Self, MetalibError> {
        for (name, v) in [
            ("height", height_m),
            ("pitch", pitch_m),
            ("wavelength", wavelength_m),
            ("tau_per_t2", tau_per_t2),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(MetalibError::param(
                    name,
                    format!("must be finite and > 0, got {v}"),
                ));
            }
        }
        let n = diameters_m.len();
        if n < 2 || phase_rad.len() != n || amplitude.len() != n {
            return Err(MetalibError::InvalidData(format!(
                "need >= 2 samples of equal length (diameters {n}, phases {}, amplitudes {})",
                phase_rad.len(),
                amplitude.len()
            )));
        }
        if diameters_m
            .iter()
            .chain(phase_rad)
            .chain(&amplitude)
            .any(|v| !v.is_finite())
        {
            return Err(MetalibError::InvalidData("non-finite sample".into()));
        }
        if diameters_m.windows(2).any(|w| w[1] <= w[0]) || diameters_m[0] < 0.0 {
            return Err(MetalibError::InvalidData(
                "diameters must be >= 0 and strictly ascending".into(),
            ));
        }
        if amplitude.iter().any(|a| *a < 0.0) {
            return Err(MetalibError::InvalidData("negative amplitude".into()));
        }
        let uw = crate::select::unwrap(phase_rad);
        let dir = (uw[1] - uw[0]).signum();
        if uw.windows(2).any(|w| (w[1] - w[0]) * dir <= 0.0) {
            return Err(MetalibError::InvalidData(
                "unwrapped phase is not strictly monotonic in diameter".into(),
            ));
        }
        Ok(Self {
            height_m,
            pitch_m,
            wavelength_m,
            diameters_m,
            phase_unwrapped: uw,
            amplitude,
            tau_per_t2,
        })
    }

    /// Library from a user CSV with header-less or headed rows `diameter_nm,phase_rad,transmittance`;
    /// |t| = sqrt(τ / tau_per_t2).
    pub fn from_csv(
        text: &str,
        height_m: f64,
        pitch_m: f64,
        wavelength_m: f64,
        tau_per_t2: f64,
    ) -> Result<Self, MetalibError> {
        let (mut d, mut p, mut a) = (Vec::new(), Vec::new(), Vec::new());
        for (ln, line) in text.lines().enumerate() {
            let line = line.trim();
            if line.is_empty() || line.starts_with('#') {
                continue;
            }
            let f: Vec<&str> = line.split(',').map(str::trim).collect();
            let parsed: Result<Vec<f64>, _> = f.iter().map(|x| x.parse::<f64>()).collect();
            match parsed {
                Ok(v) if v.len() == 3 => {
                    // Physical ranges: 1e308 rad gave a coverage of 1e308 rad, diameters of
                    // 1e-308 nm a blueprint of empty pillars, and τ = 2 a cell with gain.
                    let bad = if v[2].is_nan() || v[2] < 0.0 || v[2] > 1.0 + 1e-9 {
                        Some("transmittance must lie in [0, 1] (a passive cell)")
                    } else if v[1].is_nan() || v[1].abs() > MAX_LIBRARY_PHASE_RAD {
                        Some("|phase_rad| must be at most 1000 rad")
                    } else if !(v[0] == 0.0 || (1.0..=1e6).contains(&v[0])) {
                        Some("diameter_nm must be 0 (no pillar) or lie in [1, 1e6] nm")
                    } else {
                        None
                    };
                    if let Some(why) = bad {
                        return Err(MetalibError::InvalidData(format!("line {}: {why}", ln + 1)));
                    }
                    d.push(v[0] * 1e-9);
                    p.push(v[1]);
                    a.push((v[2] / tau_per_t2).sqrt());
                }
                // The header, as documented: another first line (`a,b,c`) is not skipped.
                _ if ln == 0 && f.len() == 3 && f[0].to_ascii_lowercase().contains("diameter") => {
                    continue;
                }
                _ => {
                    return Err(MetalibError::InvalidData(format!(
                        "line {}: expected `diameter_nm,phase_rad,transmittance`",
                        ln + 1
                    )));
                }
            }
        }
        Self::new(height_m, pitch_m, wavelength_m, d, &p, a, tau_per_t2)
    }

    /// Library from one (height, pitch) slice of a sweep, restricted to the usable run.
    pub fn from_sweep(
        data: &crate::sweep::SweepData,
        height_m: f64,
        pitch_m: f64,
        criteria: &crate::select::Criteria,
    ) -> Result<(Self, crate::select::PairSelection), MetalibError> {
        let find = |v: &[f64], x: f64, name: &'static str| {
            v.iter()
                .position(|y| (y - x).abs() <= 1e-6 * x.abs().max(1e-12))
                .ok_or_else(|| {
                    MetalibError::OutOfRange(format!("{name} {x} m is not on the sweep grid"))
                })
        };
        let ih = find(&data.heights_m, height_m, "height")?;
        let is = find(&data.pitches_m, pitch_m, "pitch")?;
        let nf = data.fractions.len();
        let base = data.idx(ih, is, 0);
        let d: Vec<f64> = data.fractions.iter().map(|f| f * pitch_m).collect();
        let sel = crate::select::select_curve(
            height_m,
            pitch_m,
            &d,
            &data.phase[base..base + nf],
            &data.transmittance[base..base + nf],
            criteria,
        );
        let (s, e) = sel.run.ok_or_else(|| {
            MetalibError::OutOfRange("no usable diameters at this (height, pitch)".into())
        })?;
        let mut amp = Vec::new();
        let mut tau_per_t2 = f64::NAN;
        for j in s..=e {
            let t = Complex64::new(data.t_re[base + j], data.t_im[base + j]);
            amp.push(t.norm());
            if t.norm_sqr() > 0.0 && tau_per_t2.is_nan() {
                tau_per_t2 = data.transmittance[base + j] / t.norm_sqr();
            }
        }
        let lib = Self::new(
            height_m,
            pitch_m,
            data.manifest.config.wavelength_m,
            d[s..=e].to_vec(),
            &data.phase[base + s..=base + e],
            amp,
            tau_per_t2,
        )?;
        Ok((lib, sel))
    }

    /// Unwrapped phase span covered (rad).
    pub fn coverage_rad(&self) -> f64 {
        (self.phase_unwrapped[self.phase_unwrapped.len() - 1] - self.phase_unwrapped[0]).abs()
    }

    fn check_diameter(&self, d: f64) -> Result<(), MetalibError> {
        let (lo, hi) = self.diameter_range_m();
        if !d.is_finite() {
            return Err(MetalibError::param("diameter", "must be finite"));
        }
        if d < lo - 1e-15 || d > hi + 1e-15 {
            return Err(MetalibError::OutOfRange(format!(
                "diameter {d} m outside [{lo}, {hi}] m"
            )));
        }
        Ok(())
    }

    /// Segment index and weight for diameter d (assumed in range).
    fn locate(&self, d: f64) -> (usize, f64) {
        let ds = &self.diameters_m;
        let i = ds.partition_point(|&x| x <= d).clamp(1, ds.len() - 1) - 1;
        let w = ((d - ds[i]) / (ds[i + 1] - ds[i])).clamp(0.0, 1.0);
        (i, w)
    }

    /// Unwrapped phase (rad) at diameter d by linear interpolation.
    pub fn phase_at(&self, d: f64) -> Result<f64, MetalibError> {
        self.check_diameter(d)?;
        let (i, w) = self.locate(d);
        Ok(self.phase_unwrapped[i] * (1.0 - w) + self.phase_unwrapped[i + 1] * w)
    }
}

impl PillarLibrary for TabulatedLibrary {
    fn height_m(&self) -> f64 {
        self.height_m
    }
    fn pitch_m(&self) -> f64 {
        self.pitch_m
    }
    fn wavelength_m(&self) -> f64 {
        self.wavelength_m
    }
    fn diameter_range_m(&self) -> (f64, f64) {
        (
            self.diameters_m[0],
            self.diameters_m[self.diameters_m.len() - 1],
        )
    }

    fn diameter_for_phase(&self, phase_rad: f64) -> Result<f64, MetalibError> {
        if !phase_rad.is_finite() {
            return Err(MetalibError::param("phase", "must be finite"));
        }
        let p = &self.phase_unwrapped;
        let n = p.len();
        let (lo, hi) = if p[0] < p[n - 1] {
            (p[0], p[n - 1])
        } else {
            (p[n - 1], p[0])
        };
        // Bring the target onto [lo, lo + 2π).
        let target = lo + (phase_rad - lo).rem_euclid(2.0 * PI);
        let target = if target > hi {
            // In the uncovered gap: snap to the circularly nearer end.
            let to_hi = target - hi;
            let to_lo = lo + 2.0 * PI - target;
            if to_hi <= to_lo { hi } else { lo }
        } else {
            target
        };
        // Monotone piecewise-linear inverse.
        let asc = p[0] < p[n - 1];
        let k = if asc {
            p.partition_point(|&x| x <= target)
        } else {
            p.partition_point(|&x| x >= target)
        }
        .clamp(1, n - 1)
            - 1;
        let w = ((target - p[k]) / (p[k + 1] - p[k])).clamp(0.0, 1.0);
        Ok(self.diameters_m[k] * (1.0 - w) + self.diameters_m[k + 1] * w)
    }

    fn response(&self, diameter_m: f64) -> Result<Complex64, MetalibError> {
        self.check_diameter(diameter_m)?;
        let (i, w) = self.locate(diameter_m);
        let a = self.amplitude[i] * (1.0 - w) + self.amplitude[i + 1] * w;
        let ph = self.phase_unwrapped[i] * (1.0 - w) + self.phase_unwrapped[i + 1] * w;
        Ok(Complex64::from_polar(a, ph))
    }

    fn transmittance(&self, diameter_m: f64) -> Result<f64, MetalibError> {
        Ok(self.tau_per_t2 * self.response(diameter_m)?.norm_sqr())
    }
}

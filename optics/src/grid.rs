//! The aperture sampling grid: a square grid of pitch Δ centred on the optical axis that covers a
//! circular aperture of diameter D.

use crate::error::{OpticsError, Result, positive};
use faer::Mat;

/// Square sampling grid over a circular aperture (metres). Sample (r, c) sits at
/// x = (c − (n−1)/2)·Δ, y = (r − (n−1)/2)·Δ; rows run along y, columns along x.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ApertureGrid {
    /// Samples per side.
    pub n: usize,
    /// Sample pitch Δ (m).
    pub pitch_m: f64,
    /// Aperture diameter D (m).
    pub diameter_m: f64,
}

impl ApertureGrid {
    /// Grid of pitch `pitch_m` just covering an aperture of diameter `diameter_m` (n = ⌈D/Δ⌉).
    pub fn new(diameter_m: f64, pitch_m: f64) -> Result<Self> {
        positive("diameter_m", diameter_m)?;
        positive("pitch_m", pitch_m)?;
        let n = (diameter_m / pitch_m - 1e-9).ceil().max(1.0);
        if n > 20_000.0 {
            return Err(OpticsError::param(
                "pitch_m",
                format!("{n} samples across the aperture is too many (max 20000)"),
            ));
        }
        Ok(Self {
            n: n as usize,
            pitch_m,
            diameter_m,
        })
    }

    /// Coordinate (m) of sample index `i` along either axis.
    #[inline]
    pub fn coord(&self, i: usize) -> f64 {
        (i as f64 - (self.n as f64 - 1.0) * 0.5) * self.pitch_m
    }

    /// Fraction of each sample's cell inside the aperture circle (anti-aliased edge: 8×8
    /// sub-samples where the cell straddles the rim), so the sampled pupil converges smoothly.
    pub fn aperture_weights(&self) -> Mat<f64> {
        let r = self.diameter_m * 0.5;
        let h = self.pitch_m * 0.5;
        let diag = h * std::f64::consts::SQRT_2;
        Mat::from_fn(self.n, self.n, |i, j| {
            let (y, x) = (self.coord(i), self.coord(j));
            let rho = x.hypot(y);
            if rho + diag <= r {
                1.0
            } else if rho - diag >= r {
                0.0
            } else {
                const S: usize = 8;
                let mut inside = 0usize;
                for a in 0..S {
                    for b in 0..S {
                        let yy = y - h + (a as f64 + 0.5) * self.pitch_m / S as f64;
                        let xx = x - h + (b as f64 + 0.5) * self.pitch_m / S as f64;
                        if xx * xx + yy * yy <= r * r {
                            inside += 1;
                        }
                    }
                }
                inside as f64 / (S * S) as f64
            }
        })
    }
}

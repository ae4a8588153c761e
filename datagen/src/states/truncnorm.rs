//! TRUNCNORM(μ, σ, l, u): the normal distribution restricted to [l, u] and renormalized.
//!
//! Sampling is exact rejection sampling (Robert 1995, "Simulation of truncated normal
//! variables", Statistics and Computing 5:121–125): a normal, uniform or translated-exponential
//! proposal depending on where [l, u] lies, so bounds many σ into a tail cost no precision
//! (no CDF inversion, no erfc underflow) and acceptance stays bounded away from zero.

use rand::Rng;
use rand_distr::{Distribution, StandardNormal};
use std::f64::consts::{PI, SQRT_2};

/// Invalid truncated-normal parameters.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("TRUNCNORM(μ={mu}, σ={sigma}, l={lo}, u={hi}): {reason}")]
pub struct TruncNormError {
    /// Mean of the parent normal.
    pub mu: f64,
    /// Standard deviation of the parent normal.
    pub sigma: f64,
    /// Lower bound.
    pub lo: f64,
    /// Upper bound.
    pub hi: f64,
    /// What is wrong.
    pub reason: &'static str,
}

/// A truncated normal distribution (parameters in the unit of the variable).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TruncNormal {
    mu: f64,
    sigma: f64,
    lo: f64,
    hi: f64,
    // Standardized bounds (l − μ)/σ, (u − μ)/σ.
    a: f64,
    b: f64,
}

impl TruncNormal {
    /// TRUNCNORM(μ, σ, l, u); `l` may be −∞ and `u` +∞, σ > 0, l < u.
    pub fn new(mu: f64, sigma: f64, lo: f64, hi: f64) -> Result<Self, TruncNormError> {
        let err = |reason| TruncNormError {
            mu,
            sigma,
            lo,
            hi,
            reason,
        };
        if !(mu.is_finite() && sigma.is_finite()) {
            return Err(err("μ and σ must be finite"));
        }
        if sigma.is_nan() || sigma <= 0.0 {
            return Err(err("σ must be positive"));
        }
        if lo.is_nan() || hi.is_nan() || lo >= hi || lo == f64::INFINITY || hi == f64::NEG_INFINITY
        {
            return Err(err("bounds must satisfy l < u"));
        }
        let (a, b) = ((lo - mu) / sigma, (hi - mu) / sigma);
        if a.is_nan() || b.is_nan() || a >= b {
            return Err(err("bounds collapse after standardization"));
        }
        Ok(TruncNormal {
            mu,
            sigma,
            lo,
            hi,
            a,
            b,
        })
    }

    /// The (lower, upper) bounds.
    pub fn bounds(&self) -> (f64, f64) {
        (self.lo, self.hi)
    }

    /// Analytic mean μ + σ (φ(a) − φ(b)) / Z, Z = Φ(b) − Φ(a), evaluated on the side of the
    /// mean where Z has no cancellation.
    pub fn mean(&self) -> f64 {
        let (r, _) = self.ratios();
        self.mu + self.sigma * r
    }

    /// Analytic variance σ² [1 + (a φ(a) − b φ(b))/Z − ((φ(a) − φ(b))/Z)²].
    pub fn variance(&self) -> f64 {
        let (r, s) = self.ratios();
        self.sigma * self.sigma * (1.0 + s - r * r)
    }

    // ((φ(a) − φ(b))/Z, (a φ(a) − b φ(b))/Z) computed on the tail side so Z keeps its digits.
    fn ratios(&self) -> (f64, f64) {
        let (a, b, flip) = if self.a >= 0.0 {
            (self.a, self.b, false)
        } else if self.b <= 0.0 {
            (-self.b, -self.a, true)
        } else {
            (self.a, self.b, false)
        };
        let phi = |x: f64| {
            if x.is_infinite() {
                0.0
            } else {
                (-0.5 * x * x).exp() / (2.0 * PI).sqrt()
            }
        };
        let xphi = |x: f64| if x.is_infinite() { 0.0 } else { x * phi(x) };
        let q = |x: f64| 0.5 * statrs::function::erf::erfc(x / SQRT_2); // upper tail 1 − Φ(x)
        let z = if a >= 0.0 {
            q(a) - q(b)
        } else {
            1.0 - q(-a) - q(b)
        };
        let r = (phi(a) - phi(b)) / z;
        let s = (xphi(a) - xphi(b)) / z;
        if flip { (-r, s) } else { (r, s) }
    }

    /// One draw.
    pub fn sample<R: Rng + ?Sized>(&self, rng: &mut R) -> f64 {
        let z = if self.a >= 0.0 {
            right_tail(self.a, self.b, rng)
        } else if self.b <= 0.0 {
            -right_tail(-self.b, -self.a, rng)
        } else {
            central(self.a, self.b, rng)
        };
        (self.mu + self.sigma * z).clamp(self.lo, self.hi)
    }
}

impl Distribution<f64> for TruncNormal {
    fn sample<R: Rng + ?Sized>(&self, rng: &mut R) -> f64 {
        TruncNormal::sample(self, rng)
    }
}

/// Uniform on (0, 1].
fn open_unit<R: Rng + ?Sized>(rng: &mut R) -> f64 {
    1.0 - rng.random::<f64>()
}

/// Standard normal truncated to [a, b] with a < 0 < b.
fn central<R: Rng + ?Sized>(a: f64, b: f64, rng: &mut R) -> f64 {
    if b - a >= (2.0 * PI).sqrt() {
        // Acceptance Φ(b) − Φ(a) ≥ ~0.49 for intervals this wide around 0.
        loop {
            let z: f64 = StandardNormal.sample(rng);
            if (a..=b).contains(&z) {
                return z;
            }
        }
    }
    loop {
        let z = a + (b - a) * rng.random::<f64>();
        if rng.random::<f64>() <= (-0.5 * z * z).exp() {
            return z;
        }
    }
}

/// Standard normal truncated to [a, b] with 0 ≤ a < b ≤ ∞.
fn right_tail<R: Rng + ?Sized>(a: f64, b: f64, rng: &mut R) -> f64 {
    let root = (a * a + 4.0).sqrt();
    let lambda = 0.5 * (a + root);
    // Robert's switch: the uniform proposal beats the exponential one on short intervals.
    let uniform_width = (2.0 / (a + root)) * ((a * a - a * root) / 4.0 + 0.5).exp();
    if b - a <= uniform_width {
        loop {
            let z = a + (b - a) * rng.random::<f64>();
            // exp((a² − z²)/2) written as exp(−(z − a)(z + a)/2) to keep it exact for large a.
            if rng.random::<f64>() <= (-0.5 * (z - a) * (z + a)).exp() {
                return z;
            }
        }
    }
    loop {
        let z = a - open_unit(rng).ln() / lambda;
        if z > b {
            continue;
        }
        if rng.random::<f64>() <= (-0.5 * (z - lambda) * (z - lambda)).exp() {
            return z;
        }
    }
}

/// UNIFORM(l, u) for Table S3.
pub fn uniform<R: Rng + ?Sized>(lo: f64, hi: f64, rng: &mut R) -> f64 {
    lo + (hi - lo) * rng.random::<f64>()
}

//! Angular error between directions and summary statistics of error samples.

use crate::geom::{self, Vec3};
use serde::Serialize;

/// Angle (rad) between two non-zero vectors by atan2(|a × b|, a · b): accurate near 0 and π.
pub fn angular_error(a: Vec3, b: Vec3) -> f64 {
    geom::norm(geom::cross(a, b)).atan2(geom::dot(a, b))
}

/// Mean, median, 95th percentile and maximum of a sample (same unit as the sample).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Summary {
    /// Number of values.
    pub n: usize,
    /// Arithmetic mean.
    pub mean: f64,
    /// Median (50th percentile).
    pub median: f64,
    /// 95th percentile.
    pub p95: f64,
    /// Largest value.
    pub max: f64,
}

/// Percentile `q` ∈ [0, 1] of sorted values by linear interpolation between order statistics
/// (the "type 7" rule: position q·(n − 1)).
pub fn percentile_sorted(sorted: &[f64], q: f64) -> f64 {
    let pos = q.clamp(0.0, 1.0) * (sorted.len() - 1) as f64;
    let lo = pos.floor() as usize;
    let hi = (lo + 1).min(sorted.len() - 1);
    let t = pos - lo as f64;
    sorted[lo] + t * (sorted[hi] - sorted[lo])
}

impl Summary {
    /// Summary of the finite values of `values`; `None` when there are none.
    pub fn of(values: &[f64]) -> Option<Summary> {
        let mut v: Vec<f64> = values.iter().copied().filter(|x| x.is_finite()).collect();
        if v.is_empty() {
            return None;
        }
        v.sort_by(f64::total_cmp);
        let mean = v.iter().sum::<f64>() / v.len() as f64;
        Some(Summary {
            n: v.len(),
            mean,
            median: percentile_sorted(&v, 0.5),
            p95: percentile_sorted(&v, 0.95),
            max: v[v.len() - 1],
        })
    }

    /// The same summary with every statistic multiplied by `k` (e.g. rad → deg).
    pub fn scaled(self, k: f64) -> Summary {
        Summary {
            n: self.n,
            mean: self.mean * k,
            median: self.median * k,
            p95: self.p95 * k,
            max: self.max * k,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tiny_angles_are_resolved() {
        // acos(a·b) loses everything below ~1e-8 rad; atan2 keeps it.
        let a = [0.0, 0.0, 1.0];
        let t: f64 = 1e-12;
        let b = [t.sin(), 0.0, t.cos()];
        assert!((angular_error(a, b) - t).abs() < 1e-24);
        assert!((angular_error(a, [0.0, 0.0, -1.0]) - std::f64::consts::PI).abs() < 1e-15);
    }

    #[test]
    fn summary_of_uniform_grid() {
        let v: Vec<f64> = (0..=100).map(|i| i as f64).collect();
        let s = Summary::of(&v).unwrap();
        assert_eq!((s.mean, s.median, s.p95, s.max), (50.0, 50.0, 95.0, 100.0));
        assert!(Summary::of(&[f64::NAN]).is_none());
    }
}

//! Accuracy–compute Pareto fronts (B.6, Fig. 8): points (MACs, V) per lens, the front of
//! points no other point beats in both, and whether one lens's front dominates another's.

use serde::{Deserialize, Serialize};

/// One evaluated subnet.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Point {
    /// C_total (MACs).
    pub macs: u64,
    /// V (degrees; lower is better).
    pub v_deg: f64,
}

/// The Pareto front of `pts` (fewer MACs and lower V are better), sorted by MACs: each point
/// has a strictly lower V than every cheaper-or-equal point before it.
pub fn front(pts: &[Point]) -> Vec<Point> {
    let mut v: Vec<Point> = pts
        .iter()
        .filter(|p| p.v_deg.is_finite())
        .cloned()
        .collect();
    v.sort_by(|a, b| a.macs.cmp(&b.macs).then(a.v_deg.total_cmp(&b.v_deg)));
    let mut out: Vec<Point> = Vec::new();
    for p in v {
        if out.last().is_none_or(|l| p.v_deg < l.v_deg) {
            if out.last().is_some_and(|l| l.macs == p.macs) {
                out.pop();
            }
            out.push(p);
        }
    }
    out
}

/// True when every point of front `b` is weakly beaten (≤ MACs and ≤ V) by a point of front
/// `a`, and at least one strictly: `a` dominates `b`.
pub fn dominates(a: &[Point], b: &[Point]) -> bool {
    if a.is_empty() || b.is_empty() {
        return false;
    }
    let mut strict = false;
    for q in b {
        let best = a
            .iter()
            .filter(|p| p.macs <= q.macs)
            .map(|p| p.v_deg)
            .fold(f64::INFINITY, f64::min);
        if best > q.v_deg {
            return false;
        }
        if best < q.v_deg || a.iter().any(|p| p.macs < q.macs && p.v_deg <= q.v_deg) {
            strict = true;
        }
    }
    strict
}

#[cfg(test)]
mod tests {
    use super::*;

    fn p(macs: u64, v: f64) -> Point {
        Point { macs, v_deg: v }
    }

    #[test]
    fn front_keeps_only_undominated_points() {
        let pts = [
            p(10, 5.0),
            p(5, 9.0),
            p(20, 6.0),
            p(30, 2.0),
            p(10, 4.0),
            p(40, f64::NAN),
        ];
        assert_eq!(front(&pts), vec![p(5, 9.0), p(10, 4.0), p(30, 2.0)]);
        assert!(front(&[]).is_empty());
    }

    #[test]
    fn dominance_needs_every_point_beaten() {
        let a = [p(5, 8.0), p(10, 3.0)];
        let b = [p(6, 9.0), p(12, 4.0)];
        assert!(dominates(&a, &b));
        assert!(!dominates(&b, &a));
        assert!(!dominates(&a, &a));
        assert!(!dominates(&[p(5, 1.0)], &[p(4, 9.0)]), "nothing as cheap");
    }
}

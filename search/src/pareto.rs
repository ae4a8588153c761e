//! Accuracy–compute Pareto fronts (B.6, Fig. 8): points (MACs, V) per lens, the front of
//! points no other point beats in both, whether one lens's front dominates another's, and how
//! far those verdicts survive resampling the evaluation frames (a paired bootstrap).

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
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

/// One lens's subnets scored frame by frame: per subnet its MACs and its gaze error on every
/// evaluation frame (degrees; a failed frame counted as V counts it, 90°).
#[derive(Clone, Debug, PartialEq)]
pub struct LensFrames {
    /// C_total per subnet (MACs).
    pub macs: Vec<u64>,
    /// Per subnet, the error on each frame (degrees), the frames in the same order for every
    /// subnet and every lens.
    pub errors_deg: Vec<Vec<f64>>,
}

impl LensFrames {
    /// Per subnet, V: the mean of its frames' errors (degrees), summed as `evaluate_net` sums.
    pub fn points(&self) -> Vec<Point> {
        self.macs
            .iter()
            .zip(&self.errors_deg)
            .map(|(&macs, e)| Point {
                macs,
                v_deg: e.iter().sum::<f64>() / e.len() as f64,
            })
            .collect()
    }
}

/// One lens trained several times (other seeds) as one: per subnet and frame the mean of the
/// runs' errors, so each subnet's V is the mean of its runs' V, and per subnet the mean of the
/// runs' MACs, rounded (a learned pitch differs from run to run, and with it the MACs at the
/// resolution it gives). The training's randomness then averages out of the comparison
/// instead of deciding it; the runs must hold the same subnets on the same frames.
pub fn average_runs(runs: &[LensFrames]) -> Result<LensFrames, String> {
    let Some(first) = runs.first() else {
        return Err("no runs to average".into());
    };
    let (ns, nf) = (
        first.errors_deg.len(),
        first.errors_deg.first().map_or(0, Vec::len),
    );
    for (k, r) in runs.iter().enumerate() {
        if r.macs.len() != ns || r.errors_deg.len() != ns {
            return Err(format!(
                "run {k}: {} subnets ({} MAC counts), run 0 has {ns}",
                r.errors_deg.len(),
                r.macs.len()
            ));
        }
        if let Some(e) = r.errors_deg.iter().find(|e| e.len() != nf) {
            return Err(format!("run {k}: {} frames, run 0 has {nf}", e.len()));
        }
    }
    if runs.len() == 1 {
        return Ok(first.clone());
    }
    let n = runs.len() as f64;
    Ok(LensFrames {
        macs: (0..ns)
            .map(|s| (runs.iter().map(|r| r.macs[s] as f64).sum::<f64>() / n).round() as u64)
            .collect(),
        errors_deg: (0..ns)
            .map(|s| {
                (0..nf)
                    .map(|f| runs.iter().map(|r| r.errors_deg[s][f]).sum::<f64>() / n)
                    .collect()
            })
            .collect(),
    })
}

/// Per training seed i, the mean over subnets of V(a's run i) − V(b's run i) (degrees): lens
/// a's and lens b's runs paired by position, as `--runs` lists them. None unless both lenses
/// hold the same number of runs, each with the same number of subnets.
pub fn seed_differences(a: &[LensFrames], b: &[LensFrames]) -> Option<Vec<f64>> {
    if a.len() != b.len() {
        return None;
    }
    a.iter()
        .zip(b)
        .map(|(x, y)| {
            let (px, py) = (x.points(), y.points());
            (px.len() == py.len() && !px.is_empty()).then(|| {
                px.iter()
                    .zip(&py)
                    .map(|(p, q)| p.v_deg - q.v_deg)
                    .sum::<f64>()
                    / px.len() as f64
            })
        })
        .collect()
}

/// The mean of `d` (one value per training seed, degrees) with its Student's t central 90 %
/// interval, mean ± t₀.₉₅,ₙ₋₁·s/√n with s the sample standard deviation: how far the seeds
/// place the mean. None for fewer than two values, a value not finite, or an interval past
/// f64's range.
pub fn seed_interval(d: &[f64]) -> Option<Interval> {
    use statrs::distribution::{ContinuousCDF, StudentsT};
    let n = d.len();
    if n < 2 || d.iter().any(|v| !v.is_finite()) {
        return None;
    }
    // The sums run on d / 2^e with 2^e near the largest |d|, so that neither Σd nor the squares
    // overflow for finite values near f64::MAX (they gave ±∞ and NaN); scaling by a power of
    // two is exact, so values that stay normal once scaled get the unscaled formula's bits
    // (a subnormal one loses low bits; values below ~1e-154, whose squares underflowed to a
    // zero width before, now get their width).
    let top = d.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let e = if top > 0.0 {
        (top.log2().floor() as i64).clamp(-1022, 1023)
    } else {
        0
    };
    let scale = f64::from_bits(((e + 1023) as u64) << 52);
    let mean = d.iter().map(|v| v / scale).sum::<f64>() / n as f64;
    let var = d.iter().map(|v| (v / scale - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
    let t = StudentsT::new(0.0, 1.0, (n - 1) as f64)
        .ok()?
        .inverse_cdf(0.95);
    let half = t * (var / n as f64).sqrt();
    let (value, lo, hi) = (mean * scale, (mean - half) * scale, (mean + half) * scale);
    (value.is_finite() && lo.is_finite() && hi.is_finite()).then_some(Interval { value, lo, hi })
}

/// An estimate with its central 90 % bootstrap interval (degrees).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Interval {
    /// The estimate on the frames as given.
    pub value: f64,
    /// 5th percentile over the bootstrap draws.
    pub lo: f64,
    /// 95th percentile over the bootstrap draws.
    pub hi: f64,
}

/// What a paired bootstrap over the evaluation set's items says about the lenses (indices in
/// the order given to [`bootstrap`]).
#[derive(Clone, Debug, PartialEq)]
pub struct Bootstrap {
    /// Resamples drawn.
    pub draws: usize,
    /// Frames in the evaluation set.
    pub frames: usize,
    /// Clusters (items) drawn per resample.
    pub clusters: usize,
    /// Per lens, the median of V over its subnets.
    pub median_v: Vec<Interval>,
    /// `[a][b]`: the fraction of draws in which lens a's front dominates lens b's.
    pub dominates: Vec<Vec<f64>>,
    /// `[a][b]`: the mean over subnets of V_a − V_b, paired subnet by subnet (None where the
    /// two lenses do not hold the same number of subnets).
    pub mean_diff: Vec<Vec<Option<Interval>>>,
}

/// The `q` quantile of `v` (sorted in place), linearly interpolated between order statistics.
fn quantile(v: &mut [f64], q: f64) -> f64 {
    v.sort_by(f64::total_cmp);
    let x = q * (v.len() - 1) as f64;
    let (i, t) = (x.floor() as usize, x - x.floor());
    let j = (i + 1).min(v.len() - 1);
    v[i] + (v[j] - v[i]) * t
}

fn median(v: &[f64]) -> f64 {
    quantile(&mut v.to_vec(), 0.5)
}

/// A paired cluster bootstrap of the Pareto comparison over the evaluation set: frame f belongs
/// to cluster `clusters[f]` (an ambiguity item: its anchor, slip and gaze frames share an eye
/// and a subject, so they are not independent draws); each of `draws` resamples draws the
/// clusters with replacement (seeded by `seed`), the same clusters for every subnet of every
/// lens, and recomputes every V (the mean over the resampled frames), each lens's median V and
/// front, the fronts' dominance and the paired mean differences. It measures how much the
/// verdicts depend on which items the evaluation set happens to hold, not on the training's own
/// randomness.
pub fn bootstrap(
    lenses: &[LensFrames],
    clusters: &[usize],
    draws: usize,
    seed: u64,
) -> Result<Bootstrap, String> {
    if draws == 0 {
        return Err("draws: at least one resample".into());
    }
    let frames = lenses
        .first()
        .and_then(|l| l.errors_deg.first())
        .map_or(0, Vec::len);
    if frames == 0 {
        return Err("no frames to resample".into());
    }
    if clusters.len() != frames {
        return Err(format!(
            "{} cluster labels for {frames} frames",
            clusters.len()
        ));
    }
    // Clusters renumbered 0..n in order of first appearance; each one's frames.
    let mut index = std::collections::HashMap::new();
    let mut members: Vec<Vec<usize>> = Vec::new();
    for (f, &c) in clusters.iter().enumerate() {
        let k = *index.entry(c).or_insert_with(|| {
            members.push(Vec::new());
            members.len() - 1
        });
        members[k].push(f);
    }
    for (k, l) in lenses.iter().enumerate() {
        if l.macs.len() != l.errors_deg.len() || l.macs.is_empty() {
            return Err(format!(
                "lens {k}: {} MAC counts for {} subnets' errors",
                l.macs.len(),
                l.errors_deg.len()
            ));
        }
        if let Some(e) = l.errors_deg.iter().find(|e| e.len() != frames) {
            return Err(format!("lens {k}: {} frames, lens 0 has {frames}", e.len()));
        }
        // An angle between two directions: a stored error of 1e308 (an edited state) made the
        // means overflow and printed null with exit 0.
        if l.errors_deg
            .iter()
            .flatten()
            .any(|e| !(0.0..=180.0).contains(e))
        {
            return Err(format!(
                "lens {k}: a frame's error is not an angle in [0°, 180°]"
            ));
        }
    }
    let nl = lenses.len();
    let mean = |e: &[f64], w: &[u32]| -> f64 {
        let n: u32 = w.iter().sum();
        e.iter().zip(w).map(|(&x, &c)| x * c as f64).sum::<f64>() / n as f64
    };
    // The statistics of one weighting of the frames (multiplicities `w`).
    let stats = |w: &[u32]| {
        let pts: Vec<Vec<Point>> = lenses
            .iter()
            .map(|l| {
                l.macs
                    .iter()
                    .zip(&l.errors_deg)
                    .map(|(&macs, e)| Point {
                        macs,
                        v_deg: mean(e, w),
                    })
                    .collect()
            })
            .collect();
        let med: Vec<f64> = pts
            .iter()
            .map(|p| median(&p.iter().map(|q| q.v_deg).collect::<Vec<_>>()))
            .collect();
        let fronts: Vec<Vec<Point>> = pts.iter().map(|p| front(p)).collect();
        let mut dom = vec![vec![false; nl]; nl];
        let mut diff = vec![vec![None; nl]; nl];
        for a in 0..nl {
            for b in 0..nl {
                if a == b {
                    continue;
                }
                dom[a][b] = dominates(&fronts[a], &fronts[b]);
                if pts[a].len() == pts[b].len() {
                    let d: f64 = pts[a]
                        .iter()
                        .zip(&pts[b])
                        .map(|(p, q)| p.v_deg - q.v_deg)
                        .sum();
                    diff[a][b] = Some(d / pts[a].len() as f64);
                }
            }
        }
        (med, dom, diff)
    };
    let (med0, _, diff0) = stats(&vec![1; frames]);
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut w = vec![0u32; frames];
    let mut meds = vec![Vec::with_capacity(draws); nl];
    let mut diffs = vec![vec![Vec::with_capacity(draws); nl]; nl];
    let mut wins = vec![vec![0usize; nl]; nl];
    for _ in 0..draws {
        w.fill(0);
        for _ in 0..members.len() {
            for &f in &members[rng.random_range(0..members.len())] {
                w[f] += 1;
            }
        }
        let (med, dom, diff) = stats(&w);
        for a in 0..nl {
            meds[a].push(med[a]);
            for b in 0..nl {
                wins[a][b] += dom[a][b] as usize;
                if let Some(d) = diff[a][b] {
                    diffs[a][b].push(d);
                }
            }
        }
    }
    let interval = |value: f64, v: &mut Vec<f64>| Interval {
        value,
        lo: quantile(v, 0.05),
        hi: quantile(v, 0.95),
    };
    Ok(Bootstrap {
        draws,
        frames,
        clusters: members.len(),
        median_v: (0..nl).map(|a| interval(med0[a], &mut meds[a])).collect(),
        dominates: wins
            .iter()
            .map(|r| r.iter().map(|&n| n as f64 / draws as f64).collect())
            .collect(),
        mean_diff: (0..nl)
            .map(|a| {
                (0..nl)
                    .map(|b| diff0[a][b].map(|d| interval(d, &mut diffs[a][b])))
                    .collect()
            })
            .collect(),
    })
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

    fn lens(macs: &[u64], errors: Vec<Vec<f64>>) -> LensFrames {
        LensFrames {
            macs: macs.to_vec(),
            errors_deg: errors,
        }
    }

    /// Errors of three subnets on `f` frames, a pattern that differs between frames.
    fn pattern(f: usize, shift: f64) -> Vec<Vec<f64>> {
        (0..3)
            .map(|s| {
                (0..f)
                    .map(|i| 5.0 + shift + ((i * 7 + s * 3) % 11) as f64)
                    .collect()
            })
            .collect()
    }

    #[test]
    fn a_frame_error_that_is_no_angle_is_refused() {
        let macs = [10, 20, 30];
        let items: Vec<usize> = (0..12).map(|f| f / 3).collect();
        for bad in [1e308, -50.0, 180.5, f64::NAN] {
            let mut e = pattern(12, 0.0);
            e[1][4] = bad;
            let r = bootstrap(
                &[lens(&macs, pattern(12, 0.0)), lens(&macs, e)],
                &items,
                10,
                1,
            );
            assert!(r.unwrap_err().contains("lens 1"), "{bad}");
        }
    }

    #[test]
    fn bootstrap_of_a_lens_against_itself_and_a_shifted_copy() {
        let macs = [10, 20, 30];
        let a = lens(&macs, pattern(12, 0.0));
        let b = lens(&macs, pattern(12, 3.0));
        let items: Vec<usize> = (0..12).map(|f| f / 3).collect();
        let bs = bootstrap(&[a.clone(), a.clone(), b], &items, 300, 1).unwrap();
        // The same errors never dominate each other; paired differences are exactly 0.
        assert_eq!(bs.dominates[0][1], 0.0);
        assert_eq!(bs.dominates[1][0], 0.0);
        let d = bs.mean_diff[0][1].unwrap();
        assert_eq!((d.value, d.lo, d.hi), (0.0, 0.0, 0.0));
        // 3° lower on every frame: dominates in every draw, by exactly 3° whatever the draw.
        assert_eq!(bs.dominates[0][2], 1.0);
        assert_eq!(bs.dominates[2][0], 0.0);
        let d = bs.mean_diff[0][2].unwrap();
        for v in [d.value, d.lo, d.hi] {
            assert!((v + 3.0).abs() < 1e-12, "{d:?}");
        }
        let (m0, m2) = (bs.median_v[0], bs.median_v[2]);
        assert!((m2.value - m0.value - 3.0).abs() < 1e-12);
        assert!(m0.lo <= m0.value && m0.value <= m0.hi && m0.lo < m0.hi);
        assert_eq!(bs.clusters, 4);
        let again = bootstrap(
            &[a.clone(), a, lens(&macs, pattern(12, 3.0))],
            &items,
            300,
            1,
        );
        assert_eq!(bs, again.unwrap());
    }

    #[test]
    fn bootstrap_interval_of_a_mean_matches_the_central_limit() {
        // One subnet, F frames of errors with standard deviation σ: V's 90 % interval is
        // V ± 1.645 σ/√F for large F (σ computed from the sample, population form).
        let f = 400;
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let e: Vec<f64> = (0..f).map(|_| rng.random_range(0.0..20.0)).collect();
        let m = e.iter().sum::<f64>() / f as f64;
        let sd = (e.iter().map(|x| (x - m).powi(2)).sum::<f64>() / f as f64).sqrt();
        let singles: Vec<usize> = (0..f).collect();
        let bs = bootstrap(&[lens(&[1], vec![e.clone()])], &singles, 4000, 2).unwrap();
        let iv = bs.median_v[0];
        assert!((iv.value - m).abs() < 1e-12);
        let half = 1.645 * sd / (f as f64).sqrt();
        for (got, want) in [(iv.hi - iv.value, half), (iv.value - iv.lo, half)] {
            assert!((got / want - 1.0).abs() < 0.1, "{got} vs {want}");
        }
        // The same errors in clusters of four identical frames (an item's frames perfectly
        // correlated): F/4 independent draws, so an interval twice as wide, √4.
        let copies: Vec<f64> = e[..f / 4].iter().flat_map(|&x| [x; 4]).collect();
        let m4 = copies.iter().sum::<f64>() / f as f64;
        let sd4 = (copies.iter().map(|x| (x - m4).powi(2)).sum::<f64>() / f as f64).sqrt();
        let by_item: Vec<usize> = (0..f).map(|i| i / 4).collect();
        let iv = bootstrap(&[lens(&[1], vec![copies])], &by_item, 4000, 2)
            .unwrap()
            .median_v[0];
        let half = 1.645 * sd4 / ((f / 4) as f64).sqrt();
        for (got, want) in [(iv.hi - iv.value, half), (iv.value - iv.lo, half)] {
            assert!((got / want - 1.0).abs() < 0.15, "{got} vs {want}");
        }
    }

    /// Averaging runs is linear: each subnet's V is the mean of the runs' V, the MACs their
    /// rounded mean; one run is itself; runs with other subnets or frames are refused.
    #[test]
    fn seed_intervals_are_students_t_from_the_tables() {
        // t₀.₉₅ with 2 and 1 degrees of freedom: 2.919986 and 6.313752 (standard tables).
        let i = seed_interval(&[-1.0, 0.0, 1.0]).unwrap();
        let half = 2.919986 / 3f64.sqrt();
        assert!(
            i.value.abs() < 1e-15 && (i.hi - half).abs() < 1e-6 && (i.lo + half).abs() < 1e-6,
            "{i:?}"
        );
        let i = seed_interval(&[0.0, 2.0]).unwrap();
        assert!(
            (i.value - 1.0).abs() < 1e-15 && (i.hi - 1.0 - 6.313752).abs() < 1e-6,
            "{i:?}"
        );
        assert!((i.value - i.lo - (i.hi - i.value)).abs() < 1e-12);
        // Equal seeds: no spread, the interval is the point.
        let i = seed_interval(&[0.5; 4]).unwrap();
        assert_eq!((i.lo, i.value, i.hi), (0.5, 0.5, 0.5));
        assert!(seed_interval(&[1.0]).is_none());
        assert!(seed_interval(&[]).is_none());
        assert!(seed_interval(&[1.0, f64::NAN]).is_none());
    }

    #[test]
    fn averaged_runs_have_the_mean_of_their_v() {
        let a = lens(&[100, 200, 301], pattern(5, 0.0));
        let b = lens(&[102, 200, 300], pattern(5, 3.0));
        let c = lens(&[104, 200, 300], pattern(5, -1.5));
        let m = average_runs(&[a.clone(), b.clone(), c.clone()]).unwrap();
        assert_eq!(m.macs, vec![102, 200, 300]);
        let (pa, pb, pc, pm) = (a.points(), b.points(), c.points(), m.points());
        for s in 0..3 {
            let want = (pa[s].v_deg + pb[s].v_deg + pc[s].v_deg) / 3.0;
            assert!(
                (pm[s].v_deg - want).abs() < 1e-12,
                "{} vs {want}",
                pm[s].v_deg
            );
            // 0 + 3 − 1.5 over three runs: 0.5° above run a on every subnet.
            assert!((pm[s].v_deg - pa[s].v_deg - 0.5).abs() < 1e-12);
        }
        assert_eq!(average_runs(std::slice::from_ref(&a)).unwrap(), a);
        assert!(average_runs(&[]).is_err());
        let fewer = lens(&[100, 200], pattern(5, 0.0)[..2].to_vec());
        assert!(
            average_runs(&[a.clone(), fewer])
                .unwrap_err()
                .contains("subnets")
        );
        let short = lens(&[100, 200, 301], pattern(4, 0.0));
        assert!(
            average_runs(&[a.clone(), short])
                .unwrap_err()
                .contains("frames")
        );
        // Per seed, the paired differences: b − a is +3 on every subnet, c − a −1.5.
        let d = seed_differences(&[b.clone(), c.clone()], &[a.clone(), a.clone()]).unwrap();
        assert!(
            (d[0] - 3.0).abs() < 1e-12 && (d[1] + 1.5).abs() < 1e-12,
            "{d:?}"
        );
        assert!(seed_differences(&[b, c], std::slice::from_ref(&a)).is_none());
    }

    #[test]
    fn bootstrap_refuses_what_it_cannot_resample() {
        let a = lens(&[1, 2], pattern(4, 0.0)[..2].to_vec());
        let c = [0, 0, 1, 1];
        assert!(bootstrap(std::slice::from_ref(&a), &c, 10, 0).is_ok());
        assert!(bootstrap(std::slice::from_ref(&a), &c, 0, 0).is_err());
        assert!(bootstrap(std::slice::from_ref(&a), &c[..3], 10, 0).is_err());
        assert!(bootstrap(&[], &[], 10, 0).is_err());
        let five = lens(&[1, 2], pattern(5, 0.0)[..2].to_vec());
        assert!(bootstrap(&[a.clone(), five], &c, 10, 0).is_err());
        let short = lens(&[1], pattern(4, 0.0)[..2].to_vec());
        assert!(bootstrap(&[short], &c, 10, 0).is_err());
        let mut bad = a.clone();
        bad.errors_deg[1][2] = f64::NAN;
        assert!(bootstrap(&[a, bad], &c, 10, 0).is_err());
    }
}

/// Extreme but legal inputs: MACs over the whole u64 range, V over every finite magnitude (and
/// NaN and infinities where a caller might pass them), ties in both.
#[cfg(test)]
mod props {
    use super::*;
    use proptest::prelude::*;

    /// A V: mostly degrees, sometimes extreme, equal or not finite.
    fn v_deg() -> impl Strategy<Value = f64> {
        prop_oneof![
            6 => 0.0..180.0f64,
            2 => -1e300..1e300f64,
            1 => prop::sample::select(vec![0.0, 1.0, f64::MAX, -f64::MAX, f64::MIN_POSITIVE]),
            1 => prop::sample::select(vec![f64::NAN, f64::INFINITY, f64::NEG_INFINITY]),
        ]
    }

    fn points() -> impl Strategy<Value = Vec<Point>> {
        let macs = prop_oneof![0..64u64, any::<u64>()];
        prop::collection::vec((macs, v_deg()), 0..40).prop_map(|v| {
            v.into_iter()
                .map(|(macs, v_deg)| Point { macs, v_deg })
                .collect()
        })
    }

    /// `p` at most as costly and as wrong as `q`, and better in one.
    fn beats(p: &Point, q: &Point) -> bool {
        p.macs <= q.macs && p.v_deg <= q.v_deg && (p.macs < q.macs || p.v_deg < q.v_deg)
    }

    proptest! {
        /// The front holds finite input points, strictly cheaper and strictly better in
        /// turn; no input point beats one of them, and each finite input point is matched or
        /// beaten by one of them.
        #[test]
        fn the_front_is_what_nothing_beats(pts in points()) {
            let f = front(&pts);
            for w in f.windows(2) {
                prop_assert!(w[0].macs < w[1].macs && w[0].v_deg > w[1].v_deg, "{f:?}");
            }
            for q in &f {
                prop_assert!(q.v_deg.is_finite() && pts.contains(q));
                prop_assert!(!pts.iter().filter(|p| p.v_deg.is_finite()).any(|p| beats(p, q)));
            }
            for p in pts.iter().filter(|p| p.v_deg.is_finite()) {
                prop_assert!(f.iter().any(|q| q.macs <= p.macs && q.v_deg <= p.v_deg), "{p:?}");
            }
        }

        /// Dominance is irreflexive and antisymmetric, and a front shifted to a lower V at the
        /// same MACs dominates the original.
        #[test]
        fn dominance_is_a_strict_order(a in points(), b in points()) {
            let (fa, fb) = (front(&a), front(&b));
            prop_assert!(!dominates(&fa, &fa));
            prop_assert!(!(dominates(&fa, &fb) && dominates(&fb, &fa)));
            let lower: Vec<Point> = fa
                .iter()
                .map(|p| Point { macs: p.macs, v_deg: p.v_deg - 1.0f64.max(p.v_deg.abs() * 1e-9) })
                .collect();
            if !fa.is_empty() && lower.iter().all(|p| p.v_deg.is_finite()) {
                prop_assert!(dominates(&lower, &fa) && !dominates(&fa, &lower));
            }
        }

        /// Any finite seeds' differences up to 1e300 give a finite interval around their
        /// mean, the mean inside their range (to its round-off); near f64::MAX a finite
        /// interval or none, never ±∞ or NaN.
        #[test]
        fn the_seed_interval_is_finite_and_holds_the_mean(
            d in prop::collection::vec(-1e300..1e300f64, 0..12),
            edge in prop::collection::vec(
                prop::sample::select(vec![f64::MAX, -f64::MAX, 1e308, -1e308, 0.0]),
                2..6,
            ),
        ) {
            match seed_interval(&d) {
                None => prop_assert!(d.len() < 2),
                Some(i) => {
                    prop_assert!(i.value.is_finite() && i.lo.is_finite() && i.hi.is_finite());
                    prop_assert!(i.lo <= i.value && i.value <= i.hi, "{i:?}");
                    let (lo, hi) = d.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &v| {
                        (l.min(v), h.max(v))
                    });
                    // The mean of equal values can round an ulp past them.
                    let ulps = 4.0 * f64::EPSILON * lo.abs().max(hi.abs());
                    prop_assert!(
                        lo - ulps <= i.value && i.value <= hi + ulps,
                        "{i:?} outside {lo}..{hi}"
                    );
                }
            }
            if let Some(i) = seed_interval(&edge) {
                prop_assert!(i.value.is_finite() && i.lo.is_finite() && i.hi.is_finite());
            }
        }

        /// Differences of angles get the unscaled formula's bits: the scaling is exact.
        #[test]
        fn the_seed_interval_of_angles_is_the_plain_formulas(
            d in prop::collection::vec(-180.0..180.0f64, 2..12),
        ) {
            use statrs::distribution::{ContinuousCDF, StudentsT};
            let n = d.len() as f64;
            let mean = d.iter().sum::<f64>() / n;
            let var = d.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0);
            let t = StudentsT::new(0.0, 1.0, n - 1.0).unwrap().inverse_cdf(0.95);
            let half = t * (var / n).sqrt();
            let i = seed_interval(&d).unwrap();
            prop_assert_eq!(i.value.to_bits(), mean.to_bits());
            prop_assert_eq!(i.lo.to_bits(), (mean - half).to_bits());
            prop_assert_eq!(i.hi.to_bits(), (mean + half).to_bits());
        }
    }
}

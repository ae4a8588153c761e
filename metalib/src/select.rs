//! Candidate selection (Sec. D.1 criteria) over a sweep, and the Fig. S4 / S5 figures.

use crate::error::MetalibError;
use crate::plot::{Canvas, Curve, colormap, curves_svg, heatmap_svg};
use crate::sweep::SweepData;
use rayon::prelude::*;
use std::f64::consts::PI;
use std::path::Path;

/// Selection thresholds (SI units).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Criteria {
    /// Minimal zero-order transmittance of a kept diameter.
    pub min_transmittance: f64,
    /// Largest |dφ/dd| (rad/m) between neighbouring kept diameters.
    pub max_slope_rad_per_m: f64,
    /// Diameters within this distance (m) of a rejected one are dropped too.
    pub buffer_m: f64,
    /// Required phase coverage (rad).
    pub min_coverage_rad: f64,
    /// Injectivity: a usable run must be strictly monotonic in d (D.1). When false (only for
    /// the criteria-sensitivity study), runs are limited by τ, buffer and slope alone and
    /// their coverage is the span max φ − min φ.
    pub require_monotonic: bool,
}

impl Default for Criteria {
    fn default() -> Self {
        Self {
            min_transmittance: 0.90,
            max_slope_rad_per_m: 9.0_f64.to_radians() / 1e-9,
            buffer_m: 5e-9,
            min_coverage_rad: 2.0 * PI * 1.05,
            require_monotonic: true,
        }
    }
}

/// Outcome for one (height, pitch) pair.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PairSelection {
    /// Height (m).
    pub height_m: f64,
    /// Pitch (m).
    pub pitch_m: f64,
    /// Whether the best usable diameter run covers the required phase.
    pub viable: bool,
    /// Index range [first, last] (fraction indices) of the best run, if any.
    pub run: Option<(usize, usize)>,
    /// Smallest usable diameter (m) of the best run (NaN if none).
    pub diameter_min_m: f64,
    /// Largest usable diameter (m) of the best run (NaN if none).
    pub diameter_max_m: f64,
    /// Unwrapped phase span of the best run (rad).
    pub phase_coverage_rad: f64,
    /// Fig. S4a: the largest achievable minimum τ over a contiguous diameter window spanning 2π.
    pub min_transmittance_2pi: f64,
    /// Fig. S4b: height / smallest usable diameter of a viable pair (NaN otherwise).
    pub max_aspect_ratio: f64,
}

/// Unwraps a phase sequence so that neighbouring differences lie in (−π, π].
pub fn unwrap(phase: &[f64]) -> Vec<f64> {
    let mut out = Vec::with_capacity(phase.len());
    let mut offset = 0.0;
    for (i, &p) in phase.iter().enumerate() {
        if i > 0 {
            let prev = phase[i - 1];
            let d = p - prev;
            if d > PI {
                offset -= 2.0 * PI;
            } else if d <= -PI {
                offset += 2.0 * PI;
            }
        }
        out.push(p + offset);
    }
    out
}

/// `good` less every diameter within `buffer` (m) of one that is not good. Diameters in
/// ascending order take one pass and a difference array (each bad diameter's reach found by
/// bisection with the same comparison): a buffer around every bad cell of a 10⁵-diameter
/// curve took 10 s cell by cell, the quadratic loop kept for an unordered curve.
fn buffered(diameters_m: &[f64], good: &[bool], buffer: f64) -> Vec<bool> {
    let near = |a: f64, b: f64| (a - b).abs() <= buffer;
    let mut usable = good.to_vec();
    if !diameters_m.windows(2).all(|w| w[0] <= w[1]) {
        for j in (0..good.len()).filter(|&j| !good[j]) {
            for (u, &d) in usable.iter_mut().zip(diameters_m) {
                *u &= !near(d, diameters_m[j]);
            }
        }
        return usable;
    }
    // cover[i] counts the bad diameters whose reach starts at or before i, less those whose
    // reach ended before it.
    let mut cover = vec![0i64; good.len() + 1];
    for j in (0..good.len()).filter(|&j| !good[j]) {
        let dj = diameters_m[j];
        let lo = diameters_m.partition_point(|&d| d < dj && !near(d, dj));
        let hi = diameters_m.partition_point(|&d| d <= dj || near(d, dj));
        cover[lo] += 1;
        cover[hi] -= 1;
    }
    let mut depth = 0;
    for (u, c) in usable.iter_mut().zip(&cover) {
        depth += c;
        *u &= depth == 0;
    }
    usable
}

/// Fig. S4a's quantity: the largest minimum τ over a run of neighbouring diameters whose
/// unwrapped phase spans 2π (NaN where none does; NaN cells are passed over). Only each
/// start's shortest such run counts (a longer one's minimum is no larger), and the shortest
/// run's end never moves back as its start moves on: one pass with monotone queues for the
/// window's phase extremes and least τ. The search from every start took O(n²) on a curve
/// that never spans 2π (a lossy pillar over 10⁵ diameters ran past a minute).
fn min_tau_over_2pi(uw: &[f64], tau: &[f64]) -> f64 {
    use std::collections::VecDeque;
    /// Keeps the queue's values monotone for `keep(back, new)`; NaN values never enter.
    fn push(q: &mut VecDeque<usize>, v: &[f64], j: usize, keep: fn(f64, f64) -> bool) {
        if v[j].is_nan() {
            return;
        }
        while q.back().is_some_and(|&b| !keep(v[b], v[j])) {
            q.pop_back();
        }
        q.push_back(j);
    }
    let (mut lo, mut hi, mut least) = (VecDeque::new(), VecDeque::new(), VecDeque::new());
    let spans = |lo: &VecDeque<usize>, hi: &VecDeque<usize>| match (lo.front(), hi.front()) {
        (Some(&a), Some(&b)) => uw[b] - uw[a] >= 2.0 * PI,
        _ => false,
    };
    let mut best = f64::NAN;
    let mut j = 0;
    for i in 0..uw.len() {
        for q in [&mut lo, &mut hi, &mut least] {
            while q.front().is_some_and(|&f| f < i) {
                q.pop_front();
            }
        }
        while !spans(&lo, &hi) && j < uw.len() {
            push(&mut lo, uw, j, |b, x| b < x);
            push(&mut hi, uw, j, |b, x| b > x);
            push(&mut least, tau, j, |b, x| b < x);
            j += 1;
        }
        if !spans(&lo, &hi) {
            // The window reaches the last diameter: no later start spans 2π either.
            break;
        }
        if let Some(&m) = least.front() {
            best = if best.is_nan() {
                tau[m]
            } else {
                best.max(tau[m])
            };
        }
    }
    best
}

/// Applies the criteria to one diameter curve (diameters ascending, m).
pub fn select_curve(
    height_m: f64,
    pitch_m: f64,
    diameters_m: &[f64],
    phase: &[f64],
    tau: &[f64],
    c: &Criteria,
) -> PairSelection {
    let n = diameters_m.len();
    let uw = unwrap(phase);
    let good: Vec<bool> = (0..n)
        .map(|j| tau[j].is_finite() && phase[j].is_finite() && tau[j] >= c.min_transmittance)
        .collect();
    let usable = buffered(diameters_m, &good, c.buffer_m + 1e-15);
    // Runs of neighbouring usable diameters with one strict monotonic direction and bounded slope.
    let mut best: Option<(usize, usize, f64)> = None;
    let mut start = None::<usize>;
    let mut dir = 0.0_f64;
    // Span of the unwrapped phase over the run (for a monotonic run, |φ_e − φ_s|).
    let close = |s: usize, e: usize, best: &mut Option<(usize, usize, f64)>| {
        let (lo, hi) = uw[s..=e]
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| {
                (a.min(v), b.max(v))
            });
        let cov = hi - lo;
        if best.is_none_or(|b| cov > b.2) {
            *best = Some((s, e, cov));
        }
    };
    for i in 0..n {
        if !usable[i] {
            if let Some(s) = start.take() {
                close(s, i - 1, &mut best);
            }
            continue;
        }
        match start {
            None => {
                start = Some(i);
                dir = 0.0;
            }
            Some(s) => {
                let dphi = uw[i] - uw[i - 1];
                let dd = diameters_m[i] - diameters_m[i - 1];
                let slope_ok = (dphi / dd).abs() < c.max_slope_rad_per_m;
                let sign = dphi.signum();
                let mono_ok = !c.require_monotonic || (dphi != 0.0 && (dir == 0.0 || sign == dir));
                if slope_ok && mono_ok {
                    dir = sign;
                } else {
                    close(s, i - 1, &mut best);
                    // The new run starts at i−1 if that step alone is admissible, else at i.
                    if slope_ok && dphi != 0.0 {
                        start = Some(i - 1);
                        dir = sign;
                    } else {
                        start = Some(i);
                        dir = 0.0;
                    }
                }
            }
        }
    }
    if let Some(s) = start {
        close(s, n - 1, &mut best);
    }
    let min_tau_2pi = min_tau_over_2pi(&uw, tau);
    let (run, dmin, dmax, cov) = match best {
        Some((s, e, cov)) => (Some((s, e)), diameters_m[s], diameters_m[e], cov),
        None => (None, f64::NAN, f64::NAN, 0.0),
    };
    let viable = cov >= c.min_coverage_rad;
    PairSelection {
        height_m,
        pitch_m,
        viable,
        run,
        diameter_min_m: dmin,
        diameter_max_m: dmax,
        phase_coverage_rad: cov,
        min_transmittance_2pi: min_tau_2pi,
        max_aspect_ratio: if viable { height_m / dmin } else { f64::NAN },
    }
}

/// Selection for every (height, pitch) of a sweep, ordered `[height][pitch]`.
pub fn select_sweep(data: &SweepData, c: &Criteria) -> Vec<PairSelection> {
    let (nh, ns, nf) = (
        data.heights_m.len(),
        data.pitches_m.len(),
        data.fractions.len(),
    );
    (0..nh * ns)
        .into_par_iter()
        .map(|k| {
            let (ih, is) = (k / ns, k % ns);
            let s = data.pitches_m[is];
            let base = data.idx(ih, is, 0);
            let d: Vec<f64> = data.fractions.iter().map(|f| f * s).collect();
            select_curve(
                data.heights_m[ih],
                s,
                &d,
                &data.phase[base..base + nf],
                &data.transmittance[base..base + nf],
                c,
            )
        })
        .collect()
}

/// Heat map of `values` [height][pitch] (height increasing upwards), NaN drawn grey.
fn heatmap(
    values: &[f64],
    nh: usize,
    ns: usize,
    lo: f64,
    hi: f64,
    mark: Option<(usize, usize)>,
) -> Canvas {
    let px = 4;
    let mut c = Canvas::new(ns * px, nh * px);
    for ih in 0..nh {
        for is in 0..ns {
            let v = values[ih * ns + is];
            let rgb = if v.is_finite() {
                colormap(((v - lo) / (hi - lo)).clamp(0.0, 1.0))
            } else {
                [128, 128, 128]
            };
            c.fill_rect(is * px, (nh - 1 - ih) * px, px, px, rgb);
        }
    }
    if let Some((ih, is)) = mark {
        c.fill_rect(
            (is * px).saturating_sub(2),
            ((nh - 1 - ih) * px).saturating_sub(2),
            px + 4,
            px + 4,
            [255, 0, 0],
        );
    }
    c
}

/// Writes Fig. S4 (three heat maps) and Fig. S5 (phase curves at `pitch_m`) into `dir`.
pub fn write_figures(
    dir: &Path,
    data: &SweepData,
    sel: &[PairSelection],
    mark: Option<(f64, f64)>,
    curve_pitch_m: f64,
) -> Result<Vec<String>, MetalibError> {
    let files = render_figures(dir, data, sel, mark, curve_pitch_m)?;
    crate::sweep::write_set(dir, &files)
}

/// The files of [`write_figures`] (paths in `dir`, bytes), rendered in memory, for a caller
/// that writes them with files of its own as one set ([`crate::sweep::write_set`]).
pub fn render_figures(
    dir: &Path,
    data: &SweepData,
    sel: &[PairSelection],
    mark: Option<(f64, f64)>,
    curve_pitch_m: f64,
) -> Result<Vec<(std::path::PathBuf, Vec<u8>)>, MetalibError> {
    for (name, v) in [
        ("mark", mark.map_or(1.0, |m| m.0.min(m.1))),
        ("curve_pitch_m", curve_pitch_m),
    ] {
        if !(v.is_finite() && v > 0.0) {
            return Err(MetalibError::param(
                name,
                format!("must be finite and > 0, got {v}"),
            ));
        }
    }
    let (nh, ns) = (data.heights_m.len(), data.pitches_m.len());
    let nearest = |v: &[f64], x: f64| {
        v.iter()
            .enumerate()
            .min_by(|a, b| (a.1 - x).abs().total_cmp(&(b.1 - x).abs()))
            .map(|(i, _)| i)
            .unwrap_or(0)
    };
    let mark_idx = mark.map(|(h, s)| (nearest(&data.heights_m, h), nearest(&data.pitches_m, s)));
    // Everything is rendered in memory first and written as one set ([`write_set`]), so a
    // failure never leaves a half-updated figure directory.
    let mut files: Vec<(std::path::PathBuf, Vec<u8>)> = Vec::new();
    let min_tau: Vec<f64> = sel.iter().map(|p| p.min_transmittance_2pi).collect();
    let aspect: Vec<f64> = sel.iter().map(|p| p.max_aspect_ratio).collect();
    let viable: Vec<f64> = sel
        .iter()
        .map(|p| if p.viable { 1.0 } else { 0.0 })
        .collect();
    let amax = aspect
        .iter()
        .copied()
        .filter(|v| v.is_finite())
        .fold(1.0, f64::max);
    let heights_nm: Vec<f64> = data.heights_m.iter().map(|h| h * 1e9).collect();
    let pitches_nm: Vec<f64> = data.pitches_m.iter().map(|s| s * 1e9).collect();
    for (name, vals, lo, hi, title, bar) in [
        (
            "figS4a_min_transmittance",
            &min_tau,
            0.0,
            1.0,
            "Fig. S4a: largest minimum τ over a diameter window spanning 2π",
            "min τ",
        ),
        (
            "figS4b_max_aspect_ratio",
            &aspect,
            0.0,
            amax,
            "Fig. S4b: aspect ratio h / d_min of the usable run (viable pairs)",
            "h / d_min",
        ),
        (
            "figS4c_viable",
            &viable,
            0.0,
            1.0,
            "Fig. S4c: viable (h, s) pairs under the D.1 criteria",
            "viable (1) or not (0)",
        ),
    ] {
        let p = dir.join(format!("{name}.png"));
        files.push((p, heatmap(vals, nh, ns, lo, hi, mark_idx).png()?));
        let svg = heatmap_svg(
            title,
            bar,
            vals,
            &heights_nm,
            &pitches_nm,
            (lo, hi),
            mark_idx,
        )?;
        files.push((dir.join(format!("{name}.svg")), svg.into_bytes()));
    }
    // Fig. S5: unwrapped phase vs diameter at the chosen pitch for every 100 nm of height.
    let is = nearest(&data.pitches_m, curve_pitch_m);
    let s = data.pitches_m[is];
    let nf = data.fractions.len();
    let d: Vec<f64> = data.fractions.iter().map(|f| f * s).collect();
    let mut c = Canvas::new(800, 600);
    c.fill_rect(0, 0, 800, 600, [255, 255, 255]);
    let (x0, y0, w, h) = (60.0, 40.0, 700.0, 500.0);
    c.line(x0, y0 + h, x0 + w, y0 + h, [0, 0, 0]);
    c.line(x0, y0, x0, y0 + h, [0, 0, 0]);
    let mut csv = String::from("height_nm,diameter_nm,phase_unwrapped_rad,transmittance\n");
    let heights: Vec<usize> = (0..nh)
        .filter(|&ih| ((data.heights_m[ih] * 1e9).round() as i64) % 100 == 0)
        .collect();
    let ymax = 4.0 * PI;
    let mut curves = Vec::with_capacity(heights.len());
    for (k, &ih) in heights.iter().enumerate() {
        let base = data.idx(ih, is, 0);
        let uw = unwrap(&data.phase[base..base + nf]);
        curves.push(Curve {
            label: format!("h = {:.0} nm", data.heights_m[ih] * 1e9),
            points: (0..nf)
                .map(|j| {
                    (
                        d[j] * 1e9,
                        uw[j] - uw[0],
                        data.transmittance[base + j] >= 0.9,
                    )
                })
                .collect(),
        });
        let rgb = colormap(k as f64 / heights.len().max(2) as f64 - 0.0);
        let pt = |j: usize| {
            let x = x0 + w * (d[j] - d[0]) / (d[nf - 1] - d[0]).max(1e-30);
            // Baseline a quarter up: curves span −π…4π relative to the smallest diameter.
            let y = y0 + h - h * (0.25 + 0.75 * (uw[j] - uw[0]) / ymax).clamp(0.0, 1.0);
            (x, y)
        };
        for j in 0..nf {
            csv.push_str(&format!(
                "{:.1},{:.2},{:.6},{:.6}\n",
                data.heights_m[ih] * 1e9,
                d[j] * 1e9,
                uw[j],
                data.transmittance[base + j]
            ));
            if j > 0 {
                let ((xa, ya), (xb, yb)) = (pt(j - 1), pt(j));
                let ok = data.transmittance[base + j] >= 0.9;
                let col = if ok {
                    rgb
                } else {
                    [rgb[0] / 3 + 170, rgb[1] / 3 + 170, rgb[2] / 3 + 170]
                };
                c.line(xa, ya, xb, yb, col);
            }
        }
    }
    files.push((dir.join("figS5_phase_curves.png"), c.png()?));
    // Curves without a finite point (every cell of the pitch failed) have no axes to draw.
    let plottable = curves
        .iter()
        .flat_map(|c| &c.points)
        .any(|p| p.0.is_finite() && p.1.is_finite());
    if plottable {
        let svg = curves_svg(
            &format!(
                "Fig. S5: unwrapped phase vs diameter at s = {:.0} nm (solid where τ ≥ 0.90)",
                s * 1e9
            ),
            "pillar diameter d (nm)",
            "phase − phase at the smallest d (rad)",
            &curves,
        )?;
        files.push((dir.join("figS5_phase_curves.svg"), svg.into_bytes()));
    }
    files.push((dir.join("figS5_phase_curves.csv"), csv.into_bytes()));
    Ok(files)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The ascending path's buffer equals the cell-by-cell one, on curves with repeated
    /// diameters, bad cells at the ends and in runs, and buffers from none to the whole curve.
    /// Uniform draws in [0, 1) from a seeded linear congruential generator (metalib has no
    /// random-number dependency).
    fn uniform(seed: u64) -> impl FnMut() -> f64 {
        let mut state = seed;
        move || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 33) as f64 / (1u64 << 31) as f64
        }
    }

    /// The largest minimum τ over the shortest 2π runs, from every start by brute force.
    fn min_tau_2pi_brute(uw: &[f64], tau: &[f64]) -> f64 {
        let mut best = f64::NAN;
        for i in 0..uw.len() {
            let (mut lo, mut hi, mut mt) = (f64::NAN, f64::NAN, f64::NAN);
            for j in i..uw.len() {
                (lo, hi, mt) = (lo.min(uw[j]), hi.max(uw[j]), mt.min(tau[j]));
                if hi - lo >= 2.0 * PI {
                    if !mt.is_nan() {
                        best = if best.is_nan() { mt } else { best.max(mt) };
                    }
                    break;
                }
            }
        }
        best
    }

    #[test]
    fn min_tau_over_2pi_in_one_pass_equals_every_start_searched() {
        let mut next = uniform(99);
        for trial in 0..2000 {
            let n = trial % 30;
            // Phases that wander up and down by up to 2 rad a step, a few NaN cells.
            let mut p = 0.0;
            let uw: Vec<f64> = (0..n)
                .map(|_| {
                    p += (next() - 0.4) * 2.0;
                    if next() < 0.05 { f64::NAN } else { p }
                })
                .collect();
            let tau: Vec<f64> = (0..n)
                .map(|_| if next() < 0.05 { f64::NAN } else { next() })
                .collect();
            let (a, b) = (min_tau_over_2pi(&uw, &tau), min_tau_2pi_brute(&uw, &tau));
            assert!(
                a == b || (a.is_nan() && b.is_nan()),
                "{uw:?} {tau:?}: {a} vs {b}"
            );
        }
        // A curve that never spans 2π: NaN, at 10⁵ diameters in one pass.
        let uw: Vec<f64> = (0..100_000).map(|i| i as f64 * 1e-5).collect();
        assert!(min_tau_over_2pi(&uw, &vec![0.5; uw.len()]).is_nan());
    }

    #[test]
    fn the_buffer_by_difference_array_equals_the_quadratic_loop() {
        let mut next = uniform(12345);
        for trial in 0..300 {
            let n = 1 + trial % 40;
            let mut d: Vec<f64> = (0..n).map(|_| (next() * 20.0).round() * 1e-8).collect();
            d.sort_by(f64::total_cmp);
            let good: Vec<bool> = (0..n).map(|_| next() > 0.3).collect();
            for buffer in [0.0, 1e-15, 1e-8 + 1e-15, 3.3e-8, 1e-6] {
                let mut slow = good.clone();
                for j in (0..n).filter(|&j| !good[j]) {
                    for i in 0..n {
                        if (d[i] - d[j]).abs() <= buffer {
                            slow[i] = false;
                        }
                    }
                }
                assert_eq!(buffered(&d, &good, buffer), slow, "{d:?} {good:?} {buffer}");
            }
        }
        // An unordered curve takes the quadratic loop: the same answer as before.
        let d = [3e-8, 1e-8, 2e-8];
        assert_eq!(
            buffered(&d, &[true, false, true], 1.5e-8),
            vec![true, false, false]
        );
    }
}

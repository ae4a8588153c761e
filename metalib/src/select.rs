//! Candidate selection (Sec. D.1 criteria) over a sweep, and the Fig. S4 / S5 figures.

use crate::error::MetalibError;
use crate::plot::{Canvas, Curve, colormap, curves_svg, heatmap_svg};
use crate::sweep::{SweepData, check_output_target, write_atomic};
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
    let mut usable = good.clone();
    for j in (0..n).filter(|&j| !good[j]) {
        for (i, u) in usable.iter_mut().enumerate() {
            if (diameters_m[i] - diameters_m[j]).abs() <= c.buffer_m + 1e-15 {
                *u = false;
            }
        }
    }
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
    // Fig. S4a: best window spanning 2π.
    let mut min_tau_2pi = f64::NAN;
    for i in 0..n {
        let (mut lo, mut hi, mut mt) = (uw[i], uw[i], tau[i]);
        for j in i..n {
            lo = lo.min(uw[j]);
            hi = hi.max(uw[j]);
            mt = mt.min(tau[j]);
            if !(min_tau_2pi.is_nan() || mt > min_tau_2pi) {
                break;
            }
            if hi - lo >= 2.0 * PI {
                min_tau_2pi = if min_tau_2pi.is_nan() {
                    mt
                } else {
                    min_tau_2pi.max(mt)
                };
                break;
            }
        }
    }
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
    std::fs::create_dir_all(dir).map_err(|e| MetalibError::Io {
        path: dir.display().to_string(),
        cause: e,
    })?;
    let (nh, ns) = (data.heights_m.len(), data.pitches_m.len());
    let nearest = |v: &[f64], x: f64| {
        v.iter()
            .enumerate()
            .min_by(|a, b| (a.1 - x).abs().total_cmp(&(b.1 - x).abs()))
            .map(|(i, _)| i)
            .unwrap_or(0)
    };
    let mark_idx = mark.map(|(h, s)| (nearest(&data.heights_m, h), nearest(&data.pitches_m, s)));
    // Everything is rendered in memory first and written only when every figure succeeded,
    // so a failure never leaves a half-updated figure directory.
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
    if !curves.is_empty() {
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
    for (p, _) in &files {
        check_output_target(p)?;
    }
    let mut written = Vec::with_capacity(files.len());
    for (p, bytes) in files {
        write_atomic(&p, &bytes)?;
        written.push(p.display().to_string());
    }
    Ok(written)
}

//! PSF pixel values against an independent reference: the Rayleigh–Sommerfeld (first kind)
//! field of the sampled aperture, summed directly over the aperture cells (no FFT, no band
//! limit, no periodization), |U|² integrated over each pixel by a tensor Gauss–Legendre rule.
//! The reference shares only the sampled pupil (cell centres, rim weights, lens phase and the
//! source's spherical wave) with the model, so it checks the band limit, the spectral
//! sampling, the window DFT and the pixel integral together.

use nanoeye_optics::{ApertureGrid, AsmPsf, Hyperbolic, PhaseMap, PhaseProfile, PsfConfig};
use num_complex::Complex64;
use rayon::prelude::*;
use std::f64::consts::{PI, TAU};

const LAMBDA: f64 = 940e-9;

/// Gauss–Legendre nodes and weights on [−1, 1] (Newton on P_n from Chebyshev guesses).
fn gauss_legendre(n: usize) -> Vec<(f64, f64)> {
    (0..n)
        .map(|i| {
            let mut x = (PI * (i as f64 + 0.75) / (n as f64 + 0.5)).cos();
            loop {
                let (mut p0, mut p1) = (1.0, x);
                for k in 2..=n {
                    let p2 = ((2 * k - 1) as f64 * x * p1 - (k - 1) as f64 * p0) / k as f64;
                    p0 = p1;
                    p1 = p2;
                }
                let dp = n as f64 * (x * p1 - p0) / (x * x - 1.0);
                let dx = p1 / dp;
                x -= dx;
                if dx.abs() < 1e-15 {
                    let (mut p0, mut p1) = (1.0, x);
                    for k in 2..=n {
                        let p2 = ((2 * k - 1) as f64 * x * p1 - (k - 1) as f64 * p0) / k as f64;
                        p0 = p1;
                        p1 = p2;
                    }
                    let dp = n as f64 * (x * p1 - p0) / (x * x - 1.0);
                    return (x, 2.0 / ((1.0 - x * x) * dp * dp));
                }
            }
        })
        .collect()
}

/// Aperture cells (x, y, u·Δ²) of `map` lit by a unit spherical wave from the on-axis point
/// at depth `z`, and the power incident on the aperture Σ wΔ².
fn cells(map: &PhaseMap, z: f64) -> (Vec<(f64, f64, Complex64)>, f64) {
    let g = map.grid;
    let k = TAU / LAMBDA;
    let w = g.aperture_weights();
    let d2 = g.pitch_m * g.pitch_m;
    let mut out = vec![];
    let mut p_in = 0.0;
    for i in 0..g.n {
        for j in 0..g.n {
            if w[(i, j)] == 0.0 {
                continue;
            }
            let (x, y) = (g.coord(j), g.coord(i));
            let r2 = x * x + y * y;
            let wave = k * r2 / ((r2 + z * z).sqrt() + z);
            let u = Complex64::from_polar(
                w[(i, j)] * map.amplitude[(i, j)] * d2,
                map.phase_rad[(i, j)] + wave,
            );
            out.push((x, y, u));
            p_in += w[(i, j)] * d2;
        }
    }
    (out, p_in)
}

/// Rayleigh–Sommerfeld (first kind) field at (x, y) on the plane at distance `s`:
/// U = Σ u (s/R²)(1/(2πR) − i/λ) e^{ikR}.
fn rs_field(cells: &[(f64, f64, Complex64)], s: f64, x: f64, y: f64) -> Complex64 {
    let k = TAU / LAMBDA;
    let mut acc = Complex64::new(0.0, 0.0);
    for &(cx, cy, u) in cells {
        let (dx, dy) = (x - cx, y - cy);
        let r = (dx * dx + dy * dy + s * s).sqrt();
        let kern = Complex64::new(1.0 / (TAU * r), -1.0 / LAMBDA) * (s / (r * r));
        acc += u * kern * Complex64::from_polar(1.0, k * r);
    }
    acc
}

struct Case {
    label: &'static str,
    z: f64,
    pitch: f64,
    window: usize,
    /// Gauss–Legendre nodes per pixel side.
    gl: usize,
}

/// Largest |model − reference| over a few pixels, relative to the model plane's peak.
fn max_rel_error(grid: ApertureGrid, map: &PhaseMap, s: f64, c: &Case) -> f64 {
    let cfg = PsfConfig {
        sensor_distance_m: s,
        pitch_m: c.pitch,
        window_px: c.window,
        ..PsfConfig::default()
    };
    let model = AsmPsf::new(cfg, grid).unwrap();
    let plane = model.plane(map, c.z).unwrap();
    let w = c.window;
    let peak = (0..w * w)
        .map(|k| plane[(k / w, k % w)])
        .fold(0.0, f64::max);
    let (cl, p_in) = cells(map, c.z);
    assert!((p_in / model.incident_power_m2() - 1.0).abs() < 1e-12);
    let h = w as i64 / 2;
    let pixels: Vec<(usize, usize)> = [(0, 0), (0, 1), (-1, 2), (2, -3), (4, 0), (-5, -2), (1, 6)]
        .iter()
        .map(|&(dr, dc)| {
            (
                (h + dr).clamp(0, w as i64 - 1) as usize,
                (h + dc).clamp(0, w as i64 - 1) as usize,
            )
        })
        .collect();
    let rule = gauss_legendre(c.gl);
    let half = 0.5 * c.pitch;
    let reference: Vec<f64> = pixels
        .par_iter()
        .map(|&(r, col)| {
            let yc = (r as f64 + 0.5 - w as f64 / 2.0) * c.pitch;
            let xc = (col as f64 + 0.5 - w as f64 / 2.0) * c.pitch;
            let mut acc = 0.0;
            for &(ty, wy) in &rule {
                for &(tx, wx) in &rule {
                    let u = rs_field(&cl, s, xc + half * tx, yc + half * ty);
                    acc += wy * wx * u.norm_sqr();
                }
            }
            acc * half * half / p_in
        })
        .collect();
    let mut err = 0.0f64;
    for (&(r, col), &v) in pixels.iter().zip(&reference) {
        err = err.max((plane[(r, col)] - v).abs() / peak);
    }
    println!(
        "fb {:.4} L {:?} {}: z = {:.3} mm, p = {} µm, W = {}, q = {}: max |model − RS| / peak = {err:.2e} (peak {peak:.4e})",
        model.band_limit() * 1e-6,
        model.sizes(),
        c.label,
        c.z * 1e3,
        c.pitch * 1e6,
        w,
        model.subpixels()
    );
    err
}

/// F/2 rig scaled down 20× (D = 50 µm, s = 100 µm, object in focus at 1.25 mm, Δ = 0.5 µm):
/// in focus and at z = 150 µm (W020 ≈ 2λ, geometric blur 29 µm), on 3 µm and 0.5 µm pixels.
#[test]
fn pixel_values_match_the_rayleigh_sommerfeld_pixel_integral() {
    let (d, s, zf) = (50e-6, 100e-6, 1.25e-3);
    let grid = ApertureGrid::new(d, 0.5e-6).unwrap();
    let lens = Hyperbolic {
        wavelength_m: LAMBDA,
        object_distance_m: zf,
        image_distance_m: s,
    };
    let map = lens.phase_map(&grid).unwrap();
    let cases = [
        Case {
            label: "in focus, 3 µm",
            z: zf,
            pitch: 3e-6,
            window: 16,
            gl: 12,
        },
        Case {
            label: "defocus, 3 µm",
            z: 150e-6,
            pitch: 3e-6,
            window: 16,
            gl: 12,
        },
        Case {
            label: "in focus, 0.5 µm",
            z: zf,
            pitch: 0.5e-6,
            window: 64,
            gl: 6,
        },
        Case {
            label: "defocus, 0.5 µm",
            z: 150e-6,
            pitch: 0.5e-6,
            window: 96,
            gl: 6,
        },
    ];
    let errs: Vec<f64> = cases
        .iter()
        .map(|c| max_rel_error(grid, &map, s, c))
        .collect();
    for (c, e) in cases.iter().zip(&errs) {
        assert!(*e <= 1e-4, "{}: error {e:e} of the peak", c.label);
    }
}

//! Fabrication blueprint: phase map → diameter map, GDSII layout of circles, PNG preview and the
//! RMS phase error left by the library's coverage and the diameter grid.

use crate::error::MetalibError;
use crate::library::PillarLibrary;
use crate::plot::Canvas;
use std::f64::consts::PI;

/// Vertices per GDSII circle polygon (the closing vertex is written in addition).
pub const DEFAULT_CIRCLE_VERTICES: usize = 64;
/// GDSII database unit (m): 0.1 nm.
pub const GDS_DB_UNIT_M: f64 = 1e-10;

/// Blueprint options (SI units).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BlueprintOptions {
    /// Fabrication grid the diameters are rounded to (m); 0 keeps them continuous.
    pub diameter_step_m: f64,
    /// Polygon vertices per circle (≥ 8).
    pub circle_vertices: usize,
    /// GDSII layer number.
    pub layer: i16,
    /// Restrict to the circle inscribed in the map (else the full map).
    pub circular_aperture: bool,
}

impl Default for BlueprintOptions {
    fn default() -> Self {
        Self {
            diameter_step_m: 1e-9,
            circle_vertices: DEFAULT_CIRCLE_VERTICES,
            layer: 1,
            circular_aperture: true,
        }
    }
}

/// Result of the inversion.
#[derive(Debug, Clone)]
pub struct Blueprint {
    /// Rows of the lattice.
    pub rows: usize,
    /// Columns of the lattice.
    pub cols: usize,
    /// Diameter per site (m), NaN outside the aperture, row-major.
    pub diameters_m: Vec<f64>,
    /// Number of pillars placed.
    pub pillars: usize,
    /// RMS of the wrapped difference between target and realised phase (rad) over placed pillars.
    pub rms_phase_error_rad: f64,
    /// Largest such difference (rad).
    pub max_phase_error_rad: f64,
}

/// Largest |phase| (rad) a phase-map site may hold: beyond it f64 rounding alone exceeds
/// 1e-7 rad, so the wrapped target would be wrong (1e308 gave a 2.6 rad error).
pub const MAX_ABS_PHASE_RAD: f64 = 1e9;

impl BlueprintOptions {
    /// Checks the options before any work: vertex count, diameter grid.
    pub fn validate(&self) -> Result<(), MetalibError> {
        if self.circle_vertices < 8 || self.circle_vertices > 8190 {
            return Err(MetalibError::param(
                "circle_vertices",
                format!("must be in 8..=8190, got {}", self.circle_vertices),
            ));
        }
        // A step of 1e300 m passed and failed later, in the inversion, as a phase error; one
        // of 1e-317 m overflowed d / step to inf and the stepping back inside never ended.
        let s = self.diameter_step_m;
        if !(s == 0.0 || (MIN_DIAMETER_STEP_M..=MAX_DIAMETER_STEP_M).contains(&s)) {
            return Err(MetalibError::param(
                "diameter_step",
                format!(
                    "must be 0 (continuous) or lie in [{:e}, {:e}] m, got {:e}",
                    MIN_DIAMETER_STEP_M, MAX_DIAMETER_STEP_M, s
                ),
            ));
        }
        Ok(())
    }
}

/// Smallest non-zero diameter quantisation step (m): 1 pm, far below any fabrication grid.
pub const MIN_DIAMETER_STEP_M: f64 = 1e-12;

/// Largest diameter quantisation step (m): 1 µm, beyond any lattice pitch at 940 nm.
pub const MAX_DIAMETER_STEP_M: f64 = 1e-6;

fn wrap(x: f64) -> f64 {
    (x + PI).rem_euclid(2.0 * PI) - PI
}

/// Inverts a row-major phase map (rad, one value per lattice site; non-finite = no pillar).
pub fn invert_phase_map(
    lib: &dyn PillarLibrary,
    phase: &[f64],
    rows: usize,
    cols: usize,
    opt: &BlueprintOptions,
) -> Result<Blueprint, MetalibError> {
    if rows == 0 || cols == 0 || rows.checked_mul(cols) != Some(phase.len()) {
        return Err(MetalibError::param(
            "phase",
            format!("map of {} values is not {rows}×{cols}", phase.len()),
        ));
    }
    opt.validate()?;
    if let Some((k, v)) = phase
        .iter()
        .enumerate()
        .find(|(_, v)| v.is_infinite() || v.abs() > MAX_ABS_PHASE_RAD)
    {
        return Err(MetalibError::param(
            "phase",
            format!(
                "site (row {}, col {}) holds {v}; phases must be finite with |φ| ≤ \
                 {MAX_ABS_PHASE_RAD:e} rad (NaN marks a site without a pillar)",
                k / cols,
                k % cols
            ),
        ));
    }
    let (dlo, dhi) = lib.diameter_range_m();
    let pitch = lib.pitch_m();
    if dhi > pitch {
        return Err(MetalibError::param(
            "library",
            format!(
                "largest diameter {dhi} m exceeds the lattice pitch {pitch} m: neighbouring \
                 pillars would overlap"
            ),
        ));
    }
    let (cy, cx) = ((rows as f64 - 1.0) / 2.0, (cols as f64 - 1.0) / 2.0);
    let rad = rows.min(cols) as f64 / 2.0;
    let mut diam = vec![f64::NAN; rows * cols];
    let (mut sum2, mut maxe, mut count) = (0.0, 0.0_f64, 0usize);
    for r in 0..rows {
        for c in 0..cols {
            let target = phase[r * cols + c];
            if !target.is_finite() {
                continue;
            }
            if opt.circular_aperture
                && ((r as f64 - cy).powi(2) + (c as f64 - cx).powi(2)).sqrt() > rad
            {
                continue;
            }
            let mut d = lib.diameter_for_phase(target)?;
            if opt.diameter_step_m > 0.0 {
                d = (d / opt.diameter_step_m).round() * opt.diameter_step_m;
                // Rounding may step just outside the library; step back inside.
                while d > dhi + 1e-15 {
                    d -= opt.diameter_step_m;
                }
                while d < dlo - 1e-15 {
                    d += opt.diameter_step_m;
                }
                if d > dhi + 1e-15 {
                    return Err(MetalibError::param(
                        "diameter_step",
                        "coarser than the library's diameter range",
                    ));
                }
            }
            let realised = lib.response(d)?.arg();
            let e = wrap(realised - target).abs();
            sum2 += e * e;
            maxe = maxe.max(e);
            count += 1;
            diam[r * cols + c] = d;
        }
    }
    Ok(Blueprint {
        rows,
        cols,
        diameters_m: diam,
        pillars: count,
        rms_phase_error_rad: if count > 0 {
            (sum2 / count as f64).sqrt()
        } else {
            0.0
        },
        max_phase_error_rad: maxe,
    })
}

fn rec(out: &mut Vec<u8>, kind: u8, dtype: u8, payload: &[u8]) {
    let len = (4 + payload.len()) as u16;
    out.extend_from_slice(&len.to_be_bytes());
    out.push(kind);
    out.push(dtype);
    out.extend_from_slice(payload);
}

/// GDSII 8-byte real (excess-64, base-16 mantissa).
pub fn gds_real8(x: f64) -> [u8; 8] {
    if x == 0.0 {
        return [0; 8];
    }
    let sign = if x < 0.0 { 0x80u8 } else { 0 };
    let mut m = x.abs();
    let mut e: i32 = 64;
    while m >= 1.0 {
        m /= 16.0;
        e += 1;
    }
    while m < 1.0 / 16.0 {
        m *= 16.0;
        e -= 1;
    }
    let mant = (m * 2f64.powi(56)).round() as u64;
    let mut b = mant.to_be_bytes();
    b[0] = sign | (e as u8 & 0x7f);
    b
}

fn ascii_even(s: &str) -> Vec<u8> {
    let mut v: Vec<u8> = s
        .bytes()
        .filter(|c| c.is_ascii_graphic() || *c == b' ')
        .collect();
    if v.len() % 2 == 1 {
        v.push(0);
    }
    v
}

/// GDSII stream with one structure `METALENS`: one closed `circle_vertices`-gon per pillar on
/// `layer`, centred on its lattice site (origin at the map centre, x along columns, y up).
pub fn gdsii(
    bp: &Blueprint,
    pitch_m: f64,
    opt: &BlueprintOptions,
) -> Result<Vec<u8>, MetalibError> {
    opt.validate()?;
    if !(pitch_m.is_finite() && pitch_m > 0.0) {
        return Err(MetalibError::param("pitch", "must be finite and > 0"));
    }
    if let Some(d) = bp
        .diameters_m
        .iter()
        .copied()
        .filter(|d| d.is_finite())
        .find(|&d| d > pitch_m)
    {
        return Err(MetalibError::param(
            "pitch",
            format!(
                "pillar diameter {d} m exceeds the pitch {pitch_m} m: neighbouring pillars \
                 would overlap"
            ),
        ));
    }
    let extent = pitch_m * bp.rows.max(bp.cols) as f64 / GDS_DB_UNIT_M;
    if extent > 2.0e9 {
        return Err(MetalibError::param(
            "phase",
            "layout too large for 32-bit GDSII coordinates at 0.1 nm",
        ));
    }
    // Reserved whole and up front: grown by doubling, a 2500² map's 2.7 GB stream asked for
    // another 2.7 GB while holding 1.35 (an allocation abort under ulimit -v 4 GB).
    let len = gdsii_len(bp, opt);
    let mut out = Vec::new();
    usize::try_from(len)
        .ok()
        .and_then(|n| out.try_reserve_exact(n).ok())
        .ok_or_else(|| {
            MetalibError::param(
                "phase",
                format!(
                    "the layout's {len} bytes cannot be allocated: a smaller map or fewer vertices"
                ),
            )
        })?;
    let date = [0u8; 24];
    rec(&mut out, 0x00, 0x02, &600i16.to_be_bytes());
    rec(&mut out, 0x01, 0x02, &date);
    rec(&mut out, 0x02, 0x06, &ascii_even("NANOEYE"));
    // UNITS: database unit in user units (µm), then in metres.
    let mut units = Vec::new();
    units.extend_from_slice(&gds_real8(GDS_DB_UNIT_M / 1e-6));
    units.extend_from_slice(&gds_real8(GDS_DB_UNIT_M));
    rec(&mut out, 0x03, 0x05, &units);
    rec(&mut out, 0x05, 0x02, &date);
    rec(&mut out, 0x06, 0x06, &ascii_even("METALENS"));
    let (cy, cx) = ((bp.rows as f64 - 1.0) / 2.0, (bp.cols as f64 - 1.0) / 2.0);
    let nv = opt.circle_vertices;
    for r in 0..bp.rows {
        for c in 0..bp.cols {
            let d = bp.diameters_m[r * bp.cols + c];
            if !d.is_finite() || d <= 0.0 {
                continue;
            }
            let (x0, y0) = ((c as f64 - cx) * pitch_m, (cy - r as f64) * pitch_m);
            rec(&mut out, 0x08, 0x00, &[]);
            rec(&mut out, 0x0D, 0x02, &opt.layer.to_be_bytes());
            rec(&mut out, 0x0E, 0x02, &0i16.to_be_bytes());
            let mut xy = Vec::with_capacity((nv + 1) * 8);
            // Vertices on the circle of equal area would bias d; we place them on the circle.
            for k in 0..=nv {
                let a = 2.0 * PI * (k % nv) as f64 / nv as f64;
                let x = ((x0 + 0.5 * d * a.cos()) / GDS_DB_UNIT_M).round() as i32;
                let y = ((y0 + 0.5 * d * a.sin()) / GDS_DB_UNIT_M).round() as i32;
                xy.extend_from_slice(&x.to_be_bytes());
                xy.extend_from_slice(&y.to_be_bytes());
            }
            rec(&mut out, 0x10, 0x03, &xy);
            rec(&mut out, 0x11, 0x00, &[]);
        }
    }
    rec(&mut out, 0x07, 0x00, &[]);
    rec(&mut out, 0x04, 0x00, &[]);
    debug_assert_eq!(out.len() as u64, len);
    Ok(out)
}

/// Bytes of the GDSII stream [`gdsii`] writes for `bp` with `opt`'s circle vertices: 106 of
/// library and structure header, 24 + 8 (V + 1) per pillar (BOUNDARY, LAYER, DATATYPE, the
/// closed XY ring of V vertices, ENDEL), 8 of ENDSTR and ENDLIB.
pub fn gdsii_len(bp: &Blueprint, opt: &BlueprintOptions) -> u64 {
    let pillars = bp
        .diameters_m
        .iter()
        .filter(|d| d.is_finite() && **d > 0.0)
        .count() as u64;
    let per = 24 + 8 * (opt.circle_vertices as u64 + 1);
    106 + pillars.saturating_mul(per) + 8
}

/// Grey-scale preview of the diameter map (black = smallest library diameter, white = largest,
/// dark red = no pillar), scaled up to at least 512 px on the long side.
pub fn preview_png(bp: &Blueprint, dmin: f64, dmax: f64) -> Result<Vec<u8>, MetalibError> {
    let scale = (512 / bp.rows.max(bp.cols)).max(1);
    let mut c = Canvas::new(bp.cols * scale, bp.rows * scale);
    for r in 0..bp.rows {
        for col in 0..bp.cols {
            let d = bp.diameters_m[r * bp.cols + col];
            let rgb = if d.is_finite() {
                let v =
                    (255.0 * ((d - dmin) / (dmax - dmin).max(1e-30)).clamp(0.0, 1.0)).round() as u8;
                [v, v, v]
            } else {
                [60, 0, 0]
            };
            c.fill_rect(col * scale, r * scale, scale, scale, rgb);
        }
    }
    c.png()
}

#[cfg(test)]
mod bad_input_tests {
    use super::*;
    use crate::library::TabulatedLibrary;

    fn lib(pitch_m: f64, dmax_m: f64) -> TabulatedLibrary {
        let n = 64;
        let d: Vec<f64> = (0..n)
            .map(|i| 100e-9 + (dmax_m - 100e-9) * i as f64 / (n - 1) as f64)
            .collect();
        let phase: Vec<f64> = (0..n)
            .map(|i| 2.2 * PI * i as f64 / (n - 1) as f64)
            .collect();
        TabulatedLibrary::new(700e-9, pitch_m, 940e-9, d, &phase, vec![0.95; n], 1.45).unwrap()
    }

    #[test]
    fn infinite_and_huge_phases_are_refused_nan_is_empty() {
        let l = lib(500e-9, 400e-9);
        let opt = BlueprintOptions {
            circular_aperture: false,
            ..BlueprintOptions::default()
        };
        for bad in [f64::INFINITY, f64::NEG_INFINITY, 1e308] {
            let e = invert_phase_map(&l, &[0.0, bad, 1.0, f64::NAN], 2, 2, &opt).unwrap_err();
            assert!(e.to_string().contains("row 0, col 1"), "{e}");
        }
        let bp = invert_phase_map(&l, &[0.0, 2.0, 1.0, f64::NAN], 2, 2, &opt).unwrap();
        assert_eq!(bp.pillars, 3);
    }

    #[test]
    fn pillars_wider_than_the_pitch_are_refused() {
        let opt = BlueprintOptions {
            circular_aperture: false,
            ..BlueprintOptions::default()
        };
        let wide = lib(300e-9, 450e-9);
        assert!(invert_phase_map(&wide, &[0.0, 6.0], 1, 2, &opt).is_err());
        let l = lib(500e-9, 400e-9);
        let bp = invert_phase_map(&l, &[0.0, 6.0], 1, 2, &opt).unwrap();
        assert!(gdsii(&bp, 300e-9, &opt).is_err());
        assert!(gdsii(&bp, 500e-9, &opt).is_ok());
        // The stream's length is known before it is built (reserved whole, weighed by the CLI):
        // exactly, over vertex counts and maps with holes (NaN: no pillar).
        let holes = invert_phase_map(&l, &[0.0, 2.0, 1.0, f64::NAN, 3.0, 0.5], 2, 3, &opt).unwrap();
        for (b, nv) in [(&bp, 64), (&holes, 8), (&holes, 257)] {
            let o = BlueprintOptions {
                circle_vertices: nv,
                ..opt
            };
            let g = gdsii(b, 500e-9, &o).unwrap();
            assert_eq!(g.len() as u64, gdsii_len(b, &o), "{nv} vertices");
        }
        let few = BlueprintOptions {
            circle_vertices: 4,
            ..opt
        };
        assert!(few.validate().is_err());
    }
}

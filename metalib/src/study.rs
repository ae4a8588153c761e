//! Material and criteria study (issue 19): for pillar indices n + ik (a grid and the named
//! tables of [`crate::dispersion`]) at one pitch, is the target height viable under the D.1
//! criteria, with which usable diameter range, and how does the outcome change when each
//! criterion is relaxed on its own.
//!
//! Cost: one eigen-solve per (n, k, diameter); every height comes from the same solve.

use crate::dispersion;
use crate::error::MetalibError;
use crate::material::{DEFAULT_WAVELENGTH_M, Materials};
use crate::rcwa::{CellSpec, LayerModes, Rule};
use crate::select::{Criteria, PairSelection, select_curve};
use crate::sweep::Range;
use rayon::prelude::*;
use std::f64::consts::PI;

/// What to compute.
#[derive(Debug, Clone, PartialEq)]
pub struct StudyConfig {
    /// Wavelength (m).
    pub wavelength_m: f64,
    /// Lattice pitch (m).
    pub pitch_m: f64,
    /// Height (m) whose viability is the question.
    pub target_height_m: f64,
    /// Heights (m) also evaluated (free: same eigen-solves), to report the viable ones nearby.
    pub heights_m: Range,
    /// Diameters as fractions of the pitch (the sweep's grid by default).
    pub fractions: Range,
    /// Truncation order.
    pub harmonics: usize,
    /// Factorisation rule.
    pub rule: Rule,
    /// Real parts of the pillar index on the grid.
    pub n_values: Vec<f64>,
    /// Extinction coefficients on the grid.
    pub k_values: Vec<f64>,
    /// Named tables (by `dispersion` name) evaluated at the wavelength.
    pub materials: Vec<String>,
    /// The paper's usable diameter range (m): ≈ 100–275 nm (supplement D.1).
    pub paper_range_m: (f64, f64),
    /// How far (m) each end of a usable run may lie from the paper's to count as "near".
    pub range_tolerance_m: f64,
}

impl Default for StudyConfig {
    fn default() -> Self {
        Self {
            wavelength_m: DEFAULT_WAVELENGTH_M,
            pitch_m: 530e-9,
            target_height_m: 700e-9,
            heights_m: Range {
                start: 500e-9,
                stop: 900e-9,
                step: 10e-9,
            },
            fractions: Range {
                start: 0.10,
                stop: 0.90,
                step: 0.005,
            },
            harmonics: crate::rcwa::DEFAULT_HARMONICS,
            rule: crate::rcwa::DEFAULT_RULE,
            n_values: (0..=10).map(|i| 3.0 + 0.1 * i as f64).collect(),
            k_values: vec![0.0, 0.002, 0.005, 0.01],
            materials: dispersion::names(),
            paper_range_m: (100e-9, 275e-9),
            range_tolerance_m: 25e-9,
        }
    }
}

/// A named set of selection criteria.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Variant {
    /// Short name (JSON key).
    pub name: &'static str,
    /// What differs from D.1.
    pub description: &'static str,
    /// The criteria.
    pub criteria: Criteria,
}

/// D.1 as implemented, then each criterion relaxed on its own, then all relaxed together.
pub fn criteria_variants() -> Vec<Variant> {
    let d = Criteria::default();
    vec![
        Variant {
            name: "d1",
            description: "D.1 as implemented: tau >= 0.90, 5 nm buffer, strictly monotonic, slope < 9 deg/nm, coverage >= 1.05 x 2 pi",
            criteria: d,
        },
        Variant {
            name: "tau_0.85",
            description: "transmittance threshold 0.85 instead of 0.90",
            criteria: Criteria {
                min_transmittance: 0.85,
                ..d
            },
        },
        Variant {
            name: "tau_0.80",
            description: "transmittance threshold 0.80 instead of 0.90",
            criteria: Criteria {
                min_transmittance: 0.80,
                ..d
            },
        },
        Variant {
            name: "no_buffer",
            description: "no 5 nm buffer around rejected diameters",
            criteria: Criteria { buffer_m: 0.0, ..d },
        },
        Variant {
            name: "not_monotonic",
            description: "monotonicity not required (coverage = phase span of the run)",
            criteria: Criteria {
                require_monotonic: false,
                ..d
            },
        },
        Variant {
            name: "no_slope_limit",
            description: "no 9 deg/nm phase-slope limit",
            criteria: Criteria {
                max_slope_rad_per_m: f64::INFINITY,
                ..d
            },
        },
        Variant {
            name: "no_margin",
            description: "coverage >= 2 pi (no 5 % margin)",
            criteria: Criteria {
                min_coverage_rad: 2.0 * PI,
                ..d
            },
        },
        Variant {
            name: "all_relaxed",
            description: "tau >= 0.80, no buffer, not monotonic, no slope limit, coverage >= 2 pi",
            criteria: Criteria {
                min_transmittance: 0.80,
                buffer_m: 0.0,
                require_monotonic: false,
                max_slope_rad_per_m: f64::INFINITY,
                min_coverage_rad: 2.0 * PI,
            },
        },
    ]
}

/// Phase and τ against diameter for every height, one pillar index.
#[derive(Debug, Clone, PartialEq)]
pub struct Curves {
    /// Heights (m).
    pub heights_m: Vec<f64>,
    /// Diameters (m), ascending.
    pub diameters_m: Vec<f64>,
    /// arg t, `[height][diameter]` flattened.
    pub phase: Vec<f64>,
    /// τ, same layout.
    pub transmittance: Vec<f64>,
}

impl Curves {
    /// Selection of one height under `c`.
    pub fn select(&self, ih: usize, pitch_m: f64, c: &Criteria) -> PairSelection {
        let nd = self.diameters_m.len();
        let r = ih * nd..(ih + 1) * nd;
        select_curve(
            self.heights_m[ih],
            pitch_m,
            &self.diameters_m,
            &self.phase[r.clone()],
            &self.transmittance[r],
            c,
        )
    }
}

fn grid(cfg: &StudyConfig) -> Result<(Vec<f64>, Vec<f64>), MetalibError> {
    let heights = cfg.heights_m.values("heights")?;
    let fractions = cfg.fractions.values("fractions")?;
    if let Some(f) = fractions.iter().find(|f| !(**f > 0.0 && **f <= 1.0)) {
        return Err(MetalibError::param(
            "fractions",
            format!("fraction {f} outside (0, 1]"),
        ));
    }
    crate::sweep::check_heights(&heights)?;
    Ok((heights, fractions))
}

/// Solves every diameter for pillar index n + ik (in parallel over diameters).
pub fn curves(cfg: &StudyConfig, n: f64, k: f64) -> Result<Curves, MetalibError> {
    let (heights, fractions) = grid(cfg)?;
    let materials = Materials {
        n_pillar: n,
        k_pillar: k,
        ..Materials::default()
    };
    let diameters: Vec<f64> = fractions.iter().map(|f| f * cfg.pitch_m).collect();
    let spec = |d: f64| CellSpec {
        wavelength_m: cfg.wavelength_m,
        pitch_m: cfg.pitch_m,
        diameter_m: d,
        materials,
        harmonics: cfg.harmonics,
        rule: cfg.rule,
    };
    spec(diameters[0]).validate()?;
    let cols: Vec<Vec<(f64, f64)>> = diameters
        .par_iter()
        .map(|&d| {
            let modes = LayerModes::new(&spec(d))?;
            heights
                .iter()
                .map(|&h| {
                    let t = modes.transmission_at(h)?;
                    Ok((t.arg(), modes.transmittance_of(t)))
                })
                .collect::<Result<Vec<_>, MetalibError>>()
        })
        .collect::<Result<_, _>>()?;
    let (nh, nd) = (heights.len(), diameters.len());
    let mut phase = vec![0.0; nh * nd];
    let mut tau = vec![0.0; nh * nd];
    for (id, col) in cols.iter().enumerate() {
        for (ih, &(p, t)) in col.iter().enumerate() {
            phase[ih * nd + id] = p;
            tau[ih * nd + id] = t;
        }
    }
    Ok(Curves {
        heights_m: heights,
        diameters_m: diameters,
        phase,
        transmittance: tau,
    })
}

/// Outcome of one criteria variant at the target height.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct VariantOutcome {
    /// Variant name.
    pub variant: &'static str,
    /// Whether the target (h, s) is viable.
    pub viable: bool,
    /// Usable run (nm), if any run exists (absent from the JSON otherwise).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub usable_range_nm: Option<[f64; 2]>,
    /// Phase coverage of the best run (rad).
    pub coverage_rad: f64,
    /// Shortest diameter window (nm) inside the usable run whose phase span reaches the
    /// variant's required coverage (a viable run can be trimmed to it), if the run reaches it
    /// (absent from the JSON otherwise).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub shortest_window_nm: Option<[f64; 2]>,
    /// Viable and both ends of the usable run, or of its shortest window, within the
    /// tolerance of the paper's 100–275 nm.
    pub near_paper_range: bool,
    /// Heights (nm) at this pitch that are viable under the variant.
    pub viable_heights_nm: Vec<f64>,
}

/// Everything computed for one pillar index.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct PointOutcome {
    /// Material name, or "grid".
    pub source: String,
    /// n.
    pub n: f64,
    /// k.
    pub k: f64,
    /// Fig. S4a quantity at the target height: largest minimum τ over a diameter window
    /// spanning 2π (absent when no window spans 2π).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub min_transmittance_2pi: Option<f64>,
    /// One entry per criteria variant, in [`criteria_variants`] order.
    pub variants: Vec<VariantOutcome>,
}

/// Evaluates every variant on `c` (heights from `c`, target height from `cfg`).
pub fn outcome(
    cfg: &StudyConfig,
    source: &str,
    n: f64,
    k: f64,
    c: &Curves,
) -> Result<PointOutcome, MetalibError> {
    let it = c
        .heights_m
        .iter()
        .position(|h| (h - cfg.target_height_m).abs() < 1e-12)
        .ok_or_else(|| {
            MetalibError::param(
                "target_height",
                format!("{} m is not on the height grid", cfg.target_height_m),
            )
        })?;
    let (lo, hi) = cfg.paper_range_m;
    let nd = c.diameters_m.len();
    let uw = crate::select::unwrap(&c.phase[it * nd..(it + 1) * nd]);
    let mut min_tau = None;
    let variants = criteria_variants()
        .iter()
        .map(|v| {
            let s = c.select(it, cfg.pitch_m, &v.criteria);
            if v.name == "d1" && s.min_transmittance_2pi.is_finite() {
                min_tau = Some(s.min_transmittance_2pi);
            }
            let range = s
                .run
                .map(|_| [s.diameter_min_m * 1e9, s.diameter_max_m * 1e9]);
            let window = s.run.and_then(|(a, b)| {
                shortest_window(&uw, a, b, v.criteria.min_coverage_rad)
                    .map(|(i, j)| [c.diameters_m[i] * 1e9, c.diameters_m[j] * 1e9])
            });
            let close = |r: [f64; 2]| {
                (r[0] * 1e-9 - lo).abs() <= cfg.range_tolerance_m
                    && (r[1] * 1e-9 - hi).abs() <= cfg.range_tolerance_m
            };
            let near = s.viable && (range.is_some_and(close) || window.is_some_and(close));
            VariantOutcome {
                variant: v.name,
                viable: s.viable,
                usable_range_nm: range,
                coverage_rad: s.phase_coverage_rad,
                shortest_window_nm: window,
                near_paper_range: near,
                viable_heights_nm: (0..c.heights_m.len())
                    .filter(|&ih| c.select(ih, cfg.pitch_m, &v.criteria).viable)
                    .map(|ih| (c.heights_m[ih] * 1e9).round())
                    .collect(),
            }
        })
        .collect();
    Ok(PointOutcome {
        source: source.to_string(),
        n,
        k,
        min_transmittance_2pi: min_tau,
        variants,
    })
}

/// Shortest index window [i, j] within [a, b] whose unwrapped-phase span reaches `need`.
fn shortest_window(uw: &[f64], a: usize, b: usize, need: f64) -> Option<(usize, usize)> {
    let mut best: Option<(usize, usize)> = None;
    for i in a..=b {
        let (mut lo, mut hi) = (uw[i], uw[i]);
        for (j, &v) in uw.iter().enumerate().take(b + 1).skip(i) {
            lo = lo.min(v);
            hi = hi.max(v);
            if hi - lo >= need {
                if best.is_none_or(|(p, q)| j - i < q - p) {
                    best = Some((i, j));
                }
                break;
            }
        }
    }
    best
}

/// The whole study: named materials first, then the (n, k) grid row by row (n outer).
/// `progress(done, total)` is called after each pillar index.
pub fn run_study(
    cfg: &StudyConfig,
    progress: &dyn Fn(usize, usize),
) -> Result<Vec<PointOutcome>, MetalibError> {
    for (name, v) in [("n_values", &cfg.n_values), ("k_values", &cfg.k_values)] {
        if let Some(x) = v.iter().find(|x| !x.is_finite()) {
            return Err(MetalibError::param(name, format!("{x} is not finite")));
        }
    }
    let mut points: Vec<(String, f64, f64)> = Vec::new();
    for m in &cfg.materials {
        let (n, k) = dispersion::by_name(m)?.nk_at(cfg.wavelength_m)?;
        points.push((m.clone(), n, k));
    }
    for &n in &cfg.n_values {
        for &k in &cfg.k_values {
            points.push(("grid".into(), n, k));
        }
    }
    let total = points.len();
    let mut out = Vec::with_capacity(total);
    for (i, (src, n, k)) in points.iter().enumerate() {
        let c = curves(cfg, *n, *k)?;
        out.push(outcome(cfg, src, *n, *k, &c)?);
        progress(i + 1, total);
    }
    Ok(out)
}

//! Depth-dependent PSFs by band-limited angular-spectrum propagation, evaluated only over the
//! sensor window by a separable chirp-z DFT and box-integrated over pixels (S24), with the
//! finite-difference ∂PSF/∂z stack and the vector–Jacobian product w.r.t. the phase map.
//!
//! Per depth z: point source → spherical wave e^{ik(r−z)} over the pupil → pupil weight ·
//! a·e^{iφ} → spectrum sampled at spacing 1/L (the aperture field folded modulo the period L,
//! then an N_L×N_L FFT; exact samples of its continuous spectrum) → × H(f) = e^{i2πs√(λ⁻²−f²)},
//! tapered to zero beyond the directions that can reach the window → separable window DFT onto
//! a uniform sub-pixel grid (q points per pixel side, at least the intensity's Nyquist rate,
//! plus T points of margin), by chirp-z (`czt`) → |·|² → exact pixel integral of the
//! band-limited intensity by a spectral quadrature (separable weights k, `pixel_kernel`) →
//! ÷ power incident on the aperture. Sampling the spectrum at 1/L periodizes the sensor field with period L, so L must
//! exceed the region of the sensor plane that holds light (see docs/optics.md).

use crate::czt::ChirpOp;
use crate::error::{OpticsError, Result, positive};
use crate::grid::ApertureGrid;
use crate::profile::{PhaseMap, sag_phase};
use faer::{Mat, c64};
use nanoeye_fft::{Fft, Planner};
use rayon::prelude::*;
use std::f64::consts::{PI, TAU};
use std::sync::{Arc, Mutex};

/// Optical and sensor parameters of a PSF evaluation (SI units).
#[derive(Clone, Copy, Debug)]
pub struct PsfConfig {
    /// Wavelength λ (m).
    pub wavelength_m: f64,
    /// Metasurface-to-sensor distance s (m).
    pub sensor_distance_m: f64,
    /// Sensor pixel pitch p (m).
    pub pitch_m: f64,
    /// PSF window width W (pixels per side); the window is centred on `window_center_m`.
    pub window_px: usize,
    /// Largest sub-pixel spacing (m) of the intensity samples the pixel integral is computed
    /// from; q = ⌈p / δ_max⌉ points per pixel side. The spacing is always at most 0.8× the
    /// intensity's Nyquist spacing 1/(4 f_b) (f_b the field's band limit), which this can only
    /// tighten. `None`: 0.8/(4 f_b).
    pub max_subpixel_m: Option<f64>,
    /// Period L (m) of the spectral sampling (the padding). `None`: D + W·p + 4√(λs).
    pub period_m: Option<f64>,
    /// Lateral position (x, y) of the point source (m); (0, 0) is on axis.
    pub source_xy_m: [f64; 2],
    /// Sensor-plane position (x, y) of the window centre (m).
    pub window_center_m: [f64; 2],
}

impl Default for PsfConfig {
    /// λ = 940 nm, s = 2 mm, p = 3 µm, W = 64, on axis.
    fn default() -> Self {
        Self {
            wavelength_m: 940e-9,
            sensor_distance_m: 2e-3,
            pitch_m: 3e-6,
            window_px: 64,
            max_subpixel_m: None,
            period_m: None,
            source_xy_m: [0.0, 0.0],
            window_center_m: [0.0, 0.0],
        }
    }
}

/// How a caller uses an [`AsmPsf`], for its memory estimate [`AsmPsf::memory_bytes`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PsfUsage {
    /// One stack of one map.
    Once,
    /// Stacks of several maps in turn: the memo keeps the last map's aperture samples while
    /// the next map's are built.
    Repeated,
    /// Repeated stacks and their VJPs (a lens training).
    Training,
}

/// PSFs of one lens over a set of depths, with their finite-difference depth derivative.
#[derive(Clone, Debug)]
pub struct PsfStack {
    /// Source depths z_k (m), as requested (any order; ∂/∂z uses neighbours in this order).
    pub depths_m: Vec<f64>,
    /// Sensor pixel pitch p (m).
    pub pitch_m: f64,
    /// PSF per depth, W×W, rows along y; pixel values are the fraction of the power incident
    /// on the aperture that falls on the pixel. Zero for planes not computed.
    pub planes: Vec<Mat<f32>>,
    /// ∂PSF/∂z per depth (1/m) by finite differences across the stack (central inside,
    /// one-sided at the ends); zero where a needed neighbour was not computed.
    pub dz_planes: Vec<Mat<f32>>,
    /// Whether each plane was computed (false: skipped as empty).
    pub computed: Vec<bool>,
}

impl PsfStack {
    /// The stack of f64 planes (`None`: not computed, stored as zeros) at `depths_m` (m) for
    /// pitch `pitch_m` (m) and window `window_px`: f32 planes and their depth derivative.
    /// Planes computed in pieces (by depth, on several processes) and put back in order give
    /// the stack [`PsfModel::forward`] gives.
    pub fn from_planes(
        depths_m: &[f64],
        pitch_m: f64,
        window_px: usize,
        planes: &[Option<Mat<f64>>],
    ) -> PsfStack {
        let dz = depth_derivative(depths_m, planes);
        let w = window_px;
        let conv = |v: &Option<Mat<f64>>| v.as_ref().map_or_else(|| Mat::zeros(w, w), to_f32);
        PsfStack {
            depths_m: depths_m.to_vec(),
            pitch_m,
            computed: planes.iter().map(Option::is_some).collect(),
            planes: planes.iter().map(conv).collect(),
            dz_planes: dz.iter().map(conv).collect(),
        }
    }
}

/// Gradient of a scalar loss w.r.t. a [`PhaseMap`].
#[derive(Clone, Debug)]
pub struct PhaseMapGrad {
    /// ∂loss/∂φ (per radian), n×n.
    pub phase_rad: Mat<f64>,
    /// ∂loss/∂a (per unit amplitude), n×n.
    pub amplitude: Mat<f64>,
}

/// A model mapping a metasurface to PSF stacks over depth, with its VJP.
pub trait PsfModel: Send + Sync {
    /// PSF stack at `depths_m` (m, each > 0). `active[k] == false` skips depth k (its plane
    /// and derivative stay zero): use it for depth planes without scene content.
    fn forward(
        &self,
        map: &PhaseMap,
        depths_m: &[f64],
        active: Option<&[bool]>,
    ) -> Result<PsfStack>;

    /// Gradient w.r.t. `map` of a scalar loss whose gradient w.r.t. the stack is
    /// `grad_planes[k]` (`∂loss/∂planes[k]`, W×W) and optionally `grad_dz[k]`
    /// (`∂loss/∂dz_planes[k]`). Planes whose total upstream gradient is zero are skipped.
    fn vjp(
        &self,
        map: &PhaseMap,
        depths_m: &[f64],
        grad_planes: &[Mat<f64>],
        grad_dz: Option<&[Mat<f64>]>,
    ) -> Result<PhaseMapGrad>;
}

/// Band-limited angular-spectrum PSF model on a fixed aperture grid and sensor window.
pub struct AsmPsf {
    cfg: PsfConfig,
    grid: ApertureGrid,
    weights: Mat<f64>,
    /// Sub-pixel points per pixel side.
    q: usize,
    /// Margin (sub-pixel points) of the field grid beyond the window on every side: the
    /// half-length of the sub-cell quadrature kernel.
    taps: usize,
    /// Field grid points per side: W q + 2T.
    n_ext: usize,
    /// Pixel-integral weights k_i (m), i < q + 2T: pixel r along an axis is
    /// Σ_i k_i I[r q + i] over the field grid, and the plane is k ⊗ k applied to |V|².
    kern: Vec<f64>,
    /// Largest error of the sub-cell quadrature over the intensity's band, relative to δ.
    quad_err: f64,
    /// Band limit f_b (1/m) of the field per axis: the largest band frequency m_max / L.
    f_band: f64,
    /// FFT size of the folded grid.
    n_fold: usize,
    /// Rows of the folded grid that hold aperture samples: min(n, N_L).
    fold_rows: usize,
    /// Band frequency indices m (f = m / L), ascending.
    band: Vec<i64>,
    /// Where each band frequency sits in a folded FFT's output: m mod N_L (a signed modulo per
    /// element in the inner loops cost a few per cent of a training step).
    band_at: Vec<usize>,
    /// Transfer function × Δ² × the window DFTs' pre-multipliers (pre_y[a]·pre_x[b]), Nb×Nb
    /// (rows f_y, columns f_x).
    h: Mat<c64>,
    /// |post_y[j]·post_x[k]|²: the window DFTs' post-multipliers are this modulus times a
    /// phase, which the intensity does not see, so they are left out of the field.
    post_gain: f64,
    /// Window DFTs (Nb band samples → W q + 2T field grid points) for y and x, and their
    /// adjoints.
    ey: ChirpOp,
    ex: ChirpOp,
    ey_adj: ChirpOp,
    ex_adj: ChirpOp,
    /// Power incident on the aperture for a unit-amplitude wave (m²).
    p_in: f64,
    fft: Arc<dyn Fft<f64>>,
    ifft: Arc<dyn Fft<f64>>,
    /// The fields of the last stack computed, for a VJP at the same map (see [`FieldMemo`]).
    memo: Mutex<Option<FieldMemo>>,
}

/// Most bytes of fields [`FieldMemo`] keeps; a stack whose fields need more keeps none.
const FIELD_MEMO_BYTES: usize = 64 << 20;

/// The fields V of the last [`AsmPsf::planes_f64`] call, by depth, and the map they belong
/// to. A VJP at the same map needs each depth's field again, which costs as much as the
/// plane itself; training calls the VJP right after the stack, with the map unchanged.
struct FieldMemo {
    /// Bit patterns of the map's phase and amplitude samples, column by column.
    key: Vec<u64>,
    /// (depth's bit pattern, its field) for every plane computed.
    fields: Vec<(u64, Mat<c64>)>,
    /// The map's aperture samples (one sincos per cell to rebuild).
    samples: Samples,
}

/// A plane and, when the memo keeps it, the field it was integrated from.
type PlaneAndField = (Mat<f64>, Option<Mat<c64>>);

/// The memo key of `map`: its samples' bit patterns (equal keys ⇔ the same map, bit for bit).
fn map_key(map: &PhaseMap) -> Vec<u64> {
    let mut key = Vec::with_capacity(2 * map.phase_rad.nrows() * map.phase_rad.ncols());
    for m in [&map.phase_rad, &map.amplitude] {
        for c in m.col_iter() {
            key.extend(c.iter().map(|v| v.to_bits()));
        }
    }
    key
}

/// Whether `key` is [`map_key`]`(map)`, without building the key.
fn same_map(key: &[u64], map: &PhaseMap) -> bool {
    let n = map.phase_rad.nrows() * map.phase_rad.ncols();
    key.len() == 2 * n
        && [&map.phase_rad, &map.amplitude]
            .into_iter()
            .flat_map(|m| m.col_iter())
            .flat_map(|c| c.iter())
            .zip(key)
            .all(|(v, &b)| v.to_bits() == b)
}

/// Smallest n' ≥ n whose prime factors are all in {2, 3, 5, 7} (fast FFT sizes).
pub fn fast_fft_size(n: usize) -> usize {
    let mut m = n.max(1);
    loop {
        let mut r = m;
        for p in [2, 3, 5, 7] {
            while r.is_multiple_of(p) {
                r /= p;
            }
        }
        if r == 1 {
            return m;
        }
        m += 1;
    }
}

/// Band columns per batched FFT call (bounds the column buffer to COL_CHUNK·N_L values).
const COL_CHUNK: usize = 16;

/// Rows of the folded grid per batched row-FFT call in [`AsmPsf::field`]: the block stays in
/// cache while its band columns are copied out.
const ROW_BLOCK: usize = 16;

/// Aperture samples of one phase map, structure-of-arrays so the per-depth loop streams
/// 24 bytes per sample.
struct Samples {
    /// Index into the folded N_L×N_L grid (row-major), ascending: samples are ordered by
    /// it, so a block of the grid's rows holds a contiguous range of samples.
    fold: Vec<u32>,
    /// Samples of fold row r: `row_at[r]..row_at[r + 1]` (fold_rows + 1 offsets).
    row_at: Vec<u32>,
    /// Index into `d2` of the sample's distance to the source.
    wave: Vec<u32>,
    /// Amplitude a × pupil weight × e^{iφ}.
    ua: Vec<c64>,
    /// Pupil weight × e^{iφ}.
    unit: Vec<c64>,
    /// Amplitude a.
    amp: Vec<f64>,
    /// Index (row-major) into the n×n aperture grid.
    cell: Vec<u32>,
    /// Distinct squared lateral distances to the source (m²): an on-axis source sees each of
    /// them from up to 8 samples (the grid's mirror and diagonal symmetries), so the spherical
    /// wave costs one sincos per distinct radius, not per sample.
    d2: Vec<f64>,
}

impl Samples {
    fn len(&self) -> usize {
        self.fold.len()
    }
}

/// What [`AsmPsf::new`] sizes from a configuration and a grid (SI units).
struct Sizing {
    lam: f64,
    s: f64,
    /// Aperture sampling step Δ.
    delta: f64,
    half_win: f64,
    n_fold: usize,
    /// Band frequencies per axis N_b = 2 m_max + 1.
    nb: usize,
    df: f64,
    f_1: f64,
    f_b: f64,
    m_max: i64,
    f_band: f64,
    q: usize,
    sub: f64,
    cw: Vec<f64>,
    quad_err: f64,
    taps: usize,
    n_ext: usize,
}

struct Workspace {
    /// Spherical-wave factor e^{ik(r−z)} per distinct radius.
    wave: Vec<c64>,
    /// ROW_BLOCK rows of the folded N_L×N_L grid (row-major): the grid is only ever streamed
    /// through a block of rows, never stored whole.
    blk: Vec<c64>,
    /// The band columns of the folded grid, column-major N_b × N_L.
    colbuf: Vec<c64>,
    scratch: Vec<c64>,
    cbuf: Vec<c64>,
    t: Mat<c64>,
    v: Mat<c64>,
    /// |V|² (or its upstream gradient), n_ext × n_ext.
    iv: Mat<f64>,
    /// Intensity integrated along x per field row, n_ext × W.
    ix: Mat<f64>,
}

/// Oversampling of the intensity samples: spacing δ ≤ this / (2·intensity band).
const OVERSAMPLE: f64 = 0.8;

/// Target of the sub-cell quadrature's largest error over the intensity's band, relative to
/// δ (the exact weight of a constant).
const QUAD_TOL: f64 = 1e-10;

fn sinc(x: f64) -> f64 {
    if x == 0.0 {
        1.0
    } else {
        (PI * x).sin() / (PI * x)
    }
}

/// Sub-cell quadrature for band-limited functions sampled at spacing δ: weights c_n
/// (n = −T..=T, c_{−n} = c_n, returned as c_0..=c_T in units of δ) with
/// Σ_n c_n e^{i2πνnδ} = sinc(δν) for |δν| ≤ `xb`, so that Σ_n c_n f((j + n)δ) is the integral of
/// f over [jδ − δ/2, jδ + δ/2] / δ for every f whose spectrum lies in |ν| ≤ xb/δ. Fitted by
/// least squares (truncated SVD) on Chebyshev points of [0, xb]; returns the weights and the
/// largest error of the fit on a grid of 4001 points.
fn subcell_weights(xb: f64, t: usize) -> (Vec<f64>, f64) {
    let m = 6 * (t + 1) + 64;
    let xs: Vec<f64> = (0..m)
        .map(|k| 0.5 * xb * (1.0 - (PI * (k as f64 + 0.5) / m as f64).cos()))
        .collect();
    let a = Mat::from_fn(m, t + 1, |k, n| {
        let c = (TAU * xs[k] * n as f64).cos();
        if n == 0 { c } else { 2.0 * c }
    });
    let mut c = vec![0.0; t + 1];
    if let Some((u, sv, v)) = svd_seq(&a) {
        let smax = sv[0];
        for i in 0..=t {
            if sv[i] < 1e-14 * smax {
                continue;
            }
            let ub: f64 = (0..m).map(|k| u[(k, i)] * sinc(xs[k])).sum::<f64>() / sv[i];
            for (n, cn) in c.iter_mut().enumerate() {
                *cn += v[(n, i)] * ub;
            }
        }
    }
    let err = (0..=4000)
        .map(|k| {
            let x = xb * k as f64 / 4000.0;
            let f = c[0]
                + 2.0
                    * (1..=t)
                        .map(|n| c[n] * (TAU * x * n as f64).cos())
                        .sum::<f64>();
            (f - sinc(x)).abs()
        })
        .fold(0.0, f64::max);
    (c, err)
}

/// Full SVD (U, singular values, V) on this thread: faer's default runs on the rayon pool and
/// its last bits depend on the pool's size, and the quadrature weights reach every PSF and
/// PSF VJP (runs with different thread counts, e.g. MPI ranks with one thread each, must agree).
fn svd_seq(a: &Mat<f64>) -> Option<(Mat<f64>, Vec<f64>, Mat<f64>)> {
    use faer::dyn_stack::{MemBuffer, MemStack};
    use faer::linalg::svd::{ComputeSvdVectors, svd, svd_scratch};
    let (m, n) = a.shape();
    let mut u = Mat::<f64>::zeros(m, m);
    let mut v = Mat::<f64>::zeros(n, n);
    let mut sv = faer::diag::Diag::<f64>::zeros(m.min(n));
    let full = ComputeSvdVectors::Full;
    let req = svd_scratch::<f64>(m, n, full, full, faer::Par::Seq, Default::default());
    svd(
        a.as_ref(),
        sv.as_mut(),
        Some(u.as_mut()),
        Some(v.as_mut()),
        faer::Par::Seq,
        MemStack::new(&mut MemBuffer::new(req)),
        Default::default(),
    )
    .ok()?;
    let sv = (0..m.min(n)).map(|i| sv[i]).collect();
    Some((u, sv, v))
}

/// The shortest sub-cell quadrature (T ≤ 160) whose error is ≤ [`QUAD_TOL`], or the best found.
fn subcell_quadrature(xb: f64) -> (Vec<f64>, f64) {
    let mut best: Option<(Vec<f64>, f64)> = None;
    let mut t = 4usize;
    while t <= 160 {
        let (c, err) = subcell_weights(xb, t);
        let done = err <= QUAD_TOL;
        if best.as_ref().is_none_or(|b| err < b.1) {
            best = Some((c, err));
        }
        if done {
            break;
        }
        t += (t / 4).max(2);
    }
    best.unwrap_or_else(|| (vec![1.0], f64::INFINITY))
}

impl AsmPsf {
    /// The sizes `new` builds with, validated: computed alone by [`AsmPsf::memory_bytes`] so a
    /// caller can weigh a configuration before anything is allocated.
    fn sizing(cfg: &PsfConfig, grid: &ApertureGrid) -> Result<Sizing> {
        let lam = positive("wavelength_m", cfg.wavelength_m)?;
        let s = positive("sensor_distance_m", cfg.sensor_distance_m)?;
        let p = positive("pitch_m", cfg.pitch_m)?;
        if cfg.window_px == 0 || cfg.window_px > 4096 {
            return Err(OpticsError::param(
                "window_px",
                format!("must be 1..=4096, got {}", cfg.window_px),
            ));
        }
        for v in cfg.source_xy_m.iter().chain(cfg.window_center_m.iter()) {
            if !v.is_finite() {
                return Err(OpticsError::param(
                    "source_xy_m/window_center_m",
                    "must be finite",
                ));
            }
        }
        let d = grid.diameter_m;
        let delta = grid.pitch_m;
        let w = cfg.window_px;
        let user_sub = match cfg.max_subpixel_m {
            Some(v) => Some(positive("max_subpixel_m", v)?),
            None => None,
        };
        // Margin (m) beyond the window over which the band is tapered: 4√(λs), four Fresnel
        // lengths, so the taper's own diffraction stays outside the window.
        let margin = 4.0 * (lam * s).sqrt();
        let period = match cfg.period_m {
            Some(v) => positive("period_m", v)?,
            None => d + w as f64 * p + margin,
        };
        // Checked in floating point first: a huge period must not wrap the integer size.
        let folded = ((period / delta) - 1e-9).ceil().max(2.0);
        if folded.is_nan() || folded > 16384.0 {
            // Say what makes the period up: unset, it follows from the aperture, the window and
            // the aperture sampling, none of which the caller calls a period.
            let made_of = match cfg.period_m {
                Some(_) => String::from("as given"),
                None => format!(
                    "the aperture's {d:.4e} m + the {w}-pixel window's {:.4e} m + a taper \
                     margin of {margin:.4e} m",
                    w as f64 * p
                ),
            };
            return Err(OpticsError::param(
                "period_m",
                format!(
                    "the period of {period:.4e} m ({made_of}) sampled every {delta:.4e} m is a \
                     folded grid of {folded:e} samples, more than 16384: sample the aperture \
                     more coarsely, or narrow the window"
                ),
            ));
        }
        let n_fold = fast_fft_size(folded as usize);
        if n_fold > 16384 {
            return Err(OpticsError::param(
                "period_m",
                format!("folded grid {n_fold} too large"),
            ));
        }
        let l_eff = n_fold as f64 * delta;
        let df = 1.0 / l_eff;
        // Directions whose rays from the aperture can land in the window (per axis): H is 1
        // there, and falls to 0 (raised cosine per axis) by the directions that land `margin`
        // beyond the window; the band edge is capped below the grid's Nyquist frequency and the
        // evanescent cut.
        let half_win = 0.5 * w as f64 * p;
        let reach = 0.5 * d
            + half_win
            + cfg.window_center_m[0]
                .abs()
                .max(cfg.window_center_m[1].abs());
        let t = reach / s;
        let f_reach = t / (lam * (1.0 + t * t).sqrt());
        // Band edge: the taper runs from the directions that reach the window to those that land
        // a Fresnel-scale margin beyond it.
        let t_b = (reach + margin) / s;
        let f_b = (t_b / (lam * (1.0 + t_b * t_b).sqrt()))
            .min(0.5 / delta * (1.0 - 1e-9))
            .min(1.0 / lam);
        let f_1 = f_reach.min(f_b);
        let m_max = (f_b / df).floor() as i64;
        let nb = (2 * m_max + 1) as usize;
        let f_band = m_max as f64 * df;
        // |V|² is band-limited to 2 f_b per axis: sample it at δ ≤ 0.8/(4 f_b), and integrate
        // each sub-cell exactly (to QUAD_TOL) from the 2T+1 nearest samples.
        let nyq = OVERSAMPLE / (4.0 * f_band.max(1e-300));
        let sub_max = user_sub.map_or(nyq, |v| v.min(nyq));
        let qf = (p / sub_max - 1e-9).ceil().max(1.0);
        if qf.is_nan() || qf * w as f64 > 8192.0 {
            return Err(OpticsError::param(
                "pitch_m",
                format!("{qf:e} sub-pixel points per pixel × {w} pixels is too many (max 8192)"),
            ));
        }
        let q = qf as usize;
        let sub = p / q as f64;
        let (cw, quad_err) = subcell_quadrature(2.0 * f_band * sub);
        let taps = cw.len() - 1;
        let n_ext = w * q + 2 * taps;
        if n_ext > 8192 {
            return Err(OpticsError::param(
                "max_subpixel_m",
                format!("{w}×{q} (+{taps} margin) points per side is too many (max 8192)"),
            ));
        }
        Ok(Sizing {
            lam,
            s,
            delta,
            half_win,
            n_fold,
            nb,
            df,
            f_1,
            f_b,
            m_max,
            f_band,
            q,
            sub,
            cw,
            quad_err,
            taps,
            n_ext,
        })
    }

    /// Builds the model for `grid` and `cfg`: validates, sizes the folded FFT and the band,
    /// and precomputes the transfer function and window DFT matrices.
    pub fn new(cfg: PsfConfig, grid: ApertureGrid) -> Result<Self> {
        let Sizing {
            lam,
            s,
            delta,
            half_win,
            n_fold,
            nb,
            df,
            f_1,
            f_b,
            m_max,
            f_band,
            q,
            sub,
            cw,
            quad_err,
            taps,
            n_ext,
        } = Self::sizing(&cfg, &grid)?;
        let band: Vec<i64> = (-m_max..=m_max).collect();
        // Pixel weights: the q sub-cells of a pixel, each with the 2T+1 weights around it.
        let mut kern = vec![0.0; q + 2 * taps];
        for j in 0..q {
            for (n, &c) in cw.iter().enumerate() {
                kern[taps + j + n] += c * sub;
                if n > 0 {
                    kern[taps + j - n] += c * sub;
                }
            }
        }
        let k_inv2 = 1.0 / (lam * lam);
        let h_raw = Mat::from_fn(nb, nb, |a, b| {
            let (fy, fx) = (band[a] as f64 * df, band[b] as f64 * df);
            let arg = k_inv2 - fx * fx - fy * fy;
            let tau = |f: f64| {
                let f = f.abs();
                if f <= f_1 {
                    1.0
                } else if f >= f_b {
                    0.0
                } else {
                    0.5 * (1.0 + (PI * (f - f_1) / (f_b - f_1)).cos())
                }
            };
            if arg <= 0.0 {
                c64::new(0.0, 0.0)
            } else {
                c64::from_polar(delta * delta * tau(fx) * tau(fy), TAU * s * arg.sqrt())
            }
        });
        let c = (grid.n as f64 - 1.0) * 0.5 * delta;
        let mut planner = Planner::<f64>::new();
        // Field point j sits at y_j = centre − W p/2 + (j − T + ½)δ; the grid's origin is at −c.
        let mut make_e = |center: f64| {
            let y0 = center - half_win + (0.5 - taps as f64) * sub + c;
            ChirpOp::window_dft(&mut planner, -m_max, nb, n_ext, df, y0, sub)
        };
        let (ey, ey_adj) = make_e(cfg.window_center_m[1]);
        let (ex, ex_adj) = make_e(cfg.window_center_m[0]);
        // V = E_y M E_xᵀ with E = diag(post)·K·diag(pre): the pre-multipliers act on M's rows
        // and columns, so they fold into H once here instead of into every plane.
        let h = Mat::from_fn(nb, nb, |a, b| h_raw[(a, b)] * ey.pre()[a] * ex.pre()[b]);
        let post_gain = ey.post()[0].norm_sqr() * ex.post()[0].norm_sqr();
        let weights = grid.aperture_weights();
        let p_in = weights
            .col_iter()
            .map(|c| c.iter().sum::<f64>())
            .sum::<f64>()
            * delta
            * delta;
        let fft = planner.plan_fft_forward(n_fold);
        let ifft = planner.plan_fft_inverse(n_fold);
        Ok(Self {
            cfg,
            grid,
            weights,
            q,
            taps,
            n_ext,
            kern,
            quad_err,
            f_band,
            n_fold,
            fold_rows: grid.n.min(n_fold),
            band_at: band
                .iter()
                .map(|&m| m.rem_euclid(n_fold as i64) as usize)
                .collect(),
            band,
            h,
            post_gain,
            ey,
            ex,
            ey_adj,
            ex_adj,
            p_in,
            fft,
            ifft,
            memo: Mutex::new(None),
        })
    }

    /// Bytes the model needs (about) for `depths` depths used as `usage` says, estimated before
    /// anything is built: the phase map, the pupil weights and the aperture samples (80 B per
    /// aperture sample; 56 more where the memo keeps another map's), the transfer function,
    /// one workspace per
    /// thread that works (`threads` and `depths` bound them), the planes, and for a training
    /// the gradients (16 B per aperture sample per depth and per thread). Errors as
    /// [`AsmPsf::new`] would, naming the setting.
    pub fn memory_bytes(
        cfg: &PsfConfig,
        grid: &ApertureGrid,
        depths: usize,
        threads: usize,
        usage: PsfUsage,
    ) -> Result<u64> {
        let z = Self::sizing(cfg, grid)?;
        let c = std::mem::size_of::<c64>() as u128;
        let (n2, nl, nb, ne) = (
            (grid.n as u128).pow(2),
            z.n_fold as u128,
            z.nb as u128,
            z.n_ext as u128,
        );
        let w = cfg.window_px as u128;
        let (d, workers) = (depths as u128, threads.clamp(1, depths.max(1)) as u128);
        // Phase and amplitude (the map), the pupil weights, and per sample in `Samples`: four
        // u32 indices (with the lookup table), two c64 and an f64.
        let samples = 4 * 4 + 2 * c + 8;
        let memo_samples = if usage == PsfUsage::Once { 0 } else { samples };
        let aperture = n2 * (16 + 8 + samples + memo_samples);
        // H and, while it is built, its raw samples; the four chirp operators.
        let model = 2 * nb * nb * c + 8 * (nb + ne) * c;
        let workspace = c * (ROW_BLOCK as u128 * nl + nb * nl + ne * nb + ne * ne + 2 * nl)
            + 8 * (ne * ne + ne * w);
        let memo = (d * ne * ne * c).min(FIELD_MEMO_BYTES as u128);
        let planes = 2 * d * w * w * 8;
        let grads = if usage == PsfUsage::Training {
            // Per depth a phase and an amplitude gradient, their sum, and per worker the
            // per-sample scratch.
            (d + 1 + workers) * n2 * 16
        } else {
            0
        };
        let total = aperture + model + workers * workspace + memo + planes + grads;
        Ok(total.min(u64::MAX as u128) as u64)
    }

    /// The configuration.
    pub fn config(&self) -> &PsfConfig {
        &self.cfg
    }

    /// The aperture grid.
    pub fn grid(&self) -> &ApertureGrid {
        &self.grid
    }

    /// Sub-pixel points per pixel side q of the box integration.
    pub fn subpixels(&self) -> usize {
        self.q
    }

    /// Margin T (field grid points beyond the window on each side) of the pixel integral.
    pub fn quadrature_margin(&self) -> usize {
        self.taps
    }

    /// Field grid points per side evaluated by the window DFT: W q + 2T.
    pub fn field_points(&self) -> usize {
        self.n_ext
    }

    /// Largest error of the sub-cell quadrature over the intensity's band, relative to the
    /// exact weight (a bound on the pixel integral's error relative to ∫|Î|, per axis).
    pub fn quadrature_error(&self) -> f64 {
        self.quad_err
    }

    /// Band limit f_b (1/m) of the propagated field per axis.
    pub fn band_limit(&self) -> f64 {
        self.f_band
    }

    /// FFT size N_L of the folded spectral grid and the number of band frequencies per axis.
    pub fn sizes(&self) -> (usize, usize) {
        (self.n_fold, self.band.len())
    }

    /// FFT length of the chirp-z window DFT along y (≥ N_b + W q + 2T − 1).
    pub fn chirp_len(&self) -> usize {
        self.ey.len()
    }

    /// Power incident on the aperture for a unit-amplitude wave (m²): the PSF normalization.
    pub fn incident_power_m2(&self) -> f64 {
        self.p_in
    }

    fn check_map(&self, map: &PhaseMap) -> Result<()> {
        if map.grid.n != self.grid.n
            || (map.grid.pitch_m - self.grid.pitch_m).abs() > 1e-12 * self.grid.pitch_m
            || (map.grid.diameter_m - self.grid.diameter_m).abs() > 1e-12 * self.grid.diameter_m
        {
            return Err(OpticsError::Shape(format!(
                "phase map grid {:?} differs from the model's {:?}",
                map.grid, self.grid
            )));
        }
        Ok(())
    }

    fn check_depths(depths_m: &[f64]) -> Result<()> {
        if depths_m.is_empty() {
            return Err(OpticsError::param("depths_m", "no depths given"));
        }
        for &z in depths_m {
            positive("depths_m", z)?;
        }
        Ok(())
    }

    fn samples(&self, map: &PhaseMap) -> Samples {
        let n = self.grid.n;
        let [x0, y0] = self.cfg.source_xy_m;
        // Key of a sample's distance to the source: along an axis where the source sits on
        // the grid's centre, |2i − (n−1)| (mirror pairs share it), else the index itself; on
        // axis the pair is also sorted (the diagonal mirror). Keys lie in 0..n.
        let key = |i: usize, on_axis: bool| {
            if on_axis { (2 * i).abs_diff(n - 1) } else { i }
        };
        let (sym_x, sym_y) = (x0 == 0.0, y0 == 0.0);
        let half = 0.5 * self.grid.pitch_m;
        let mut table = vec![u32::MAX; n * n];
        let cap = n * n;
        let mut out = Samples {
            fold: Vec::with_capacity(cap),
            row_at: Vec::new(),
            wave: Vec::with_capacity(cap),
            ua: Vec::with_capacity(cap),
            unit: Vec::with_capacity(cap),
            amp: Vec::with_capacity(cap),
            cell: Vec::with_capacity(cap),
            d2: Vec::new(),
        };
        for i in 0..n {
            for j in 0..n {
                let wgt = self.weights[(i, j)];
                if wgt == 0.0 {
                    continue;
                }
                let (mut kx, mut ky) = (key(j, sym_x), key(i, sym_y));
                if sym_x && sym_y && kx > ky {
                    std::mem::swap(&mut kx, &mut ky);
                }
                let slot = &mut table[kx * n + ky];
                if *slot == u32::MAX {
                    *slot = out.d2.len() as u32;
                    // On a symmetric axis the key is the doubled offset from the centre.
                    let dx = if sym_x {
                        kx as f64 * half
                    } else {
                        self.grid.coord(j) - x0
                    };
                    let dy = if sym_y {
                        ky as f64 * half
                    } else {
                        self.grid.coord(i) - y0
                    };
                    out.d2.push(dx * dx + dy * dy);
                }
                let unit = c64::from_polar(wgt, map.phase_rad[(i, j)]);
                let amp = map.amplitude[(i, j)];
                out.fold
                    .push(((i % self.n_fold) * self.n_fold + (j % self.n_fold)) as u32);
                out.wave.push(*slot);
                out.ua.push(unit * amp);
                out.unit.push(unit);
                out.amp.push(amp);
                out.cell.push((i * n + j) as u32);
            }
        }
        // Grids wider than the folded one wrap rows onto rows: order by fold index (stable,
        // so samples sharing a fold cell keep their order of summation).
        if !out.fold.is_sorted() {
            let mut perm: Vec<usize> = (0..out.fold.len()).collect();
            perm.sort_by_key(|&s| out.fold[s]);
            fn permute<T: Copy>(v: &mut Vec<T>, perm: &[usize]) {
                *v = perm.iter().map(|&s| v[s]).collect();
            }
            permute(&mut out.fold, &perm);
            permute(&mut out.wave, &perm);
            permute(&mut out.ua, &perm);
            permute(&mut out.unit, &perm);
            permute(&mut out.amp, &perm);
            permute(&mut out.cell, &perm);
        }
        let nl = self.n_fold;
        out.row_at = (0..=self.fold_rows)
            .map(|r| out.fold.partition_point(|&f| (f as usize) < r * nl) as u32)
            .collect();
        out
    }

    /// Fills `wave` with e^{ik(r−z)} for every distinct radius of `samples`.
    fn spherical_wave(&self, samples: &Samples, z: f64, wave: &mut Vec<c64>) {
        let k = TAU / self.cfg.wavelength_m;
        wave.clear();
        wave.extend(
            samples
                .d2
                .iter()
                .map(|&d2| c64::from_polar(1.0, sag_phase(k, d2, z))),
        );
    }

    fn workspace(&self) -> Workspace {
        let nl = self.n_fold;
        let nb = self.band.len();
        let ne = self.n_ext;
        let ops = [&self.ey, &self.ex, &self.ey_adj, &self.ex_adj];
        let scratch_len = ops
            .iter()
            .map(|o| o.scratch_len())
            .fold(self.fft.get_inplace_scratch_len(), usize::max)
            .max(self.ifft.get_inplace_scratch_len());
        Workspace {
            wave: Vec::new(),
            cbuf: vec![c64::new(0.0, 0.0); ops.iter().map(|o| o.buf_len()).max().unwrap_or(0)],
            blk: vec![c64::new(0.0, 0.0); ROW_BLOCK * nl],
            colbuf: vec![c64::new(0.0, 0.0); nb * nl],
            scratch: vec![c64::new(0.0, 0.0); scratch_len],
            t: Mat::zeros(ne, nb),
            v: Mat::zeros(ne, ne),
            iv: Mat::zeros(ne, ne),
            ix: Mat::zeros(ne, self.cfg.window_px),
        }
    }

    /// Field V on the (W q + 2T)² grid for depth z, left in `ws.v`, up to the unit-modulus
    /// post-multipliers of the window DFTs (|V|² = `post_gain`·|ws.v|²).
    fn field(&self, samples: &Samples, z: f64, ws: &mut Workspace) {
        let nl = self.n_fold;
        let rows = self.fold_rows;
        let nb = self.band.len();
        let zero = c64::new(0.0, 0.0);
        self.spherical_wave(samples, z, &mut ws.wave);
        // The folded grid a block of rows at a time (rows past `fold_rows` hold no samples:
        // their FFTs would be of zeros): scatter the block's samples, FFT its rows, copy its
        // band columns out. The block stays in cache throughout; writing the whole folded grid
        // (14 MB on the default rig), reading it back along columns and zeroing it made a plane
        // 6–8 % slower (examples/plane_floor.rs, with the product M below stored).
        for r0 in (0..rows).step_by(ROW_BLOCK) {
            let nr = ROW_BLOCK.min(rows - r0);
            let blk = &mut ws.blk[..nr * nl];
            blk.fill(zero);
            let base = r0 * nl;
            for s in samples.row_at[r0] as usize..samples.row_at[r0 + nr] as usize {
                blk[samples.fold[s] as usize - base] +=
                    samples.ua[s] * ws.wave[samples.wave[s] as usize];
            }
            self.fft.process_with_scratch(blk, &mut ws.scratch);
            for (col, &cx) in ws.colbuf.chunks_exact_mut(nl).zip(&self.band_at) {
                for (d, row) in col[r0..r0 + nr].iter_mut().zip(blk.chunks_exact(nl)) {
                    *d = row[cx];
                }
            }
        }
        // Band columns, COL_CHUNK at a time through one batched FFT call; each, times H, is
        // the input of the window DFT along y, T = E_y (F ⊙ H), straight away: the product
        // M = F ⊙ H (N_b², 14 MB on the default rig) is never stored and read back.
        let len = self.ey.len();
        let ne = self.n_ext;
        for b0 in (0..nb).step_by(COL_CHUNK) {
            let nc = COL_CHUNK.min(nb - b0);
            let cols = &mut ws.colbuf[b0 * nl..(b0 + nc) * nl];
            for col in cols.chunks_exact_mut(nl) {
                col[rows..].fill(zero);
            }
            self.fft.process_with_scratch(cols, &mut ws.scratch);
            let cbuf = &mut ws.cbuf[..nc * len];
            for (c, (col, row)) in cols
                .chunks_exact_mut(nl)
                .zip(cbuf.chunks_exact_mut(len))
                .enumerate()
            {
                let hc = self.h.col_as_slice(b0 + c);
                for ((r, &iy), &hv) in row.iter_mut().zip(&self.band_at).zip(hc) {
                    *r = col[iy] * hv;
                }
                row[nb..].fill(zero);
            }
            self.ey.convolve(cbuf, &mut ws.scratch);
            for (c, row) in cbuf.chunks_exact(len).enumerate() {
                ws.t.col_as_slice_mut(b0 + c).copy_from_slice(&row[..ne]);
            }
        }
        // V = T E_xᵀ (along the rows of T).
        let (t, v) = (&ws.t, &mut ws.v);
        self.ex.apply_conv(
            ne,
            &mut ws.cbuf,
            &mut ws.scratch,
            |r, b| t[(r, b)],
            |r, j, y| v[(r, j)] = y,
        );
    }

    /// Pixel integrals of |V|²: out = K (|V|²) Kᵀ with K[r, r q + i] = k_i (W × (W q + 2T)),
    /// scaled by |post|²/P_in. Uses `ws.iv` and `ws.ix`.
    fn plane_from_field(&self, ws: &mut Workspace) -> Mat<f64> {
        let (q, w, ne) = (self.q, self.cfg.window_px, self.n_ext);
        let scale = self.post_gain / self.p_in;
        for c in 0..ne {
            let vc = ws.v.col_as_slice(c);
            for (i, v) in ws.iv.col_as_slice_mut(c).iter_mut().zip(vc) {
                *i = v.norm_sqr();
            }
        }
        // Along x: ix[:, c] = Σ_i k_i iv[:, c q + i] (contiguous columns).
        for c in 0..w {
            let acc = ws.ix.col_as_slice_mut(c);
            acc.fill(0.0);
            for (i, &k) in self.kern.iter().enumerate() {
                for (a, &v) in acc.iter_mut().zip(ws.iv.col_as_slice(c * q + i)) {
                    *a += k * v;
                }
            }
        }
        // Along y: out[r, c] = Σ_i k_i ix[r q + i, c].
        Mat::from_fn(w, w, |r, c| {
            let col = ws.ix.col_as_slice(c);
            self.kern
                .iter()
                .enumerate()
                .map(|(i, &k)| k * col[r * q + i])
                .sum::<f64>()
                * scale
        })
    }

    /// PSF of one depth `depth_m` (m) in f64 (W×W, fraction of incident power per pixel).
    pub fn plane(&self, map: &PhaseMap, depth_m: f64) -> Result<Mat<f64>> {
        self.check_map(map)?;
        positive("depth_m", depth_m)?;
        let samples = self.samples(map);
        let mut ws = self.workspace();
        self.field(&samples, depth_m, &mut ws);
        Ok(self.plane_from_field(&mut ws))
    }

    /// PSF planes in f64 (zero where not active).
    pub fn planes_f64(
        &self,
        map: &PhaseMap,
        depths_m: &[f64],
        active: Option<&[bool]>,
    ) -> Result<Vec<Option<Mat<f64>>>> {
        self.check_map(map)?;
        Self::check_depths(depths_m)?;
        if let Some(a) = active
            && a.len() != depths_m.len()
        {
            return Err(OpticsError::Shape(format!(
                "active has {} flags for {} depths",
                a.len(),
                depths_m.len()
            )));
        }
        let samples = self.samples(map);
        let used = (0..depths_m.len())
            .filter(|&k| active.is_none_or(|a| a[k]))
            .count();
        let field_bytes = self.n_ext * self.n_ext * std::mem::size_of::<c64>();
        let keep = used * field_bytes <= FIELD_MEMO_BYTES;
        let out: Vec<Option<PlaneAndField>> = depths_m
            .par_iter()
            .enumerate()
            .map_init(
                || None,
                |ws: &mut Option<Workspace>, (k, &z)| {
                    if active.is_some_and(|a| !a[k]) {
                        return None;
                    }
                    let ws = ws.get_or_insert_with(|| self.workspace());
                    self.field(&samples, z, ws);
                    let plane = self.plane_from_field(ws);
                    Some((plane, keep.then(|| ws.v.clone())))
                },
            )
            .collect();
        let mut fields = Vec::new();
        let planes = out
            .into_iter()
            .zip(depths_m)
            .map(|(o, z)| {
                o.map(|(plane, v)| {
                    fields.extend(v.map(|v| (z.to_bits(), v)));
                    plane
                })
            })
            .collect();
        let memo = keep.then(|| FieldMemo {
            key: map_key(map),
            fields,
            samples,
        });
        *self.memo.lock().unwrap_or_else(|e| e.into_inner()) = memo;
        Ok(planes)
    }
}

/// Finite-difference weights (k−, k+, coefficients) of ∂/∂z at stack index `k`.
fn fd_stencil(depths: &[f64], k: usize) -> Option<(usize, usize, f64)> {
    let n = depths.len();
    if n < 2 {
        return None;
    }
    let (lo, hi) = if k == 0 {
        (0, 1)
    } else if k == n - 1 {
        (n - 2, n - 1)
    } else {
        (k - 1, k + 1)
    };
    let dz = depths[hi] - depths[lo];
    if dz == 0.0 {
        None
    } else {
        Some((lo, hi, 1.0 / dz))
    }
}

/// ∂PSF/∂z across a stack by finite differences (central inside, one-sided at the ends);
/// `None` where a needed plane is missing.
pub fn depth_derivative(depths_m: &[f64], planes: &[Option<Mat<f64>>]) -> Vec<Option<Mat<f64>>> {
    (0..planes.len())
        .map(|k| {
            let (lo, hi, inv) = fd_stencil(depths_m, k)?;
            let (a, b) = (planes[lo].as_ref()?, planes[hi].as_ref()?);
            Some(Mat::from_fn(a.nrows(), a.ncols(), |i, j| {
                (b[(i, j)] - a[(i, j)]) * inv
            }))
        })
        .collect()
}

/// Adjoint of [`depth_derivative`]: adds the plane gradients implied by `grad_dz` into `grad`.
pub fn depth_derivative_vjp(depths_m: &[f64], grad_dz: &[Mat<f64>], grad: &mut [Mat<f64>]) {
    for (k, g) in grad_dz.iter().enumerate() {
        if let Some((lo, hi, inv)) = fd_stencil(depths_m, k) {
            for j in 0..g.ncols() {
                for i in 0..g.nrows() {
                    grad[hi][(i, j)] += g[(i, j)] * inv;
                    grad[lo][(i, j)] -= g[(i, j)] * inv;
                }
            }
        }
    }
}

fn to_f32(m: &Mat<f64>) -> Mat<f32> {
    Mat::from_fn(m.nrows(), m.ncols(), |i, j| m[(i, j)] as f32)
}

impl PsfModel for AsmPsf {
    fn forward(
        &self,
        map: &PhaseMap,
        depths_m: &[f64],
        active: Option<&[bool]>,
    ) -> Result<PsfStack> {
        let planes = self.planes_f64(map, depths_m, active)?;
        Ok(PsfStack::from_planes(
            depths_m,
            self.cfg.pitch_m,
            self.cfg.window_px,
            &planes,
        ))
    }

    fn vjp(
        &self,
        map: &PhaseMap,
        depths_m: &[f64],
        grad_planes: &[Mat<f64>],
        grad_dz: Option<&[Mat<f64>]>,
    ) -> Result<PhaseMapGrad> {
        self.check_map(map)?;
        Self::check_depths(depths_m)?;
        self.check_grads("grad_planes", depths_m.len(), grad_planes)?;
        let mut grad: Vec<Mat<f64>> = grad_planes.to_vec();
        if let Some(gdz) = grad_dz {
            self.check_grads("grad_dz", depths_m.len(), gdz)?;
            depth_derivative_vjp(depths_m, gdz, &mut grad);
        }
        let memo = self.take_memo(map);
        let mut fresh = None;
        let samples = self.samples_or(map, memo.as_ref(), &mut fresh);
        let n = self.grid.n;
        let mut out = PhaseMapGrad::zeros(n);
        // Depths in chunks of one per thread (bounded memory), their terms added in depth
        // order: the sum does not depend on the thread count, and depths computed elsewhere
        // (`vjp_terms` on other processes) added in the same order give the same bits.
        let with_grad = depths_with_gradient(&grad);
        for chunk in with_grad.chunks(rayon::current_num_threads().max(1)) {
            for t in self.terms(samples, depths_m, &grad, chunk, memo.as_ref()) {
                out.add(&t);
            }
        }
        self.put_memo(memo);
        Ok(out)
    }
}

/// Depths whose upstream gradient is not all zero: the ones a PSF VJP visits (in order).
pub fn depths_with_gradient(grad_planes: &[Mat<f64>]) -> Vec<usize> {
    (0..grad_planes.len())
        .filter(|&k| {
            grad_planes[k]
                .col_iter()
                .any(|c| c.iter().any(|&v| v != 0.0))
        })
        .collect()
}

impl PhaseMapGrad {
    /// Zero gradient on an n×n aperture grid.
    pub fn zeros(n: usize) -> PhaseMapGrad {
        PhaseMapGrad {
            phase_rad: Mat::zeros(n, n),
            amplitude: Mat::zeros(n, n),
        }
    }

    /// Adds `term` cell by cell: how [`PsfModel::vjp`] sums its per-depth terms.
    pub fn add(&mut self, term: &PhaseMapGrad) {
        add_cells(&mut self.phase_rad, &term.phase_rad);
        add_cells(&mut self.amplitude, &term.amplitude);
    }
}

/// `acc += term`, cell by cell.
pub fn add_cells(acc: &mut Mat<f64>, term: &Mat<f64>) {
    for j in 0..acc.ncols() {
        for (a, &t) in acc.col_mut(j).iter_mut().zip(term.col(j).iter()) {
            *a += t;
        }
    }
}

impl AsmPsf {
    fn check_grads(&self, name: &str, nz: usize, g: &[Mat<f64>]) -> Result<()> {
        let w = self.cfg.window_px;
        if g.len() != nz || g.iter().any(|m| m.nrows() != w || m.ncols() != w) {
            return Err(OpticsError::Shape(format!(
                "{name} must hold {nz} planes of {w}×{w}"
            )));
        }
        if g.iter()
            .any(|m| m.col_iter().any(|c| c.iter().any(|v| !v.is_finite())))
        {
            return Err(OpticsError::param(
                "grad_planes",
                "non-finite upstream gradient",
            ));
        }
        Ok(())
    }

    /// The per-depth terms of [`PsfModel::vjp`] (without ∂/∂z): for each k of `which`, in that
    /// order, the gradient w.r.t. `map` of ⟨grad_planes\[k\], PSF(z_k)⟩. `vjp` is the sum of the
    /// terms of [`depths_with_gradient`], added by [`PhaseMapGrad::add`] in increasing k from
    /// zero; a depth's term does not depend on which other depths are computed with it, so
    /// shares of the depths computed on several processes and summed in that order give `vjp`'s
    /// bits.
    pub fn vjp_terms(
        &self,
        map: &PhaseMap,
        depths_m: &[f64],
        grad_planes: &[Mat<f64>],
        which: &[usize],
    ) -> Result<Vec<PhaseMapGrad>> {
        self.check_map(map)?;
        Self::check_depths(depths_m)?;
        self.check_grads("grad_planes", depths_m.len(), grad_planes)?;
        if let Some(&k) = which.iter().find(|&&k| k >= depths_m.len()) {
            return Err(OpticsError::Shape(format!(
                "depth index {k} beyond the {} depths",
                depths_m.len()
            )));
        }
        let memo = self.take_memo(map);
        let mut fresh = None;
        let samples = self.samples_or(map, memo.as_ref(), &mut fresh);
        let out = self.terms(samples, depths_m, grad_planes, which, memo.as_ref());
        self.put_memo(memo);
        Ok(out)
    }

    /// One term per depth of `which`, in parallel over depths.
    fn terms(
        &self,
        samples: &Samples,
        depths_m: &[f64],
        grad: &[Mat<f64>],
        which: &[usize],
        memo: Option<&FieldMemo>,
    ) -> Vec<PhaseMapGrad> {
        let n = self.grid.n;
        let ns = samples.len();
        let kept = |z: f64| {
            memo.and_then(|m| m.fields.iter().find(|f| f.0 == z.to_bits()))
                .map(|f| &f.1)
        };
        which
            .par_iter()
            .map_init(
                || None,
                |ws: &mut Option<Workspace>, &k| {
                    let ws = ws.get_or_insert_with(|| self.workspace());
                    let (mut gp, mut ga) = (vec![0.0; ns], vec![0.0; ns]);
                    let z = depths_m[k];
                    match kept(z) {
                        Some(v) => {
                            ws.v.copy_from(v);
                            self.spherical_wave(samples, z, &mut ws.wave);
                        }
                        None => self.field(samples, z, ws),
                    }
                    self.plane_adjoint(samples, &grad[k], ws, &mut gp, &mut ga);
                    let mut out = PhaseMapGrad::zeros(n);
                    for (s, &cell) in samples.cell.iter().enumerate() {
                        let (i, j) = (cell as usize / n, cell as usize % n);
                        out.phase_rad[(i, j)] = gp[s];
                        out.amplitude[(i, j)] = ga[s];
                    }
                    out
                },
            )
            .collect()
    }

    /// `map`'s aperture samples: the memo's when there is one, else built into `fresh`.
    fn samples_or<'m>(
        &self,
        map: &PhaseMap,
        memo: Option<&'m FieldMemo>,
        fresh: &'m mut Option<Samples>,
    ) -> &'m Samples {
        match memo {
            Some(m) => &m.samples,
            None => fresh.insert(self.samples(map)),
        }
    }

    /// The last stack's fields if they are `map`'s, taken out of the model while a VJP runs
    /// (give them back with [`AsmPsf::put_memo`]). Another map's fields stay where they are:
    /// a VJP at some other map must not cost the next VJP at the stack's map its reuse.
    fn take_memo(&self, map: &PhaseMap) -> Option<FieldMemo> {
        let mut slot = self.memo.lock().unwrap_or_else(|e| e.into_inner());
        if slot.as_ref().is_some_and(|m| same_map(&m.key, map)) {
            slot.take()
        } else {
            None
        }
    }

    /// Gives back what [`AsmPsf::take_memo`] took, unless a stack computed meanwhile left its own.
    fn put_memo(&self, memo: Option<FieldMemo>) {
        let mut slot = self.memo.lock().unwrap_or_else(|e| e.into_inner());
        if slot.is_none() {
            *slot = memo;
        }
    }
}

impl AsmPsf {
    /// Accumulates the gradient of ⟨g, PSF(z)⟩ w.r.t. phase and amplitude per sample, from
    /// the field of depth z in `ws.v` and its spherical wave in `ws.wave` (what
    /// [`AsmPsf::field`] leaves there).
    fn plane_adjoint(
        &self,
        samples: &Samples,
        g: &Mat<f64>,
        ws: &mut Workspace,
        gp: &mut [f64],
        ga: &mut [f64],
    ) {
        let (q, w, ne) = (self.q, self.cfg.window_px, self.n_ext);
        let scale = 2.0 * self.post_gain / self.p_in;
        // ∂/∂|V|² = Kᵀ g K (the transpose of `plane_from_field`'s two passes), into ws.iv.
        ws.ix.fill(0.0);
        for c in 0..w {
            let col = ws.ix.col_as_slice_mut(c);
            for r in 0..w {
                let gv = g[(r, c)];
                for (i, &k) in self.kern.iter().enumerate() {
                    col[r * q + i] += k * gv;
                }
            }
        }
        ws.iv.fill(0.0);
        for c in 0..w {
            for (i, &k) in self.kern.iter().enumerate() {
                let (src, dst) = (ws.ix.col_as_slice(c), ws.iv.col_as_slice_mut(c * q + i));
                for (d, &v) in dst.iter_mut().zip(src) {
                    *d += k * v;
                }
            }
        }
        // gV = 2 (∂/∂|V|²) |post|²/P · V (Wirtinger gradient of |V|²), written over V in place.
        for c in 0..ne {
            for r in 0..ne {
                ws.v[(r, c)] *= ws.iv[(r, c)] * scale;
            }
        }
        // V = K_y M K_xᵀ (bare convolutions, diagonals folded into H) ⇒ gT = gV·conj(K_x)
        // (rows), gM = K_yᴴ·gT (columns).
        let (t, v) = (&mut ws.t, &ws.v);
        let nb = self.band.len();
        self.ex_adj.apply_conv(
            ne,
            &mut ws.cbuf,
            &mut ws.scratch,
            |r, j| v[(r, j)],
            |r, b, y| t[(r, b)] = y,
        );
        // gM = K_yᴴ·gT a chunk of columns at a time, times conj(H) into the band rows of the
        // folded columns, inverse FFT (as in `field`, M itself is never stored) ...
        let nl = self.n_fold;
        let rows = self.fold_rows;
        let zero = c64::new(0.0, 0.0);
        let len = self.ey_adj.len();
        for b0 in (0..nb).step_by(COL_CHUNK) {
            let nc = COL_CHUNK.min(nb - b0);
            let cbuf = &mut ws.cbuf[..nc * len];
            for (c, row) in cbuf.chunks_exact_mut(len).enumerate() {
                row[..ne].copy_from_slice(ws.t.col_as_slice(b0 + c));
                row[ne..].fill(zero);
            }
            self.ey_adj.convolve(cbuf, &mut ws.scratch);
            let cols = &mut ws.colbuf[b0 * nl..(b0 + nc) * nl];
            cols.fill(zero);
            for (c, (col, row)) in cols
                .chunks_exact_mut(nl)
                .zip(cbuf.chunks_exact(len))
                .enumerate()
            {
                let hc = self.h.col_as_slice(b0 + c);
                for ((&iy, &hv), &g) in self.band_at.iter().zip(hc).zip(row) {
                    col[iy] = g * hv.conj();
                }
            }
            self.ifft.process_with_scratch(cols, &mut ws.scratch);
        }
        // ... then the rows a block at a time: the band columns in, inverse FFT, and the
        // block's samples read out (only rows that hold samples are needed).
        for r0 in (0..rows).step_by(ROW_BLOCK) {
            let nr = ROW_BLOCK.min(rows - r0);
            let blk = &mut ws.blk[..nr * nl];
            blk.fill(zero);
            for (col, &cx) in ws.colbuf.chunks_exact(nl).zip(&self.band_at) {
                for (row, &v) in blk.chunks_exact_mut(nl).zip(&col[r0..r0 + nr]) {
                    row[cx] = v;
                }
            }
            self.ifft.process_with_scratch(blk, &mut ws.scratch);
            // `field` left e^{ik(r−z)} per distinct radius in ws.wave.
            let base = r0 * nl;
            for s in samples.row_at[r0] as usize..samples.row_at[r0 + nr] as usize {
                let gu = blk[samples.fold[s] as usize - base];
                let e = samples.unit[s] * ws.wave[samples.wave[s] as usize];
                let u = e * samples.amp[s];
                gp[s] += (gu * u.conj()).im;
                ga[s] += (gu.conj() * e).re;
            }
        }
    }
}

#[cfg(test)]
mod memo_tests {
    use super::*;

    fn model_and_maps() -> (AsmPsf, PhaseMap, PhaseMap) {
        let grid = ApertureGrid::new(40e-6, 2e-6).unwrap();
        let k = std::f64::consts::TAU / 940e-9;
        let lens = |f: f64| {
            Mat::from_fn(grid.n, grid.n, |i, j| {
                let (y, x) = (grid.coord(i), grid.coord(j));
                -k * (x * x + y * y) / (2.0 * f)
            })
        };
        let ones = Mat::from_fn(grid.n, grid.n, |_, _| 1.0);
        let a = PhaseMap::new(grid, lens(90e-6), ones.clone()).unwrap();
        let b = PhaseMap::new(grid, lens(95e-6), ones).unwrap();
        let cfg = PsfConfig {
            sensor_distance_m: 100e-6,
            pitch_m: 1e-6,
            window_px: 8,
            ..PsfConfig::default()
        };
        (AsmPsf::new(cfg, grid).unwrap(), a, b)
    }

    /// The memo key test agrees with building the key, and one changed sample (phase or
    /// amplitude) is a different map.
    #[test]
    fn same_map_is_the_key_comparison() {
        let (_, a, b) = model_and_maps();
        let key = map_key(&a);
        assert!(same_map(&key, &a));
        assert!(!same_map(&key, &b));
        let mut c = a.clone();
        c.amplitude[(3, 4)] = f64::from_bits(c.amplitude[(3, 4)].to_bits() - 1);
        assert!(!same_map(&key, &c));
        assert!(!same_map(&key[1..], &a));
    }

    /// A VJP at another map leaves the stack's fields in the model (it used to drop them), and
    /// the VJP at the stack's map takes and gives them back.
    #[test]
    fn a_vjp_at_another_map_keeps_the_stacks_fields() {
        let (model, a, b) = model_and_maps();
        let depths = [0.8e-3, 1.0e-3];
        model.planes_f64(&a, &depths, None).unwrap();
        let held = |m: &PhaseMap| {
            model
                .memo
                .lock()
                .unwrap()
                .as_ref()
                .is_some_and(|f| same_map(&f.key, m) && f.fields.len() == depths.len())
        };
        assert!(held(&a));
        let g: Vec<Mat<f64>> = depths
            .iter()
            .map(|_| Mat::from_fn(8, 8, |_, _| 1.0))
            .collect();
        model.vjp(&b, &depths, &g, None).unwrap();
        assert!(held(&a), "a VJP at another map dropped the stack's fields");
        model.vjp(&a, &depths, &g, None).unwrap();
        assert!(held(&a));
    }
}

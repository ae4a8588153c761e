//! Occlusion-aware layered image formation (S1, after Ikoma et al. 2021):
//! I⁽ᵏ⁾ = (α_k L_k) ∗ P_k + (1 − α_k ∗ P_k) · I⁽ᵏ⁻¹⁾, layers ordered back to front, I⁽⁻¹⁾ = 0,
//! with its VJP w.r.t. radiance, alpha and PSF.
//!
//! Convolution is linear ("same" size, zeros outside the image), by FFT on a grid padded to
//! at least H + W_p − 1. Both real convolutions of a layer share one complex FFT: αL + iα is
//! transformed once and multiplied by the real kernel's spectrum, so the real part carries
//! αL ∗ P and the imaginary part α ∗ P – the same saving a real-to-complex transform gives,
//! without an extra dependency.

use crate::error::{OpticsError, Result};
use crate::psf::fast_fft_size;
use faer::{Mat, MatRef, c32, c64};
use nanoeye_fft::{Fft, Float, Planner};
use std::ops::Range;
use std::sync::{Arc, Mutex};

mod tiled;

/// Columns per block in the column pass of the 2-D FFT. A block of 32 columns of S1's
/// 864-row paper-size grid is 442 KB, and the backward pass's two blocks stay in a 1 MB L2;
/// each row then yields 512 contiguous bytes to the strided gather instead of 256 (16 columns:
/// the paper-size chain's backward 5–10 % slower, `chain_floor`).
const COLS: usize = 32;

/// Side of the square tiles in which a column-major matrix meets a row-major grid.
const TILE: usize = 32;

/// Rows packed at once from a layer's column-major matrices: each column then gives 128
/// consecutive f32 (eight cache lines, which the prefetcher streams) per band instead of one
/// value per row, and the band (128 padded rows, 2.75 MB at 1344 columns) stays in the last-
/// level cache until its rows are transformed. With 16 rows (one line per column) the loads
/// waited on memory: packing took 18 % of `chain_floor`'s samples, 12 % with 128.
const PACK_ROWS: usize = 128;

/// Partial sums of the PSF adjoint's dot product with the convolved radiance.
const DOT_LANES: usize = 8;

/// Work spaces kept for reuse per imager: more than the threads that image frames at once
/// is never needed.
const POOL_MAX: usize = 16;

/// Spent gradient spectra kept for reuse per imager: a batch's frames in flight times the
/// kernels (8 slabs × 4 frames in `search`), beyond which they are freed.
const SPARE_MAX: usize = 32;

/// Values handed back by finished calls for the next ones to take, at most `max` kept.
struct Pool<T> {
    items: Mutex<Vec<T>>,
    max: usize,
}

impl<T> Pool<T> {
    fn new(max: usize) -> Self {
        Self {
            items: Mutex::new(Vec::new()),
            max,
        }
    }

    /// A kept value, if any (a poisoned lock only costs the reuse).
    fn take(&self) -> Option<T> {
        self.items.lock().ok()?.pop()
    }

    /// Keeps `v` unless `max` are kept already.
    fn give(&self, v: T) {
        if let Ok(mut items) = self.items.lock()
            && items.len() < self.max
        {
            items.push(v);
        }
    }
}

/// How a layer's planes lie in memory: S1 reads them row by row when every plane's rows are
/// contiguous (S1's grid is row-major, so the pack is then a stream), else column by column.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Layout {
    Rows,
    Cols,
}

/// Whether `m`'s lines in layout `by` (its rows or its columns) are contiguous.
fn allows(m: MatRef<'_, f32>, by: Layout) -> bool {
    match by {
        Layout::Rows => m.col_stride() == 1,
        Layout::Cols => m.row_stride() == 1,
    }
}

/// The contiguous lines of `m` in layout `by` (its rows or its columns) as slices; `m` must
/// [`allows`] `by`.
fn lines<'a>(m: MatRef<'a, f32>, by: Layout) -> Vec<&'a [f32]> {
    match by {
        Layout::Rows => (0..m.nrows())
            .map(|r| {
                m.row(r)
                    .try_as_row_major()
                    .expect("rows checked contiguous")
                    .as_slice()
            })
            .collect(),
        Layout::Cols => (0..m.ncols())
            .map(|c| {
                m.col(c)
                    .try_as_col_major()
                    .expect("columns checked contiguous")
                    .as_slice()
            })
            .collect(),
    }
}

/// A layer's planes as lines in their shared layout: the layout, α's, L's and the weight's
/// ([`SpectralLayer::lines`]).
type Lines<'a> = (
    Layout,
    Vec<&'a [f32]>,
    Vec<&'a [f32]>,
    Option<Vec<&'a [f32]>>,
);

/// A value type ∂loss/∂I may be given in to [`LayeredImager::vjp_kernels`], which runs its
/// pass in f32: an f32 gradient (the sensor's) goes in without a widened copy.
pub trait GradValue: Copy {
    /// The value rounded to f32.
    fn to_f32(self) -> f32;

    /// The H×W matrix `m` rounded to f32, row-major into `out` (H·W values).
    fn rows_into(m: &Mat<Self>, out: &mut [f32]) {
        let w = m.ncols();
        tiles(m.nrows(), w, |r, c| out[r * w + c] = m[(r, c)].to_f32());
    }
}

impl GradValue for f32 {
    fn to_f32(self) -> f32 {
        self
    }

    fn rows_into(m: &Mat<f32>, out: &mut [f32]) {
        let (h, w) = (m.nrows(), m.ncols());
        assert!(out.len() == h * w);
        // Column c of `m` is row c of a w×h row-major array with the matrix's column stride.
        let cols: Vec<&[f32]> = (0..w).map(|c| m.col_as_slice(c)).collect();
        transpose_f32(&cols, out, w, h);
    }
}

impl GradValue for f64 {
    fn to_f32(self) -> f32 {
        self as f32
    }
}

/// One pixel of the PSF adjoint's pass over a layer, for ∂L/∂I⁽ᵏ⁾ = `gv`, I⁽ᵏ⁻¹⁾ = `p`,
/// α∗P = `o` and I⁽ᵏ⁾ = `above`: gv times the convolved radiance (the radiance scale's
/// gradient term), the gradient's complex value (real: radiance channel, imaginary: occlusion
/// channel) and ∂L/∂I⁽ᵏ⁻¹⁾ = gv·(1 − o).
#[inline(always)]
fn adjoint_pixel(gain: f64, gv: f32, p: f32, o: f32, above: f32) -> (f64, f32, f32, f32) {
    let (g, p64, o64) = (gv as f64, p as f64, o as f64);
    let conv = above as f64 - (1.0 - o64) * p64;
    let v = gradient_value(gain, gv, p);
    (g * conv, v.re, v.im, gv * (1.0 - o))
}

/// The gradient's complex value at one pixel for ∂L/∂I⁽ᵏ⁾ = `gv` and I⁽ᵏ⁻¹⁾ = `p` (real:
/// radiance channel, imaginary: occlusion channel), as [`adjoint_pixel`] gives it.
#[inline(always)]
fn gradient_value(gain: f64, gv: f32, p: f32) -> c32 {
    c32::new((gain * gv as f64) as f32, -gv * p)
}

/// A layer's gain (its f32 gain times its power-of-two radiance scale) as f32 where f32 holds
/// it exactly, which it does unless the product leaves f32's range: the f64 product of such a
/// gain and an f32 value is exact, so its rounding to f32 is the f32 product's. The
/// composition and [`gradient_value`] then give their f64 form's bits in f32's eight lanes,
/// without conversions. Called once per layer or tile row, outside the pixel loops.
#[inline]
fn exact_f32(gain: f64) -> Option<f32> {
    let g = gain as f32;
    (g as f64 == gain).then_some(g)
}

/// [`gradient_value`] for a gain `g` that f32 holds exactly ([`exact_f32`]): the same bits.
#[inline(always)]
fn gradient_value_f32(g: f32, gv: f32, p: f32) -> c32 {
    c32::new(g * gv, -gv * p)
}

/// `emit` for [`adjoint_blocks`] writing the complex values into the row `gs`.
#[inline(always)]
fn into_row(gs: &mut [c32]) -> impl FnMut(usize, &[f32], &[f32]) + '_ {
    |i, re, im| {
        for (g, (&re, &im)) in gs[i..i + re.len()].iter_mut().zip(re.iter().zip(im)) {
            *g = c32::new(re, im);
        }
    }
}

/// One row of the PSF adjoint's pass ([`adjoint_pixel`] per pixel): the gradient's complex
/// values into `gs` (when given: the tiled path takes them window by window instead),
/// ∂L/∂I⁽ᵏ⁻¹⁾ over `gi` in place, the dot product into `dots`, in [`DOT_LANES`] partial sums
/// so that the pass vectorises (one running sum is a chain of dependent scalar adds).
#[inline]
fn adjoint_row(
    gain: f64,
    gi: &mut [f32],
    prev: &[f32],
    o: &[f32],
    above: &[f32],
    gs: Option<&mut [c32]>,
    dots: &mut [f64; DOT_LANES],
) {
    // The f32 form of the complex values (as the tiled windows take them) measured no gain
    // here: the whole-grid backward of a 320×200 frame, one thread, minimum of 500 calls,
    // 3.2–3.4 against 3.1–3.3 ms (four rounds).
    match gs {
        Some(gs) => adjoint_blocks(gain, gi, (prev, o, above), dots, into_row(gs)),
        // Without the complex values LLVM drops their arithmetic from the loop.
        None => adjoint_blocks(gain, gi, (prev, o, above), dots, |_, _, _| ()),
    }
}

/// [`adjoint_row`]'s pass, the gradient's complex values of pixels i.. given to
/// `emit(i, re, im)` a block of [`DOT_LANES`] at a time (the row's last w mod 8 one at a
/// time). Each block is read into registers whole and written back whole, the sums kept in
/// registers across blocks: with stores between its loads, LLVM gathered the operands one
/// value at a time (a third of the tiled backward's own time).
#[inline(always)]
fn adjoint_blocks(
    gain: f64,
    gi: &mut [f32],
    (prev, o, above): (&[f32], &[f32], &[f32]),
    dots: &mut [f64; DOT_LANES],
    mut emit: impl FnMut(usize, &[f32], &[f32]),
) {
    let w = gi.len();
    let body = w - w % DOT_LANES;
    let mut sums = *dots;
    for (c, (((gv, p), oo), ab)) in gi[..body]
        .chunks_exact_mut(DOT_LANES)
        .zip(prev[..body].chunks_exact(DOT_LANES))
        .zip(o[..body].chunks_exact(DOT_LANES))
        .zip(above[..body].chunks_exact(DOT_LANES))
        .enumerate()
    {
        let gv: &mut [f32; DOT_LANES] = gv.try_into().expect("a whole block");
        let p: &[f32; DOT_LANES] = p.try_into().expect("a whole block");
        let oo: &[f32; DOT_LANES] = oo.try_into().expect("a whole block");
        let ab: &[f32; DOT_LANES] = ab.try_into().expect("a whole block");
        let (g0, mut g1) = (*gv, [0.0f32; DOT_LANES]);
        let (mut re, mut im) = ([0.0f32; DOT_LANES], [0.0f32; DOT_LANES]);
        for j in 0..DOT_LANES {
            let (d, r, i, g) = adjoint_pixel(gain, g0[j], p[j], oo[j], ab[j]);
            (sums[j], re[j], im[j], g1[j]) = (sums[j] + d, r, i, g);
        }
        *gv = g1;
        emit(c * DOT_LANES, &re, &im);
    }
    for i in body..w {
        let (d, r, im, g) = adjoint_pixel(gain, gi[i], prev[i], o[i], above[i]);
        (sums[0], gi[i]) = (sums[0] + d, g);
        emit(i, &[r], &[im]);
    }
    *dots = sums;
}

/// `dst[c·h + r] = rows[r][c]` for the h rows `rows` (each at least w long) into the
/// row-major w×h `dst`: tile by tile as [`tiles`], 8×8 blocks in registers where AVX2 is
/// compiled in (the workspace builds for x86-64-v3), the tiles' edges one value at a time.
fn transpose_f32(rows: &[&[f32]], dst: &mut [f32], h: usize, w: usize) {
    // Checked once: the register blocks below read and write inside these bounds.
    assert!(rows.len() == h && rows.iter().all(|r| r.len() >= w) && dst.len() == h * w);
    // SAFETY: dst holds (w − 1)·h + h values (asserted), rows h of at least w.
    unsafe { transpose_raw(rows, dst.as_mut_ptr(), h, h, w) }
}

/// [`transpose_f32`] into `dst` with columns `ld` apart: `dst[c·ld + r] = rows[r][c]`.
///
/// # Safety
/// `rows` holds h rows of at least w values; `dst` is valid for writes at c·ld + r for every
/// r < h, c < w, and no reference to those values lives during the call.
unsafe fn transpose_raw(rows: &[&[f32]], dst: *mut f32, ld: usize, h: usize, w: usize) {
    debug_assert!(rows.len() == h && rows.iter().all(|r| r.len() >= w) && ld >= h);
    for r0 in (0..h).step_by(TILE) {
        let r1 = (r0 + TILE).min(h);
        for c0 in (0..w).step_by(TILE) {
            let c1 = (c0 + TILE).min(w);
            #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
            let (r8, c8) = {
                let (r8, c8) = (r1 - (r1 - r0) % 8, c1 - (c1 - c0) % 8);
                for r in (r0..r8).step_by(8) {
                    let src: [*const f32; 8] = std::array::from_fn(|i| rows[r + i].as_ptr());
                    for c in (c0..c8).step_by(8) {
                        // SAFETY: rows r .. r + 8 ≤ h hold at least c + 8 ≤ w values, and
                        // dst columns c .. c + 8 of ld values hold rows r .. r + 8 (contract).
                        unsafe { transpose8(src, c, dst, ld, r) };
                    }
                }
                (r8, c8)
            };
            #[cfg(not(all(target_arch = "x86_64", target_feature = "avx2")))]
            let (r8, c8) = (r0, c0);
            for (r, row) in rows.iter().enumerate().take(r1).skip(r0) {
                let cs = if r < r8 { c8..c1 } else { c0..c1 };
                for c in cs {
                    // SAFETY: r < h, c < w (contract).
                    unsafe { dst.add(c * ld + r).write(row[c]) };
                }
            }
        }
    }
}

/// Values c .. c + 8 of the eight rows `src` into rows c .. c + 8, columns r .. r + 8 of the
/// row-major `dst` whose rows are `ld` values apart: the 8×8 transposition by unpacks,
/// shuffles and 128-bit permutes.
///
/// # Safety
/// Each `src[i]` is valid for reads of c + 8 values; `dst` for writes at (c + j)·ld + r + i,
/// i, j < 8.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
#[inline]
unsafe fn transpose8(src: [*const f32; 8], c: usize, dst: *mut f32, ld: usize, r: usize) {
    use std::arch::x86_64::*;
    // SAFETY: inside the rows and `dst` by the contract; unaligned loads and stores.
    unsafe {
        let v = src.map(|p| _mm256_loadu_ps(p.add(c)));
        let t0 = _mm256_unpacklo_ps(v[0], v[1]);
        let t1 = _mm256_unpackhi_ps(v[0], v[1]);
        let t2 = _mm256_unpacklo_ps(v[2], v[3]);
        let t3 = _mm256_unpackhi_ps(v[2], v[3]);
        let t4 = _mm256_unpacklo_ps(v[4], v[5]);
        let t5 = _mm256_unpackhi_ps(v[4], v[5]);
        let t6 = _mm256_unpacklo_ps(v[6], v[7]);
        let t7 = _mm256_unpackhi_ps(v[6], v[7]);
        let u0 = _mm256_shuffle_ps::<0x44>(t0, t2);
        let u1 = _mm256_shuffle_ps::<0xEE>(t0, t2);
        let u2 = _mm256_shuffle_ps::<0x44>(t1, t3);
        let u3 = _mm256_shuffle_ps::<0xEE>(t1, t3);
        let u4 = _mm256_shuffle_ps::<0x44>(t4, t6);
        let u5 = _mm256_shuffle_ps::<0xEE>(t4, t6);
        let u6 = _mm256_shuffle_ps::<0x44>(t5, t7);
        let u7 = _mm256_shuffle_ps::<0xEE>(t5, t7);
        let out = [
            _mm256_permute2f128_ps::<0x20>(u0, u4),
            _mm256_permute2f128_ps::<0x20>(u1, u5),
            _mm256_permute2f128_ps::<0x20>(u2, u6),
            _mm256_permute2f128_ps::<0x20>(u3, u7),
            _mm256_permute2f128_ps::<0x31>(u0, u4),
            _mm256_permute2f128_ps::<0x31>(u1, u5),
            _mm256_permute2f128_ps::<0x31>(u2, u6),
            _mm256_permute2f128_ps::<0x31>(u3, u7),
        ];
        for (j, o) in out.into_iter().enumerate() {
            _mm256_storeu_ps(dst.add((c + j) * ld + r), o);
        }
    }
}

/// Visits every (r, c) of an h × w matrix tile by tile, so that a column-major and a
/// row-major array both stay within a few pages while they are copied into each other.
#[inline]
fn tiles(h: usize, w: usize, mut f: impl FnMut(usize, usize)) {
    for r0 in (0..h).step_by(TILE) {
        for c0 in (0..w).step_by(TILE) {
            for c in c0..(c0 + TILE).min(w) {
                for r in r0..(r0 + TILE).min(h) {
                    f(r, c);
                }
            }
        }
    }
}

/// One depth layer: radiance L (H×W), alpha α ∈ [0, 1] (H×W) and the PSF of its depth
/// (W_p×W_p, kernel centre at index (W_p/2, W_p/2)).
#[derive(Clone, Copy, Debug)]
pub struct Layer<'a> {
    /// Radiance L_k (any non-negative unit; the image carries the same unit).
    pub radiance: &'a Mat<f32>,
    /// Coverage α_k (dimensionless).
    pub alpha: &'a Mat<f32>,
    /// PSF P_k of the layer's depth (dimensionless energy fractions).
    pub psf: &'a Mat<f32>,
}

/// Gradients of a scalar loss w.r.t. every layer's inputs (zero for skipped layers).
#[derive(Clone, Debug)]
pub struct LayerGrads {
    /// ∂loss/∂L_k.
    pub radiance: Vec<Mat<f64>>,
    /// ∂loss/∂α_k.
    pub alpha: Vec<Mat<f64>>,
    /// ∂loss/∂P_k.
    pub psf: Vec<Mat<f64>>,
}

/// The padded grid's four transforms, planned in one precision.
struct Plans<T: Float> {
    fy: Arc<dyn Fft<T>>,
    fx: Arc<dyn Fft<T>>,
    iy: Arc<dyn Fft<T>>,
    ix: Arc<dyn Fft<T>>,
}

impl<T: Float> Plans<T> {
    fn new(ny: usize, nx: usize) -> Self {
        let mut pl = Planner::<T>::new();
        Self {
            fy: pl.plan_fft_forward(ny),
            fx: pl.plan_fft_forward(nx),
            iy: pl.plan_fft_inverse(ny),
            ix: pl.plan_fft_inverse(nx),
        }
    }

    /// Scratch length that serves all four.
    fn scratch_len(&self) -> usize {
        [&self.fy, &self.fx, &self.iy, &self.ix]
            .iter()
            .map(|f| f.get_inplace_scratch_len())
            .max()
            .unwrap_or(0)
    }
}

/// Planned FFTs for images of H×W with PSFs of W_p×W_p; reusable across calls.
pub struct LayeredImager {
    h: usize,
    w: usize,
    wp: usize,
    ny: usize,
    nx: usize,
    /// The reference path's transforms ([`Self::forward`], [`Self::vjp`]), in f64.
    p64: Plans<f64>,
    /// The spectral path's, in f32: its inputs, spectra and image are f32, and an f32
    /// transform of the paper-size grid takes 0.45× the time of an f64 one on AVX2 (half the
    /// bytes moved, twice the lanes); its round-off, ~1e-6 of the grid's norm, is far below
    /// a pixel's shot noise.
    p32: Plans<f32>,
    /// Work spaces of finished spectral calls, taken by the next ones: a padded grid is
    /// 9.3 MB at 1280×800 (f32), and allocating and zeroing two per frame showed in profiles.
    pool: Pool<SpectralBuffers>,
    /// Spectra of merged or finished gradient accumulators (ny·nx each, contents stale): a
    /// frame's accumulator needs one per kernel, 9.3 MB each at 1280×800, and fresh ones were
    /// most of the page faults of a backward pass.
    spare: Pool<Vec<c32>>,
    /// The tiled spectral path's geometry, plans and work spaces, when it is used
    /// ([`Self::with_tiles`]).
    tiling: Option<tiled::Tiling>,
}

/// Per layer kept for the VJP: the image below it I⁽ᵏ⁻¹⁾ and its occlusion α∗P.
type Saved = Option<(Mat<f64>, Mat<f64>)>;

/// Work space of the spectral path (see [`LayeredImager::spectral_buffers`]).
struct SpectralBuffers {
    a: Vec<c32>,
    blk: Vec<c32>,
    blk2: Vec<c32>,
    scratch: Vec<c32>,
    /// The gradient's padded grid of [`LayeredImager::vjp_kernels`] (empty until needed).
    g: Vec<c32>,
}

struct Buffers {
    a: Vec<c64>,
    p: Vec<c64>,
    /// Column blocks of the 2-D FFT (COLS × ny).
    work: Vec<c64>,
    scratch: Vec<c64>,
}

impl LayeredImager {
    /// Imager for H×W images and W_p×W_p PSFs; its spectral path runs on tiles when the
    /// padded grid is large (docs/optics.md, "Tiles"), else on the whole grid.
    pub fn new(height: usize, width: usize, psf_px: usize) -> Result<Self> {
        let mut im = Self::whole(height, width, psf_px)?;
        if let Some(t) = tiled::auto_tile(height, width, psf_px, im.ny * im.nx) {
            im.tiling = Some(tiled::Tiling::new(height, width, psf_px, t));
        }
        Ok(im)
    }

    /// Imager whose spectral path runs on tiles of at least `tile`×`tile` pixels (widened
    /// to fill the tiles' transform; at most the image's longer side), or on the whole
    /// padded grid for `None`.
    pub fn with_tiles(
        height: usize,
        width: usize,
        psf_px: usize,
        tile: Option<usize>,
    ) -> Result<Self> {
        let mut im = Self::whole(height, width, psf_px)?;
        if let Some(t) = tile {
            let most = height.max(width);
            if t == 0 || t > most {
                return Err(OpticsError::param(
                    "tile",
                    format!("must be 1..={most} pixels (the image's longer side), got {t}"),
                ));
            }
            im.tiling = Some(tiled::Tiling::new(height, width, psf_px, t));
        }
        Ok(im)
    }

    /// The side of the tiles its spectral path runs on (`None`: the whole padded grid).
    pub fn tile(&self) -> Option<usize> {
        self.tiling.as_ref().map(|t| t.t)
    }

    /// Imager whose spectral path runs on the whole padded grid.
    fn whole(height: usize, width: usize, psf_px: usize) -> Result<Self> {
        for (name, v) in [("height", height), ("width", width), ("psf_px", psf_px)] {
            if v == 0 || v > 16384 {
                return Err(OpticsError::param(
                    name,
                    format!("must be 1..=16384, got {v}"),
                ));
            }
        }
        let ny = fast_fft_size(height + psf_px - 1);
        let nx = fast_fft_size(width + psf_px - 1);
        Ok(Self {
            h: height,
            w: width,
            wp: psf_px,
            ny,
            nx,
            p64: Plans::new(ny, nx),
            p32: Plans::new(ny, nx),
            pool: Pool::new(POOL_MAX),
            spare: Pool::new(SPARE_MAX),
            tiling: None,
        })
    }

    fn buffers(&self) -> Buffers {
        let s = self.p64.scratch_len();
        let z = c64::new(0.0, 0.0);
        Buffers {
            a: vec![z; self.ny * self.nx],
            p: vec![z; self.ny * self.nx],
            work: vec![z; COLS * self.ny],
            scratch: vec![z; s],
        }
    }

    /// 2-D FFT of the ny × nx row-major grid `data` in place: rows, then columns. `span`
    /// limits the work to what the caller has or needs: forward, the rows holding data (the
    /// transform of a zero row is zero, so the others are skipped); inverse, the columns it
    /// will read (the others are left after the row pass only). Same arithmetic per row and
    /// column as the whole transform, so the values it computes are the same.
    fn fft2(
        &self,
        data: &mut [c64],
        work: &mut [c64],
        scratch: &mut [c64],
        inverse: bool,
        span: Range<usize>,
    ) {
        let (nx, ny) = (self.nx, self.ny);
        let (rf, cf, rows, cols) = if inverse {
            (&self.p64.ix, &self.p64.iy, 0..ny, span)
        } else {
            (&self.p64.fx, &self.p64.fy, span, 0..nx)
        };
        rf.process_with_scratch(&mut data[rows.start * nx..rows.end * nx], scratch);
        // Columns in blocks of COLS: one row's block is a few whole cache lines, where a
        // single column would touch one line per row for 16 bytes of it.
        let mut c0 = cols.start;
        while c0 < cols.end {
            let bw = COLS.min(cols.end - c0);
            let work = &mut work[..bw * ny];
            for (r, row) in data.chunks_exact(nx).enumerate() {
                for (j, &v) in row[c0..c0 + bw].iter().enumerate() {
                    work[j * ny + r] = v;
                }
            }
            cf.process_with_scratch(work, scratch);
            for (r, row) in data.chunks_exact_mut(nx).enumerate() {
                for (j, v) in row[c0..c0 + bw].iter_mut().enumerate() {
                    *v = work[j * ny + r];
                }
            }
            c0 += bw;
        }
    }

    fn check(&self, layers: &[Layer]) -> Result<()> {
        for (k, l) in layers.iter().enumerate() {
            let shapes = [
                (
                    l.radiance.nrows(),
                    l.radiance.ncols(),
                    self.h,
                    self.w,
                    "radiance",
                ),
                (l.alpha.nrows(), l.alpha.ncols(), self.h, self.w, "alpha"),
                (l.psf.nrows(), l.psf.ncols(), self.wp, self.wp, "psf"),
            ];
            for (r, c, er, ec, name) in shapes {
                if r != er || c != ec {
                    return Err(OpticsError::Shape(format!(
                        "layer {k}: {name} is {r}×{c}, expected {er}×{ec}"
                    )));
                }
            }
            for m in [l.radiance, l.alpha, l.psf] {
                if m.col_iter().any(|c| c.iter().any(|v| !v.is_finite())) {
                    return Err(OpticsError::param(
                        "layers",
                        format!("layer {k} holds non-finite values"),
                    ));
                }
            }
        }
        Ok(())
    }

    fn empty(l: &Layer) -> bool {
        l.alpha.col_iter().all(|c| c.iter().all(|&v| v == 0.0))
    }

    /// P̂ of a layer into `b.p`.
    fn psf_spectrum(&self, l: &Layer, b: &mut Buffers) {
        b.p.fill(c64::new(0.0, 0.0));
        for r in 0..self.wp {
            for c in 0..self.wp {
                b.p[r * self.nx + c] = c64::new(l.psf[(r, c)] as f64, 0.0);
            }
        }
        self.fft2(&mut b.p, &mut b.work, &mut b.scratch, false, 0..self.wp);
    }

    /// (αL ∗ P, α ∗ P) of one layer, cropped to H×W, as one complex image in `b.a` (spatial).
    fn convolve(&self, l: &Layer, b: &mut Buffers) {
        self.psf_spectrum(l, b);
        b.a.fill(c64::new(0.0, 0.0));
        for r in 0..self.h {
            for c in 0..self.w {
                let al = l.alpha[(r, c)] as f64;
                b.a[r * self.nx + c] = c64::new(al * l.radiance[(r, c)] as f64, al);
            }
        }
        self.fft2(&mut b.a, &mut b.work, &mut b.scratch, false, 0..self.h);
        let norm = 1.0 / (self.ny * self.nx) as f64;
        b.a.iter_mut().zip(&b.p).for_each(|(a, p)| *a *= p * norm);
        self.fft2(
            &mut b.a,
            &mut b.work,
            &mut b.scratch,
            true,
            self.wp / 2..self.wp / 2 + self.w,
        );
    }

    fn forward_f64(&self, layers: &[Layer], keep: bool) -> (Mat<f64>, Vec<Saved>) {
        let (cy, cx) = (self.wp / 2, self.wp / 2);
        let mut img = Mat::<f64>::zeros(self.h, self.w);
        let mut saved = Vec::with_capacity(layers.len());
        let mut b = self.buffers();
        for l in layers {
            if Self::empty(l) {
                saved.push(None);
                continue;
            }
            self.convolve(l, &mut b);
            let o = Mat::from_fn(self.h, self.w, |r, c| b.a[(r + cy) * self.nx + c + cx].im);
            if keep {
                saved.push(Some((img.clone(), o.clone())));
            }
            for c in 0..self.w {
                for r in 0..self.h {
                    let conv = b.a[(r + cy) * self.nx + c + cx].re;
                    img[(r, c)] = conv + (1.0 - o[(r, c)]) * img[(r, c)];
                }
            }
        }
        (img, saved)
    }

    /// Sensor-plane intensity I (H×W) of the layers (back to front); layers with α ≡ 0 skipped.
    pub fn forward(&self, layers: &[Layer]) -> Result<Mat<f32>> {
        self.check(layers)?;
        let (img, _) = self.forward_f64(layers, false);
        Ok(Mat::from_fn(self.h, self.w, |r, c| img[(r, c)] as f32))
    }

    /// [`Self::forward`] in f64 (the accumulation precision), for losses and gradient checks.
    pub fn forward_f64_image(&self, layers: &[Layer]) -> Result<Mat<f64>> {
        self.check(layers)?;
        Ok(self.forward_f64(layers, false).0)
    }

    /// Gradients w.r.t. each layer's radiance, alpha and PSF of a loss with ∂loss/∂I = `grad`.
    pub fn vjp(&self, layers: &[Layer], grad: &Mat<f64>) -> Result<LayerGrads> {
        self.check(layers)?;
        if grad.nrows() != self.h || grad.ncols() != self.w {
            return Err(OpticsError::Shape(format!(
                "grad is {}×{}, image is {}×{}",
                grad.nrows(),
                grad.ncols(),
                self.h,
                self.w
            )));
        }
        let (_, saved) = self.forward_f64(layers, true);
        let n = layers.len();
        let mut out = LayerGrads {
            radiance: vec![Mat::zeros(self.h, self.w); n],
            alpha: vec![Mat::zeros(self.h, self.w); n],
            psf: vec![Mat::zeros(self.wp, self.wp); n],
        };
        let (cy, cx) = (self.wp / 2, self.wp / 2);
        let mut gi = grad.clone();
        let mut b = self.buffers();
        let mut g = vec![c64::new(0.0, 0.0); self.ny * self.nx];
        let norm = 1.0 / (self.ny * self.nx) as f64;
        for k in (0..n).rev() {
            let Some((prev, o)) = &saved[k] else { continue };
            let l = &layers[k];
            // g_c = gI (to αL∗P), g_o = −gI·I⁽ᵏ⁻¹⁾ (to α∗P), packed as g_c + i g_o at the
            // output's offset (cy, cx) in the padded grid.
            g.fill(c64::new(0.0, 0.0));
            for r in 0..self.h {
                for c in 0..self.w {
                    g[(r + cy) * self.nx + c + cx] =
                        c64::new(gi[(r, c)], -gi[(r, c)] * prev[(r, c)]);
                }
            }
            for c in 0..self.w {
                for r in 0..self.h {
                    gi[(r, c)] *= 1.0 - o[(r, c)];
                }
            }
            self.fft2(&mut g, &mut b.work, &mut b.scratch, false, cy..cy + self.h);
            // Â of the packed input αL + iα.
            b.a.fill(c64::new(0.0, 0.0));
            for r in 0..self.h {
                for c in 0..self.w {
                    let al = l.alpha[(r, c)] as f64;
                    b.a[r * self.nx + c] = c64::new(al * l.radiance[(r, c)] as f64, al);
                }
            }
            self.fft2(&mut b.a, &mut b.work, &mut b.scratch, false, 0..self.h);
            // ∂/∂P(u,v) = Re Σ G(t+u) conj(A(t)) → IFFT(Ĝ·conj(Â)).
            b.a.iter_mut()
                .zip(&g)
                .for_each(|(a, gg)| *a = gg * a.conj() * norm);
            self.fft2(&mut b.a, &mut b.work, &mut b.scratch, true, 0..self.wp);
            for r in 0..self.wp {
                for c in 0..self.wp {
                    out.psf[k][(r, c)] = b.a[r * self.nx + c].re;
                }
            }
            // ∂/∂(αL, α) = Σ G(t+y0) P(t) → IFFT(Ĝ·conj(P̂)), real and imaginary parts.
            self.psf_spectrum(l, &mut b);
            g.iter_mut()
                .zip(&b.p)
                .for_each(|(gg, p)| *gg *= p.conj() * norm);
            self.fft2(&mut g, &mut b.work, &mut b.scratch, true, 0..self.w);
            for r in 0..self.h {
                for c in 0..self.w {
                    let v = g[r * self.nx + c];
                    let (al, lr) = (l.alpha[(r, c)] as f64, l.radiance[(r, c)] as f64);
                    out.radiance[k][(r, c)] = v.re * al;
                    out.alpha[k][(r, c)] = v.re * lr + v.im;
                }
            }
        }
        Ok(out)
    }
}

/// Kernel spectra P̂ on a [`LayeredImager`]'s padded grid, computed once and shared by every
/// frame of a batch (a batch's layers at one depth all use the same PSF). Stored times the
/// inverse FFT's 1/(ny·nx), the product every layer's spectrum is multiplied by.
pub struct KernelSpectra {
    spec: Vec<Option<Vec<c32>>>,
}

/// One layer for the spectral path: radiance, alpha, the index of its kernel, and the factors
/// S1 applies to the radiance. The planes may be column-major (an owned `Mat`) or row-major
/// (the transpose of one), all three the same: row-major planes are packed into S1's
/// row-major grid as a stream, column-major ones through a transposition (2.9–3.4 ms against
/// 0.6–1.0 ms per 800×1280 layer on the AMD EPYC VM, docs/bench/chain.md).
#[derive(Clone, Copy, Debug)]
pub struct SpectralLayer<'a> {
    /// Radiance L_k, before `gain` and `weight`.
    pub radiance: MatRef<'a, f32>,
    /// Coverage α_k.
    pub alpha: MatRef<'a, f32>,
    /// Index into the [`KernelSpectra`].
    pub kernel: usize,
    /// Factor on the whole radiance (1: none), applied to its convolution (in f64) rather
    /// than to the radiance: the layer's spectrum ([`LayerSpectra`]) then does not depend on
    /// it, and a caller whose gain changes every step (η_k of a lens in training) can keep
    /// the spectrum.
    pub gain: f32,
    /// Factor per pixel on the radiance, H×W (`None`: none). S1 packs `weight(i, j) · L(i, j)`,
    /// rounded to f32, so a caller need not store the scaled radiance of every layer.
    pub weight: Option<MatRef<'a, f32>>,
}

impl<'a> SpectralLayer<'a> {
    /// A layer whose radiance is used as it is.
    pub fn new(radiance: MatRef<'a, f32>, alpha: MatRef<'a, f32>, kernel: usize) -> Self {
        Self {
            radiance,
            alpha,
            kernel,
            gain: 1.0,
            weight: None,
        }
    }

    /// The layout its planes share (rows first), `None` when they share none.
    fn layout(&self) -> Option<Layout> {
        [Layout::Rows, Layout::Cols].into_iter().find(|&by| {
            [Some(self.radiance), Some(self.alpha), self.weight]
                .into_iter()
                .flatten()
                .all(|m| allows(m, by))
        })
    }

    /// Its planes' lines (rows or columns) in their shared layout: α, L and the weight's.
    fn lines(&self) -> Lines<'a> {
        let by = self.layout().expect("layouts checked by check_layers");
        (
            by,
            lines(self.alpha, by),
            lines(self.radiance, by),
            self.weight.map(|m| lines(m, by)),
        )
    }

    /// Whether the radiance S1 packs (after `weight`) is finite everywhere.
    fn radiance_finite(&self) -> bool {
        let (_, _, rad, wt) = self.lines();
        match wt {
            Some(wt) => rad.iter().zip(&wt).all(|(r, s)| {
                r.iter()
                    .zip(s.iter())
                    .fold(true, |ok, (&y, &s)| ok & (s * y).is_finite())
            }),
            None => rad
                .iter()
                .all(|r| r.iter().fold(true, |ok, &y| ok & y.is_finite())),
        }
    }

    /// Whether the layer has no coverage (α ≡ 0): it is skipped, and has no spectrum.
    fn uncovered(&self) -> bool {
        let (_, al, _, _) = self.lines();
        al.iter().all(|c| c.iter().all(|&v| v == 0.0))
    }

    /// The power of two s ≥ max |α·w·L| (1 when that is 0 or not finite) that S1 divides the
    /// radiance channel by before packing it with α: one f32 FFT carries both channels, and
    /// its round-off, relative to the larger, would otherwise put 1e-7 of a radiance in the
    /// thousands into α∗P, the occlusion every layer behind is multiplied by. A power of two,
    /// so the division and the product with s after the transform round nothing.
    fn radiance_scale(&self) -> f32 {
        let (_, al, rad, wt) = self.lines();
        let mut m = 0.0f32;
        for (c, (al, rad)) in al.iter().zip(&rad).enumerate() {
            m = match &wt {
                Some(wt) => al
                    .iter()
                    .zip(rad.iter())
                    .zip(wt[c])
                    .fold(m, |m, ((&x, &y), &s)| m.max((x * (s * y)).abs())),
                None => al
                    .iter()
                    .zip(rad.iter())
                    .fold(m, |m, (&x, &y)| m.max((x * y).abs())),
            };
        }
        scale_of(m)
    }
}

/// The power of two s ≥ `m` (1 when `m` is 0 or not finite): a layer's radiance scale from
/// the largest |α·w·L| ([`SpectralLayer::radiance_scale`]).
fn scale_of(m: f32) -> f32 {
    if m > 0.0 && m.is_finite() {
        2f32.powi((m.log2().ceil() as i32).clamp(-126, 127))
    } else {
        1.0
    }
}

/// The pixels of an H×W image one layer's composition can change: per row one span of
/// columns (empty where it changes none), and where that span starts in a plane that holds
/// the spans packed row after row. The whole-grid path's layers reach every pixel; a layer on
/// tiles reaches, per row, from its first tile window to its last, widened to multiples of
/// [`DOT_LANES`] (`tiled::reach`), so its planes on the tape and the passes over them skip
/// the rest of the frame (where α∗P = 0 and I⁽ᵏ⁾ = I⁽ᵏ⁻¹⁾ exactly).
#[derive(Debug)]
struct Reach {
    /// Per row, its span of columns [start, end).
    spans: Vec<(usize, usize)>,
    /// Per row, where its span starts in a packed plane; one more entry: the plane's length.
    at: Vec<usize>,
}

impl Reach {
    /// Every pixel of an h×w image: the packed planes are the row-major image.
    fn full(h: usize, w: usize) -> Self {
        Self::from_spans(vec![(0, w); h])
    }

    /// From per-row spans (start ≥ end: empty).
    fn from_spans(mut spans: Vec<(usize, usize)>) -> Self {
        let mut at = Vec::with_capacity(spans.len() + 1);
        let mut n = 0;
        for s in &mut spans {
            if s.0 >= s.1 {
                *s = (0, 0);
            }
            at.push(n);
            n += s.1 - s.0;
        }
        at.push(n);
        Reach { spans, at }
    }

    /// Pixels in the reach (the length of its packed planes).
    fn len(&self) -> usize {
        self.at[self.spans.len()]
    }

    /// The non-empty rows: (row, its columns, their range in a packed plane).
    fn rows(&self) -> impl Iterator<Item = (usize, Range<usize>, Range<usize>)> + '_ {
        self.rows_in(0..self.spans.len())
    }

    /// [`Self::rows`] among the image rows `rows`.
    fn rows_in(
        &self,
        rows: Range<usize>,
    ) -> impl Iterator<Item = (usize, Range<usize>, Range<usize>)> + '_ {
        self.spans[rows.clone()]
            .iter()
            .zip(rows)
            .filter(|(s, _)| s.1 > s.0)
            .map(|(&(a, b), r)| (r, a..b, self.at[r]..self.at[r] + b - a))
    }

    /// Where pixel (r, c), which must lie in the reach, is in a packed plane.
    #[inline]
    fn packed(&self, r: usize, c: usize) -> usize {
        debug_assert!(
            self.spans[r].0 <= c && c < self.spans[r].1,
            "({r}, {c}) outside"
        );
        self.at[r] + c - self.spans[r].0
    }
}

/// One layer's planes on S1's tape, over its reach: I⁽ᵏ⁻¹⁾ (the image below it) and α∗P;
/// on tiles also the tiles the layer was imaged on, which its reach was made from (the
/// backward takes them instead of finding them again, and refuses spectra of other tiles).
struct Planes {
    prev: Vec<f32>,
    o: Vec<f32>,
    reach: Reach,
    tiles: Vec<u32>,
}

/// What a spectral forward pass keeps for the PSF VJP: per layer the image below it and its
/// occlusion α∗P over the pixels the layer reaches (the whole image on the whole grid, the
/// tiles' windows on tiles), in f32 (the adjoint needs them to round-off precision only);
/// the final image; and the layer spectra the pass computed (none when they were given),
/// which the VJP uses in place of computing them again.
pub struct S1Tape {
    saved: Vec<Option<Planes>>,
    /// The final image, row-major H×W.
    image: Vec<f32>,
    /// The spectral grid of the imager that made it ([`LayeredImager::spectral_grid`]).
    grid: (usize, usize, usize),
    /// Per layer, its radiance channel's scale ([`SpectralLayer::radiance_scale`]).
    scales: Vec<f32>,
    spectra: Option<LayerSpectra>,
}

impl S1Tape {
    /// The layer spectra the forward pass computed, taken off the tape (to keep them for
    /// later calls); the VJP then needs them given, or computes them again.
    pub fn take_spectra(&mut self) -> Option<LayerSpectra> {
        self.spectra.take()
    }

    /// Bytes of layer spectra the tape holds (nx·ny·8 per covered layer, 0 once taken).
    pub fn spectra_bytes(&self) -> usize {
        self.spectra.as_ref().map_or(0, LayerSpectra::bytes)
    }
}

/// Per layer of a frame, the tiles its coverage reaches and its radiance scale
/// ([`SpectralLayer::radiance_scale`]'s value), as S1's tiled path finds them in a pass over
/// the planes ([`LayeredImager::layer_cover`]). They depend on α, L and the weight alone — not
/// on the PSFs or the gain — so a caller that images the same layers again (a frame at every
/// training step) can skip that pass ([`LayeredImager::forward_spectral_covered`]). A few
/// bytes per tile.
#[derive(Clone, Debug, PartialEq)]
pub struct LayerCover {
    layers: Vec<Option<(Vec<u32>, f32)>>,
    /// The imager's image height and width, tile side and tile grid side it was made for.
    grid: [usize; 4],
}

impl LayerCover {
    /// Bytes it holds (about).
    pub fn bytes(&self) -> usize {
        self.layers
            .iter()
            .map(|l| std::mem::size_of_val(l) + l.as_ref().map_or(0, |(t, _)| 4 * t.len()))
            .sum()
    }
}

/// The spectra F{α·w·L/s + iα} of a frame's layers on S1's padded grid (s a power of two
/// per layer, [`SpectralLayer::radiance_scale`]), column by column
/// (`None` for a layer without coverage), from [`LayeredImager::layer_spectra`]. They hold
/// no PSF and no gain, so they stay valid while the lens trains: S1 given them skips each
/// layer's packing, forward row and column transforms (in the forward pass and in the PSF
/// adjoint), about half of its work. f32 (nx·ny·8 bytes per covered layer), the precision
/// of S1's spectral path, so S1 given them computes the same bits as S1 computing them.
#[derive(Debug, PartialEq)]
pub struct LayerSpectra {
    layers: Vec<Option<Vec<c32>>>,
    /// Per layer, the power of two its radiance channel was divided by
    /// ([`SpectralLayer::radiance_scale`]; 1 for a layer without coverage).
    scales: Vec<f32>,
    nx: usize,
    ny: usize,
    /// The tiles' side on the tiled path (0: the whole padded grid).
    tile: usize,
    /// The image's H×W: spectra of another imager's frames are refused even where the grids
    /// agree.
    image: (usize, usize),
    /// On the tiled path, per layer the tiles it covers (row-major tile index), whose
    /// spectra its entry holds one after the other; empty on the whole-grid path.
    tiles: Vec<Vec<u32>>,
}

impl LayerSpectra {
    /// Bytes held.
    pub fn bytes(&self) -> usize {
        let n: usize = self.layers.iter().flatten().map(Vec::len).sum();
        n * std::mem::size_of::<c32>()
    }

    /// Bytes of one covered layer's spectrum for an imager: on the whole grid exactly what
    /// [`Self::bytes`] counts per layer, on tiles the most (every tile covered).
    pub fn layer_bytes(im: &LayeredImager) -> usize {
        let points = match &im.tiling {
            Some(t) => t.rows * t.cols * t.n * t.n,
            None => im.nx * im.ny,
        };
        points * std::mem::size_of::<c32>()
    }
}

/// Writes (a kernel's first term: `fresh`) or adds `term` into `slot[at]`.
#[inline(always)]
fn accumulate(slot: &mut Vec<c32>, fresh: bool, at: Range<usize>, term: impl Iterator<Item = c32>) {
    if fresh {
        slot.extend(term);
    } else {
        slot[at].iter_mut().zip(term).for_each(|(s, t)| *s += t);
    }
}

/// ∂loss/∂P accumulated in the frequency domain over frames: one inverse FFT per kernel at
/// the end instead of one per layer and frame.
pub struct KernelGradAccumulator {
    spec: Vec<Option<Vec<c32>>>,
    /// Σ over layers using kernel j of ⟨∂loss/∂I⁽ᵏ⁾, (α_k L_k) ∗ P_j⟩: the gradient w.r.t. a
    /// scalar factor on the layer's radiance.
    pub radiance_scale: Vec<f64>,
}

impl LayeredImager {
    /// FFTs of the kernels (`None`: unused, skipped), each stored column by column (the
    /// layout the fused column pass reads).
    pub fn kernel_spectra(&self, kernels: &[Option<&Mat<f32>>]) -> Result<KernelSpectra> {
        for (j, m) in kernels.iter().enumerate() {
            if let Some(m) = m
                && (m.nrows() != self.wp || m.ncols() != self.wp)
            {
                return Err(OpticsError::Shape(format!(
                    "kernel {j} is {}×{}, expected {}×{}",
                    m.nrows(),
                    m.ncols(),
                    self.wp,
                    self.wp
                )));
            }
        }
        if let Some(t) = &self.tiling {
            return self.tiled_kernel_spectra(t, kernels);
        }
        let mut sb = self.spectral_buffers();
        let (nx, ny) = (self.nx, self.ny);
        let mut spec = Vec::with_capacity(kernels.len());
        let norm = 1.0 / (ny * nx) as f32;
        for k in kernels {
            match k {
                None => spec.push(None),
                Some(m) => {
                    let rows = 0..self.wp;
                    for r in rows.clone() {
                        let row = &mut sb.a[r * nx..(r + 1) * nx];
                        for (c, v) in row.iter_mut().enumerate() {
                            *v = if c < self.wp {
                                c32::new(m[(r, c)], 0.0)
                            } else {
                                c32::new(0.0, 0.0)
                            };
                        }
                    }
                    self.p32
                        .fx
                        .process_with_scratch(&mut sb.a[..self.wp * nx], &mut sb.scratch);
                    let mut out = Vec::with_capacity(nx * ny);
                    for c0 in (0..nx).step_by(COLS) {
                        let bw = COLS.min(nx - c0);
                        let blk = &mut sb.blk[..bw * ny];
                        self.gather(&sb.a, c0, rows.clone(), blk);
                        self.p32.fy.process_with_scratch(blk, &mut sb.scratch);
                        out.extend(blk.iter().map(|p| p * norm));
                    }
                    spec.push(Some(out));
                }
            }
        }
        self.pool.give(sb);
        Ok(KernelSpectra { spec })
    }

    /// Most bytes a [`KernelGradAccumulator`] of `n` kernels comes to hold: one spectrum of
    /// S1's grid (a tile's grid on tiles) per kernel.
    pub fn kernel_grad_bytes(&self, n: usize) -> usize {
        let (nx, ny, _) = self.spectral_grid();
        n.saturating_mul(nx * ny * std::mem::size_of::<c32>())
    }

    /// A zeroed accumulator for `n` kernels.
    pub fn kernel_grad_accumulator(&self, n: usize) -> KernelGradAccumulator {
        KernelGradAccumulator {
            spec: vec![None; n],
            radiance_scale: vec![0.0; n],
        }
    }

    /// Shapes and kernels; finiteness is checked where the layers are packed.
    fn check_spectral(&self, layers: &[SpectralLayer], ks: &KernelSpectra) -> Result<()> {
        self.check_layers(layers)?;
        let (nx, ny, _) = self.spectral_grid();
        for (k, l) in layers.iter().enumerate() {
            match ks.spec.get(l.kernel) {
                Some(Some(p)) if p.len() == nx * ny => {}
                Some(Some(p)) => {
                    return Err(OpticsError::Shape(format!(
                        "kernel {} has a spectrum of {} values, this imager's spectral grid \
                         {}×{} (kernel spectra of another imager?)",
                        l.kernel,
                        p.len(),
                        ny,
                        nx
                    )));
                }
                _ => {
                    return Err(OpticsError::param(
                        "kernel",
                        format!("layer {k} uses kernel {} which was not computed", l.kernel),
                    ));
                }
            }
        }
        Ok(())
    }

    /// The spectral path's transform grid (nx, ny) and tile side (0: the whole grid).
    fn spectral_grid(&self) -> (usize, usize, usize) {
        match &self.tiling {
            Some(t) => (t.n, t.n, t.t),
            None => (self.nx, self.ny, 0),
        }
    }

    /// Spectra given with `layers` belong to this imager's grid and to as many layers.
    fn check_spectra(&self, layers: &[SpectralLayer], s: Option<&LayerSpectra>) -> Result<()> {
        let (nx, ny, tile) = self.spectral_grid();
        let here = (self.h, self.w, nx, ny, tile, layers.len());
        match s {
            Some(s) if (s.image.0, s.image.1, s.nx, s.ny, s.tile, s.layers.len()) != here => {
                Err(OpticsError::Shape(format!(
                    "layer spectra of {} layers of {}×{} on a {}×{} grid (tiles of {}), for {} \
                     layers of {}×{} on {}×{} (tiles of {})",
                    s.layers.len(),
                    s.image.0,
                    s.image.1,
                    s.ny,
                    s.nx,
                    s.tile,
                    layers.len(),
                    self.h,
                    self.w,
                    ny,
                    nx,
                    tile
                )))
            }
            _ => Ok(()),
        }
    }

    /// Shapes of the layers' matrices and finite gains.
    fn check_layers(&self, layers: &[SpectralLayer]) -> Result<()> {
        for (k, l) in layers.iter().enumerate() {
            let mats = [("radiance", Some(l.radiance)), ("alpha", Some(l.alpha))];
            for (name, m) in mats.into_iter().chain([("weight", l.weight)]) {
                let Some(m) = m else { continue };
                if m.nrows() != self.h || m.ncols() != self.w {
                    return Err(OpticsError::Shape(format!(
                        "layer {k}: {name} is {}×{}, expected {}×{}",
                        m.nrows(),
                        m.ncols(),
                        self.h,
                        self.w
                    )));
                }
            }
            if l.layout().is_none() {
                return Err(OpticsError::Shape(format!(
                    "layer {k}: radiance, alpha and weight must share one memory layout, all \
                     with contiguous rows (transposes of owned matrices) or all with contiguous \
                     columns (owned matrices)"
                )));
            }
            if !l.gain.is_finite() {
                return Err(OpticsError::param(
                    "gain",
                    format!("layer {k} has gain {}", l.gain),
                ));
            }
        }
        Ok(())
    }

    /// The spectral path's row-major H×W image as a matrix, refused when not finite.
    fn finished(&self, image: &[f32]) -> Result<Mat<f32>> {
        let (h, w) = (self.h, self.w);
        assert_eq!(image.len(), h * w);
        // A layer's image beyond f32's range stays infinite, or turns NaN where a layer in
        // front covers it: either way the image is not finite. The largest magnitude's bits
        // in one pass without an early exit, which vectorises.
        let top = image
            .iter()
            .fold(0u32, |m, v| m.max(v.to_bits() & 0x7fff_ffff));
        if top >= f32::INFINITY.to_bits() {
            return Err(OpticsError::param(
                "layers",
                "the image exceeds f32's range (gain × weighted radiance too large)",
            ));
        }
        let mut m = Mat::<f32>::zeros(h, w);
        // Through the register transpositions: a value at a time through the matrix's
        // indexing it took 4–7 % of the paper-size forward (`perf`).
        if h * w > 0 {
            // Checked, not assumed: the writes below trust the owned matrix's layout.
            assert!(m.row_stride() == 1 && m.col_stride() >= h as isize);
            let rows: Vec<&[f32]> = image.chunks_exact(w).collect();
            let ld = m.col_stride() as usize;
            // SAFETY: column c of the matrix starts at c·ld from its pointer, its h values
            // contiguous (row stride 1, checked); no reference into it lives meanwhile.
            unsafe { transpose_raw(&rows, m.as_ptr_mut(), ld, h, w) };
        }
        Ok(m)
    }

    /// Layer `k` of the call, which uses kernel `kernel` (a caller that reorders its layers
    /// names them by kernel, e.g. a depth slab).
    fn non_finite(k: usize, kernel: usize) -> OpticsError {
        OpticsError::param(
            "layers",
            format!("layer {k} (kernel {kernel}) holds non-finite values"),
        )
    }

    /// Work space of the spectral path: one padded grid (every row is written before it is
    /// read, so a reused one needs no clearing), two column blocks and FFT scratch; one a
    /// finished call returned when there is one.
    fn spectral_buffers(&self) -> SpectralBuffers {
        if let Some(sb) = self.pool.take() {
            return sb;
        }
        let s = self.p32.scratch_len();
        let z = c32::new(0.0, 0.0);
        SpectralBuffers {
            a: vec![z; self.ny * self.nx],
            blk: vec![z; COLS * self.ny],
            blk2: vec![z; COLS * self.ny],
            scratch: vec![z; s],
            g: Vec::new(),
        }
    }

    /// An empty spectrum with room for the padded grid, reused when one was given back.
    fn spare_spectrum(&self) -> Vec<c32> {
        let (nx, ny, _) = self.spectral_grid();
        let n = ny * nx;
        match self.spare.take() {
            Some(mut v) => {
                v.clear();
                v.reserve_exact(n);
                v
            }
            None => Vec::with_capacity(n),
        }
    }

    /// Columns `c0 .. c0 + blk.len() / ny` of the row-major grid `data` into `blk`, column j
    /// at `j * ny`; rows outside `live` are taken as zero without being read.
    fn gather(&self, data: &[c32], c0: usize, live: Range<usize>, blk: &mut [c32]) {
        let (nx, ny) = (self.nx, self.ny);
        let bw = blk.len() / ny;
        for col in blk.chunks_exact_mut(ny) {
            col[..live.start].fill(c32::new(0.0, 0.0));
            col[live.end..].fill(c32::new(0.0, 0.0));
        }
        // Four rows at a time: each column then takes 32 contiguous bytes per visit instead
        // of one value.
        let mut r = live.start;
        while r + 4 <= live.end {
            let row = |i: usize| &data[(r + i) * nx + c0..(r + i) * nx + c0 + bw];
            let (d0, d1, d2, d3) = (row(0), row(1), row(2), row(3));
            for (j, col) in blk.chunks_exact_mut(ny).enumerate() {
                let q: &mut [c32; 4] = (&mut col[r..r + 4]).try_into().expect("four");
                *q = [d0[j], d1[j], d2[j], d3[j]];
            }
            r += 4;
        }
        for r in r..live.end {
            for (j, &v) in data[r * nx + c0..r * nx + c0 + bw].iter().enumerate() {
                blk[j * ny + r] = v;
            }
        }
    }

    /// Rows `rows` of a column block back into the row-major grid `data`.
    fn scatter(&self, blk: &[c32], c0: usize, rows: Range<usize>, data: &mut [c32]) {
        let (nx, ny) = (self.nx, self.ny);
        let bw = blk.len() / ny;
        for r in rows {
            for (j, v) in data[r * nx + c0..r * nx + c0 + bw].iter_mut().enumerate() {
                *v = blk[j * ny + r];
            }
        }
    }

    /// Packs αL/s + iα of a layer into rows 0..H of `a` (zero beyond column W), L scaled by
    /// the layer's weight on the way and s its [`SpectralLayer::radiance_scale`], and
    /// transforms each row that holds data while it is still in cache; the column transform
    /// happens block by block in the caller. Returns the rows from the first to the last with
    /// data, and s: a row with α ≡ 0 is zero (αL = 0 too) and so is its transform, which is
    /// skipped, and the caller's column pass need not read the rows outside. `None` when a
    /// packed value is not finite (a non-finite α or weighted L, or 0 · ∞): the inputs are
    /// checked here, in the pass that reads them anyway. Row-major planes are read row by
    /// row, column-major ones in bands of [`PACK_ROWS`]; both pack the same values.
    fn layer_rows(
        &self,
        l: &SpectralLayer,
        a: &mut [c32],
        scratch: &mut [c32],
    ) -> Option<(Range<usize>, f32)> {
        let (h, w, nx) = (self.h, self.w, self.nx);
        let scale = l.radiance_scale();
        let inv = 1.0 / scale;
        let (by, al, rad, wt) = l.lines();
        let pack = |o: &mut c32, x: f32, y: f32| *o = c32::new(x * y * inv, x);
        let (mut first, mut end) = (h, 0);
        // One packed row: its tail cleared, checked finite, transformed when it holds data.
        let mut finish = |r: usize, row: &mut [c32]| -> bool {
            row[w..].fill(c32::new(0.0, 0.0));
            // Both folds without early exit, so that they vectorise.
            let (data, finite) = row[..w].iter().fold((false, true), |(d, f), v| {
                (d | (v.im != 0.0), f & v.re.is_finite() & v.im.is_finite())
            });
            if data && finite {
                first = first.min(r);
                end = r + 1;
                self.p32.fx.process_with_scratch(row, scratch);
            }
            finite
        };
        match by {
            Layout::Rows => {
                for (r, row) in a[..h * nx].chunks_exact_mut(nx).enumerate() {
                    let (al, rad, out) = (al[r], rad[r], &mut row[..w]);
                    match &wt {
                        Some(wt) => {
                            for (o, ((&x, &y), &s)) in
                                out.iter_mut().zip(al.iter().zip(rad).zip(wt[r]))
                            {
                                pack(o, x, s * y);
                            }
                        }
                        None => {
                            for (o, (&x, &y)) in out.iter_mut().zip(al.iter().zip(rad)) {
                                pack(o, x, y);
                            }
                        }
                    }
                    if !finish(r, row) {
                        return None;
                    }
                }
            }
            Layout::Cols => {
                for r0 in (0..h).step_by(PACK_ROWS) {
                    let r1 = (r0 + PACK_ROWS).min(h);
                    let band = &mut a[r0 * nx..r1 * nx];
                    for (c, (al, rad)) in al.iter().zip(&rad).enumerate() {
                        let (al, rad) = (&al[r0..r1], &rad[r0..r1]);
                        let mut put = |i: usize, x: f32, y: f32| pack(&mut band[i * nx + c], x, y);
                        match &wt {
                            Some(wt) => {
                                for (i, ((&x, &y), &s)) in
                                    al.iter().zip(rad).zip(&wt[c][r0..r1]).enumerate()
                                {
                                    put(i, x, s * y);
                                }
                            }
                            None => {
                                for (i, (&x, &y)) in al.iter().zip(rad).enumerate() {
                                    put(i, x, y);
                                }
                            }
                        }
                    }
                    for (i, row) in band.chunks_exact_mut(nx).enumerate() {
                        if !finish(r0 + i, row) {
                            return None;
                        }
                    }
                }
            }
        }
        Some((first.min(end)..end, scale))
    }

    /// The spectra of `layers` (their gains are not used), to be given to
    /// [`Self::forward_spectral`], [`Self::image_spectral`] and [`Self::vjp_kernels`] for the
    /// same layers in place of computing them each call. One FFT per covered layer; the same
    /// finiteness errors as a forward pass.
    pub fn layer_spectra(&self, layers: &[SpectralLayer]) -> Result<LayerSpectra> {
        self.check_layers(layers)?;
        if let Some(t) = &self.tiling {
            return self.tiled_layer_spectra(t, layers);
        }
        let (nx, ny) = (self.nx, self.ny);
        let mut sb = self.spectral_buffers();
        let mut out = Vec::with_capacity(layers.len());
        let mut scales = Vec::with_capacity(layers.len());
        for (k, l) in layers.iter().enumerate() {
            let Some((live, scale)) = self.packed(l, k, &mut sb)? else {
                out.push(None);
                scales.push(1.0);
                continue;
            };
            scales.push(scale);
            let mut spec = Vec::with_capacity(nx * ny);
            for c0 in (0..nx).step_by(COLS) {
                let blk = &mut sb.blk[..COLS.min(nx - c0) * ny];
                self.gather(&sb.a, c0, live.clone(), blk);
                self.p32.fy.process_with_scratch(blk, &mut sb.scratch);
                spec.extend_from_slice(blk);
            }
            out.push(Some(spec));
        }
        self.pool.give(sb);
        Ok(LayerSpectra {
            layers: out,
            scales,
            nx,
            ny,
            tile: 0,
            tiles: Vec::new(),
            image: (self.h, self.w),
        })
    }

    /// Layer `k` packed and row-transformed into `sb.a` ([`Self::layer_rows`]), its rows
    /// with data and its radiance scale returned; `None` for a layer without coverage, which
    /// is skipped. Either way
    /// a non-finite value is refused: an uncovered layer, not packed, is checked apart, since
    /// it still may not hold what a covered one would be refused for.
    fn packed(
        &self,
        l: &SpectralLayer,
        k: usize,
        sb: &mut SpectralBuffers,
    ) -> Result<Option<(Range<usize>, f32)>> {
        if l.uncovered() {
            return match l.radiance_finite() {
                true => Ok(None),
                false => Err(Self::non_finite(k, l.kernel)),
            };
        }
        match self.layer_rows(l, &mut sb.a, &mut sb.scratch) {
            Some(packed) => Ok(Some(packed)),
            None => Err(Self::non_finite(k, l.kernel)),
        }
    }

    /// S1 with precomputed kernel spectra (two FFTs per non-empty layer, one with the layers'
    /// `spectra`); keeps the tape the PSF VJP needs, with the layer spectra it computed when
    /// none were given (nx·ny·8 bytes per covered layer: [`S1Tape::take_spectra`]). Per block
    /// of columns the forward column transform, the product with P̂ and the inverse column
    /// transform run back to back while the block is in cache, and only the H rows the output
    /// keeps go through the inverse row transform.
    pub fn forward_spectral(
        &self,
        layers: &[SpectralLayer],
        ks: &KernelSpectra,
        spectra: Option<&LayerSpectra>,
    ) -> Result<(Mat<f32>, S1Tape)> {
        let (m, tape) = self.spectral(layers, ks, spectra, true, None)?;
        Ok((m, tape.expect("kept")))
    }

    /// [`Self::forward_spectral`] with the layers' cover from this imager's
    /// [`Self::layer_cover`], computed once for these layers (their planes not changed since),
    /// which spares the tiled path its pass over the planes: the same bits. The planes'
    /// finiteness is then the cover's check, not checked again. A cover of another imager or
    /// of another number of layers is refused.
    pub fn forward_spectral_covered(
        &self,
        layers: &[SpectralLayer],
        ks: &KernelSpectra,
        spectra: Option<&LayerSpectra>,
        cover: Option<&LayerCover>,
    ) -> Result<(Mat<f32>, S1Tape)> {
        if let Some(c) = cover {
            if Some(c.grid) != self.cover_grid() {
                let [h, w, t, n] = c.grid;
                return Err(OpticsError::Shape(format!(
                    "a layer cover of {h}×{w} images on tiles of {t} ({n}² grids) for this imager \
                     of {}×{} ({}): make it with this imager's layer_cover",
                    self.h,
                    self.w,
                    self.tiling
                        .as_ref()
                        .map_or("no tiles".into(), |t| format!("tiles of {}", t.t))
                )));
            }
            if c.layers.len() != layers.len() {
                return Err(OpticsError::Shape(format!(
                    "a cover of {} layers for {} layers",
                    c.layers.len(),
                    layers.len()
                )));
            }
        }
        let (m, tape) = self.spectral(layers, ks, spectra, true, cover)?;
        Ok((m, tape.expect("kept")))
    }

    /// The layers' cover (tiles reached and radiance scales) that the tiled path finds in its
    /// pass over their planes, refusing what that pass refuses; `None` for an imager that
    /// does not tile.
    pub fn layer_cover(&self, layers: &[SpectralLayer]) -> Result<Option<LayerCover>> {
        let Some(t) = &self.tiling else {
            return Ok(None);
        };
        self.check_layers(layers)?;
        let layers = layers
            .iter()
            .enumerate()
            .map(|(k, l)| self.scan(t, l, k))
            .collect::<Result<_>>()?;
        Ok(Some(LayerCover {
            layers,
            grid: [self.h, self.w, t.t, t.n],
        }))
    }

    /// What a layer cover made by this imager records of it (`None`: it makes none).
    fn cover_grid(&self) -> Option<[usize; 4]> {
        self.tiling.as_ref().map(|t| [self.h, self.w, t.t, t.n])
    }

    /// [`Self::forward_spectral`]'s image alone, the same bits, without the tape's per-layer
    /// copies (for a forward nothing will differentiate).
    pub fn image_spectral(
        &self,
        layers: &[SpectralLayer],
        ks: &KernelSpectra,
        spectra: Option<&LayerSpectra>,
    ) -> Result<Mat<f32>> {
        Ok(self.spectral(layers, ks, spectra, false, None)?.0)
    }

    /// S1 on the spectral path, with the tape when `keep`.
    fn spectral(
        &self,
        layers: &[SpectralLayer],
        ks: &KernelSpectra,
        spectra: Option<&LayerSpectra>,
        keep: bool,
        cover: Option<&LayerCover>,
    ) -> Result<(Mat<f32>, Option<S1Tape>)> {
        self.check_spectral(layers, ks)?;
        self.check_spectra(layers, spectra)?;
        if let Some(t) = &self.tiling {
            return self.tiled_spectral(t, layers, ks, (spectra, cover), keep);
        }
        let (h, w, nx, ny) = (self.h, self.w, self.nx, self.ny);
        let (cy, cx) = (self.wp / 2, self.wp / 2);
        // The image so far, I⁽ᵏ⁻¹⁾ (I⁽⁻¹⁾ = 0), row-major like the grid rows it is composed
        // with; with the tape, each layer's I⁽ᵏ⁾ is a new vector and this one is kept.
        let mut prev = vec![0.0f32; h * w];
        let mut saved = Vec::with_capacity(layers.len());
        // The layer spectra computed on the way, for the tape: a copy of each column block
        // while it is in cache, not a pass.
        let mut record = (keep && spectra.is_none()).then(|| Vec::with_capacity(layers.len()));
        // Each layer's radiance scale (1 for a skipped layer).
        let mut scales = Vec::with_capacity(layers.len());
        let mut sb = self.spectral_buffers();
        for (k, l) in layers.iter().enumerate() {
            let p = ks.spec[l.kernel].as_ref().expect("checked");
            let scale = match spectra.map(|s| (s.layers[k].as_deref(), s.scales[k])) {
                Some((None, _)) => {
                    saved.push(None);
                    scales.push(1.0);
                    continue;
                }
                Some((Some(spec), scale)) => {
                    for c0 in (0..nx).step_by(COLS) {
                        let span = c0 * ny..(c0 + COLS.min(nx - c0)) * ny;
                        let blk = &mut sb.blk[..span.len()];
                        blk.iter_mut()
                            .zip(&spec[span.clone()])
                            .zip(&p[span])
                            .for_each(|((b, &s), p)| *b = s * p);
                        self.p32.iy.process_with_scratch(blk, &mut sb.scratch);
                        self.scatter(blk, c0, cy..cy + h, &mut sb.a);
                    }
                    scale
                }
                None => {
                    let Some((live, scale)) = self.packed(l, k, &mut sb)? else {
                        saved.push(None);
                        scales.push(1.0);
                        if let Some(r) = record.as_mut() {
                            r.push(None);
                        }
                        continue;
                    };
                    let mut rec = record.as_ref().map(|_| Vec::with_capacity(nx * ny));
                    for c0 in (0..nx).step_by(COLS) {
                        let bw = COLS.min(nx - c0);
                        let blk = &mut sb.blk[..bw * ny];
                        self.gather(&sb.a, c0, live.clone(), blk);
                        self.p32.fy.process_with_scratch(blk, &mut sb.scratch);
                        if let Some(rec) = rec.as_mut() {
                            rec.extend_from_slice(blk);
                        }
                        let p = &p[c0 * ny..(c0 + bw) * ny];
                        blk.iter_mut().zip(p).for_each(|(a, p)| *a *= p);
                        self.p32.iy.process_with_scratch(blk, &mut sb.scratch);
                        self.scatter(blk, c0, cy..cy + h, &mut sb.a);
                    }
                    if let Some(r) = record.as_mut() {
                        r.push(rec);
                    }
                    scale
                }
            };
            scales.push(scale);
            // Each kept row is inverse-transformed and composed while it is in cache; with
            // the tape, into a new vector (the next layer's I⁽ᵏ⁻¹⁾), else in place. The gain
            // and the radiance scale multiply the convolved radiance.
            let gain = l.gain as f64 * scale as f64;
            // I⁽ᵏ⁾ = gain·s·Re(conv) + (1 − α∗P)·I⁽ᵏ⁻¹⁾ in f32, the precision the image, the
            // tape and the transforms have: 1 − α∗P of a near opaque layer is exact
            // (Sterbenz), and each layer adds a rounding of 6e-8 of the pixel. The product
            // with the gain is taken in f64, so that only the image can overflow.
            let compose = |v: c32, p: f32| (gain * v.re as f64) as f32 + (1.0 - v.im) * p;
            let out = &mut sb.a[cy * nx..(cy + h) * nx];
            if keep {
                let (mut o, mut cur) = (Vec::with_capacity(h * w), Vec::with_capacity(h * w));
                for (prow, grow) in prev.chunks_exact(w).zip(out.chunks_exact_mut(nx)) {
                    self.p32.ix.process_with_scratch(grow, &mut sb.scratch);
                    // Two passes over a row in cache, each of which vectorises (one loop with
                    // two pushes does not).
                    let src = &grow[cx..cx + w];
                    o.extend(src.iter().map(|v| v.im));
                    cur.extend(src.iter().zip(prow).map(|(&v, &p)| compose(v, p)));
                }
                saved.push(Some(Planes {
                    prev: std::mem::replace(&mut prev, cur),
                    o,
                    reach: Reach::full(h, w),
                    tiles: Vec::new(),
                }));
            } else {
                for (prow, grow) in prev.chunks_exact_mut(w).zip(out.chunks_exact_mut(nx)) {
                    self.p32.ix.process_with_scratch(grow, &mut sb.scratch);
                    for (p, &v) in prow.iter_mut().zip(&grow[cx..cx + w]) {
                        *p = compose(v, *p);
                    }
                }
            }
        }
        self.pool.give(sb);
        let record = record.map(|layers| (layers, Vec::new()));
        self.finish_pass(prev, saved, scales, record, keep)
    }

    /// A spectral forward pass's result from its final image I (row-major H×W): the image as
    /// a matrix (refused when not finite) and, when `keep`, the tape — the per-layer planes,
    /// radiance scales and the spectra recorded on the way (with their tiles on the tiled
    /// path), on this imager's spectral grid.
    #[allow(clippy::type_complexity)]
    fn finish_pass(
        &self,
        image: Vec<f32>,
        saved: Vec<Option<Planes>>,
        scales: Vec<f32>,
        record: Option<(Vec<Option<Vec<c32>>>, Vec<Vec<u32>>)>,
        keep: bool,
    ) -> Result<(Mat<f32>, Option<S1Tape>)> {
        let m = self.finished(&image)?;
        let (nx, ny, tile) = self.spectral_grid();
        let spectra = record.map(|(layers, tiles)| LayerSpectra {
            layers,
            scales: scales.clone(),
            nx,
            ny,
            tile,
            tiles,
            image: (self.h, self.w),
        });
        let tape = keep.then_some(S1Tape {
            saved,
            image,
            grid: self.spectral_grid(),
            scales,
            spectra,
        });
        Ok((m, tape))
    }

    /// Adds ∂loss/∂P (in the frequency domain) and ∂loss/∂(radiance scale) of one frame into
    /// `acc`, for ∂loss/∂I = `grad` (f32 or f64: the pass rounds it to f32). Two FFTs per
    /// non-empty layer (one with the layers' `spectra`, given or on the tape); no input
    /// gradients. The column transforms of the gradient and of the layer and their product
    /// run block by block, so neither full spectrum is ever stored.
    pub fn vjp_kernels<G: GradValue>(
        &self,
        layers: &[SpectralLayer],
        tape: &S1Tape,
        grad: &Mat<G>,
        acc: &mut KernelGradAccumulator,
        spectra: Option<&LayerSpectra>,
    ) -> Result<()> {
        if grad.nrows() != self.h || grad.ncols() != self.w || tape.saved.len() != layers.len() {
            return Err(OpticsError::Shape(format!(
                "grad is {}×{} for {} layers; forward was {}×{} with {} layers",
                grad.nrows(),
                grad.ncols(),
                layers.len(),
                self.h,
                self.w,
                tape.saved.len()
            )));
        }
        if tape.grid != self.spectral_grid() {
            // Its planes cover the reach of another imager's tiles (or whole frames).
            return Err(OpticsError::Shape(
                "the tape comes from another imager (another grid or tiling)".into(),
            ));
        }
        self.check_layers(layers)?;
        let spectra = spectra.or(tape.spectra.as_ref());
        self.check_spectra(layers, spectra)?;
        let (h, w, nx, ny) = (self.h, self.w, self.nx, self.ny);
        // ∂L/∂I⁽ᵏ⁾ in f32, as the tape's images: each layer multiplies it by (1 − o) and rounds
        // once (6e-8 relative), and the pass moves half the bytes; the dot product with the
        // convolved radiance stays in f64.
        let mut gi = vec![0.0f32; h * w];
        G::rows_into(grad, &mut gi);
        if let Some(t) = &self.tiling {
            return self.tiled_vjp_kernels(t, layers, tape, gi, acc, spectra);
        }
        let (cy, cx) = (self.wp / 2, self.wp / 2);
        let mut sb = self.spectral_buffers();
        // Rows cy .. cy + H are written for every layer before they are read, the others
        // never read: a reused grid needs no clearing.
        let mut g = std::mem::take(&mut sb.g);
        g.resize(ny * nx, c32::new(0.0, 0.0));
        let norm = 1.0 / (ny * nx) as f32;
        let n = layers.len();
        // I⁽ᵏ⁾ of each layer: the next non-empty layer's `prev`, or the final image.
        let mut above: &[f32] = &tape.image;
        for k in (0..n).rev() {
            let Some(Planes { prev, o, .. }) = &tape.saved[k] else {
                continue;
            };
            // The whole grid keeps whole images (the tape's grid is this imager's, checked
            // above): I⁽ᵏ⁾ of a layer is the next one's I⁽ᵏ⁻¹⁾.
            let l = &layers[k];
            let spec = match spectra.map(|s| s.layers[k].as_deref()) {
                Some(None) => {
                    return Err(OpticsError::Shape(format!(
                        "layer {k} has no spectrum but was imaged: spectra of other layers"
                    )));
                }
                Some(Some(s)) => Some(s),
                None => None,
            };
            let gain = l.gain as f64 * tape.scales[k] as f64;
            // ⟨gI, conv⟩ with conv = I⁽ᵏ⁾ − (1 − o)·I⁽ᵏ⁻¹⁾; g = gain·s·gI − i gI·I⁽ᵏ⁻¹⁾ at the
            // output's offset (cy, cx), zero elsewhere in its rows (the gain and the radiance
            // scale s multiply the convolved radiance, the real part).
            // The dot product in DOT_LANES partial sums, so that the pass vectorises (one
            // running sum is a chain of dependent scalar adds); summed in a fixed order.
            let mut dots = [0.0f64; DOT_LANES];
            for r in 0..h {
                let row = &mut g[(r + cy) * nx..(r + cy + 1) * nx];
                row[..cx].fill(c32::new(0.0, 0.0));
                row[cx + w..].fill(c32::new(0.0, 0.0));
                let span = r * w..(r + 1) * w;
                adjoint_row(
                    gain,
                    &mut gi[span.clone()],
                    &prev[span.clone()],
                    &o[span.clone()],
                    &above[span],
                    Some(&mut row[cx..cx + w]),
                    &mut dots,
                );
                self.p32.fx.process_with_scratch(row, &mut sb.scratch);
            }
            let dot: f64 = dots.iter().sum();
            let live = cy..cy + h;
            let rows = match spec {
                Some(_) => 0..0,
                None => match self.layer_rows(l, &mut sb.a, &mut sb.scratch) {
                    Some((rows, _)) => rows,
                    None => return Err(Self::non_finite(k, l.kernel)),
                },
            };
            // A kernel's first term is written, not added to zeros: the accumulator of a
            // frame (nx·ny per kernel) is then filled once instead of cleared and summed into.
            let fresh = acc.spec[l.kernel].is_none();
            let slot = acc.spec[l.kernel].get_or_insert_with(|| self.spare_spectrum());
            for c0 in (0..nx).step_by(COLS) {
                let bw = COLS.min(nx - c0);
                let (gb, ab) = (&mut sb.blk[..bw * ny], &mut sb.blk2[..bw * ny]);
                self.gather(&g, c0, live.clone(), gb);
                self.p32.fy.process_with_scratch(gb, &mut sb.scratch);
                let at = c0 * ny..(c0 + bw) * ny;
                let a: &[c32] = match spec {
                    Some(s) => &s[at.clone()],
                    None => {
                        self.gather(&sb.a, c0, rows.clone(), ab);
                        self.p32.fy.process_with_scratch(ab, &mut sb.scratch);
                        ab
                    }
                };
                accumulate(
                    slot,
                    fresh,
                    at,
                    gb.iter().zip(a).map(|(gg, a)| gg * a.conj() * norm),
                );
            }
            acc.radiance_scale[l.kernel] += dot;
            above = prev;
        }
        sb.g = g;
        self.pool.give(sb);
        Ok(())
    }

    /// Sums `other` into `acc` (per-frame accumulators of a batch); its spent spectra are
    /// kept for the next frames' accumulators.
    pub fn merge_kernel_grads(
        &self,
        acc: &mut KernelGradAccumulator,
        other: KernelGradAccumulator,
    ) {
        for (a, o) in acc.spec.iter_mut().zip(other.spec) {
            match (a.as_mut(), o) {
                (Some(x), Some(y)) => {
                    x.iter_mut().zip(&y).for_each(|(p, q)| *p += q);
                    self.spare.give(y);
                }
                (None, Some(y)) => *a = Some(y),
                _ => {}
            }
        }
        for (a, o) in acc.radiance_scale.iter_mut().zip(other.radiance_scale) {
            *a += o;
        }
    }

    /// ∂loss/∂P_j (W_p×W_p) from an accumulator: one inverse FFT per kernel that got gradient
    /// (all columns, then only the W_p rows that are kept).
    pub fn kernel_grads(&self, acc: KernelGradAccumulator) -> Vec<Mat<f64>> {
        if let Some(t) = &self.tiling {
            return self.tiled_kernel_grads(t, acc);
        }
        let (nx, ny, wp) = (self.nx, self.ny, self.wp);
        let mut sb = self.spectral_buffers();
        let mut row = vec![c32::new(0.0, 0.0); nx];
        let grads = acc
            .spec
            .into_iter()
            .map(|s| match s {
                None => Mat::zeros(wp, wp),
                Some(mut v) => {
                    self.p32.iy.process_with_scratch(&mut v, &mut sb.scratch);
                    let mut out = Mat::zeros(wp, wp);
                    for r in 0..wp {
                        for (c, x) in row.iter_mut().enumerate() {
                            *x = v[c * ny + r];
                        }
                        self.p32.ix.process_with_scratch(&mut row, &mut sb.scratch);
                        for c in 0..wp {
                            out[(r, c)] = row[c].re as f64;
                        }
                    }
                    self.spare.give(v);
                    out
                }
            })
            .collect();
        self.pool.give(sb);
        grads
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A column-major f32 matrix goes row-major value for value (the register blocks, the
    /// tiles' edges and the tiles' own edges), as the f64 matrix's scalar path rounds it:
    /// shapes around multiples of 8 and of the 32-value tiles.
    #[test]
    fn a_matrix_goes_row_major_value_for_value() {
        for (h, w) in [
            (1, 1),
            (7, 9),
            (8, 8),
            (9, 17),
            (33, 40),
            (64, 31),
            (65, 97),
        ] {
            let m = Mat::<f32>::from_fn(h, w, |r, c| (r * 1000 + c) as f32 + 0.25);
            let m64 = Mat::<f64>::from_fn(h, w, |r, c| m[(r, c)] as f64);
            let (mut out, mut out64) = (vec![f32::NAN; h * w], vec![f32::NAN; h * w]);
            f32::rows_into(&m, &mut out);
            f64::rows_into(&m64, &mut out64);
            for r in 0..h {
                for c in 0..w {
                    assert_eq!(
                        out[r * w + c].to_bits(),
                        m[(r, c)].to_bits(),
                        "{h}×{w} ({r}, {c})"
                    );
                    assert_eq!(
                        out64[r * w + c].to_bits(),
                        m[(r, c)].to_bits(),
                        "{h}×{w} ({r}, {c})"
                    );
                }
            }
        }
    }

    /// The 2-D FFT one column at a time, every row and every column.
    fn fft2_by_column(im: &LayeredImager, data: &mut [c64], inverse: bool) {
        let (rf, cf) = if inverse {
            (&im.p64.ix, &im.p64.iy)
        } else {
            (&im.p64.fx, &im.p64.fy)
        };
        rf.process(data);
        let mut col = vec![c64::new(0.0, 0.0); im.ny];
        for c in 0..im.nx {
            for (r, v) in col.iter_mut().enumerate() {
                *v = data[r * im.nx + c];
            }
            cf.process(&mut col);
            for (r, v) in col.iter().enumerate() {
                data[r * im.nx + c] = *v;
            }
        }
    }

    #[test]
    fn blocked_fft2_computes_what_the_column_by_column_one_does() {
        // nx = 40 is not a multiple of the block width, so the last block is partial.
        let im = LayeredImager::new(21, 34, 7).unwrap();
        assert_eq!(im.nx % COLS, 8);
        let mut b = im.buffers();
        let live = 3..17;
        let grid = |r: usize, c: usize| {
            if live.contains(&r) {
                c64::new(
                    ((r * 31 + c * 17) % 23) as f64 - 11.0,
                    ((r + 3 * c) % 5) as f64,
                )
            } else {
                c64::new(0.0, 0.0)
            }
        };
        let mut want: Vec<c64> = (0..im.ny * im.nx)
            .map(|i| grid(i / im.nx, i % im.nx))
            .collect();
        let mut got = want.clone();
        fft2_by_column(&im, &mut want, false);
        im.fft2(&mut got, &mut b.work, &mut b.scratch, false, live.clone());
        // Bit for bit: skipping zero rows and blocking the columns change no arithmetic.
        assert!(want.iter().zip(&got).all(|(a, b)| a == b));
        let cols = 5..29;
        fft2_by_column(&im, &mut want, true);
        im.fft2(&mut got, &mut b.work, &mut b.scratch, true, cols.clone());
        for r in 0..im.ny {
            for c in cols.clone() {
                assert_eq!(want[r * im.nx + c], got[r * im.nx + c], "({r}, {c})");
            }
        }
    }
}

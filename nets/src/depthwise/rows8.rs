//! Depthwise 3×3 at stride 2 on planes 8 pixels wide, in registers.
//!
//! Such a plane's output rows are four values, half a 256-bit register, and consecutive output
//! rows are contiguous, so in the forward a register holds output rows m and m + 1. Its low
//! lane reads input rows 2m − 1 + ky and its high lane rows 2m + 1 + ky: each pair of input
//! rows is split into even and odd columns by two in-lane shuffles, and the odd columns
//! shifted by one value within each lane give the left tap, so an output pair is nine fused
//! multiply–adds and one store, with no padded copy of the plane and no transposition into channel blocks (the
//! channel-block path, which took these planes, ran 480×8×8 at stride 2 at 1.5–1.7× the
//! memory roofline). Each output sums its taps in (ky, kx) order from zero, as the plane path
//! does, so y is the plane path's bits (test `rows_of_8_give_the_plane_paths_bits`).

use super::{Geom, backward_planes, forward_planes, has_fma, store_row_pair};
use std::arch::x86_64::*;
use std::mem::MaybeUninit;

/// Height of the square planes (a 128² input at stride 16) whose row loops are compiled for
/// it: unrolled, with their padding rows known. On one thread at batch 16, 480×8×8's forward
/// ran 137 → 75 µs with it; the backward 294 → 184 µs (the version [`plane_backward`]
/// replaced), 153 µs as it is now.
const SQUARE: usize = 8;

/// Whether a layer with this geometry goes through this path.
pub(super) fn takes(g: &Geom) -> bool {
    g.k == 3 && g.s == 2 && g.w == 8 && g.wo == 4 && g.h > 0 && g.ho == g.h.div_ceil(2) && has_fma()
}

/// Forward over all planes (as [`super::forward`]); panics unless `takes(g)`.
pub(super) fn forward(g: &Geom, c: usize, x: &[f32], w: &[f32], y: &mut [MaybeUninit<f32>]) {
    // The planes below run AVX2 and FMA code on that check alone.
    assert!(takes(g), "rows of 8 for {g:?}");
    // SAFETY: `takes` checked AVX2 and FMA on this CPU.
    forward_planes(g, c, (x, w), y, |h, ho, x, wk, out| unsafe {
        plane(h, ho, x, wk, out)
    });
}

/// Input row `r` of eight values as two halves (columns 0–3, 4–7); rows −1 and `h` and
/// beyond are the zero padding.
#[target_feature(enable = "avx2,fma")]
#[inline]
fn halves(x: &[f32], h: usize, r: isize) -> (__m128, __m128) {
    if r < 0 || r as usize >= h {
        return (_mm_setzero_ps(), _mm_setzero_ps());
    }
    let row = &x[r as usize * 8..][..8];
    // SAFETY: `row` holds eight values: two loads of four.
    unsafe {
        (
            _mm_loadu_ps(row.as_ptr()),
            _mm_loadu_ps(row.as_ptr().add(4)),
        )
    }
}

/// Input rows `lo` (low lane) and `hi` (high lane) as their (left, centre, right) taps for the
/// four outputs of each lane: odd columns shifted by one, even columns, odd columns.
#[target_feature(enable = "avx2,fma")]
#[inline]
fn taps(x: &[f32], h: usize, lo: isize, hi: isize) -> [__m256; 3] {
    let (l0, l1) = halves(x, h, lo);
    let (h0, h1) = halves(x, h, hi);
    let a = _mm256_set_m128(h0, l0);
    let b = _mm256_set_m128(h1, l1);
    // Within each 128-bit lane [a0 a2 b0 b2] = columns 0, 2, 4, 6, and [a1 a3 b1 b3].
    let even = _mm256_shuffle_ps::<0x88>(a, b);
    let odd = _mm256_shuffle_ps::<0xDD>(a, b);
    // Columns −1 (zero), 1, 3, 5 in each lane: a byte shift within lanes brings in zeros.
    let left = _mm256_castsi256_ps(_mm256_slli_si256::<4>(_mm256_castps_si256(odd)));
    [left, even, odd]
}

/// The `ho` output rows of four of one 8-wide plane of `h` rows.
///
/// # Safety
/// The CPU has AVX2 and FMA; `x` holds h·8 values and `out` ho·4.
#[target_feature(enable = "avx2,fma")]
unsafe fn plane(h: usize, ho: usize, x: &[f32], wk: &[f32; 9], out: &mut [MaybeUninit<f32>]) {
    // SAFETY: as this function's.
    unsafe { at_height!(h, SQUARE, plane_rows(h, ho, x, wk, out)) }
}

/// [`plane`] for planes of `H` rows (`h` and `ho` unused), or of `h` when `H` is 0.
///
/// # Safety
/// As [`plane`]'s.
#[target_feature(enable = "avx2,fma")]
unsafe fn plane_rows<const H: usize>(
    h: usize,
    ho: usize,
    x: &[f32],
    wk: &[f32; 9],
    out: &mut [MaybeUninit<f32>],
) {
    let (h, ho) = if H > 0 { (H, H.div_ceil(2)) } else { (h, ho) };
    assert!(x.len() >= h * 8 && out.len() >= ho * 4);
    let wv: [__m256; 9] = std::array::from_fn(|t| _mm256_set1_ps(wk[t]));
    let mut m = 0;
    while m < ho {
        // Output row m reads input rows 2m − 1 + ky, row m + 1 rows 2m + 1 + ky.
        let r = 2 * m as isize;
        let mut acc = _mm256_setzero_ps();
        for ky in 0..3 {
            let row = taps(x, h, r - 1 + ky as isize, r + 1 + ky as isize);
            for (kx, v) in row.iter().enumerate() {
                acc = _mm256_fmadd_ps(wv[3 * ky + kx], *v, acc);
            }
        }
        store_row_pair(out, ho, m, acc);
        m += 2;
    }
}

/// Backward over all planes (as [`super::backward`]): dL/dx into `dx`, each plane's nine
/// weight gradients into `dw_planes` (overwritten); panics unless `takes(g)`.
pub(super) fn backward(
    g: &Geom,
    c: usize,
    inputs: (&[f32], &[f32], &[f32]),
    dx: &mut [MaybeUninit<f32>],
    dw_planes: &mut [f32],
) {
    assert!(takes(g), "rows of 8 for {g:?}");
    // SAFETY: `takes` checked AVX2 and FMA on this CPU.
    backward_planes(
        g,
        c,
        inputs,
        (dx, dw_planes),
        &|h, ho, xwd, dx, dw, _| unsafe { plane_backward(h, ho, xwd, dx, dw) },
    );
}

/// Output row `m` of an 8-wide plane's `ho` rows of dL/dy as D = [row | row] and D' = [0 |
/// the row shifted left by one value, zero last]; zeros past the last row.
#[target_feature(enable = "avx2,fma")]
#[inline]
fn out_row(dy: &[f32], ho: usize, m: usize) -> (__m256, __m256) {
    let zero = _mm256_setzero_ps();
    if m >= ho {
        return (zero, zero);
    }
    // A slice, not the caller's length check alone, bounds this read: ho·4 wraps for absurd ho.
    let r = &dy[4 * m..][..4];
    // SAFETY: `r` holds four values.
    let v = unsafe { _mm_loadu_ps(r.as_ptr()) };
    let d = _mm256_set_m128(v, v);
    // [d1 d2 d3 d0] per lane, then zeros over the low lane and the last value.
    (
        d,
        _mm256_blend_ps::<0x8F>(_mm256_permute_ps::<0x39>(d), zero),
    )
}

/// Input row `r` of an 8-wide plane of `h` rows as [even | odd] columns; zeros outside the
/// plane (its padding).
#[target_feature(enable = "avx2,fma")]
#[inline]
fn split(x: &[f32], h: usize, r: isize) -> __m256 {
    if r < 0 || r as usize >= h {
        return _mm256_setzero_ps();
    }
    let row = &x[r as usize * 8..][..8];
    // SAFETY: `row` holds eight values.
    let v = unsafe { _mm256_loadu_ps(row.as_ptr()) };
    _mm256_permutevar8x32_ps(v, _mm256_setr_epi32(0, 2, 4, 6, 1, 3, 5, 7))
}

/// One 8-wide plane's backward: `x` h·8 values, `dy` ho·4, into `dx` (h·8, written whole) and
/// `dw` (the nine taps' gradients, overwritten).
///
/// Registers hold one row of four outputs in both lanes, D = [dy row | dy row], and
/// D' = [0 | dy row shifted left by one value, zero last]. An input row split into [even |
/// odd] columns is, for output j, [centre tap | right tap] (one permute per row), and its odd
/// half against D' pairs output j + 1 with its left tap: so dL/dw needs no per-tap shuffles,
/// only D ⊙ row and D' ⊙ row per (output row, tap row), and dL/dx for an input row is at most
/// four multiply–adds of D, D' of the two output rows it touches with [weight | weight]
/// pairs, then one permute to interleave its columns. dL/dw sums each lane over even output
/// rows, then odd ones, adds the two and reduces the lanes (s₀ + s₂) + (s₁ + s₃): the sums
/// and orders of the two-rows-per-register version this replaced (the left taps' lanes move
/// by one, a reordering that addition's commutativity leaves exact), whose bits it gave on
/// random planes of 1–40 rows when it replaced it (zeros may differ in sign). With infinite
/// values the left taps' sums differ from that version's and the plane path's: an infinite
/// x in the last column makes them NaN (0 · ∞ in D′'s zero lane; dropping that lane by a
/// blend made the backward 9 % slower), and an infinite dL/dy in an output row's first
/// column does not (there it met the padding column). Sums are in other orders than the
/// plane path's: the same values to round-off (test `rows_of_8_backward_is_the_plane_paths`).
///
/// # Safety
/// The CPU has AVX2 and FMA; the slices are as long as stated.
#[target_feature(enable = "avx2,fma")]
unsafe fn plane_backward(
    h: usize,
    ho: usize,
    inputs: (&[f32], &[f32; 9], &[f32]),
    dx: &mut [MaybeUninit<f32>],
    dw: &mut [f32; 9],
) {
    // SAFETY: as this function's.
    unsafe { at_height!(h, SQUARE, plane_backward_rows(h, ho, inputs, dx, dw)) }
}

/// [`plane_backward`] for planes of `H` rows (`h` and `ho` unused), or of `h` when `H` is 0.
///
/// # Safety
/// As [`plane_backward`]'s.
#[target_feature(enable = "avx2,fma")]
unsafe fn plane_backward_rows<const H: usize>(
    h: usize,
    ho: usize,
    (x, wk, dy): (&[f32], &[f32; 9], &[f32]),
    dx: &mut [MaybeUninit<f32>],
    dw: &mut [f32; 9],
) {
    let (h, ho) = if H > 0 { (H, H.div_ceil(2)) } else { (h, ho) };
    assert!(x.len() >= h * 8 && dx.len() >= h * 8 && dy.len() >= ho * 4);
    let zero = _mm256_setzero_ps();
    let dy_row = |m: usize| out_row(dy, ho, m);
    // Per tap row ky, [centre | right] sums (D ⊙ input row) at 2ky and [· | left] ones
    // (D' ⊙ input row) at 2ky + 1: over even output rows, then odd ones added.
    let mut sums = [zero; 6];
    for first in 0..2 {
        let (mut c0, mut c1, mut c2, mut l0, mut l1, mut l2) = (zero, zero, zero, zero, zero, zero);
        let mut m = first;
        while m < ho {
            let (d, next) = dy_row(m);
            let r = 2 * m as isize - 1;
            let (r0, r1, r2) = (split(x, h, r), split(x, h, r + 1), split(x, h, r + 2));
            c0 = _mm256_fmadd_ps(d, r0, c0);
            l0 = _mm256_fmadd_ps(next, r0, l0);
            c1 = _mm256_fmadd_ps(d, r1, c1);
            l1 = _mm256_fmadd_ps(next, r1, l1);
            c2 = _mm256_fmadd_ps(d, r2, c2);
            l2 = _mm256_fmadd_ps(next, r2, l2);
            m += 2;
        }
        for (s, a) in sums.iter_mut().zip([c0, l0, c1, l1, c2, l2]) {
            *s = if first == 0 { a } else { _mm256_add_ps(*s, a) };
        }
    }
    // Within each lane (s₀ + s₂, s₁ + s₃), then their sum in value 0.
    let reduce = |v: __m256| {
        let u = _mm256_add_ps(v, _mm256_permute_ps::<0x4E>(v));
        _mm256_add_ps(u, _mm256_movehdup_ps(u))
    };
    for ky in 0..3 {
        let (c, l) = (reduce(sums[2 * ky]), reduce(sums[2 * ky + 1]));
        dw[3 * ky] = _mm_cvtss_f32(_mm256_extractf128_ps::<1>(l));
        dw[3 * ky + 1] = _mm256_cvtss_f32(c);
        dw[3 * ky + 2] = _mm_cvtss_f32(_mm256_extractf128_ps::<1>(c));
    }
    // Input row 2m takes tap row 1 of output row m; row 2m + 1 tap row 2 of m, then 0 of
    // m + 1; in each, the even columns the centre tap of D and the odd ones its right tap and
    // the left tap of D' (a sum in the order of the version this replaced, up to added
    // zeros).
    let pair = |lo: f32, hi: f32| _mm256_setr_m128(_mm_set1_ps(lo), _mm_set1_ps(hi));
    let (w_even, w_even_next) = (pair(wk[4], wk[5]), pair(0.0, wk[3]));
    let (w_odd, w_odd_next) = (pair(wk[7], wk[8]), pair(0.0, wk[6]));
    let (w_below, w_below_next) = (pair(wk[1], wk[2]), pair(0.0, wk[0]));
    let interleave = _mm256_setr_epi32(0, 4, 1, 5, 2, 6, 3, 7);
    let mut below = dy_row(0);
    for m in 0..h.div_ceil(2) {
        let (d, next) = below;
        below = dy_row(m + 1);
        let even = _mm256_fmadd_ps(w_even_next, next, _mm256_mul_ps(w_even, d));
        let dst = &mut dx[16 * m..][..8];
        // SAFETY: `dst` holds eight values, input row 2m.
        unsafe {
            _mm256_storeu_ps(
                dst.as_mut_ptr().cast(),
                _mm256_permutevar8x32_ps(even, interleave),
            )
        };
        if 2 * m + 1 < h {
            let odd = _mm256_fmadd_ps(w_odd_next, next, _mm256_mul_ps(w_odd, d));
            let odd = _mm256_fmadd_ps(w_below, below.0, odd);
            let odd = _mm256_fmadd_ps(w_below_next, below.1, odd);
            let dst = &mut dx[16 * m + 8..][..8];
            // SAFETY: `dst` holds eight values, input row 2m + 1.
            unsafe {
                _mm256_storeu_ps(
                    dst.as_mut_ptr().cast(),
                    _mm256_permutevar8x32_ps(odd, interleave),
                )
            };
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Planes of 8 columns through the entry point: y bit for bit the plane path's
    /// (`assert_plane_path_bits`: 1–40 rows, odd and even, several planes and channels).
    #[test]
    fn rows_of_8_give_the_plane_paths_bits() {
        if !has_fma() {
            return;
        }
        super::super::assert_plane_path_bits((8, 3, 2), 8, forward);
    }

    /// The backward through the entry point against the plane path's, planes of 1–40 rows:
    /// dL/dx and dL/dw equal to round-off (other summation orders).
    #[test]
    fn rows_of_8_backward_is_the_plane_paths() {
        if !has_fma() {
            return;
        }
        super::super::assert_plane_path_backward((8, 3, 2), 88, false, backward);
    }
}

//! Depthwise 3×3 at stride 2 on planes 16 pixels wide, forward, in registers.
//!
//! Such a plane's output rows are eight values, one 256-bit register, and each input row is
//! two: its even and odd columns are split by two shuffles and its odd columns shifted by one
//! lane give the left tap, so an output row is nine fused multiply–adds on registers, with no
//! padded copy of the plane and no transposition into channel blocks (the channel-block path,
//! which took these planes, spent more on its transposes than on its multiply–adds: 240×16×16
//! at stride 2 ran at 1.65× the memory roofline). Each output sums its taps in (ky, kx) order
//! from zero, as the plane path does, so y is the plane path's bits (test
//! `rows_of_16_give_the_plane_paths_bits`).

use super::{Geom, backward_planes, forward_planes, has_fma};
use std::arch::x86_64::*;
use std::mem::MaybeUninit;

/// Height of the square planes (a 128² input at stride 8) whose row loops are compiled for
/// it: unrolled, with their padding rows known, the forward and backward of 240×16×16 ran
/// 7 % and 22 % faster on one thread than with the height a run-time value.
const SQUARE: usize = 16;

/// Whether a layer with this geometry goes through this path.
pub(super) fn takes(g: &Geom) -> bool {
    g.k == 3
        && g.s == 2
        && g.w == 16
        && g.wo == 8
        && g.h > 0
        && g.ho == g.h.div_ceil(2)
        && has_fma()
}

/// Forward over all planes (as [`super::forward`]); panics unless `takes(g)`.
pub(super) fn forward(g: &Geom, c: usize, x: &[f32], w: &[f32], y: &mut [MaybeUninit<f32>]) {
    // The planes below run AVX2 and FMA code on that check alone.
    assert!(takes(g), "rows of 16 for {g:?}");
    // SAFETY: `takes` checked AVX2 and FMA on this CPU.
    forward_planes(g, c, (x, w), y, |h, ho, x, wk, out| unsafe {
        plane(h, ho, x, wk, out)
    });
}

/// A padding row.
static ZEROS: [f32; 16] = [0.0; 16];

/// One input row `r` (−1 and `h` are the zero padding) as its (left, centre, right) taps for
/// the eight outputs: odd columns shifted right by one, even columns, odd columns.
#[target_feature(enable = "avx2,fma")]
#[inline]
fn taps(x: &[f32], h: usize, r: isize) -> [__m256; 3] {
    if r < 0 || r as usize >= h {
        return [_mm256_setzero_ps(); 3];
    }
    row_taps(&x[r as usize * 16..][..16])
}

/// As [`taps`], the padding rows read from a row of zeros: a select rather than a branch
/// around the loads (the forward 11 % faster on 240×16×16, one thread; the backward's dL/dw
/// 5 % slower that way, so it keeps [`taps`]).
#[target_feature(enable = "avx2,fma")]
#[inline]
fn taps_selected(x: &[f32], h: usize, r: isize) -> [__m256; 3] {
    row_taps(if r < 0 || r as usize >= h {
        &ZEROS
    } else {
        &x[r as usize * 16..][..16]
    })
}

/// A row of sixteen values as its (left, centre, right) taps for the eight outputs.
#[target_feature(enable = "avx2,fma")]
#[inline]
fn row_taps(row: &[f32]) -> [__m256; 3] {
    let row = &row[..16];
    // SAFETY: `row` holds 16 values: two loads of eight.
    let (lo, hi) = unsafe {
        (
            _mm256_loadu_ps(row.as_ptr()),
            _mm256_loadu_ps(row.as_ptr().add(8)),
        )
    };
    // Within each 128-bit lane [lo0 lo2 hi0 hi2] / [lo1 lo3 hi1 hi3]; the 64-bit quarters
    // then put back in column order.
    let order = |v: __m256| _mm256_castpd_ps(_mm256_permute4x64_pd::<0xD8>(_mm256_castps_pd(v)));
    let even = order(_mm256_shuffle_ps::<0x88>(lo, hi));
    let odd = order(_mm256_shuffle_ps::<0xDD>(lo, hi));
    let shifted = _mm256_permutevar8x32_ps(odd, _mm256_setr_epi32(0, 0, 1, 2, 3, 4, 5, 6));
    [
        _mm256_blend_ps::<1>(shifted, _mm256_setzero_ps()),
        even,
        odd,
    ]
}

/// The `ho` output rows of eight of one 16-wide plane of `h` rows.
///
/// # Safety
/// The CPU has AVX2 and FMA; `x` holds h·16 values and `out` ho·8.
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
    assert!(x.len() >= h * 16 && out.len() >= ho * 8);
    let wv: [__m256; 9] = std::array::from_fn(|t| _mm256_set1_ps(wk[t]));
    // Output row m reads input rows 2m − 1, 2m, 2m + 1; the last is the next row's first.
    let mut top = taps_selected(x, h, -1);
    for m in 0..ho {
        let mid = taps_selected(x, h, 2 * m as isize);
        let bottom = taps_selected(x, h, 2 * m as isize + 1);
        let mut acc = _mm256_setzero_ps();
        for (ky, row) in [&top, &mid, &bottom].into_iter().enumerate() {
            for (kx, v) in row.iter().enumerate() {
                acc = _mm256_fmadd_ps(wv[3 * ky + kx], *v, acc);
            }
        }
        let dst = &mut out[8 * m..][..8];
        // SAFETY: `dst` holds eight values.
        unsafe { _mm256_storeu_ps(dst.as_mut_ptr().cast(), acc) };
        top = bottom;
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
    assert!(takes(g), "rows of 16 for {g:?}");
    // SAFETY: `takes` checked AVX2 and FMA on this CPU.
    backward_planes(
        g,
        c,
        inputs,
        (dx, dw_planes),
        &|h, ho, xwd, dx, dw, _| unsafe { plane_backward(h, ho, xwd, dx, dw) },
    );
}

/// One 16-wide plane's backward: `x` h·16 values, `dy` ho·8, into `dx` (h·16, written whole)
/// and `dw` (the nine taps' gradients, overwritten): dL/dw from the forward's tap registers
/// against each output row, reduced across lanes at the end; dL/dx row by row as its even
/// and odd columns, interleaved. Sums in other orders than the plane path's (test
/// `rows_of_16_backward_is_the_plane_paths`).
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
    assert!(x.len() >= h * 16 && dx.len() >= h * 16 && dy.len() >= ho * 8);
    let mut acc = [_mm256_setzero_ps(); 9];
    let mut top = taps(x, h, -1);
    for m in 0..ho {
        let mid = taps(x, h, 2 * m as isize);
        let bottom = taps(x, h, 2 * m as isize + 1);
        // A slice, not the assert above alone, bounds the read: ho·8 wraps for absurd ho.
        let r = &dy[8 * m..][..8];
        // SAFETY: `r` holds eight values.
        let d = unsafe { _mm256_loadu_ps(r.as_ptr()) };
        for (ky, row) in [&top, &mid, &bottom].into_iter().enumerate() {
            for (kx, v) in row.iter().enumerate() {
                acc[3 * ky + kx] = _mm256_fmadd_ps(d, *v, acc[3 * ky + kx]);
            }
        }
        top = bottom;
    }
    for (g, a) in dw.iter_mut().zip(acc) {
        *g = lane_sum(a);
    }
    let w = |t: usize| _mm256_set1_ps(wk[t]);
    let next = _mm256_setr_epi32(1, 2, 3, 4, 5, 6, 7, 7);
    // Output row m (zero past the last) and the same shifted left by one value.
    let row = |m: usize| -> (__m256, __m256) {
        if m >= ho {
            return (_mm256_setzero_ps(), _mm256_setzero_ps());
        }
        let r = &dy[8 * m..][..8];
        // SAFETY: `r` holds eight values.
        let v = unsafe { _mm256_loadu_ps(r.as_ptr()) };
        let shifted = _mm256_permutevar8x32_ps(v, next);
        (v, _mm256_blend_ps::<0x80>(shifted, _mm256_setzero_ps()))
    };
    for r in 0..h {
        let (even, odd) = if r % 2 == 0 {
            let (a, a1) = row(r / 2);
            let e = _mm256_mul_ps(w(4), a);
            (e, _mm256_fmadd_ps(w(3), a1, _mm256_mul_ps(w(5), a)))
        } else {
            let ((a, a1), (b, b1)) = (row(r / 2), row(r / 2 + 1));
            let e = _mm256_fmadd_ps(w(1), b, _mm256_mul_ps(w(7), a));
            let o = _mm256_fmadd_ps(w(6), a1, _mm256_mul_ps(w(8), a));
            let o = _mm256_fmadd_ps(w(0), b1, _mm256_fmadd_ps(w(2), b, o));
            (e, o)
        };
        // Within each 128-bit lane [e0 o0 e1 o1] and [e2 o2 e3 o3]: columns 0–7 are the low
        // lanes of both, columns 8–15 the high lanes.
        let (lo, hi) = (_mm256_unpacklo_ps(even, odd), _mm256_unpackhi_ps(even, odd));
        let dst = &mut dx[16 * r..][..16];
        // SAFETY: `dst` holds sixteen values: two stores of eight.
        unsafe {
            _mm256_storeu_ps(
                dst.as_mut_ptr().cast(),
                _mm256_permute2f128_ps::<0x20>(lo, hi),
            );
            _mm256_storeu_ps(
                dst.as_mut_ptr().cast::<f32>().add(8),
                _mm256_permute2f128_ps::<0x31>(lo, hi),
            );
        }
    }
}

/// The sum of a register's eight lanes.
#[target_feature(enable = "avx2,fma")]
#[inline]
fn lane_sum(v: __m256) -> f32 {
    let s = _mm_add_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps::<1>(v));
    let s = _mm_add_ps(s, _mm_movehl_ps(s, s));
    _mm_cvtss_f32(_mm_add_ss(s, _mm_movehdup_ps(s)))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Planes of 16 columns through the entry point: y bit for bit the plane path's
    /// (`assert_plane_path_bits`: 1–40 rows, several planes and channels).
    #[test]
    fn rows_of_16_give_the_plane_paths_bits() {
        if !has_fma() {
            return;
        }
        super::super::assert_plane_path_bits((16, 3, 2), 16, forward);
    }

    /// The backward through the entry point against the plane path's, planes of 1–40 rows:
    /// dL/dx and dL/dw equal to round-off (other summation orders).
    #[test]
    fn rows_of_16_backward_is_the_plane_paths() {
        if !has_fma() {
            return;
        }
        super::super::assert_plane_path_backward((16, 3, 2), 1616, false, backward);
    }
}

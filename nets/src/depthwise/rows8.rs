//! Depthwise 3×3 at stride 2 on planes 8 pixels wide, forward, two output rows per register.
//!
//! Such a plane's output rows are four values, half a 256-bit register, and consecutive output
//! rows are contiguous, so a register holds output rows m and m + 1. Its low lane reads input
//! rows 2m − 1 + ky and its high lane rows 2m + 1 + ky: each pair of input rows is split into
//! even and odd columns by two in-lane shuffles, and the odd columns shifted by one value
//! within each lane give the left tap, so an output pair is nine fused multiply–adds and one
//! store, with no padded copy of the plane and no transposition into channel blocks (the
//! channel-block path, which took these planes, ran 480×8×8 at stride 2 at 1.5–1.7× the
//! memory roofline). Each output sums its taps in (ky, kx) order from zero, as the plane path
//! does, so y is the plane path's bits (test `rows_of_8_give_the_plane_paths_bits`).

use super::{Geom, backward_planes, forward_planes, has_fma};
use std::arch::x86_64::*;
use std::mem::MaybeUninit;

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
        if m + 1 < ho {
            let dst = &mut out[4 * m..][..8];
            // SAFETY: `dst` holds eight values: output rows m and m + 1.
            unsafe { _mm256_storeu_ps(dst.as_mut_ptr().cast(), acc) };
        } else {
            // An odd last row: its pair's high lane is past the plane.
            let dst = &mut out[4 * m..][..4];
            // SAFETY: `dst` holds four values.
            unsafe { _mm_storeu_ps(dst.as_mut_ptr().cast(), _mm256_castps256_ps128(acc)) };
        }
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

/// The sum of a register's eight lanes.
#[target_feature(enable = "avx2,fma")]
#[inline]
pub(super) fn lane_sum(v: __m256) -> f32 {
    let s = _mm_add_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps::<1>(v));
    let s = _mm_add_ps(s, _mm_movehl_ps(s, s));
    _mm_cvtss_f32(_mm_add_ss(s, _mm_movehdup_ps(s)))
}

/// One 8-wide plane's backward: `x` h·8 values, `dy` ho·4, into `dx` (h·8, written whole) and
/// `dw` (the nine taps' gradients, overwritten).
///
/// dL/dw[ky, kx] is Σ dy ⊙ (the forward's tap register), two output rows per register as in
/// the forward, reduced across lanes at the end. dL/dx two input rows per register: an even
/// input row 2m takes only ky = 1 of output row m, an odd row 2m + 1 ky = 2 of row m and
/// ky = 0 of row m + 1; within a row, even column 2j takes kx = 1 of output j, odd column
/// 2j + 1 kx = 2 of j and kx = 0 of j + 1 (output row shifted by one value). The even and odd
/// columns are then interleaved into the rows. Sums are in other orders than the plane path's:
/// the same values to round-off (test `rows_of_8_backward_is_the_plane_paths`).
///
/// # Safety
/// The CPU has AVX2 and FMA; the slices are as long as stated.
#[target_feature(enable = "avx2,fma")]
unsafe fn plane_backward(
    h: usize,
    ho: usize,
    (x, wk, dy): (&[f32], &[f32; 9], &[f32]),
    dx: &mut [MaybeUninit<f32>],
    dw: &mut [f32; 9],
) {
    assert!(x.len() >= h * 8 && dx.len() >= h * 8 && dy.len() >= ho * 4);
    let mut acc = [_mm256_setzero_ps(); 9];
    let mut m = 0;
    while m < ho {
        let r = 2 * m as isize;
        // Slices, not the assert above alone, bound these reads: ho·4 wraps for absurd ho.
        let lo = &dy[4 * m..][..4];
        let hi = (m + 1 < ho).then(|| &dy[4 * m + 4..][..4]);
        // SAFETY: four values each.
        let d = unsafe {
            let hi = hi.map_or(_mm_setzero_ps(), |r| _mm_loadu_ps(r.as_ptr()));
            _mm256_set_m128(hi, _mm_loadu_ps(lo.as_ptr()))
        };
        for ky in 0..3 {
            let row = taps(x, h, r - 1 + ky as isize, r + 1 + ky as isize);
            for (kx, v) in row.iter().enumerate() {
                acc[3 * ky + kx] = _mm256_fmadd_ps(d, *v, acc[3 * ky + kx]);
            }
        }
        m += 2;
    }
    for (g, a) in dw.iter_mut().zip(acc) {
        *g = lane_sum(a);
    }
    // Input rows 2m and 2m + 1 at once, row 2m in the low lane and 2m + 1 in the high one:
    // with a = output row m in both lanes and b = row m + 1 in the high lane only (zeros
    // below), e = (w4 | w7)·a + (· | w1)·b and o = (w5 | w8)·a + (w3 | w6)·a' + (· | w2)·b +
    // (· | w0)·b' (' = shifted left by one value): each lane's sum in the order of the row at
    // a time this replaces, the low lane's extra terms multiplying zeros (with finite weights,
    // its values up to a zero's sign; an infinite w0, w1 or w2 makes them NaN).
    let pair = |lo: usize, hi: usize| _mm256_setr_m128(_mm_set1_ps(wk[lo]), _mm_set1_ps(wk[hi]));
    let (we_a, we_b) = (pair(4, 7), _mm256_set1_ps(wk[1]));
    let (wo_a, wo_a1) = (pair(5, 8), pair(3, 6));
    let (wo_b, wo_b1) = (_mm256_set1_ps(wk[2]), _mm256_set1_ps(wk[0]));
    // Output row m (zero past the last) as four values.
    let row = |m: usize| -> __m128 {
        if m >= ho {
            return _mm_setzero_ps();
        }
        let r = &dy[4 * m..][..4];
        // SAFETY: `r` holds four values.
        unsafe { _mm_loadu_ps(r.as_ptr()) }
    };
    let shifted = |v: __m256| _mm256_castsi256_ps(_mm256_srli_si256::<4>(_mm256_castps_si256(v)));
    for m in 0..h.div_ceil(2) {
        let v = row(m);
        let a = _mm256_setr_m128(v, v);
        let b = _mm256_setr_m128(_mm_setzero_ps(), row(m + 1));
        let e = _mm256_fmadd_ps(we_b, b, _mm256_mul_ps(we_a, a));
        let o = _mm256_fmadd_ps(wo_a1, shifted(a), _mm256_mul_ps(wo_a, a));
        let o = _mm256_fmadd_ps(wo_b1, shifted(b), _mm256_fmadd_ps(wo_b, b, o));
        // Per lane [e0 o0 e1 o1] and [e2 o2 e3 o3]: row 2m is the two low lanes, row 2m + 1
        // the two high ones.
        let (lo, hi) = (_mm256_unpacklo_ps(e, o), _mm256_unpackhi_ps(e, o));
        let dst = &mut dx[16 * m..][..8];
        // SAFETY: `dst` holds eight values, input row 2m.
        unsafe {
            _mm256_storeu_ps(
                dst.as_mut_ptr().cast(),
                _mm256_permute2f128_ps::<0x20>(lo, hi),
            )
        };
        if 2 * m + 1 < h {
            let dst = &mut dx[16 * m + 8..][..8];
            // SAFETY: `dst` holds eight values, input row 2m + 1.
            unsafe {
                _mm256_storeu_ps(
                    dst.as_mut_ptr().cast(),
                    _mm256_permute2f128_ps::<0x31>(lo, hi),
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

//! Depthwise 3×3 at stride 1 on planes 4 pixels wide, forward, two rows per register.
//!
//! The last stage's maps at a 128² input are 4×4: a plane is two registers, and the channel
//! blocks (eight planes transposed into channels innermost and back, for sixteen outputs
//! each) spent more on the transpositions than on the multiply–adds: 672×4×4 at batch 16
//! took 75.9–77.0 µs there (20.1–20.4 GMAC/s), 58.4–62.6 µs here with the plane's height
//! read at run time and 38.6–38.8 µs (39.9–40.1 GMAC/s) with the 4×4 plane's compiled in
//! (`dw_prof`, two threads, AMD EPYC VM).
//! Here a register holds output rows m and m + 1; tap row ky reads input rows m − 1 + ky and
//! m + ky, themselves one register (rows outside the plane zero), and the left and right taps
//! are that register's rows shifted by one value within each 128-bit lane, a zero shifted in
//! (the padding columns): nine fused multiply–adds and one store per two output rows. Each
//! output sums its taps from zero in (ky, kx) order, padding included, as the plane path
//! does, so y is the plane path's bits (test `rows_of_4_give_the_plane_paths_bits`).

use super::{Geom, forward_planes, has_fma, store_row_pair};
use std::arch::x86_64::*;
use std::mem::MaybeUninit;

/// Whether a layer with this geometry goes through this path.
pub(super) fn takes(g: &Geom) -> bool {
    g.k == 3 && g.s == 1 && g.w == 4 && g.wo == 4 && g.h > 0 && g.ho == g.h && has_fma()
}

/// Forward over all planes (as [`super::forward`]); panics unless `takes(g)`.
pub(super) fn forward(g: &Geom, c: usize, x: &[f32], w: &[f32], y: &mut [MaybeUninit<f32>]) {
    // The planes below run AVX2 and FMA code on that check alone.
    assert!(takes(g), "rows of 4 for {g:?}");
    // SAFETY: `takes` checked AVX2 and FMA on this CPU.
    forward_planes(g, c, (x, w), y, |h, _, x, wk, out| unsafe {
        plane(h, x, wk, out)
    });
}

/// Input rows `r` (low lane) and `r + 1` (high lane) of a 4-wide plane of `h` rows; rows
/// outside the plane are zeros.
#[target_feature(enable = "avx2,fma")]
#[inline]
fn pair(x: &[f32], h: usize, r: isize) -> __m256 {
    if r >= 0 && (r as usize) + 1 < h {
        let v = &x[r as usize * 4..][..8];
        // SAFETY: `v` holds eight values.
        return unsafe { _mm256_loadu_ps(v.as_ptr()) };
    }
    let row = |r: isize| {
        if r < 0 || r as usize >= h {
            return _mm_setzero_ps();
        }
        let v = &x[r as usize * 4..][..4];
        // SAFETY: `v` holds four values.
        unsafe { _mm_loadu_ps(v.as_ptr()) }
    };
    _mm256_set_m128(row(r + 1), row(r))
}

/// Height of the square planes (a 128² input at stride 32) whose row loop is compiled for it:
/// unrolled, its padding rows known.
const SQUARE: usize = 4;

/// The `h` output rows of four of one 4-wide plane of `h` rows.
///
/// # Safety
/// The CPU has AVX2 and FMA; `x` and `out` hold h·4 values.
#[target_feature(enable = "avx2,fma")]
unsafe fn plane(h: usize, x: &[f32], wk: &[f32; 9], out: &mut [MaybeUninit<f32>]) {
    // SAFETY: as this function's.
    unsafe { at_height!(h, SQUARE, plane_rows(h, x, wk, out)) }
}

/// [`plane`] for planes of `H` rows (`h` unused), or of `h` when `H` is 0.
///
/// # Safety
/// As [`plane`]'s.
#[target_feature(enable = "avx2,fma")]
unsafe fn plane_rows<const H: usize>(
    h: usize,
    x: &[f32],
    wk: &[f32; 9],
    out: &mut [MaybeUninit<f32>],
) {
    let h = if H > 0 { H } else { h };
    assert!(x.len() >= h * 4 && out.len() >= h * 4);
    let wv: [__m256; 9] = std::array::from_fn(|t| _mm256_set1_ps(wk[t]));
    let mut m = 0;
    while m < h {
        let mut acc = _mm256_setzero_ps();
        for ky in 0..3 {
            // Output rows m, m + 1 read input rows m − 1 + ky, m + ky.
            let c = pair(x, h, m as isize - 1 + ky as isize);
            let c_i = _mm256_castps_si256(c);
            // Columns j − 1 and j + 1 within each row: a byte shift within each 128-bit lane
            // brings in the padding's zero.
            let left = _mm256_castsi256_ps(_mm256_slli_si256::<4>(c_i));
            let right = _mm256_castsi256_ps(_mm256_srli_si256::<4>(c_i));
            acc = _mm256_fmadd_ps(wv[3 * ky], left, acc);
            acc = _mm256_fmadd_ps(wv[3 * ky + 1], c, acc);
            acc = _mm256_fmadd_ps(wv[3 * ky + 2], right, acc);
        }
        store_row_pair(out, h, m, acc);
        m += 2;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Planes of 4 columns through the entry point: y bit for bit the plane path's
    /// (`assert_plane_path_bits`: 1–40 rows, odd and even, several planes and channels).
    #[test]
    fn rows_of_4_give_the_plane_paths_bits() {
        if !has_fma() {
            return;
        }
        super::super::assert_plane_path_bits((4, 3, 1), 4, forward);
    }
}

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

use super::{Geom, has_fma};
use rayon::prelude::*;
use std::arch::x86_64::*;

/// Whether a layer with this geometry goes through this path.
pub(super) fn takes(g: &Geom) -> bool {
    g.k == 3 && g.s == 2 && g.w == 8 && g.wo == 4 && g.h > 0 && has_fma()
}

/// Forward over all planes (as [`super::forward`]); panics unless `takes(g)`.
pub(super) fn forward(g: &Geom, c: usize, x: &[f32], w: &[f32], y: &mut [f32]) {
    // The planes below run AVX2 and FMA code on that check alone.
    assert!(takes(g), "rows of 8 for {g:?}");
    let (hw, howo) = (g.h * g.w, g.ho * g.wo);
    assert!(x.len() / hw == y.len() / howo && w.len() == 9 * c);
    y.par_chunks_mut(howo)
        .enumerate()
        .with_min_len(g.planes_per_task())
        .for_each(|(idx, out)| {
            let xp = &x[idx * hw..][..hw];
            let wk: &[f32; 9] = w[(idx % c) * 9..][..9].try_into().expect("nine taps");
            // SAFETY: `takes` checked AVX2 and FMA on this CPU.
            unsafe { plane(g.h, g.ho, xp, wk, out) };
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
unsafe fn plane(h: usize, ho: usize, x: &[f32], wk: &[f32; 9], out: &mut [f32]) {
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
            unsafe { _mm256_storeu_ps(dst.as_mut_ptr(), acc) };
        } else {
            // An odd last row: its pair's high lane is past the plane.
            let dst = &mut out[4 * m..][..4];
            // SAFETY: `dst` holds four values.
            unsafe { _mm_storeu_ps(dst.as_mut_ptr(), _mm256_castps256_ps128(acc)) };
        }
        m += 2;
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
        super::super::assert_plane_path_bits(8, 8, forward);
    }
}

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

use super::{Geom, has_fma};
use rayon::prelude::*;
use std::arch::x86_64::*;

/// Whether a layer with this geometry goes through this path.
pub(super) fn takes(g: &Geom) -> bool {
    g.k == 3 && g.s == 2 && g.w == 16 && g.wo == 8 && g.h > 0 && has_fma()
}

/// Forward over all planes (as [`super::forward`]); panics unless `takes(g)`.
pub(super) fn forward(g: &Geom, c: usize, x: &[f32], w: &[f32], y: &mut [f32]) {
    // The planes below run AVX2 and FMA code on that check alone.
    assert!(takes(g), "rows of 16 for {g:?}");
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

/// One input row `r` (−1 and `h` are the zero padding) as its (left, centre, right) taps for
/// the eight outputs: odd columns shifted right by one, even columns, odd columns.
#[target_feature(enable = "avx2,fma")]
#[inline]
fn taps(x: &[f32], h: usize, r: isize) -> [__m256; 3] {
    let zero = _mm256_setzero_ps();
    if r < 0 || r as usize >= h {
        return [zero; 3];
    }
    let row = &x[r as usize * 16..][..16];
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
    [_mm256_blend_ps::<1>(shifted, zero), even, odd]
}

/// The `ho` output rows of eight of one 16-wide plane of `h` rows.
///
/// # Safety
/// The CPU has AVX2 and FMA; `x` holds h·16 values and `out` ho·8.
#[target_feature(enable = "avx2,fma")]
unsafe fn plane(h: usize, ho: usize, x: &[f32], wk: &[f32; 9], out: &mut [f32]) {
    assert!(x.len() >= h * 16 && out.len() >= ho * 8);
    let wv: [__m256; 9] = std::array::from_fn(|t| _mm256_set1_ps(wk[t]));
    // Output row m reads input rows 2m − 1, 2m, 2m + 1; the last is the next row's first.
    let mut top = taps(x, h, -1);
    for m in 0..ho {
        let mid = taps(x, h, 2 * m as isize);
        let bottom = taps(x, h, 2 * m as isize + 1);
        let mut acc = _mm256_setzero_ps();
        for (ky, row) in [&top, &mid, &bottom].into_iter().enumerate() {
            for (kx, v) in row.iter().enumerate() {
                acc = _mm256_fmadd_ps(wv[3 * ky + kx], *v, acc);
            }
        }
        let dst = &mut out[8 * m..][..8];
        // SAFETY: `dst` holds eight values.
        unsafe { _mm256_storeu_ps(dst.as_mut_ptr(), acc) };
        top = bottom;
    }
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
        super::super::assert_plane_path_bits(16, 16, forward);
    }
}

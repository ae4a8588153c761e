//! Depthwise 3×3 at stride 2, forward, read straight from the plane in registers, any width.
//!
//! The plane path splits every plane's columns by parity into a padded scratch before its
//! sweep. Here eight outputs of a row take their three taps from registers: the input columns
//! 2j, 2j + 1 (two loads from column 2x₀, split into even and odd by one in-lane shuffle each)
//! and 2j − 1 (two loads from column 2x₀ − 1, their even half). The shuffles leave the eight
//! outputs in the lane order 0 1 4 5 2 3 6 7 in every tap alike, so the multiply–adds run in
//! that order and one 64-bit permute puts the sum back in column order before its store. Rows
//! above and below the plane are zero taps, and the blocks at the left and right edges load and
//! store with lane masks (masked lanes read as zero). Every output sums its nine taps from
//! zero in (ky, kx) order, padding included, as the plane path does, so y is the plane path's
//! bits (test `stride_2_gives_the_plane_paths_bits`). Planes 8 and 16 wide keep their own paths
//! ([`super::rows8`], [`super::rows16`]), small output planes of channels in multiples of eight
//! the channel blocks.

use super::stride1::inside;
use super::{Geom, HALF, has_fma, k3_forward_planes};
use std::arch::x86_64::*;

/// Whether a layer with this geometry goes through this path.
pub(super) fn takes(g: &Geom) -> bool {
    // Column indices (below w + 2·HALF) fit the lane masks' 32-bit integers.
    g.k == 3
        && g.s == 2
        && g.h > 0
        && g.w > 0
        && g.ho == g.h.div_ceil(2)
        && g.wo == g.w.div_ceil(2)
        && g.w < (i32::MAX as usize) / 2 - 4 * HALF
        && has_fma()
}

/// Forward over all planes (as [`super::forward`]); panics unless `takes(g)`.
pub(super) fn forward(g: &Geom, c: usize, x: &[f32], w: &[f32], y: &mut [f32]) {
    // The planes below run AVX2 and FMA code on that check alone.
    assert!(takes(g), "stride 2 for {g:?}");
    let (width, wo) = (g.w, g.wo);
    // SAFETY: `takes` checked AVX2 and FMA on this CPU; the driver hands each plane its h·w
    // inputs and ho·wo outputs.
    k3_forward_planes(g, c, (x, w), y, |h, ho, x, wk, out| unsafe {
        plane(h, width, (ho, wo), x, wk, out)
    });
}

/// Where a block of eight outputs reads its input row: unmasked, or with the masks of the four
/// loads (columns from 2x₀ − 1, 2x₀ + 7, 2x₀, 2x₀ + 8).
#[derive(Clone, Copy)]
enum Reach {
    Inside,
    Masked([__m256i; 4]),
}

/// Input row `row` (None: the zero padding) as the (left, centre, right) taps of the eight
/// outputs from `x0`, in the lane order 0 1 4 5 2 3 6 7.
///
/// # Safety
/// AVX2; `row` holds at least the columns `reach` lets through (all of 2x₀ − 1 .. 2x₀ + 16 when
/// `Inside`).
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn taps(row: Option<&[f32]>, x0: usize, reach: Reach) -> [__m256; 3] {
    let Some(row) = row else {
        return [_mm256_setzero_ps(); 3];
    };
    let p = row.as_ptr();
    let c = 2 * x0;
    // SAFETY: inside the row by the contract, or masked (masked lanes are neither read nor
    // faulted on; wrapping arithmetic: addresses before or past the row are never dereferenced).
    let [l0, l1, e0, e1] = unsafe {
        match reach {
            Reach::Inside => [
                _mm256_loadu_ps(p.add(c - 1)),
                _mm256_loadu_ps(p.add(c + 7)),
                _mm256_loadu_ps(p.add(c)),
                _mm256_loadu_ps(p.add(c + 8)),
            ],
            Reach::Masked(m) => [
                _mm256_maskload_ps(p.wrapping_add(c).wrapping_sub(1), m[0]),
                _mm256_maskload_ps(p.wrapping_add(c + 7), m[1]),
                _mm256_maskload_ps(p.wrapping_add(c), m[2]),
                _mm256_maskload_ps(p.wrapping_add(c + 8), m[3]),
            ],
        }
    };
    [
        _mm256_shuffle_ps::<0x88>(l0, l1),
        _mm256_shuffle_ps::<0x88>(e0, e1),
        _mm256_shuffle_ps::<0xDD>(e0, e1),
    ]
}

/// One plane: `x` h·w values, `out` ho·wo.
///
/// # Safety
/// The CPU must have AVX2 and FMA; ho = ⌈h/2⌉, wo = ⌈w/2⌉.
#[target_feature(enable = "avx2,fma")]
unsafe fn plane(
    h: usize,
    w: usize,
    (ho, wo): (usize, usize),
    x: &[f32],
    wk: &[f32; 9],
    out: &mut [f32],
) {
    // Checked without wrapping: the blocks below trust these sizes.
    let hw = h.checked_mul(w).expect("plane size overflows");
    let howo = ho.checked_mul(wo).expect("plane size overflows");
    assert!(x.len() == hw && out.len() == howo && ho == h.div_ceil(2) && wo == w.div_ceil(2));
    let wv: [__m256; 9] = std::array::from_fn(|t| _mm256_set1_ps(wk[t]));
    let row = |r: usize| (r < h).then(|| &x[r * w..][..w]);
    // Row by row, left to right: the plane is read in address order. (A column of blocks at
    // a time, reusing each row's taps for two output rows, was no faster than the plane path
    // in a first measurement, beside other jobs.)
    for m in 0..ho {
        let rows = [row((2 * m).wrapping_sub(1)), row(2 * m), row(2 * m + 1)];
        let dst = out[m * wo..][..wo].as_mut_ptr();
        let mut x0 = 0;
        while x0 < wo {
            let c = 2 * x0 as isize;
            let (reach, store) = if x0 >= 1 && 2 * x0 + 2 * HALF <= w {
                (Reach::Inside, None)
            } else {
                let m = [c - 1, c + 7, c, c + 8].map(|s| inside(s, w));
                (Reach::Masked(m), Some(inside(x0 as isize, wo)))
            };
            let mut acc = _mm256_setzero_ps();
            for (ky, r) in rows.iter().enumerate() {
                // SAFETY: every row `row` gives holds w values; `reach` is Inside only where
                // columns 2x₀ − 1 .. 2x₀ + 16 lie inside it.
                let t = unsafe { taps(*r, x0, reach) };
                for (kx, v) in t.iter().enumerate() {
                    acc = _mm256_fmadd_ps(wv[3 * ky + kx], *v, acc);
                }
            }
            // Lanes 0 1 4 5 2 3 6 7 back to column order: 64-bit quarters 0 2 1 3.
            let acc = _mm256_castpd_ps(_mm256_permute4x64_pd::<0xD8>(_mm256_castps_pd(acc)));
            // SAFETY: output row m holds wo values; unmasked, x0 + 8 ≤ w / 2 ≤ wo.
            unsafe {
                match store {
                    None => _mm256_storeu_ps(dst.add(x0), acc),
                    Some(mask) => _mm256_maskstore_ps(dst.add(x0), mask, acc),
                }
            }
            x0 += HALF;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Planes of 1–40 rows and widths from one column to past several registers (odd and
    /// even, the main job's 35, 70, 87 and 139), through the entry point: y bit for bit the
    /// plane path's (padding rows and masked edge lanes summed as its zeros are).
    #[test]
    fn stride_2_gives_the_plane_paths_bits() {
        if !has_fma() {
            return;
        }
        for w in [
            1, 2, 3, 7, 8, 9, 15, 16, 17, 18, 31, 32, 33, 35, 70, 87, 139,
        ] {
            super::super::assert_plane_path_bits(w, 2, 200 + w as u64, forward);
        }
    }
}

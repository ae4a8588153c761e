//! Depthwise 3×3 at stride 2, forward and backward, read straight from the plane in registers,
//! any width.
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
//! bits (test `stride_2_gives_the_plane_paths_bits`).
//!
//! The backward needs no phase-split copies either. dL/dw takes the forward's tap registers
//! against each block of dL/dy (put in the same lane order), one accumulator per tap, row by
//! row and block by block as the plane path's chains run, so the lanes summed in column order
//! at the end are its bits. dL/dx goes sixteen input columns at a time: their even columns take
//! the centre taps of one block of dL/dy, their odd columns the left and right taps of that
//! block and of the block one column on; the two halves are interleaved by unpack and
//! 128-bit permutes. Each cell sums its taps from zero in (ky, kx) order, rows and columns
//! of dL/dy past the plane read as zeros, as the plane path's phase sweeps do: the same bits
//! (test `stride_2_backward_is_the_plane_paths_bits`). Planes 8 and 16 wide keep their own paths
//! ([`super::rows8`], [`super::rows16`]), small output planes of channels in multiples of eight
//! the channel blocks.

use super::stride1::inside;
use super::{Geom, HALF, LANES, has_fma, k3_backward_planes, k3_forward_planes};
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

/// Backward over all planes (as [`super::backward`]): dL/dx into `dx`, each plane's nine
/// weight gradients into `dw_planes` (overwritten); panics unless `takes(g)`.
pub(super) fn backward(
    g: &Geom,
    c: usize,
    inputs: (&[f32], &[f32], &[f32]),
    dx: &mut [f32],
    dw_planes: &mut [f32],
) {
    assert!(takes(g), "stride 2 for {g:?}");
    let (width, wo) = (g.w, g.wo);
    // SAFETY: `takes` checked AVX2 and FMA on this CPU; the driver hands each plane its h·w
    // inputs and gradients, ho·wo output gradients.
    k3_backward_planes(
        g,
        c,
        inputs,
        (dx, dw_planes),
        &|h, ho, xwd, dx, dw| unsafe { plane_backward(h, width, (ho, wo), xwd, dx, dw) },
    );
}

/// Where a block of eight outputs reads its input row: unmasked, or with the masks of the four
/// loads (columns from 2x₀ − 1, 2x₀ + 7, 2x₀, 2x₀ + 8).
#[derive(Clone, Copy)]
enum Reach {
    Inside,
    Masked([__m256i; 4]),
}

/// How the block of eight outputs from column x₀ reads its input rows (w wide), and the lane
/// mask of its outputs (wo of them) where it is not wholly inside: Inside needs columns
/// 2x₀ − 1 .. 2x₀ + 16 of the row, which also puts x₀ + 8 ≤ w/2 ≤ wo.
#[target_feature(enable = "avx2")]
fn block_reach(x0: usize, w: usize, wo: usize) -> (Reach, Option<__m256i>) {
    if x0 >= 1 && 2 * x0 + 2 * HALF <= w {
        return (Reach::Inside, None);
    }
    let c = 2 * x0 as isize;
    let m = [c - 1, c + 7, c, c + 8].map(|s| inside(s, w));
    (Reach::Masked(m), Some(inside(x0 as isize, wo)))
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
            let (reach, store) = block_reach(x0, w, wo);
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

/// Lanes 0 1 4 5 2 3 6 7 to column order and back (64-bit quarters 0 2 1 3, its own inverse).
#[target_feature(enable = "avx2")]
fn swap_quarters(v: __m256) -> __m256 {
    _mm256_castpd_ps(_mm256_permute4x64_pd::<0xD8>(_mm256_castps_pd(v)))
}

/// One plane's backward: `x` and `dx` h·w values, `dy` ho·wo, the nine taps' gradients into
/// `dw` (both overwritten).
///
/// # Safety
/// The CPU must have AVX2 and FMA; ho = ⌈h/2⌉, wo = ⌈w/2⌉.
#[target_feature(enable = "avx2,fma")]
unsafe fn plane_backward(
    h: usize,
    w: usize,
    (ho, wo): (usize, usize),
    (x, wk, dy): (&[f32], &[f32; 9], &[f32]),
    dx: &mut [f32],
    dw: &mut [f32; 9],
) {
    // Checked without wrapping: the blocks below trust these sizes.
    let hw = h.checked_mul(w).expect("plane size overflows");
    let howo = ho.checked_mul(wo).expect("plane size overflows");
    assert!(x.len() == hw && dx.len() == hw && dy.len() == howo);
    assert!(ho == h.div_ceil(2) && wo == w.div_ceil(2));
    // SAFETY: AVX2 and FMA by the contract; sizes checked above.
    unsafe {
        weight_grads(h, w, (ho, wo), x, dy, dw);
        input_grads(h, w, (ho, wo), wk, dy, dx);
    }
}

/// dL/dw of one plane: per tap, lane sums of dL/dy times the forward's tap registers over the
/// rows and blocks in the plane path's order (row by row, blocks left to right, lane l holding
/// the columns ≡ l mod 8), the lanes then summed in column order as the plane path does: its
/// bits. The lanes past the last output column multiply zeros by zeros, as its masked loads do.
///
/// # Safety
/// AVX2 and FMA; `x` holds h·w values, `dy` ho·wo, ho = ⌈h/2⌉, wo = ⌈w/2⌉.
#[target_feature(enable = "avx2,fma")]
unsafe fn weight_grads(
    h: usize,
    w: usize,
    (ho, wo): (usize, usize),
    x: &[f32],
    dy: &[f32],
    dw: &mut [f32; 9],
) {
    let mut acc = [_mm256_setzero_ps(); 9];
    let row = |r: usize| (r < h).then(|| &x[r * w..][..w]);
    for m in 0..ho {
        let rows = [row((2 * m).wrapping_sub(1)), row(2 * m), row(2 * m + 1)];
        let d = dy[m * wo..][..wo].as_ptr();
        let mut x0 = 0;
        while x0 < wo {
            let (reach, keep) = block_reach(x0, w, wo);
            // SAFETY: unmasked, x0 + 8 ≤ w / 2 ≤ wo; masked lanes are not read.
            let g = unsafe {
                match keep {
                    None => _mm256_loadu_ps(d.add(x0)),
                    Some(mask) => _mm256_maskload_ps(d.wrapping_add(x0), mask),
                }
            };
            let g = swap_quarters(g);
            // Taps of the lanes past wo read real columns (2·wo − 1 when w is even): zeroed,
            // as the plane path's masked loads are (times the zero of dL/dy, an infinite
            // input there would make NaN; finite ones change nothing).
            let keep = keep.map(|mask| swap_quarters(_mm256_castsi256_ps(mask)));
            for (ky, r) in rows.iter().enumerate() {
                // SAFETY: every row `row` gives holds w values; `reach` is Inside only where
                // columns 2x₀ − 1 .. 2x₀ + 16 lie inside it.
                let t = unsafe { taps(*r, x0, reach) };
                for (kx, v) in t.iter().enumerate() {
                    let v = keep.map_or(*v, |k| _mm256_and_ps(*v, k));
                    acc[3 * ky + kx] = _mm256_fmadd_ps(g, v, acc[3 * ky + kx]);
                }
            }
            x0 += HALF;
        }
    }
    for (t, a) in acc.iter().enumerate() {
        let mut lanes = [0.0f32; HALF];
        // SAFETY: a store of exactly HALF values into `lanes`.
        unsafe { _mm256_storeu_ps(lanes.as_mut_ptr(), swap_quarters(*a)) };
        dw[t] = lanes.iter().sum::<f32>();
    }
}

/// dL/dx of one plane, sixteen columns at a time as their even and odd halves: input cell
/// (i, j) takes the taps (ky, kx) with 2·oy + ky = i + 1 and 2·ox + kx = j + 1, summed from
/// zero in (ky, kx) order, rows and columns of dL/dy past the plane read as zeros: the sums
/// of the plane path's phase sweeps, bit for bit.
///
/// # Safety
/// AVX2 and FMA; `dx` holds h·w values, `dy` ho·wo, ho = ⌈h/2⌉, wo = ⌈w/2⌉.
#[target_feature(enable = "avx2,fma")]
unsafe fn input_grads(
    h: usize,
    w: usize,
    (ho, wo): (usize, usize),
    wk: &[f32; 9],
    dy: &[f32],
    dx: &mut [f32],
) {
    let wv: [__m256; 9] = std::array::from_fn(|t| _mm256_set1_ps(wk[t]));
    let z = _mm256_setzero_ps();
    // dL/dy row m's eight values from column c₀ and the eight from c₀ + 1; zeros past the plane.
    let drow = |m: usize, c0: usize, inner: bool| -> (__m256, __m256) {
        if m >= ho {
            return (z, z);
        }
        let p = dy[m * wo..][..wo].as_ptr();
        // SAFETY: inner, c₀ + 9 ≤ wo; masked lanes are not read (wrapping arithmetic: the
        // addresses of masked lanes are never dereferenced).
        unsafe {
            if inner {
                (_mm256_loadu_ps(p.add(c0)), _mm256_loadu_ps(p.add(c0 + 1)))
            } else {
                (
                    _mm256_maskload_ps(p.wrapping_add(c0), inside(c0 as isize, wo)),
                    _mm256_maskload_ps(p.wrapping_add(c0 + 1), inside(c0 as isize + 1, wo)),
                )
            }
        }
    };
    for i in 0..h {
        let dst = dx[i * w..][..w].as_mut_ptr();
        let mut j0 = 0;
        while j0 < w {
            let (c0, inner) = (j0 / 2, j0 + 2 * HALF + 2 <= w);
            let (even, odd) = if i % 2 == 0 {
                let (v, v1) = drow(i / 2, c0, inner);
                let e = _mm256_fmadd_ps(wv[4], v, z);
                (e, _mm256_fmadd_ps(wv[5], v, _mm256_fmadd_ps(wv[3], v1, z)))
            } else {
                // Tap rows ky = 0 (output row (i + 1)/2) before ky = 2 (row (i − 1)/2).
                let (b, b1) = drow(i.div_ceil(2), c0, inner);
                let (a, a1) = drow(i / 2, c0, inner);
                let e = _mm256_fmadd_ps(wv[7], a, _mm256_fmadd_ps(wv[1], b, z));
                let o = _mm256_fmadd_ps(wv[2], b, _mm256_fmadd_ps(wv[0], b1, z));
                (e, _mm256_fmadd_ps(wv[8], a, _mm256_fmadd_ps(wv[6], a1, o)))
            };
            // Within each 128-bit lane [e0 o0 e1 o1] and [e2 o2 e3 o3]: columns j₀ .. j₀ + 8
            // are the low lanes of both, j₀ + 8 .. j₀ + 16 the high lanes.
            let (lo, hi) = (_mm256_unpacklo_ps(even, odd), _mm256_unpackhi_ps(even, odd));
            let (left, right) = (
                _mm256_permute2f128_ps::<0x20>(lo, hi),
                _mm256_permute2f128_ps::<0x31>(lo, hi),
            );
            // SAFETY: inner, j₀ + 16 ≤ w; otherwise the masks keep the stores inside the row.
            unsafe {
                if inner {
                    _mm256_storeu_ps(dst.add(j0), left);
                    _mm256_storeu_ps(dst.add(j0 + HALF), right);
                } else {
                    let j = j0 as isize;
                    _mm256_maskstore_ps(dst.wrapping_add(j0), inside(j, w), left);
                    _mm256_maskstore_ps(dst.wrapping_add(j0 + HALF), inside(j + 8, w), right);
                }
            }
            j0 += LANES;
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

    /// The backward through the entry point, the same widths and those whose last block holds
    /// seven outputs, 1–40 rows, finite values and then infinities among them: dL/dx and dL/dw
    /// bit for bit the plane path's (padding taps and the lanes past the last output column
    /// summed as its zeros are).
    #[test]
    fn stride_2_backward_is_the_plane_paths_bits() {
        if !has_fma() {
            return;
        }
        for w in [
            1, 2, 3, 7, 8, 9, 13, 14, 15, 16, 17, 18, 29, 30, 31, 32, 33, 35, 70, 87, 139,
        ] {
            super::super::assert_plane_path_backward((w, 2), 300 + w as u64, true, backward);
        }
    }
}

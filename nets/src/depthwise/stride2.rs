//! Depthwise 3×3 and 5×5 at stride 2, forward (both) and backward (3×3), read straight from
//! the plane in registers, any width.
//!
//! The plane path splits every plane's columns by parity into a padded scratch before its
//! sweep. Here eight outputs of a row take their k taps from registers: pairs of loads of
//! sixteen columns from 2x₀ − 2, 2x₀ (and 2x₀ + 2 for k = 5), each split into its even and odd
//! columns by one in-lane shuffle — tap kx of output j is column 2j + kx − k/2. The shuffles
//! leave the eight outputs in the lane order 0 1 4 5 2 3 6 7 in every tap alike, so the
//! multiply–adds run in that order and one 64-bit permute puts the sum back in column order
//! before its store. The forward goes four output rows at a time, two blocks of eight
//! outputs wide where the row allows: each input row's taps, kx by kx, go into every output
//! row they reach, eight independent sums in flight (one block's k² multiply–adds as a single
//! chain waited on their latency). Rows above and below the plane are zero taps, and the
//! blocks at the left and right edges load and store with lane masks (masked lanes read as
//! zero). Every output sums its k² taps from zero in (ky, kx) order, padding included, as the
//! plane path does, so y is the plane path's bits (test `stride_2_gives_the_plane_paths_bits`).
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
use super::{Geom, HALF, LANES, forward_planes, has_fma, k3_backward_planes};
use std::arch::x86_64::*;

/// Whether a layer with this geometry goes through this path's forward (k = 3 or 5).
pub(super) fn takes(g: &Geom) -> bool {
    // Column indices (below w + 2·HALF) fit the lane masks' 32-bit integers.
    (g.k == 3 || g.k == 5)
        && g.s == 2
        && g.h > 0
        && g.w > 0
        && g.ho == g.h.div_ceil(2)
        && g.wo == g.w.div_ceil(2)
        && g.w < (i32::MAX as usize) / 2 - 4 * HALF
        && has_fma()
}

/// Whether a layer with this geometry goes through this path's backward (k = 3 only).
pub(super) fn takes_backward(g: &Geom) -> bool {
    g.k == 3 && takes(g)
}

/// Forward over all planes (as [`super::forward`]); panics unless `takes(g)`.
pub(super) fn forward(g: &Geom, c: usize, x: &[f32], w: &[f32], y: &mut [f32]) {
    // The planes below run AVX2 and FMA code on that check alone.
    assert!(takes(g), "stride 2 for {g:?}");
    let (width, wo) = (g.w, g.wo);
    // SAFETY: `takes` checked AVX2 and FMA on this CPU; the driver hands each plane its h·w
    // inputs and ho·wo outputs.
    if g.k == 5 {
        forward_planes(g, c, (x, w), y, |h, ho, x, wk, out| unsafe {
            plane::<5, 25>(h, width, (ho, wo), x, wk, out)
        });
    } else {
        forward_planes(g, c, (x, w), y, |h, ho, x, wk, out| unsafe {
            plane::<3, 9>(h, width, (ho, wo), x, wk, out)
        });
    }
}

/// Backward over all planes (as [`super::backward`]): dL/dx into `dx`, each plane's nine
/// weight gradients into `dw_planes` (overwritten); panics unless `takes_backward(g)`.
pub(super) fn backward(
    g: &Geom,
    c: usize,
    inputs: (&[f32], &[f32], &[f32]),
    dx: &mut [f32],
    dw_planes: &mut [f32],
) {
    assert!(takes_backward(g), "stride 2 backward for {g:?}");
    let (width, wo) = (g.w, g.wo);
    // SAFETY: `takes_backward` checked AVX2 and FMA on this CPU; the driver hands each plane
    // its h·w inputs and gradients, ho·wo output gradients.
    k3_backward_planes(
        g,
        c,
        inputs,
        (dx, dw_planes),
        &|h, ho, xwd, dx, dw| unsafe { plane_backward(h, width, (ho, wo), xwd, dx, dw) },
    );
}

/// Where a block of eight outputs reads its input row: unmasked, or with the masks of its
/// loads (pairs of eight columns from 2x₀ − 2, 2x₀ and, for k = 5, 2x₀ + 2; first and second
/// of each pair).
#[derive(Clone, Copy)]
enum Reach {
    Inside,
    Masked([__m256i; 6]),
}

/// Pairs of eight-column loads a block of eight outputs of a k×k kernel reads per input row.
const fn pairs(k: usize) -> usize {
    k / 2 + 1
}

/// How the block of eight outputs from column x₀ of a k×k kernel reads its input rows (w
/// wide), and the lane mask of its outputs (wo of them) where it is not wholly inside: Inside
/// needs columns 2x₀ − 2 .. 2x₀ + 2·pairs(k) + 12 of the row, which also puts x₀ + 8 ≤ w/2 ≤ wo.
#[target_feature(enable = "avx2")]
fn block_reach<const K: usize>(x0: usize, w: usize, wo: usize) -> (Reach, Option<__m256i>) {
    if x0 >= 1 && 2 * x0 + 2 * pairs(K) + 12 <= w {
        return (Reach::Inside, None);
    }
    let c = 2 * x0 as isize;
    let m = std::array::from_fn(|i| {
        if i < 2 * pairs(K) {
            inside(c - 2 + 2 * (i / 2) as isize + 8 * (i % 2) as isize, w)
        } else {
            _mm256_setzero_si256()
        }
    });
    (Reach::Masked(m), Some(inside(x0 as isize, wo)))
}

/// Pair `i` of input row `row`'s loads for the eight outputs from `x0`: columns 2x₀ − 2 + 2i
/// .. + 16 (zeros for the padding, None); its even and odd halves are the columns 2j − 2 + 2i
/// and 2j − 1 + 2i of the eight outputs j, in the lane order 0 1 4 5 2 3 6 7.
///
/// # Safety
/// AVX2; `row` holds at least the columns `reach` lets through (all of 2x₀ − 2 + 2i ..
/// 2x₀ + 2i + 14 when `Inside`).
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn pair_loads(row: Option<&[f32]>, x0: usize, i: usize, reach: Reach) -> (__m256, __m256) {
    let Some(row) = row else {
        return (_mm256_setzero_ps(), _mm256_setzero_ps());
    };
    let p = row.as_ptr();
    let at = (2 * x0 + 2 * i).wrapping_sub(2);
    // SAFETY: inside the row by the contract, or masked (masked lanes are neither read nor
    // faulted on; wrapping arithmetic: addresses before or past the row are never
    // dereferenced).
    unsafe {
        match reach {
            Reach::Inside => (_mm256_loadu_ps(p.add(at)), _mm256_loadu_ps(p.add(at + 8))),
            Reach::Masked(m) => (
                _mm256_maskload_ps(p.wrapping_add(at), m[2 * i]),
                _mm256_maskload_ps(p.wrapping_add(at.wrapping_add(8)), m[2 * i + 1]),
            ),
        }
    }
}

/// Input row `row` (None: the zero padding) as the three taps of the 3×3 kernel for the eight
/// outputs from `x0` (columns 2j − 1, 2j, 2j + 1 of output j), in the lane order 0 1 4 5 2 3 6 7.
///
/// # Safety
/// AVX2 and FMA; as [`pair_loads`] for pairs 0 and 1.
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn taps3(row: Option<&[f32]>, x0: usize, reach: Reach) -> [__m256; 3] {
    // SAFETY: this function's contract.
    let ((a0, b0), (a1, b1)) =
        unsafe { (pair_loads(row, x0, 0, reach), pair_loads(row, x0, 1, reach)) };
    [
        _mm256_shuffle_ps::<0xDD>(a0, b0),
        _mm256_shuffle_ps::<0x88>(a1, b1),
        _mm256_shuffle_ps::<0xDD>(a1, b1),
    ]
}

/// One plane of a k×k kernel (KK = k² taps): `x` h·w values, `out` ho·wo.
///
/// # Safety
/// The CPU must have AVX2 and FMA; ho = ⌈h/2⌉, wo = ⌈w/2⌉, k = 3 or 5.
#[target_feature(enable = "avx2,fma")]
unsafe fn plane<const K: usize, const KK: usize>(
    h: usize,
    w: usize,
    (ho, wo): (usize, usize),
    x: &[f32],
    wk: &[f32; KK],
    out: &mut [f32],
) {
    // Checked without wrapping: the blocks below trust these sizes.
    let hw = h.checked_mul(w).expect("plane size overflows");
    let howo = ho.checked_mul(wo).expect("plane size overflows");
    assert!(x.len() == hw && out.len() == howo && ho == h.div_ceil(2) && wo == w.div_ceil(2));
    assert!(K * K == KK && (K == 3 || K == 5));
    let wv: [__m256; KK] = std::array::from_fn(|t| _mm256_set1_ps(wk[t]));
    // Four output rows at a time, left to right: each input row's taps serve every output
    // row they reach (two or three of the four), and the sums of four rows by two blocks are
    // independent chains. One row at a time, a block's k² fused multiply–adds formed one
    // chain and waited on its latency (the 5×5 kernel ran 40 % slower than the plane path
    // that way).
    let mut m = 0;
    // SAFETY (all three): rows m .. m + R ≤ ho; the rest is this function's contract.
    while m + 4 <= ho {
        unsafe { output_rows::<K, KK, 4>(m, h, w, wo, x, &wv, out) };
        m += 4;
    }
    while m + 2 <= ho {
        unsafe { output_rows::<K, KK, 2>(m, h, w, wo, x, &wv, out) };
        m += 2;
    }
    if m < ho {
        unsafe { output_rows::<K, KK, 1>(m, h, w, wo, x, &wv, out) };
    }
}

/// Output rows m .. m + R of one plane (see [`plane`]): block by block, input rows 2m − k/2 ..
/// 2(m + R − 1) + k/2 read top to bottom, so each output still sums its taps from zero in
/// (ky, kx) order.
///
/// # Safety
/// AVX2 and FMA; m + R ≤ ho = ⌈h/2⌉, wo = ⌈w/2⌉, `x` holds h·w values and `out` ho·wo.
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn output_rows<const K: usize, const KK: usize, const R: usize>(
    m: usize,
    h: usize,
    w: usize,
    wo: usize,
    x: &[f32],
    wv: &[__m256; KK],
    out: &mut [f32],
) {
    // Input rows 2m − k/2 + i (at most 2·4 + 5 − 2 of them), sliced once for all blocks;
    // rows above or below the plane (those above wrap past h) read as None.
    let rows: [Option<&[f32]>; 11] = std::array::from_fn(|i| {
        let r = (2 * m + i).wrapping_sub(K / 2);
        (i < 2 * R + K - 2 && r < h).then(|| &x[r * w..][..w])
    });
    let dst = out[m * wo..][..R * wo].as_mut_ptr();
    let rows = &rows[..2 * R + K - 2];
    let mut x0 = 0;
    while x0 < wo {
        // Interior blocks apart, so that their loads and stores compile without masks, and
        // two at a time where they can: R·V independent sums in flight.
        let interior = |x0: usize| x0 >= 1 && 2 * x0 + 2 * pairs(K) + 12 <= w;
        // SAFETY: x0 + 8(V − 1) < wo; the rest is this function's contract.
        unsafe {
            let inner = interior(x0) && interior(x0 + HALF);
            // Edge blocks in pairs too for the 5×5 kernel (7 % faster at 96×44×70) but not
            // for the 3×3 one (8 % slower; one thread, `dw_prof`). So a single unmasked block
            // is the 3×3 kernel's only: an interior 5×5 block always has a partner.
            if x0 + HALF < wo && (inner || K == 5) {
                if inner {
                    block::<K, KK, R, 2, false>(rows, x0, (w, wo), wv, dst);
                } else {
                    block::<K, KK, R, 2, true>(rows, x0, (w, wo), wv, dst);
                }
                x0 += 2 * HALF;
            } else {
                if interior(x0) {
                    block::<K, KK, R, 1, false>(rows, x0, (w, wo), wv, dst);
                } else {
                    block::<K, KK, R, 1, true>(rows, x0, (w, wo), wv, dst);
                }
                x0 += HALF;
            }
        }
    }
}

/// V blocks of eight outputs from column x₀ of output rows m .. m + R (`dst` from row m's
/// start, rows wo apart), from input rows 2m − k/2 .. (`rows`, 2R + k − 2 of them, None the
/// padding); `MASKED`: some block reaches past a row's edge (see [`block_reach`]). Each input
/// row's taps go, kx by kx, into every output row they reach, so each output sums its taps
/// from zero in (ky, kx) order.
///
/// # Safety
/// AVX2 and FMA; every row in `rows` holds w values, `dst` R·wo; x0 + 8(V − 1) < wo; unless
/// `MASKED`, x₀ ≥ 1 and 2(x₀ + 8(V − 1)) + 2·pairs(k) + 12 ≤ w.
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn block<
    const K: usize,
    const KK: usize,
    const R: usize,
    const V: usize,
    const MASKED: bool,
>(
    rows: &[Option<&[f32]>],
    x0: usize,
    (w, wo): (usize, usize),
    wv: &[__m256; KK],
    dst: *mut f32,
) {
    let reach: [(Reach, Option<__m256i>); V] = std::array::from_fn(|v| {
        if MASKED {
            block_reach::<K>(x0 + v * HALF, w, wo)
        } else {
            (Reach::Inside, None)
        }
    });
    let mut acc = [[_mm256_setzero_ps(); V]; R];
    for (i, row) in rows.iter().enumerate() {
        for pair in 0..pairs(K) {
            // SAFETY: every row in `rows` holds w values; `reach` is Inside only where the
            // columns `pair_loads` reads lie inside it.
            let ab: [(__m256, __m256); V] = std::array::from_fn(|v| unsafe {
                pair_loads(*row, x0 + v * HALF, pair, reach[v].0)
            });
            for odd in [false, true] {
                // The even (odd) half is column 2j − 2 + d of output j, d = 2·pair (+ 1): tap
                // kx = d + k/2 − 2 where that is one of the kernel's.
                let d = 2 * pair + odd as usize;
                if d + K / 2 < 2 || d + K / 2 - 2 >= K {
                    continue;
                }
                let kx = d + K / 2 - 2;
                let t: [__m256; V] = std::array::from_fn(|v| {
                    let (a, b) = ab[v];
                    if odd {
                        _mm256_shuffle_ps::<0xDD>(a, b)
                    } else {
                        _mm256_shuffle_ps::<0x88>(a, b)
                    }
                });
                for (r, acc) in acc.iter_mut().enumerate() {
                    // Output row m + r takes input row 2m − k/2 + i as its tap row ky = i − 2r.
                    if i >= 2 * r && i - 2 * r < K {
                        let wt = wv[K * (i - 2 * r) + kx];
                        for (a, t) in acc.iter_mut().zip(&t) {
                            *a = _mm256_fmadd_ps(wt, *t, *a);
                        }
                    }
                }
            }
        }
    }
    for (r, acc) in acc.iter().enumerate() {
        for (v, a) in acc.iter().enumerate() {
            // Lanes 0 1 4 5 2 3 6 7 back to column order.
            let a = swap_quarters(*a);
            // SAFETY: output row m + r holds wo values; unmasked, x0 + 8V ≤ w / 2 ≤ wo;
            // masked, no lane past the row is written.
            unsafe {
                let d = dst.add(r * wo + x0 + v * HALF);
                match reach[v].1 {
                    None => _mm256_storeu_ps(d, a),
                    Some(mask) => _mm256_maskstore_ps(d, mask, a),
                }
            }
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
            let (reach, keep) = block_reach::<3>(x0, w, wo);
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
                // the columns `taps` reads lie inside it.
                let t = unsafe { taps3(*r, x0, reach) };
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
            for k in [3, 5] {
                super::super::assert_plane_path_bits((w, k, 2), 200 + w as u64, forward);
            }
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

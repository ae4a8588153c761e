//! Depthwise 3×3 and 5×5 at stride 2, forward and backward, read straight from the plane in
//! registers, any width.
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
//! chain waited on their latency). Rows above and below the plane are zero taps. The first
//! block of a row (with its neighbour where that is interior) loads columns 0 .. 16 and
//! shifts them up two lanes for the columns −2 .. 14 its first pair reads, the two before the
//! row as zeros (widths from 16 for 3×3, 18 for 5×5). Other blocks at the edges load and store
//! with lane masks (masked lanes read as zero), except that where the blocks ending at the
//! row's end read no column past it (3×3, even widths from 22) the last one or two start
//! there, over some outputs again; on odd widths (3×3, from 21) they read one column past it,
//! which the last block loads one column early and shifts in as zero. On rows of 8n + 1 and
//! 8n + 2 outputs (3×3, widths 16n + 1 .. 16n + 4) the blocks stop at 8n and the last two
//! outputs of all four rows go in one register ([`tail_pairs`]). Every
//! output sums its k² taps from zero in (ky, kx) order, padding included, as the plane path
//! does, so y is the plane path's bits wherever its block starts (test `stride_2_gives_the_plane_paths_bits`).
//!
//! The backward needs no phase-split copies either. The 3×3 kernel's dL/dw takes the forward's
//! tap registers against each block of dL/dy (put in the same lane order), one accumulator per
//! tap, row by row and block by block as the plane path's chains run, so the lanes summed in
//! column order at the end are its bits; output row m's dL/dw terms are followed by dL/dx's
//! input rows 2m and 2m + 1 (2m alone at the end of an odd height), one pass over the plane
//! ([`grads`]). The 5×5 kernel's dL/dw is the plane path's (read from the plane this way it
//! ran no faster). dL/dx goes two input rows and two blocks of sixteen columns at a time: a
//! block's even columns take the taps kx ≡ k/2 (mod 2), its odd columns the others, each from
//! a load of eight dL/dy columns offset by −1, 0 or +1; the two halves are interleaved by
//! unpack and 128-bit permutes; on odd widths (3×3, from 17) the last block starts at the odd
//! column w − 16 (over columns already written), its halves' parities swapped, instead of
//! masking the edge. Each cell sums its taps from zero in (ky, kx) order, rows and columns of
//! dL/dy past the plane read as zeros, as the plane path's phase sweeps do, wherever its block
//! starts: the same bits (test `stride_2_backward_is_the_plane_paths_bits`). Planes 8 and 16
//! wide keep their own paths ([`super::rows8`], [`super::rows16`]), small output planes of
//! channels in multiples of eight the channel blocks, except the rows this path covers faster
//! ([`preferred`]).

use super::stride1::inside;
use super::{
    Geom, HALF, LANES, PREFETCH_WIDTH, Scratch, backward_planes, forward_planes, has_fma,
    plane_weight_grad, prefetch,
};
use std::arch::x86_64::*;
use std::mem::MaybeUninit;

/// Whether a layer with this geometry goes through this path, forward and backward (k = 3 or
/// 5).
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

/// Whether a layer the channel blocks ([`super::channels`]) could take runs faster here: the
/// 3×3 forward on output rows of 13 or more (two or three blocks of eight, their edges
/// unmasked from widths 16), the backward on rows of whole blocks (16, 24, 32 outputs) and the
/// 3×3 backward on odd widths from 35 (rows of 18 or more; its dL/dx's last block unmasked).
/// Rows of 10 too: one block and the last pair ([`pairs_tail`]; 192×22×20 two threads 196
/// → 143 µs), but not rows of 9 (336×11×18: 144 µs through the channel blocks, 150 here).
/// The channel blocks transpose four input pixels per output at stride 2; on narrower rows,
/// for the other backward rows and for the 5×5 forward they are still the faster (`dw_prof`,
/// docs/bench/nets.md).
pub(super) fn preferred(g: &Geom, backward: bool) -> bool {
    takes(g)
        && if backward {
            g.wo.is_multiple_of(HALF) && g.wo >= 2 * HALF
                || g.k == 3 && !g.w.is_multiple_of(2) && g.wo > 2 * HALF + 1
        } else {
            g.k == 3 && (g.wo >= 13 || g.wo == HALF + 2)
        }
}

/// Forward over all planes (as [`super::forward`]); panics unless `takes(g)`.
pub(super) fn forward(g: &Geom, c: usize, x: &[f32], w: &[f32], y: &mut [MaybeUninit<f32>]) {
    // The planes below run AVX2 and FMA code on that check alone.
    assert!(takes(g), "stride 2 for {g:?}");
    let (width, wo) = (g.w, g.wo);
    // The padding rows' one row of zeros, read by every plane of the 3×3 kernel.
    let zeros = vec![0.0f32; g.w];
    // SAFETY: `takes` checked AVX2 and FMA on this CPU; the driver hands each plane its h·w
    // inputs and ho·wo outputs.
    if g.k == 5 {
        forward_planes(g, c, (x, w), y, |h, ho, x, wk, out| unsafe {
            plane::<5, 25>(h, width, (ho, wo), (x, &zeros), wk, out)
        });
    } else {
        forward_planes(g, c, (x, w), y, |h, ho, x, wk, out| unsafe {
            plane::<3, 9>(h, width, (ho, wo), (x, &zeros), wk, out)
        });
    }
}

/// Backward over all planes (as [`super::backward`]): dL/dx into `dx`, each plane's k²
/// weight gradients into `dw_planes` (overwritten); panics unless `takes(g)`.
pub(super) fn backward(
    g: &Geom,
    c: usize,
    inputs: (&[f32], &[f32], &[f32]),
    dx: &mut [MaybeUninit<f32>],
    dw_planes: &mut [f32],
) {
    assert!(takes(g), "stride 2 backward for {g:?}");
    let (width, wo) = (g.w, g.wo);
    // SAFETY (both): `takes` checked AVX2 and FMA on this CPU; the driver hands each plane its
    // h·w inputs and gradients, ho·wo output gradients.
    if g.k == 5 {
        backward_planes::<25>(
            g,
            c,
            inputs,
            (dx, dw_planes),
            &|h, ho, xwd, dx, dw, sc| unsafe { plane_backward5(g, (h, ho), xwd, (dx, dw), sc) },
        );
    } else {
        backward_planes::<9>(
            g,
            c,
            inputs,
            (dx, dw_planes),
            &|h, ho, xwd, dx, dw, _| unsafe { plane_backward(h, width, (ho, wo), xwd, dx, dw) },
        );
    }
}

/// Input rows ahead of a group of four output rows whose new input rows the forward
/// prefetches on rows of at least [`PREFETCH_WIDTH`]: four groups. On 48×87×139 (3×3, batch
/// 16, two threads) the forward took 2.76–2.87 ms without, 2.44–2.50 ms with two groups into
/// L1 and 1.33–1.44 ms with four into L2.
const AHEAD: usize = 32;
/// Input rows ahead of an output row whose two new input rows dL/dw prefetches on rows of at
/// least [`PREFETCH_WIDTH`]: eight output rows. On 48×87×139 the 3×3 backward (then two
/// passes, dL/dw before dL/dx) took 4.38–4.61 ms without, 3.29–3.48 ms with.
const AHEAD_DW: usize = 16;

/// Where a block of eight outputs reads its input row: unmasked, or with the masks of its
/// loads (pairs of eight columns from 2x₀ − 2, 2x₀ and, for k = 5, 2x₀ + 2; first and second
/// of each pair).
#[derive(Clone, Copy)]
enum Reach {
    Inside,
    /// The first block of a row (x₀ = 0) whose columns from 0 are inside it: the two columns
    /// before the row, which only the first pair reads, are lanes shifted in as zeros.
    Left,
    /// The last block of a row of odd width w of the 3×3 kernel, at x₀ = wo − 8 ≥ 1: its one
    /// column past the row (w, the last its second pair reads) is a lane shifted in as zero.
    Right,
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

/// Whether the first block of a row (x₀ = 0) of a k×k kernel reads its input row as
/// [`Reach::Left`]: columns 0 .. 2·pairs(k) + 12 inside the row (w wide), which also puts its
/// eight outputs inside theirs.
const fn left_inside<const K: usize>(w: usize) -> bool {
    2 * pairs(K) + 12 <= w
}

/// [`block`]'s `EDGE`: every block reads its rows unmasked ([`Reach::Inside`]).
const INSIDE: u8 = 0;
/// [`block`]'s `EDGE`: the first block at x₀ = 0 as [`Reach::Left`], any other inside.
const LEFT: u8 = 1;
/// [`block`]'s `EDGE`: each block as [`block_reach`] finds it, lane masks where it reaches
/// past a row.
const MASKS: u8 = 2;
/// [`block`]'s `EDGE` (3×3 only): the last block as [`Reach::Right`], any other inside.
const RIGHT: u8 = 3;

/// `body` for i = 0, 1, .. n − 1 (n ≤ 11) written out, i a literal in each: the row loops of
/// [`block`] with a constant trip count were still left rolled for some (R, V, EDGE), their
/// taps' rows then chosen by branches and their weights indexed at run time.
macro_rules! rows_loop {
    ($unroll:expr, $n:expr, |$i:ident| $body:block) => {
        if $unroll {
            debug_assert!($n <= 11, "rows_loop! writes out 11 rows");
            rows_loop!(@ $n, $i, $body, 0 1 2 3 4 5 6 7 8 9 10)
        } else {
            for $i in 0..$n $body
        }
    };
    (@ $n:expr, $i:ident, $body:block, $($k:literal)*) => {{
        $({
            let $i: usize = $k;
            if $i < $n $body
        })*
    }};
}

/// Pair `i` of input row `row`'s loads for the eight outputs from `x0`: columns 2x₀ − 2 + 2i
/// .. + 16 (zeros for the padding, None); its even and odd halves are the columns 2j − 2 + 2i
/// and 2j − 1 + 2i of the eight outputs j, in the lane order 0 1 4 5 2 3 6 7.
///
/// # Safety
/// AVX2; `row` holds at least the columns `reach` lets through: all of 2x₀ − 2 + 2i ..
/// 2x₀ + 2i + 14 when `Inside`; when `Left` (x₀ = 0) those for i ≥ 1 and 0 .. 16 for i = 0;
/// when `Right` (3×3 only, i ≤ 1: pair 1 is the last), 2x₀ − 2 .. w with 2x₀ + 16 = w + 1.
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn pair_loads(row: Option<&[f32]>, x0: usize, i: usize, reach: Reach) -> (__m256, __m256) {
    let Some(row) = row else {
        return (_mm256_setzero_ps(), _mm256_setzero_ps());
    };
    let p = row.as_ptr();
    let at = (2 * x0 + 2 * i).wrapping_sub(2);
    // SAFETY: inside the row by the contract (Inside, Left and Right read only columns of the
    // row), or masked (masked lanes are neither read nor faulted on; wrapping arithmetic:
    // addresses before or past the row are never dereferenced).
    unsafe {
        match reach {
            Reach::Inside => (_mm256_loadu_ps(p.add(at)), _mm256_loadu_ps(p.add(at + 8))),
            // Columns −2 .. 14 from the loads of 0 .. 16, moved up two lanes: a byte shift
            // within 128-bit lanes of (upper, lower) pairs of halves put side by side.
            Reach::Left if i == 0 => {
                let (u0, u1) = (_mm256_loadu_ps(p), _mm256_loadu_ps(p.add(8)));
                let lo = _mm256_permute2f128_ps::<0x08>(u0, u0);
                let mid = _mm256_permute2f128_ps::<0x21>(u0, u1);
                let shift = |hi: __m256, lo: __m256| {
                    _mm256_castsi256_ps(_mm256_alignr_epi8::<8>(
                        _mm256_castps_si256(hi),
                        _mm256_castps_si256(lo),
                    ))
                };
                (shift(u0, lo), shift(u1, mid))
            }
            // Columns 2x₀ + 8 .. 2x₀ + 16 = w + 1 from the load of w − 8 .. w, moved down one
            // lane: the same byte shift with the upper half's lanes above it zero.
            Reach::Right if i == 1 => {
                let v = _mm256_loadu_ps(p.add(at + 7));
                let hi = _mm256_permute2f128_ps::<0x81>(v, v);
                let b = _mm256_castsi256_ps(_mm256_alignr_epi8::<4>(
                    _mm256_castps_si256(hi),
                    _mm256_castps_si256(v),
                ));
                (_mm256_loadu_ps(p.add(at)), b)
            }
            Reach::Left | Reach::Right => {
                (_mm256_loadu_ps(p.add(at)), _mm256_loadu_ps(p.add(at + 8)))
            }
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

/// One plane of a k×k kernel (KK = k² taps): `x` h·w values, `zeros` a row of w zeros (the
/// padding rows), `out` ho·wo.
///
/// # Safety
/// The CPU must have AVX2 and FMA; ho = ⌈h/2⌉, wo = ⌈w/2⌉, k = 3 or 5.
#[target_feature(enable = "avx2,fma")]
unsafe fn plane<const K: usize, const KK: usize>(
    h: usize,
    w: usize,
    (ho, wo): (usize, usize),
    (x, zeros): (&[f32], &[f32]),
    wk: &[f32; KK],
    out: &mut [MaybeUninit<f32>],
) {
    // Checked without wrapping: the blocks below trust these sizes.
    let hw = h.checked_mul(w).expect("plane size overflows");
    let howo = ho.checked_mul(wo).expect("plane size overflows");
    assert!(x.len() == hw && out.len() == howo && ho == h.div_ceil(2) && wo == w.div_ceil(2));
    assert!(zeros.len() == w);
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
        unsafe { output_rows::<K, KK, 4>(m, h, w, wo, (x, zeros), &wv, out) };
        m += 4;
    }
    while m + 2 <= ho {
        unsafe { output_rows::<K, KK, 2>(m, h, w, wo, (x, zeros), &wv, out) };
        m += 2;
    }
    if m < ho {
        unsafe { output_rows::<K, KK, 1>(m, h, w, wo, (x, zeros), &wv, out) };
    }
}

/// Output rows m .. m + R of one plane (see [`plane`]): block by block, input rows 2m − k/2 ..
/// 2(m + R − 1) + k/2 read top to bottom, so each output still sums its taps from zero in
/// (ky, kx) order.
///
/// # Safety
/// AVX2 and FMA; m + R ≤ ho = ⌈h/2⌉, wo = ⌈w/2⌉, `x` holds h·w values, `zeros` w and `out`
/// ho·wo.
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn output_rows<const K: usize, const KK: usize, const R: usize>(
    m: usize,
    h: usize,
    w: usize,
    wo: usize,
    (x, zeros): (&[f32], &[f32]),
    wv: &[__m256; KK],
    out: &mut [MaybeUninit<f32>],
) {
    // Input rows 2m − k/2 + i (at most 2·4 + 5 − 2 of them), sliced once for all blocks;
    // rows above or below the plane (those above wrap past h) are padding. The 3×3 kernel
    // reads them from the row of zeros, so that its loads have no branches around them:
    // with them, its unrolled block issued all its rows' loads first and spilled them to
    // the stack (41 % of its forward's samples on stack moves); one thread 1.20–1.25 →
    // 0.90–1.09 ms on 96×44×70. The 5×5 kernel skips them (None) as before: read from the
    // row of zeros it ran 10 % slower.
    let rows: [Option<&[f32]>; 11] = std::array::from_fn(|i| {
        let r = (2 * m + i).wrapping_sub(K / 2);
        if i < 2 * R + K - 2 && r < h {
            Some(&x[r * w..][..w])
        } else {
            (K == 3).then_some(zeros)
        }
    });
    let dst = out[m * wo..][..R * wo].as_mut_ptr().cast::<f32>();
    // Blocks of eight up to `end`, the last two outputs of rows 8n + 1 or 8n + 2 wide in one
    // register for all R rows.
    let tail = pairs_tail(K, wo);
    let end = if tail { wo - wo % HALF } else { wo };
    // The eight input rows that the group whose first output row is m + AHEAD / 2 reads and
    // no group before it does (rows 2m + AHEAD + k/2 − 1 ..): prefetched on wide rows, the
    // columns of this step's one or two blocks.
    let ahead = x.as_ptr().wrapping_add((2 * m + AHEAD + K / 2 - 1) * w);
    let wide = R == 4 && w >= PREFETCH_WIDTH;
    let mut x0 = 0;
    while x0 < end {
        if wide {
            for j in 0..8 {
                prefetch(ahead.wrapping_add(j * w + 2 * x0));
                prefetch(ahead.wrapping_add(j * w + 2 * x0 + 2 * HALF));
            }
        }
        // Interior blocks apart, so that their loads and stores compile without masks, and
        // two at a time where they can: R·V independent sums in flight.
        let interior = |x0: usize| x0 >= 1 && 2 * x0 + 2 * pairs(K) + 12 <= w;
        // SAFETY: x0 + 8(V − 1) < wo; the rest is this function's contract.
        unsafe {
            let inner = interior(x0) && interior(x0 + HALF);
            // Masked edge blocks in pairs too for the 5×5 kernel (7 % faster at 96×44×70) but
            // not for the 3×3 one (8 % slower; one thread, `dw_prof`). So a single unmasked
            // INSIDE block is the 3×3 kernel's only: an interior 5×5 block always has a
            // partner. The first block unmasked (LEFT) goes with its neighbour where that is
            // interior; on narrower rows the 3×3 one runs alone, the 5×5 one stays a masked
            // pair as before.
            // Where the blocks ending at the row's end are unmasked (3×3, even widths from 22;
            // rows of 8n + 1 and 8n + 2 outputs end in `tail_pairs` instead),
            // the last one or two run there, over some outputs again: each output's sum is the
            // same wherever its block starts, so those are rewritten with their own bits, and
            // the right edge needs no masked loads. On 96×44×70 a single block and a masked
            // one became one unmasked pair: two threads 429–446 → 388–398 µs (`dw_prof`).
            // Such a start lies before x0 and its block ends at `end` (the bound above holds).
            let last = |blocks: usize| {
                end.checked_sub(blocks * HALF)
                    .filter(|&e| e < x0 && (0..blocks).all(|v| interior(e + v * HALF)))
            };
            // On odd widths the blocks ending at the row's end read one column past it, which
            // the last one shifts in as zero instead (3×3).
            let right = |blocks: usize| {
                wo.checked_sub(blocks * HALF).filter(|&e| {
                    K == 3
                        && !tail
                        && !w.is_multiple_of(2)
                        && e >= 1
                        && e <= x0
                        && (0..blocks - 1).all(|v| interior(e + v * HALF))
                })
            };
            if x0 == 0 && left_inside::<K>(w) && (K == 3 || interior(HALF)) {
                if interior(HALF) {
                    block::<K, KK, R, 2, LEFT>(&rows, 0, (w, wo), wv, dst);
                    x0 = 2 * HALF;
                } else {
                    block::<K, KK, R, 1, LEFT>(&rows, 0, (w, wo), wv, dst);
                    x0 = HALF;
                }
            } else if let (false, true, Some(e)) = (inner, x0 + HALF < end, last(2)) {
                block::<K, KK, R, 2, INSIDE>(&rows, e, (w, wo), wv, dst);
                x0 = wo;
            } else if let (false, Some(e)) = (interior(x0), last(1)) {
                block::<K, KK, R, 1, INSIDE>(&rows, e, (w, wo), wv, dst);
                x0 = wo;
            } else if let (false, true, Some(e)) = (inner, x0 + HALF < end, right(2)) {
                block::<K, KK, R, 2, RIGHT>(&rows, e, (w, wo), wv, dst);
                x0 = wo;
            } else if let (false, Some(e)) = (interior(x0), right(1)) {
                block::<K, KK, R, 1, RIGHT>(&rows, e, (w, wo), wv, dst);
                x0 = wo;
            } else if x0 + HALF < end && (inner || K == 5) {
                if inner {
                    block::<K, KK, R, 2, INSIDE>(&rows, x0, (w, wo), wv, dst);
                } else {
                    block::<K, KK, R, 2, MASKS>(&rows, x0, (w, wo), wv, dst);
                }
                x0 += 2 * HALF;
            } else {
                if interior(x0) {
                    block::<K, KK, R, 1, INSIDE>(&rows, x0, (w, wo), wv, dst);
                } else {
                    block::<K, KK, R, 1, MASKS>(&rows, x0, (w, wo), wv, dst);
                }
                x0 += HALF;
            }
        }
    }
    if tail {
        let wv3: &[__m256; 9] = wv[..].try_into().expect("3×3 taps");
        // SAFETY: `pairs_tail(K, wo)`, so k = 3 and the rows are the 3×3 kernel's; the rest is
        // this function's contract.
        unsafe { tail_pairs::<R>(&rows, (w, wo), wv3, dst) };
    }
}

/// V blocks of eight outputs from column x₀ of output rows m .. m + R (`dst` from row m's
/// start, rows wo apart), from input rows 2m − k/2 .. (`rows`, 2R + k − 2 of them; the padding
/// rows the row of zeros for k = 3, None for k = 5); `EDGE`: [`INSIDE`], [`LEFT`] (x₀ = 0, the
/// first block [`Reach::Left`]), [`RIGHT`] (the last block [`Reach::Right`]) or [`MASKS`]
/// (some block may reach past a row's edge, see [`block_reach`]). Each input row's taps go, kx
/// by kx, into every output row they reach, so each output sums its taps from zero in (ky, kx)
/// order.
///
/// # Safety
/// AVX2 and FMA; every row in `rows` holds w values, `dst` R·wo; x0 + 8(V − 1) < wo; for
/// `INSIDE`, x₀ ≥ 1 and 2(x₀ + 8(V − 1)) + 2·pairs(k) + 12 ≤ w; for `LEFT`, x₀ = 0,
/// [`left_inside`] and, for V = 2, block 1 as for `INSIDE`; for `RIGHT`, k = 3, w odd, the
/// last block at x₀ + 8(V − 1) = wo − 8 ≥ 1 and, for V = 2, block 0 as for `INSIDE`.
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn block<const K: usize, const KK: usize, const R: usize, const V: usize, const EDGE: u8>(
    rows: &[Option<&[f32]>; 11],
    x0: usize,
    (w, wo): (usize, usize),
    wv: &[__m256; KK],
    dst: *mut f32,
) {
    // Reach::Right's shifted load replaces pair 1's, the 3×3 kernel's last pair only.
    debug_assert!(EDGE != RIGHT || K == 3);
    let reach: [(Reach, Option<__m256i>); V] = std::array::from_fn(|v| match EDGE {
        MASKS => block_reach::<K>(x0 + v * HALF, w, wo),
        LEFT if v == 0 => (Reach::Left, None),
        RIGHT if v == V - 1 => (Reach::Right, None),
        _ => (Reach::Inside, None),
    });
    let mut acc = [[_mm256_setzero_ps(); V]; R];
    // A constant trip count (not the slice's length), so that each output row's accumulators
    // stay in registers; written out for the 3×3 kernel, whose loop LLVM left rolled for the
    // first blocks of a row (one thread, 192×22×35: 465–506 → 391–405 µs, `dw_prof`). The
    // 5×5 kernel's written out issued its rows' loads first and spilled them (96×44×70 two
    // threads 794–807 → 1737–1750 µs), so it stays a loop.
    rows_loop!(K == 3, 2 * R + K - 2, |i| {
        // The 3×3 kernel's rows are never None (see `output_rows`): Some here at compile
        // time, so no branch guards its loads.
        let row = if K == 3 {
            Some(rows[i].unwrap_or_default())
        } else {
            rows[i]
        };
        for pair in 0..pairs(K) {
            // SAFETY: every row in `rows` holds w values; `reach` is unmasked (Inside, Left,
            // Right) only where the columns `pair_loads` reads lie inside it.
            let ab: [(__m256, __m256); V] = std::array::from_fn(|v| unsafe {
                pair_loads(row, x0 + v * HALF, pair, reach[v].0)
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
    });
    for (r, acc) in acc.iter().enumerate() {
        for (v, a) in acc.iter().enumerate() {
            // Lanes 0 1 4 5 2 3 6 7 back to column order.
            let a = swap_quarters(*a);
            // SAFETY: output row m + r holds wo values; unmasked, x0 + 8V ≤ wo (≤ w / 2 for
            // Inside and Left, = wo for Right); masked, no lane past the row is written.
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

/// Whether the 3×3 forward on output rows `wo` wide leaves their last two outputs to
/// [`tail_pairs`]: rows of 8n + 1 and 8n + 2 (n ≥ 1), whose last one or two outputs would
/// otherwise take a whole block of eight (the 22×35 map's rows of 18: 24 lanes for 18
/// outputs; that block took a third of the layer's time, 192×22×35 one thread 333 µs on
/// rows of 16 against 487 µs on rows of 18, `dw_prof`).
const fn pairs_tail(k: usize, wo: usize) -> bool {
    k == 3 && wo > HALF && (wo % HALF == 1 || wo % HALF == 2)
}

/// The last two outputs (wo − 2, wo − 1) of output rows m .. m + R (R = 1, 2 or 4) of the
/// 3×3 kernel, the four rows' pairs in one register in column order: rows m and m + 1 in the
/// lower 128 bits, m + 2 and m + 3 in the upper. Tap kx of output j is column 2j + kx − 1, so
/// a pair reads columns s = 2wo − 5 ..= 2wo − 1 of its input rows (the last the padding on odd
/// widths); an in-lane shuffle of four columns of two rows each gives a tap's four pairs.
/// Each output sums its nine taps from zero in (ky, kx) order, as the blocks do, so a pair
/// the last block also wrote (rows of 8n + 1) is rewritten with the same bits.
///
/// # Safety
/// AVX2 and FMA; [`pairs_tail`] for (3, wo), wo = ⌈w/2⌉; `rows` as [`block`]'s (input rows
/// 2m − 1 .., w values each, the padding and rows past 2R + 1 the row of zeros); `dst` R·wo.
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn tail_pairs<const R: usize>(
    rows: &[Option<&[f32]>; 11],
    (w, wo): (usize, usize),
    wv: &[__m256; 9],
    dst: *mut f32,
) {
    debug_assert!(matches!(R, 1 | 2 | 4) && pairs_tail(3, wo) && wo == w.div_ceil(2));
    let s = 2 * wo - 5;
    let even = w.is_multiple_of(2);
    // Columns s .. s + 4 of input row i (from 2m − 1), and on even widths s + 1 .. s + 5
    // (the last, 2wo − 1 = w − 1, inside the row).
    // SAFETY: s + 3 ≤ w − 1 always, s + 4 = w − 1 on even widths; every row holds w values.
    let at = |i: usize, o: usize| unsafe {
        _mm_loadu_ps(rows[i].unwrap_or_default().as_ptr().add(s + o))
    };
    let mut acc = _mm256_setzero_ps();
    for ky in 0..3 {
        // Rows 2r + ky for the output rows r = 0 1 | 2 3.
        let (u, v) = (
            _mm256_set_m128(at(ky + 4, 0), at(ky, 0)),
            _mm256_set_m128(at(ky + 6, 0), at(ky + 2, 0)),
        );
        let t2 = if even {
            let (u, v) = (
                _mm256_set_m128(at(ky + 4, 1), at(ky, 1)),
                _mm256_set_m128(at(ky + 6, 1), at(ky + 2, 1)),
            );
            _mm256_shuffle_ps::<0xDD>(u, v)
        } else {
            // Columns s + 2 and the padding past the row.
            _mm256_blend_ps::<0xAA>(_mm256_shuffle_ps::<0x22>(u, v), _mm256_setzero_ps())
        };
        let taps = [
            _mm256_shuffle_ps::<0x88>(u, v),
            _mm256_shuffle_ps::<0xDD>(u, v),
            t2,
        ];
        for (kx, t) in taps.iter().enumerate() {
            acc = _mm256_fmadd_ps(wv[3 * ky + kx], *t, acc);
        }
    }
    let v = _mm256_castps_si256(acc);
    let (lo, hi) = (_mm256_castsi256_si128(v), _mm256_extracti128_si256::<1>(v));
    // Each pair as the low 64 bits of a register, stored unaligned (a row's pair need not
    // start at a multiple of 8 bytes).
    let pairs = [
        lo,
        _mm_unpackhi_epi64(lo, lo),
        hi,
        _mm_unpackhi_epi64(hi, hi),
    ];
    for (r, pair) in pairs.iter().enumerate().take(R) {
        // SAFETY: output row r < R holds wo values from dst + r·wo; the store writes the last
        // two.
        unsafe { _mm_storeu_si64(dst.add(r * wo + wo - 2).cast::<u8>(), *pair) };
    }
}

/// Lanes 0 1 4 5 2 3 6 7 to column order and back (64-bit quarters 0 2 1 3, its own inverse).
#[target_feature(enable = "avx2")]
fn swap_quarters(v: __m256) -> __m256 {
    _mm256_castpd_ps(_mm256_permute4x64_pd::<0xD8>(_mm256_castps_pd(v)))
}

/// One plane's 3×3 backward: `x` and `dx` h·w values, `dy` ho·wo; dL/dx written whole, the
/// nine taps' gradients into `dw` (overwritten).
///
/// # Safety
/// The CPU must have AVX2 and FMA; ho = ⌈h/2⌉, wo = ⌈w/2⌉.
#[target_feature(enable = "avx2,fma")]
unsafe fn plane_backward(
    h: usize,
    w: usize,
    (ho, wo): (usize, usize),
    (x, wk, dy): (&[f32], &[f32; 9], &[f32]),
    dx: &mut [MaybeUninit<f32>],
    dw: &mut [f32; 9],
) {
    // Checked without wrapping: the blocks below trust these sizes.
    let hw = h.checked_mul(w).expect("plane size overflows");
    let howo = ho.checked_mul(wo).expect("plane size overflows");
    assert!(x.len() == hw && dx.len() == hw && dy.len() == howo);
    assert!(ho == h.div_ceil(2) && wo == w.div_ceil(2));
    // SAFETY: AVX2 and FMA by the contract; sizes checked above.
    unsafe {
        let wv: [__m256; 9] = std::array::from_fn(|t| _mm256_set1_ps(wk[t]));
        grads(h, w, (ho, wo), (x, &wv, dy), dx, dw);
    }
}

/// One plane's 5×5 backward (`g` the layer's geometry, this plane's h and ho): dL/dw by the
/// plane path (read from the plane in registers as the 3×3 kernel's is, it ran no faster),
/// dL/dx in registers.
///
/// # Safety
/// The CPU must have AVX2 and FMA; g.k = 5, g.s = 2, `x` and `dx` hold h·w values, `dy` ho·wo,
/// ho = ⌈h/2⌉, wo = ⌈w/2⌉.
#[target_feature(enable = "avx2,fma")]
unsafe fn plane_backward5(
    g: &Geom,
    (h, ho): (usize, usize),
    (x, wk, dy): (&[f32], &[f32; 25], &[f32]),
    (dx, dw): (&mut [MaybeUninit<f32>], &mut [f32; 25]),
    sc: &mut Scratch,
) {
    let (w, wo) = (g.w, g.wo);
    let hw = h.checked_mul(w).expect("plane size overflows");
    let howo = ho.checked_mul(wo).expect("plane size overflows");
    assert!(x.len() == hw && dx.len() == hw && dy.len() == howo);
    assert!(g.k == 5 && ho == h.div_ceil(2) && wo == w.div_ceil(2));
    plane_weight_grad::<true>(g, x, dy, sc, dw);
    // SAFETY: AVX2 and FMA by the contract; sizes checked above.
    unsafe { input_grads::<5, 25>(h, w, (ho, wo), wk, dy, dx) };
}

/// dL/dw and dL/dx of one plane of the 3×3 kernel (taps `wv`), in one pass: output row m's
/// dL/dw terms, then input rows 2m and 2m + 1 of dL/dx ([`input_rows`]; 2m alone when it is
/// the last row), so the plane's input is read and its dL/dx written in the same sweep: on
/// 48×87×139 (batch 16, two threads) 2–5 % faster than the two passes in the same binary
/// (docs/bench/nets.md).
///
/// dL/dw: per tap, lane sums of dL/dy times the forward's tap registers over the rows and
/// blocks in the plane path's order (row by row, blocks left to right, lane l holding the
/// columns ≡ l mod 8), the lanes then summed in column order as the plane path does: its
/// bits. The lanes past the last output column multiply zeros by zeros, as its masked loads do.
/// dL/dx: each row pair (or last row) as [`input_grads`] computes it, the same bits.
///
/// # Safety
/// AVX2 and FMA; `x` and `dx` hold h·w values, `dy` ho·wo, ho = ⌈h/2⌉, wo = ⌈w/2⌉.
#[target_feature(enable = "avx2,fma")]
unsafe fn grads(
    h: usize,
    w: usize,
    (ho, wo): (usize, usize),
    (x, wv, dy): (&[f32], &[__m256; 9], &[f32]),
    dx: &mut [MaybeUninit<f32>],
    dw: &mut [f32; 9],
) {
    let mut acc = [_mm256_setzero_ps(); 9];
    let row = |r: usize| (r < h).then(|| &x[r * w..][..w]);
    let wide = w >= PREFETCH_WIDTH;
    for m in 0..ho {
        let rows = [row((2 * m).wrapping_sub(1)), row(2 * m), row(2 * m + 1)];
        let d = dy[m * wo..][..wo].as_ptr();
        // The two input rows the output row AHEAD_DW / 2 on reads first, prefetched on wide
        // rows.
        let ahead = x.as_ptr().wrapping_add((2 * m + AHEAD_DW) * w);
        let mut x0 = 0;
        while x0 < wo {
            if wide {
                prefetch(ahead.wrapping_add(2 * x0));
                prefetch(ahead.wrapping_add(w + 2 * x0));
            }
            let (reach, keep) = if x0 == 0 && left_inside::<3>(w) {
                (Reach::Left, None)
            } else {
                block_reach::<3>(x0, w, wo)
            };
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
                // SAFETY: every row `row` gives holds w values; `reach` is unmasked (Inside,
                // Left) only where the columns `taps` reads lie inside it.
                let t = unsafe { taps3(*r, x0, reach) };
                for (kx, v) in t.iter().enumerate() {
                    let v = keep.map_or(*v, |k| _mm256_and_ps(*v, k));
                    acc[3 * ky + kx] = _mm256_fmadd_ps(g, v, acc[3 * ky + kx]);
                }
            }
            x0 += HALF;
        }
        // SAFETY (both): input rows 2m .. 2m + R ≤ h (2m < h as m < ⌈h/2⌉); the rest is this
        // function's contract.
        unsafe {
            if 2 * m + 2 <= h {
                input_rows::<3, 9, 2>(2 * m, w, (ho, wo), wv, dy, dx);
            } else {
                input_rows::<3, 9, 1>(2 * m, w, (ho, wo), wv, dy, dx);
            }
        }
    }
    for (t, a) in acc.iter().enumerate() {
        let mut lanes = [0.0f32; HALF];
        // SAFETY: a store of exactly HALF values into `lanes`.
        unsafe { _mm256_storeu_ps(lanes.as_mut_ptr(), swap_quarters(*a)) };
        dw[t] = lanes.iter().sum::<f32>();
    }
}

/// dL/dx of one plane of a k×k kernel (KK = k² taps, k = 3 or 5): input cell (i, j) takes the
/// taps (ky, kx) with 2·oy + ky = i + k/2 and 2·ox + kx = j + k/2, summed from zero in (ky, kx)
/// order, rows and columns of dL/dy past the plane read as zeros: the sums of the plane path's
/// phase sweeps, bit for bit. Two input rows and two blocks of sixteen columns at a time,
/// each block as its even and odd columns: eight sums in flight (one row and block at a time,
/// a 5×5 cell's chain of nine multiply–adds waits on their latency).
///
/// # Safety
/// AVX2 and FMA; `dx` holds h·w values, `dy` ho·wo, ho = ⌈h/2⌉, wo = ⌈w/2⌉.
#[target_feature(enable = "avx2,fma")]
unsafe fn input_grads<const K: usize, const KK: usize>(
    h: usize,
    w: usize,
    (ho, wo): (usize, usize),
    wk: &[f32; KK],
    dy: &[f32],
    dx: &mut [MaybeUninit<f32>],
) {
    assert!(K * K == KK && (K == 3 || K == 5));
    assert!(dx.len() == h * w && dy.len() == ho * wo && ho == h.div_ceil(2));
    assert!(wo == w.div_ceil(2));
    let wv: [__m256; KK] = std::array::from_fn(|t| _mm256_set1_ps(wk[t]));
    let mut i = 0;
    // SAFETY (both): rows i .. i + R ≤ h, i even; the rest is this function's contract.
    while i + 2 <= h {
        unsafe { input_rows::<K, KK, 2>(i, w, (ho, wo), &wv, dy, dx) };
        i += 2;
    }
    if i < h {
        unsafe { input_rows::<K, KK, 1>(i, w, (ho, wo), &wv, dy, dx) };
    }
}

/// Input rows i₀ .. i₀ + R (i₀ even) of one plane's dL/dx (see [`input_grads`]), from dL/dy
/// rows i₀/2 − 1 .. i₀/2 + 1.
///
/// # Safety
/// AVX2 and FMA; i₀ even, i₀ + R ≤ h; `dx` holds h·w values, `dy` ho·wo, ho = ⌈h/2⌉,
/// wo = ⌈w/2⌉.
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn input_rows<const K: usize, const KK: usize, const R: usize>(
    i0: usize,
    w: usize,
    (ho, wo): (usize, usize),
    wv: &[__m256; KK],
    dy: &[f32],
    dx: &mut [MaybeUninit<f32>],
) {
    // dL/dy rows i₀/2 − 1 + e (those above wrap past ho): None, zeros, past the plane.
    let drows: [Option<&[f32]>; 3] = std::array::from_fn(|e| {
        let m = (i0 / 2 + e).wrapping_sub(1);
        (m < ho).then(|| &dy[m * wo..][..wo])
    });
    let dst = dx[i0 * w..][..R * w].as_mut_ptr().cast::<f32>();
    // Blocks whose loads (dL/dy columns c₀ − 1 .. c₀ + 9 with c₀ = j₀/2, from c₀ for k = 3)
    // and stores (columns j₀ .. j₀ + 16) stay inside their rows.
    let interior = |j0: usize| (K == 3 || j0 >= 2) && j0 / 2 + 9 <= wo && j0 + LANES <= w;
    // On odd widths (3×3) the last block that ends at the row's end starts at the odd column
    // w − 16, over columns already written (each cell's sum is the same wherever its block
    // starts), so the right edge needs no masks.
    let odd_last = K == 3 && !w.is_multiple_of(2) && w > LANES;
    let mut j0 = 0;
    while j0 < w {
        // SAFETY: j₀ < w, and unmasked blocks are interior (the odd last block: c₀ + 9 = wo,
        // columns w − 16 .. w); the rest is this function's contract.
        unsafe {
            if interior(j0) && interior(j0 + LANES) {
                dx_block::<K, KK, R, 2, false, false>(&drows, j0, (w, wo), wv, dst);
                j0 += 2 * LANES;
            } else {
                if interior(j0) {
                    dx_block::<K, KK, R, 1, false, false>(&drows, j0, (w, wo), wv, dst);
                } else if odd_last && w - LANES <= j0 {
                    dx_block::<K, KK, R, 1, false, true>(&drows, w - LANES, (w, wo), wv, dst);
                    j0 = w;
                    continue;
                } else {
                    dx_block::<K, KK, R, 1, true, false>(&drows, j0, (w, wo), wv, dst);
                }
                j0 += LANES;
            }
        }
    }
}

/// V blocks of sixteen input columns from j₀ of input rows i₀ .. i₀ + R (`dst` from row i₀'s
/// start, rows w apart), from dL/dy rows i₀/2 − 1 ..= i₀/2 + 1 (`drows`, each wo wide, None past
/// the plane). dL/dy row i₀/2 − 1 + e serves input row i₀ + r with tap row ky = r + k/2 + 2 −
/// 2e, so the rows go from e = 2 down: each sum takes its tap rows in ascending order, and in
/// each its taps kx in ascending order, column 2c + q taking tap kx from dL/dy column
/// c + (q + k/2 − kx)/2. `MASKED`: lane masks on every load and store. `ODD` (3×3, V = 1):
/// j₀ is odd, so lane pair (c, q) holds column j₀ + 2c + q of parity 1 − q, its taps chosen
/// and its dL/dy columns offset accordingly.
///
/// # Safety
/// AVX2 and FMA; j₀ < w; `dst` holds R·w values; unless `MASKED`, j₀ + 16V ≤ w and
/// ⌊j₀/2⌋ + 8(V − 1) + 9 ≤ wo and, for k = 5, j₀ ≥ 2. `ODD` (for its values, not its memory
/// accesses): k = 3, V = 1, not `MASKED`, j₀ odd.
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn dx_block<
    const K: usize,
    const KK: usize,
    const R: usize,
    const V: usize,
    const MASKED: bool,
    const ODD: bool,
>(
    drows: &[Option<&[f32]>; 3],
    j0: usize,
    (w, wo): (usize, usize),
    wv: &[__m256; KK],
    dst: *mut f32,
) {
    let p = K / 2;
    // An odd start moves the 3×3 kernel's taps to dL/dy columns d = 1, 2 only (ld below).
    debug_assert!(!ODD || (K == 3 && V == 1 && !MASKED && !j0.is_multiple_of(2)));
    let z = _mm256_setzero_ps();
    // acc[r][q][v]: the columns j₀ + 2c + q of block v in input row i₀ + r (parity q, or
    // 1 − q for an odd start).
    let mut acc = [[[z; V]; 2]; R];
    // Plain counted loops over constants, so that they unroll and the loads and weights stay
    // in registers (written with iterator filters, they indexed both on the stack).
    for e in (0..3usize).rev() {
        if (0..R).all(|r| r + p + 2 < 2 * e || r + p + 2 - 2 * e >= K) {
            continue;
        }
        // Columns c + d − 1 for the eight c from block v's c₀ (d = 0 only for k = 5).
        let ld: [[__m256; V]; 3] = std::array::from_fn(|d| {
            std::array::from_fn(|v| {
                let Some(row) = drows[e] else { return z };
                if K == 3 && d == 0 {
                    return z;
                }
                let c = j0 / 2 + v * HALF + d;
                let at = row.as_ptr().wrapping_add(c).wrapping_sub(1);
                // SAFETY: unmasked, columns c₀ − 1 .. c₀ + 9 are inside the row (the contract);
                // masked lanes are neither read nor faulted on.
                unsafe {
                    if MASKED {
                        _mm256_maskload_ps(at, inside(c as isize - 1, wo))
                    } else {
                        _mm256_loadu_ps(at)
                    }
                }
            })
        });
        for r in 0..R {
            if r + p + 2 < 2 * e || r + p + 2 - 2 * e >= K {
                continue;
            }
            let ky = r + p + 2 - 2 * e;
            for q in 0..2 {
                // Column j₀ + 2c + q is 2(c₀ + c) + q, or for an odd start 2(c₀ + c + q) + 1 − q.
                let parity = q ^ ODD as usize;
                for kx in 0..K {
                    if !(parity + p + kx).is_multiple_of(2) {
                        continue;
                    }
                    let d = (parity + p + 2 - kx) / 2 + ODD as usize * q;
                    let wt = wv[K * ky + kx];
                    for v in 0..V {
                        acc[r][q][v] = _mm256_fmadd_ps(wt, ld[d][v], acc[r][q][v]);
                    }
                }
            }
        }
    }
    for (r, acc) in acc.iter().enumerate() {
        for v in 0..V {
            let (even, odd) = (acc[0][v], acc[1][v]);
            // Within each 128-bit lane [e0 o0 e1 o1] and [e2 o2 e3 o3]: the block's first eight
            // columns are the low lanes of both, the next eight the high lanes.
            let (lo, hi) = (_mm256_unpacklo_ps(even, odd), _mm256_unpackhi_ps(even, odd));
            let (left, right) = (
                _mm256_permute2f128_ps::<0x20>(lo, hi),
                _mm256_permute2f128_ps::<0x31>(lo, hi),
            );
            let j = j0 + v * LANES;
            let d = dst.wrapping_add(r * w + j);
            // SAFETY: j + 16 ≤ w, or no lane past the row is written (a left-edge block
            // masks its loads only).
            unsafe {
                if MASKED && j + LANES > w {
                    // Through a buffer, not AVX2 masked stores: one thread 96×44×70 2166–2215
                    // → 1884–1925 µs on an AMD EPYC VM (docs/bench/nets.md).
                    let mut buf = [0.0f32; LANES];
                    _mm256_storeu_ps(buf.as_mut_ptr(), left);
                    _mm256_storeu_ps(buf.as_mut_ptr().add(HALF), right);
                    std::ptr::copy_nonoverlapping(buf.as_ptr(), d, w - j);
                } else {
                    _mm256_storeu_ps(d, left);
                    _mm256_storeu_ps(d.add(HALF), right);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Planes of 1–40 rows and widths from one column to past several registers (odd and
    /// even, the main job's 35, 70, 87 and 139; rows of 8n + 1 and 8n + 2 outputs, whose last
    /// pair [`tail_pairs`] computes, odd and even), through the entry point: y bit for bit the
    /// plane path's (padding rows and masked edge lanes summed as its zeros are).
    #[test]
    fn stride_2_gives_the_plane_paths_bits() {
        if !has_fma() {
            return;
        }
        for w in [
            1, 2, 3, 7, 8, 9, 15, 16, 17, 18, 19, 20, 31, 32, 33, 34, 35, 36, 47, 49, 50, 70, 87,
            139,
        ] {
            for k in [3, 5] {
                super::super::assert_plane_path_bits((w, k, 2), 200 + w as u64, forward);
            }
        }
    }

    /// The 3×3 and 5×5 backward through the entry point, the same widths and those whose last
    /// block holds seven outputs, 1–40 rows, finite values and then infinities among them:
    /// dL/dx and dL/dw bit for bit the plane path's (padding taps and the lanes past the last
    /// output column summed as its zeros are).
    #[test]
    fn stride_2_backward_is_the_plane_paths_bits() {
        if !has_fma() {
            return;
        }
        for w in [
            1, 2, 3, 7, 8, 9, 13, 14, 15, 16, 17, 18, 29, 30, 31, 32, 33, 35, 70, 87, 139,
        ] {
            for k in [3, 5] {
                super::super::assert_plane_path_backward((w, k, 2), 300 + w as u64, true, backward);
            }
        }
    }
}

//! Depthwise 3×3 at stride 1, forward, read straight from the plane in registers.
//!
//! The plane path copies every plane into a zero-padded scratch before its sweep: one more
//! pass over the plane than the convolution needs. Here the padding is never written: the rows
//! above and below the plane read a row of zeros; on rows wider than eight the first block
//! takes column −1 as a zero shifted into its load of columns 0 .. 8, and the last block
//! starts at w − 8 (over outputs already written) with column w shifted in as a zero, so no
//! load or store is masked (the edge blocks' masked loads and stores took about a third of
//! the 192×22×35 forward on an AMD EPYC VM); rows of at most eight load and store under lane
//! masks, whose masked
//! lanes read as zero. Four output rows at a time
//! share each input row's three shifted loads (six rows: 18 loads for 36 fused multiply–adds),
//! and every output sums its nine taps from zero in (ky, kx) order, padding included, as the
//! plane path does, so y is the plane path's bits (test `stride_1_gives_the_plane_paths_bits`).

use super::{Geom, HALF, PREFETCH_WIDTH, forward_planes, has_fma, prefetch};
use std::arch::x86_64::*;
use std::mem::MaybeUninit;

/// Whether a layer with this geometry goes through this path.
pub(super) fn takes(g: &Geom) -> bool {
    // Widths fit the lane masks' 32-bit column indices.
    g.k == 3
        && g.s == 1
        && g.ho == g.h
        && g.wo == g.w
        && g.h > 0
        && g.w > 0
        && g.w < i32::MAX as usize - HALF
        && has_fma()
}

/// Forward over all planes (as [`super::forward`]); panics unless `takes(g)`.
pub(super) fn forward(g: &Geom, c: usize, x: &[f32], w: &[f32], y: &mut [MaybeUninit<f32>]) {
    // The planes below run AVX2 and FMA code on that check alone.
    assert!(takes(g), "stride 1 for {g:?}");
    // The padding rows' one row of zeros, read by every plane.
    let zeros = vec![0.0f32; g.w];
    let width = g.w;
    // SAFETY: `takes` checked AVX2 and FMA on this CPU; the driver hands each plane its h·w
    // inputs and outputs.
    forward_planes(g, c, (x, w), y, |h, _, x, wk, out| unsafe {
        plane(h, width, x, wk, &zeros, out)
    });
}

/// Lanes `i` with `0 ≤ start + i < w`, all bits set (callable where AVX2 is enabled); the
/// masks of both register paths' edge blocks.
#[target_feature(enable = "avx2")]
pub(super) fn inside(start: isize, w: usize) -> __m256i {
    let idx = _mm256_add_epi32(
        _mm256_set1_epi32(start as i32),
        _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7),
    );
    _mm256_and_si256(
        _mm256_cmpgt_epi32(idx, _mm256_set1_epi32(-1)),
        _mm256_cmpgt_epi32(_mm256_set1_epi32(w as i32), idx),
    )
}

/// One plane: `x` and `out` hold h·w values, `zeros` at least w zeros (also the plane path's
/// stride-1 dL/dx: dL/dy correlated with the kernel turned by 180°).
///
/// # Safety
/// The CPU must have AVX2 and FMA.
#[target_feature(enable = "avx2,fma")]
pub(super) unsafe fn plane(
    h: usize,
    w: usize,
    x: &[f32],
    wk: &[f32; 9],
    zeros: &[f32],
    out: &mut [MaybeUninit<f32>],
) {
    // Checked without wrapping: the blocks below trust h·w.
    let hw = h.checked_mul(w).expect("plane size overflows");
    assert!(x.len() == hw && out.len() == hw && zeros.len() >= w);
    let taps: [__m256; 9] = std::array::from_fn(|t| _mm256_set1_ps(wk[t]));
    let mut m = 0;
    // SAFETY (all three): rows m .. m + R < h, the slices' lengths checked above.
    while m + 4 <= h {
        unsafe { rows::<4>(h, w, x, &taps, zeros, m, out) };
        m += 4;
    }
    while m + 2 <= h {
        unsafe { rows::<2>(h, w, x, &taps, zeros, m, out) };
        m += 2;
    }
    if m < h {
        unsafe { rows::<1>(h, w, x, &taps, zeros, m, out) };
    }
}

/// Output rows `m .. m + R` (R ≤ 4) of one plane, every column.
///
/// # Safety
/// AVX2 and FMA; `m + R ≤ h`, `x` and `out` hold h·w values, `zeros` at least w.
#[target_feature(enable = "avx2,fma")]
unsafe fn rows<const R: usize>(
    h: usize,
    w: usize,
    x: &[f32],
    taps: &[__m256; 9],
    zeros: &[f32],
    m: usize,
    out: &mut [MaybeUninit<f32>],
) {
    // Input rows m − 1 .. m + R; those outside the plane are the zero padding.
    let mut src = [zeros.as_ptr(); 6];
    for (j, p) in src.iter_mut().enumerate().take(R + 2) {
        let r = (m + j).wrapping_sub(1);
        if r < h {
            *p = x[r * w..].as_ptr();
        }
    }
    let dst = out[m * w..].as_mut_ptr().cast::<f32>();
    // The first of the four input rows that the group AHEAD rows on reads first (none of
    // the groups before it does): prefetched block by block on wide rows.
    let ahead = x.as_ptr().wrapping_add((m + 1 + AHEAD) * w);
    let wide = R == 4 && w >= PREFETCH_WIDTH;
    let mut x0 = 0;
    while x0 < w {
        if wide {
            for j in 0..4 {
                prefetch(ahead.wrapping_add(j * w + x0));
            }
        }
        // SAFETY: every row behind `src` holds w values; an interior block reads columns
        // x0 − 1 .. x0 + HALF + 1 ≤ w, the first and last blocks of a row wider than eight
        // columns 0 .. 9 and w − 9 .. w, a block of a narrower row only the columns its masks
        // let through; rows m .. m + R of `out` hold the stores.
        unsafe {
            if x0 >= 1 && x0 + HALF < w {
                block::<R, INSIDE>(&src, taps, x0, w, dst);
            } else if w <= HALF {
                block::<R, MASKED>(&src, taps, x0, w, dst);
            } else if x0 == 0 {
                block::<R, LEFT>(&src, taps, 0, w, dst);
            } else {
                // The last block starts at w − 8, over outputs already written (each with the
                // same bits wherever its block starts), so that it stores without a mask.
                block::<R, RIGHT>(&src, taps, w - HALF, w, dst);
            }
        }
        x0 += HALF;
    }
}

/// Rows ahead of a group of four output rows whose new input rows its blocks prefetch on
/// rows of at least [`PREFETCH_WIDTH`]: four groups. On 24×100×160 at batch 16 (two threads)
/// the forward took 2.26–2.57 ms without, 1.87–2.03 ms with two groups into L1 and
/// 1.48–1.64 ms with four into L2.
const AHEAD: usize = 16;

/// [`block`]'s `EDGE`: columns x₀ − 1 .. x₀ + 9 inside the row.
const INSIDE: u8 = 0;
/// [`block`]'s `EDGE`: x₀ = 0 on a row wider than eight; column −1 (the padding) is lane 0 of
/// the load of columns 0 .. 8 moved up one lane, a zero shifted in.
const LEFT: u8 = 1;
/// [`block`]'s `EDGE`: x₀ = w − 8 ≥ 1; column w (the padding) is lane 7 of the load of
/// columns w − 8 .. w moved down one lane, a zero shifted in.
const RIGHT: u8 = 2;
/// [`block`]'s `EDGE`: rows of at most eight, loads and stores under lane masks.
const MASKED: u8 = 3;

/// Columns `x0 .. x0 + HALF` (those below w) of R output rows, `dst` at the first row's start.
///
/// # Safety
/// AVX2 and FMA; `src[0 .. R + 2]` each point at w readable values; for `INSIDE`, `1 ≤ x0`
/// and `x0 + HALF < w`; for `LEFT`, x0 = 0 and w > HALF; for `RIGHT`, x0 = w − HALF ≥ 1;
/// `dst` holds R rows of w.
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn block<const R: usize, const EDGE: u8>(
    src: &[*const f32; 6],
    taps: &[__m256; 9],
    x0: usize,
    w: usize,
    dst: *mut f32,
) {
    let mut acc = [_mm256_setzero_ps(); R];
    let masks = if EDGE == MASKED {
        [
            inside(x0 as isize - 1, w),
            inside(x0 as isize, w),
            inside(x0 as isize + 1, w),
        ]
    } else {
        [_mm256_setzero_si256(); 3]
    };
    for (j, &p) in src.iter().enumerate().take(R + 2) {
        // The row's columns x0 − 1, x0, x0 + 1 onwards: the three taps of each output lane.
        // Masked lanes are neither read nor faulted on, so the addresses one before the row's
        // start are never touched (wrapping arithmetic: never dereferenced there).
        // SAFETY: inside the row by the contract, or masked.
        let [a, b, c] = unsafe {
            if EDGE == MASKED {
                [
                    _mm256_maskload_ps(p.wrapping_add(x0).wrapping_sub(1), masks[0]),
                    _mm256_maskload_ps(p.add(x0), masks[1]),
                    _mm256_maskload_ps(p.wrapping_add(x0 + 1), masks[2]),
                ]
            } else if EDGE == LEFT {
                let b = _mm256_loadu_ps(p);
                let up = _mm256_permutevar8x32_ps(b, _mm256_setr_epi32(0, 0, 1, 2, 3, 4, 5, 6));
                [
                    _mm256_blend_ps::<0x01>(up, _mm256_setzero_ps()),
                    b,
                    _mm256_loadu_ps(p.add(1)),
                ]
            } else if EDGE == RIGHT {
                let b = _mm256_loadu_ps(p.add(x0));
                let down = _mm256_permutevar8x32_ps(b, _mm256_setr_epi32(1, 2, 3, 4, 5, 6, 7, 7));
                [
                    _mm256_loadu_ps(p.add(x0 - 1)),
                    b,
                    _mm256_blend_ps::<0x80>(down, _mm256_setzero_ps()),
                ]
            } else {
                [
                    _mm256_loadu_ps(p.add(x0 - 1)),
                    _mm256_loadu_ps(p.add(x0)),
                    _mm256_loadu_ps(p.add(x0 + 1)),
                ]
            }
        };
        // Input row j is tap row ky = j − r of output row r: ky rises with j, so each output
        // still sums (ky, kx) in order.
        for (r, acc) in acc.iter_mut().enumerate() {
            let Some(ky) = j.checked_sub(r).filter(|&ky| ky < 3) else {
                continue;
            };
            *acc = _mm256_fmadd_ps(taps[3 * ky], a, *acc);
            *acc = _mm256_fmadd_ps(taps[3 * ky + 1], b, *acc);
            *acc = _mm256_fmadd_ps(taps[3 * ky + 2], c, *acc);
        }
    }
    for (r, a) in acc.iter().enumerate() {
        // SAFETY: row r of `dst` holds w values; masked, only the columns below w are written.
        unsafe {
            let d = dst.add(r * w + x0);
            if EDGE == MASKED {
                _mm256_maskstore_ps(d, masks[1], *a);
            } else {
                _mm256_storeu_ps(d, *a);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Planes of 1–40 rows and widths from one column to past several registers, through the
    /// entry point: y bit for bit the plane path's (padding rows and masked edge lanes summed
    /// as its zeros are).
    #[test]
    fn stride_1_gives_the_plane_paths_bits() {
        if !has_fma() {
            return;
        }
        for w in [1, 2, 7, 8, 9, 10, 15, 16, 17, 18, 35, 70, 139] {
            super::super::assert_plane_path_bits((w, 3, 1), 100 + w as u64, forward);
        }
    }

    /// The stride-1 backward's dL/dx, which now reads dL/dy in registers, against what the
    /// plane path computed before: dL/dy padded and correlated with the kernel turned by
    /// 180° (the plane path's forward on dL/dy), bit for bit; and dL/dw, whose code is the
    /// plane path's, against the definition.
    #[test]
    fn stride_1_dx_is_the_plane_paths_bits() {
        use rand::{Rng, SeedableRng, rngs::StdRng};
        if !has_fma() {
            return;
        }
        let mut rng = StdRng::seed_from_u64(7);
        let mut sc = super::super::Scratch::default();
        for w in [1, 5, 8, 9, 16, 17, 35, 70] {
            for h in [1, 2, 3, 4, 5, 7, 12] {
                let g = Geom::k3(h, w, 1);
                let (n, c) = (2, 3);
                let len = n * c * h * w;
                let x: Vec<f32> = (0..len).map(|_| rng.random_range(-1.0..1.0)).collect();
                let dy: Vec<f32> = (0..len).map(|_| rng.random_range(-1.0..1.0)).collect();
                let wk: Vec<f32> = (0..c * 9).map(|_| rng.random_range(-1.0..1.0)).collect();
                let (mut dx, mut dw) = (vec![f32::NAN; len], vec![f32::NAN; n * c * 9]);
                super::super::backward(
                    &g,
                    c,
                    &x,
                    &wk,
                    &dy,
                    // SAFETY: the paths write initialised values only.
                    unsafe { super::super::as_uninit(&mut dx) },
                    &mut dw,
                );
                for p in 0..n * c {
                    let flip: Vec<f32> = wk[(p % c) * 9..][..9].iter().rev().copied().collect();
                    let mut dx0 = vec![f32::NAN; h * w];
                    let dyp = &dy[p * h * w..][..h * w];
                    // SAFETY: has_fma() holds (checked above).
                    unsafe { super::super::forward_plane_fma(&g, dyp, &flip, &mut sc, &mut dx0) };
                    for (i, (a, b)) in dx[p * h * w..][..h * w].iter().zip(&dx0).enumerate() {
                        assert_eq!(a.to_bits(), b.to_bits(), "dx[{p}][{i}], {h}×{w}");
                    }
                    let xp = &x[p * h * w..][..h * w];
                    for t in 0..9 {
                        let (ky, kx) = (t / 3, t % 3);
                        let mut r = 0.0f64;
                        for oy in 0..h {
                            for ox in 0..w {
                                let (iy, ix) =
                                    ((oy + ky).wrapping_sub(1), (ox + kx).wrapping_sub(1));
                                if iy < h && ix < w {
                                    r += xp[iy * w + ix] as f64 * dyp[oy * w + ox] as f64;
                                }
                            }
                        }
                        let d = dw[p * 9 + t] as f64;
                        assert!(
                            (d - r).abs() <= 1e-5 * (1.0 + (h * w) as f64),
                            "dw[{p}][{t}] {d} vs {r}"
                        );
                    }
                }
            }
        }
    }
}

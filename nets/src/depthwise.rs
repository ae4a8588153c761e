//! Depthwise k×k convolution kernels (forward, input and weight gradients), NCHW.
//!
//! Each (image, channel) plane is copied once into a zero-padded scratch whose columns are
//! split by parity of the stride (phase q = column mod s), so every tap (ky, kx) of every
//! output row reads one contiguous, bounds-free run of `wo` values: the inner loops are
//! straight-line multiply–adds the compiler vectorizes. The forward pass computes up to four
//! output rows at a time so that several accumulator registers are in flight, with one
//! bounds check per plane; at stride 2 the phase split is a pairwise column copy (register
//! shuffles with AVX2). dL/dx runs through the same row blocks as a correlation of dL/dy: with
//! the kernel turned by 180° at stride 1, with each phase's sub-kernel at stride s ≥ 2 (see
//! [`strided_dx`]). On x86-64 with AVX2 and FMA (checked at run time) the same code is
//! compiled a second time with fused multiply–adds. Scratch lives per rayon task, not per
//! plane, and its zero padding is written once per geometry; planes are grouped so a task
//! carries enough work to pay for the scheduling. Output planes of at most 256 values (the
//! low-resolution stages), where a plane's fixed costs outweigh its multiply–adds, go through
//! blocks of eight channels instead ([`channels`]), which give the same y and dL/dx bits.
//! 3×3 layers at stride 2 on planes 8 or 16 wide run in registers ([`rows8`], [`rows16`]):
//! the same y bits; their backward sums in other orders (equal to round-off). The 3×3
//! forward at stride 1 on planes 4 wide runs in registers too ([`rows4`]; the same y bits).
//! The other 3×3 layers at stride 1 read the plane itself, without the padded copy
//! ([`stride1`]), for y and for dL/dx (dL/dy correlated with the turned kernel): the same
//! bits; so do the other 3×3 and 5×5 layers at stride 2 ([`stride2`]), forward and backward
//! (the 5×5 dL/dw by the plane path), again the same bits. On rows of at least
//! [`PREFETCH_WIDTH`] columns these two prefetch their input rows ahead of the rows in
//! flight.

use rayon::prelude::*;
use std::mem::MaybeUninit;

/// `$f::<$square>(args)` when `$h == $square`, else `$f::<0>(args)`: a plane function's
/// version compiled for that height (row loops unrolled, padding rows known) or for any.
#[cfg(target_arch = "x86_64")]
macro_rules! at_height {
    ($h:expr, $square:expr, $f:ident($($arg:expr),* $(,)?)) => {
        if $h == $square {
            $f::<$square>($($arg),*)
        } else {
            $f::<0>($($arg),*)
        }
    };
}

#[cfg(target_arch = "x86_64")]
mod channels;
#[cfg(target_arch = "x86_64")]
mod rows16;
#[cfg(target_arch = "x86_64")]
mod rows4;
#[cfg(target_arch = "x86_64")]
mod rows8;
#[cfg(target_arch = "x86_64")]
mod stride1;
#[cfg(target_arch = "x86_64")]
mod stride2;

/// Output lanes accumulated in registers per block of an output row.
const LANES: usize = 16;
/// A block of one 256-bit register of f32 lanes.
const HALF: usize = LANES / 2;
/// Smallest number of multiply–adds a rayon task should carry.
const TASK_MACS: usize = 1 << 16;

/// The narrowest rows whose register paths prefetch the input rows ahead of those in flight.
/// At batch 16 the layers on the main job's and the bench's widest maps (87×139, 100×160)
/// waited on their input rows from memory: the hardware prefetcher did not keep up with the
/// several rows a group of output rows reads at once (`perf annotate`: the loads of the
/// group's newest rows). On the 44×70 and 22×35 maps, whose rows came in time, the extra
/// instructions cost 4–43 % (AMD EPYC VM; docs/bench/nets.md).
#[cfg(target_arch = "x86_64")]
const PREFETCH_WIDTH: usize = 128;

/// Asks for the cache line holding `p` with hint T1 (into L2 where the CPU honours it; the
/// first form, hint T0 two groups ahead, gained less than T1 four groups ahead: distance and
/// hint changed together). Only a hint: `p` may lie past its slice (the next plane, or past
/// the tensor), is never dereferenced and never faults.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn prefetch(p: *const f32) {
    use std::arch::x86_64::{_MM_HINT_T1, _mm_prefetch};
    // SAFETY: SSE, the instruction's only requirement, is part of every x86-64 CPU; a
    // prefetch reads nothing the program sees, whatever the address.
    unsafe { _mm_prefetch::<_MM_HINT_T1>(p.cast()) };
}

/// Output rows `m` and `m + 1` of four values (`acc`'s low and high 128-bit lanes) into
/// `out`, a plane of `rows` such rows; only row m when it is the last (the high lane is then
/// past the plane). The store of the 4-wide register paths ([`rows4`], [`rows8`]).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
fn store_row_pair(
    out: &mut [MaybeUninit<f32>],
    rows: usize,
    m: usize,
    acc: std::arch::x86_64::__m256,
) {
    use std::arch::x86_64::*;
    if m + 1 < rows {
        let dst = &mut out[4 * m..][..8];
        // SAFETY: `dst` holds eight values: output rows m and m + 1.
        unsafe { _mm256_storeu_ps(dst.as_mut_ptr().cast(), acc) };
    } else {
        let dst = &mut out[4 * m..][..4];
        // SAFETY: `dst` holds four values.
        unsafe { _mm_storeu_ps(dst.as_mut_ptr().cast(), _mm256_castps256_ps128(acc)) };
    }
}

/// Shape of one plane's depthwise convolution (same padding k/2, stride s).
#[derive(Clone, Copy, Debug)]
pub(crate) struct Geom {
    /// Input height, width (pixels).
    pub h: usize,
    pub w: usize,
    /// Output height, width (pixels).
    pub ho: usize,
    pub wo: usize,
    /// Kernel size and stride.
    pub k: usize,
    pub s: usize,
}

impl Geom {
    fn pad(&self) -> usize {
        self.k / 2
    }
    /// Padded rows.
    fn rows(&self) -> usize {
        self.h + 2 * self.pad()
    }
    /// Columns of one phase of a padded row.
    fn cw(&self) -> usize {
        (self.w + 2 * self.pad()).div_ceil(self.s)
    }
    fn scratch_len(&self) -> usize {
        self.rows() * self.s * self.cw()
    }
    /// Planes per rayon task.
    fn planes_per_task(&self) -> usize {
        (TASK_MACS / (self.ho * self.wo * self.k * self.k).max(1)).max(1)
    }
    /// Rows and columns of dL/dy zero-padded for the strided dL/dx: p before, and after it as
    /// many as the taps of the last interior cell reach.
    fn strided_dy_extent(&self) -> (usize, usize) {
        let (p, s) = (self.pad(), self.s);
        (
            self.ho.max((p + self.h - 1) / s + 1) + p,
            self.wo.max((p + self.w - 1) / s + 1) + p,
        )
    }
    /// Phase rows (or columns) of phase q that hold interior cells, of n: the first at or after
    /// the padding and one past the last.
    fn phase_span(&self, q: usize, n: usize) -> (usize, usize) {
        let (p, s) = (self.pad(), self.s);
        (
            p.saturating_sub(q).div_ceil(s),
            (p + n).saturating_sub(q).div_ceil(s),
        )
    }
    /// The taps that reach the cells of phase (ρ, γ) in (ky, kx) order: each tap's index
    /// ky·k + kx and its offset from the cell's own position in the padded dL/dy of `wp`
    /// columns (see [`strided_dx`]).
    fn phase_taps(
        &self,
        (rho, gamma): (usize, usize),
        wp: usize,
    ) -> impl Iterator<Item = (usize, usize)> {
        let (p, s, k) = (self.pad(), self.s, self.k);
        (rho..k).step_by(s).flat_map(move |ky| {
            (gamma..k).step_by(s).map(move |kx| {
                (
                    ky * k + kx,
                    (p - (ky - rho) / s) * wp + p - (kx - gamma) / s,
                )
            })
        })
    }
}

/// a·b + c, fused where the target has FMA.
#[inline(always)]
pub(crate) fn madd<const FMA: bool>(a: f32, b: f32, c: f32) -> f32 {
    // Without the FMA target feature `mul_add` would be a libm call; with it, one instruction.
    if FMA { a.mul_add(b, c) } else { a * b + c }
}

/// Copies plane `x` (h × w) into the zero-padded, phase-split scratch.
///
/// A geometry writes the same interior cells for every plane, so the padding is zeroed only
/// when `shape` (the geometry the scratch was last laid out for) changes.
#[inline(always)]
fn fill<const AVX2: bool>(g: &Geom, x: &[f32], buf: &mut Vec<f32>, shape: &mut Option<[usize; 4]>) {
    let key = [g.h, g.w, g.k, g.s];
    if *shape != Some(key) {
        buf.clear();
        // HALF values of slack: the forward pass reads a row's last partial block a whole
        // register wide (see forward_rows).
        buf.resize(g.scratch_len() + HALF, 0.0);
        *shape = Some(key);
    }
    let (p, s, cw, w) = (g.pad(), g.s, g.cw(), g.w);
    for (iy, row) in x.chunks_exact(w).enumerate() {
        let r = iy + p;
        if s == 1 {
            copy_run(&mut buf[r * cw + p..][..w], row);
            continue;
        }
        if s == 2 {
            // Column pairs of the input row go to the two phases (the generic step_by copy
            // below made the stride-2 forward benches 1.3–2.2× slower).
            let (row0, row1) = buf[r * 2 * cw..][..2 * cw].split_at_mut(cw);
            // Input column 0 lands in phase p mod 2 at phase column p / 2.
            let (a, b) = if p % 2 == 0 {
                (row0, row1)
            } else {
                (row1, row0)
            };
            let (a, b) = (
                &mut a[p / 2..][..w.div_ceil(2)],
                &mut b[p.div_ceil(2)..][..w / 2],
            );
            if w % 2 == 1 {
                a[w / 2] = row[w - 1];
            }
            let a = &mut a[..w / 2];
            // Sixteen inputs to eight of each phase at a time: with AVX2, two shuffles and two
            // lane permutes (the compiler left any loop over pairs scalar, one load and store
            // per value: 40 % of a stride-2 16×16 plane's forward pass).
            let mut blocks = row.chunks_exact(2 * HALF);
            let mut xa = a.chunks_exact_mut(HALF);
            let mut xb = b.chunks_exact_mut(HALF);
            for ((pr, x), y) in (&mut blocks).zip(&mut xa).zip(&mut xb) {
                let pr: &[f32; 2 * HALF] = pr.try_into().expect("block of 2·HALF");
                let x: &mut [f32; HALF] = x.try_into().expect("block of HALF");
                let y: &mut [f32; HALF] = y.try_into().expect("block of HALF");
                #[cfg(target_arch = "x86_64")]
                if AVX2 {
                    // SAFETY: AVX2 is enabled wherever this is instantiated with AVX2 = true
                    // (the `_fma` entry points); the arrays hold 16 and 8 values.
                    unsafe { deinterleave_avx2(pr, x, y) };
                    continue;
                }
                for i in 0..HALF {
                    x[i] = pr[2 * i];
                    y[i] = pr[2 * i + 1];
                }
            }
            let (x, y) = (xa.into_remainder(), xb.into_remainder());
            for ((pr, x), y) in blocks.remainder().chunks_exact(2).zip(x).zip(y) {
                *x = pr[0];
                *y = pr[1];
            }
            continue;
        }
        for q in 0..s {
            let (first, j0) = phase_start(q, p, s);
            let dst = &mut buf[(r * s + q) * cw..][..cw];
            if let (Some(d), Some(src)) = (dst.get_mut(j0..), row.get(first..)) {
                for (d, &v) in d.iter_mut().zip(src.iter().step_by(s)) {
                    *d = v;
                }
            }
        }
    }
}

/// `dst` ← `src` (equal lengths) in register-wide pieces: rows are short (16–160 values), and a
/// call to `memmove` per row cost a sixth of a 16×16 plane's forward pass.
#[inline(always)]
fn copy_run(dst: &mut [f32], src: &[f32]) {
    let mut d = dst.chunks_exact_mut(HALF);
    let mut s = src.chunks_exact(HALF);
    for (d, s) in (&mut d).zip(&mut s) {
        let v: [f32; HALF] = s.try_into().expect("chunk of HALF");
        d.copy_from_slice(&v);
    }
    for (d, &v) in d.into_remainder().iter_mut().zip(s.remainder()) {
        *d = v;
    }
}

/// Even and odd values of `pr` into `x` and `y`.
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn deinterleave_avx2(pr: &[f32; 2 * HALF], x: &mut [f32; HALF], y: &mut [f32; HALF]) {
    use std::arch::x86_64::*;
    // SAFETY: AVX2 by the contract; unaligned loads and stores of exactly the arrays' 8 values.
    unsafe {
        let lo = _mm256_loadu_ps(pr.as_ptr());
        let hi = _mm256_loadu_ps(pr.as_ptr().add(HALF));
        // Per 128-bit lane: [lo0 lo2 hi0 hi2 | lo4 lo6 hi4 hi6]; the 64-bit permute (0 2 1 3)
        // puts the pairs in order.
        let ev = _mm256_shuffle_ps::<0b10_00_10_00>(lo, hi);
        let od = _mm256_shuffle_ps::<0b11_01_11_01>(lo, hi);
        let ev = _mm256_castpd_ps(_mm256_permute4x64_pd::<0b11_01_10_00>(_mm256_castps_pd(ev)));
        let od = _mm256_castpd_ps(_mm256_permute4x64_pd::<0b11_01_10_00>(_mm256_castps_pd(od)));
        _mm256_storeu_ps(x.as_mut_ptr(), ev);
        _mm256_storeu_ps(y.as_mut_ptr(), od);
    }
}

/// `x` and `y` interleaved into `pr` (the inverse of [`deinterleave_avx2`]).
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn interleave_avx2(x: &[f32; HALF], y: &[f32; HALF], pr: &mut [f32; 2 * HALF]) {
    use std::arch::x86_64::*;
    // SAFETY: AVX2 by the contract; unaligned loads and stores of exactly the arrays' values.
    unsafe {
        let ev = _mm256_loadu_ps(x.as_ptr());
        let od = _mm256_loadu_ps(y.as_ptr());
        // Per 128-bit lane: [e0 o0 e1 o1 | e4 o4 e5 o5] and [e2 o2 e3 o3 | e6 o6 e7 o7].
        let lo = _mm256_unpacklo_ps(ev, od);
        let hi = _mm256_unpackhi_ps(ev, od);
        _mm256_storeu_ps(pr.as_mut_ptr(), _mm256_permute2f128_ps::<0x20>(lo, hi));
        _mm256_storeu_ps(
            pr.as_mut_ptr().add(HALF),
            _mm256_permute2f128_ps::<0x31>(lo, hi),
        );
    }
}

/// Phase `q` of a padded row (pad `p`, stride `s`) starts at input column `first` (the first
/// with (first + p) mod s = q), stored at phase column `j0` = (first + p) / s.
#[inline(always)]
fn phase_start(q: usize, p: usize, s: usize) -> (usize, usize) {
    let first = (q + s - p % s) % s;
    (first, (first + p) / s)
}

/// The inverse of [`fill`] on the interior: padded, phase-split `buf` → plane `x`.
#[inline(always)]
fn unfill<const AVX2: bool>(g: &Geom, buf: &[f32], x: &mut [f32]) {
    let (p, s, cw, w) = (g.pad(), g.s, g.cw(), g.w);
    for (iy, row) in x.chunks_exact_mut(w).enumerate() {
        let r = iy + p;
        if s == 1 {
            row.copy_from_slice(&buf[r * cw + p..][..w]);
            continue;
        }
        if s == 2 {
            // The inverse of fill's column pairs.
            let (row0, row1) = buf[r * 2 * cw..][..2 * cw].split_at(cw);
            let (a, b) = if p % 2 == 0 {
                (row0, row1)
            } else {
                (row1, row0)
            };
            let (a, b) = (&a[p / 2..][..w.div_ceil(2)], &b[p.div_ceil(2)..][..w / 2]);
            if w % 2 == 1 {
                row[w - 1] = a[w / 2];
            }
            let a = &a[..w / 2];
            // Eight of each phase to sixteen outputs at a time, as in `fill`.
            let mut blocks = row.chunks_exact_mut(2 * HALF);
            let mut xa = a.chunks_exact(HALF);
            let mut xb = b.chunks_exact(HALF);
            for ((pr, x), y) in (&mut blocks).zip(&mut xa).zip(&mut xb) {
                let pr: &mut [f32; 2 * HALF] = pr.try_into().expect("block of 2·HALF");
                let x: &[f32; HALF] = x.try_into().expect("block of HALF");
                let y: &[f32; HALF] = y.try_into().expect("block of HALF");
                #[cfg(target_arch = "x86_64")]
                if AVX2 {
                    // SAFETY: as in `fill`.
                    unsafe { interleave_avx2(x, y, pr) };
                    continue;
                }
                for i in 0..HALF {
                    pr[2 * i] = x[i];
                    pr[2 * i + 1] = y[i];
                }
            }
            let (x, y) = (xa.remainder(), xb.remainder());
            for ((pr, &x), &y) in blocks.into_remainder().chunks_exact_mut(2).zip(x).zip(y) {
                pr[0] = x;
                pr[1] = y;
            }
            continue;
        }
        for q in 0..s {
            let (first, j0) = phase_start(q, p, s);
            let src = &buf[(r * s + q) * cw..][..cw];
            if let (Some(src), Some(d)) = (src.get(j0..), row.get_mut(first..)) {
                for (d, &v) in d.iter_mut().step_by(s).zip(src) {
                    *d = v;
                }
            }
        }
    }
}

/// Offset of tap (ky, kx) from the start of output row 0's input window, per tap; output row
/// `oy` adds `oy · s² · cw`.
#[inline(always)]
fn tap_offsets(g: &Geom, offs: &mut Vec<usize>) {
    offs.clear();
    let (s, cw) = (g.s, g.cw());
    for ky in 0..g.k {
        for kx in 0..g.k {
            offs.push((ky * s + kx % s) * cw + kx / s);
        }
    }
}

/// Per-task scratch: the padded plane, its gradient, the tap offsets and the turned kernel.
#[derive(Default)]
pub(crate) struct Scratch {
    buf: Vec<f32>,
    /// The geometry (h, w, k, s) `buf`'s zero padding is laid out for.
    shape: Option<[usize; 4]>,
    dbuf: Vec<f32>,
    /// dL/dy zero-padded for the strided dL/dx, and the geometry (h, w, k, s) its padding is
    /// laid out for.
    dpad: Vec<f32>,
    dshape: Option<[usize; 4]>,
    offs: Vec<usize>,
    /// The kernel turned by 180° (stride-1 dL/dx) or one phase's sub-kernel (strided dL/dx).
    flip: Vec<f32>,
    /// A row of zeros, the padding rows of [`stride1`]'s dL/dx.
    zeros: Vec<f32>,
}

#[inline(always)]
fn forward_plane<const FMA: bool>(
    g: &Geom,
    x: &[f32],
    wk: &[f32],
    sc: &mut Scratch,
    out: &mut [f32],
) {
    fill::<FMA>(g, x, &mut sc.buf, &mut sc.shape);
    tap_offsets(g, &mut sc.offs);
    forward_padded::<FMA>(g, &sc.buf, &sc.offs, wk, out);
}

/// The forward pass from a plane already in the padded scratch layout.
#[inline(always)]
fn forward_padded<const FMA: bool>(
    g: &Geom,
    buf: &[f32],
    offs: &[usize],
    wk: &[f32],
    out: &mut [f32],
) {
    let sw = Sweep {
        rows: g.ho,
        in_step: g.s * g.s * g.cw(),
        out_step: g.wo,
        cols: (0, g.wo),
    };
    sweep::<FMA>(&sw, buf, offs, wk, out);
}

/// A correlation over a rectangle of outputs: output row `m`, column `j` (`cols.0 ≤ j <
/// cols.1`) is `Σₜ wk[t]·buf[m·in_step + offs[t] + j]`, stored at `out[m·out_step + j]`.
#[derive(Clone, Copy, Debug)]
struct Sweep {
    rows: usize,
    in_step: usize,
    out_step: usize,
    cols: (usize, usize),
}

/// Every output of `sw`, its taps summed in `offs` order.
#[inline(always)]
fn sweep<const FMA: bool>(sw: &Sweep, buf: &[f32], offs: &[usize], wk: &[f32], out: &mut [f32]) {
    let (lo, end) = sw.cols;
    if sw.rows == 0 || lo >= end {
        return;
    }
    // One bounds check per sweep for every tap read of the blocks below: the furthest is the
    // last row's largest tap offset plus the columns rounded up to whole HALF blocks.
    let reach = offs
        .iter()
        .max()
        .map_or(0, |&m| m + lo + (end - lo).next_multiple_of(HALF));
    assert!(
        (sw.rows - 1) * sw.in_step + reach <= buf.len(),
        "depthwise scratch too short for {sw:?}"
    );
    assert!((sw.rows - 1) * sw.out_step + end <= out.len() && wk.len() >= offs.len());
    // Several output rows per pass keep eight accumulator registers in flight (one row's
    // chain of k² fused multiply–adds alone is latency-bound, and more rows share each
    // weight's broadcast); each output still sums its taps in the same order, so the result
    // is the same bit for bit.
    let mut m = 0;
    // SAFETY (all three calls): rows m .. m + R ≤ rows, checked against `buf` and `out` above.
    while m + 4 <= sw.rows {
        unsafe { sweep_rows::<FMA, 4>(sw, buf, offs, wk, m, out) };
        m += 4;
    }
    while m + 2 <= sw.rows {
        unsafe { sweep_rows::<FMA, 2>(sw, buf, offs, wk, m, out) };
        m += 2;
    }
    if m < sw.rows {
        unsafe { sweep_rows::<FMA, 1>(sw, buf, offs, wk, m, out) };
    }
}

/// `N` values of `buf` from `at`, unchecked.
///
/// # Safety
/// `at + N ≤ buf.len()`.
#[inline(always)]
unsafe fn run<const N: usize>(buf: &[f32], at: usize) -> &[f32; N] {
    // SAFETY: the caller keeps `at + N` inside `buf`; f32 has no alignment beyond 4.
    unsafe { &*(buf.as_ptr().add(at) as *const [f32; N]) }
}

/// Output rows `m .. m + R` of `sw`.
///
/// # Safety
/// `m + R ≤ sw.rows`, and the reads and writes of those rows are inside `buf` and `out`, the
/// columns rounded up to whole HALF blocks on the read side (checked once by [`sweep`]); `wk`
/// holds one weight per offset.
#[inline(always)]
unsafe fn sweep_rows<const FMA: bool, const R: usize>(
    sw: &Sweep,
    buf: &[f32],
    offs: &[usize],
    wk: &[f32],
    m: usize,
    out: &mut [f32],
) {
    let ((lo, end), in_step, out_step) = (sw.cols, sw.in_step, sw.out_step);
    let base = m * in_step;
    #[cfg(target_arch = "x86_64")]
    if FMA {
        // LLVM left the one-register blocks below scalar, accumulators spilled to the stack
        // (65 % of the max subnet's forward samples at 278×174 were scalar FMAs); written
        // with intrinsics they are the same fused multiply–adds in the same order.
        let mut x0 = lo;
        while x0 < end {
            // SAFETY: FMA = true only inside the avx2+fma entry points; rows and reach are
            // this function's contract, each block reads at most the columns rounded up to
            // HALF.
            unsafe {
                if x0 + LANES <= end {
                    block_fma::<R, 2>(sw, buf, offs, wk, (m, x0), out);
                    x0 += LANES;
                } else {
                    block_fma::<R, 1>(sw, buf, offs, wk, (m, x0), out);
                    x0 += HALF;
                }
            }
        }
        return;
    }
    let mut x0 = lo;
    while x0 + LANES <= end {
        let mut acc = [[0.0f32; LANES]; R];
        for (&wv, &off) in wk.iter().zip(offs) {
            for (r, acc) in acc.iter_mut().enumerate() {
                // SAFETY: row m + r < rows and x0 + LANES ≤ end (see the contract).
                let src = unsafe { run::<LANES>(buf, base + r * in_step + off + x0) };
                for (a, &v) in acc.iter_mut().zip(src) {
                    *a = madd::<FMA>(wv, v, *a);
                }
            }
        }
        for (r, acc) in acc.iter().enumerate() {
            out[(m + r) * out_step + x0..][..LANES].copy_from_slice(acc);
        }
        x0 += LANES;
    }
    // Rows narrower than LANES (stride-2 layers at the low resolutions) and the last partial
    // block: a whole register per row, the lanes past `end` computed from whatever the scratch
    // holds there and dropped.
    while x0 < end {
        let mut acc = [[0.0f32; HALF]; R];
        for (&wv, &off) in wk.iter().zip(offs) {
            for (r, acc) in acc.iter_mut().enumerate() {
                // SAFETY: x0 + HALF ≤ the columns rounded up to HALF, inside the reach checked.
                let src = unsafe { run::<HALF>(buf, base + r * in_step + off + x0) };
                for (a, &v) in acc.iter_mut().zip(src) {
                    *a = madd::<FMA>(wv, v, *a);
                }
            }
        }
        let cols = (end - x0).min(HALF);
        for (r, acc) in acc.iter().enumerate() {
            out[(m + r) * out_step + x0..][..cols].copy_from_slice(&acc[..cols]);
        }
        x0 += HALF;
    }
}

/// Output rows `m .. m + R` of `sw`, columns `x0 .. min(x0 + V·HALF, sw.cols.1)`: each output
/// sums its taps in `offs` order by fused multiply–adds, R·V registers in flight.
///
/// # Safety
/// The CPU must have AVX2 and FMA; `(m + R − 1)·in_step + max(offs) + x0 + V·HALF ≤
/// buf.len()`; `out` holds `(m + R − 1)·out_step + sw.cols.1` values, `wk` one weight per
/// offset.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn block_fma<const R: usize, const V: usize>(
    sw: &Sweep,
    buf: &[f32],
    offs: &[usize],
    wk: &[f32],
    (m, x0): (usize, usize),
    out: &mut [f32],
) {
    use std::arch::x86_64::*;
    let mut acc = [[_mm256_setzero_ps(); V]; R];
    let (p, end, in_step, out_step) = (buf.as_ptr(), sw.cols.1, sw.in_step, sw.out_step);
    for (&wv, &off) in wk.iter().zip(offs) {
        let w = _mm256_set1_ps(wv);
        for (r, acc) in acc.iter_mut().enumerate() {
            // SAFETY: inside `buf` by the contract.
            let src = unsafe { p.add((m + r) * in_step + off + x0) };
            for (v, a) in acc.iter_mut().enumerate() {
                // SAFETY: as above; unaligned loads.
                *a = _mm256_fmadd_ps(w, unsafe { _mm256_loadu_ps(src.add(v * HALF)) }, *a);
            }
        }
    }
    let cols = (end - x0).min(V * HALF);
    if cols == V * HALF {
        for (r, acc) in acc.iter().enumerate() {
            let dst = &mut out[(m + r) * out_step + x0..][..V * HALF];
            for (v, a) in acc.iter().enumerate() {
                // SAFETY: HALF values at v·HALF inside `dst`, whose length was checked.
                unsafe { _mm256_storeu_ps(dst.as_mut_ptr().add(v * HALF), *a) };
            }
        }
        return;
    }
    for (r, acc) in acc.iter().enumerate() {
        let mut lanes = [[0.0f32; HALF]; V];
        for (l, a) in lanes.iter_mut().zip(acc) {
            // SAFETY: a store of exactly HALF values into `l`.
            unsafe { _mm256_storeu_ps(l.as_mut_ptr(), *a) };
        }
        out[(m + r) * out_step + x0..][..cols].copy_from_slice(&lanes.as_flattened()[..cols]);
    }
}

/// dL/dx of one plane into `dx`, dL/dw of its k² taps into `dw` (overwritten).
#[inline(always)]
fn backward_plane<const FMA: bool>(
    g: &Geom,
    x: &[f32],
    wk: &[f32],
    dy: &[f32],
    sc: &mut Scratch,
    dx: &mut [MaybeUninit<f32>],
    dw: &mut [f32],
) {
    plane_weight_grad::<FMA>(g, x, dy, sc, dw);
    if g.s == 1 {
        // At stride 1 with same padding, dL/dx is dL/dy correlated with the kernel turned by
        // 180°, on the same geometry (ho = h, wo = w): the forward pass's register-blocked
        // rows instead of a scatter that loads and stores dL/dx once per tap.
        sc.flip.clear();
        sc.flip.extend(wk.iter().rev());
        #[cfg(target_arch = "x86_64")]
        if FMA && stride1::takes(g) {
            // The same sums in the same order, read from dL/dy itself: no padded copy.
            sc.zeros.resize(g.w, 0.0);
            let flip: &[f32; 9] = sc.flip[..].try_into().expect("3×3 at stride 1");
            // SAFETY: FMA = true only inside the avx2+fma entry points; dy and dx hold h·w
            // values at stride 1 with same padding.
            unsafe { stride1::plane(g.h, g.w, dy, flip, &sc.zeros, dx) };
            return;
        }
        let dx = zeroed_chunk(dx);
        fill::<FMA>(g, dy, &mut sc.buf, &mut sc.shape);
        forward_padded::<FMA>(g, &sc.buf, &sc.offs, &sc.flip, dx);
        return;
    }
    strided_dx::<FMA>(g, wk, dy, sc, zeroed_chunk(dx));
}

/// dL/dw of one plane's k² taps into `dw` (overwritten), from its input `x` padded into the
/// scratch and dL/dy.
#[inline(always)]
fn plane_weight_grad<const FMA: bool>(
    g: &Geom,
    x: &[f32],
    dy: &[f32],
    sc: &mut Scratch,
    dw: &mut [f32],
) {
    fill::<FMA>(g, x, &mut sc.buf, &mut sc.shape);
    tap_offsets(g, &mut sc.offs);
    weight_grad::<FMA>(g, &sc.buf, &sc.offs, dy, dw);
}

/// dL/dx of one plane at stride s ≥ 2, as s² stride-1 correlations of dL/dy, one per phase.
///
/// Padded input cell (r, c) = (s·oy + ky, s·ox + kx) takes w[ky, kx]·dL/dy[oy, ox], so the
/// cells of one phase (r mod s, c mod s) = (ρ, γ) see only the taps ky ≡ ρ, kx ≡ γ, each at a
/// fixed offset in dL/dy: a dense correlation with that sub-kernel, written once per cell
/// into the phase-split scratch layout that [`unfill`] reads (a scatter instead loads and
/// stores every cell once per tap). Each cell sums its taps in (ky, kx) order, the order of
/// the scatter, with zero padding adding exact zeros: the same bits.
#[inline(always)]
fn strided_dx<const FMA: bool>(g: &Geom, wk: &[f32], dy: &[f32], sc: &mut Scratch, dx: &mut [f32]) {
    let (p, s, cw) = (g.pad(), g.s, g.cw());
    let (hp, wp) = g.strided_dy_extent();
    let key = [g.h, g.w, g.k, g.s];
    if sc.dshape != Some(key) {
        sc.dpad.clear();
        // HALF values of slack: a row's last partial block is read a whole register wide.
        sc.dpad.resize(hp * wp + HALF, 0.0);
        sc.dshape = Some(key);
    }
    for (oy, row) in dy.chunks_exact(g.wo).take(g.ho).enumerate() {
        copy_run(&mut sc.dpad[(oy + p) * wp + p..][..g.wo], row);
    }
    // Every interior cell is written below and unfill reads only those: no zeroing.
    if sc.dbuf.len() != g.scratch_len() {
        sc.dbuf.resize(g.scratch_len(), 0.0);
    }
    for rho in 0..s {
        let (m0, m1) = g.phase_span(rho, g.h);
        for gamma in 0..s {
            let (j0, j1) = g.phase_span(gamma, g.w);
            sc.offs.clear();
            sc.flip.clear();
            for (t, off) in g.phase_taps((rho, gamma), wp) {
                sc.offs.push(off);
                sc.flip.push(wk[t]);
            }
            let sw = Sweep {
                rows: m1.saturating_sub(m0),
                in_step: wp,
                out_step: s * s * cw,
                cols: (j0, j1),
            };
            if sw.rows == 0 {
                continue;
            }
            let out = &mut sc.dbuf[m0 * s * s * cw + (rho * s + gamma) * cw..];
            sweep::<FMA>(&sw, &sc.dpad[m0 * wp..], &sc.offs, &sc.flip, out);
        }
    }
    unfill::<FMA>(g, &sc.dbuf, dx);
}

/// Most taps whose weight gradients one pass over dL/dy accumulates side by side.
const TAPS: usize = 8;

/// dL/dw of one plane (k² taps, overwritten) from the padded input `buf` and dL/dy.
///
/// Taps go in near-equal groups of at most [`TAPS`]: each block of dL/dy is loaded once per
/// group, and the group's lane sums are independent chains (one tap's chain of fused
/// multiply–adds alone waits on its own latency).
#[inline(always)]
fn weight_grad<const FMA: bool>(g: &Geom, buf: &[f32], offs: &[usize], dy: &[f32], dw: &mut [f32]) {
    let kk = offs.len();
    let per = kk.div_ceil(kk.div_ceil(TAPS));
    for (d, o) in dw.chunks_mut(per).zip(offs.chunks(per)) {
        match o.len() {
            1 => tap_group::<FMA, 1>(g, buf, o, dy, d),
            2 => tap_group::<FMA, 2>(g, buf, o, dy, d),
            3 => tap_group::<FMA, 3>(g, buf, o, dy, d),
            4 => tap_group::<FMA, 4>(g, buf, o, dy, d),
            5 => tap_group::<FMA, 5>(g, buf, o, dy, d),
            6 => tap_group::<FMA, 6>(g, buf, o, dy, d),
            7 => tap_group::<FMA, 7>(g, buf, o, dy, d),
            _ => tap_group::<FMA, 8>(g, buf, o, dy, d),
        }
    }
}

/// Weight gradients of `T` taps (offsets `offs`) into `dw`.
#[inline(always)]
fn tap_group<const FMA: bool, const T: usize>(
    g: &Geom,
    buf: &[f32],
    offs: &[usize],
    dy: &[f32],
    dw: &mut [f32],
) {
    let (wo, row_step) = (g.wo, g.s * g.s * g.cw());
    let offs: [usize; T] = std::array::from_fn(|t| offs[t]);
    let mut lanes = [[0.0f32; HALF]; T];
    let mut rest = [0.0f32; T];
    let x0 = wo - wo % HALF;
    #[cfg(target_arch = "x86_64")]
    if FMA {
        // The blocks as the forward's (the loop below reloaded each block of dL/dy once per
        // tap, two loads per multiply–add), and a row's last partial block as one masked
        // register (the loop below's scalar tail was, at the main job's widths 35 and 70, a
        // tenth of the columns at an eighth of the speed).
        let reach = offs.iter().max().map_or(0, |&m| m + wo);
        assert!(g.ho == 0 || (g.ho - 1) * row_step + reach <= buf.len() && dy.len() >= g.ho * wo);
        // SAFETY: FMA = true only inside the avx2+fma entry points; the reads are inside
        // `buf` and `dy` by the assertion.
        unsafe { tap_lanes_fma::<T>(buf, &offs, dy, (g.ho, wo, row_step), &mut lanes) };
        for t in 0..T {
            dw[t] = lanes[t].iter().sum::<f32>();
        }
        return;
    }
    for (oy, grow) in dy.chunks_exact(wo).enumerate() {
        let row = &buf[oy * row_step..];
        for (b, gb) in grow.chunks_exact(HALF).enumerate() {
            for t in 0..T {
                let src = &row[offs[t] + b * HALF..][..HALF];
                for l in 0..HALF {
                    lanes[t][l] = madd::<FMA>(gb[l], src[l], lanes[t][l]);
                }
            }
        }
        for (j, &gv) in grow[x0..].iter().enumerate() {
            for t in 0..T {
                rest[t] = madd::<FMA>(gv, row[offs[t] + x0 + j], rest[t]);
            }
        }
    }
    for t in 0..T {
        dw[t] = lanes[t].iter().sum::<f32>() + rest[t];
    }
}

/// [`tap_group`] in registers: lane sums of dL/dy · x over every output row, per tap, into
/// `lanes`; a row's last `wo mod HALF` columns are one masked register.
///
/// # Safety
/// The CPU must have AVX2 and FMA; `(ho − 1)·row_step + max(offs) + wo ≤ buf.len()` and `dy`
/// holds ho·wo values.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn tap_lanes_fma<const T: usize>(
    buf: &[f32],
    offs: &[usize; T],
    dy: &[f32],
    (ho, wo, row_step): (usize, usize, usize),
    lanes: &mut [[f32; HALF]; T],
) {
    use std::arch::x86_64::*;
    let mut acc = [_mm256_setzero_ps(); T];
    let (p, q) = (buf.as_ptr(), dy.as_ptr());
    let (x0, rem) = (wo - wo % HALF, (wo % HALF) as i32);
    // Lanes below `rem`; the others read nothing and load zeros, which add exact zeros.
    let mask = _mm256_cmpgt_epi32(
        _mm256_set1_epi32(rem),
        _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7),
    );
    for oy in 0..ho {
        for b in 0..wo / HALF {
            // SAFETY: inside `dy` and `buf` by the contract; unaligned loads.
            unsafe {
                let gb = _mm256_loadu_ps(q.add(oy * wo + b * HALF));
                let row = p.add(oy * row_step + b * HALF);
                for (a, &o) in acc.iter_mut().zip(offs) {
                    *a = _mm256_fmadd_ps(gb, _mm256_loadu_ps(row.add(o)), *a);
                }
            }
        }
        if rem > 0 {
            // SAFETY: the unmasked lanes are inside `dy` and `buf` by the contract.
            unsafe {
                let gb = _mm256_maskload_ps(q.add(oy * wo + x0), mask);
                let row = p.add(oy * row_step + x0);
                for (a, &o) in acc.iter_mut().zip(offs) {
                    *a = _mm256_fmadd_ps(gb, _mm256_maskload_ps(row.add(o), mask), *a);
                }
            }
        }
    }
    for (l, a) in lanes.iter_mut().zip(&acc) {
        // SAFETY: a store of exactly HALF values into `l`.
        unsafe { _mm256_storeu_ps(l.as_mut_ptr(), *a) };
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn forward_plane_fma(g: &Geom, x: &[f32], wk: &[f32], sc: &mut Scratch, out: &mut [f32]) {
    forward_plane::<true>(g, x, wk, sc, out)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn backward_plane_fma(
    g: &Geom,
    x: &[f32],
    wk: &[f32],
    dy: &[f32],
    sc: &mut Scratch,
    dx: &mut [MaybeUninit<f32>],
    dw: &mut [f32],
) {
    backward_plane::<true>(g, x, wk, dy, sc, dx, dw)
}

/// `out` zeroed and handed back as initialised values: the paths that write through
/// `&mut [f32]` zero their own chunk just before writing it, while it is in cache (a
/// separate pass over a fresh output moved its bytes twice).
fn zeroed_chunk(out: &mut [MaybeUninit<f32>]) -> &mut [f32] {
    out.fill(MaybeUninit::new(0.0));
    // SAFETY: every element was just written; MaybeUninit<f32> has f32's layout.
    unsafe { &mut *(out as *mut [MaybeUninit<f32>] as *mut [f32]) }
}

/// Initialised values seen as possibly uninitialised, for the entry points that take an
/// output they overwrite whole (the tests hand them NaNs, so a value left unwritten shows).
///
/// # Safety
/// Whoever writes through the result writes initialised values only.
#[cfg(test)]
unsafe fn as_uninit(s: &mut [f32]) -> &mut [MaybeUninit<f32>] {
    // SAFETY: same layout; the caller keeps every element initialised.
    unsafe { &mut *(s as *mut [f32] as *mut [MaybeUninit<f32>]) }
}

/// Whether this CPU has AVX2 and FMA (the fused code paths).
pub(crate) fn has_fma() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// Forward over all planes: `x` is N·C planes of h×w, `w` C kernels of k², `y` N·C planes of
/// ho×wo, every value written (so it may start uninitialised). Shapes are the caller's to
/// check.
pub(crate) fn forward(g: &Geom, c: usize, x: &[f32], w: &[f32], y: &mut [MaybeUninit<f32>]) {
    let (hw, howo, kk) = (g.h * g.w, g.ho * g.wo, g.k * g.k);
    if howo == 0 || hw == 0 {
        y.fill(MaybeUninit::new(0.0));
        return;
    }
    // Whole planes, one output plane per input plane: every path below writes y plane by
    // plane.
    assert!(x.len().is_multiple_of(hw) && y.len() == howo * (x.len() / hw));
    #[cfg(target_arch = "x86_64")]
    if rows16::takes(g) {
        rows16::forward(g, c, x, w, y);
        return;
    }
    #[cfg(target_arch = "x86_64")]
    if rows8::takes(g) {
        rows8::forward(g, c, x, w, y);
        return;
    }
    #[cfg(target_arch = "x86_64")]
    if rows4::takes(g) {
        rows4::forward(g, c, x, w, y);
        return;
    }
    #[cfg(target_arch = "x86_64")]
    if channels::takes(g, c) && !stride2::preferred(g, false) {
        channels::forward(g, c, x, w, y);
        return;
    }
    #[cfg(target_arch = "x86_64")]
    if stride1::takes(g) {
        stride1::forward(g, c, x, w, y);
        return;
    }
    #[cfg(target_arch = "x86_64")]
    if stride2::takes(g) {
        stride2::forward(g, c, x, w, y);
        return;
    }
    let fma = has_fma();
    y.par_chunks_mut(howo)
        .enumerate()
        .with_min_len(g.planes_per_task())
        .for_each_init(Scratch::default, |sc, (idx, out)| {
            let out = zeroed_chunk(out);
            let xp = &x[idx * hw..][..hw];
            let wk = &w[(idx % c) * kk..][..kk];
            #[cfg(target_arch = "x86_64")]
            if fma {
                // SAFETY: AVX2 and FMA were detected on this CPU just above.
                unsafe { forward_plane_fma(g, xp, wk, sc, out) };
                return;
            }
            let _ = fma;
            forward_plane::<false>(g, xp, wk, sc, out)
        });
}

/// Backward over all planes: dL/dx into `dx` (N·C planes of h×w, every value written, so it
/// may start uninitialised) and per-plane dL/dw into `dw_planes` (N·C blocks of k²,
/// overwritten; the caller sums over images in a fixed order so the result does not depend on
/// the thread count).
pub(crate) fn backward(
    g: &Geom,
    c: usize,
    x: &[f32],
    w: &[f32],
    dy: &[f32],
    dx: &mut [MaybeUninit<f32>],
    dw_planes: &mut [f32],
) {
    let (hw, howo, kk) = (g.h * g.w, g.ho * g.wo, g.k * g.k);
    if hw == 0 || howo == 0 {
        dx.fill(MaybeUninit::new(0.0));
        dw_planes.fill(0.0);
        return;
    }
    // Whole planes that pair one to one with the weight gradients' blocks: every path below
    // zips the two, and a plane of dL/dx left out of the zip would stay unwritten.
    assert!(dx.len() == x.len() && dx.len().is_multiple_of(hw));
    assert!(dw_planes.len() == kk * (dx.len() / hw) && dy.len() == howo * (dx.len() / hw));
    #[cfg(target_arch = "x86_64")]
    if rows16::takes(g) {
        rows16::backward(g, c, (x, w, dy), dx, dw_planes);
        return;
    }
    #[cfg(target_arch = "x86_64")]
    if rows8::takes(g) {
        rows8::backward(g, c, (x, w, dy), dx, dw_planes);
        return;
    }
    #[cfg(target_arch = "x86_64")]
    if channels::takes(g, c) && !stride2::preferred(g, true) {
        channels::backward(g, c, x, w, dy, dx, dw_planes);
        return;
    }
    #[cfg(target_arch = "x86_64")]
    if stride2::takes(g) {
        stride2::backward(g, c, (x, w, dy), dx, dw_planes);
        return;
    }
    let fma = has_fma();
    dx.par_chunks_mut(hw)
        .zip(dw_planes.par_chunks_mut(kk))
        .enumerate()
        .with_min_len(g.planes_per_task())
        .for_each_init(Scratch::default, |sc, (idx, (dxp, dwp))| {
            let xp = &x[idx * hw..][..hw];
            let g_ = &dy[idx * howo..][..howo];
            let wk = &w[(idx % c) * kk..][..kk];
            #[cfg(target_arch = "x86_64")]
            if fma {
                // SAFETY: AVX2 and FMA were detected on this CPU just above.
                unsafe { backward_plane_fma(g, xp, wk, g_, sc, dxp, dwp) };
                return;
            }
            let _ = fma;
            backward_plane::<false>(g, xp, wk, g_, sc, dxp, dwp)
        });
}

/// A k×k forward (KK = k² taps) over every plane of `x` (`c` channels) into `y`:
/// `plane(h, ho, x, wk, out)` computes one plane's `ho` output rows from its `h` input rows
/// and k² taps.
#[cfg(target_arch = "x86_64")]
fn forward_planes<const KK: usize>(
    g: &Geom,
    c: usize,
    (x, w): (&[f32], &[f32]),
    y: &mut [MaybeUninit<f32>],
    plane: impl Fn(usize, usize, &[f32], &[f32; KK], &mut [MaybeUninit<f32>]) + Sync,
) {
    let (hw, howo) = (g.h * g.w, g.ho * g.wo);
    assert!(g.k * g.k == KK && x.len() / hw == y.len() / howo && w.len() == KK * c);
    y.par_chunks_mut(howo)
        .enumerate()
        .with_min_len(g.planes_per_task())
        .for_each(|(idx, out)| {
            let xp = &x[idx * hw..][..hw];
            let wk: &[f32; KK] = w[(idx % c) * KK..][..KK].try_into().expect("k² taps");
            plane(g.h, g.ho, xp, wk, out);
        });
}

/// One plane's k×k backward (KK = k² taps): (h, ho, (x, taps, dy), dx, dw, scratch).
#[cfg(target_arch = "x86_64")]
type BackwardPlane<'a, const KK: usize> = dyn Fn(
        usize,
        usize,
        (&[f32], &[f32; KK], &[f32]),
        &mut [MaybeUninit<f32>],
        &mut [f32; KK],
        &mut Scratch,
    ) + Sync
    + 'a;

/// A k×k backward (KK = k² taps) over every plane: dL/dx into `dx`, each plane's k² weight
/// gradients into `dw_planes` (overwritten), `plane` doing one plane with a scratch of its
/// task's (left empty by the paths that need none).
#[cfg(target_arch = "x86_64")]
fn backward_planes<const KK: usize>(
    g: &Geom,
    c: usize,
    (x, w, dy): (&[f32], &[f32], &[f32]),
    (dx, dw_planes): (&mut [MaybeUninit<f32>], &mut [f32]),
    plane: &BackwardPlane<'_, KK>,
) {
    let (hw, howo) = (g.h * g.w, g.ho * g.wo);
    assert!(g.k * g.k == KK && x.len() == dx.len() && x.len().is_multiple_of(hw));
    assert!(x.len() / hw == dy.len() / howo);
    assert!(w.len() == KK * c && dw_planes.len() == KK * (x.len() / hw));
    dx.par_chunks_mut(hw)
        .zip(dw_planes.par_chunks_mut(KK))
        .enumerate()
        .with_min_len(g.planes_per_task())
        .for_each_init(Scratch::default, |sc, (idx, (dxp, dwp))| {
            let xp = &x[idx * hw..][..hw];
            let dyp = &dy[idx * howo..][..howo];
            let wk: &[f32; KK] = w[(idx % c) * KK..][..KK].try_into().expect("k² taps");
            let dwp: &mut [f32; KK] = dwp.try_into().expect("k² gradients");
            plane(g.h, g.ho, (xp, wk, dyp), dxp, dwp, sc);
        });
}

#[cfg(test)]
impl Geom {
    /// A 3×3 kernel at stride `s` (padding 1) on planes of h × w.
    fn k3(h: usize, w: usize, s: usize) -> Geom {
        Geom::kxk(h, w, 3, s)
    }
    /// A k×k kernel at stride `s` (padding k/2) on planes of h × w.
    fn kxk(h: usize, w: usize, k: usize, s: usize) -> Geom {
        use crate::conv::out_size;
        Geom {
            h,
            w,
            ho: out_size(h, k, s),
            wo: out_size(w, k, s),
            k,
            s,
        }
    }
}

/// A forward path's entry point: (geometry, channels, x, taps, y).
#[cfg(all(test, target_arch = "x86_64"))]
type ForwardPath = fn(&Geom, usize, &[f32], &[f32], &mut [MaybeUninit<f32>]);

/// Checks a k×k forward path at stride `s` for planes `w` wide against the plane path, bit for
/// bit: planes of 1–40 rows (odd and even, fewer rows than the kernel), values of both signs
/// and zeros, two images of three channels through `fwd`, the path's entry point.
#[cfg(all(test, target_arch = "x86_64"))]
fn assert_plane_path_bits((w, k, s): (usize, usize, usize), seed: u64, fwd: ForwardPath) {
    use rand::{Rng, SeedableRng, rngs::StdRng};
    let mut rng = StdRng::seed_from_u64(seed);
    let mut sc = Scratch::default();
    let kk = k * k;
    for h in 1..41 {
        let g = Geom::kxk(h, w, k, s);
        let (n, c) = (2, 3);
        let (hw, howo) = (w * h, g.wo * g.ho);
        let x: Vec<f32> = (0..n * c * hw)
            .map(|i| {
                if i % 7 == 0 {
                    0.0
                } else {
                    rng.random_range(-1.0..1.0)
                }
            })
            .collect();
        let wk: Vec<f32> = (0..c * kk).map(|_| rng.random_range(-1.0..1.0)).collect();
        let mut y = vec![f32::NAN; n * c * howo];
        // SAFETY: the paths write initialised values only.
        fwd(&g, c, &x, &wk, unsafe { as_uninit(&mut y) });
        for p in 0..n * c {
            let mut y0 = vec![f32::NAN; howo];
            // SAFETY: the callers run only where has_fma() holds.
            unsafe {
                forward_plane_fma(
                    &g,
                    &x[p * hw..][..hw],
                    &wk[(p % c) * kk..][..kk],
                    &mut sc,
                    &mut y0,
                )
            };
            for (i, (a, b)) in y[p * howo..][..howo].iter().zip(&y0).enumerate() {
                assert_eq!(
                    a.to_bits(),
                    b.to_bits(),
                    "y[{p}][{i}] {a} vs {b}, h {h}, w {w}, k {k}"
                );
            }
        }
    }
}

/// A k×k backward path at stride `s`, `bwd(g, c, (x, w, dy), dx, dw_planes)`, for planes `w`
/// wide against the plane path: planes of 1–40 rows, two images of three channels, values of
/// both signs and zeros. `exact`: the same bits. Otherwise its sums run in other orders, so
/// each path carries its own round-off: dL/dx is a sum of at most four products of numbers in
/// [−1, 1], ≤ 4·γ₄ ≈ 9.5e-7 off in each, so the two agree to 2e-6; dL/dw sums a plane's
/// ho·wo·(taps) products in chains of at most 27 operations, so they agree to
/// 4e-6 × (1 + Σ|dy|) (a misplaced term, ~0.25, is far beyond both).
#[cfg(all(test, target_arch = "x86_64"))]
#[allow(clippy::type_complexity)]
fn assert_plane_path_backward(
    (w, k, s): (usize, usize, usize),
    seed: u64,
    exact: bool,
    bwd: fn(&Geom, usize, (&[f32], &[f32], &[f32]), &mut [MaybeUninit<f32>], &mut [f32]),
) {
    // The tolerances below are the 3×3 kernel's.
    assert!(exact || k == 3, "inexact comparison for k = 3 only");
    use rand::{Rng, SeedableRng, rngs::StdRng};
    let mut rng = StdRng::seed_from_u64(seed);
    let mut sc = Scratch::default();
    let kk = k * k;
    // Exact paths get a second round with infinities among x and dy (one in 40): a product
    // of zero padding or of a masked lane with one is NaN, so a zero the path skips or a lane
    // it leaves unmasked shows, where with finite values adding ±0 to a sum changes nothing.
    let mut value = |i: usize, inf: bool| {
        if i.is_multiple_of(7) {
            0.0
        } else if inf && rng.random_range(0..40) == 0 {
            if i.is_multiple_of(2) {
                f32::INFINITY
            } else {
                f32::NEG_INFINITY
            }
        } else {
            rng.random_range(-1.0f32..1.0)
        }
    };
    let rounds = if exact {
        [false, true].as_slice()
    } else {
        &[false]
    };
    for (&inf, h) in rounds.iter().flat_map(|r| std::iter::repeat(r).zip(1..41)) {
        let g = Geom::kxk(h, w, k, s);
        let (n, c) = (2, 3);
        let (hw, howo) = (w * h, g.wo * g.ho);
        let x: Vec<f32> = (0..n * c * hw).map(|i| value(i, inf)).collect();
        let dy: Vec<f32> = (0..n * c * howo).map(|i| value(i, inf)).collect();
        let wk: Vec<f32> = (0..c * kk).map(|i| value(i, false)).collect();
        let mut dx = vec![f32::NAN; n * c * hw];
        let mut dw = vec![f32::NAN; n * c * kk];
        bwd(
            &g,
            c,
            (&x, &wk, &dy),
            // SAFETY: the paths write initialised values only.
            unsafe { as_uninit(&mut dx) },
            &mut dw,
        );
        for p in 0..n * c {
            let (mut dx0, mut dw0) = (vec![f32::NAN; hw], vec![f32::NAN; kk]);
            let dyp = &dy[p * howo..][..howo];
            // SAFETY: the callers run only where has_fma() holds.
            unsafe {
                backward_plane_fma(
                    &g,
                    &x[p * hw..][..hw],
                    &wk[(p % c) * kk..][..kk],
                    dyp,
                    &mut sc,
                    as_uninit(&mut dx0),
                    &mut dw0,
                )
            };
            if exact {
                let first = |a: &[f32], b: &[f32]| {
                    a.iter()
                        .zip(b)
                        .position(|(a, b)| a.to_bits() != b.to_bits())
                };
                let i = first(&dx[p * hw..][..hw], &dx0);
                assert!(
                    i.is_none(),
                    "dx[{p}][{i:?}] differs, h {h}, w {w}, k {k}, infinities {inf}"
                );
                let t = first(&dw[p * kk..][..kk], &dw0);
                assert!(
                    t.is_none(),
                    "dw[{p}][{t:?}] differs, h {h}, w {w}, k {k}, infinities {inf}"
                );
                continue;
            }
            for (i, (a, b)) in dx[p * hw..][..hw].iter().zip(&dx0).enumerate() {
                assert!((a - b).abs() <= 2e-6, "dx[{p}][{i}] {a} vs {b}, h {h}");
            }
            let tol = 4e-6 * (1.0 + dyp.iter().map(|v| v.abs()).sum::<f32>());
            for (t, (a, b)) in dw[p * kk..][..kk].iter().zip(&dw0).enumerate() {
                assert!((a - b).abs() <= tol, "dw[{p}][{t}] {a} vs {b}, h {h}");
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::conv::out_size;
    use rand::{Rng, SeedableRng, rngs::StdRng};

    /// Direct definition, f64: y[o] = Σ_t w[t]·x[o·s + t − p] with zeros outside.
    fn reference(g: &Geom, x: &[f32], wk: &[f32], dy: &[f32]) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
        let p = g.pad() as isize;
        let mut y = vec![0.0f64; g.ho * g.wo];
        let mut dx = vec![0.0f64; g.h * g.w];
        let mut dw = vec![0.0f64; g.k * g.k];
        for oy in 0..g.ho {
            for ox in 0..g.wo {
                for ky in 0..g.k {
                    for kx in 0..g.k {
                        let iy = (oy * g.s + ky) as isize - p;
                        let ix = (ox * g.s + kx) as isize - p;
                        if iy < 0 || ix < 0 || iy >= g.h as isize || ix >= g.w as isize {
                            continue;
                        }
                        let (i, t, o) = (
                            iy as usize * g.w + ix as usize,
                            ky * g.k + kx,
                            oy * g.wo + ox,
                        );
                        y[o] += wk[t] as f64 * x[i] as f64;
                        dx[i] += wk[t] as f64 * dy[o] as f64;
                        dw[t] += x[i] as f64 * dy[o] as f64;
                    }
                }
            }
        }
        (y, dx, dw)
    }

    /// The register paths for planes 4, 8 and 16 wide take only their own output height: a
    /// geometry claiming another goes to the plane path (their loops trust ho = ⌈h/2⌉, and
    /// ho = h for the 4-wide stride-1 path).
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn rows_paths_take_only_their_output_height() {
        if !has_fma() {
            return;
        }
        for w in [8, 16] {
            let g = Geom::k3(10, w, 2);
            assert!(rows8::takes(&g) || rows16::takes(&g));
            let other = Geom { ho: 3, ..g };
            assert!(!rows8::takes(&other) && !rows16::takes(&other));
        }
        let g = Geom::k3(10, 4, 1);
        assert!(rows4::takes(&g));
        for other in [Geom { ho: 3, ..g }, Geom { wo: 3, ..g }] {
            assert!(!rows4::takes(&other));
        }
    }

    /// Both code paths (plain and, where the CPU has it, FMA) against the direct definition
    /// on random shapes: tiny planes smaller than the kernel, odd and even sizes, rows shorter
    /// and longer than a register block, strides 1–3.
    #[test]
    fn planes_match_the_definition() {
        let mut rng = StdRng::seed_from_u64(7);
        // One scratch per code path for all cases, reused as the rayon tasks reuse theirs:
        // planes of a new geometry must not see the previous one's values.
        let mut scratch = [Scratch::default(), Scratch::default()];
        for case in 0..300 {
            let k = [1, 3, 5, 7][case % 4];
            let s = 1 + case % 3;
            let (h, w) = (rng.random_range(1..24), rng.random_range(1..41));
            let g = Geom {
                h,
                w,
                ho: out_size(h, k, s),
                wo: out_size(w, k, s),
                k,
                s,
            };
            let x: Vec<f32> = (0..h * w).map(|_| rng.random_range(-1.0..1.0)).collect();
            let wk: Vec<f32> = (0..k * k).map(|_| rng.random_range(-1.0..1.0)).collect();
            let dy: Vec<f32> = (0..g.ho * g.wo)
                .map(|_| rng.random_range(-1.0..1.0))
                .collect();
            let (y0, dx0, dw0) = reference(&g, &x, &wk, &dy);
            let close = |a: &[f32], b: &[f64], what: &str| {
                for (i, (&u, &v)) in a.iter().zip(b).enumerate() {
                    assert!(
                        (u as f64 - v).abs() < 1e-5 * (1.0 + v.abs()) * (k * k) as f64,
                        "{what}[{i}] {u} vs {v} in {g:?}"
                    );
                }
            };
            let mut runs: Vec<bool> = vec![false];
            if has_fma() {
                runs.push(true);
            }
            for fma in runs {
                let sc = &mut scratch[fma as usize];
                let mut y = vec![f32::NAN; g.ho * g.wo];
                let mut dx = vec![f32::NAN; h * w];
                let mut dw = vec![f32::NAN; k * k];
                // Another plane of the same geometry first: its values must not leak through.
                let other: Vec<f32> = x.iter().map(|v| 3.0 - v).collect();
                let mut y_other = vec![f32::NAN; g.ho * g.wo];
                if fma {
                    #[cfg(target_arch = "x86_64")]
                    // SAFETY: has_fma() checked the CPU.
                    unsafe {
                        forward_plane_fma(&g, &other, &wk, sc, &mut y_other)
                    };
                } else {
                    forward_plane::<false>(&g, &other, &wk, sc, &mut y_other);
                }
                if fma {
                    #[cfg(target_arch = "x86_64")]
                    // SAFETY: has_fma() checked the CPU.
                    unsafe {
                        forward_plane_fma(&g, &x, &wk, sc, &mut y);
                        backward_plane_fma(&g, &x, &wk, &dy, sc, as_uninit(&mut dx), &mut dw);
                    }
                } else {
                    forward_plane::<false>(&g, &x, &wk, sc, &mut y);
                    backward_plane::<false>(
                        &g,
                        &x,
                        &wk,
                        &dy,
                        sc,
                        // SAFETY: the paths write initialised values only.
                        unsafe { as_uninit(&mut dx) },
                        &mut dw,
                    );
                }
                close(&y, &y0, "y");
                // Blocking rows and lanes must not reorder the sum: every output adds its taps
                // in order, zero padding included, exactly as one scalar loop does.
                for oy in 0..g.ho {
                    for ox in 0..g.wo {
                        let mut acc = 0.0f32;
                        for ky in 0..k {
                            for kx in 0..k {
                                let (iy, ix) = (
                                    (oy * s + ky) as isize - (k / 2) as isize,
                                    (ox * s + kx) as isize - (k / 2) as isize,
                                );
                                let v = if (0..h as isize).contains(&iy)
                                    && (0..w as isize).contains(&ix)
                                {
                                    x[iy as usize * w + ix as usize]
                                } else {
                                    0.0
                                };
                                let wv = wk[ky * k + kx];
                                acc = if fma {
                                    wv.mul_add(v, acc)
                                } else {
                                    wv * v + acc
                                };
                            }
                        }
                        let got = y[oy * g.wo + ox];
                        assert_eq!(
                            got.to_bits(),
                            acc.to_bits(),
                            "y[{oy},{ox}] {got} vs {acc} in {g:?}"
                        );
                    }
                }
                close(&dx, &dx0, "dx");
                // dL/dx likewise sums each cell's taps in one fixed order: (ky, kx) descending
                // at stride 1 (the turned kernel), ascending at stride s ≥ 2 (the phases'
                // sub-kernels), zero padding adding exact zeros.
                let mut taps: Vec<(usize, usize)> = (0..k)
                    .flat_map(|ky| (0..k).map(move |kx| (ky, kx)))
                    .collect();
                if s == 1 {
                    taps.reverse();
                }
                for iy in 0..h {
                    for ix in 0..w {
                        let mut acc = 0.0f32;
                        for &(ky, kx) in &taps {
                            let (ny, nx) = (iy + k / 2, ix + k / 2);
                            if ny < ky || nx < kx || (ny - ky) % s != 0 || (nx - kx) % s != 0 {
                                continue;
                            }
                            let (oy, ox) = ((ny - ky) / s, (nx - kx) / s);
                            if oy >= g.ho || ox >= g.wo {
                                continue;
                            }
                            let (wv, v) = (wk[ky * k + kx], dy[oy * g.wo + ox]);
                            acc = if fma {
                                wv.mul_add(v, acc)
                            } else {
                                wv * v + acc
                            };
                        }
                        let got = dx[iy * w + ix];
                        assert_eq!(
                            got.to_bits(),
                            acc.to_bits(),
                            "dx[{iy},{ix}] {got} vs {acc} in {g:?}"
                        );
                    }
                }
                close(&dw, &dw0, "dw");
            }
        }
    }
}

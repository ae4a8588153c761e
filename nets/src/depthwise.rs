//! Depthwise k×k convolution kernels (forward, input and weight gradients), NCHW.
//!
//! Each (image, channel) plane is copied once into a zero-padded scratch whose columns are
//! split by parity of the stride (phase q = column mod s), so every tap (ky, kx) of every
//! output row reads one contiguous, bounds-free run of `wo` values: the inner loops are
//! straight-line multiply–adds the compiler vectorizes. The forward pass computes two or four
//! output rows at a time so that several accumulator registers are in flight; at stride 2
//! the phase split is a pairwise column copy. On x86-64 with AVX2 and FMA (checked
//! at run time) the same code is compiled a second time with fused multiply–adds.
//! Scratch lives per rayon task, not per plane; planes are grouped so a task carries enough
//! work to pay for the scheduling.

use rayon::prelude::*;

/// Output lanes accumulated in registers per block of an output row.
const LANES: usize = 16;
/// A block of one 256-bit register of f32 lanes.
const HALF: usize = LANES / 2;
/// Smallest number of multiply–adds a rayon task should carry.
const TASK_MACS: usize = 1 << 16;

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
}

/// a·b + c, fused where the target has FMA.
#[inline(always)]
pub(crate) fn madd<const FMA: bool>(a: f32, b: f32, c: f32) -> f32 {
    // Without the FMA target feature `mul_add` would be a libm call; with it, one instruction.
    if FMA { a.mul_add(b, c) } else { a * b + c }
}

/// Copies plane `x` (h × w) into the zero-padded, phase-split scratch.
#[inline(always)]
fn fill(g: &Geom, x: &[f32], buf: &mut Vec<f32>) {
    buf.clear();
    buf.resize(g.scratch_len(), 0.0);
    let (p, s, cw, w) = (g.pad(), g.s, g.cw(), g.w);
    for (iy, row) in x.chunks_exact(w).enumerate() {
        let r = iy + p;
        if s == 1 {
            buf[r * cw + p..][..w].copy_from_slice(row);
            continue;
        }
        if s == 2 {
            // Column pairs of the input row go to the two phases: one strided-load loop the
            // compiler vectorizes with shuffles (the generic step_by copy below made the
            // stride-2 forward benches 1.3–2.2× slower).
            let (row0, row1) = buf[r * 2 * cw..][..2 * cw].split_at_mut(cw);
            // Input column 0 lands in phase p mod 2 at phase column p / 2.
            let (a, b) = if p % 2 == 0 {
                (row0, row1)
            } else {
                (row1, row0)
            };
            let (a, b) = (&mut a[p / 2..], &mut b[p.div_ceil(2)..]);
            let pairs = row.chunks_exact(2);
            if let Some(&last) = pairs.remainder().first() {
                a[w / 2] = last;
            }
            for ((pr, x), y) in pairs.zip(a.iter_mut()).zip(b.iter_mut()) {
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

/// Phase `q` of a padded row (pad `p`, stride `s`) starts at input column `first` (the first
/// with (first + p) mod s = q), stored at phase column `j0` = (first + p) / s.
#[inline(always)]
fn phase_start(q: usize, p: usize, s: usize) -> (usize, usize) {
    let first = (q + s - p % s) % s;
    (first, (first + p) / s)
}

/// The inverse of [`fill`] on the interior: padded, phase-split `buf` → plane `x`.
#[inline(always)]
fn unfill(g: &Geom, buf: &[f32], x: &mut [f32]) {
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
            let (a, b) = (&a[p / 2..], &b[p.div_ceil(2)..]);
            let mut pairs = row.chunks_exact_mut(2);
            for ((pr, &x), &y) in (&mut pairs).zip(a).zip(b) {
                pr[0] = x;
                pr[1] = y;
            }
            if let Some(last) = pairs.into_remainder().first_mut() {
                *last = a[w / 2];
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
    dbuf: Vec<f32>,
    offs: Vec<usize>,
    /// The kernel turned by 180° (stride-1 dL/dx).
    flip: Vec<f32>,
}

#[inline(always)]
fn forward_plane<const FMA: bool>(
    g: &Geom,
    x: &[f32],
    wk: &[f32],
    sc: &mut Scratch,
    out: &mut [f32],
) {
    fill(g, x, &mut sc.buf);
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
    // Several output rows per pass keep four or more independent accumulator registers in
    // flight (one row's chain of k² fused multiply–adds alone is latency-bound); each output
    // still sums its taps in the same order, so the result is the same bit for bit.
    let ho = g.ho;
    let mut oy = 0;
    if g.wo < LANES {
        while oy + 4 <= ho {
            forward_rows::<FMA, 4>(g, buf, offs, wk, oy, out);
            oy += 4;
        }
    }
    while oy + 2 <= ho {
        forward_rows::<FMA, 2>(g, buf, offs, wk, oy, out);
        oy += 2;
    }
    if oy < ho {
        forward_rows::<FMA, 1>(g, buf, offs, wk, oy, out);
    }
}

/// Output rows `oy .. oy + R` of one plane from its padded scratch `buf`.
#[inline(always)]
fn forward_rows<const FMA: bool, const R: usize>(
    g: &Geom,
    buf: &[f32],
    offs: &[usize],
    wk: &[f32],
    oy: usize,
    out: &mut [f32],
) {
    let (wo, row_step) = (g.wo, g.s * g.s * g.cw());
    let base = oy * row_step;
    let mut x0 = 0;
    while x0 + LANES <= wo {
        let mut acc = [[0.0f32; LANES]; R];
        for (&wv, &off) in wk.iter().zip(offs) {
            for (r, acc) in acc.iter_mut().enumerate() {
                let src = &buf[base + r * row_step + off + x0..][..LANES];
                for (a, &v) in acc.iter_mut().zip(src) {
                    *a = madd::<FMA>(wv, v, *a);
                }
            }
        }
        for (r, acc) in acc.iter().enumerate() {
            out[(oy + r) * wo + x0..][..LANES].copy_from_slice(acc);
        }
        x0 += LANES;
    }
    // Maps narrower than LANES (stride-2 layers at the low resolutions): one register per row.
    if x0 + HALF <= wo {
        let mut acc = [[0.0f32; HALF]; R];
        for (&wv, &off) in wk.iter().zip(offs) {
            for (r, acc) in acc.iter_mut().enumerate() {
                let src = &buf[base + r * row_step + off + x0..][..HALF];
                for (a, &v) in acc.iter_mut().zip(src) {
                    *a = madd::<FMA>(wv, v, *a);
                }
            }
        }
        for (r, acc) in acc.iter().enumerate() {
            out[(oy + r) * wo + x0..][..HALF].copy_from_slice(acc);
        }
        x0 += HALF;
    }
    if x0 < wo {
        for r in 0..R {
            let tail = &mut out[(oy + r) * wo + x0..][..wo - x0];
            tail.fill(0.0);
            for (&wv, &off) in wk.iter().zip(offs) {
                let src = &buf[base + r * row_step + off + x0..][..tail.len()];
                for (a, &v) in tail.iter_mut().zip(src) {
                    *a = madd::<FMA>(wv, v, *a);
                }
            }
        }
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
    dx: &mut [f32],
    dw: &mut [f32],
) {
    fill(g, x, &mut sc.buf);
    tap_offsets(g, &mut sc.offs);
    weight_grad::<FMA>(g, &sc.buf, &sc.offs, dy, dw);
    if g.s == 1 {
        // At stride 1 with same padding, dL/dx is dL/dy correlated with the kernel turned by
        // 180°, on the same geometry (ho = h, wo = w): the forward pass's register-blocked
        // rows instead of a scatter that loads and stores dL/dx once per tap.
        sc.flip.clear();
        sc.flip.extend(wk.iter().rev());
        fill(g, dy, &mut sc.buf);
        forward_padded::<FMA>(g, &sc.buf, &sc.offs, &sc.flip, dx);
        return;
    }
    sc.dbuf.clear();
    sc.dbuf.resize(g.scratch_len(), 0.0);
    let (wo, row_step) = (g.wo, g.s * g.s * g.cw());
    for (&wv, &off) in wk.iter().zip(&sc.offs) {
        for (oy, grow) in dy.chunks_exact(wo).enumerate() {
            for (t, &gv) in sc.dbuf[oy * row_step + off..][..wo].iter_mut().zip(grow) {
                *t = madd::<FMA>(wv, gv, *t);
            }
        }
    }
    unfill(g, &sc.dbuf, dx);
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
    for (oy, grow) in dy.chunks_exact(wo).enumerate() {
        let row = &buf[oy * row_step..];
        let blocks = grow.chunks_exact(HALF);
        let x0 = wo - blocks.remainder().len();
        for (b, gb) in blocks.enumerate() {
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
    dx: &mut [f32],
    dw: &mut [f32],
) {
    backward_plane::<true>(g, x, wk, dy, sc, dx, dw)
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
/// ho×wo (overwritten). Shapes are the caller's to check.
pub(crate) fn forward(g: &Geom, c: usize, x: &[f32], w: &[f32], y: &mut [f32]) {
    let (hw, howo, kk) = (g.h * g.w, g.ho * g.wo, g.k * g.k);
    if howo == 0 || hw == 0 {
        y.fill(0.0);
        return;
    }
    let fma = has_fma();
    y.par_chunks_mut(howo)
        .enumerate()
        .with_min_len(g.planes_per_task())
        .for_each_init(Scratch::default, |sc, (idx, out)| {
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

/// Backward over all planes: dL/dx into `dx` (N·C planes of h×w, overwritten) and per-plane
/// dL/dw into `dw_planes` (N·C blocks of k², overwritten; the caller sums over images in a
/// fixed order so the result does not depend on the thread count).
pub(crate) fn backward(
    g: &Geom,
    c: usize,
    x: &[f32],
    w: &[f32],
    dy: &[f32],
    dx: &mut [f32],
    dw_planes: &mut [f32],
) {
    let (hw, howo, kk) = (g.h * g.w, g.ho * g.wo, g.k * g.k);
    if hw == 0 || howo == 0 {
        dx.fill(0.0);
        dw_planes.fill(0.0);
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
                        backward_plane_fma(&g, &x, &wk, &dy, sc, &mut dx, &mut dw);
                    }
                } else {
                    forward_plane::<false>(&g, &x, &wk, sc, &mut y);
                    backward_plane::<false>(&g, &x, &wk, &dy, sc, &mut dx, &mut dw);
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
                close(&dw, &dw0, "dw");
            }
        }
    }
}

//! Depthwise convolution on blocks of eight channels, for small planes.
//!
//! On a plane of a few dozen outputs the plane path's fixed costs — the padded copy, the
//! stride-2 phase split and its inverse, output rows narrower than a register — outweigh its
//! multiply–adds (an 8×8 stride-2 output plane ran at 7–9 GMAC/s). Here eight consecutive
//! planes of one image are transposed into a zero-padded scratch with the channels innermost,
//! one 256-bit register per pixel, so every tap of every output, at any stride and width, is
//! one register at a fixed offset and one per-tap register holds the eight channels' weights.
//! Each output and each dL/dx cell sums its taps in the plane path's order, from zero, by
//! fused multiply–adds, so y and dL/dx are the plane path's bits (test
//! `channel_blocks_give_the_plane_paths_bits`); dL/dw sums each tap over the outputs in
//! row-major order, where the plane path sums register lanes, so its last bits differ.
//!
//! Only compiled for x86-64 and only taken where the CPU has AVX2 and FMA ([`takes`]).

use super::{Geom, has_fma};
use rayon::prelude::*;
use std::arch::x86_64::*;
use std::mem::MaybeUninit;

/// Channels per block: one f32 register.
const CB: usize = 8;
/// Largest output plane (ho·wo) the block path takes; larger planes fill the plane path's
/// 16-wide register blocks and gain nothing from the transposes.
const SMALL: usize = 256;
/// Smallest number of multiply–adds a rayon task should carry.
const TASK_MACS: usize = 1 << 16;

/// Whether a layer of `c` channels with this geometry goes through channel blocks.
pub(super) fn takes(g: &Geom, c: usize) -> bool {
    c.is_multiple_of(CB) && g.ho * g.wo <= SMALL && g.ho * g.wo > 0 && has_fma()
}

/// Blocks of eight planes per rayon task.
fn blocks_per_task(g: &Geom) -> usize {
    (TASK_MACS / (CB * g.ho * g.wo * g.k * g.k).max(1)).max(1)
}

/// Per-task scratch: padded input and dL/dy with channels innermost, and an output block.
#[derive(Default)]
struct Scratch {
    xin: Vec<f32>,
    /// The geometry (h, w, k, s) `xin`'s zero padding is laid out for.
    xshape: Option<[usize; 4]>,
    dpad: Vec<f32>,
    dshape: Option<[usize; 4]>,
    out: Vec<f32>,
}

/// What every block of a call shares, computed once per call rather than per block of eight
/// planes (whose whole pass is a microsecond at 8×8): the taps' offsets in the padded input
/// and, at stride s ≥ 2, the dL/dx phases with their taps.
struct Plan {
    /// The k² taps' offsets (pixels) in the padded input, in (ky, kx) order.
    offs: Vec<usize>,
    /// Stride s ≥ 2: per phase (ρ, γ) with interior cells, its sweep, first cell and taps.
    phases: Vec<PhaseSweep>,
    /// Every phase's taps' offsets in the padded dL/dy, phase after phase (ranges in
    /// `phases`; a phase without interior cells keeps its taps here but has no sweep).
    phase_offs: Vec<usize>,
    /// The phases' taps' indices ky·k + kx, in `phase_offs` order: the order of the weight
    /// table a stride-s backward reads ([`weight_table`]).
    phase_order: Vec<usize>,
}

/// One dL/dx phase of a strided backward.
struct PhaseSweep {
    sweep: Sweep,
    /// First dL/dy pixel and first output cell of the sweep.
    from: usize,
    at: usize,
    /// Its taps in [`Plan::phase_offs`] (and its weights, eight per tap, in the table).
    taps: std::ops::Range<usize>,
}

impl Plan {
    /// The weight table of a backward ([`weight_table`]): at stride 1 each kernel turned by
    /// 180°, at stride s ≥ 2 the taps phase by phase.
    fn backward_weights(&self, g: &Geom, w: &[f32], c: usize) -> Vec<f32> {
        let kk = g.k * g.k;
        if g.s == 1 {
            let turned: Vec<usize> = (0..kk).rev().collect();
            weight_table(w, c, kk, &turned)
        } else {
            weight_table(w, c, kk, &self.phase_order)
        }
    }

    /// The plan of every call with geometry `g`.
    fn new(g: &Geom) -> Plan {
        let wp = padded_width(g);
        let offs = (0..g.k)
            .flat_map(|ky| (0..g.k).map(move |kx| ky * wp + kx))
            .collect();
        let (mut phases, mut phase_offs, mut phase_order) = (Vec::new(), Vec::new(), Vec::new());
        if g.s >= 2 {
            let (p, s) = (g.pad(), g.s);
            let (_, wd) = dy_extent(g);
            // The cells of phase (ρ, γ) see the taps ky ≡ ρ, kx ≡ γ (mod s), each at a fixed
            // offset in dL/dy: the plane path's `strided_dx`, with the same order of taps.
            for rho in 0..s {
                let (m0, m1) = g.phase_span(rho, g.h);
                for gamma in 0..s {
                    let (j0, j1) = g.phase_span(gamma, g.w);
                    // Every phase's taps go into the order, so that the weight table keeps
                    // all k² taps per block (the phases partition them).
                    let first = phase_offs.len();
                    for (t, off) in g.phase_taps((rho, gamma), wd) {
                        phase_offs.push(off);
                        phase_order.push(t);
                    }
                    if m1 <= m0 || j1 <= j0 {
                        continue;
                    }
                    phases.push(PhaseSweep {
                        sweep: Sweep {
                            rows: m1 - m0,
                            cols: j1 - j0,
                            in_step: wd,
                            in_col: 1,
                            out_step: s * g.w,
                            out_col: s,
                        },
                        from: m0 * wd + j0,
                        // Phase row m, column j is the interior cell (m·s + ρ − p, j·s + γ − p).
                        at: (m0 * s + rho - p) * g.w + j0 * s + gamma - p,
                        taps: first..phase_offs.len(),
                    });
                }
            }
        }
        Plan {
            offs,
            phases,
            phase_offs,
            phase_order,
        }
    }
}

impl Scratch {
    /// Transposes the block `xb` into `xin`, the padded input of `g` ((h + 2p) × (w + 2p)
    /// pixels), zeroed only when the geometry changes (every block writes the same interior
    /// pixels).
    #[target_feature(enable = "avx2,fma")]
    fn load_input(&mut self, g: &Geom, xb: &[f32]) {
        let (p, wp) = (g.pad(), padded_width(g));
        let key = [g.h, g.w, g.k, g.s];
        if self.xshape != Some(key) {
            self.xin.clear();
            self.xin.resize((g.h + 2 * p) * wp * CB, 0.0);
            self.xshape = Some(key);
        }
        to_channels(xb, g.w, &mut self.xin, wp, p);
    }

    /// Lays `dpad` out as dL/dy with p zero rows and columns before it and enough after for
    /// every dL/dx cell's taps ([`dy_extent`]), zeroed only when the geometry changes.
    fn dy_layout(&mut self, g: &Geom) {
        let key = [g.h, g.w, g.k, g.s];
        if self.dshape != Some(key) {
            let (hp, wp) = dy_extent(g);
            self.dpad.clear();
            self.dpad.resize(hp * wp * CB, 0.0);
            self.dshape = Some(key);
        }
    }
}

/// The weights of `c` channels (k² each) as blocks of eight channels, block-major, then
/// tap-major with the eight channels innermost, the taps in `order` (k² indices ky·k + kx).
fn weight_table(w: &[f32], c: usize, kk: usize, order: &[usize]) -> Vec<f32> {
    let mut table = Vec::with_capacity(c / CB * order.len() * CB);
    for c0 in (0..c).step_by(CB) {
        for &t in order {
            table.extend((0..CB).map(|j| w[(c0 + j) * kk + t]));
        }
    }
    table
}

/// Rows and columns of the padded dL/dy: at stride 1 the forward's padded shape, at stride
/// s ≥ 2 the plane path's.
fn dy_extent(g: &Geom) -> (usize, usize) {
    if g.s == 1 {
        return (g.h + 2 * g.pad(), padded_width(g));
    }
    g.strided_dy_extent()
}

/// Pixels per row of the padded input, w + 2p.
fn padded_width(g: &Geom) -> usize {
    g.w + 2 * g.pad()
}

/// Forward over all planes (as [`super::forward`]); panics unless `takes(g, c)`.
pub(super) fn forward(g: &Geom, c: usize, x: &[f32], w: &[f32], y: &mut [MaybeUninit<f32>]) {
    // The blocks below run AVX2 and FMA code on that check alone.
    assert!(takes(g, c), "channel blocks for {c} channels of {g:?}");
    let (hw, howo, kk) = (g.h * g.w, g.ho * g.wo, g.k * g.k);
    let order: Vec<usize> = (0..kk).collect();
    let table = weight_table(w, c, kk, &order);
    let plan = Plan::new(g);
    let blocks = c / CB;
    y.par_chunks_mut(CB * howo)
        .enumerate()
        .with_min_len(blocks_per_task(g))
        .for_each_init(Scratch::default, |sc, (b, out)| {
            let xb = &x[b * CB * hw..][..CB * hw];
            let wv = &table[(b % blocks) * kk * CB..][..kk * CB];
            // SAFETY: `takes` checked AVX2 and FMA on this CPU.
            unsafe { forward_block(g, &plan, xb, wv, sc, out) };
        });
}

/// Backward over all planes (as [`super::backward`]); panics unless `takes(g, c)`.
pub(super) fn backward(
    g: &Geom,
    c: usize,
    x: &[f32],
    w: &[f32],
    dy: &[f32],
    dx: &mut [MaybeUninit<f32>],
    dw_planes: &mut [f32],
) {
    assert!(takes(g, c), "channel blocks for {c} channels of {g:?}");
    let (hw, howo, kk) = (g.h * g.w, g.ho * g.wo, g.k * g.k);
    let plan = Plan::new(g);
    let table = plan.backward_weights(g, w, c);
    let blocks = c / CB;
    dx.par_chunks_mut(CB * hw)
        .zip(dw_planes.par_chunks_mut(CB * kk))
        .enumerate()
        .with_min_len(blocks_per_task(g))
        .for_each_init(Scratch::default, |sc, (b, (dxb, dwb))| {
            let xb = &x[b * CB * hw..][..CB * hw];
            let dyb = &dy[b * CB * howo..][..CB * howo];
            let wv = &table[(b % blocks) * kk * CB..][..kk * CB];
            // SAFETY: `takes` checked AVX2 and FMA on this CPU.
            unsafe { backward_block(g, &plan, xb, wv, dyb, sc, dxb, dwb) };
        });
}

/// One block's forward: `xb` eight planes of h×w, `out` eight of ho×wo (every value written),
/// `wv` the block's weights ([`weight_table`]).
#[target_feature(enable = "avx2,fma")]
fn forward_block(
    g: &Geom,
    plan: &Plan,
    xb: &[f32],
    wv: &[f32],
    sc: &mut Scratch,
    out: &mut [MaybeUninit<f32>],
) {
    let (s, wp) = (g.s, padded_width(g));
    sc.load_input(g, xb);
    sc.out.resize(g.ho * g.wo * CB, 0.0);
    let sw = Sweep {
        rows: g.ho,
        cols: g.wo,
        in_step: s * wp,
        in_col: s,
        out_step: g.wo,
        out_col: 1,
    };
    sweep(&sw, (&sc.xin, 0), &plan.offs, wv, (&mut sc.out, 0));
    from_channels(&sc.out, out);
}

/// One block's backward: dL/dx into `dxb` (eight planes of h×w, every value written), each
/// plane's k² weight gradients into `dwb` (overwritten); `wv` the block's weights
/// ([`weight_table`]), turned by 180° at stride 1, phase by phase ([`Plan::phase_order`]) at
/// stride s ≥ 2.
#[allow(clippy::too_many_arguments)]
#[target_feature(enable = "avx2,fma")]
fn backward_block(
    g: &Geom,
    plan: &Plan,
    xb: &[f32],
    wv: &[f32],
    dyb: &[f32],
    sc: &mut Scratch,
    dxb: &mut [MaybeUninit<f32>],
    dwb: &mut [f32],
) {
    let (p, wp) = (g.pad(), padded_width(g));
    sc.load_input(g, xb);
    sc.dy_layout(g);
    let (_, wd) = dy_extent(g);
    to_channels(dyb, g.wo, &mut sc.dpad, wd, p);
    weight_grad(g, &sc.xin, &plan.offs, (&sc.dpad, wd), dwb);
    sc.out.resize(g.h * g.w * CB, 0.0);
    if g.s == 1 {
        // dL/dy correlated with the kernel turned by 180° on the forward's padded shape, as
        // the plane path does.
        let sw = Sweep {
            rows: g.h,
            cols: g.w,
            in_step: wp,
            in_col: 1,
            out_step: g.w,
            out_col: 1,
        };
        sweep(&sw, (&sc.dpad, 0), &plan.offs, wv, (&mut sc.out, 0));
        from_channels(&sc.out, dxb);
        return;
    }
    for ph in &plan.phases {
        let t = ph.taps.clone();
        sweep(
            &ph.sweep,
            (&sc.dpad, ph.from),
            &plan.phase_offs[t.clone()],
            &wv[t.start * CB..t.end * CB],
            (&mut sc.out, ph.at),
        );
    }
    from_channels(&sc.out, dxb);
}

/// A correlation over a grid of outputs, in pixels of eight channels: output (m, j) at
/// `out[o + m·out_step + j·out_col]` is `Σₜ wv[t] ⊙ src[i + m·in_step + j·in_col + offs[t]]`,
/// taps summed in `offs` order from zero.
#[derive(Clone, Copy, Debug)]
struct Sweep {
    rows: usize,
    cols: usize,
    in_step: usize,
    in_col: usize,
    out_step: usize,
    out_col: usize,
}

/// Every output of `sw`; `(src, i)` and `(out, o)` are buffers and first pixels.
#[target_feature(enable = "avx2,fma")]
fn sweep(
    sw: &Sweep,
    (src, i): (&[f32], usize),
    offs: &[usize],
    wv: &[f32],
    (out, o): (&mut [f32], usize),
) {
    if sw.rows == 0 || sw.cols == 0 {
        return;
    }
    let reach = offs.iter().max().map_or(0, |&m| m + 1);
    assert!(
        (i + (sw.rows - 1) * sw.in_step + (sw.cols - 1) * sw.in_col + reach) * CB <= src.len(),
        "channel-block sweep reads past its input: {sw:?}"
    );
    assert!((o + (sw.rows - 1) * sw.out_step + (sw.cols - 1) * sw.out_col + 1) * CB <= out.len());
    assert!(wv.len() >= offs.len() * CB);
    // Eight outputs share each weight's load and keep eight chains of fused multiply–adds
    // in flight: eight of a row or, on rows narrower than eight, a tile of two or four rows
    // (an 8×8 stride-2 layer's outputs and its dL/dx phases are rows of four).
    // SAFETY (every tile): rows m .. m + R ≤ rows and columns j .. j + N ≤ cols, inside both
    // buffers by the assertions above.
    let mut m = 0;
    if sw.cols < 4 {
        // SAFETY: see above.
        unsafe { tiles::<4, 2>(sw, (src, i), offs, wv, (out, o), &mut m) };
    } else if sw.cols < 8 {
        // SAFETY: see above.
        unsafe { tiles::<2, 4>(sw, (src, i), offs, wv, (out, o), &mut m) };
    }
    for m in m..sw.rows {
        let mut j = 0;
        while j + 8 <= sw.cols {
            unsafe { outputs::<1, 8>(sw, src, i, offs, wv, out, o, (m, j)) };
            j += 8;
        }
        while j + 4 <= sw.cols {
            unsafe { outputs::<1, 4>(sw, src, i, offs, wv, out, o, (m, j)) };
            j += 4;
        }
        while j < sw.cols {
            unsafe { outputs::<1, 1>(sw, src, i, offs, wv, out, o, (m, j)) };
            j += 1;
        }
    }
}

/// Rows `*m ..` of `sw` in tiles of R rows while R are left (`*m` advanced past them): N
/// outputs of each row at a time, then the row's last `cols mod N` one at a time.
///
/// # Safety
/// The CPU has AVX2 and FMA; every row and column of `sw` is inside `src` and `out` (checked
/// by [`sweep`]).
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn tiles<const R: usize, const N: usize>(
    sw: &Sweep,
    (src, i): (&[f32], usize),
    offs: &[usize],
    wv: &[f32],
    (out, o): (&mut [f32], usize),
    m: &mut usize,
) {
    while *m + R <= sw.rows {
        let mut j = 0;
        // SAFETY (both): rows *m .. *m + R ≤ rows, columns j .. j + N ≤ cols (contract).
        while j + N <= sw.cols {
            unsafe { outputs::<R, N>(sw, src, i, offs, wv, out, o, (*m, j)) };
            j += N;
        }
        while j < sw.cols {
            unsafe { outputs::<R, 1>(sw, src, i, offs, wv, out, o, (*m, j)) };
            j += 1;
        }
        *m += R;
    }
}

/// Outputs (m .. m + R, j .. j + N) of `sw`, each its taps summed in `offs` order from zero.
///
/// # Safety
/// The CPU has AVX2 and FMA; every read and write is inside `src` and `out` (checked by
/// [`sweep`]).
#[allow(clippy::too_many_arguments)]
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn outputs<const R: usize, const N: usize>(
    sw: &Sweep,
    src: &[f32],
    i: usize,
    offs: &[usize],
    wv: &[f32],
    out: &mut [f32],
    o: usize,
    (m, j): (usize, usize),
) {
    let mut acc = [[_mm256_setzero_ps(); N]; R];
    let base: [*const f32; R] = std::array::from_fn(|r| {
        src.as_ptr()
            .wrapping_add((i + (m + r) * sw.in_step + j * sw.in_col) * CB)
    });
    for (t, &off) in offs.iter().enumerate() {
        // SAFETY: `wv` holds a register per tap; the reads are inside `src` (contract).
        unsafe {
            let w = _mm256_loadu_ps(wv.as_ptr().add(t * CB));
            for (row, b) in acc.iter_mut().zip(&base) {
                for (n, a) in row.iter_mut().enumerate() {
                    let v = _mm256_loadu_ps(b.add((n * sw.in_col + off) * CB));
                    *a = _mm256_fmadd_ps(w, v, *a);
                }
            }
        }
    }
    for (r, row) in acc.iter().enumerate() {
        let dst = out
            .as_mut_ptr()
            .wrapping_add((o + (m + r) * sw.out_step + j * sw.out_col) * CB);
        for (n, a) in row.iter().enumerate() {
            // SAFETY: inside `out` (contract).
            unsafe { _mm256_storeu_ps(dst.add(n * sw.out_col * CB), *a) };
        }
    }
}

/// Most taps whose gradients one pass over dL/dy accumulates side by side.
const TAPS: usize = 8;

/// dL/dw of the block's k² taps into `dwb` (plane-major, k² per plane, overwritten) from the
/// padded input and the padded dL/dy `(dpad, wd)`; each tap sums over the outputs in
/// row-major order.
#[target_feature(enable = "avx2,fma")]
fn weight_grad(
    g: &Geom,
    xin: &[f32],
    offs: &[usize],
    (dpad, wd): (&[f32], usize),
    dwb: &mut [f32],
) {
    let (p, s, kk, wp) = (g.pad(), g.s, g.k * g.k, padded_width(g));
    let reach = offs.iter().max().map_or(0, |&m| m + 1);
    assert!(((g.ho - 1) * s * wp + (g.wo - 1) * s + reach) * CB <= xin.len());
    assert!(((g.ho - 1 + p) * wd + g.wo - 1 + p + 1) * CB <= dpad.len() && dwb.len() >= CB * kk);
    let per = kk.div_ceil(kk.div_ceil(TAPS));
    let at = (wp, wd, p, s);
    for (n, group) in offs.chunks(per).enumerate() {
        // SAFETY (all): the reads are inside `xin` and `dpad` by the assertions above.
        let sums = unsafe {
            match group.len() {
                1 => tap_sums::<1>(g, xin, dpad, group, at),
                2 => tap_sums::<2>(g, xin, dpad, group, at),
                3 => tap_sums::<3>(g, xin, dpad, group, at),
                4 => tap_sums::<4>(g, xin, dpad, group, at),
                5 => tap_sums::<5>(g, xin, dpad, group, at),
                6 => tap_sums::<6>(g, xin, dpad, group, at),
                7 => tap_sums::<7>(g, xin, dpad, group, at),
                _ => tap_sums::<8>(g, xin, dpad, group, at),
            }
        };
        for (t, lanes) in sums.iter().enumerate().take(group.len()) {
            for (j, &v) in lanes.iter().enumerate() {
                dwb[j * kk + n * per + t] = v;
            }
        }
    }
}

/// The sums over the outputs of dL/dy · x for the `T` taps `offs` (eight channels each; the
/// first `T` of the result), accumulators in registers.
///
/// # Safety
/// The CPU has AVX2 and FMA; the reads are inside `xin` and `dpad` (checked by
/// [`weight_grad`]).
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn tap_sums<const T: usize>(
    g: &Geom,
    xin: &[f32],
    dpad: &[f32],
    offs: &[usize],
    (wp, wd, p, s): (usize, usize, usize, usize),
) -> [[f32; CB]; TAPS] {
    let offs: [usize; T] = std::array::from_fn(|t| offs[t] * CB);
    let mut acc = [_mm256_setzero_ps(); T];
    for oy in 0..g.ho {
        // SAFETY: inside `dpad` and `xin` (contract).
        unsafe {
            let drow = dpad.as_ptr().add(((oy + p) * wd + p) * CB);
            let xrow = xin.as_ptr().add(oy * s * wp * CB);
            for ox in 0..g.wo {
                let d = _mm256_loadu_ps(drow.add(ox * CB));
                let x = xrow.add(ox * s * CB);
                for (a, &off) in acc.iter_mut().zip(&offs) {
                    *a = _mm256_fmadd_ps(d, _mm256_loadu_ps(x.add(off)), *a);
                }
            }
        }
    }
    let mut out = [[0.0f32; CB]; TAPS];
    for (o, a) in out.iter_mut().zip(&acc) {
        // SAFETY: a store of CB values into `o`.
        unsafe { _mm256_storeu_ps(o.as_mut_ptr(), *a) };
    }
    out
}

/// Eight planes of `w`-wide rows (`src`, plane-major) into the padded channels-innermost
/// layout `dst` of `wp` pixels per row, pixel (y, x) at (y + p, x + p).
///
/// Row by row, eight pixels at a time, a row's last `w mod 8` as masked loads (one to four of
/// them through half a transpose): a running position per pixel (and before it a division)
/// cost more than the transposes at 8×8.
#[target_feature(enable = "avx2,fma")]
fn to_channels(src: &[f32], w: usize, dst: &mut [f32], wp: usize, p: usize) {
    let hw = src.len() / CB;
    if hw == 0 {
        return;
    }
    let h = hw / w;
    assert!(hw == h * w && ((h - 1 + p) * wp + w + p) * CB <= dst.len());
    let rem = w % CB;
    // Lanes below `rem`; the others read nothing and load zeros.
    let mask = _mm256_cmpgt_epi32(
        _mm256_set1_epi32(rem as i32),
        _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7),
    );
    let mask4 = _mm_cmpgt_epi32(_mm_set1_epi32(rem as i32), _mm_setr_epi32(0, 1, 2, 3));
    let (s, d) = (src.as_ptr(), dst.as_mut_ptr());
    for y in 0..h {
        let mut x = 0;
        // SAFETY (every block): pixels y·w + x .. + 8 (+ rem) of each plane are inside `src`
        // (masked lanes past them are neither read nor faulted on), their destinations inside
        // `dst` (assertion above).
        while x + CB <= w {
            unsafe {
                let t = transpose(std::array::from_fn(|j| {
                    _mm256_loadu_ps(s.add(j * hw + y * w + x))
                }));
                let at = d.add(((y + p) * wp + x + p) * CB);
                for (n, v) in t.iter().enumerate() {
                    _mm256_storeu_ps(at.add(n * CB), *v);
                }
            }
            x += CB;
        }
        if rem > 0 && rem <= 4 {
            // Up to four pixels: eight 128-bit loads as four registers [channel j | channel
            // j + 4] (four inserts), and the in-lane half of the transpose (8 shuffles; the
            // whole transpose is 24): 336×11×18 at stride 2 (rows of 18), batch 16, forward
            // 140–142 against 144–156 µs on two threads, 274–282 against 283–311 µs on one.
            unsafe {
                let ld = |j: usize| _mm_maskload_ps(s.add(j * hw + y * w + x), mask4);
                let px =
                    transpose_lanes(std::array::from_fn(|j| _mm256_set_m128(ld(j + 4), ld(j))));
                store_pixels(d.add(((y + p) * wp + x + p) * CB), &px, rem);
            }
        } else if rem > 0 {
            unsafe {
                let t = transpose(std::array::from_fn(|j| {
                    _mm256_maskload_ps(s.add(j * hw + y * w + x), mask)
                }));
                store_pixels(d.add(((y + p) * wp + x + p) * CB), &t, rem);
            }
        }
    }
}

/// The first `n` (1 to 7, at most `regs.len()`) of `regs` as consecutive pixels from `at`.
///
/// One store per register, the count matched to a constant: a loop over the run-time count
/// was compiled to the registers spilled to the stack and a call to `memcpy` (10.6 % of the
/// 336×11×18 stride-2 forward's samples on a Xeon VM).
///
/// # Safety
/// The CPU has AVX2; `at` has room for `n` pixels of eight values.
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn store_pixels(at: *mut f32, regs: &[__m256], n: usize) {
    /// The first `N` of `regs` (a constant trip count, unrolled).
    ///
    /// # Safety
    /// The CPU has AVX2; `at` has room for `N` pixels, `regs` holds at least `N`.
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    unsafe fn first<const N: usize>(at: *mut f32, regs: &[__m256]) {
        for (k, v) in regs[..N].iter().enumerate() {
            // SAFETY: pixel k < N ≤ n is inside `at` (contract).
            unsafe { _mm256_storeu_ps(at.add(k * CB), *v) };
        }
    }
    // SAFETY (every arm): the caller's contract, with N = n.
    unsafe {
        match n {
            1 => first::<1>(at, regs),
            2 => first::<2>(at, regs),
            3 => first::<3>(at, regs),
            4 => first::<4>(at, regs),
            5 => first::<5>(at, regs),
            6 => first::<6>(at, regs),
            7 => first::<7>(at, regs),
            _ => unreachable!("store_pixels: {n} pixels"),
        }
    }
}

/// The channels-innermost pixels of `src` (unpadded, `dst.len() / 8` of them) into eight
/// planes `dst`, every value written, so the caller's output is not zeroed first.
#[target_feature(enable = "avx2,fma")]
fn from_channels(src: &[f32], dst: &mut [MaybeUninit<f32>]) {
    let hw = dst.len() / CB;
    // Eight whole planes, so that the transposes and the tail below write every value.
    assert!(dst.len() == hw * CB && src.len() >= hw * CB);
    let (s, d) = (src.as_ptr(), dst.as_mut_ptr().cast::<f32>());
    let mut i = 0;
    while i + CB <= hw {
        // SAFETY: i + 8 ≤ hw (the assertion above holds `src` and `dst` to hw pixels).
        unsafe { eight_pixels(s, d, hw, i) };
        i += CB;
    }
    if i < hw && hw >= CB {
        // The last `hw mod 8` pixels as the last eight, over values already written (the
        // same values): their scalar copies, 48 at 6×9 outputs, cost more than a transpose.
        // SAFETY: pixels hw − 8 .. hw, inside both (the assertion above).
        unsafe { eight_pixels(s, d, hw, hw - CB) };
        return;
    }
    for i in i..hw {
        for j in 0..CB {
            dst[j * hw + i] = MaybeUninit::new(src[i * CB + j]);
        }
    }
}

/// Pixels i .. i + 8 of the channels-innermost `src` into rows i .. i + 8 of the eight planes
/// (`hw` values each) of `dst`.
///
/// # Safety
/// The CPU has AVX2; `src` holds pixels i .. i + 8, `dst` eight planes of `hw` ≥ i + 8.
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn eight_pixels(src: *const f32, dst: *mut f32, hw: usize, i: usize) {
    // SAFETY (all): inside `src` and `dst` (contract).
    let t = transpose(std::array::from_fn(|n| unsafe {
        _mm256_loadu_ps(src.add((i + n) * CB))
    }));
    for (j, v) in t.iter().enumerate() {
        unsafe { _mm256_storeu_ps(dst.add(j * hw + i), *v) };
    }
}

/// The 8×8 transpose of eight registers (row r, lane l → row l, lane r).
#[target_feature(enable = "avx2,fma")]
#[inline]
fn transpose(r: [__m256; 8]) -> [__m256; 8] {
    let [s0, s1, s2, s3] = transpose_lanes([r[0], r[1], r[2], r[3]]);
    let [s4, s5, s6, s7] = transpose_lanes([r[4], r[5], r[6], r[7]]);
    [
        _mm256_permute2f128_ps::<0x20>(s0, s4),
        _mm256_permute2f128_ps::<0x20>(s1, s5),
        _mm256_permute2f128_ps::<0x20>(s2, s6),
        _mm256_permute2f128_ps::<0x20>(s3, s7),
        _mm256_permute2f128_ps::<0x31>(s0, s4),
        _mm256_permute2f128_ps::<0x31>(s1, s5),
        _mm256_permute2f128_ps::<0x31>(s2, s6),
        _mm256_permute2f128_ps::<0x31>(s3, s7),
    ]
}

/// The 4×4 transpose within each 128-bit lane of four registers (row r, lane l → row l, lane
/// r, in both halves alike): the first two stages of [`transpose`], and the whole of
/// `to_channels`' half transpose.
#[target_feature(enable = "avx2,fma")]
#[inline]
fn transpose_lanes(r: [__m256; 4]) -> [__m256; 4] {
    let t0 = _mm256_unpacklo_ps(r[0], r[1]);
    let t1 = _mm256_unpackhi_ps(r[0], r[1]);
    let t2 = _mm256_unpacklo_ps(r[2], r[3]);
    let t3 = _mm256_unpackhi_ps(r[2], r[3]);
    [
        _mm256_shuffle_ps::<0x44>(t0, t2),
        _mm256_shuffle_ps::<0xEE>(t0, t2),
        _mm256_shuffle_ps::<0x44>(t1, t3),
        _mm256_shuffle_ps::<0xEE>(t1, t3),
    ]
}

#[cfg(test)]
mod tests {
    use super::super::{Scratch as PlaneScratch, backward_plane_fma, forward_plane_fma};
    use super::*;
    use crate::conv::out_size;
    use rand::{Rng, SeedableRng, rngs::StdRng};

    /// Every geometry the block path takes (strides 1–3, planes smaller than the kernel, rows
    /// shorter and longer than a block of eight, pixel counts not a multiple of eight): y and
    /// dL/dx bit for bit the plane path's, dL/dw within rounding of it; one scratch reused
    /// across geometries as a rayon task reuses its own, so no stale padding leaks through.
    #[test]
    fn channel_blocks_give_the_plane_paths_bits() {
        if !has_fma() {
            return;
        }
        let mut rng = StdRng::seed_from_u64(11);
        let mut sc = Scratch::default();
        let mut psc = PlaneScratch::default();
        let mut cases = 0;
        while cases < 240 {
            let k = [1, 3, 5, 7][cases % 4];
            let s = 1 + (cases / 4) % 3;
            let (h, w) = (rng.random_range(1..34), rng.random_range(1..34));
            let g = Geom {
                h,
                w,
                ho: out_size(h, k, s),
                wo: out_size(w, k, s),
                k,
                s,
            };
            let c = CB * rng.random_range(1..3);
            if !takes(&g, c) {
                continue;
            }
            cases += 1;
            let (hw, howo, kk) = (h * w, g.ho * g.wo, k * k);
            let x: Vec<f32> = (0..c * hw).map(|_| rng.random_range(-1.0..1.0)).collect();
            let wk: Vec<f32> = (0..c * kk).map(|_| rng.random_range(-1.0..1.0)).collect();
            let dy: Vec<f32> = (0..c * howo).map(|_| rng.random_range(-1.0..1.0)).collect();
            let (mut y, mut dx, mut dw) = (
                vec![f32::NAN; c * howo],
                vec![f32::NAN; c * hw],
                vec![f32::NAN; c * kk],
            );
            let plan = Plan::new(&g);
            let order: Vec<usize> = (0..kk).collect();
            let (table, turned) = (
                weight_table(&wk, c, kk, &order),
                plan.backward_weights(&g, &wk, c),
            );
            for b in 0..c / CB {
                let xb = &x[b * CB * hw..][..CB * hw];
                let dyb = &dy[b * CB * howo..][..CB * howo];
                let wv = &table[b * kk * CB..][..kk * CB];
                let wt = &turned[b * kk * CB..][..kk * CB];
                // SAFETY: has_fma() checked the CPU; the blocks write initialised values only.
                unsafe {
                    forward_block(
                        &g,
                        &plan,
                        xb,
                        wv,
                        &mut sc,
                        super::super::as_uninit(&mut y[b * CB * howo..][..CB * howo]),
                    );
                    backward_block(
                        &g,
                        &plan,
                        xb,
                        wt,
                        dyb,
                        &mut sc,
                        super::super::as_uninit(&mut dx[b * CB * hw..][..CB * hw]),
                        &mut dw[b * CB * kk..][..CB * kk],
                    );
                }
            }
            for ch in 0..c {
                let (xp, wp, dyp) = (
                    &x[ch * hw..][..hw],
                    &wk[ch * kk..][..kk],
                    &dy[ch * howo..][..howo],
                );
                let (mut y0, mut dx0, mut dw0) = (vec![0.0; howo], vec![0.0; hw], vec![0.0; kk]);
                // SAFETY: has_fma() checked the CPU.
                unsafe {
                    forward_plane_fma(&g, xp, wp, &mut psc, &mut y0);
                    backward_plane_fma(
                        &g,
                        xp,
                        wp,
                        dyp,
                        &mut psc,
                        super::super::as_uninit(&mut dx0),
                        &mut dw0,
                    );
                }
                for (i, (a, b)) in y[ch * howo..][..howo].iter().zip(&y0).enumerate() {
                    assert_eq!(a.to_bits(), b.to_bits(), "y[{ch}][{i}] {a} vs {b} in {g:?}");
                }
                for (i, (a, b)) in dx[ch * hw..][..hw].iter().zip(&dx0).enumerate() {
                    assert_eq!(
                        a.to_bits(),
                        b.to_bits(),
                        "dx[{ch}][{i}] {a} vs {b} in {g:?}"
                    );
                }
                // Both sum howo products per tap, in different orders.
                let scale: f32 = dyp.iter().map(|v| v.abs()).sum();
                for (t, (a, b)) in dw[ch * kk..][..kk].iter().zip(&dw0).enumerate() {
                    assert!(
                        (a - b).abs() <= 1e-6 * scale.max(1.0),
                        "dw[{ch}][{t}] {a} vs {b} in {g:?}"
                    );
                }
            }
        }
    }

    /// The parallel entry points over several images and blocks are the blocks one by one,
    /// whatever the thread count.
    #[test]
    fn parallel_blocks_match_one_at_a_time() {
        if !has_fma() {
            return;
        }
        let g = Geom {
            h: 16,
            w: 16,
            ho: 8,
            wo: 8,
            k: 5,
            s: 2,
        };
        let (n, c) = (3, 24);
        let mut rng = StdRng::seed_from_u64(5);
        let (hw, howo, kk) = (g.h * g.w, g.ho * g.wo, g.k * g.k);
        let x: Vec<f32> = (0..n * c * hw)
            .map(|_| rng.random_range(-1.0..1.0))
            .collect();
        let wk: Vec<f32> = (0..c * kk).map(|_| rng.random_range(-1.0..1.0)).collect();
        let dy: Vec<f32> = (0..n * c * howo)
            .map(|_| rng.random_range(-1.0..1.0))
            .collect();
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| {
                let mut y = vec![0.0; n * c * howo];
                let mut dx = vec![0.0; n * c * hw];
                let mut dw = vec![0.0; n * c * kk];
                // SAFETY: the paths write initialised values only.
                forward(&g, c, &x, &wk, unsafe { super::super::as_uninit(&mut y) });
                backward(
                    &g,
                    c,
                    &x,
                    &wk,
                    &dy,
                    // SAFETY: the paths write initialised values only.
                    unsafe { super::super::as_uninit(&mut dx) },
                    &mut dw,
                );
                (y, dx, dw)
            })
        };
        let one = run(1);
        assert_eq!(one, run(3));
        let mut sc = Scratch::default();
        let order: Vec<usize> = (0..kk).collect();
        let (table, plan) = (weight_table(&wk, c, kk, &order), Plan::new(&g));
        for b in 0..n * c / CB {
            let mut y = vec![f32::NAN; CB * howo];
            let wv = &table[(b % (c / CB)) * kk * CB..][..kk * CB];
            let xb = &x[b * CB * hw..][..CB * hw];
            // SAFETY: has_fma() checked the CPU; the block writes initialised values only.
            unsafe { forward_block(&g, &plan, xb, wv, &mut sc, super::super::as_uninit(&mut y)) };
            assert_eq!(y, one.0[b * CB * howo..][..CB * howo]);
        }
    }
}

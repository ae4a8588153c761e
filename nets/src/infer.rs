//! Batch-1 inference of one subnet on the calling thread, for the tracker: batch norms folded
//! into the convolutions before them, elastic kernels and weight sub-matrices extracted once,
//! every activation buffer allocated once at construction, no gradient state. Computes the same
//! function as [`Supernet::forward`] in [`crate::BnMode::Eval`] to float rounding, except that
//! the calibration head's hidden layer holds its weights in half precision (`HalfDense`: the
//! tracker's one memory-bound layer), which moves Δt by a bounded amount the tests check.
//!
//! Features are stored pixel-major (HWC: one row of C channels per pixel), not in the
//! supernet's NCHW planes. At the subnets' deep stages a plane holds 6–24 pixels but there are
//! hundreds of channels, so every per-channel loop (depthwise taps, squeeze-excitation, bias and
//! activation) runs along the channels, where the vectors are long; 1×1 convolutions are the
//! same GEMMs with the operands transposed. The whole pass is compiled a second time with AVX2
//! and FMA, chosen at run time.

use crate::act::Act;
use crate::arch::{Arch, N_STAGES, STEM_CHANNELS};
use crate::block::{MbBlock, elastic_kernel, sub_cols};
use crate::conv::out_size;
use crate::depthwise::{Geom, has_fma, madd};
use crate::error::{NetsError, Result};
use crate::norm::BatchNorm;
use crate::pool::centred_coordinate;
use crate::resize::taps;
use crate::supernet::{Supernet, head_inputs};
use faer::linalg::matmul::matmul;
use faer::{Accum, MatMut, MatRef, Par};

/// Most activation values an [`Inference`] may hold (4 GiB of f32): beyond it, refuse.
const MAX_FLOATS: usize = 1 << 30;

/// Scales the rows of `w` (rows × cols) by the inference-mode batch norm `bn` and returns the
/// folded bias β + (b − μ)·γ/√(σ² + ε); `bias` is the convolution's own bias, if any.
fn fold(bn: &BatchNorm, w: &mut [f32], rows: usize, bias: Option<&[f32]>) -> Vec<f32> {
    let cols = w.len() / rows.max(1);
    (0..rows)
        .map(|o| {
            let s = bn.gamma.value[o] / (bn.running_var[o] + bn.eps).sqrt();
            w[o * cols..][..cols].iter_mut().for_each(|v| *v *= s);
            let b0 = bias.map_or(0.0, |b| b[o]);
            bn.beta.value[o] + (b0 - bn.running_mean[o]) * s
        })
        .collect()
}

/// `rows × cols` row-major → `cols × rows` row-major.
fn transpose(a: &[f32], rows: usize, cols: usize) -> Vec<f32> {
    let mut t = vec![0.0; a.len()];
    for (r, row) in a.chunks_exact(cols.max(1)).enumerate().take(rows) {
        for (c, &v) in row.iter().enumerate() {
            t[c * rows + r] = v;
        }
    }
    t
}

/// Applies `act` to every value of `y`.
#[inline(always)]
fn act_pass(y: &mut [f32], act: Act) {
    // One loop per activation, so that each is a straight vectorizable pass.
    match act {
        Act::Identity => {}
        Act::Relu => y.iter_mut().for_each(|v| *v = v.max(0.0)),
        Act::HSwish => y.iter_mut().for_each(|v| *v = Act::HSwish.apply(*v)),
        Act::HSigmoid => y.iter_mut().for_each(|v| *v = Act::HSigmoid.apply(*v)),
    }
}

/// Adds the per-channel bias `b` to every pixel row of `y` (HWC) and applies the activation.
#[inline(always)]
fn bias_act(y: &mut [f32], b: &[f32], act: Act) {
    for row in y.chunks_exact_mut(b.len()) {
        row.iter_mut().zip(b).for_each(|(v, &bo)| *v += bo);
        act_pass(row, act);
    }
}

/// Dot product with eight independent accumulators, so that the sum vectorizes.
#[inline(always)]
fn dot<const FMA: bool>(a: &[f32], b: &[f32]) -> f32 {
    let mut acc = [0.0f32; 8];
    let (ac, bc) = (a.chunks_exact(8), b.chunks_exact(8));
    let rest: f32 = ac
        .remainder()
        .iter()
        .zip(bc.remainder())
        .map(|(x, y)| x * y)
        .sum();
    for (x, y) in ac.zip(bc) {
        for l in 0..8 {
            acc[l] = madd::<FMA>(x[l], y[l], acc[l]);
        }
    }
    acc.iter().sum::<f32>() + rest
}

/// A 1×1 convolution with bias and activation on HWC features: Y (hw × cout) = X (hw × cin) ·
/// Wᵀ, with Wᵀ (cin × cout) stored row-major.
struct Pointwise {
    wt: Vec<f32>,
    b: Vec<f32>,
    cin: usize,
    cout: usize,
    act: Act,
}

impl Pointwise {
    /// From weights `w` (cout × cin, row-major) and bias `b`.
    fn new(w: &[f32], b: Vec<f32>, cin: usize, cout: usize, act: Act) -> Self {
        Self {
            wt: transpose(w, cout, cin),
            b,
            cin,
            cout,
            act,
        }
    }
    #[inline(always)]
    fn run(&self, x: &[f32], hw: usize, y: &mut [f32]) {
        let xm = MatRef::from_row_major_slice(&x[..hw * self.cin], hw, self.cin);
        let wm = MatRef::from_row_major_slice(&self.wt, self.cin, self.cout);
        let y = &mut y[..hw * self.cout];
        matmul(
            MatMut::from_row_major_slice_mut(y, hw, self.cout),
            Accum::Replace,
            xm,
            wm,
            1.0f32,
            Par::Seq,
        );
        bias_act(y, &self.b, self.act);
    }
}

/// A dense layer y = act(W x + b) whose weights are stored in IEEE half precision: the
/// calibration head's hidden layer (1360 → 1280 at the default head, 7 MB in f32) is the
/// largest weight matrix of the tracker and is streamed whole for every frame, so its bytes,
/// not its 1.7 M multiply-adds, bound it. Rounding each weight to f16 (relative error ≤ 2⁻¹¹,
/// absolute ≤ 2⁻²⁵ below f16's normal range) moves each output by at most
/// 2⁻¹¹·Σᵢ|xᵢ wᵢⱼ| + 2⁻²⁵·Σᵢ|xᵢ| (the bound the tests check); sums are in f32.
struct HalfDense {
    /// Wᵀ (cin × cout), row-major, as f16 bits.
    wt: Vec<u16>,
    b: Vec<f32>,
    cin: usize,
    cout: usize,
    act: Act,
    /// Whether this CPU has AVX, FMA and F16C (the vector kernel), detected once.
    f16c: bool,
}

impl HalfDense {
    fn new(d: &crate::supernet::Dense, cin: usize, act: Act) -> Self {
        let wt = transpose(&d.w.value, d.cout, cin)
            .into_iter()
            .map(|v| half::f16::from_f32(v).to_bits())
            .collect();
        Self {
            wt,
            b: d.b.value.clone(),
            cin,
            cout: d.cout,
            act,
            f16c: has_f16c(),
        }
    }

    /// y (cout) = act(W x + b) for one input x (cin).
    fn run(&self, x: &[f32], y: &mut [f32]) {
        let (x, y) = (&x[..self.cin], &mut y[..self.cout]);
        y.fill(0.0);
        if self.f16c {
            #[cfg(target_arch = "x86_64")]
            // SAFETY: AVX, FMA and F16C were detected on this CPU at construction (`self.f16c`).
            unsafe {
                self.accumulate_f16c(x, y)
            };
        } else {
            for (&xi, row) in x.iter().zip(self.wt.chunks_exact(self.cout)) {
                for (v, &w) in y.iter_mut().zip(row) {
                    *v += xi * half::f16::from_bits(w).to_f32();
                }
            }
        }
        bias_act(y, &self.b, self.act);
    }

    /// y += Wᵀ-rows · x: four input rows per sweep over y, so y is loaded and stored once per
    /// four rows; eight outputs per instruction, f16 → f32 by F16C.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx,fma,f16c")]
    fn accumulate_f16c(&self, x: &[f32], y: &mut [f32]) {
        use std::arch::x86_64::*;
        let n = self.cout;
        let full = n / 8 * 8;
        for (rows, xs) in self.wt.chunks(4 * n).zip(x.chunks(4)) {
            for j in (0..full).step_by(8) {
                // SAFETY: j + 8 ≤ n = the length of y and of every row.
                unsafe {
                    let mut acc = _mm256_loadu_ps(y.as_ptr().add(j));
                    for (row, &xi) in rows.chunks_exact(n).zip(xs) {
                        let w = _mm256_cvtph_ps(_mm_loadu_si128(row.as_ptr().add(j).cast()));
                        acc = _mm256_fmadd_ps(w, _mm256_set1_ps(xi), acc);
                    }
                    _mm256_storeu_ps(y.as_mut_ptr().add(j), acc);
                }
            }
            for (j, v) in y.iter_mut().enumerate().skip(full) {
                for (row, &xi) in rows.chunks_exact(n).zip(xs) {
                    *v = xi.mul_add(half::f16::from_bits(row[j]).to_f32(), *v);
                }
            }
        }
    }
}

/// Whether this CPU has AVX, FMA and F16C ([`HalfDense`]'s vector kernel).
fn has_f16c() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx")
            && std::arch::is_x86_feature_detected!("fma")
            && std::arch::is_x86_feature_detected!("f16c")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// Depthwise k×k convolution (same padding k/2, stride s) with bias and activation on HWC
/// features of `c` channels; kernels stored tap-major (k² × c).
struct Depthwise {
    wt: Vec<f32>,
    b: Vec<f32>,
    g: Geom,
    act: Act,
}

/// Input indices `o·s + t − p` of output `o` over taps t = 0..k that fall inside [0, n): the
/// first tap and the first input index.
#[inline(always)]
fn window(o: usize, s: usize, p: usize, k: usize, n: usize) -> (usize, usize, usize) {
    let start = o * s;
    let t0 = p.saturating_sub(start);
    let t1 = k.min(n + p - start);
    (t0, t1, start + t0 - p)
}

impl Depthwise {
    #[inline(always)]
    fn run<const FMA: bool>(&self, x: &[f32], y: &mut [f32]) {
        let (g, c) = (&self.g, self.b.len());
        let p = g.k / 2;
        for oy in 0..g.ho {
            let (ky0, ky1, iy0) = window(oy, g.s, p, g.k, g.h);
            for ox in 0..g.wo {
                let (kx0, kx1, ix0) = window(ox, g.s, p, g.k, g.w);
                let out = &mut y[(oy * g.wo + ox) * c..][..c];
                out.copy_from_slice(&self.b);
                for (dy, ky) in (ky0..ky1).enumerate() {
                    for (dx, kx) in (kx0..kx1).enumerate() {
                        let xi = &x[((iy0 + dy) * g.w + ix0 + dx) * c..][..c];
                        let wi = &self.wt[(ky * g.k + kx) * c..][..c];
                        for ((o, &xv), &wv) in out.iter_mut().zip(xi).zip(wi) {
                            *o = madd::<FMA>(xv, wv, *o);
                        }
                    }
                }
                act_pass(out, self.act);
            }
        }
    }
}

/// The stem: a 3×3 stride-2 convolution from `cin` planes (CHW input) to HWC features, with
/// bias and h-swish; kernels stored (cin × 9 × cout).
struct Stem {
    wt: Vec<f32>,
    b: Vec<f32>,
    g: Geom,
    cin: usize,
}

impl Stem {
    #[inline(always)]
    fn run<const FMA: bool>(&self, x: &[f32], y: &mut [f32]) {
        let (g, c) = (&self.g, self.b.len());
        let (p, hw) = (g.k / 2, g.h * g.w);
        for oy in 0..g.ho {
            let (ky0, ky1, iy0) = window(oy, g.s, p, g.k, g.h);
            for ox in 0..g.wo {
                let (kx0, kx1, ix0) = window(ox, g.s, p, g.k, g.w);
                let out = &mut y[(oy * g.wo + ox) * c..][..c];
                out.copy_from_slice(&self.b);
                for i in 0..self.cin {
                    for (dy, ky) in (ky0..ky1).enumerate() {
                        for (dx, kx) in (kx0..kx1).enumerate() {
                            let xv = x[i * hw + (iy0 + dy) * g.w + ix0 + dx];
                            let wi = &self.wt[((i * g.k + ky) * g.k + kx) * c..][..c];
                            for (o, &wv) in out.iter_mut().zip(wi) {
                                *o = madd::<FMA>(xv, wv, *o);
                            }
                        }
                    }
                }
                act_pass(out, Act::HSwish);
            }
        }
    }
}

/// Squeeze-and-excitation on HWC features, with its pooled vector and squeeze activations.
struct Squeeze {
    w1: Vec<f32>,
    b1: Vec<f32>,
    w2: Vec<f32>,
    b2: Vec<f32>,
    s: Vec<f32>,
    z: Vec<f32>,
}

impl Squeeze {
    #[inline(always)]
    fn run<const FMA: bool>(&mut self, y: &mut [f32]) {
        let (c, m) = (self.b2.len(), self.b1.len());
        let hw = y.len() / c;
        self.s.fill(0.0);
        for row in y.chunks_exact(c) {
            self.s.iter_mut().zip(row).for_each(|(a, &v)| *a += v);
        }
        let inv = 1.0 / hw as f32;
        self.s.iter_mut().for_each(|v| *v *= inv);
        for j in 0..m {
            let d = dot::<FMA>(&self.w1[j * c..][..c], &self.s);
            self.z[j] = Act::Relu.apply(self.b1[j] + d);
        }
        // The gate replaces the pooled vector, which is no longer needed.
        for ch in 0..c {
            let d = dot::<FMA>(&self.w2[ch * m..][..m], &self.z);
            self.s[ch] = Act::HSigmoid.apply(self.b2[ch] + d);
        }
        for row in y.chunks_exact_mut(c) {
            row.iter_mut().zip(&self.s).for_each(|(v, &g)| *v *= g);
        }
    }
}

/// One inverted-residual block at a fixed input size.
struct Block {
    expand: Option<Pointwise>,
    dw: Depthwise,
    se: Option<Squeeze>,
    project: Pointwise,
    residual: bool,
    /// Middle channels; input and output planes (pixels).
    mid: usize,
    hw_in: usize,
    hw_out: usize,
    /// Output (hw_out × cout).
    out: Vec<f32>,
}

/// Bilinear resampling of HWC features of `c` channels between two fixed sizes, separable:
/// rows first (into `tmp`, hi × wo × c), then columns, each a straight pass along contiguous
/// memory. The arithmetic is that of [`crate::resize`]'s (rows blended, then the two rows).
struct Resize {
    ty: Vec<(usize, usize, f32)>,
    tx: Vec<(usize, usize, f32)>,
    wi: usize,
    c: usize,
    tmp: Vec<f32>,
}

impl Resize {
    fn new(hi: usize, wi: usize, ho: usize, wo: usize, c: usize) -> Self {
        Self {
            ty: taps(hi, ho),
            tx: taps(wi, wo),
            wi,
            c,
            tmp: vec![0.0; hi * wo * c],
        }
    }
    #[inline(always)]
    fn run(&mut self, x: &[f32], out: &mut [f32], add: bool) {
        let (c, wi, wo) = (self.c, self.wi, self.tx.len());
        let row_out = wo * c;
        // Only the input rows some output row reads are blended.
        let mut last = usize::MAX;
        for &(y0, y1, _) in &self.ty {
            for iy in [y0, y1] {
                // Taps are non-decreasing, so every row at or below `last` is done.
                if last != usize::MAX && iy <= last {
                    continue;
                }
                last = iy;
                let src = &x[iy * wi * c..][..wi * c];
                let dst = &mut self.tmp[iy * row_out..][..row_out];
                for (d, &(x0, x1, lx)) in dst.chunks_exact_mut(c).zip(&self.tx) {
                    let (a, b) = (&src[x0 * c..][..c], &src[x1 * c..][..c]);
                    for ((o, &va), &vb) in d.iter_mut().zip(a).zip(b) {
                        *o = va * (1.0 - lx) + vb * lx;
                    }
                }
            }
        }
        for (orow, &(y0, y1, ly)) in out.chunks_exact_mut(row_out).zip(&self.ty) {
            let (a, b) = (
                &self.tmp[y0 * row_out..][..row_out],
                &self.tmp[y1 * row_out..][..row_out],
            );
            let rows = orow.iter_mut().zip(a).zip(b);
            if add {
                rows.for_each(|((o, &va), &vb)| *o += va * (1.0 - ly) + vb * ly);
            } else {
                rows.for_each(|((o, &va), &vb)| *o = va * (1.0 - ly) + vb * ly);
            }
        }
    }
}

/// What one inference returns: pupil-mask logits at the input size (H × W, row-major) and the
/// slippage Δt in the units of the training targets.
#[derive(Debug)]
pub struct InferenceOutput<'a> {
    /// Mask logits (H·W).
    pub mask_logits: &'a [f32],
    /// Slippage Δt (x, y, z).
    pub slip: [f32; 3],
}

/// A subnet compiled for batch-1 inference at one input size (see the module docs).
pub struct Inference {
    /// Input channels, height, width (pixels).
    cin: usize,
    h: usize,
    w: usize,
    /// Network input after the resolution scale, per input plane (None: same size).
    scale: Option<Resize>,
    xr: Vec<f32>,
    stem: Stem,
    stem_out: Vec<f32>,
    blocks: Vec<Block>,
    /// Index in `blocks` of the stride-8 output (the stride-2 one is block 0, the stride-32
    /// one the last).
    i8: usize,
    /// Shared buffers of the blocks' middle features.
    mid_a: Vec<f32>,
    mid_b: Vec<f32>,
    // Decoder: projections, resizes, buffers.
    dec: [Pointwise; 4],
    up32: Resize,
    up8: Resize,
    up2: Resize,
    p32: Vec<f32>,
    p8: Vec<f32>,
    p2: Vec<f32>,
    lo: Vec<f32>,
    logits: Vec<f32>,
    // Calibration head.
    head_expand: Pointwise,
    head_map: Vec<f32>,
    head_g: Vec<f32>,
    /// The last stage's feature map (rows, columns).
    head_hw: (usize, usize),
    /// The stride-8 feature map (rows, columns).
    head_hw8: (usize, usize),
    hidden: HalfDense,
    hidden_out: Vec<f32>,
    slip_head: Pointwise,
}

fn block_for(b: &MbBlock, k: usize, e: usize, (h, w): (usize, usize)) -> (Block, (usize, usize)) {
    let mid = b.mid_for(e);
    let expand = b.expand.as_ref().map(|w1| {
        let mut wm = w1.value[..mid * b.cin].to_vec();
        let bias = fold(&b.bn1, &mut wm, mid, None);
        Pointwise::new(&wm, bias, b.cin, mid, b.act)
    });
    let (mut kernel, _, _) = elastic_kernel(&b.dw.value, &b.t5.value, &b.t3.value, mid, k);
    let kb = fold(&b.bn2, &mut kernel, mid, None);
    let g = Geom {
        h,
        w,
        ho: out_size(h, k, b.stride),
        wo: out_size(w, k, b.stride),
        k,
        s: b.stride,
    };
    let se = b.se.as_ref().map(|p| {
        let (w1, w2) = b.se_sub(p, mid);
        let m = w1.len() / mid;
        Squeeze {
            w1,
            b1: p.b1.value[..m].to_vec(),
            w2,
            b2: p.b2.value[..mid].to_vec(),
            s: vec![0.0; mid],
            z: vec![0.0; m],
        }
    });
    let mut w3 = sub_cols(&b.project.value, b.cout, b.max_mid, mid);
    let b3 = fold(&b.bn3, &mut w3, b.cout, None);
    let hw_out = g.ho * g.wo;
    let blk = Block {
        expand,
        dw: Depthwise {
            wt: transpose(&kernel, mid, k * k),
            b: kb,
            g,
            act: b.act,
        },
        se,
        project: Pointwise::new(&w3, b3, mid, b.cout, Act::Identity),
        residual: b.residual(),
        mid,
        hw_in: h * w,
        hw_out,
        out: vec![0.0; b.cout * hw_out],
    };
    (blk, (g.ho, g.wo))
}

fn dense(d: &crate::supernet::Dense, cin: usize, act: Act) -> Pointwise {
    Pointwise::new(&d.w.value, d.b.value.clone(), cin, d.cout, act)
}

/// The x̂ then ŷ means (`pool::moments_forward`) of a channels-innermost map of `rows` ×
/// `cols` pixels into `out` (2·C values).
fn moments_hwc(map: &[f32], (rows, cols): (usize, usize), out: &mut [f32]) {
    let c = out.len() / 2;
    out.fill(0.0);
    let (mx, my) = out.split_at_mut(c);
    for (i, line) in map.chunks_exact(c * cols).enumerate() {
        let yi = centred_coordinate(i, rows);
        for (j, px) in line.chunks_exact(c).enumerate() {
            let xj = centred_coordinate(j, cols);
            for ((x, y), &v) in mx.iter_mut().zip(my.iter_mut()).zip(px) {
                *x += xj * v;
                *y += yi * v;
            }
        }
    }
    let inv = 1.0 / (rows * cols) as f32;
    out.iter_mut().for_each(|v| *v *= inv);
}

impl Inference {
    /// Compiles subnet `arch` of `net` (its current, inference-mode batch-norm statistics:
    /// recalibrate first) for single images of `h` × `w` pixels.
    pub fn new(net: &Supernet, arch: &Arch, h: usize, w: usize) -> Result<Self> {
        arch.validate()?;
        if h == 0 || w == 0 {
            return Err(NetsError::Shape(format!("inference input {h}×{w}")));
        }
        let cin = net.config.in_channels;
        let (hs, ws) = (arch.scaled(h), arch.scaled(w));
        // Bound what the buffers will hold before allocating any (the widest stage-1 features
        // at stride 2 dominate: 16·6 channels).
        let est = (cin + 128) as u128 * (hs as u128 * ws as u128 + h as u128 * w as u128);
        if est > MAX_FLOATS as u128 {
            return Err(NetsError::Shape(format!(
                "inference input {h}×{w} needs more than {MAX_FLOATS} activation values"
            )));
        }
        let scale = ((hs, ws) != (h, w)).then(|| Resize::new(h, w, hs, ws, 1));
        let (h2, w2) = (out_size(hs, 3, 2), out_size(ws, 3, 2));
        let mut stem_k = net.stem.value.clone();
        let stem_b = fold(&net.stem_bn, &mut stem_k, STEM_CHANNELS, None);
        let stem = Stem {
            // (cout × cin·9) → (cin·9 × cout).
            wt: transpose(&stem_k, STEM_CHANNELS, cin * 9),
            b: stem_b,
            g: Geom {
                h: hs,
                w: ws,
                ho: h2,
                wo: w2,
                k: 3,
                s: 2,
            },
            cin,
        };
        let mut blocks = Vec::new();
        let (b0, mut size) = block_for(&net.blocks[0], 3, 1, (h2, w2));
        blocks.push(b0);
        let (mut i8, mut size8) = (0, size);
        for s in 0..N_STAGES {
            for b in 0..arch.depth[s] {
                let l = s * 4 + b;
                let (blk, sz) = block_for(&net.blocks[1 + l], arch.kernel[l], arch.expand[l], size);
                blocks.push(blk);
                size = sz;
            }
            if s == 1 {
                i8 = blocks.len() - 1;
                size8 = size;
            }
        }
        let mid_len = blocks
            .iter()
            .map(|b| b.mid * b.hw_in.max(b.hw_out))
            .max()
            .unwrap_or(0);
        let cfg = &net.config;
        let dw = cfg.decoder_width;
        let c_last = net.blocks.last().map_or(0, |b| b.cout);
        let mut he_w = net.head_expand.value.clone();
        let he_b = fold(&net.head_bn, &mut he_w, cfg.head_expand, None);
        let hw32 = size.0 * size.1;
        Ok(Self {
            cin,
            h,
            w,
            xr: if scale.is_some() {
                vec![0.0; cin * hs * ws]
            } else {
                Vec::new()
            },
            scale,
            stem,
            stem_out: vec![0.0; STEM_CHANNELS * h2 * w2],
            blocks,
            i8,
            mid_a: vec![0.0; mid_len],
            mid_b: vec![0.0; mid_len],
            dec: [
                dense(&net.dec[0], c_last, Act::Identity),
                dense(&net.dec[1], net.dec[1].w.value.len() / dw, Act::Identity),
                dense(&net.dec[2], STEM_CHANNELS, Act::Identity),
                dense(&net.dec[3], dw, Act::Identity),
            ],
            up32: Resize::new(size.0, size.1, size8.0, size8.1, dw),
            up8: Resize::new(size8.0, size8.1, h2, w2, dw),
            up2: Resize::new(h2, w2, h, w, 1),
            p32: vec![0.0; dw * hw32],
            p8: vec![0.0; dw * size8.0 * size8.1],
            p2: vec![0.0; dw * h2 * w2],
            lo: vec![0.0; h2 * w2],
            logits: vec![0.0; h * w],
            head_expand: Pointwise::new(&he_w, he_b, c_last, cfg.head_expand, Act::HSwish),
            head_map: vec![0.0; cfg.head_expand * hw32],
            head_g: vec![0.0; head_inputs(cfg.head_expand)],
            head_hw: size,
            head_hw8: size8,
            hidden: HalfDense::new(&net.head_hidden, head_inputs(cfg.head_expand), Act::HSwish),
            hidden_out: vec![0.0; cfg.head_hidden],
            slip_head: dense(&net.head_out, cfg.head_hidden, Act::Identity),
        })
    }
    /// The most (any axis, in Δt's unit) by which the half-precision weights of the
    /// calibration head's hidden layer can have moved the last [`Self::run`]'s Δt from what
    /// f32 weights give: each weight's rounding (≤ 2⁻¹¹ of it, ≤ 2⁻²⁵ below f16's normal
    /// range) summed with the layer's inputs, through hard-swish (Lipschitz 1.5) and the slip
    /// head. 0 before the first run.
    pub fn slip_rounding_bound(&self) -> f32 {
        let hd = &self.hidden;
        let x = &self.head_g;
        let sx: f32 = x.iter().map(|v| v.abs()).sum();
        // |w| ≤ |w₁₆|/(1 − 2⁻¹¹) for a normal weight, so its rounding is ≤ 2⁻¹¹/(1 − 2⁻¹¹)·|w₁₆|.
        let rel = 2f32.powi(-11) / (1.0 - 2f32.powi(-11));
        let mut dy = vec![2f32.powi(-25) * sx; hd.cout];
        for (&xi, row) in x.iter().zip(hd.wt.chunks_exact(hd.cout)) {
            for (d, &w) in dy.iter_mut().zip(row) {
                *d += rel * (xi * half::f16::from_bits(w).to_f32()).abs();
            }
        }
        let sh = &self.slip_head;
        (0..sh.cout)
            .map(|k| {
                dy.iter()
                    .enumerate()
                    .map(|(j, d)| sh.wt[j * sh.cout + k].abs() * 1.5 * d)
                    .sum::<f32>()
            })
            .fold(0.0, f32::max)
    }

    /// Input size (height, width) in pixels.
    pub fn input_size(&self) -> (usize, usize) {
        (self.h, self.w)
    }

    /// One image `x` (C_in × H × W, row-major planes) through the subnet.
    pub fn run(&mut self, x: &[f32]) -> Result<InferenceOutput<'_>> {
        let (h, w, cin) = (self.h, self.w, self.cin);
        if x.len() != cin * h * w {
            return Err(NetsError::Shape(format!(
                "inference input of {} values, expected {cin}×{h}×{w}",
                x.len()
            )));
        }
        #[cfg(target_arch = "x86_64")]
        let slip = if has_fma() {
            // SAFETY: AVX2 and FMA were detected on this CPU just above.
            unsafe { self.pass_fma(x) }
        } else {
            self.pass::<false>(x)
        };
        #[cfg(not(target_arch = "x86_64"))]
        let slip = self.pass::<false>(x);
        Ok(InferenceOutput {
            mask_logits: &self.logits,
            slip,
        })
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    fn pass_fma(&mut self, x: &[f32]) -> [f32; 3] {
        self.pass::<true>(x)
    }

    /// The forward pass of [`Self::run`] on a checked input; returns the slippage.
    #[inline(always)]
    fn pass<const FMA: bool>(&mut self, x: &[f32]) -> [f32; 3] {
        let (h, w) = (self.h, self.w);
        let xr: &[f32] = match &mut self.scale {
            Some(r) => {
                let (hwi, hwo) = (h * w, self.xr.len() / self.cin);
                for (src, dst) in x.chunks_exact(hwi).zip(self.xr.chunks_exact_mut(hwo)) {
                    r.run(src, dst, false);
                }
                &self.xr
            }
            None => x,
        };
        self.stem.run::<FMA>(xr, &mut self.stem_out);
        for bi in 0..self.blocks.len() {
            let (done, rest) = self.blocks.split_at_mut(bi);
            let b = &mut rest[0];
            let x: &[f32] = if bi == 0 {
                &self.stem_out
            } else {
                &done[bi - 1].out
            };
            let a1: &[f32] = match &b.expand {
                Some(e) => {
                    e.run(x, b.hw_in, &mut self.mid_a);
                    &self.mid_a
                }
                None => x,
            };
            let a2 = &mut self.mid_b[..b.mid * b.hw_out];
            b.dw.run::<FMA>(&a1[..b.mid * b.hw_in], a2);
            if let Some(se) = &mut b.se {
                se.run::<FMA>(a2);
            }
            b.project.run(a2, b.hw_out, &mut b.out);
            if b.residual {
                b.out.iter_mut().zip(x).for_each(|(o, v)| *o += v);
            }
        }
        let last = self.blocks.len() - 1;
        let (f2, f8, f32_) = (&self.blocks[0], &self.blocks[self.i8], &self.blocks[last]);
        // Perception decoder (FPN-like, as in `Supernet::forward`).
        self.dec[0].run(&f32_.out, f32_.hw_out, &mut self.p32);
        self.dec[1].run(&f8.out, f8.hw_out, &mut self.p8);
        self.up32.run(&self.p32, &mut self.p8, true);
        act_pass(&mut self.p8, Act::Relu);
        self.dec[2].run(&f2.out, f2.hw_out, &mut self.p2);
        self.up8.run(&self.p8, &mut self.p2, true);
        act_pass(&mut self.p2, Act::Relu);
        self.dec[3].run(&self.p2, f2.hw_out, &mut self.lo);
        self.up2.run(&self.lo, &mut self.logits, false);
        // Calibration head: the expansion's channel means, then the x, y moments of the last
        // stage and of the stride-8 stage (as in `Supernet::forward`).
        self.head_expand
            .run(&f32_.out, f32_.hw_out, &mut self.head_map);
        let c_last = f32_.out.len() / f32_.hw_out;
        let (m, rest) = self.head_g.split_at_mut(self.head_map.len() / f32_.hw_out);
        m.fill(0.0);
        for px in self.head_map.chunks_exact(m.len()) {
            m.iter_mut().zip(px).for_each(|(a, &v)| *a += v);
        }
        let inv = 1.0 / f32_.hw_out as f32;
        m.iter_mut().for_each(|v| *v *= inv);
        let (m32, m8) = rest.split_at_mut(2 * c_last);
        moments_hwc(&f32_.out, self.head_hw, m32);
        moments_hwc(&f8.out, self.head_hw8, m8);
        self.hidden.run(&self.head_g, &mut self.hidden_out);
        let mut slip = [0.0f32; 3];
        self.slip_head.run(&self.hidden_out, 1, &mut slip);
        slip
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::norm::BnMode;
    use crate::tensor::Tensor;
    use crate::{Arch, SupernetConfig};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn matches_the_supernet_in_eval_mode() {
        // One input channel (the camera) and two, so that the stem's sum over input planes
        // is exercised too.
        for cin in [1, 2] {
            matches_the_supernet(cin);
        }
    }

    fn matches_the_supernet(cin: usize) {
        let cfg = SupernetConfig {
            head_expand: 48,
            head_hidden: 32,
            in_channels: cin,
            ..SupernetConfig::default()
        };
        let mut net = Supernet::new(cfg, 7).unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        // Non-trivial affine parameters, so that folding them is exercised; the statistics
        // come from recalibration, as in every evaluation and in the tracker.
        net.visit_bn(&mut |_, bn| {
            for i in 0..bn.channels() {
                bn.gamma.value[i] = rng.random_range(0.5..1.5);
                bn.beta.value[i] = rng.random_range(-0.3..0.3);
            }
        });
        let mut scaled = Arch::sample(&mut rng);
        scaled.resolution_scale = 0.63;
        for (arch, h, w) in [
            (Arch::min(), 40, 56),
            (Arch::max(), 37, 50),
            (scaled, 45, 61),
        ] {
            let mut img = || -> Vec<f32> {
                (0..cin * h * w)
                    .map(|_| rng.random_range(0.0..1.0))
                    .collect()
            };
            let calib: Vec<f32> = (0..4).flat_map(|_| img()).collect();
            let calib = Tensor::from_vec(4, cin, h, w, calib).unwrap();
            net.recalibrate_bn(&arch, &[calib]).unwrap();
            let x = img();
            let t = Tensor::from_vec(1, cin, h, w, x.clone()).unwrap();
            let want = net.forward(&arch, &t, BnMode::Eval).unwrap();
            // How far f32 rounding alone moves the reference: the same forward pass on the
            // input scaled by (1 + 2⁻²²), about two ulps. An untrained, recalibrated network
            // amplifies it to ~3e-5 of the largest logit through 20 blocks; the compiled
            // path (BN folded into the weights, sums in another order) must stay within a
            // few such perturbations.
            let xp: Vec<f32> = x.iter().map(|v| v * (1.0 + 2f32.powi(-22))).collect();
            let tp = Tensor::from_vec(1, cin, h, w, xp).unwrap();
            let near = net.forward(&arch, &tp, BnMode::Eval).unwrap();
            let maxdiff = |a: &[f32], b: &[f32]| {
                a.iter()
                    .zip(b)
                    .fold(0.0f32, |m, (p, q)| m.max((p - q).abs()))
            };
            let scale = want
                .mask_logits
                .data
                .iter()
                .fold(1.0f32, |m, v| m.max(v.abs()));
            let tol_logits =
                1e-6 * scale + 4.0 * maxdiff(&near.mask_logits.data, &want.mask_logits.data);
            let slip_scale = want.slip.data.iter().fold(1.0f32, |m, v| m.max(v.abs()));
            let tol_slip = 1e-6 * slip_scale + 4.0 * maxdiff(&near.slip.data, &want.slip.data);
            let mut inf = Inference::new(&net, &arch, h, w).unwrap();
            // Twice: buffers reused across frames must not leak state between them.
            for _ in 0..2 {
                let got = inf.run(&x).unwrap();
                let (logits, slip) = (got.mask_logits.to_vec(), got.slip);
                let err = maxdiff(&logits, &want.mask_logits.data);
                assert!(
                    err <= tol_logits,
                    "logits differ by {err} (tolerance {tol_logits})"
                );
                // The hidden layer's f16 weights (HalfDense) move Δt by at most this.
                let f16_bound = inf.slip_rounding_bound();
                assert!(f16_bound > 0.0 && f16_bound.is_finite());
                let err = maxdiff(&slip, &want.slip.data);
                assert!(
                    err <= tol_slip + f16_bound,
                    "slip differs by {err} (tolerance {tol_slip} + f16 bound {f16_bound})"
                );
            }
        }
    }

    #[test]
    fn half_dense_computes_the_product_with_the_rounded_weights() {
        use crate::supernet::Dense;
        use crate::tensor::Param;
        // Odd sizes: the four-row groups and the eight-wide columns both leave remainders.
        for (cin, cout) in [(7, 37), (8, 16), (1, 3), (13, 1), (1360, 1280)] {
            let mut rng = ChaCha8Rng::seed_from_u64((cin * 1000 + cout) as u64);
            // Weights over many magnitudes, down into f16's subnormal range.
            let w: Vec<f32> = (0..cin * cout)
                .map(|_| rng.random_range(-1.0f32..1.0) * 10f32.powi(rng.random_range(-7..1)))
                .collect();
            let b: Vec<f32> = (0..cout).map(|_| rng.random_range(-1.0..1.0)).collect();
            let x: Vec<f32> = (0..cin).map(|_| rng.random_range(-2.0..2.0)).collect();
            let d = Dense {
                w: Param::new(w.clone()),
                b: Param::new(b.clone()),
                cout,
            };
            let hd = HalfDense::new(&d, cin, Act::Identity);
            let mut y = vec![f32::NAN; cout];
            hd.run(&x, &mut y);
            for j in 0..cout {
                let row = &w[j * cin..(j + 1) * cin];
                // The same product in f64 with each weight rounded to f16 first ...
                let want: f64 = b[j] as f64
                    + row
                        .iter()
                        .zip(&x)
                        .map(|(&wi, &xi)| half::f16::from_f32(wi).to_f64() * xi as f64)
                        .sum::<f64>();
                let mag: f64 = row.iter().zip(&x).map(|(a, b)| (a * b).abs() as f64).sum();
                // ... which an f32 sum of cin terms meets within cin ulps of its magnitude.
                let tol = (cin as f64 + 2.0) * f32::EPSILON as f64 * (mag + b[j].abs() as f64);
                assert!(
                    (y[j] as f64 - want).abs() <= tol,
                    "{cin}×{cout}, output {j}: {} vs {want} (tolerance {tol})",
                    y[j]
                );
                // And the rounding itself stays within its bound of the f32 weights' product.
                let exact: f64 = b[j] as f64
                    + row
                        .iter()
                        .zip(&x)
                        .map(|(&wi, &xi)| wi as f64 * xi as f64)
                        .sum::<f64>();
                let sx: f64 = x.iter().map(|v| v.abs() as f64).sum();
                let bound = 2f64.powi(-11) * mag + 2f64.powi(-25) * sx;
                assert!(
                    (want - exact).abs() <= bound,
                    "rounding {} > {bound}",
                    want - exact
                );
            }
        }
    }

    #[test]
    fn refuses_wrong_inputs() {
        let net = Supernet::new(SupernetConfig::default(), 1).unwrap();
        assert!(Inference::new(&net, &Arch::min(), 0, 8).is_err());
        assert!(Inference::new(&net, &Arch::min(), 1 << 20, 1 << 20).is_err());
        let mut inf = Inference::new(&net, &Arch::min(), 16, 16).unwrap();
        assert!(inf.run(&[0.0; 10]).is_err());
    }
}

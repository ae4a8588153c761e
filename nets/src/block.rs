//! Elastic inverted-residual block (MBConv): 1×1 expansion, depthwise k×k, optional SE,
//! 1×1 projection, residual when shapes allow. Holds the widest weights; a forward pass uses
//! the first `mid` middle channels (elastic width) and a k×k kernel derived from the stored
//! 7×7 one by centre crop and learned transforms (elastic kernel).

use crate::act::Act;
use crate::arch::{mid_channels, se_channels};
use crate::conv::{depthwise_forward, depthwise_vjp, pointwise_forward, pointwise_vjp};
use crate::dense::{gemm, rm};
use crate::error::{NetsError, Result};
use crate::norm::{BatchNorm, BnMode};
use crate::se::{SeCache, SeGrads, SeWeights, se_forward, se_vjp};
use crate::tensor::{Param, Tensor};
use faer::Accum;
use rand::Rng;
use rand_distr::{Distribution, Normal};

/// Largest depthwise kernel stored.
pub const KMAX: usize = 7;

/// Fills a parameter with N(0, std²) draws.
pub fn normal_param<R: Rng + ?Sized>(rng: &mut R, len: usize, std: f32) -> Param {
    let d = Normal::new(0.0f32, std.max(1e-12))
        .unwrap_or_else(|_| Normal::new(0.0, 1.0).expect("unit normal"));
    Param::new((0..len).map(|_| d.sample(rng)).collect())
}

fn identity(n: usize) -> Param {
    let mut v = vec![0.0f32; n * n];
    for i in 0..n {
        v[i * n + i] = 1.0;
    }
    Param::new(v)
}

/// Copies the centre `k`×`k` of a `big`×`big` kernel.
fn crop(src: &[f32], big: usize, k: usize, dst: &mut [f32]) {
    let o = (big - k) / 2;
    for y in 0..k {
        dst[y * k..(y + 1) * k].copy_from_slice(&src[(y + o) * big + o..][..k]);
    }
}

/// Adds a `k`×`k` kernel into the centre of a `big`×`big` one.
fn uncrop_add(src: &[f32], k: usize, big: usize, dst: &mut [f32]) {
    let o = (big - k) / 2;
    for y in 0..k {
        for x in 0..k {
            dst[(y + o) * big + o + x] += src[y * k + x];
        }
    }
}

/// Effective kernels of `mid` channels at size k from 7×7 weights and transforms T5 (25×25),
/// T3 (9×9): k5 = crop5(w7)·T5, k3 = crop3(k5)·T3. Returns (kernel, crop25, crop9) per channel.
pub fn elastic_kernel(
    w7: &[f32],
    t5: &[f32],
    t3: &[f32],
    mid: usize,
    k: usize,
) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    if k == KMAX {
        return (w7[..mid * 49].to_vec(), Vec::new(), Vec::new());
    }
    // All channels at once: K5 (mid × 25) = C25·T5, K3 (mid × 9) = C9·T3.
    let mut c25 = vec![0.0f32; mid * 25];
    for ch in 0..mid {
        crop(&w7[ch * 49..][..49], 7, 5, &mut c25[ch * 25..][..25]);
    }
    let mut k5 = vec![0.0f32; mid * 25];
    gemm(
        &mut k5,
        mid,
        25,
        Accum::Replace,
        rm(&c25, mid, 25),
        rm(t5, 25, 25),
    );
    if k == 5 {
        return (k5, c25, Vec::new());
    }
    let mut c9 = vec![0.0f32; mid * 9];
    for ch in 0..mid {
        crop(&k5[ch * 25..][..25], 5, 3, &mut c9[ch * 9..][..9]);
    }
    let mut k3 = vec![0.0f32; mid * 9];
    gemm(
        &mut k3,
        mid,
        9,
        Accum::Replace,
        rm(&c9, mid, 9),
        rm(t3, 9, 9),
    );
    (k3, c25, c9)
}

/// VJP of [`elastic_kernel`]: adds gradients into dW7, dT5, dT3 from dL/dkernel.
#[allow(clippy::too_many_arguments)]
pub fn elastic_kernel_vjp(
    t5: &[f32],
    t3: &[f32],
    c25: &[f32],
    c9: &[f32],
    mid: usize,
    k: usize,
    dk: &[f32],
    dw7: &mut [f32],
    dt5: &mut [f32],
    dt3: &mut [f32],
) {
    if k == KMAX {
        for (a, b) in dw7[..mid * 49].iter_mut().zip(dk) {
            *a += b;
        }
        return;
    }
    // All channels at once: dT += Cᵀ·dK and dC = dK·Tᵀ per stage, then the crops' adjoints.
    let mut dk5 = vec![0.0f32; mid * 25];
    if k == 3 {
        let g = &dk[..mid * 9];
        gemm(
            dt3,
            9,
            9,
            Accum::Add,
            rm(c9, mid, 9).transpose(),
            rm(g, mid, 9),
        );
        let mut dc9 = vec![0.0f32; mid * 9];
        gemm(
            &mut dc9,
            mid,
            9,
            Accum::Replace,
            rm(g, mid, 9),
            rm(t3, 9, 9).transpose(),
        );
        for ch in 0..mid {
            uncrop_add(&dc9[ch * 9..][..9], 3, 5, &mut dk5[ch * 25..][..25]);
        }
    } else {
        dk5.copy_from_slice(&dk[..mid * 25]);
    }
    gemm(
        dt5,
        25,
        25,
        Accum::Add,
        rm(c25, mid, 25).transpose(),
        rm(&dk5, mid, 25),
    );
    let mut dc25 = vec![0.0f32; mid * 25];
    gemm(
        &mut dc25,
        mid,
        25,
        Accum::Replace,
        rm(&dk5, mid, 25),
        rm(t5, 25, 25).transpose(),
    );
    for ch in 0..mid {
        uncrop_add(&dc25[ch * 25..][..25], 5, 7, &mut dw7[ch * 49..][..49]);
    }
}

/// Squeeze-excitation parameters at the widest size: W1 (S × M), b1, W2 (M × S), b2.
#[derive(Clone, Debug)]
pub struct SeParams {
    /// Squeeze weights, widest (S_max × M_max).
    pub w1: Param,
    /// Squeeze bias.
    pub b1: Param,
    /// Excite weights, widest (M_max × S_max).
    pub w2: Param,
    /// Excite bias.
    pub b2: Param,
}

struct Cache {
    x: Tensor,
    /// The depthwise input: the expansion's activation, or None when it is `x` itself.
    a1: Option<Tensor>,
    a2: Tensor,
    /// SE weights and cache, and its output (the projection's input); without SE that input
    /// is `a2`.
    se: Option<(Vec<f32>, Vec<f32>, SeCache, Tensor)>,
    kernel: Vec<f32>,
    c25: Vec<f32>,
    c9: Vec<f32>,
    w3: Vec<f32>,
    mid: usize,
    k: usize,
}

/// One elastic MBConv block.
pub struct MbBlock {
    /// Input channels.
    pub cin: usize,
    /// Output channels.
    pub cout: usize,
    /// Depthwise stride.
    pub stride: usize,
    /// Activation of the middle features.
    pub act: Act,
    /// Widest middle width.
    pub max_mid: usize,
    /// 1×1 expansion (max_mid × cin); None for the expand-1 first block.
    pub expand: Option<Param>,
    /// Batch norm after the expansion.
    pub bn1: BatchNorm,
    /// Depthwise 7×7 weights (max_mid × 49).
    pub dw: Param,
    /// Learned 25×25 transform for 5×5 kernels.
    pub t5: Param,
    /// Learned 9×9 transform for 3×3 kernels.
    pub t3: Param,
    /// Batch norm after the depthwise conv.
    pub bn2: BatchNorm,
    /// Squeeze-excitation, if the stage has it.
    pub se: Option<SeParams>,
    /// 1×1 projection (cout × max_mid).
    pub project: Param,
    /// Batch norm after the projection.
    pub bn3: BatchNorm,
    cache: Option<Cache>,
}

impl MbBlock {
    /// A block with He-normal weights and identity kernel transforms; `expand_one` builds the
    /// fixed first block (no expansion, middle width = cin).
    pub fn new<R: Rng + ?Sized>(
        cin: usize,
        cout: usize,
        stride: usize,
        act: Act,
        se: bool,
        expand_one: bool,
        rng: &mut R,
    ) -> Self {
        let max_mid = if expand_one {
            cin
        } else {
            mid_channels(cin, 6)
        };
        let expand =
            (!expand_one).then(|| normal_param(rng, max_mid * cin, (2.0 / cin as f32).sqrt()));
        let se = se.then(|| {
            let s = se_channels(max_mid);
            SeParams {
                w1: normal_param(rng, s * max_mid, (2.0 / max_mid as f32).sqrt()),
                b1: Param::new(vec![0.0; s]),
                w2: normal_param(rng, max_mid * s, (1.0 / s as f32).sqrt()),
                b2: Param::new(vec![0.0; max_mid]),
            }
        });
        Self {
            cin,
            cout,
            stride,
            act,
            max_mid,
            expand,
            bn1: BatchNorm::new(max_mid),
            dw: normal_param(rng, max_mid * 49, (2.0f32 / 9.0).sqrt()),
            t5: identity(25),
            t3: identity(9),
            bn2: BatchNorm::new(max_mid),
            se,
            project: normal_param(rng, cout * max_mid, (1.0 / max_mid as f32).sqrt()),
            bn3: BatchNorm::new(cout),
            cache: None,
        }
    }

    /// Whether the block adds its input to its output.
    pub fn residual(&self) -> bool {
        self.stride == 1 && self.cin == self.cout
    }

    /// Middle width for expansion `e` (the fixed width of an expand-1 block).
    pub fn mid_for(&self, e: usize) -> usize {
        if self.expand.is_none() {
            self.max_mid
        } else {
            mid_channels(self.cin, e).min(self.max_mid)
        }
    }

    /// Forward pass with kernel `k` and expansion `e`.
    pub fn forward(&mut self, x: &Tensor, k: usize, e: usize, mode: BnMode) -> Result<Tensor> {
        if x.c != self.cin {
            return Err(NetsError::Shape(format!(
                "block expects {} channels, got {}",
                self.cin, x.c
            )));
        }
        let mid = self.mid_for(e);
        let (cin, act) = (self.cin, self.act);
        // The elastic kernel does not depend on x: its small serial GEMMs run beside the
        // expansion, which would otherwise leave the pool's other thread idle for them.
        let (a1, (kernel, c25, c9)) = rayon::join(
            // Each batch norm applies the activation after it in the same pass (`forward_act`).
            || -> Result<Option<Tensor>> {
                match &self.expand {
                    Some(w1) => {
                        let u1 = pointwise_forward(x, &w1.value[..mid * cin], mid, None)?;
                        Ok(Some(self.bn1.forward_act(u1, mode, act)?))
                    }
                    None => Ok(None),
                }
            },
            || elastic_kernel(&self.dw.value, &self.t5.value, &self.t3.value, mid, k),
        );
        let a1 = a1?;
        let u2 = depthwise_forward(a1.as_ref().unwrap_or(x), &kernel, k, self.stride)?;
        let a2 = self.bn2.forward_act(u2, mode, self.act)?;
        let se = match &self.se {
            Some(p) => {
                let (w1, w2) = self.se_sub(p, mid);
                let s = w1.len() / mid;
                let wt = SeWeights {
                    w1: &w1,
                    b1: &p.b1.value[..s],
                    w2: &w2,
                    b2: &p.b2.value[..mid],
                };
                let (y, c) = se_forward(&a2, &wt)?;
                Some((w1, w2, c, y))
            }
            None => None,
        };
        let a3 = se.as_ref().map_or(&a2, |s| &s.3);
        let w3 = sub_cols(&self.project.value, self.cout, self.max_mid, mid);
        let u3 = pointwise_forward(a3, &w3, self.cout, None)?;
        let mut y = self.bn3.forward_act(u3, mode, Act::Identity)?;
        if self.residual() {
            y.add_assign(x);
        }
        self.cache = Some(Cache {
            x: x.clone(),
            a1,
            a2,
            se,
            kernel,
            c25,
            c9,
            w3,
            mid,
            k,
        });
        Ok(y)
    }

    /// SE weights (W1, W2) restricted to the first `mid` middle channels.
    pub(crate) fn se_sub(&self, p: &SeParams, mid: usize) -> (Vec<f32>, Vec<f32>) {
        let smax = p.b1.len();
        let s = se_channels(mid).min(smax);
        let w1 = sub_cols(&p.w1.value, s, self.max_mid, mid);
        let w2 = sub_cols(&p.w2.value[..mid * smax], mid, smax, s);
        (w1, w2)
    }

    /// VJP of the last forward: returns dL/dx, accumulates every parameter gradient.
    pub fn backward(&mut self, dy: &Tensor) -> Result<Tensor> {
        let c = self
            .cache
            .take()
            .ok_or_else(|| NetsError::Shape("block backward without forward".into()))?;
        let mid = c.mid;
        let du3 = self.bn3.backward(dy)?;
        let mut dw3 = vec![0.0f32; c.w3.len()];
        let a3 = c.se.as_ref().map_or(&c.a2, |s| &s.3);
        let da3 = pointwise_vjp(a3, &c.w3, self.cout, &du3, &mut dw3, None)?;
        add_cols(&dw3, self.cout, self.max_mid, mid, &mut self.project.grad);
        let da2 = match (&mut self.se, &c.se) {
            (Some(p), Some((w1, w2, sc, _))) => {
                let smax = p.b1.len();
                let s = w1.len() / mid;
                let wt = SeWeights {
                    w1,
                    b1: &p.b1.value[..s],
                    w2,
                    b2: &p.b2.value[..mid],
                };
                let mut gw1 = vec![0.0f32; w1.len()];
                let mut gw2 = vec![0.0f32; w2.len()];
                let d = se_vjp(
                    &c.a2,
                    &wt,
                    sc,
                    &da3,
                    SeGrads {
                        w1: &mut gw1,
                        b1: &mut p.b1.grad[..s],
                        w2: &mut gw2,
                        b2: &mut p.b2.grad[..mid],
                    },
                )?;
                add_cols(&gw1, s, self.max_mid, mid, &mut p.w1.grad);
                add_cols(&gw2, mid, smax, s, &mut p.w2.grad[..mid * smax]);
                d
            }
            _ => da3,
        };
        let du2 = self.bn2.backward_owned(da2)?;
        let mut dk = vec![0.0f32; c.kernel.len()];
        let a1 = c.a1.as_ref().unwrap_or(&c.x);
        let da1 = depthwise_vjp(a1, &c.kernel, c.k, self.stride, &du2, &mut dk)?;
        let cin = self.cin;
        // The elastic kernel's VJP (small serial GEMMs) beside the expansion's backward: the
        // two touch disjoint parameters.
        let (dx, ()) = rayon::join(
            || -> Result<Tensor> {
                match (&mut self.expand, &c.a1) {
                    (Some(w1), Some(_)) => {
                        let du1 = self.bn1.backward_owned(da1)?;
                        let (wv, wg) = (&w1.value[..mid * cin], &mut w1.grad[..mid * cin]);
                        pointwise_vjp(&c.x, wv, mid, &du1, wg, None)
                    }
                    _ => Ok(da1),
                }
            },
            || {
                elastic_kernel_vjp(
                    &self.t5.value,
                    &self.t3.value,
                    &c.c25,
                    &c.c9,
                    mid,
                    c.k,
                    &dk,
                    &mut self.dw.grad,
                    &mut self.t5.grad,
                    &mut self.t3.grad,
                )
            },
        );
        let mut dx = dx?;
        if self.residual() {
            dx.add_assign(dy);
        }
        Ok(dx)
    }

    /// Visits every parameter with a name relative to the block.
    pub fn visit(&mut self, f: &mut dyn FnMut(&str, &mut Param)) {
        if let Some(w) = &mut self.expand {
            f("expand", w);
            f("bn1.gamma", &mut self.bn1.gamma);
            f("bn1.beta", &mut self.bn1.beta);
        }
        f("dw", &mut self.dw);
        f("t5", &mut self.t5);
        f("t3", &mut self.t3);
        f("bn2.gamma", &mut self.bn2.gamma);
        f("bn2.beta", &mut self.bn2.beta);
        if let Some(p) = &mut self.se {
            f("se.w1", &mut p.w1);
            f("se.b1", &mut p.b1);
            f("se.w2", &mut p.w2);
            f("se.b2", &mut p.b2);
        }
        f("project", &mut self.project);
        f("bn3.gamma", &mut self.bn3.gamma);
        f("bn3.beta", &mut self.bn3.beta);
    }

    /// Visits every batch-norm layer.
    pub fn visit_bn(&mut self, f: &mut dyn FnMut(&str, &mut BatchNorm)) {
        if self.expand.is_some() {
            f("bn1", &mut self.bn1);
        }
        f("bn2", &mut self.bn2);
        f("bn3", &mut self.bn3);
    }

    /// Sorts middle channels by importance (L1 norm of their projection column), most important
    /// first, permuting every tensor that indexes them so the widest block computes the same
    /// function; SE squeeze channels are sorted by the L1 norm of their excite column.
    pub fn reorganize(&mut self) {
        if self.expand.is_none() {
            return;
        }
        let (m, co) = (self.max_mid, self.cout);
        let imp: Vec<f32> = (0..m)
            .map(|j| (0..co).map(|o| self.project.value[o * m + j].abs()).sum())
            .collect();
        let mut order: Vec<usize> = (0..m).collect();
        order.sort_by(|&a, &b| imp[b].total_cmp(&imp[a]));
        permute_cols(&mut self.project.value, co, m, &order);
        if let Some(w) = &mut self.expand {
            permute_rows(&mut w.value, m, self.cin, &order);
        }
        for bn in [&mut self.bn1, &mut self.bn2] {
            permute_rows(&mut bn.gamma.value, m, 1, &order);
            permute_rows(&mut bn.beta.value, m, 1, &order);
            permute_rows(&mut bn.running_mean, m, 1, &order);
            permute_rows(&mut bn.running_var, m, 1, &order);
        }
        permute_rows(&mut self.dw.value, m, 49, &order);
        if let Some(p) = &mut self.se {
            let s = p.b1.len();
            permute_cols(&mut p.w1.value, s, m, &order);
            permute_rows(&mut p.w2.value, m, s, &order);
            permute_rows(&mut p.b2.value, m, 1, &order);
            let simp: Vec<f32> = (0..s)
                .map(|j| (0..m).map(|c| p.w2.value[c * s + j].abs()).sum())
                .collect();
            let mut so: Vec<usize> = (0..s).collect();
            so.sort_by(|&a, &b| simp[b].total_cmp(&simp[a]));
            permute_cols(&mut p.w2.value, m, s, &so);
            permute_rows(&mut p.w1.value, s, m, &so);
            permute_rows(&mut p.b1.value, s, 1, &so);
        }
    }
}

/// The first `c` columns of a row-major (rows × stride) matrix, packed.
pub(crate) fn sub_cols(src: &[f32], rows: usize, stride: usize, c: usize) -> Vec<f32> {
    let mut out = Vec::with_capacity(rows * c);
    for r in 0..rows {
        out.extend_from_slice(&src[r * stride..][..c]);
    }
    out
}

/// Adds a packed (rows × c) matrix into the first `c` columns of a (rows × stride) one.
fn add_cols(src: &[f32], rows: usize, stride: usize, c: usize, dst: &mut [f32]) {
    for r in 0..rows {
        for (a, b) in dst[r * stride..][..c].iter_mut().zip(&src[r * c..][..c]) {
            *a += b;
        }
    }
}

fn permute_rows(v: &mut [f32], rows: usize, cols: usize, order: &[usize]) {
    let old = v[..rows * cols].to_vec();
    for (new_r, &old_r) in order.iter().enumerate() {
        v[new_r * cols..][..cols].copy_from_slice(&old[old_r * cols..][..cols]);
    }
}

fn permute_cols(v: &mut [f32], rows: usize, cols: usize, order: &[usize]) {
    let old = v[..rows * cols].to_vec();
    for r in 0..rows {
        for (new_c, &old_c) in order.iter().enumerate() {
            v[r * cols + new_c] = old[r * cols + old_c];
        }
    }
}

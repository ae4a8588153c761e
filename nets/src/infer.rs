//! Batch-1 inference of one subnet on the calling thread, for the tracker: batch norms folded
//! into the convolutions before them, elastic kernels and weight sub-matrices extracted once,
//! every activation buffer allocated once at construction, no gradient state. Computes the same
//! function as [`Supernet::forward`] in [`crate::BnMode::Eval`] (to float rounding).

use crate::act::Act;
use crate::arch::{Arch, N_STAGES, STEM_CHANNELS};
use crate::block::{MbBlock, elastic_kernel, sub_cols};
use crate::conv::out_size;
use crate::depthwise::{self, Geom, Scratch};
use crate::error::{NetsError, Result};
use crate::norm::BatchNorm;
use crate::resize::{resize_plane, taps};
use crate::supernet::Supernet;
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

/// Adds the per-channel bias and applies the activation over `hw`-sized planes.
#[inline]
fn bias_act(y: &mut [f32], hw: usize, b: &[f32], act: Act) {
    // One loop per activation, so that each is a straight vectorizable pass.
    fn pass(y: &mut [f32], hw: usize, b: &[f32], f: impl Fn(f32) -> f32) {
        for (row, &bo) in y.chunks_exact_mut(hw).zip(b) {
            row.iter_mut().for_each(|v| *v = f(*v + bo));
        }
    }
    match act {
        Act::Identity => pass(y, hw, b, |v| v),
        Act::Relu => pass(y, hw, b, |v| v.max(0.0)),
        Act::HSwish => pass(y, hw, b, |v| Act::HSwish.apply(v)),
        Act::HSigmoid => pass(y, hw, b, |v| Act::HSigmoid.apply(v)),
    }
}

/// A 1×1 convolution with bias and activation: W (cout × cin).
struct Pointwise {
    w: Vec<f32>,
    b: Vec<f32>,
    cin: usize,
    cout: usize,
    act: Act,
}

impl Pointwise {
    fn run(&self, x: &[f32], hw: usize, y: &mut [f32]) {
        let wm = MatRef::from_row_major_slice(&self.w, self.cout, self.cin);
        let xm = MatRef::from_row_major_slice(&x[..self.cin * hw], self.cin, hw);
        let y = &mut y[..self.cout * hw];
        matmul(
            MatMut::from_row_major_slice_mut(y, self.cout, hw),
            Accum::Replace,
            wm,
            xm,
            1.0f32,
            Par::Seq,
        );
        bias_act(y, hw, &self.b, self.act);
    }
}

/// A per-channel k×k convolution (depthwise, or the stem's one input channel per tap set) with
/// bias and activation.
struct Spatial {
    /// Kernels, (cout × cin_per_out) blocks of k².
    k: Vec<f32>,
    b: Vec<f32>,
    g: Geom,
    act: Act,
}

/// Squeeze-and-excitation with its pooled vector and squeeze activations.
struct Squeeze {
    w1: Vec<f32>,
    b1: Vec<f32>,
    w2: Vec<f32>,
    b2: Vec<f32>,
    s: Vec<f32>,
    z: Vec<f32>,
}

impl Squeeze {
    fn run(&mut self, y: &mut [f32], hw: usize) {
        let (c, m) = (self.b2.len(), self.b1.len());
        for (s, p) in self.s.iter_mut().zip(y.chunks_exact(hw)) {
            *s = p.iter().sum::<f32>() / hw as f32;
        }
        for j in 0..m {
            let d: f32 = self.w1[j * c..][..c]
                .iter()
                .zip(&self.s)
                .map(|(w, v)| w * v)
                .sum();
            self.z[j] = Act::Relu.apply(self.b1[j] + d);
        }
        for (ch, p) in y.chunks_exact_mut(hw).enumerate() {
            let d: f32 = self.w2[ch * m..][..m]
                .iter()
                .zip(&self.z)
                .map(|(w, v)| w * v)
                .sum();
            let g = Act::HSigmoid.apply(self.b2[ch] + d);
            p.iter_mut().for_each(|v| *v *= g);
        }
    }
}

/// One inverted-residual block at a fixed input size.
struct Block {
    expand: Option<Pointwise>,
    dw: Spatial,
    se: Option<Squeeze>,
    project: Pointwise,
    residual: bool,
    /// Middle channels; input and output planes (pixels).
    mid: usize,
    hw_in: usize,
    hw_out: usize,
    /// Output (cout × hw_out).
    out: Vec<f32>,
}

/// Bilinear resampling between two fixed plane sizes.
struct Resize {
    ty: Vec<(usize, usize, f32)>,
    tx: Vec<(usize, usize, f32)>,
    hi: usize,
    wi: usize,
}

impl Resize {
    fn new(hi: usize, wi: usize, ho: usize, wo: usize) -> Self {
        Self {
            ty: taps(hi, ho),
            tx: taps(wi, wo),
            hi,
            wi,
        }
    }
    fn run(&self, x: &[f32], c: usize, out: &mut [f32], add: bool) {
        let (hwi, hwo) = (self.hi * self.wi, self.ty.len() * self.tx.len());
        for ch in 0..c {
            let src = &x[ch * hwi..][..hwi];
            let dst = &mut out[ch * hwo..][..hwo];
            resize_plane(src, self.wi, &self.ty, &self.tx, dst, add);
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
    /// Network input after the resolution scale (None: same size).
    scale: Option<Resize>,
    xr: Vec<f32>,
    stem: Spatial,
    stem_out: Vec<f32>,
    stem_plane: Vec<f32>,
    blocks: Vec<Block>,
    /// Index in `blocks` of the stride-8 output (the stride-2 one is block 0, the stride-32
    /// one the last).
    i8: usize,
    /// Shared buffers of the blocks' middle features.
    mid_a: Vec<f32>,
    mid_b: Vec<f32>,
    sc: Scratch,
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
    hidden: Pointwise,
    hidden_out: Vec<f32>,
    slip_head: Pointwise,
}

fn block_for(b: &MbBlock, k: usize, e: usize, (h, w): (usize, usize)) -> (Block, (usize, usize)) {
    let mid = b.mid_for(e);
    let expand = match &b.expand {
        Some(w1) => {
            let mut wm = w1.value[..mid * b.cin].to_vec();
            let bias = fold(&b.bn1, &mut wm, mid, None);
            Some(Pointwise {
                w: wm,
                b: bias,
                cin: b.cin,
                cout: mid,
                act: b.act,
            })
        }
        None => None,
    };
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
    let se = match &b.se {
        Some(p) => {
            let (w1, w2) = b.se_sub(p, mid);
            let m = w1.len() / mid;
            Some(Squeeze {
                w1,
                b1: p.b1.value[..m].to_vec(),
                w2,
                b2: p.b2.value[..mid].to_vec(),
                s: vec![0.0; mid],
                z: vec![0.0; m],
            })
        }
        None => None,
    };
    let mut w3 = sub_cols(&b.project.value, b.cout, b.max_mid, mid);
    let b3 = fold(&b.bn3, &mut w3, b.cout, None);
    let hw_out = g.ho * g.wo;
    let blk = Block {
        expand,
        dw: Spatial {
            k: kernel,
            b: kb,
            g,
            act: b.act,
        },
        se,
        project: Pointwise {
            w: w3,
            b: b3,
            cin: mid,
            cout: b.cout,
            act: Act::Identity,
        },
        residual: b.residual(),
        mid,
        hw_in: h * w,
        hw_out,
        out: vec![0.0; b.cout * hw_out],
    };
    (blk, (g.ho, g.wo))
}

fn dense(d: &crate::supernet::Dense, cin: usize, act: Act) -> Pointwise {
    Pointwise {
        w: d.w.value.clone(),
        b: d.b.value.clone(),
        cin,
        cout: d.cout,
        act,
    }
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
        let scale = ((hs, ws) != (h, w)).then(|| Resize::new(h, w, hs, ws));
        let (h2, w2) = (out_size(hs, 3, 2), out_size(ws, 3, 2));
        let mut stem_k = net.stem.value.clone();
        let stem_b = fold(&net.stem_bn, &mut stem_k, STEM_CHANNELS, None);
        let stem = Spatial {
            k: stem_k,
            b: stem_b,
            g: Geom {
                h: hs,
                w: ws,
                ho: h2,
                wo: w2,
                k: 3,
                s: 2,
            },
            act: Act::HSwish,
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
            stem_plane: if cin > 1 {
                vec![0.0; h2 * w2]
            } else {
                Vec::new()
            },
            blocks,
            i8,
            mid_a: vec![0.0; mid_len],
            mid_b: vec![0.0; mid_len],
            sc: Scratch::default(),
            dec: [
                dense(&net.dec[0], c_last, Act::Identity),
                dense(&net.dec[1], net.dec[1].w.value.len() / dw, Act::Identity),
                dense(&net.dec[2], STEM_CHANNELS, Act::Identity),
                dense(&net.dec[3], dw, Act::Identity),
            ],
            up32: Resize::new(size.0, size.1, size8.0, size8.1),
            up8: Resize::new(size8.0, size8.1, h2, w2),
            up2: Resize::new(h2, w2, h, w),
            p32: vec![0.0; dw * hw32],
            p8: vec![0.0; dw * size8.0 * size8.1],
            p2: vec![0.0; dw * h2 * w2],
            lo: vec![0.0; h2 * w2],
            logits: vec![0.0; h * w],
            head_expand: Pointwise {
                w: he_w,
                b: he_b,
                cin: c_last,
                cout: cfg.head_expand,
                act: Act::HSwish,
            },
            head_map: vec![0.0; cfg.head_expand * hw32],
            head_g: vec![0.0; cfg.head_expand],
            hidden: dense(&net.head_hidden, cfg.head_expand, Act::HSwish),
            hidden_out: vec![0.0; cfg.head_hidden],
            slip_head: dense(&net.head_out, cfg.head_hidden, Act::Identity),
        })
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
        let xr: &[f32] = match &self.scale {
            Some(r) => {
                r.run(x, cin, &mut self.xr, false);
                &self.xr
            }
            None => x,
        };
        // Stem: per output channel, the sum over input channels of a 3×3 stride-2 plane pass.
        let st = &self.stem;
        let (hwi, hwo) = (st.g.h * st.g.w, st.g.ho * st.g.wo);
        for (o, out) in self.stem_out.chunks_exact_mut(hwo).enumerate() {
            for i in 0..cin {
                let wk = &st.k[(o * cin + i) * 9..][..9];
                let xp = &xr[i * hwi..][..hwi];
                if i == 0 {
                    depthwise::forward_one(&st.g, xp, wk, &mut self.sc, out);
                } else {
                    depthwise::forward_one(&st.g, xp, wk, &mut self.sc, &mut self.stem_plane);
                    out.iter_mut()
                        .zip(&self.stem_plane)
                        .for_each(|(a, b)| *a += b);
                }
            }
        }
        bias_act(&mut self.stem_out, hwo, &st.b, st.act);
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
            let kk = b.dw.g.k * b.dw.g.k;
            let a2 = &mut self.mid_b[..b.mid * b.hw_out];
            for (c, out) in a2.chunks_exact_mut(b.hw_out).enumerate() {
                let xp = &a1[c * b.hw_in..][..b.hw_in];
                depthwise::forward_one(&b.dw.g, xp, &b.dw.k[c * kk..][..kk], &mut self.sc, out);
            }
            bias_act(a2, b.hw_out, &b.dw.b, b.dw.act);
            if let Some(se) = &mut b.se {
                se.run(a2, b.hw_out);
            }
            b.project.run(a2, b.hw_out, &mut b.out);
            if b.residual {
                b.out.iter_mut().zip(x).for_each(|(o, v)| *o += v);
            }
        }
        let last = self.blocks.len() - 1;
        let (f2, f8, f32_) = (&self.blocks[0], &self.blocks[self.i8], &self.blocks[last]);
        // Perception decoder (FPN-like, as in `Supernet::forward`).
        let dw = self.dec[0].cout;
        self.dec[0].run(&f32_.out, f32_.hw_out, &mut self.p32);
        self.dec[1].run(&f8.out, f8.hw_out, &mut self.p8);
        self.up32.run(&self.p32, dw, &mut self.p8, true);
        self.p8.iter_mut().for_each(|v| *v = v.max(0.0));
        self.dec[2].run(&f2.out, f2.hw_out, &mut self.p2);
        self.up8.run(&self.p8, dw, &mut self.p2, true);
        self.p2.iter_mut().for_each(|v| *v = v.max(0.0));
        self.dec[3].run(&self.p2, f2.hw_out, &mut self.lo);
        self.up2.run(&self.lo, 1, &mut self.logits, false);
        // Calibration head.
        self.head_expand
            .run(&f32_.out, f32_.hw_out, &mut self.head_map);
        for (g, p) in self
            .head_g
            .iter_mut()
            .zip(self.head_map.chunks_exact(f32_.hw_out))
        {
            *g = p.iter().sum::<f32>() / f32_.hw_out as f32;
        }
        self.hidden.run(&self.head_g, 1, &mut self.hidden_out);
        let mut slip = [0.0f32; 3];
        self.slip_head.run(&self.hidden_out, 1, &mut slip);
        Ok(InferenceOutput {
            mask_logits: &self.logits,
            slip,
        })
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
        let cfg = SupernetConfig {
            head_expand: 48,
            head_hidden: 32,
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
            let mut img =
                || -> Vec<f32> { (0..h * w).map(|_| rng.random_range(0.0..1.0)).collect() };
            let calib: Vec<f32> = (0..4).flat_map(|_| img()).collect();
            let calib = Tensor::from_vec(4, 1, h, w, calib).unwrap();
            net.recalibrate_bn(&arch, &[calib]).unwrap();
            let x = img();
            let t = Tensor::from_vec(1, 1, h, w, x.clone()).unwrap();
            let want = net.forward(&arch, &t, BnMode::Eval).unwrap();
            // How far f32 rounding alone moves the reference: the same forward pass on the
            // input scaled by (1 + 2⁻²²), about two ulps. An untrained, recalibrated network
            // amplifies it to ~3e-5 of the largest logit through 20 blocks; the compiled
            // path (BN folded into the weights, sums in another order) must stay within a
            // few such perturbations.
            let xp: Vec<f32> = x.iter().map(|v| v * (1.0 + 2f32.powi(-22))).collect();
            let tp = Tensor::from_vec(1, 1, h, w, xp).unwrap();
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
                let err = maxdiff(got.mask_logits, &want.mask_logits.data);
                assert!(
                    err <= tol_logits,
                    "logits differ by {err} (tolerance {tol_logits})"
                );
                let err = maxdiff(&got.slip, &want.slip.data);
                assert!(
                    err <= tol_slip,
                    "slip differs by {err} (tolerance {tol_slip})"
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

//! The elastic OFA-MobileNetV3 supernet with its perception (pupil-mask logits) and
//! calibration (slippage Δt) heads; explicit backward down to the input image.

use crate::act::Act;
use crate::arch::{Arch, N_STAGES, STAGES, STEM_CHANNELS, SupernetConfig};
use crate::block::{MbBlock, normal_param};
use crate::conv::{conv2d_forward, conv2d_vjp, pointwise_forward, pointwise_vjp};
use crate::error::{NetsError, Result};
use crate::norm::{BatchNorm, BnMode};
use crate::pool::{gap_forward, gap_vjp, moments_forward, moments_vjp};
use crate::resize::{bilinear_forward, bilinear_vjp};
use crate::tensor::{Param, Tensor};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

/// Outputs of one forward pass.
#[derive(Clone, Debug)]
pub struct SupernetOutput {
    /// Pupil-mask logits at the input resolution (N, 1, H, W).
    pub mask_logits: Tensor,
    /// Slippage Δt (N, 3, 1, 1), in the units of the training targets (metres for real data).
    pub slip: Tensor,
}

struct Cache {
    x_shape: [usize; 4],
    xr: Tensor,
    f2: Tensor,
    f8: Tensor,
    f32_: Tensor,
    // decoder
    p32: Tensor,
    p8: Tensor,
    r8: Tensor,
    p2: Tensor,
    r2: Tensor,
    // calibration head
    ha: Tensor,
    g: Tensor,
    z: Tensor,
    za: Tensor,
    active: Vec<(usize, usize)>,
}

/// A biased 1×1 convolution (or, on 1×1 maps, a linear layer): W (C_out × C_in), b.
pub struct Dense {
    /// Weights.
    pub w: Param,
    /// Bias.
    pub b: Param,
    /// Output channels.
    pub cout: usize,
}

impl Dense {
    fn new(rng: &mut ChaCha8Rng, cin: usize, cout: usize, std: f32) -> Self {
        Self {
            w: normal_param(rng, cin * cout, std),
            b: Param::new(vec![0.0; cout]),
            cout,
        }
    }
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        pointwise_forward(x, &self.w.value, self.cout, Some(&self.b.value))
    }
    fn vjp(&mut self, x: &Tensor, dy: &Tensor) -> Result<Tensor> {
        pointwise_vjp(
            x,
            &self.w.value,
            self.cout,
            dy,
            &mut self.w.grad,
            Some(&mut self.b.grad),
        )
    }
}

/// The weight-sharing supernet (stem, first block, 5 elastic stages of 4 blocks, heads).
pub struct Supernet {
    /// Fixed widths.
    pub config: SupernetConfig,
    /// Stem 3×3 stride-2 weights (16 × C_in × 3 × 3).
    pub stem: Param,
    /// Stem batch norm.
    pub stem_bn: BatchNorm,
    /// First block (depthwise 3×3, 16 → 16) then the 20 elastic blocks, stage-major.
    pub blocks: Vec<MbBlock>,
    /// Calibration head 1×1 expansion (head_expand × 160).
    pub head_expand: Param,
    /// Its batch norm.
    pub head_bn: BatchNorm,
    /// Calibration head hidden linear.
    pub head_hidden: Dense,
    /// Calibration head output linear (→ 3).
    pub head_out: Dense,
    /// Decoder projections of the stride-32, -8 and -2 features, and the logit conv.
    pub dec: [Dense; 4],
    cache: Option<Cache>,
}

impl Supernet {
    /// A freshly initialized supernet; `seed` fixes every weight.
    pub fn new(config: SupernetConfig, seed: u64) -> Result<Self> {
        config.validate()?;
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let cin = config.in_channels;
        let stem = normal_param(
            &mut rng,
            STEM_CHANNELS * cin * 9,
            (2.0 / (9 * cin) as f32).sqrt(),
        );
        let mut blocks = vec![MbBlock::new(
            STEM_CHANNELS,
            STEM_CHANNELS,
            1,
            Act::Relu,
            false,
            true,
            &mut rng,
        )];
        let mut c = STEM_CHANNELS;
        for st in STAGES {
            for b in 0..4 {
                let s = if b == 0 { st.stride } else { 1 };
                blocks.push(MbBlock::new(
                    c,
                    st.channels,
                    s,
                    st.act,
                    st.se,
                    false,
                    &mut rng,
                ));
                c = st.channels;
            }
        }
        let (he, hh, dw) = (config.head_expand, config.head_hidden, config.decoder_width);
        let head_in = head_inputs(he);
        Ok(Self {
            stem,
            stem_bn: BatchNorm::new(STEM_CHANNELS),
            blocks,
            head_expand: normal_param(&mut rng, he * c, (2.0 / c as f32).sqrt()),
            head_bn: BatchNorm::new(he),
            head_hidden: Dense::new(&mut rng, head_in, hh, (2.0 / head_in as f32).sqrt()),
            head_out: Dense::new(&mut rng, hh, 3, (0.1 / hh as f32).sqrt()),
            dec: [
                Dense::new(&mut rng, c, dw, (1.0 / c as f32).sqrt()),
                Dense::new(
                    &mut rng,
                    STAGES[1].channels,
                    dw,
                    (1.0 / STAGES[1].channels as f32).sqrt(),
                ),
                Dense::new(
                    &mut rng,
                    STEM_CHANNELS,
                    dw,
                    (1.0 / STEM_CHANNELS as f32).sqrt(),
                ),
                Dense::new(&mut rng, dw, 1, (1.0 / dw as f32).sqrt()),
            ],
            config,
            cache: None,
        })
    }

    /// Forward pass of subnet `arch` on images `x` (N, C_in, H, W).
    pub fn forward(&mut self, arch: &Arch, x: &Tensor, mode: BnMode) -> Result<SupernetOutput> {
        in_pool(|| self.forward_pass(arch, x, mode))
    }

    fn forward_pass(&mut self, arch: &Arch, x: &Tensor, mode: BnMode) -> Result<SupernetOutput> {
        arch.validate()?;
        if x.c != self.config.in_channels || x.n == 0 || x.h == 0 || x.w == 0 {
            return Err(NetsError::Shape(format!(
                "input {:?} does not fit a supernet of {} input channels",
                x.shape(),
                self.config.in_channels
            )));
        }
        let (hs, ws) = (arch.scaled(x.h), arch.scaled(x.w));
        let xr = if (hs, ws) == (x.h, x.w) {
            x.clone()
        } else {
            bilinear_forward(x, hs, ws)
        };
        let u0 = conv2d_forward(&xr, &self.stem.value, STEM_CHANNELS, 3, 2)?;
        let mut h = self.stem_bn.forward_act(u0, mode, Act::HSwish)?;
        h = self.blocks[0].forward(&h, 3, 1, mode)?;
        let f2 = h.clone();
        let mut f8 = None;
        let mut active = Vec::new();
        for s in 0..N_STAGES {
            for b in 0..arch.depth[s] {
                let l = s * 4 + b;
                h = self.blocks[1 + l].forward(&h, arch.kernel[l], arch.expand[l], mode)?;
                active.push((1 + l, s));
            }
            if s == 1 {
                f8 = Some(h.clone());
            }
        }
        // Stage 1's output, which the loop above always reaches.
        let f8 = f8.ok_or_else(|| NetsError::Shape("the supernet has no stage 1".into()))?;
        let f32_ = h;
        // Perception decoder.
        let p32 = self.dec[0].forward(&f32_)?;
        let mut p8 = self.dec[1].forward(&f8)?;
        p8.add_assign(&bilinear_forward(&p32, f8.h, f8.w));
        let r8 = p8.like(Act::Relu.forward(&p8.data));
        let mut p2 = self.dec[2].forward(&f2)?;
        p2.add_assign(&bilinear_forward(&r8, f2.h, f2.w));
        let r2 = p2.like(Act::Relu.forward(&p2.data));
        let lo = self.dec[3].forward(&r2)?;
        let mask_logits = bilinear_forward(&lo, x.h, x.w);
        // Calibration head.
        let hu = pointwise_forward(
            &f32_,
            &self.head_expand.value,
            self.config.head_expand,
            None,
        )?;
        let ha = self.head_bn.forward_act(hu, mode, Act::HSwish)?;
        // The expansion's means and the x, y moments of the stride-32 and stride-8 features:
        // slippage translates the face across the frame, which a global mean cannot see; the
        // stride-8 map places a translation on a 4× finer grid (docs/nets.md).
        let g = concat_features(&[
            &gap_forward(&ha),
            &moments_forward(&f32_),
            &moments_forward(&f8),
        ]);
        let z = self.head_hidden.forward(&g)?;
        let za = z.like(Act::HSwish.forward(&z.data));
        let slip = self.head_out.forward(&za)?;
        self.cache = Some(Cache {
            x_shape: x.shape(),
            xr,
            f2,
            f8,
            f32_,
            p32,
            p8,
            r8,
            p2,
            r2,
            ha,
            g,
            z,
            za,
            active,
        });
        Ok(SupernetOutput { mask_logits, slip })
    }

    /// The calibration head's hidden activations of the last forward pass, (N, hidden, 1, 1):
    /// what its output layer [`Supernet::head_out`] maps to Δt (None before any forward).
    pub fn head_hidden_features(&self) -> Option<&Tensor> {
        self.cache.as_ref().map(|c| &c.za)
    }

    /// Backward pass of the last forward from dL/dlogits and dL/dslip; accumulates every
    /// parameter gradient and returns dL/dx, the gradient w.r.t. the input images.
    pub fn backward(&mut self, d_logits: &Tensor, d_slip: &Tensor) -> Result<Tensor> {
        in_pool(|| self.backward_pass(d_logits, d_slip))
    }

    fn backward_pass(&mut self, d_logits: &Tensor, d_slip: &Tensor) -> Result<Tensor> {
        let c = self
            .cache
            .take()
            .ok_or_else(|| NetsError::Shape("backward without forward".into()))?;
        let [n, _, h, w] = c.x_shape;
        if d_logits.shape() != [n, 1, h, w] || d_slip.shape() != [n, 3, 1, 1] {
            return Err(NetsError::Shape(format!(
                "upstream gradients {:?}, {:?} do not match the forward pass",
                d_logits.shape(),
                d_slip.shape()
            )));
        }
        // Calibration head.
        let dza = self.head_out.vjp(&c.za, d_slip)?;
        let dz = Tensor {
            data: Act::HSwish.vjp(&c.z.data, &dza.data),
            ..dza
        };
        let dg = self.head_hidden.vjp(&c.g, &dz)?;
        let [dgap, dmom, dmom8] = split_features(&dg, head_parts(self.config.head_expand));
        let dha = gap_vjp(c.ha.shape(), &dgap);
        let dhu = self.head_bn.backward_owned(dha)?;
        let mut df32 = pointwise_vjp(
            &c.f32_,
            &self.head_expand.value,
            self.config.head_expand,
            &dhu,
            &mut self.head_expand.grad,
            None,
        )?;
        df32.add_assign(&moments_vjp(c.f32_.shape(), &dmom));
        // Decoder.
        let dlo = bilinear_vjp([n, 1, c.r2.h, c.r2.w], d_logits);
        let dr2 = self.dec[3].vjp(&c.r2, &dlo)?;
        let dp2 = Tensor {
            data: Act::Relu.vjp(&c.p2.data, &dr2.data),
            ..dr2
        };
        let mut df2 = self.dec[2].vjp(&c.f2, &dp2)?;
        let dr8 = bilinear_vjp(c.r8.shape(), &dp2);
        let dp8 = Tensor {
            data: Act::Relu.vjp(&c.p8.data, &dr8.data),
            ..dr8
        };
        let mut df8 = self.dec[1].vjp(&c.f8, &dp8)?;
        df8.add_assign(&moments_vjp(c.f8.shape(), &dmom8));
        let dp32 = bilinear_vjp(c.p32.shape(), &dp8);
        df32.add_assign(&self.dec[0].vjp(&c.f32_, &dp32)?);
        // Backbone, last block first; decoder taps join at the stage-2 and first-block outputs.
        let mut g = df32;
        let mut injected8 = false;
        for &(bi, s) in c.active.iter().rev() {
            if s <= 1 && !injected8 {
                g.add_assign(&df8);
                injected8 = true;
            }
            g = self.blocks[bi].backward(&g)?;
        }
        if !injected8 {
            g.add_assign(&df8);
        }
        df2.add_assign(&g);
        let g = self.blocks[0].backward(&df2)?;
        let du0 = self.stem_bn.backward_owned(g)?;
        let dxr = conv2d_vjp(
            &c.xr,
            &self.stem.value,
            STEM_CHANNELS,
            3,
            2,
            &du0,
            &mut self.stem.grad,
        )?;
        Ok(if (c.xr.h, c.xr.w) == (h, w) {
            dxr
        } else {
            bilinear_vjp(c.x_shape, &dxr)
        })
    }

    /// Visits every learnable parameter with a stable name.
    pub fn visit(&mut self, f: &mut dyn FnMut(&str, &mut Param)) {
        f("stem", &mut self.stem);
        f("stem_bn.gamma", &mut self.stem_bn.gamma);
        f("stem_bn.beta", &mut self.stem_bn.beta);
        for (i, b) in self.blocks.iter_mut().enumerate() {
            b.visit(&mut |name, p| f(&format!("blocks.{i}.{name}"), p));
        }
        f("head_expand", &mut self.head_expand);
        f("head_bn.gamma", &mut self.head_bn.gamma);
        f("head_bn.beta", &mut self.head_bn.beta);
        f("head_hidden.w", &mut self.head_hidden.w);
        f("head_hidden.b", &mut self.head_hidden.b);
        f("head_out.w", &mut self.head_out.w);
        f("head_out.b", &mut self.head_out.b);
        for (i, d) in self.dec.iter_mut().enumerate() {
            f(&format!("dec.{i}.w"), &mut d.w);
            f(&format!("dec.{i}.b"), &mut d.b);
        }
    }

    /// Visits every batch-norm layer with a stable name.
    pub fn visit_bn(&mut self, f: &mut dyn FnMut(&str, &mut BatchNorm)) {
        f("stem_bn", &mut self.stem_bn);
        for (i, b) in self.blocks.iter_mut().enumerate() {
            b.visit_bn(&mut |name, bn| f(&format!("blocks.{i}.{name}"), bn));
        }
        f("head_bn", &mut self.head_bn);
    }

    /// Sets every gradient to zero.
    pub fn zero_grad(&mut self) {
        self.visit(&mut |_, p| p.zero_grad());
    }

    /// Total stored scalars.
    pub fn num_params(&mut self) -> usize {
        let mut n = 0;
        self.visit(&mut |_, p| n += p.len());
        n
    }

    /// Sorts every block's middle channels by importance (elastic width, OFA's reorganize).
    pub fn reorganize(&mut self) {
        self.blocks.iter_mut().for_each(MbBlock::reorganize);
    }

    /// Exact BN recalibration of subnet `arch`: every batch goes through in batch-statistics
    /// mode while per-channel Σx, Σx² are summed; running statistics become the pooled values.
    pub fn recalibrate_bn(&mut self, arch: &Arch, batches: &[Tensor]) -> Result<()> {
        if batches.is_empty() {
            return Err(NetsError::Param(
                "BN recalibration needs at least one batch".into(),
            ));
        }
        self.visit_bn(&mut |_, bn| bn.begin_recalibration());
        for b in batches {
            self.forward(arch, b, BnMode::Recalibrate)?;
        }
        self.visit_bn(&mut |_, bn| bn.finish_recalibration());
        self.cache = None;
        Ok(())
    }
}

/// Runs `op` on a thread of rayon's pool (directly if already on one).
///
/// A pass is a few hundred short parallel loops; started from a thread outside the pool, each
/// would hand its work to the pool and sleep until woken (a futex round trip per loop: 4.5 %
/// of the min subnet's samples at 128², batch 16, and the wake-up latency on top). Inside the
/// pool they fork from a worker.
fn in_pool<R: Send>(op: impl FnOnce() -> R + Send) -> R {
    rayon::scope(|_| op())
}

/// Widths of the calibration head's pooled features for an expansion of `he` channels, in
/// order: the expansion's means, the last stage's x and y moments, the stride-8 stage's.
pub fn head_parts(he: usize) -> [usize; 3] {
    [
        he,
        2 * STAGES[N_STAGES - 1].channels,
        2 * STAGES[1].channels,
    ]
}

/// Total width of [`head_parts`]: the hidden layer's input.
pub fn head_inputs(he: usize) -> usize {
    head_parts(he).iter().sum()
}

/// Per sample, the features of each part in turn (all (N, C_i, 1, 1)).
fn concat_features(parts: &[&Tensor]) -> Tensor {
    let n = parts[0].n;
    let c: usize = parts.iter().map(|p| p.c).sum();
    let mut data = Vec::with_capacity(n * c);
    for i in 0..n {
        for p in parts {
            data.extend_from_slice(&p.data[i * p.c..][..p.c]);
        }
    }
    Tensor {
        n,
        c,
        h: 1,
        w: 1,
        data,
    }
}

/// Inverse of [`concat_features`] for parts of `widths` features each.
fn split_features<const K: usize>(g: &Tensor, widths: [usize; K]) -> [Tensor; K] {
    let mut parts = widths.map(|c| Tensor::zeros(g.n, c, 1, 1));
    for (i, row) in g.data.chunks_exact(g.c).enumerate() {
        let mut at = 0;
        for p in parts.iter_mut() {
            let c = p.c;
            p.data[i * c..][..c].copy_from_slice(&row[at..at + c]);
            at += c;
        }
    }
    parts
}

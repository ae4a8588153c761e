//! Batch normalization with training, evaluation and exact-recalibration modes.

use crate::act::{Act, PAR_MIN};
use crate::error::{NetsError, Result};
use crate::tensor::{Param, Tensor};
use rayon::prelude::*;

/// Running sums per channel statistic: independent chains the compiler keeps in registers.
const LANES: usize = 8;

/// Values per stretch of the large-plane backward's sums: their dpre and x̂ go to two arrays
/// on the stack (2 KiB) before they are summed. A multiple of LANES.
const STRETCH: usize = 256;
const _: () = assert!(
    STRETCH.is_multiple_of(LANES),
    "the sums take whole blocks of LANES"
);

/// Planes of fewer values than this are summed per position over the images and normalized
/// image by image (the deep stages' 2×2 … 10×10 maps), larger ones plane by plane.
const SMALL_PLANE: usize = 128;

/// How batch-norm layers normalize during a forward pass.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BnMode {
    /// Batch statistics; running statistics updated with momentum 0.1.
    Train,
    /// Stored running statistics.
    Eval,
    /// Batch statistics, and exact per-channel sums Σx, Σx² accumulated over all batches seen
    /// since `begin_recalibration` (no running average).
    Recalibrate,
}

#[derive(Clone, Debug)]
struct Cache {
    /// The layer's input x, kept instead of x̂: the backward pass recomputes x̂ = (x − μ)·σ⁻¹
    /// by the forward's expression (the same bits), so the forward writes one tensor, not two.
    x: Vec<f32>,
    mean: Vec<f32>,
    inv_std: Vec<f32>,
    batch_stats: bool,
    shape: [usize; 4],
    /// The activation applied after the normalization (Identity for none).
    act: Act,
}

/// Batch normalization over (N, H, W) per channel, y = γ·(x−μ)/√(σ²+ε) + β; the layer holds
/// the widest channel count and a forward pass uses the first C channels (elastic width).
#[derive(Clone, Debug)]
pub struct BatchNorm {
    /// Scale γ.
    pub gamma: Param,
    /// Shift β.
    pub beta: Param,
    /// Running / recalibrated mean.
    pub running_mean: Vec<f32>,
    /// Running / recalibrated (biased) variance.
    pub running_var: Vec<f32>,
    /// Variance floor ε.
    pub eps: f32,
    acc: Option<(Vec<f64>, Vec<f64>, Vec<f64>)>,
    cache: Option<Cache>,
}

impl BatchNorm {
    /// A layer of `c` channels with γ = 1, β = 0, running statistics (0, 1).
    pub fn new(c: usize) -> Self {
        Self {
            gamma: Param::new(vec![1.0; c]),
            beta: Param::new(vec![0.0; c]),
            running_mean: vec![0.0; c],
            running_var: vec![1.0; c],
            eps: 1e-5,
            acc: None,
            cache: None,
        }
    }

    /// Widest channel count.
    pub fn channels(&self) -> usize {
        self.gamma.len()
    }

    /// Normalizes `x` (its C ≤ the layer's width) and caches what the backward pass needs.
    pub fn forward(&mut self, x: &Tensor, mode: BnMode) -> Result<Tensor> {
        self.forward_act(x.clone(), mode, Act::Identity)
    }

    /// Normalizes `x` (moved in: the layer keeps it for the backward pass) and applies `act`:
    /// act(γ·x̂ + β). The pre-activation is not stored; the backward pass recomputes it by the
    /// same expression, so the pair computes what `forward` followed by `Act::forward` does,
    /// bit for bit, with one pass and one tensor fewer each way.
    pub fn forward_act(&mut self, x: Tensor, mode: BnMode, act: Act) -> Result<Tensor> {
        let c = x.c;
        if c > self.channels() {
            return Err(NetsError::Shape(format!(
                "batch norm of width {} given {c} channels",
                self.channels()
            )));
        }
        let hw = x.plane();
        let m = (x.n * hw) as f64;
        let batch_stats = mode != BnMode::Eval;
        let p = Pass {
            c,
            hw,
            gamma: &self.gamma.value,
            beta: &self.beta.value,
        };
        let mut mean = vec![0.0f32; c];
        let mut var = vec![0.0f32; c];
        if batch_stats {
            if m == 0.0 {
                return Err(NetsError::Shape("batch norm over an empty batch".into()));
            }
            let (s1, s2) = p.stats(x.n, &x.data);
            for ch in 0..c {
                let mu = s1[ch] / m;
                mean[ch] = mu as f32;
                var[ch] = (s2[ch] / m - mu * mu).max(0.0) as f32;
            }
            match mode {
                BnMode::Train => {
                    for ch in 0..c {
                        self.running_mean[ch] = 0.9 * self.running_mean[ch] + 0.1 * mean[ch];
                        self.running_var[ch] = 0.9 * self.running_var[ch] + 0.1 * var[ch];
                    }
                }
                BnMode::Recalibrate => {
                    let width = self.channels();
                    let acc = self.acc.get_or_insert_with(|| {
                        (vec![0.0; width], vec![0.0; width], vec![0.0; width])
                    });
                    for ch in 0..c {
                        acc.0[ch] += s1[ch];
                        acc.1[ch] += s2[ch];
                        acc.2[ch] += m;
                    }
                }
                BnMode::Eval => {}
            }
        } else {
            mean.copy_from_slice(&self.running_mean[..c]);
            var.copy_from_slice(&self.running_var[..c]);
        }
        let inv_std: Vec<f32> = var.iter().map(|v| 1.0 / (v + self.eps).sqrt()).collect();
        let mut y = Tensor::zeros(x.n, c, x.h, x.w);
        if hw > 0 {
            // One monomorphic pass per activation: a `match` inside the loop would keep it
            // from vectorizing.
            let (y, x) = (&mut y.data, &x.data);
            match act {
                Act::Identity => p.normalize(|v| v, x, &mean, &inv_std, y),
                Act::Relu => p.normalize(|v| Act::Relu.apply(v), x, &mean, &inv_std, y),
                Act::HSwish => p.normalize(|v| Act::HSwish.apply(v), x, &mean, &inv_std, y),
                Act::HSigmoid => p.normalize(|v| Act::HSigmoid.apply(v), x, &mean, &inv_std, y),
            }
        }
        let shape = x.shape();
        self.cache = Some(Cache {
            x: x.data,
            mean,
            inv_std,
            batch_stats,
            shape,
            act,
        });
        Ok(y)
    }

    /// VJP of the last forward (through its activation): returns dL/dx and accumulates dL/dγ,
    /// dL/dβ.
    pub fn backward(&mut self, dy: &Tensor) -> Result<Tensor> {
        self.backward_owned(dy.clone())
    }

    /// [`BatchNorm::backward`] writing dL/dx over `dy`'s values (no second tensor).
    pub fn backward_owned(&mut self, mut dy: Tensor) -> Result<Tensor> {
        let cache = self
            .cache
            .take()
            .ok_or_else(|| NetsError::Shape("batch norm backward without forward".into()))?;
        if dy.shape() != cache.shape {
            return Err(NetsError::Shape(format!(
                "batch norm upstream gradient {:?}",
                dy.shape()
            )));
        }
        let [nb, c, h, w] = cache.shape;
        let hw = h * w;
        if hw == 0 {
            return Ok(dy);
        }
        let p = Pass {
            c,
            hw,
            gamma: &self.gamma.value,
            beta: &self.beta.value,
        };
        // dL/d(pre-activation) from dL/dy, x̂, γ and β: the forward's expression for the
        // pre-activation, so the derivative is taken where the forward pass was.
        let d = &mut dy.data;
        let sums = match cache.act {
            Act::Identity => p.backward(|g, _, _, _| g, nb, &cache, d),
            Act::Relu => p.backward(
                |g, h, ga, be| g * Act::Relu.deriv(ga * h + be),
                nb,
                &cache,
                d,
            ),
            Act::HSwish => p.backward(
                |g, h, ga, be| g * Act::HSwish.deriv(ga * h + be),
                nb,
                &cache,
                d,
            ),
            Act::HSigmoid => p.backward(
                |g, h, ga, be| g * Act::HSigmoid.deriv(ga * h + be),
                nb,
                &cache,
                d,
            ),
        };
        for (ch, &(sg, sgx)) in sums.iter().enumerate() {
            self.gamma.grad[ch] += sgx;
            self.beta.grad[ch] += sg;
        }
        Ok(dy)
    }

    /// Clears the recalibration sums.
    pub fn begin_recalibration(&mut self) {
        self.acc = None;
    }

    /// Sets the running statistics of every channel seen since `begin_recalibration` to the
    /// exact pooled mean and (biased) variance.
    pub fn finish_recalibration(&mut self) {
        if let Some((s1, s2, cnt)) = self.acc.take() {
            for ch in 0..self.channels() {
                if cnt[ch] > 0.0 {
                    let mu = s1[ch] / cnt[ch];
                    self.running_mean[ch] = mu as f32;
                    self.running_var[ch] = (s2[ch] / cnt[ch] - mu * mu).max(0.0) as f32;
                }
            }
        }
    }
}

/// x̂ = (x − μ)·σ⁻¹: one expression for the forward pass and the backward's recomputation.
#[inline(always)]
fn xhat(x: f32, mu: f32, inv_std: f32) -> f32 {
    (x - mu) * inv_std
}

/// Adds value i of `plane` (as f64) to `a[i mod LANES]` and its square to `b[i mod LANES]`,
/// blocks of LANES in order, then the tail.
fn lane_sums(plane: &[f32], a: &mut [f64; LANES], b: &mut [f64; LANES]) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has AVX2.
        unsafe { lane_sums_avx2(plane, a, b) };
        return;
    }
    lane_sums_scalar(plane, a, b);
}

/// [`lane_sums`] in plain Rust: LLVM keeps its eight f64 lanes scalar (`vcvtss2sd`,
/// `vaddsd`), in every form of the loop tried.
fn lane_sums_scalar(plane: &[f32], a: &mut [f64; LANES], b: &mut [f64; LANES]) {
    let blocks = plane.chunks_exact(LANES);
    let tail = blocks.remainder();
    for blk in blocks {
        for l in 0..LANES {
            let v = blk[l] as f64;
            a[l] += v;
            b[l] += v * v;
        }
    }
    for (l, &v) in tail.iter().enumerate() {
        a[l] += v as f64;
        b[l] += (v as f64) * (v as f64);
    }
}

/// [`lane_sums`] in two pairs of four-lane registers: per lane the same sums in the same
/// order, so the same bits (the square of an f32 is exact in f64).
///
/// # Safety
/// The CPU has AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn lane_sums_avx2(plane: &[f32], a: &mut [f64; LANES], b: &mut [f64; LANES]) {
    use std::arch::x86_64::*;
    const _: () = assert!(LANES == 8, "two registers of four f64 lanes");
    let blocks = plane.chunks_exact(LANES);
    let tail = blocks.remainder();
    // SAFETY (all): `a`, `b` and each block hold eight values.
    unsafe {
        let (mut a0, mut a1) = (
            _mm256_loadu_pd(a.as_ptr()),
            _mm256_loadu_pd(a.as_ptr().add(4)),
        );
        let (mut b0, mut b1) = (
            _mm256_loadu_pd(b.as_ptr()),
            _mm256_loadu_pd(b.as_ptr().add(4)),
        );
        for blk in blocks {
            let v = _mm256_loadu_ps(blk.as_ptr());
            let lo = _mm256_cvtps_pd(_mm256_castps256_ps128(v));
            let hi = _mm256_cvtps_pd(_mm256_extractf128_ps::<1>(v));
            a0 = _mm256_add_pd(a0, lo);
            a1 = _mm256_add_pd(a1, hi);
            b0 = _mm256_add_pd(b0, _mm256_mul_pd(lo, lo));
            b1 = _mm256_add_pd(b1, _mm256_mul_pd(hi, hi));
        }
        _mm256_storeu_pd(a.as_mut_ptr(), a0);
        _mm256_storeu_pd(a.as_mut_ptr().add(4), a1);
        _mm256_storeu_pd(b.as_mut_ptr(), b0);
        _mm256_storeu_pd(b.as_mut_ptr().add(4), b1);
    }
    // Fewer than LANES values: the plain loop's tail.
    lane_sums_scalar(tail, a, b);
}

/// The element-wise passes of one batch-norm call: C channels of H·W pixels, γ, β.
struct Pass<'a> {
    c: usize,
    hw: usize,
    gamma: &'a [f32],
    beta: &'a [f32],
}

impl Pass<'_> {
    /// The channel ranges `c0..c1` of the small-plane sums' tasks, in order: at least
    /// `PAR_MIN` values over `nb` images each (a channel's sums do not depend on its block).
    fn channel_blocks(&self, nb: usize) -> impl IndexedParallelIterator<Item = (usize, usize)> {
        let c = self.c;
        let cb = (PAR_MIN / (nb * self.hw).max(1)).clamp(1, c);
        (0..c.div_ceil(cb))
            .into_par_iter()
            .map(move |blk| (blk * cb, ((blk + 1) * cb).min(c)))
    }

    /// Per-channel Σx and Σx² over `nb` images (f64), the same sums for any thread count.
    fn stats(&self, nb: usize, x: &[f32]) -> (Vec<f64>, Vec<f64>) {
        let (c, hw) = (self.c, self.hw);
        if hw < SMALL_PLANE {
            // Per position of a block of channels, images in order, then per channel its
            // positions in order: one vectorizable loop over each image's block, where the
            // per-plane loops below ran a few values per plane.
            return self
                .channel_blocks(nb)
                .flat_map_iter(|(c0, c1)| {
                    let len = (c1 - c0) * hw;
                    let (mut a, mut b) = (vec![0.0f64; len], vec![0.0f64; len]);
                    for n in 0..nb {
                        let xs = &x[(n * c + c0) * hw..][..len];
                        for ((a, b), &v) in a.iter_mut().zip(b.iter_mut()).zip(xs) {
                            let v = v as f64;
                            *a += v;
                            *b += v * v;
                        }
                    }
                    (0..c1 - c0)
                        .map(|k| {
                            let at = k * hw..(k + 1) * hw;
                            (a[at.clone()].iter().sum::<f64>(), b[at].iter().sum::<f64>())
                        })
                        .collect::<Vec<_>>()
                })
                .unzip();
        }
        // Per channel, images in order, in LANES running sums (one chain of dependent
        // additions per channel was latency-bound): the same sums for any thread count.
        (0..c)
            .into_par_iter()
            .map(|ch| {
                let (mut a, mut b) = ([0.0f64; LANES], [0.0f64; LANES]);
                for n in 0..nb {
                    lane_sums(&x[(n * c + ch) * hw..][..hw], &mut a, &mut b);
                }
                (a.iter().sum::<f64>(), b.iter().sum::<f64>())
            })
            .unzip()
    }

    /// y = f(γ·x̂ + β) with x̂ = (x − μ)·σ⁻¹ into `y`, plane by plane.
    fn normalize<F: Fn(f32) -> f32 + Sync>(
        &self,
        f: F,
        x: &[f32],
        mean: &[f32],
        inv_std: &[f32],
        y: &mut [f32],
    ) {
        let (c, hw) = (self.c, self.hw);
        if hw < SMALL_PLANE {
            // Image by image over per-position copies of the channel constants: one loop of
            // C·H·W values instead of C loops of a few (the same expression, the same bits).
            let [g, b, mu, is] =
                [&self.gamma[..c], &self.beta[..c], mean, inv_std].map(|v| spread(v, hw));
            y.par_chunks_mut(c * hw)
                .zip(x.par_chunks(c * hw))
                .with_min_len((PAR_MIN / (c * hw)).max(1))
                .for_each(|(yi, xi)| {
                    let consts = g.iter().zip(&b).zip(mu.iter().zip(&is));
                    for ((y, &v), ((&g, &b), (&mu, &is))) in yi.iter_mut().zip(xi).zip(consts) {
                        *y = f(g * xhat(v, mu, is) + b);
                    }
                });
            return;
        }
        y.par_chunks_mut(hw)
            .zip(x.par_chunks(hw))
            .enumerate()
            .with_min_len((PAR_MIN / hw).max(1))
            .for_each(|(idx, (yp, xp))| {
                let ch = idx % c;
                let (g, b, mu, is) = (self.gamma[ch], self.beta[ch], mean[ch], inv_std[ch]);
                for (y, &v) in yp.iter_mut().zip(xp) {
                    *y = f(g * xhat(v, mu, is) + b);
                }
            });
    }

    /// dL/dx over dL/dy in `d`, with `dpre(dL/dy, x̂, γ, β)` the gradient at the
    /// pre-activation; returns the per-channel sums (Σ dpre, Σ dpre·x̂) = (dL/dβ, dL/dγ).
    fn backward<D: Fn(f32, f32, f32, f32) -> f32 + Sync>(
        &self,
        dpre: D,
        nb: usize,
        cache: &Cache,
        d: &mut [f32],
    ) -> Vec<(f32, f32)> {
        if self.hw < SMALL_PLANE {
            return self.backward_small(dpre, nb, cache, d);
        }
        let (c, hw) = (self.c, self.hw);
        let m = (nb * hw) as f32;
        let sums: Vec<(f32, f32)> = (0..c)
            .into_par_iter()
            .map(|ch| {
                let (ga, be) = (self.gamma[ch], self.beta[ch]);
                let (mu, is) = (cache.mean[ch], cache.inv_std[ch]);
                let (mut sg, mut sgx) = ([0.0f32; LANES], [0.0f32; LANES]);
                // dpre and x̂ of a stretch of values first, in a loop of their own, then their
                // LANES running sums: with the sums in the same loop the compiler kept it scalar
                // (h-swish's derivative a branch and a scalar division per value).
                let (mut pg, mut px) = ([0.0f32; STRETCH], [0.0f32; STRETCH]);
                for n in 0..nb {
                    let off = (n * c + ch) * hw;
                    let (gs, xs) = (&d[off..off + hw], &cache.x[off..off + hw]);
                    let body = hw - hw % LANES;
                    for (l, (&g, &v)) in gs[body..].iter().zip(&xs[body..]).enumerate() {
                        let xh = xhat(v, mu, is);
                        let g = dpre(g, xh, ga, be);
                        sg[l] += g;
                        sgx[l] += g * xh;
                    }
                    let stretches = gs[..body].chunks(STRETCH).zip(xs[..body].chunks(STRETCH));
                    for (g, v) in stretches {
                        let (pg, px) = (&mut pg[..g.len()], &mut px[..g.len()]);
                        let vals = g.iter().zip(v);
                        for ((pg, px), (&g, &v)) in pg.iter_mut().zip(px.iter_mut()).zip(vals) {
                            let xh = xhat(v, mu, is);
                            *pg = dpre(g, xh, ga, be);
                            *px = xh;
                        }
                        for (g, xh) in pg.chunks_exact(LANES).zip(px.chunks_exact(LANES)) {
                            for l in 0..LANES {
                                sg[l] += g[l];
                                sgx[l] += g[l] * xh[l];
                            }
                        }
                    }
                }
                (sg.iter().sum::<f32>(), sgx.iter().sum::<f32>())
            })
            .collect();
        d.par_chunks_mut(hw)
            .zip(cache.x.par_chunks(hw))
            .enumerate()
            .with_min_len((PAR_MIN / hw).max(1))
            .for_each(|(idx, (dp, xp))| {
                let ch = idx % c;
                let (sg, sgx) = sums[ch];
                let (ga, be) = (self.gamma[ch], self.beta[ch]);
                let (mu, is) = (cache.mean[ch], cache.inv_std[ch]);
                let k = ga * is;
                if cache.batch_stats {
                    for (d, &v) in dp.iter_mut().zip(xp) {
                        let xh = xhat(v, mu, is);
                        *d = k * (dpre(*d, xh, ga, be) - sg / m - xh * sgx / m);
                    }
                } else {
                    for (d, &v) in dp.iter_mut().zip(xp) {
                        *d = k * dpre(*d, xhat(v, mu, is), ga, be);
                    }
                }
            });
        sums
    }

    /// [`Pass::backward`] for planes of fewer than [`SMALL_PLANE`] values: the sums per
    /// position of a block of channels, images in order, then per channel its positions in
    /// order; dL/dx image by image over per-position copies of the channel constants.
    fn backward_small<D: Fn(f32, f32, f32, f32) -> f32 + Sync>(
        &self,
        dpre: D,
        nb: usize,
        cache: &Cache,
        d: &mut [f32],
    ) -> Vec<(f32, f32)> {
        let (c, hw) = (self.c, self.hw);
        let m = (nb * hw) as f32;
        let [ga, be, mu, is] = [
            &self.gamma[..c],
            &self.beta[..c],
            &cache.mean[..],
            &cache.inv_std[..],
        ]
        .map(|v| spread(v, hw));
        let dd: &[f32] = d;
        let sums: Vec<(f32, f32)> = self
            .channel_blocks(nb)
            .flat_map_iter(|(c0, c1)| {
                let len = (c1 - c0) * hw;
                let at = c0 * hw..c1 * hw;
                let (ga, be, mu, is) = (&ga[at.clone()], &be[at.clone()], &mu[at.clone()], &is[at]);
                let (mut sg, mut sgx) = (vec![0.0f32; len], vec![0.0f32; len]);
                for n in 0..nb {
                    let off = (n * c + c0) * hw;
                    let (gs, xs) = (&dd[off..off + len], &cache.x[off..off + len]);
                    // Zipped, not indexed: bounds checks kept the indexed loop scalar.
                    let consts = ga.iter().zip(be).zip(mu.iter().zip(is));
                    let acc = sg.iter_mut().zip(sgx.iter_mut());
                    for (((s, t), (&g, &v)), ((&ga, &be), (&mu, &is))) in
                        acc.zip(gs.iter().zip(xs)).zip(consts)
                    {
                        let xh = xhat(v, mu, is);
                        let g = dpre(g, xh, ga, be);
                        *s += g;
                        *t += g * xh;
                    }
                }
                (0..c1 - c0)
                    .map(|k| {
                        let at = k * hw..(k + 1) * hw;
                        (
                            sg[at.clone()].iter().sum::<f32>(),
                            sgx[at].iter().sum::<f32>(),
                        )
                    })
                    .collect::<Vec<_>>()
            })
            .collect();
        let sg = spread(&sums.iter().map(|s| s.0).collect::<Vec<_>>(), hw);
        let sgx = spread(&sums.iter().map(|s| s.1).collect::<Vec<_>>(), hw);
        let len = c * hw;
        d.par_chunks_mut(len)
            .zip(cache.x.par_chunks(len))
            .with_min_len((PAR_MIN / len).max(1))
            .for_each(|(di, xi)| {
                let consts = ga.iter().zip(&be).zip(mu.iter().zip(&is));
                let vals = di.iter_mut().zip(xi);
                if cache.batch_stats {
                    let sums = sg.iter().zip(&sgx);
                    for (((d, &v), ((&ga, &be), (&mu, &is))), (&sg, &sgx)) in
                        vals.zip(consts).zip(sums)
                    {
                        let xh = xhat(v, mu, is);
                        *d = ga * is * (dpre(*d, xh, ga, be) - sg / m - xh * sgx / m);
                    }
                } else {
                    for ((d, &v), ((&ga, &be), (&mu, &is))) in vals.zip(consts) {
                        *d = ga * is * dpre(*d, xhat(v, mu, is), ga, be);
                    }
                }
            });
        sums
    }
}

/// Each of `v`'s values repeated `hw` times: a per-channel constant at every position.
fn spread(v: &[f32], hw: usize) -> Vec<f32> {
    // Filled as it grows: a zeroed vector filled after was written twice (the allocator's
    // memset was 1.4 % of the max subnet's training pass at batch 4).
    let mut out = Vec::with_capacity(v.len() * hw);
    for &x in v {
        out.extend(std::iter::repeat_n(x, hw));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng, rngs::StdRng};

    /// The fused normalize-and-activate pass and its backward compute what the separate
    /// layers do (batch norm, then the activation; the activation's VJP, then batch norm's),
    /// bit for bit, in every mode and for every activation, on values that straddle the
    /// activations' kinks.
    #[test]
    fn fused_activation_matches_the_separate_layers_bit_for_bit() {
        let mut rng = StdRng::seed_from_u64(11);
        let (n, c, h, w) = (3, 5, 7, 9);
        let x = Tensor::from_vec(
            n,
            c,
            h,
            w,
            (0..n * c * h * w)
                .map(|_| rng.random_range(-6.0..6.0))
                .collect(),
        )
        .expect("shape");
        let dy: Vec<f32> = (0..x.len()).map(|_| rng.random_range(-1.0..1.0)).collect();
        for act in [Act::Identity, Act::Relu, Act::HSwish, Act::HSigmoid] {
            for mode in [BnMode::Train, BnMode::Eval, BnMode::Recalibrate] {
                let mut bn = BatchNorm::new(c);
                for ch in 0..c {
                    bn.gamma.value[ch] = rng.random_range(0.5..2.0);
                    bn.beta.value[ch] = rng.random_range(-1.0..1.0);
                    bn.running_mean[ch] = rng.random_range(-1.0..1.0);
                    bn.running_var[ch] = rng.random_range(0.5..3.0);
                }
                let mut fused = bn.clone();
                let v = bn.forward(&x, mode).expect("bn");
                let a = act.forward(&v.data);
                let dv = v.like(act.vjp(&v.data, &dy));
                let dx = bn.backward(&dv).expect("bn vjp");
                let a2 = fused.forward_act(x.clone(), mode, act).expect("fused");
                let dx2 = fused.backward_owned(x.like(dy.clone())).expect("fused vjp");
                let bits = |v: &[f32]| v.iter().map(|f| f.to_bits()).collect::<Vec<_>>();
                let what = format!("{act:?} {mode:?}");
                assert_eq!(bits(&a), bits(&a2.data), "forward, {what}");
                assert_eq!(bits(&dx.data), bits(&dx2.data), "dL/dx, {what}");
                assert_eq!(bits(&bn.gamma.grad), bits(&fused.gamma.grad), "dγ, {what}");
                assert_eq!(bits(&bn.beta.grad), bits(&fused.beta.grad), "dβ, {what}");
            }
        }
    }

    /// Training-mode forward and backward against the definition in f64, on planes below and
    /// above [`SMALL_PLANE`] (the two summation layouts), with h-swish's kinks straddled; and
    /// the same bits from one thread as from three, over several channel blocks per pass.
    #[test]
    fn both_plane_layouts_match_the_definition_and_any_thread_count() {
        let mut rng = StdRng::seed_from_u64(12);
        for (n, c, h, w) in [(4, 300, 3, 3), (3, 7, 2, 2), (2, 5, 12, 12), (3, 4, 19, 9)] {
            let len = n * c * h * w;
            let hw = h * w;
            let x: Vec<f32> = (0..len).map(|_| rng.random_range(-4.0..6.0)).collect();
            let dy: Vec<f32> = (0..len).map(|_| rng.random_range(-1.0..1.0)).collect();
            let mut bn = BatchNorm::new(c);
            for ch in 0..c {
                bn.gamma.value[ch] = rng.random_range(0.5..2.0);
                bn.beta.value[ch] = rng.random_range(-1.0..1.0);
            }
            let run = |threads: usize| {
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .expect("pool");
                let mut b = bn.clone();
                pool.install(|| {
                    let t = Tensor::from_vec(n, c, h, w, x.clone()).expect("shape");
                    let y = b.forward_act(t, BnMode::Train, Act::HSwish).expect("fwd");
                    let dx = b.backward_owned(y.like(dy.clone())).expect("bwd");
                    (y.data, dx.data, b.gamma.grad, b.beta.grad)
                })
            };
            let one = run(1);
            let three = run(3);
            let bits = |v: &[f32]| v.iter().map(|f| f.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&one.0), bits(&three.0), "y, {n}x{c}x{h}x{w}");
            assert_eq!(bits(&one.1), bits(&three.1), "dx, {n}x{c}x{h}x{w}");
            assert_eq!(bits(&one.2), bits(&three.2), "dγ, {n}x{c}x{h}x{w}");
            assert_eq!(bits(&one.3), bits(&three.3), "dβ, {n}x{c}x{h}x{w}");
            // The definition: x̂ over the batch and the plane, y = h-swish(γx̂ + β); dL/dpre
            // = dy·h-swish'(pre); dL/dx = γσ⁻¹(dpre − mean(dpre) − x̂·mean(dpre·x̂)).
            let m = (n * hw) as f64;
            let at = |i: usize, ch: usize, p: usize| (i * c + ch) * hw + p;
            for ch in 0..c {
                let vals = || (0..n).flat_map(move |i| (0..hw).map(move |p| at(i, ch, p)));
                let mu = vals().map(|k| x[k] as f64).sum::<f64>() / m;
                let var = vals().map(|k| (x[k] as f64 - mu).powi(2)).sum::<f64>() / m;
                let is = 1.0 / (var + bn.eps as f64).sqrt();
                let (ga, be) = (bn.gamma.value[ch] as f64, bn.beta.value[ch] as f64);
                let xh = |k: usize| (x[k] as f64 - mu) * is;
                let dpre = |k: usize| {
                    let pre = ga * xh(k) + be;
                    let d = if pre <= -3.0 {
                        0.0
                    } else if pre >= 3.0 {
                        1.0
                    } else {
                        (2.0 * pre + 3.0) / 6.0
                    };
                    dy[k] as f64 * d
                };
                let sg = vals().map(dpre).sum::<f64>();
                let sgx = vals().map(|k| dpre(k) * xh(k)).sum::<f64>();
                assert!(
                    (one.3[ch] as f64 - sg).abs() < 1e-4 * (1.0 + sg.abs()),
                    "dβ {ch}"
                );
                assert!(
                    (one.2[ch] as f64 - sgx).abs() < 1e-4 * (1.0 + sgx.abs()),
                    "dγ {ch}"
                );
                for k in vals() {
                    let pre = ga * xh(k) + be;
                    let y = pre * (pre + 3.0).clamp(0.0, 6.0) / 6.0;
                    assert!(
                        (one.0[k] as f64 - y).abs() < 1e-4 * (1.0 + y.abs()),
                        "y {k}"
                    );
                    let dx = ga * is * (dpre(k) - sg / m - xh(k) * sgx / m);
                    assert!(
                        (one.1[k] as f64 - dx).abs() < 1e-4 * (1.0 + dx.abs()),
                        "dx {k}"
                    );
                }
            }
        }
    }

    /// The statistics' lane sums in registers equal the plain loop bit for bit: planes with
    /// and without a tail, from running sums already under way, over values of any scale.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn lane_sums_in_registers_equal_the_plain_loop() {
        if !std::arch::is_x86_feature_detected!("avx2") {
            return;
        }
        let mut rng = StdRng::seed_from_u64(17);
        for hw in [0, 1, 7, 8, 9, 128, 131, 1029] {
            for scale in [1e-30f32, 1.0, 3e18] {
                let plane: Vec<f32> = (0..hw)
                    .map(|_| rng.random_range(-1.0f32..1.0) * scale)
                    .collect();
                let start: [f64; LANES] = std::array::from_fn(|_| rng.random_range(-9.0..9.0));
                let (mut a, mut b) = (start, start.map(f64::abs));
                let (mut a0, mut b0) = (a, b);
                // SAFETY: the CPU has AVX2 (checked above).
                unsafe { lane_sums_avx2(&plane, &mut a, &mut b) };
                lane_sums_scalar(&plane, &mut a0, &mut b0);
                assert_eq!(
                    a.map(f64::to_bits),
                    a0.map(f64::to_bits),
                    "sums, {hw} values"
                );
                assert_eq!(
                    b.map(f64::to_bits),
                    b0.map(f64::to_bits),
                    "squares, {hw} values"
                );
            }
        }
    }

    /// The large-plane backward's sums (dpre and x̂ of a stretch first, then summed) equal the
    /// per-lane loop they replaced, bit for bit, and so does dL/dx: planes with and without a
    /// tail, of one to several stretches, in both modes and for every activation.
    #[test]
    fn stretched_backward_sums_equal_the_per_lane_loop() {
        let mut rng = StdRng::seed_from_u64(13);
        for (nb, c, hw) in [
            (2, 3, 128),
            (3, 2, 620),
            (1, 2, 1029),
            (2, 1, 257),
            (1, 1, 512),
        ] {
            let len = nb * c * hw;
            let x: Vec<f32> = (0..len).map(|_| rng.random_range(-4.0..6.0)).collect();
            let d: Vec<f32> = (0..len).map(|_| rng.random_range(-1.0..1.0)).collect();
            let ga: Vec<f32> = (0..c).map(|_| rng.random_range(0.5..2.0)).collect();
            let be: Vec<f32> = (0..c).map(|_| rng.random_range(-1.0..1.0)).collect();
            let mean: Vec<f32> = (0..c).map(|_| rng.random_range(-0.5..1.5)).collect();
            let inv_std: Vec<f32> = (0..c).map(|_| rng.random_range(0.2..1.5)).collect();
            let p = Pass {
                c,
                hw,
                gamma: &ga,
                beta: &be,
            };
            for act in [Act::Identity, Act::Relu, Act::HSwish, Act::HSigmoid] {
                for batch_stats in [true, false] {
                    let cache = Cache {
                        x: x.clone(),
                        mean: mean.clone(),
                        inv_std: inv_std.clone(),
                        batch_stats,
                        shape: [nb, c, 1, hw],
                        act,
                    };
                    let dpre = |g: f32, h: f32, ga: f32, be: f32| g * act.deriv(ga * h + be);
                    let mut got = d.clone();
                    let sums = p.backward(dpre, nb, &cache, &mut got);
                    let m = (nb * hw) as f32;
                    for ch in 0..c {
                        // The loop before: the tail's values first, then blocks of LANES.
                        let (mu, is) = (mean[ch], inv_std[ch]);
                        let (mut sg, mut sgx) = ([0.0f32; LANES], [0.0f32; LANES]);
                        for n in 0..nb {
                            let off = (n * c + ch) * hw;
                            let (gs, xs) = (&d[off..off + hw], &x[off..off + hw]);
                            let (gb, xb) = (gs.chunks_exact(LANES), xs.chunks_exact(LANES));
                            let tail = gb.remainder().iter().zip(xb.remainder());
                            for (l, (&g, &v)) in tail.enumerate() {
                                let xh = xhat(v, mu, is);
                                let g = dpre(g, xh, ga[ch], be[ch]);
                                sg[l] += g;
                                sgx[l] += g * xh;
                            }
                            for (g, v) in gb.zip(xb) {
                                for l in 0..LANES {
                                    let xh = xhat(v[l], mu, is);
                                    let g = dpre(g[l], xh, ga[ch], be[ch]);
                                    sg[l] += g;
                                    sgx[l] += g * xh;
                                }
                            }
                        }
                        let (sg, sgx) = (sg.iter().sum::<f32>(), sgx.iter().sum::<f32>());
                        let what = format!("{nb}x{c}x{hw} {act:?} {batch_stats}, channel {ch}");
                        assert_eq!(sums[ch].0.to_bits(), sg.to_bits(), "dβ, {what}");
                        assert_eq!(sums[ch].1.to_bits(), sgx.to_bits(), "dγ, {what}");
                        let k = ga[ch] * is;
                        for n in 0..nb {
                            for i in (n * c + ch) * hw..(n * c + ch + 1) * hw {
                                let xh = xhat(x[i], mu, is);
                                let g = dpre(d[i], xh, ga[ch], be[ch]);
                                let want = if batch_stats {
                                    k * (g - sg / m - xh * sgx / m)
                                } else {
                                    k * g
                                };
                                assert_eq!(got[i].to_bits(), want.to_bits(), "dL/dx {i}, {what}");
                            }
                        }
                    }
                }
            }
        }
    }
}

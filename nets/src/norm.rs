//! Batch normalization with training, evaluation and exact-recalibration modes.

use crate::act::PAR_MIN;
use crate::error::{NetsError, Result};
use crate::tensor::{Param, Tensor};
use rayon::prelude::*;

/// Running sums per channel statistic: independent chains the compiler keeps in registers.
const LANES: usize = 8;

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
    xhat: Vec<f32>,
    inv_std: Vec<f32>,
    batch_stats: bool,
    shape: [usize; 4],
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
        let mut mean = vec![0.0f32; c];
        let mut var = vec![0.0f32; c];
        if batch_stats {
            if m == 0.0 {
                return Err(NetsError::Shape("batch norm over an empty batch".into()));
            }
            // Per channel, images in order, in LANES running sums (one chain of dependent
            // additions per channel was latency-bound): the same sums for any thread count.
            let (s1, s2): (Vec<f64>, Vec<f64>) = (0..c)
                .into_par_iter()
                .map(|ch| {
                    let (mut a, mut b) = ([0.0f64; LANES], [0.0f64; LANES]);
                    for n in 0..x.n {
                        let plane = &x.data[(n * c + ch) * hw..][..hw];
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
                    (a.iter().sum::<f64>(), b.iter().sum::<f64>())
                })
                .unzip();
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
        let mut xhat = vec![0.0f32; x.len()];
        if hw > 0 {
            let (gamma, beta) = (&self.gamma.value, &self.beta.value);
            y.data
                .par_chunks_mut(hw)
                .zip(xhat.par_chunks_mut(hw))
                .zip(x.data.par_chunks(hw))
                .enumerate()
                .with_min_len((PAR_MIN / hw).max(1))
                .for_each(|(idx, ((yp, hp), xp))| {
                    let ch = idx % c;
                    let (g, b, mu, is) = (gamma[ch], beta[ch], mean[ch], inv_std[ch]);
                    for ((y, h), &v) in yp.iter_mut().zip(hp.iter_mut()).zip(xp) {
                        *h = (v - mu) * is;
                        *y = g * *h + b;
                    }
                });
        }
        self.cache = Some(Cache {
            xhat,
            inv_std,
            batch_stats,
            shape: x.shape(),
        });
        Ok(y)
    }

    /// VJP of the last forward: returns dL/dx and accumulates dL/dγ, dL/dβ.
    pub fn backward(&mut self, dy: &Tensor) -> Result<Tensor> {
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
        let m = (nb * hw) as f32;
        let mut dx = Tensor::zeros(nb, c, h, w);
        if hw == 0 {
            return Ok(dx);
        }
        let sums: Vec<(f32, f32)> = (0..c)
            .into_par_iter()
            .map(|ch| {
                let (mut sg, mut sgx) = ([0.0f32; LANES], [0.0f32; LANES]);
                for n in 0..nb {
                    let off = (n * c + ch) * hw;
                    let (gs, hs) = (&dy.data[off..off + hw], &cache.xhat[off..off + hw]);
                    let (gb, hb) = (gs.chunks_exact(LANES), hs.chunks_exact(LANES));
                    for (l, (&g, &xh)) in gb.remainder().iter().zip(hb.remainder()).enumerate() {
                        sg[l] += g;
                        sgx[l] += g * xh;
                    }
                    for (g, xh) in gb.zip(hb) {
                        for l in 0..LANES {
                            sg[l] += g[l];
                            sgx[l] += g[l] * xh[l];
                        }
                    }
                }
                (sg.iter().sum::<f32>(), sgx.iter().sum::<f32>())
            })
            .collect();
        for (ch, &(sg, sgx)) in sums.iter().enumerate() {
            self.gamma.grad[ch] += sgx;
            self.beta.grad[ch] += sg;
        }
        let gamma = &self.gamma.value;
        dx.data
            .par_chunks_mut(hw)
            .zip(dy.data.par_chunks(hw))
            .zip(cache.xhat.par_chunks(hw))
            .enumerate()
            .with_min_len((PAR_MIN / hw).max(1))
            .for_each(|(idx, ((dxp, gp), hp))| {
                let ch = idx % c;
                let (sg, sgx) = sums[ch];
                let k = gamma[ch] * cache.inv_std[ch];
                if cache.batch_stats {
                    for ((d, &g), &xh) in dxp.iter_mut().zip(gp).zip(hp) {
                        *d = k * (g - sg / m - xh * sgx / m);
                    }
                } else {
                    for (d, &g) in dxp.iter_mut().zip(gp) {
                        *d = k * g;
                    }
                }
            });
        Ok(dx)
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

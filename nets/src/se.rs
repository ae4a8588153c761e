//! Squeeze-and-excitation: y = x ⊙ h-sigmoid(W2·ReLU(W1·GAP(x) + b1) + b2).

use crate::act::{Act, PAR_MIN};
use crate::error::{NetsError, Result};
use crate::tensor::Tensor;
use rayon::prelude::*;

/// Weights of one SE module: W1 (M, C), b1 (M), W2 (C, M), b2 (C), all row-major.
#[derive(Clone, Copy, Debug)]
pub struct SeWeights<'a> {
    /// Squeeze weights (M × C).
    pub w1: &'a [f32],
    /// Squeeze bias (M).
    pub b1: &'a [f32],
    /// Excite weights (C × M).
    pub w2: &'a [f32],
    /// Excite bias (C).
    pub b2: &'a [f32],
}

/// Gradients of one SE module, same layout as [`SeWeights`].
#[derive(Debug)]
pub struct SeGrads<'a> {
    /// dL/dW1.
    pub w1: &'a mut [f32],
    /// dL/db1.
    pub b1: &'a mut [f32],
    /// dL/dW2.
    pub w2: &'a mut [f32],
    /// dL/db2.
    pub b2: &'a mut [f32],
}

/// What the SE backward pass needs: pooled input, squeeze and excite pre-activations.
#[derive(Clone, Debug)]
pub struct SeCache {
    s: Vec<f32>,
    z: Vec<f32>,
    a: Vec<f32>,
    m: usize,
}

fn check(x: &Tensor, wt: &SeWeights) -> Result<usize> {
    let c = x.c;
    let m = wt.b1.len();
    if wt.w1.len() != m * c || wt.w2.len() != c * m || wt.b2.len() != c {
        return Err(NetsError::Shape(format!(
            "SE weights do not fit C = {c}, M = {m}"
        )));
    }
    Ok(m)
}

/// SE forward pass.
pub fn se_forward(x: &Tensor, wt: &SeWeights) -> Result<(Tensor, SeCache)> {
    let m = check(x, wt)?;
    let (c, hw) = (x.c, x.plane());
    let per_task = (PAR_MIN / hw.max(1)).max(1);
    let s: Vec<f32> = x
        .data
        .par_chunks(hw.max(1))
        .with_min_len(per_task)
        .map(|p| p.iter().sum::<f32>() / hw as f32)
        .collect();
    let mut z = vec![0.0f32; x.n * m];
    let mut a = vec![0.0f32; x.n * c];
    for n in 0..x.n {
        let sn = &s[n * c..][..c];
        for j in 0..m {
            z[n * m + j] = wt.b1[j]
                + wt.w1[j * c..][..c]
                    .iter()
                    .zip(sn)
                    .map(|(w, v)| w * v)
                    .sum::<f32>();
        }
        for ch in 0..c {
            a[n * c + ch] = wt.b2[ch]
                + (0..m)
                    .map(|j| wt.w2[ch * m + j] * Act::Relu.apply(z[n * m + j]))
                    .sum::<f32>();
        }
    }
    let mut y = x.clone();
    y.data
        .par_chunks_mut(hw.max(1))
        .zip(&a)
        .with_min_len(per_task)
        .for_each(|(p, &av)| {
            let g = Act::HSigmoid.apply(av);
            p.iter_mut().for_each(|v| *v *= g);
        });
    Ok((y, SeCache { s, z, a, m }))
}

/// VJP of [`se_forward`]: returns dL/dx and accumulates the weight gradients.
pub fn se_vjp(
    x: &Tensor,
    wt: &SeWeights,
    cache: &SeCache,
    dy: &Tensor,
    gr: SeGrads,
) -> Result<Tensor> {
    let m = check(x, wt)?;
    x.check_same(dy, "SE upstream gradient")?;
    if m != cache.m {
        return Err(NetsError::Shape("SE cache from another width".into()));
    }
    let (c, hw) = (x.c, x.plane());
    let mut dx = Tensor::zeros(x.n, c, x.h, x.w);
    if dx.data.is_empty() {
        return Ok(dx);
    }
    let per_task = (PAR_MIN / hw).max(1);
    // The plane-sized work (dL/dgate and the gated gradient) in parallel; the small dense
    // layers below stay serial, in the original order.
    let dgate: Vec<f32> = dx
        .data
        .par_chunks_mut(hw)
        .zip(dy.data.par_chunks(hw))
        .zip(x.data.par_chunks(hw))
        .zip(&cache.a)
        .with_min_len(per_task)
        .map(|(((dxp, gp), xp), &av)| {
            let g = Act::HSigmoid.apply(av);
            let mut dg = 0.0f32;
            for ((d, &gy), &xv) in dxp.iter_mut().zip(gp).zip(xp) {
                dg += gy * xv;
                *d = gy * g;
            }
            dg
        })
        .collect();
    let mut ds_all = vec![0.0f32; x.n * c];
    for n in 0..x.n {
        let ds = &mut ds_all[n * c..][..c];
        let mut dz = vec![0.0f32; m];
        for ch in 0..c {
            let av = cache.a[n * c + ch];
            let da = dgate[n * c + ch] * Act::HSigmoid.deriv(av);
            gr.b2[ch] += da;
            for j in 0..m {
                gr.w2[ch * m + j] += da * Act::Relu.apply(cache.z[n * m + j]);
                dz[j] += da * wt.w2[ch * m + j];
            }
        }
        for j in 0..m {
            let dzj = dz[j] * Act::Relu.deriv(cache.z[n * m + j]);
            gr.b1[j] += dzj;
            for ch in 0..c {
                gr.w1[j * c + ch] += dzj * cache.s[n * c + ch];
                ds[ch] += dzj * wt.w1[j * c + ch];
            }
        }
    }
    dx.data
        .par_chunks_mut(hw)
        .zip(&ds_all)
        .with_min_len(per_task)
        .for_each(|(p, &d)| {
            let v = d / hw as f32;
            p.iter_mut().for_each(|x| *x += v);
        });
    Ok(dx)
}

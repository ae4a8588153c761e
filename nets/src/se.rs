//! Squeeze-and-excitation: y = x ⊙ h-sigmoid(W2·ReLU(W1·GAP(x) + b1) + b2).

use crate::act::{Act, PAR_MIN};
use crate::dense::{gemm, rm};
use crate::error::{NetsError, Result};
use crate::tensor::Tensor;
use faer::Accum;
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

/// What the SE backward pass needs: pooled input, squeeze activations ReLU(z) (their
/// derivative is read from them: ReLU(z) > 0 exactly where z > 0), excite pre-activations.
#[derive(Clone, Debug)]
pub struct SeCache {
    s: Vec<f32>,
    r: Vec<f32>,
    a: Vec<f32>,
    m: usize,
}

/// One dense layer for the whole batch: Y (n × out) = X (n × inp)·Wᵀ + b, with W (out × inp)
/// row-major and out = `b.len()`; one GEMM where per-image dot products would run serially.
fn dense_rows(x: &[f32], n: usize, inp: usize, w: &[f32], b: &[f32]) -> Vec<f32> {
    let out = b.len();
    let mut y: Vec<f32> = (0..n).flat_map(|_| b.iter().copied()).collect();
    gemm(
        &mut y,
        n,
        out,
        Accum::Add,
        rm(x, n, inp),
        rm(w, out, inp).transpose(),
    );
    y
}

/// Adds every row of `rows` (rows of `acc.len()` values) into `acc`: a bias gradient.
fn add_rows(acc: &mut [f32], rows: &[f32]) {
    for row in rows.chunks_exact(acc.len().max(1)) {
        acc.iter_mut().zip(row).for_each(|(g, &d)| *g += d);
    }
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
    // z = S·W1ᵀ + b1 (N × M), a = ReLU(z)·W2ᵀ + b2 (N × C).
    let n = x.n;
    let mut r = dense_rows(&s, n, c, wt.w1, wt.b1);
    r.iter_mut().for_each(|v| *v = Act::Relu.apply(*v));
    let a = dense_rows(&r, n, m, wt.w2, wt.b2);
    let mut y = x.clone();
    y.data
        .par_chunks_mut(hw.max(1))
        .zip(&a)
        .with_min_len(per_task)
        .for_each(|(p, &av)| {
            let g = Act::HSigmoid.apply(av);
            p.iter_mut().for_each(|v| *v *= g);
        });
    Ok((y, SeCache { s, r, a, m }))
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
    let c = x.c;
    if gr.w1.len() != m * c || gr.w2.len() != c * m || gr.b1.len() != m || gr.b2.len() != c {
        return Err(NetsError::Shape(format!(
            "SE gradients do not fit C = {c}, M = {m}"
        )));
    }
    let hw = x.plane();
    let mut dx = Tensor::zeros(x.n, c, x.h, x.w);
    if dx.data.is_empty() {
        return Ok(dx);
    }
    let per_task = (PAR_MIN / hw).max(1);
    // The plane-sized work (dL/dgate and the gated gradient) in parallel.
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
    // The dense layers' backward as GEMMs over the batch (N × C and N × M matrices).
    let n = x.n;
    let da: Vec<f32> = dgate
        .iter()
        .zip(&cache.a)
        .map(|(&g, &av)| g * Act::HSigmoid.deriv(av))
        .collect();
    let r = &cache.r;
    add_rows(gr.b2, &da);
    // dL/dW2 (C × M) += daᵀ·ReLU(z).
    gemm(
        gr.w2,
        c,
        m,
        Accum::Add,
        rm(&da, n, c).transpose(),
        rm(r, n, m),
    );
    // dL/dz (N × M) = (da·W2) ⊙ ReLU′(z).
    let mut dz = vec![0.0f32; n * m];
    gemm(
        &mut dz,
        n,
        m,
        Accum::Replace,
        rm(&da, n, c),
        rm(wt.w2, c, m),
    );
    dz.iter_mut()
        .zip(r)
        .for_each(|(d, &rv)| *d *= Act::Relu.deriv(rv));
    add_rows(gr.b1, &dz);
    // dL/dW1 (M × C) += dzᵀ·S; dL/dS (N × C) = dz·W1.
    gemm(
        gr.w1,
        m,
        c,
        Accum::Add,
        rm(&dz, n, m).transpose(),
        rm(&cache.s, n, c),
    );
    let mut ds_all = vec![0.0f32; n * c];
    gemm(
        &mut ds_all,
        n,
        c,
        Accum::Replace,
        rm(&dz, n, m),
        rm(wt.w1, m, c),
    );
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

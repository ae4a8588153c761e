//! Convolutions with explicit vector–Jacobian products: dense k×k (the stem), depthwise k×k,
//! and 1×1 (pointwise) on faer's GEMM. Padding is "same" (k/2), strides 1 or 2.

use crate::depthwise;
use crate::error::{NetsError, Result};
use crate::tensor::Tensor;
use faer::linalg::matmul::matmul;
use faer::{Accum, MatMut, MatRef, Par};
use rayon::prelude::*;

/// Output size of a same-padded convolution: ⌊(n + 2⌊k/2⌋ − k)/s⌋ + 1.
pub fn out_size(n: usize, k: usize, stride: usize) -> usize {
    (n + 2 * (k / 2) - k) / stride + 1
}

/// Range of output indices `o` for which `o·s + t − p` lies in [0, n).
#[inline]
fn valid_range(n_in: usize, n_out: usize, s: usize, t: usize, p: usize) -> (usize, usize) {
    let lo = if t >= p { 0 } else { (p - t).div_ceil(s) };
    let hi = if n_in + p > t {
        ((n_in - 1 + p - t) / s + 1).min(n_out)
    } else {
        0
    };
    (lo, hi.max(lo))
}

fn check_weights(len: usize, want: usize, what: &str) -> Result<()> {
    if len != want {
        return Err(NetsError::Shape(format!(
            "{what}: {len} weights, expected {want}"
        )));
    }
    Ok(())
}

/// Dense k×k convolution (groups = 1, no bias): weights (C_out, C_in, k, k).
pub fn conv2d_forward(
    x: &Tensor,
    w: &[f32],
    cout: usize,
    k: usize,
    stride: usize,
) -> Result<Tensor> {
    check_weights(w.len(), cout * x.c * k * k, "conv2d")?;
    let (ho, wo) = (out_size(x.h, k, stride), out_size(x.w, k, stride));
    let mut y = Tensor::zeros(x.n, cout, ho, wo);
    let p = k / 2;
    let cin = x.c;
    y.data
        .par_chunks_mut(ho * wo)
        .enumerate()
        .for_each(|(idx, out)| {
            let (n, o) = (idx / cout, idx % cout);
            for i in 0..cin {
                let xp = &x.data[(n * cin + i) * x.h * x.w..][..x.h * x.w];
                for ky in 0..k {
                    let (y0, y1) = valid_range(x.h, ho, stride, ky, p);
                    for kx in 0..k {
                        let wv = w[((o * cin + i) * k + ky) * k + kx];
                        let (x0, x1) = valid_range(x.w, wo, stride, kx, p);
                        for oy in y0..y1 {
                            let iy = oy * stride + ky - p;
                            let row = &xp[iy * x.w..];
                            let orow = &mut out[oy * wo..];
                            for ox in x0..x1 {
                                orow[ox] += wv * row[ox * stride + kx - p];
                            }
                        }
                    }
                }
            }
        });
    Ok(y)
}

/// VJP of [`conv2d_forward`]: returns dL/dx and adds dL/dw into `dw`.
pub fn conv2d_vjp(
    x: &Tensor,
    w: &[f32],
    cout: usize,
    k: usize,
    stride: usize,
    dy: &Tensor,
    dw: &mut [f32],
) -> Result<Tensor> {
    check_weights(w.len(), cout * x.c * k * k, "conv2d")?;
    check_weights(dw.len(), w.len(), "conv2d gradient")?;
    let (ho, wo) = (out_size(x.h, k, stride), out_size(x.w, k, stride));
    if dy.shape() != [x.n, cout, ho, wo] {
        return Err(NetsError::Shape(format!(
            "conv2d upstream gradient {:?}",
            dy.shape()
        )));
    }
    let p = k / 2;
    let cin = x.c;
    let mut dx = Tensor::zeros(x.n, cin, x.h, x.w);
    let dws: Vec<Vec<f32>> = dx
        .data
        .par_chunks_mut(cin * x.h * x.w)
        .enumerate()
        .map(|(n, dxi)| {
            let mut dwl = vec![0.0f32; w.len()];
            for o in 0..cout {
                let g = &dy.data[(n * cout + o) * ho * wo..][..ho * wo];
                for i in 0..cin {
                    let xp = &x.data[(n * cin + i) * x.h * x.w..][..x.h * x.w];
                    let dxp = &mut dxi[i * x.h * x.w..][..x.h * x.w];
                    for ky in 0..k {
                        let (y0, y1) = valid_range(x.h, ho, stride, ky, p);
                        for kx in 0..k {
                            let wi = ((o * cin + i) * k + ky) * k + kx;
                            let wv = w[wi];
                            let (x0, x1) = valid_range(x.w, wo, stride, kx, p);
                            let mut acc = 0.0f32;
                            for oy in y0..y1 {
                                let iy = oy * stride + ky - p;
                                for ox in x0..x1 {
                                    let ix = ox * stride + kx - p;
                                    let gv = g[oy * wo + ox];
                                    acc += gv * xp[iy * x.w + ix];
                                    dxp[iy * x.w + ix] += gv * wv;
                                }
                            }
                            dwl[wi] += acc;
                        }
                    }
                }
            }
            dwl
        })
        .collect();
    for d in dws {
        for (a, b) in dw.iter_mut().zip(d) {
            *a += b;
        }
    }
    Ok(dx)
}

/// Depthwise k×k convolution: weights (C, k, k), one filter per channel, no bias.
pub fn depthwise_forward(x: &Tensor, w: &[f32], k: usize, stride: usize) -> Result<Tensor> {
    check_weights(w.len(), x.c * k * k, "depthwise")?;
    check_stride(stride)?;
    let g = depthwise_geom(x, k, stride);
    let mut y = Tensor::zeros(x.n, x.c, g.ho, g.wo);
    depthwise::forward(&g, x.c, &x.data, w, &mut y.data);
    Ok(y)
}

fn check_stride(stride: usize) -> Result<()> {
    if stride == 0 {
        return Err(NetsError::Shape("convolution stride 0".into()));
    }
    Ok(())
}

fn depthwise_geom(x: &Tensor, k: usize, stride: usize) -> depthwise::Geom {
    depthwise::Geom {
        h: x.h,
        w: x.w,
        ho: out_size(x.h, k, stride),
        wo: out_size(x.w, k, stride),
        k,
        s: stride,
    }
}

/// VJP of [`depthwise_forward`]: returns dL/dx and adds dL/dw into `dw`.
pub fn depthwise_vjp(
    x: &Tensor,
    w: &[f32],
    k: usize,
    stride: usize,
    dy: &Tensor,
    dw: &mut [f32],
) -> Result<Tensor> {
    check_weights(w.len(), x.c * k * k, "depthwise")?;
    check_weights(dw.len(), w.len(), "depthwise gradient")?;
    check_stride(stride)?;
    let g = depthwise_geom(x, k, stride);
    if dy.shape() != [x.n, x.c, g.ho, g.wo] {
        return Err(NetsError::Shape(format!(
            "depthwise upstream gradient {:?}",
            dy.shape()
        )));
    }
    let kk = k * k;
    let mut dx = Tensor::zeros(x.n, x.c, x.h, x.w);
    let mut per_plane = vec![0.0f32; x.n * x.c * kk];
    depthwise::backward(&g, x.c, &x.data, w, &dy.data, &mut dx.data, &mut per_plane);
    // Images summed in index order: the same result for any thread count.
    for img in per_plane.chunks_exact(x.c * kk) {
        for (a, b) in dw.iter_mut().zip(img) {
            *a += b;
        }
    }
    Ok(dx)
}

/// 1×1 convolution as one GEMM per image, Y_n = W·X_n (+ b): weights (C_out, C_in) row-major.
pub fn pointwise_forward(
    x: &Tensor,
    w: &[f32],
    cout: usize,
    bias: Option<&[f32]>,
) -> Result<Tensor> {
    check_weights(w.len(), cout * x.c, "pointwise")?;
    if let Some(b) = bias {
        check_weights(b.len(), cout, "pointwise bias")?;
    }
    let hw = x.plane();
    let cin = x.c;
    let mut y = Tensor::zeros(x.n, cout, x.h, x.w);
    if hw == 0 || x.n == 0 {
        return Ok(y);
    }
    let wm = MatRef::from_row_major_slice(w, cout, cin);
    if hw == 1 {
        // One pixel per image (the heads after global pooling): the batch is one GEMM,
        // Y (C_out × N) = W·X (C_in × N), so W streams once instead of once per image.
        let xm = MatRef::from_column_major_slice(&x.data, cin, x.n);
        let ym = MatMut::from_column_major_slice_mut(&mut y.data, cout, x.n);
        gemm_row_blocks(ym, Accum::Replace, wm, xm);
        if let Some(b) = bias {
            for yi in y.data.chunks_exact_mut(cout) {
                yi.iter_mut().zip(b).for_each(|(v, bo)| *v += bo);
            }
        }
        return Ok(y);
    }
    if hw <= SMALL_PLANE {
        // Few pixels per image (the deep stages): one GEMM over the batch's N·HW columns,
        // instead of N GEMMs whose fixed costs outweigh their few columns.
        let nhw = x.n * hw;
        let xp = pack_planes(&x.data, x.n, cin, hw);
        let mut yp = vec![0.0f32; cout * nhw];
        gemm_col_blocks(
            MatMut::from_row_major_slice_mut(&mut yp, cout, nhw),
            Accum::Replace,
            wm,
            MatRef::from_row_major_slice(&xp, cin, nhw),
        );
        unpack_planes(&yp, &mut y.data, x.n, cout, hw);
        if let Some(b) = bias {
            for (i, row) in y.data.chunks_mut(hw).enumerate() {
                let bo = b[i % cout];
                row.iter_mut().for_each(|v| *v += bo);
            }
        }
        return Ok(y);
    }
    y.data
        .par_chunks_mut(cout * hw)
        .enumerate()
        .for_each(|(n, yi)| {
            let xm = MatRef::from_row_major_slice(&x.data[n * cin * hw..][..cin * hw], cin, hw);
            let ym = MatMut::from_row_major_slice_mut(yi, cout, hw);
            matmul(ym, Accum::Replace, wm, xm, 1.0f32, Par::Seq);
            if let Some(b) = bias {
                for (o, row) in yi.chunks_mut(hw).enumerate() {
                    row.iter_mut().for_each(|v| *v += b[o]);
                }
            }
        });
    Ok(y)
}

/// VJP of [`pointwise_forward`]: returns dL/dx = Wᵀ·dY and adds dY·Xᵀ into `dw`, Σ dY into `db`.
pub fn pointwise_vjp(
    x: &Tensor,
    w: &[f32],
    cout: usize,
    dy: &Tensor,
    dw: &mut [f32],
    db: Option<&mut [f32]>,
) -> Result<Tensor> {
    check_weights(w.len(), cout * x.c, "pointwise")?;
    check_weights(dw.len(), w.len(), "pointwise gradient")?;
    if dy.shape() != [x.n, cout, x.h, x.w] {
        return Err(NetsError::Shape(format!(
            "pointwise upstream gradient {:?}",
            dy.shape()
        )));
    }
    let hw = x.plane();
    let cin = x.c;
    let mut dx = Tensor::zeros(x.n, cin, x.h, x.w);
    if hw == 0 || x.n == 0 {
        return Ok(dx);
    }
    let wm = MatRef::from_row_major_slice(w, cout, cin);
    if hw == 1 {
        // As in the forward pass, the batch is one GEMM per product: dX = Wᵀ·dY and
        // dW += dY·Xᵀ with N as the inner dimension, instead of N rank-1 outer products of
        // C_out × C_in each written to a fresh buffer and summed (the 1280 × 1360 head layer's
        // 7 MB per image).
        let g = MatRef::from_column_major_slice(&dy.data, cout, x.n);
        let xm = MatRef::from_column_major_slice(&x.data, cin, x.n);
        let dxm = MatMut::from_column_major_slice_mut(&mut dx.data, cin, x.n);
        gemm_row_blocks(dxm, Accum::Replace, wm.transpose(), g);
        let dwm = MatMut::from_row_major_slice_mut(dw, cout, cin);
        gemm_row_blocks(dwm, Accum::Add, g, xm.transpose());
    } else if hw <= SMALL_PLANE {
        // As in the forward pass: the batch as N·HW columns, dX = Wᵀ·dY in column blocks and
        // dW += dY·Xᵀ with N·HW as the inner dimension (no per-image partial sums).
        let nhw = x.n * hw;
        let g = pack_planes(&dy.data, x.n, cout, hw);
        let xp = pack_planes(&x.data, x.n, cin, hw);
        let gm = MatRef::from_row_major_slice(&g, cout, nhw);
        let mut dxp = vec![0.0f32; cin * nhw];
        gemm_col_blocks(
            MatMut::from_row_major_slice_mut(&mut dxp, cin, nhw),
            Accum::Replace,
            wm.transpose(),
            gm,
        );
        unpack_planes(&dxp, &mut dx.data, x.n, cin, hw);
        let dwm = MatMut::from_row_major_slice_mut(dw, cout, cin);
        gemm_row_blocks(
            dwm,
            Accum::Add,
            gm,
            MatRef::from_row_major_slice(&xp, cin, nhw).transpose(),
        );
    } else {
        pointwise_weight_grad(x, cout, dy, &mut dx, wm, dw);
    }
    if let Some(db) = db {
        check_weights(db.len(), cout, "pointwise bias gradient")?;
        for n in 0..x.n {
            for (o, dbo) in db.iter_mut().enumerate() {
                *dbo += dy.data[(n * cout + o) * hw..][..hw].iter().sum::<f32>();
            }
        }
    }
    Ok(dx)
}

/// Largest plane (pixels per image and channel) that [`pointwise_forward`] and
/// [`pointwise_vjp`] run as one GEMM over the batch.
const SMALL_PLANE: usize = 64;

/// Columns of a GEMM output per parallel task in [`gemm_col_blocks`]: fixed, like
/// [`ROW_BLOCK`].
const COL_BLOCK: usize = 256;

/// NCHW planes (`n` images of `c` planes of `hw`) as a row-major C × (N·HW) matrix.
fn pack_planes(src: &[f32], n: usize, c: usize, hw: usize) -> Vec<f32> {
    let nhw = n * hw;
    let mut out = vec![0.0f32; c * nhw];
    for (i, plane) in src.chunks_exact(hw).enumerate() {
        let (img, ch) = (i / c, i % c);
        out[ch * nhw + img * hw..][..hw].copy_from_slice(plane);
    }
    out
}

/// Inverse of [`pack_planes`]: a row-major C × (N·HW) matrix back into NCHW `dst`.
fn unpack_planes(src: &[f32], dst: &mut [f32], n: usize, c: usize, hw: usize) {
    let nhw = n * hw;
    for (i, plane) in dst.chunks_exact_mut(hw).enumerate() {
        let (img, ch) = (i / c, i % c);
        plane.copy_from_slice(&src[ch * nhw + img * hw..][..hw]);
    }
}

/// dst (+)= a·b with the columns of `dst` (and `b`) split into blocks of [`COL_BLOCK`]: the
/// row blocks of the transposed product, dstᵀ (+)= bᵀ·aᵀ.
fn gemm_col_blocks(dst: MatMut<'_, f32>, accum: Accum, a: MatRef<'_, f32>, b: MatRef<'_, f32>) {
    gemm_blocks(
        dst.transpose_mut(),
        accum,
        b.transpose(),
        a.transpose(),
        COL_BLOCK,
    );
}

/// Rows of a GEMM output per parallel task in [`gemm_row_blocks`]: fixed, so that which kernel
/// call computes an output element does not depend on the thread count.
const ROW_BLOCK: usize = 64;

/// dst (+)= a·b with the rows of `dst` (and `a`) split into blocks of [`ROW_BLOCK`].
fn gemm_row_blocks(dst: MatMut<'_, f32>, accum: Accum, a: MatRef<'_, f32>, b: MatRef<'_, f32>) {
    gemm_blocks(dst, accum, a, b, ROW_BLOCK);
}

/// dst (+)= a·b with the rows of `dst` (and `a`) split into blocks of `block`, one sequential
/// GEMM per block, the blocks in parallel.
fn gemm_blocks(
    dst: MatMut<'_, f32>,
    accum: Accum,
    a: MatRef<'_, f32>,
    b: MatRef<'_, f32>,
    block: usize,
) {
    let mut blocks = Vec::with_capacity(dst.nrows().div_ceil(block));
    let mut rest = dst;
    while rest.nrows() > block {
        let (top, bottom) = rest.split_at_row_mut(block);
        blocks.push(top);
        rest = bottom;
    }
    blocks.push(rest);
    blocks.into_par_iter().enumerate().for_each(|(i, blk)| {
        let rows = blk.nrows();
        matmul(blk, accum, a.subrows(i * block, rows), b, 1.0f32, Par::Seq);
    });
}

/// The weight and input gradients of [`pointwise_vjp`] for planes of more than one pixel: one
/// pair of GEMMs per image in parallel, the per-image weight gradients summed in image order
/// (the same result for any thread count).
fn pointwise_weight_grad(
    x: &Tensor,
    cout: usize,
    dy: &Tensor,
    dx: &mut Tensor,
    wm: MatRef<'_, f32>,
    dw: &mut [f32],
) {
    let hw = x.plane();
    let cin = x.c;
    let dws: Vec<Vec<f32>> = dx
        .data
        .par_chunks_mut(cin * hw)
        .enumerate()
        .map(|(n, dxi)| {
            let g = MatRef::from_row_major_slice(&dy.data[n * cout * hw..][..cout * hw], cout, hw);
            let xm = MatRef::from_row_major_slice(&x.data[n * cin * hw..][..cin * hw], cin, hw);
            let dxm = MatMut::from_row_major_slice_mut(dxi, cin, hw);
            matmul(dxm, Accum::Replace, wm.transpose(), g, 1.0f32, Par::Seq);
            let mut dwl = vec![0.0f32; cout * cin];
            let dwm = MatMut::from_row_major_slice_mut(&mut dwl, cout, cin);
            matmul(dwm, Accum::Replace, g, xm.transpose(), 1.0f32, Par::Seq);
            dwl
        })
        .collect();
    for d in dws {
        for (a, b) in dw.iter_mut().zip(d) {
            *a += b;
        }
    }
}

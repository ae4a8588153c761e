//! Convolutions with explicit vector–Jacobian products: dense k×k (the stem), depthwise k×k,
//! and 1×1 (pointwise) on faer's GEMM. Padding is "same" (k/2), strides 1 or 2.

use crate::act::PAR_MIN;
use crate::depthwise;
use crate::error::{NetsError, Result};
use crate::tensor::Tensor;
use faer::linalg::matmul::matmul;
use faer::{Accum, MatMut, MatRef, Par};
use rayon::prelude::*;
use std::mem::MaybeUninit;

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
    check_stride(stride)?;
    let (ho, wo) = (out_size(x.h, k, stride), out_size(x.w, k, stride));
    let mut y = Tensor::zeros(x.n, cout, ho, wo);
    if ho * wo == 0 || x.plane() == 0 {
        return Ok(y);
    }
    let ph = Phases::of(x, stride, k / 2);
    let cin = x.c;
    y.data
        .par_chunks_mut(ho * wo)
        .enumerate()
        .for_each(|(idx, out)| {
            let (n, o) = (idx / cout, idx % cout);
            // Per output element the taps add in (i, ky, kx) order, as a direct loop would.
            for i in 0..cin {
                for ky in 0..k {
                    let (y0, y1) = valid_range(x.h, ho, stride, ky, ph.pad);
                    for kx in 0..k {
                        let wv = w[((o * cin + i) * k + ky) * k + kx];
                        let (x0, x1) = valid_range(x.w, wo, stride, kx, ph.pad);
                        for oy in y0..y1 {
                            let src = ph.run(n * cin + i, oy * stride + ky - ph.pad, kx, x0, x1);
                            let orow = &mut out[oy * wo + x0..oy * wo + x1];
                            orow.iter_mut().zip(src).for_each(|(o, &v)| *o += wv * v);
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
    check_stride(stride)?;
    let (ho, wo) = (out_size(x.h, k, stride), out_size(x.w, k, stride));
    if dy.shape() != [x.n, cout, ho, wo] {
        return Err(NetsError::Shape(format!(
            "conv2d upstream gradient {:?}",
            dy.shape()
        )));
    }
    let cin = x.c;
    let mut dx = Tensor::zeros(x.n, cin, x.h, x.w);
    if ho * wo == 0 || x.plane() == 0 {
        return Ok(dx);
    }
    let ph = Phases::of(x, stride, k / 2);
    let mut dph = vec![0.0f32; ph.data.len()];
    let per_image = cin * ph.plane_len();
    let dws: Vec<Vec<f32>> = dph
        .par_chunks_mut(per_image)
        .enumerate()
        .map(|(n, dxi)| {
            let mut dwl = vec![0.0f32; w.len()];
            // dL/dx adds its taps in (o, ky, kx) order per element, as a direct loop would;
            // dL/dw sums each tap's products in LANES running sums (one dependent chain per
            // tap was latency-bound).
            for o in 0..cout {
                let g = &dy.data[(n * cout + o) * ho * wo..][..ho * wo];
                for i in 0..cin {
                    for ky in 0..k {
                        let (y0, y1) = valid_range(x.h, ho, stride, ky, ph.pad);
                        for kx in 0..k {
                            let wi = ((o * cin + i) * k + ky) * k + kx;
                            let wv = w[wi];
                            let (x0, x1) = valid_range(x.w, wo, stride, kx, ph.pad);
                            let mut acc = [0.0f32; LANES];
                            for oy in y0..y1 {
                                let iy = oy * stride + ky - ph.pad;
                                let gr = &g[oy * wo + x0..oy * wo + x1];
                                let off = ph.offset(i, iy, kx, x0);
                                let xr = &ph.data[n * per_image + off..][..x1 - x0];
                                let dr = &mut dxi[off..][..x1 - x0];
                                dr.iter_mut().zip(gr).for_each(|(d, &gv)| *d += gv * wv);
                                lane_dot(&mut acc, gr, xr);
                            }
                            dwl[wi] += acc.iter().sum::<f32>();
                        }
                    }
                }
            }
            dwl
        })
        .collect();
    // Images summed in index order: the same result for any thread count.
    for d in dws {
        for (a, b) in dw.iter_mut().zip(d) {
            *a += b;
        }
    }
    ph.unsplit(&dph, &mut dx.data);
    Ok(dx)
}

/// Running sums per lane of `a`·`b`, element j into lane j mod LANES.
#[inline]
fn lane_dot(acc: &mut [f32; LANES], a: &[f32], b: &[f32]) {
    let (ac, bc) = (a.chunks_exact(LANES), b.chunks_exact(LANES));
    for (l, (&u, &v)) in ac.remainder().iter().zip(bc.remainder()).enumerate() {
        acc[l] += u * v;
    }
    for (u, v) in ac.zip(bc) {
        for l in 0..LANES {
            acc[l] += u[l] * v[l];
        }
    }
}

/// Lanes of [`lane_dot`].
const LANES: usize = 8;

/// The planes of a tensor split by column phase for a stride s: phase r of row y holds
/// columns r, r + s, r + 2s, …, so the columns a stride-s tap reads are one contiguous run
/// (vector loads instead of a gather).
struct Phases {
    data: Vec<f32>,
    /// Stride s.
    s: usize,
    /// Padding ⌊k/2⌋ (input column of output o, tap t: o·s + t − pad).
    pad: usize,
    /// Rows per plane.
    h: usize,
    /// Columns per plane.
    w: usize,
    /// Entries per phase row, ⌈W/s⌉.
    pw: usize,
}

impl Phases {
    /// Every plane of `x` in phase layout: index ((plane·s + r)·H + y)·⌈W/s⌉ + j ↔ column j·s + r.
    fn of(x: &Tensor, s: usize, pad: usize) -> Self {
        let (h, w) = (x.h, x.w);
        let pw = w.div_ceil(s);
        let mut ph = Self {
            data: vec![0.0f32; x.n * x.c * s * h * pw],
            s,
            pad,
            h,
            w,
            pw,
        };
        let len = ph.plane_len();
        let mut data = std::mem::take(&mut ph.data);
        data.par_chunks_mut(len)
            .zip(x.data.par_chunks(h * w))
            .for_each(|(dst, src)| {
                for (y, row) in src.chunks_exact(w).enumerate() {
                    for r in 0..s {
                        let d = &mut dst[(r * h + y) * pw..][..pw];
                        for (dv, &v) in d.iter_mut().zip(row.iter().skip(r).step_by(s)) {
                            *dv = v;
                        }
                    }
                }
            });
        ph.data = data;
        ph
    }

    /// Entries per plane, s·H·⌈W/s⌉.
    fn plane_len(&self) -> usize {
        self.s * self.h * self.pw
    }

    /// Index within a plane's phases of the run that tap column `kx` reads on input row `iy`
    /// for outputs x0.. (input columns o·s + kx − pad, inside the row by `valid_range`),
    /// offset by `plane` planes.
    fn offset(&self, plane: usize, iy: usize, kx: usize, x0: usize) -> usize {
        let first = x0 * self.s + kx - self.pad;
        plane * self.plane_len() + ((first % self.s) * self.h + iy) * self.pw + first / self.s
    }

    /// The run of `plane`, input row `iy`, that tap column `kx` reads for outputs x0..x1.
    fn run(&self, plane: usize, iy: usize, kx: usize, x0: usize, x1: usize) -> &[f32] {
        &self.data[self.offset(plane, iy, kx, x0)..][..x1 - x0]
    }

    /// Phase-layout planes `src` (this layout's shape) back into row-major planes `dst`.
    fn unsplit(&self, src: &[f32], dst: &mut [f32]) {
        let (s, h, w, pw) = (self.s, self.h, self.w, self.pw);
        dst.par_chunks_mut(h * w)
            .zip(src.par_chunks(self.plane_len()))
            .for_each(|(plane, ph)| {
                for (y, row) in plane.chunks_exact_mut(w).enumerate() {
                    for r in 0..s {
                        let from = &ph[(r * h + y) * pw..][..pw];
                        for (dv, &v) in row.iter_mut().skip(r).step_by(s).zip(from) {
                            *dv = v;
                        }
                    }
                }
            });
    }
}

/// Depthwise k×k convolution: weights (C, k, k), one filter per channel, no bias.
pub fn depthwise_forward(x: &Tensor, w: &[f32], k: usize, stride: usize) -> Result<Tensor> {
    check_weights(w.len(), x.c * k * k, "depthwise")?;
    check_stride(stride)?;
    check_holds(x, "depthwise input")?;
    let g = depthwise_geom(x, k, stride);
    // SAFETY: the forward writes every output value (its contract); the input holds its
    // n·c·h·w values, so n·c·ho·wo (ho ≤ h, wo ≤ w) does not overflow.
    let y = unsafe {
        written(x.n * x.c * g.ho * g.wo, |y| {
            depthwise::forward(&g, x.c, &x.data, w, y)
        })
    };
    Tensor::from_vec(x.n, x.c, g.ho, g.wo, y)
}

/// `len` values, every one written by `fill`: no zeroing pass over a fresh output that the
/// depthwise kernels then overwrite whole (19 % of a stride-2 layer's samples).
///
/// # Safety
/// `fill` writes all `len` values (the depthwise entry points' contract; their path tests
/// start from NaNs and compare every value).
unsafe fn written(len: usize, fill: impl FnOnce(&mut [MaybeUninit<f32>])) -> Vec<f32> {
    let mut v = Vec::with_capacity(len);
    fill(&mut v.spare_capacity_mut()[..len]);
    // SAFETY: `fill` wrote all `len` values (the contract).
    unsafe { v.set_len(len) };
    v
}

/// Refuses a tensor whose values are not n·c·h·w (its fields are public): the depthwise
/// entry points size their outputs from the shape and must write all of them.
fn check_holds(x: &Tensor, what: &str) -> Result<()> {
    if !x.holds_its_shape() {
        return Err(NetsError::Shape(format!(
            "{what}: {} values for shape {:?}",
            x.data.len(),
            x.shape()
        )));
    }
    Ok(())
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
    check_holds(x, "depthwise input")?;
    check_holds(dy, "depthwise upstream gradient")?;
    let g = depthwise_geom(x, k, stride);
    if dy.shape() != [x.n, x.c, g.ho, g.wo] {
        return Err(NetsError::Shape(format!(
            "depthwise upstream gradient {:?}",
            dy.shape()
        )));
    }
    let kk = k * k;
    let mut per_plane = vec![0.0f32; x.n * x.c * kk];
    // SAFETY: the backward writes every value of dL/dx (its contract), whose n·c planes of
    // h×w are x's values (checked above).
    let dx = unsafe {
        written(x.data.len(), |dx| {
            depthwise::backward(&g, x.c, &x.data, w, &dy.data, dx, &mut per_plane)
        })
    };
    let dx = Tensor::from_vec(x.n, x.c, x.h, x.w, dx)?;
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

/// Most columns of a GEMM output per parallel task in [`gemm_col_blocks`], like
/// [`ROW_BLOCK`].
const COL_BLOCK: usize = 256;

/// NCHW planes (`n` images of `c` planes of `hw`) as a row-major C × (N·HW) matrix.
fn pack_planes(src: &[f32], n: usize, c: usize, hw: usize) -> Vec<f32> {
    let nhw = n * hw;
    let mut out = vec![0.0f32; c * nhw];
    out.par_chunks_mut(nhw)
        .enumerate()
        .with_min_len((PAR_MIN / nhw.max(1)).max(1))
        .for_each(|(ch, row)| {
            for (img, dst) in row.chunks_exact_mut(hw).enumerate() {
                dst.copy_from_slice(&src[(img * c + ch) * hw..][..hw]);
            }
        });
    out
}

/// Inverse of [`pack_planes`]: a row-major C × (N·HW) matrix back into NCHW `dst`.
fn unpack_planes(src: &[f32], dst: &mut [f32], n: usize, c: usize, hw: usize) {
    let nhw = n * hw;
    dst.par_chunks_mut(hw)
        .enumerate()
        .with_min_len((PAR_MIN / hw.max(1)).max(1))
        .for_each(|(i, plane)| {
            let (img, ch) = (i / c, i % c);
            plane.copy_from_slice(&src[ch * nhw + img * hw..][..hw]);
        });
}

/// dst (+)= a·b with the columns of `dst` (and `b`) split into blocks of at most [`COL_BLOCK`]: the
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

/// Most rows of a GEMM output per parallel task in [`gemm_row_blocks`]; the split depends on
/// the shape only, so that which kernel
/// call computes an output element does not depend on the thread count.
const ROW_BLOCK: usize = 64;

/// dst (+)= a·b with the rows of `dst` (and `a`) split into blocks of at most [`ROW_BLOCK`].
fn gemm_row_blocks(dst: MatMut<'_, f32>, accum: Accum, a: MatRef<'_, f32>, b: MatRef<'_, f32>) {
    gemm_blocks(dst, accum, a, b, ROW_BLOCK);
}

/// dst (+)= a·b with the rows of `dst` (and `a`) split into equal blocks of at most
/// `block` rows (multiples of 8), at least two where there are 16 rows or more so that both
/// cores work on the small GEMMs of the deep stages too; one sequential GEMM per block, the
/// blocks in parallel. The split depends on the shape only, not on the thread count.
fn gemm_blocks(
    dst: MatMut<'_, f32>,
    accum: Accum,
    a: MatRef<'_, f32>,
    b: MatRef<'_, f32>,
    block: usize,
) {
    let rows = dst.nrows();
    let count = rows.div_ceil(block).max(if rows >= 16 { 2 } else { 1 });
    let block = rows.div_ceil(count).next_multiple_of(8).max(1);
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

#[cfg(test)]
mod tests {
    use super::*;

    fn tensor(n: usize, c: usize, h: usize, w: usize, seed: usize) -> Tensor {
        let data = (0..n * c * h * w)
            .map(|i| (((i + seed) * 7919) % 2003) as f32 / 1001.0 - 1.0)
            .collect();
        Tensor::from_vec(n, c, h, w, data).unwrap()
    }

    /// The stem convolution, its input gradient and its weight gradient by their definitions
    /// (taps in (i, ky, kx) order per output; dL/dx in (o, ky, kx) order per input), in f32
    /// for y and dL/dx and f64 for dL/dw.
    #[allow(clippy::type_complexity)]
    fn direct(
        x: &Tensor,
        w: &[f32],
        cout: usize,
        k: usize,
        s: usize,
        dy: &Tensor,
    ) -> (Vec<f32>, Vec<f32>, Vec<f64>) {
        let (ho, wo) = (out_size(x.h, k, s), out_size(x.w, k, s));
        let p = (k / 2) as isize;
        let mut y = vec![0.0f32; x.n * cout * ho * wo];
        let mut dx = vec![0.0f32; x.data.len()];
        let mut dw = vec![0.0f64; w.len()];
        let at = |n: usize, i: usize, iy: isize, ix: isize| -> Option<usize> {
            (iy >= 0 && ix >= 0 && (iy as usize) < x.h && (ix as usize) < x.w)
                .then(|| ((n * x.c + i) * x.h + iy as usize) * x.w + ix as usize)
        };
        for n in 0..x.n {
            for o in 0..cout {
                for i in 0..x.c {
                    for ky in 0..k {
                        for kx in 0..k {
                            let wi = ((o * x.c + i) * k + ky) * k + kx;
                            for oy in 0..ho {
                                for ox in 0..wo {
                                    let iy = (oy * s + ky) as isize - p;
                                    let ix = (ox * s + kx) as isize - p;
                                    if let Some(j) = at(n, i, iy, ix) {
                                        let oi = ((n * cout + o) * ho + oy) * wo + ox;
                                        y[oi] += w[wi] * x.data[j];
                                        dx[j] += dy.data[oi] * w[wi];
                                        dw[wi] += dy.data[oi] as f64 * x.data[j] as f64;
                                    }
                                }
                            }
                        }
                    }
                }
            }
        }
        (y, dx, dw)
    }

    #[test]
    fn stem_convolution_matches_its_definition() {
        for (n, c, h, w, cout, k, s) in [
            (2, 1, 13, 22, 4, 3, 2),
            (1, 2, 9, 7, 3, 3, 1),
            (2, 1, 11, 17, 2, 5, 2),
            (1, 1, 10, 19, 2, 3, 3),
            (1, 1, 1, 1, 2, 3, 2),
        ] {
            let x = tensor(n, c, h, w, 1);
            let wt: Vec<f32> = tensor(1, 1, 1, cout * c * k * k, 2).data;
            let (ho, wo) = (out_size(h, k, s), out_size(w, k, s));
            let dy = tensor(n, cout, ho, wo, 3);
            let (y_ref, dx_ref, dw_ref) = direct(&x, &wt, cout, k, s, &dy);
            let y = conv2d_forward(&x, &wt, cout, k, s).unwrap();
            assert_eq!(y.data, y_ref, "forward, {:?}", (h, w, k, s));
            let mut dw = vec![0.0f32; wt.len()];
            let dx = conv2d_vjp(&x, &wt, cout, k, s, &dy, &mut dw).unwrap();
            assert_eq!(dx.data, dx_ref, "dL/dx, {:?}", (h, w, k, s));
            for (a, b) in dw.iter().zip(&dw_ref) {
                assert!(
                    (*a as f64 - b).abs() <= 1e-5 * (1.0 + b.abs()),
                    "dL/dw {a} vs {b}"
                );
            }
        }
    }

    /// A tensor whose values are not n·c·h·w (its fields are public) is refused by the
    /// depthwise entry points, which size their outputs from the shape and write all of them;
    /// the same tensors with their values in place go through.
    #[test]
    fn depthwise_refuses_a_tensor_that_does_not_hold_its_shape() {
        let (k, s) = (3, 2);
        let w = vec![0.1f32; 2 * k * k];
        let mut x = tensor(1, 2, 5, 6, 3);
        let dy = tensor(1, 2, out_size(5, k, s), out_size(6, k, s), 4);
        let mut dw = vec![0.0f32; w.len()];
        assert!(depthwise_forward(&x, &w, k, s).is_ok());
        assert!(depthwise_vjp(&x, &w, k, s, &dy, &mut dw).is_ok());
        x.data.push(1.0);
        assert!(depthwise_forward(&x, &w, k, s).is_err());
        assert!(depthwise_vjp(&x, &w, k, s, &dy, &mut dw).is_err());
        x.data.truncate(x.data.len() - 2);
        assert!(depthwise_forward(&x, &w, k, s).is_err());
        assert!(depthwise_vjp(&x, &w, k, s, &dy, &mut dw).is_err());
        let (x, mut short) = (tensor(1, 2, 5, 6, 3), dy.clone());
        short.data.pop();
        assert!(depthwise_vjp(&x, &w, k, s, &short, &mut dw).is_err());
    }
}

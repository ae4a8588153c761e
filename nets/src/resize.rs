//! Bilinear resampling to an arbitrary size (half-pixel centres, edge clamp) and its adjoint.

use crate::act::PAR_MIN;
use crate::tensor::Tensor;
use rayon::prelude::*;

/// Per output index: (lower source index, upper source index, weight of the upper one).
pub(crate) fn taps(n_in: usize, n_out: usize) -> Vec<(usize, usize, f32)> {
    let scale = n_in as f32 / n_out as f32;
    (0..n_out)
        .map(|o| {
            let s = ((o as f32 + 0.5) * scale - 0.5).max(0.0);
            let i0 = (s.floor() as usize).min(n_in - 1);
            let i1 = (i0 + 1).min(n_in - 1);
            (i0, i1, s - i0 as f32)
        })
        .collect()
}

/// Resizes every plane of `x` to (h, w) by bilinear interpolation.
pub fn bilinear_forward(x: &Tensor, h: usize, w: usize) -> Tensor {
    let mut y = Tensor::zeros(x.n, x.c, h, w);
    if x.plane() == 0 || h == 0 || w == 0 {
        return y;
    }
    let (ty, tx) = (taps(x.h, h), taps(x.w, w));
    let per_task = (PAR_MIN / (h * w)).max(1);
    x.data
        .par_chunks(x.plane())
        .zip(y.data.par_chunks_mut(h * w))
        .with_min_len(per_task)
        .for_each(|(p, out)| resize_plane(p, x.w, &ty, &tx, out, false));
    y
}

/// One plane `p` (rows of `wi`) resampled with taps `ty`, `tx` into `out` (|ty| × |tx|),
/// written or, with `add`, added.
#[inline]
pub(crate) fn resize_plane(
    p: &[f32],
    wi: usize,
    ty: &[(usize, usize, f32)],
    tx: &[(usize, usize, f32)],
    out: &mut [f32],
    add: bool,
) {
    let w = tx.len();
    for (oy, &(y0, y1, ly)) in ty.iter().enumerate() {
        let orow = &mut out[oy * w..][..w];
        let (r0, r1) = (&p[y0 * wi..][..wi], &p[y1 * wi..][..wi]);
        let blend = |&(x0, x1, lx): &(usize, usize, f32)| {
            let top = r0[x0] * (1.0 - lx) + r0[x1] * lx;
            let bot = r1[x0] * (1.0 - lx) + r1[x1] * lx;
            top * (1.0 - ly) + bot * ly
        };
        if add {
            orow.iter_mut().zip(tx).for_each(|(o, t)| *o += blend(t));
        } else {
            orow.iter_mut().zip(tx).for_each(|(o, t)| *o = blend(t));
        }
    }
}

/// VJP (adjoint) of [`bilinear_forward`] from input shape `like`.
pub fn bilinear_vjp(like: [usize; 4], dy: &Tensor) -> Tensor {
    let [n, c, hi, wi] = like;
    let mut dx = Tensor::zeros(n, c, hi, wi);
    if hi * wi == 0 || dy.plane() == 0 {
        return dx;
    }
    let (ty, tx) = (taps(hi, dy.h), taps(wi, dy.w));
    let per_task = (PAR_MIN / dy.plane()).max(1);
    dy.data
        .par_chunks(dy.plane())
        .zip(dx.data.par_chunks_mut(hi * wi))
        .with_min_len(per_task)
        .for_each(|(g, p)| {
            for (oy, &(y0, y1, ly)) in ty.iter().enumerate() {
                for (ox, &(x0, x1, lx)) in tx.iter().enumerate() {
                    let v = g[oy * dy.w + ox];
                    p[y0 * wi + x0] += v * (1.0 - ly) * (1.0 - lx);
                    p[y0 * wi + x1] += v * (1.0 - ly) * lx;
                    p[y1 * wi + x0] += v * ly * (1.0 - lx);
                    p[y1 * wi + x1] += v * ly * lx;
                }
            }
        });
    dx
}

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
        .for_each_init(Vec::new, |rows, (p, out)| {
            resize_plane(p, x.w, &ty, &tx, out, rows)
        });
    y
}

/// One plane `p` (rows of `wi`) resampled with taps `ty`, `tx` into `out` (|ty| × |tx|).
///
/// Each source row is interpolated along x once, into `rows` (two rows, reused while the
/// output rows read the same source rows), then each output row is one blend of two of them:
/// the same expression, top·(1 − ly) + bottom·ly with top and bottom the x-blends, as a per-pixel
/// four-tap loop, so the same bits. Where the planes shrink to half their height or less
/// (output rows rarely share source rows), that four-tap loop itself: it stores nothing in
/// between.
#[inline]
pub(crate) fn resize_plane(
    p: &[f32],
    wi: usize,
    ty: &[(usize, usize, f32)],
    tx: &[(usize, usize, f32)],
    out: &mut [f32],
    rows: &mut Vec<f32>,
) {
    let w = tx.len();
    if ty.len() * 2 <= p.len() / wi.max(1) {
        for (orow, &(y0, y1, ly)) in out.chunks_exact_mut(w).zip(ty) {
            let (r0, r1) = (&p[y0 * wi..][..wi], &p[y1 * wi..][..wi]);
            for (o, &(x0, x1, lx)) in orow.iter_mut().zip(tx) {
                let top = r0[x0] * (1.0 - lx) + r0[x1] * lx;
                let bot = r1[x0] * (1.0 - lx) + r1[x1] * lx;
                *o = top * (1.0 - ly) + bot * ly;
            }
        }
        return;
    }
    rows.resize(2 * w, 0.0);
    let (mut lo, mut hi) = rows.split_at_mut(w);
    let blend_row = |dst: &mut [f32], y: usize| {
        let r = &p[y * wi..][..wi];
        for (d, &(x0, x1, lx)) in dst.iter_mut().zip(tx) {
            *d = r[x0] * (1.0 - lx) + r[x1] * lx;
        }
    };
    let (mut have_lo, mut have_hi) = (usize::MAX, usize::MAX);
    for (orow, &(y0, y1, ly)) in out.chunks_exact_mut(w).zip(ty) {
        if y0 != have_lo {
            if y0 == have_hi {
                std::mem::swap(&mut lo, &mut hi);
                have_hi = usize::MAX;
            } else {
                blend_row(lo, y0);
            }
            have_lo = y0;
        }
        if y1 != have_hi {
            blend_row(hi, y1);
            have_hi = y1;
        }
        for ((o, &t), &b) in orow.iter_mut().zip(lo.iter()).zip(hi.iter()) {
            *o = t * (1.0 - ly) + b * ly;
        }
    }
}

/// VJP (adjoint) of [`bilinear_forward`] from input shape `like`.
///
/// Where the forward pass shrank the planes, separable: each row of dL/dy is first pulled
/// back along x (a short sum per input column), then the rows are combined along y, instead of
/// scattering every output pixel into four input pixels (read-modify-write chains through
/// memory, several outputs landing on one input). Where it enlarged them, that scatter.
pub fn bilinear_vjp(like: [usize; 4], dy: &Tensor) -> Tensor {
    let [n, c, hi, wi] = like;
    let mut dx = Tensor::zeros(n, c, hi, wi);
    if hi * wi == 0 || dy.plane() == 0 {
        return dx;
    }
    if dy.plane() <= hi * wi {
        scatter_vjp(dy, &mut dx);
        return dx;
    }
    let (ay, ax) = (Adjoint::of(hi, dy.h), Adjoint::of(wi, dy.w));
    let per_task = (PAR_MIN / dy.plane()).max(1);
    dy.data
        .par_chunks(dy.plane())
        .zip(dx.data.par_chunks_mut(hi * wi))
        .with_min_len(per_task)
        .for_each_init(Vec::new, |t, (g, p)| {
            t.resize(dy.h * wi, 0.0);
            for (grow, trow) in g.chunks_exact(dy.w).zip(t.chunks_exact_mut(wi)) {
                for (j, tv) in trow.iter_mut().enumerate() {
                    *tv = ax.taps(j).iter().map(|&(o, wt)| grow[o] * wt).sum();
                }
            }
            for (iy, prow) in p.chunks_exact_mut(wi).enumerate() {
                for &(oy, wt) in ay.taps(iy) {
                    let trow = &t[oy * wi..][..wi];
                    prow.iter_mut().zip(trow).for_each(|(d, &v)| *d += wt * v);
                }
            }
        });
    dx
}

/// [`bilinear_vjp`] by scattering each pixel of `dy` into the four pixels of `dx` it read.
fn scatter_vjp(dy: &Tensor, dx: &mut Tensor) {
    let (hi, wi) = (dx.h, dx.w);
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
}

/// The taps of [`taps`] grouped by input index: for input i, every (output, weight) that
/// reads it, outputs ascending (and an output's lower tap before its upper one).
struct Adjoint {
    start: Vec<usize>,
    entries: Vec<(usize, f32)>,
}

impl Adjoint {
    fn of(n_in: usize, n_out: usize) -> Self {
        let fwd = taps(n_in, n_out);
        let mut start = vec![0usize; n_in + 1];
        for &(i0, i1, _) in &fwd {
            start[i0 + 1] += 1;
            start[i1 + 1] += 1;
        }
        for i in 0..n_in {
            start[i + 1] += start[i];
        }
        let mut next = start.clone();
        let mut entries = vec![(0usize, 0.0f32); 2 * n_out];
        for (o, &(i0, i1, l)) in fwd.iter().enumerate() {
            for (i, wt) in [(i0, 1.0 - l), (i1, l)] {
                entries[next[i]] = (o, wt);
                next[i] += 1;
            }
        }
        Self { start, entries }
    }

    fn taps(&self, i: usize) -> &[(usize, f32)] {
        &self.entries[self.start[i]..self.start[i + 1]]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two h × w planes of values in [−1, 1] from a multiplicative hash (factor, modulus).
    fn planes(h: usize, w: usize, factor: usize, modulus: usize) -> Tensor {
        let half = (modulus / 2) as f32;
        let data = (0..2 * h * w)
            .map(|i| ((i * factor) % modulus) as f32 / half - 1.0)
            .collect();
        Tensor::from_vec(2, 1, h, w, data).unwrap()
    }

    #[test]
    fn resize_is_the_four_tap_blend_bit_for_bit_and_its_adjoint() {
        for (h, w, oh, ow) in [
            (30, 48, 200, 320),
            (200, 320, 30, 48),
            (7, 5, 7, 11),
            (1, 1, 3, 2),
        ] {
            let x = planes(h, w, 7919, 1009);
            let y = bilinear_forward(&x, oh, ow);
            let (ty, tx) = (taps(h, oh), taps(w, ow));
            for n in 0..2 {
                let p = &x.data[n * h * w..][..h * w];
                for (oy, &(y0, y1, ly)) in ty.iter().enumerate() {
                    for (ox, &(x0, x1, lx)) in tx.iter().enumerate() {
                        let top = p[y0 * w + x0] * (1.0 - lx) + p[y0 * w + x1] * lx;
                        let bot = p[y1 * w + x0] * (1.0 - lx) + p[y1 * w + x1] * lx;
                        let v = top * (1.0 - ly) + bot * ly;
                        assert_eq!(y.data[(n * oh + oy) * ow + ox].to_bits(), v.to_bits());
                    }
                }
            }
            // ⟨resize(x), g⟩ = ⟨x, resizeᵀ(g)⟩ in f64.
            let g = planes(oh, ow, 104_729, 997);
            let dx = bilinear_vjp(x.shape(), &g);
            let lhs: f64 = y
                .data
                .iter()
                .zip(&g.data)
                .map(|(a, b)| *a as f64 * *b as f64)
                .sum();
            let rhs: f64 = x
                .data
                .iter()
                .zip(&dx.data)
                .map(|(a, b)| *a as f64 * *b as f64)
                .sum();
            assert!(
                (lhs - rhs).abs() <= 1e-5 * lhs.abs().max(1.0),
                "{lhs} vs {rhs}"
            );
        }
    }
}

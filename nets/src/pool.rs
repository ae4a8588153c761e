//! Global average pooling (N, C, H, W) → (N, C, 1, 1), and first moments (N, C, H, W) →
//! (N, 2C, 1, 1), which keep where in the plane each channel responds.

use crate::tensor::Tensor;

/// Mean of each channel plane.
pub fn gap_forward(x: &Tensor) -> Tensor {
    let hw = x.plane().max(1) as f32;
    let data = x
        .data
        .chunks(x.plane().max(1))
        .map(|p| p.iter().sum::<f32>() / hw)
        .collect();
    Tensor {
        n: x.n,
        c: x.c,
        h: 1,
        w: 1,
        data,
    }
}

/// VJP of [`gap_forward`]: spreads dL/dy/(H·W) over each plane of shape `like`.
pub fn gap_vjp(like: [usize; 4], dy: &Tensor) -> Tensor {
    let [n, c, h, w] = like;
    let hw = h * w;
    let mut dx = Tensor::zeros(n, c, h, w);
    for (p, &g) in dx.data.chunks_mut(hw.max(1)).zip(&dy.data) {
        p.iter_mut().for_each(|v| *v = g / hw as f32);
    }
    dx
}

/// Coordinate of pixel centre `i` of `n` on (−1, 1): (2i + 1)/n − 1.
#[inline]
pub fn centred_coordinate(i: usize, n: usize) -> f32 {
    (2 * i + 1) as f32 / n as f32 - 1.0
}

/// First moments of each channel plane along the columns (x̂) and rows (ŷ), x̂, ŷ ∈ (−1, 1)
/// at pixel centres ([`centred_coordinate`]): per sample the C means of x̂·a, then the C means
/// of ŷ·a. A global mean is blind to where features sit; a moment moves by the channel's mean
/// times the shift when the image translates, which is what the calibration head must read
/// (slippage moves the face across the frame).
pub fn moments_forward(x: &Tensor) -> Tensor {
    let (c, h, w) = (x.c, x.h, x.w);
    let hw = (h * w).max(1);
    let inv = 1.0 / hw as f32;
    let mut data = vec![0.0f32; x.n * 2 * c];
    for (b, out) in data.chunks_exact_mut(2 * c).enumerate() {
        for ch in 0..c {
            let p = &x.data[(b * c + ch) * hw..][..h * w];
            let (mut mx, mut my) = (0.0f32, 0.0f32);
            for (i, row) in p.chunks_exact(w.max(1)).enumerate() {
                let mut r = 0.0f32;
                for (j, &v) in row.iter().enumerate() {
                    r += v;
                    mx += centred_coordinate(j, w) * v;
                }
                my += centred_coordinate(i, h) * r;
            }
            out[ch] = mx * inv;
            out[c + ch] = my * inv;
        }
    }
    Tensor {
        n: x.n,
        c: 2 * c,
        h: 1,
        w: 1,
        data,
    }
}

/// VJP of [`moments_forward`] for an input of shape `like`: dL/dx(i, j) = (x̂_j·g_x +
/// ŷ_i·g_y)/(H·W) for the channel's two upstream gradients.
pub fn moments_vjp(like: [usize; 4], dy: &Tensor) -> Tensor {
    let [n, c, h, w] = like;
    let hw = (h * w).max(1);
    let inv = 1.0 / hw as f32;
    let mut dx = Tensor::zeros(n, c, h, w);
    for b in 0..n {
        let g = &dy.data[b * 2 * c..][..2 * c];
        for ch in 0..c {
            let (gx, gy) = (g[ch] * inv, g[c + ch] * inv);
            let p = &mut dx.data[(b * c + ch) * hw..][..h * w];
            for (i, row) in p.chunks_exact_mut(w.max(1)).enumerate() {
                let base = centred_coordinate(i, h) * gy;
                for (j, v) in row.iter_mut().enumerate() {
                    *v = base + centred_coordinate(j, w) * gx;
                }
            }
        }
    }
    dx
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn random(n: usize, c: usize, h: usize, w: usize, seed: u64) -> Tensor {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        Tensor {
            n,
            c,
            h,
            w,
            data: (0..n * c * h * w)
                .map(|_| rng.random_range(-1.0f32..1.0))
                .collect(),
        }
    }

    #[test]
    fn moments_move_with_a_translation_and_the_mean_does_not() {
        // A single bright pixel: its moments are its centred coordinates over H·W.
        let (h, w) = (5, 8);
        let hw = (h * w) as f32;
        for (i, j) in [(0, 0), (2, 3), (4, 7)] {
            let mut x = Tensor::zeros(1, 1, h, w);
            x.data[i * w + j] = 1.0;
            let y = moments_forward(&x);
            assert_eq!(gap_forward(&x).data[0], 1.0 / hw);
            assert!((y.data[0] - ((2 * j + 1) as f32 / w as f32 - 1.0) / hw).abs() < 1e-7);
            assert!((y.data[1] - ((2 * i + 1) as f32 / h as f32 - 1.0) / hw).abs() < 1e-7);
        }
        // A uniform plane is centred: zero moments.
        let x = Tensor {
            data: vec![2.0; 2 * h * w],
            ..Tensor::zeros(1, 2, h, w)
        };
        let y = moments_forward(&x);
        assert!(y.data.iter().all(|v| v.abs() < 1e-6), "{:?}", y.data);
        // A blob moved one column right: its x moment grows by its mass times 2/W over H·W.
        let mut a = Tensor::zeros(1, 1, h, w);
        let mut b = Tensor::zeros(1, 1, h, w);
        for (i, j, v) in [(1, 2, 1.0), (2, 2, 0.5), (2, 3, 2.0)] {
            a.data[i * w + j] = v;
            b.data[i * w + j + 1] = v;
        }
        let d = moments_forward(&b).data[0] - moments_forward(&a).data[0];
        assert!((d - 3.5 * 2.0 / w as f32 / hw).abs() < 1e-6, "{d}");
        assert_eq!(moments_forward(&b).data[1], moments_forward(&a).data[1]);
    }

    #[test]
    fn the_vjp_is_the_adjoint_of_the_forward() {
        // The forward is linear, so <dy, F x> = <F* dy, x> exactly up to rounding, for any x.
        for (n, c, h, w) in [(2, 3, 4, 5), (1, 1, 1, 1), (3, 2, 7, 2)] {
            let x = random(n, c, h, w, 1);
            let dy = random(n, 2 * c, 1, 1, 2);
            let y = moments_forward(&x);
            let dx = moments_vjp([n, c, h, w], &dy);
            let lhs: f64 = y
                .data
                .iter()
                .zip(&dy.data)
                .map(|(a, b)| (a * b) as f64)
                .sum();
            let rhs: f64 = x
                .data
                .iter()
                .zip(&dx.data)
                .map(|(a, b)| (a * b) as f64)
                .sum();
            assert!(
                (lhs - rhs).abs() < 1e-5 * (1.0 + lhs.abs()),
                "{lhs} vs {rhs}"
            );
        }
    }
}

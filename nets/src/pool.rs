//! Global average pooling (N, C, H, W) → (N, C, 1, 1).

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

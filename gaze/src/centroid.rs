//! Centre of mass of a soft pupil mask (S9) and its vector–Jacobian product.
//!
//! The mask is a `faer::MatRef<f32>` with rows = image v (down) and columns = image u (right);
//! pixel (row i, col j) has its centre at (u, v) = ((j + 0.5)·k, (i + 0.5)·k) in camera pixels,
//! where k = camera width / mask width (masks may be an exact downscale of the image).

use crate::error::GazeError;
use faer::{Mat, MatRef};

/// Below this mask sum there is no pupil (a soft mask of a real pupil sums to ≫ 1).
pub const EMPTY_MASK_SUM: f64 = 1e-12;

/// Centroid of a mask in camera pixel coordinates, with the mask sum.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Centroid {
    /// (u, v) in camera pixels.
    pub px: [f64; 2],
    /// Σ M (mask units).
    pub mass: f64,
    /// Camera pixels per mask pixel.
    pub scale: f64,
}

/// Camera pixels per mask pixel for a `mask_w`×`mask_h` mask on a `cam_w`×`cam_h` image.
pub fn mask_scale(
    mask_w: usize,
    mask_h: usize,
    cam_w: usize,
    cam_h: usize,
) -> Result<f64, GazeError> {
    let shape_err = GazeError::MaskShape {
        mask_w,
        mask_h,
        cam_w,
        cam_h,
    };
    if mask_w == 0 || mask_h == 0 {
        return Err(shape_err);
    }
    let kx = cam_w as f64 / mask_w as f64;
    let ky = cam_h as f64 / mask_h as f64;
    if (kx - ky).abs() > 1e-9 * kx || kx < 1.0 {
        return Err(shape_err);
    }
    Ok(kx)
}

/// S9: u_p = Σ u M / Σ M, v_p = Σ v M / Σ M, at camera-pixel `scale` per mask pixel.
pub fn centroid(mask: MatRef<'_, f32>, scale: f64) -> Result<Centroid, GazeError> {
    let (h, w) = (mask.nrows(), mask.ncols());
    let (mut m0, mut mu, mut mv) = (0.0f64, 0.0f64, 0.0f64);
    for j in 0..w {
        let u = j as f64 + 0.5;
        let mut col_sum = 0.0f64;
        let mut col_v = 0.0f64;
        for i in 0..h {
            let m = mask[(i, j)] as f64;
            if !(m.is_finite() && m >= 0.0) {
                return Err(GazeError::InvalidMask {
                    row: i,
                    col: j,
                    value: m,
                });
            }
            col_sum += m;
            col_v += (i as f64 + 0.5) * m;
        }
        m0 += col_sum;
        mu += u * col_sum;
        mv += col_v;
    }
    if m0.is_nan() || m0 <= EMPTY_MASK_SUM {
        return Err(GazeError::EmptyMask { sum: m0 });
    }
    Ok(Centroid {
        px: [mu / m0 * scale, mv / m0 * scale],
        mass: m0,
        scale,
    })
}

/// VJP of S9: given ∂L/∂(u_p, v_p) returns ∂L/∂M with ∂u_p/∂M_ij = k(u_j − u_p/k)/ΣM.
pub fn centroid_vjp(c: &Centroid, h: usize, w: usize, grad_px: [f64; 2]) -> Mat<f32> {
    let (u0, v0) = (c.px[0] / c.scale, c.px[1] / c.scale);
    let gu = grad_px[0] * c.scale / c.mass;
    let gv = grad_px[1] * c.scale / c.mass;
    Mat::from_fn(h, w, |i, j| {
        (gu * (j as f64 + 0.5 - u0) + gv * (i as f64 + 0.5 - v0)) as f32
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_pixel_mask_is_its_centre() {
        let mut m = Mat::<f32>::zeros(5, 7);
        m[(3, 2)] = 0.25;
        let c = centroid(m.as_ref(), 2.0).unwrap();
        assert_eq!(c.px, [5.0, 7.0]);
    }

    #[test]
    fn rejects_empty_and_negative() {
        let m = Mat::<f32>::zeros(4, 4);
        assert!(matches!(
            centroid(m.as_ref(), 1.0),
            Err(GazeError::EmptyMask { .. })
        ));
        let mut m = Mat::<f32>::zeros(4, 4);
        m[(1, 1)] = -1.0;
        assert!(matches!(
            centroid(m.as_ref(), 1.0),
            Err(GazeError::InvalidMask { row: 1, col: 1, .. })
        ));
        m[(1, 1)] = f32::NAN;
        assert!(centroid(m.as_ref(), 1.0).is_err());
    }

    #[test]
    fn vjp_matches_finite_differences() {
        let (h, w) = (6, 9);
        let m = Mat::<f32>::from_fn(h, w, |i, j| ((i * 7 + j * 3) % 5) as f32 * 0.2 + 0.1);
        let c = centroid(m.as_ref(), 1.5).unwrap();
        let g = [0.7, -1.3];
        let grad = centroid_vjp(&c, h, w, g);
        let eps = 1e-3f32;
        for (i, j) in [(0, 0), (2, 5), (5, 8), (3, 1)] {
            let mut mp = m.clone();
            mp[(i, j)] += eps;
            let mut mm = m.clone();
            mm[(i, j)] -= eps;
            let cp = centroid(mp.as_ref(), 1.5).unwrap();
            let cm = centroid(mm.as_ref(), 1.5).unwrap();
            let fd =
                (g[0] * (cp.px[0] - cm.px[0]) + g[1] * (cp.px[1] - cm.px[1])) / (2.0 * eps as f64);
            let an = grad[(i, j)] as f64;
            assert!(
                (fd - an).abs() < 1e-4 * (1.0 + an.abs()),
                "{i},{j}: {fd} vs {an}"
            );
        }
    }
}

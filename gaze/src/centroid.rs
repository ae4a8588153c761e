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

/// The mask restricted to its dominant blob: the 8-connected component of pixels ≥ `threshold`
/// with the largest mass Σ M (values kept), everything else zeroed. A network's soft mask can
/// carry small false positives (a dark lid fold, a lash shadow) that would drag S9's centroid
/// off the pupil; a pupil is one blob. Returns the mask unchanged when no pixel reaches the
/// threshold or when any pixel is NaN (the solver then reports an empty, faint or non-finite
/// pupil as it would have).
pub fn dominant_blob(mask: MatRef<'_, f32>, threshold: f32) -> Mat<f32> {
    let (h, w) = (mask.nrows(), mask.ncols());
    // A NaN anywhere must reach the centroid, which names it; zeroing it here would hide it.
    if (0..w).any(|j| (0..h).any(|i| mask[(i, j)].is_nan())) {
        return mask.to_owned();
    }
    let mut label = vec![u32::MAX; h * w];
    let mut best = (0.0f64, u32::MAX);
    let mut stack = Vec::new();
    let mut next = 0u32;
    for i0 in 0..h {
        for j0 in 0..w {
            if label[i0 * w + j0] != u32::MAX || mask[(i0, j0)] < threshold {
                continue;
            }
            let id = next;
            next += 1;
            let mut mass = 0.0f64;
            label[i0 * w + j0] = id;
            stack.push((i0, j0));
            while let Some((i, j)) = stack.pop() {
                mass += mask[(i, j)] as f64;
                for di in -1isize..=1 {
                    for dj in -1isize..=1 {
                        let (a, b) = (i as isize + di, j as isize + dj);
                        if a < 0 || b < 0 || a >= h as isize || b >= w as isize {
                            continue;
                        }
                        let (a, b) = (a as usize, b as usize);
                        if label[a * w + b] == u32::MAX && mask[(a, b)] >= threshold {
                            label[a * w + b] = id;
                            stack.push((a, b));
                        }
                    }
                }
            }
            if mass > best.0 {
                best = (mass, id);
            }
        }
    }
    if best.1 == u32::MAX {
        return mask.to_owned();
    }
    Mat::from_fn(h, w, |i, j| {
        if label[i * w + j] == best.1 {
            mask[(i, j)]
        } else {
            0.0
        }
    })
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

    /// A disc plus a smaller far blob: the blob is removed, the disc's centroid recovered
    /// exactly; a single disc is left untouched; an all-faint mask, or one
    /// holding a NaN, comes back unchanged (and the NaN one is refused by the centroid).
    #[test]
    fn dominant_blob_drops_false_positives() {
        let disc = |ci: f64, cj: f64, r: f64| {
            move |i: usize, j: usize| {
                if (i as f64 - ci).hypot(j as f64 - cj) <= r {
                    1.0f32
                } else {
                    0.0
                }
            }
        };
        let (a, b) = (disc(20.0, 30.0, 6.0), disc(5.0, 5.0, 3.0));
        let m = Mat::<f32>::from_fn(40, 60, |i, j| a(i, j).max(b(i, j)));
        let only = Mat::<f32>::from_fn(40, 60, a);
        let d = dominant_blob(m.as_ref(), 0.5);
        assert_eq!(d, only);
        assert_eq!(dominant_blob(only.as_ref(), 0.5), only);
        let c = centroid(d.as_ref(), 1.0).unwrap();
        assert!((c.px[0] - 30.5).abs() < 1e-9 && (c.px[1] - 20.5).abs() < 1e-9);
        let faint = Mat::<f32>::from_fn(8, 8, |_, _| 0.1);
        assert_eq!(dominant_blob(faint.as_ref(), 0.5), faint);
        let mut nan = m.clone();
        nan[(39, 59)] = f32::NAN;
        let kept = dominant_blob(nan.as_ref(), 0.5);
        assert!(kept[(39, 59)].is_nan() && kept[(5, 5)] == 1.0);
        assert!(centroid(kept.as_ref(), 1.0).is_err());
    }

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

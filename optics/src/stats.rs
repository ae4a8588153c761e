//! Summary statistics of a PSF plane (energy, peak, centroid, RMS radius, lobe orientation).

use faer::Mat;

/// Moments of a non-negative image; pixel coordinates with (0, 0) at the top-left pixel's
/// centre, x along columns, y along rows.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PlaneStats {
    /// Sum of all pixels.
    pub energy: f64,
    /// Largest pixel.
    pub peak: f64,
    /// Intensity-weighted centroid (x, y) in pixels.
    pub centroid_px: [f64; 2],
    /// RMS radius about the centroid (pixels).
    pub rms_radius_px: f64,
    /// Orientation (rad, in (−π/2, π/2]) of the principal axis of the second moments.
    pub orientation_rad: f64,
}

/// Statistics of `m` (all zero when the plane carries no energy).
pub fn plane_stats(m: &Mat<f32>) -> PlaneStats {
    let (mut e, mut peak, mut sx, mut sy) = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
    for j in 0..m.ncols() {
        for i in 0..m.nrows() {
            let v = m[(i, j)] as f64;
            e += v;
            peak = peak.max(v);
            sx += v * j as f64;
            sy += v * i as f64;
        }
    }
    if e <= 0.0 || !e.is_finite() {
        return PlaneStats {
            energy: e,
            peak,
            centroid_px: [0.0; 2],
            rms_radius_px: 0.0,
            orientation_rad: 0.0,
        };
    }
    let (cx, cy) = (sx / e, sy / e);
    let (mut mxx, mut myy, mut mxy) = (0.0, 0.0, 0.0);
    for j in 0..m.ncols() {
        for i in 0..m.nrows() {
            let v = m[(i, j)] as f64;
            let (dx, dy) = (j as f64 - cx, i as f64 - cy);
            mxx += v * dx * dx;
            myy += v * dy * dy;
            mxy += v * dx * dy;
        }
    }
    PlaneStats {
        energy: e,
        peak,
        centroid_px: [cx, cy],
        rms_radius_px: ((mxx + myy) / e).sqrt(),
        orientation_rad: 0.5 * (2.0 * mxy).atan2(mxx - myy),
    }
}

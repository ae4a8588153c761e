//! One geometry from the rig: the native grid the renderer, the PSFs and S1 share, and, for an
//! effective pitch p̂, the sensor's output grid, the downsampled pupil mask, the pupil-centre
//! target and the camera intrinsics the gaze solver uses, all from one function of
//! (native grid, p̂) so they cannot disagree.

use crate::error::{Result, param, positive};
use faer::Mat;
use nanoeye_gaze::{Camera, Pose, Vec3, project};
use nanoeye_sensor::BoxIntegrator;

/// The native grid: the dataset's camera, whose pixel pitch is the base pitch p_base.
#[derive(Clone, Debug)]
pub struct NativeGrid {
    /// Camera at the native pitch (intrinsics in native pixels).
    pub camera: Camera,
}

/// Everything defined on the effective-pitch grid.
#[derive(Clone, Debug)]
pub struct PitchGrid {
    /// Effective pitch p̂ (m).
    pub p_hat_m: f64,
    /// The camera at p̂ (what the gaze solver must use).
    pub camera: Camera,
    /// Area average from the native grid to the p̂ grid (κ = 1: values stay fractions).
    averager: BoxIntegrator,
}

impl NativeGrid {
    /// The native grid of `camera`.
    pub fn new(camera: Camera) -> Result<NativeGrid> {
        camera.validate()?;
        Ok(NativeGrid { camera })
    }

    /// Native pitch p_base (m).
    pub fn pitch_m(&self) -> f64 {
        self.camera.pixel_pitch_m
    }

    /// Native (rows, cols).
    pub fn shape(&self) -> (usize, usize) {
        (self.camera.height_px, self.camera.width_px)
    }

    /// The p̂ grid. p̂ must lie between the native pitch and the sensor size.
    pub fn at(&self, p_hat_m: f64) -> Result<PitchGrid> {
        positive("pitch", p_hat_m)?;
        let base = self.pitch_m();
        if p_hat_m < base * (1.0 - 1e-12) {
            return Err(param(
                "pitch",
                format!(
                    "{:.4} µm is finer than the native grid's {:.4} µm",
                    p_hat_m * 1e6,
                    base * 1e6
                ),
            ));
        }
        let (h, w) = self.shape();
        let camera = self.camera.with_pitch(p_hat_m)?;
        let averager = BoxIntegrator::new(h, w, base, p_hat_m, p_hat_m)?;
        let out = averager.out_shape();
        if out != (camera.height_px, camera.width_px) {
            // Both count whole pixels as ⌊n·p_base/p̂⌋; a disagreement is a bug, not input.
            return Err(param(
                "pitch",
                format!(
                    "sensor grid {out:?} and camera {}×{} disagree at {p_hat_m} m",
                    camera.height_px, camera.width_px
                ),
            ));
        }
        Ok(PitchGrid {
            p_hat_m,
            camera,
            averager,
        })
    }
}

impl PitchGrid {
    /// Output (rows, cols).
    pub fn shape(&self) -> (usize, usize) {
        (self.camera.height_px, self.camera.width_px)
    }

    /// A native-grid mask (coverage fractions) averaged over each effective pixel.
    pub fn downsample_mask(&self, native: &Mat<f32>) -> Result<Mat<f32>> {
        Ok(self.averager.forward(native)?)
    }

    /// ∂L/∂p̂ (per metre) through [`Self::downsample_mask`] of `native`, for ∂L/∂(averaged
    /// mask) `grad`, with `averaged` that mask (both on the p̂ grid): the target moves with p̂
    /// too. The average is the box sum times (p_base/p̂)², so beside the box's own derivative
    /// it carries −2·⟨grad, averaged⟩/p̂.
    pub fn mask_pitch_vjp(
        &self,
        native: &Mat<f32>,
        grad: &Mat<f32>,
        averaged: &Mat<f32>,
    ) -> Result<f64> {
        let boxed = self.averager.pitch_vjp(native, grad)?;
        if averaged.shape() != grad.shape() {
            return Err(param(
                "averaged",
                format!(
                    "shape {:?}, the p̂ grid's is {:?}",
                    averaged.shape(),
                    grad.shape()
                ),
            ));
        }
        let mut dot = 0.0;
        for j in 0..grad.ncols() {
            for i in 0..grad.nrows() {
                dot += grad[(i, j)] as f64 * averaged[(i, j)] as f64;
            }
        }
        Ok(boxed - 2.0 * dot / self.p_hat_m)
    }

    /// Pinhole projection of world point `p_m` seen from `pose`, in p̂ pixels.
    pub fn project(&self, pose: &Pose, p_m: Vec3) -> Result<[f64; 2]> {
        Ok(project(&self.camera, pose, p_m)?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// ∂⟨G, mask(p̂)⟩/∂p̂ against central differences, for a disc's coverage on a grid where the
    /// box edges fall between samples (the average's (p_base/p̂)² factor included).
    #[test]
    fn mask_pitch_vjp_matches_central_differences() {
        let camera = Camera::look_at(2e-3, 3e-6, 61, 47, [0.0, 0.0, 0.0], [0.0, 0.0, 1.0]).unwrap();
        let native = NativeGrid::new(camera).unwrap();
        let mask = Mat::from_fn(47, 61, |r, c| {
            let (y, x) = (r as f64 - 20.3, c as f64 - 33.7);
            if x * x + y * y < 15.0 * 15.0 {
                1.0
            } else {
                0.0
            }
        });
        let p = 7.1e-6;
        let g = native.at(p).unwrap();
        let (h, w) = g.shape();
        let grad = Mat::from_fn(h, w, |i, j| ((i * 5 + j * 3) % 7) as f32 * 0.3 - 0.8);
        let avg = g.downsample_mask(&mask).unwrap();
        let an = g.mask_pitch_vjp(&mask, &grad, &avg).unwrap();
        let loss = |p: f64| -> f64 {
            let m = native.at(p).unwrap().downsample_mask(&mask).unwrap();
            assert_eq!(m.shape(), (h, w));
            (0..w)
                .flat_map(|j| (0..h).map(move |i| (i, j)))
                .map(|(i, j)| grad[(i, j)] as f64 * m[(i, j)] as f64)
                .sum()
        };
        let e = 1e-10;
        let fd = (loss(p + e) - loss(p - e)) / (2.0 * e);
        assert!((fd - an).abs() < 1e-3 * fd.abs(), "FD {fd:e} vs VJP {an:e}");
        // Without the (p_base/p̂)² term the box's derivative alone is far off.
        let boxed = g.averager.pitch_vjp(&mask, &grad).unwrap();
        assert!((fd - boxed).abs() > 0.05 * fd.abs(), "{fd:e} vs {boxed:e}");
        assert!(
            g.mask_pitch_vjp(&mask, &grad, &Mat::zeros(h + 1, w))
                .is_err()
        );
    }
}

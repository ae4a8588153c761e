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

    /// Pinhole projection of world point `p_m` seen from `pose`, in p̂ pixels.
    pub fn project(&self, pose: &Pose, p_m: Vec3) -> Result<[f64; 2]> {
        Ok(project(&self.camera, pose, p_m)?)
    }
}

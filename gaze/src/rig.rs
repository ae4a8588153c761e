//! The eye–camera rig: eye spheres, pinhole camera intrinsics and nominal pose, and the
//! slippage model. Serialized as JSON (schema in docs/formats.md).

use crate::error::GazeError;
use crate::geom::{self, Mat3, Vec3};
use crate::refract::Cornea;
use serde::{Deserialize, Serialize};

/// Default solver sphere radius (m): the seed's 12 mm eyeball (Sec. A.4).
pub const DEFAULT_EYE_RADIUS_M: f64 = 12e-3;
/// Default radius (m) of the sphere the pupil centre moves on: sqrt(12² − 6²) mm ≈ 10.39 mm
/// (oracles.md, eye and rig).
pub const DEFAULT_PUPIL_SPHERE_RADIUS_M: f64 = 10.392_304_845_413_264e-3;
/// Camera offset (m) from the pupil centre at primary gaze, in the world frame (DESIGN.md:
/// the seed's (−10, 10, −14) mm read as 10 mm lateral, 10 mm in front, 14 mm below).
pub const CAMERA_OFFSET_M: Vec3 = [-10e-3, -14e-3, 10e-3];

/// Plausible range (m) of the eye and pupil sphere radii: a human eye is ≈12 mm in radius;
/// anything outside 1 mm…100 mm is a unit mistake, not an eye.
pub const EYE_RADIUS_RANGE_M: (f64, f64) = (1e-3, 0.1);
/// Plausible range (m) of the camera's lens-to-sensor distance.
pub const FOCAL_LENGTH_RANGE_M: (f64, f64) = (1e-5, 1.0);
/// Plausible range (m) of the effective pixel pitch.
pub const PIXEL_PITCH_RANGE_M: (f64, f64) = (1e-7, 1e-3);
/// Largest distance (m) of the camera from the world origin (the eye): a glasses camera sits a
/// few centimetres away; beyond a metre is a unit mistake (1e308 m printed as inf).
pub const MAX_CAMERA_DISTANCE_M: f64 = 1.0;
/// Largest image side (px) a rig may declare.
pub const MAX_IMAGE_SIDE_PX: usize = 1 << 16;
/// Largest sensor side (m), pixels times pitch: a glasses camera's is a few millimetres (the
/// prototype's 3.84 mm), a full-frame sensor's 36 mm; 65,536 px of 1 mm (65 m) was taken.
pub const MAX_SENSOR_SIDE_M: f64 = 0.05;
/// Largest slippage pitch rate (rad per m of slip): 1 rad per mm.
pub const MAX_PITCH_RATE_RAD_PER_M: f64 = 1e3;
/// Largest σ of the mounting translation (m) per axis.
pub const MAX_MOUNT_TRANSLATION_SIGMA_M: f64 = 5e-3;
/// Largest σ of the mounting rotation (rad) per axis.
pub const MAX_MOUNT_ROTATION_SIGMA_RAD: f64 = 0.2;
const SQRT_3: f64 = 1.732_050_807_568_877_2;

/// Pinhole camera: intrinsics (OpenCV convention, pixel origin at the top-left pixel's corner,
/// so pixel (col, row) has its centre at (col + 0.5, row + 0.5)) and nominal pose.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Camera {
    /// Pinhole image distance (m): the metalens-to-sensor distance s, 2 mm in the prototype.
    pub focal_length_m: f64,
    /// Effective pixel pitch p̂ (m).
    pub pixel_pitch_m: f64,
    /// Focal length in pixels along x: focal_length_m / pixel_pitch_m.
    pub fx_px: f64,
    /// Focal length in pixels along y.
    pub fy_px: f64,
    /// Principal point x (px from the left image edge).
    pub cx_px: f64,
    /// Principal point y (px from the top image edge).
    pub cy_px: f64,
    /// Image width (px).
    pub width_px: usize,
    /// Image height (px).
    pub height_px: usize,
    /// Nominal optical centre T_nom (m, world frame).
    pub position_m: Vec3,
    /// Rotation taking camera-frame vectors to the world frame (rows), R_nom.
    pub rotation_cam_to_world: Mat3,
}

/// How glasses slip (C.1): a distance d along the nasal bridge moves the camera by
/// d · `bridge_direction` and pitches it by `pitch_rate_rad_per_m` · d about the interaural
/// (x) axis; a small random rigid mounting perturbation is added on top.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SlipModel {
    /// Unit direction (world frame) the glasses move along when sliding down the nose.
    pub bridge_direction: Vec3,
    /// Pitch rotation (rad) per metre of slip about the interaural (+x) axis; positive drops
    /// the front of the frame.
    pub pitch_rate_rad_per_m: f64,
    /// Standard deviation (m) of the mounting translation, per axis (truncated at 3σ).
    pub mount_translation_sigma_m: f64,
    /// Standard deviation (rad) of the mounting rotation, per axis (truncated at 3σ).
    pub mount_rotation_sigma_rad: f64,
}

/// The eye–camera rig shared by the solver, the samplers and the renderer.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Rig {
    /// Radius (m) of the sphere the solver intersects (R_eye in S12).
    pub eye_radius_m: f64,
    /// Radius (m) of the sphere the pupil centre really moves on (used to generate data).
    pub pupil_sphere_radius_m: f64,
    /// Kappa angles (horizontal, vertical; rad) from the optical to the visual axis.
    pub kappa_rad: [f64; 2],
    /// The camera.
    pub camera: Camera,
    /// The slippage model.
    pub slip: SlipModel,
    /// The cornea the refraction-aware solver looks through (absent in older rig files: the
    /// average eye).
    #[serde(default)]
    pub cornea: Cornea,
}

/// A camera pose: optical centre and camera-to-world rotation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    /// Optical centre (m, world frame).
    pub position: Vec3,
    /// Camera-to-world rotation (rows).
    pub rotation: Mat3,
}

/// Whole pixels of a resampled grid: ⌊n·k⌋ for n pixels scaled by k = old pitch / new pitch,
/// with a 1e-9 tolerance so that exact ratios (1280 px at 3 µm → 9 µm: 426) do not lose a
/// pixel to rounding. The sensor's box integrator counts its output pixels the same way.
pub fn effective_pixels(n: usize, k: f64) -> usize {
    let v = (n as f64 * k + 1e-9).floor();
    if (0.0..1e12).contains(&v) {
        v as usize
    } else {
        0
    }
}

impl Camera {
    /// A camera with image distance `focal_length_m`, pitch `pixel_pitch_m`, a centred
    /// principal point, at `position_m` aimed at `target_m` with world +y as image up.
    pub fn look_at(
        focal_length_m: f64,
        pixel_pitch_m: f64,
        width_px: usize,
        height_px: usize,
        position_m: Vec3,
        target_m: Vec3,
    ) -> Result<Self, GazeError> {
        let z = geom::sub(target_m, position_m);
        if geom::norm(z).is_nan() || geom::norm(z) <= 0.0 {
            return Err(GazeError::InvalidRig {
                field: "camera.position_m",
                reason: "camera centre coincides with its target".into(),
            });
        }
        let z = geom::normalize(z);
        // Image y points down: the component of −world-y orthogonal to the optical axis.
        let down = [0.0, -1.0, 0.0];
        let y = geom::sub(down, geom::scale(z, geom::dot(down, z)));
        if geom::norm(y) < 1e-9 {
            return Err(GazeError::InvalidRig {
                field: "camera.position_m",
                reason: "optical axis is vertical; image up is undefined".into(),
            });
        }
        let y = geom::normalize(y);
        let x = geom::cross(y, z);
        // Columns of R are the camera axes in world coordinates.
        let rotation_cam_to_world = [[x[0], y[0], z[0]], [x[1], y[1], z[1]], [x[2], y[2], z[2]]];
        let f_px = focal_length_m / pixel_pitch_m;
        let cam = Camera {
            focal_length_m,
            pixel_pitch_m,
            fx_px: f_px,
            fy_px: f_px,
            cx_px: width_px as f64 / 2.0,
            cy_px: height_px as f64 / 2.0,
            width_px,
            height_px,
            position_m,
            rotation_cam_to_world,
        };
        cam.validate()?;
        Ok(cam)
    }

    /// The same camera resampled to effective pitch `pixel_pitch_m` over the same sensor area:
    /// focal length in px scales by k = old/new pitch, the image keeps ⌊n·k⌋ whole pixels
    /// ([`effective_pixels`]) centred on the old grid, and the principal point follows.
    pub fn with_pitch(&self, pixel_pitch_m: f64) -> Result<Self, GazeError> {
        if !(pixel_pitch_m.is_finite() && pixel_pitch_m > 0.0) {
            return Err(GazeError::InvalidRig {
                field: "camera.pixel_pitch_m",
                reason: format!("must be positive and finite, got {pixel_pitch_m}"),
            });
        }
        let k = self.pixel_pitch_m / pixel_pitch_m;
        let (w, h) = (
            effective_pixels(self.width_px, k),
            effective_pixels(self.height_px, k),
        );
        if w == 0 || h == 0 {
            return Err(GazeError::InvalidRig {
                field: "camera.pixel_pitch_m",
                reason: format!(
                    "{pixel_pitch_m} m pixels do not fit the {}×{} px sensor",
                    self.width_px, self.height_px
                ),
            });
        }
        // The new grid is centred on the old one: its origin moves by half the part of the
        // sensor that no whole new pixel covers (sensor's `BoxIntegrator` convention).
        let cam = Camera {
            pixel_pitch_m,
            fx_px: self.fx_px * k,
            fy_px: self.fy_px * k,
            cx_px: self.cx_px * k - 0.5 * (self.width_px as f64 * k - w as f64),
            cy_px: self.cy_px * k - 0.5 * (self.height_px as f64 * k - h as f64),
            width_px: w,
            height_px: h,
            ..self.clone()
        };
        cam.validate()?;
        Ok(cam)
    }

    /// The nominal pose (T_nom, R_nom).
    pub fn nominal_pose(&self) -> Pose {
        Pose {
            position: self.position_m,
            rotation: self.rotation_cam_to_world,
        }
    }

    /// The pose after a pure translation `slip_m` (m) of the camera (S11).
    pub fn translated_pose(&self, slip_m: Vec3) -> Pose {
        Pose {
            position: geom::add(self.position_m, slip_m),
            rotation: self.rotation_cam_to_world,
        }
    }

    /// The pose after translation `slip_m` (m) and a rotation vector `rot_rad` (world frame,
    /// about the camera's own centre).
    pub fn slipped_pose(&self, slip_m: Vec3, rot_rad: Vec3) -> Pose {
        Pose {
            position: geom::add(self.position_m, slip_m),
            rotation: geom::mul_mm(&geom::rot_from_vector(rot_rad), &self.rotation_cam_to_world),
        }
    }

    /// The translation (m) that S11's translation-only model stands for when the camera moved
    /// by `slip_m` and turned by `rot_rad` about its own centre (as in
    /// [`Camera::slipped_pose`]): turn the whole slipped rig about the eye centre (the world
    /// origin) back to the nominal orientation; where the camera then sits, minus T_nom. The
    /// eye, a sphere about that centre, looks to the nominal camera placed there as it does to
    /// the slipped one with its gaze turned by the same rotation, so the solver given this
    /// translation errs by the rotation's angle, not by the ≈ 2–3× larger angle that a camera
    /// turned about its own centre costs when its translation alone is given (docs/gaze.md).
    pub fn eye_equivalent_slip(&self, slip_m: Vec3, rot_rad: Vec3) -> Vec3 {
        let w = geom::rot_from_vector(rot_rad);
        // Turning back by Wᵀ takes R = W·R_nom to R_nom and the centre T_nom + Δt to
        // Wᵀ·(T_nom + Δt); minus T_nom, grouped so that W = I gives Δt exactly.
        let t = self.position_m;
        geom::add(
            geom::mul_mtv(&w, slip_m),
            geom::sub(geom::mul_mtv(&w, t), t),
        )
    }

    /// Checks every field; the error names the first bad one.
    pub fn validate(&self) -> Result<(), GazeError> {
        let pos = |field, v: f64| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(GazeError::InvalidRig {
                    field,
                    reason: format!("must be positive and finite, got {v}"),
                })
            }
        };
        pos("camera.focal_length_m", self.focal_length_m)?;
        pos("camera.pixel_pitch_m", self.pixel_pitch_m)?;
        pos("camera.fx_px", self.fx_px)?;
        pos("camera.fy_px", self.fy_px)?;
        let within = |field, v: f64, (lo, hi): (f64, f64)| {
            if (lo..=hi).contains(&v) {
                Ok(())
            } else {
                Err(GazeError::InvalidRig {
                    field,
                    reason: format!("{v} lies outside the plausible range [{lo:e}, {hi:e}]"),
                })
            }
        };
        within(
            "camera.focal_length_m",
            self.focal_length_m,
            FOCAL_LENGTH_RANGE_M,
        )?;
        within(
            "camera.pixel_pitch_m",
            self.pixel_pitch_m,
            PIXEL_PITCH_RANGE_M,
        )?;
        let f_px = self.focal_length_m / self.pixel_pitch_m;
        for (field, v) in [("camera.fx_px", self.fx_px), ("camera.fy_px", self.fy_px)] {
            if (v - f_px).abs() > 1e-6 * f_px {
                return Err(GazeError::InvalidRig {
                    field,
                    reason: format!(
                        "{v} px disagrees with focal_length_m / pixel_pitch_m = {f_px} px"
                    ),
                });
            }
        }
        // Within a few image sides of the image: further out no pixel sees near the axis.
        let reach = 4.0 * MAX_IMAGE_SIDE_PX as f64;
        for (field, v) in [("camera.cx_px", self.cx_px), ("camera.cy_px", self.cy_px)] {
            if !(v.is_finite() && v.abs() <= reach) {
                return Err(GazeError::InvalidRig {
                    field,
                    reason: format!("principal point must lie within ±{reach} px, got {v:e}"),
                });
            }
        }
        if self.width_px == 0 || self.height_px == 0 {
            return Err(GazeError::InvalidRig {
                field: if self.width_px == 0 {
                    "camera.width_px"
                } else {
                    "camera.height_px"
                },
                reason: "image size must be at least 1×1 px".into(),
            });
        }
        if self.width_px > MAX_IMAGE_SIDE_PX || self.height_px > MAX_IMAGE_SIDE_PX {
            return Err(GazeError::InvalidRig {
                field: if self.width_px > MAX_IMAGE_SIDE_PX {
                    "camera.width_px"
                } else {
                    "camera.height_px"
                },
                reason: format!(
                    "image size {}×{} px exceeds the maximum side of {MAX_IMAGE_SIDE_PX} px",
                    self.width_px, self.height_px
                ),
            });
        }
        let side = self.width_px.max(self.height_px) as f64 * self.pixel_pitch_m;
        if side > MAX_SENSOR_SIDE_M {
            return Err(GazeError::InvalidRig {
                field: if self.width_px >= self.height_px {
                    "camera.width_px"
                } else {
                    "camera.height_px"
                },
                reason: format!(
                    "{}×{} px of {:e} m make a sensor {side:.3} m wide, beyond the plausible \
                     {MAX_SENSOR_SIDE_M} m",
                    self.width_px, self.height_px, self.pixel_pitch_m
                ),
            });
        }
        let d = geom::norm(self.position_m);
        if !(geom::is_finite(self.position_m) && d <= MAX_CAMERA_DISTANCE_M) {
            return Err(GazeError::InvalidRig {
                field: "camera.position_m",
                reason: format!(
                    "must lie within {MAX_CAMERA_DISTANCE_M} m of the eye, is {d:e} m away"
                ),
            });
        }
        let (dev, det) = geom::orthonormality(&self.rotation_cam_to_world);
        if !(dev < 1e-9 && (det - 1.0).abs() < 1e-9) {
            return Err(GazeError::InvalidRig {
                field: "camera.rotation_cam_to_world",
                reason: format!("must be a proper rotation (|RᵀR − I| = {dev:e}, det = {det})"),
            });
        }
        Ok(())
    }
}

impl Default for SlipModel {
    fn default() -> Self {
        // The nasal bridge slopes ≈30° from vertical, so glasses slide down and forward.
        let a = 30f64.to_radians();
        SlipModel {
            bridge_direction: [0.0, -a.cos(), a.sin()],
            // Frames pivot on the ears ≈90 mm behind the nose pads: pitch ≈ d / 90 mm.
            pitch_rate_rad_per_m: 1.0 / 0.09,
            mount_translation_sigma_m: 0.2e-3,
            mount_rotation_sigma_rad: 0.5f64.to_radians(),
        }
    }
}

impl SlipModel {
    /// Checks every field; the error names the first bad one.
    pub fn validate(&self) -> Result<(), GazeError> {
        let n = geom::norm(self.bridge_direction);
        if !(n.is_finite() && (n - 1.0).abs() < 1e-6) {
            return Err(GazeError::InvalidRig {
                field: "slip.bridge_direction",
                reason: format!("must be a unit vector, has norm {n}"),
            });
        }
        for (field, v) in [
            ("slip.pitch_rate_rad_per_m", self.pitch_rate_rad_per_m),
            (
                "slip.mount_translation_sigma_m",
                self.mount_translation_sigma_m,
            ),
            (
                "slip.mount_rotation_sigma_rad",
                self.mount_rotation_sigma_rad,
            ),
        ] {
            if !v.is_finite() {
                return Err(GazeError::InvalidRig {
                    field,
                    reason: format!("must be finite, got {v}"),
                });
            }
        }
        for (field, v) in [
            (
                "slip.mount_translation_sigma_m",
                self.mount_translation_sigma_m,
            ),
            (
                "slip.mount_rotation_sigma_rad",
                self.mount_rotation_sigma_rad,
            ),
        ] {
            if v < 0.0 {
                return Err(GazeError::InvalidRig {
                    field,
                    reason: format!("a standard deviation must be ≥ 0, got {v}"),
                });
            }
        }
        for (field, v, max) in [
            (
                "slip.pitch_rate_rad_per_m",
                self.pitch_rate_rad_per_m.abs(),
                MAX_PITCH_RATE_RAD_PER_M,
            ),
            (
                "slip.mount_translation_sigma_m",
                self.mount_translation_sigma_m,
                MAX_MOUNT_TRANSLATION_SIGMA_M,
            ),
            (
                "slip.mount_rotation_sigma_rad",
                self.mount_rotation_sigma_rad,
                MAX_MOUNT_ROTATION_SIGMA_RAD,
            ),
        ] {
            if v > max {
                return Err(GazeError::InvalidRig {
                    field,
                    reason: format!("magnitude {v} exceeds the plausible maximum {max}"),
                });
            }
        }
        Ok(())
    }
}

impl Default for Rig {
    /// The seed rig: 12 mm solver sphere, pupil on a 10.39 mm sphere, a 1280×800, 3 µm sensor
    /// (OV9281, as in the prototype, Sec. D.3) read out at 4× binning (320×200 at 12 µm)
    /// 2 mm behind the lens, at pupil_primary + (−10, −14, +10) mm aimed at the eye centre.
    fn default() -> Self {
        let pupil_primary = [0.0, 0.0, DEFAULT_PUPIL_SPHERE_RADIUS_M];
        let camera = Camera::look_at(
            2e-3,
            12e-6,
            320,
            200,
            geom::add(pupil_primary, CAMERA_OFFSET_M),
            [0.0, 0.0, 0.0],
        )
        .expect("the built-in rig is valid");
        Rig {
            eye_radius_m: DEFAULT_EYE_RADIUS_M,
            pupil_sphere_radius_m: DEFAULT_PUPIL_SPHERE_RADIUS_M,
            kappa_rad: [0.0, 0.0],
            camera,
            slip: SlipModel::default(),
            cornea: Cornea::default(),
        }
    }
}

impl Rig {
    /// Checks every field; the error names the first bad one.
    pub fn validate(&self) -> Result<(), GazeError> {
        let (lo, hi) = EYE_RADIUS_RANGE_M;
        for (field, v) in [
            ("eye_radius_m", self.eye_radius_m),
            ("pupil_sphere_radius_m", self.pupil_sphere_radius_m),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(GazeError::InvalidRig {
                    field,
                    reason: format!("must be positive and finite, got {v}"),
                });
            }
            if !(lo..=hi).contains(&v) {
                return Err(GazeError::InvalidRig {
                    field,
                    reason: format!("{v} m lies outside the plausible range [{lo}, {hi}] m"),
                });
            }
        }
        if !self
            .kappa_rad
            .iter()
            .all(|k| k.is_finite() && k.abs() < 0.5)
        {
            return Err(GazeError::InvalidRig {
                field: "kappa_rad",
                reason: format!("must be finite and below 0.5 rad, got {:?}", self.kappa_rad),
            });
        }
        // The cornea the refraction-aware solver and the renderer use, checked with the rest
        // (a rig `rig show` accepted was refused by `gaze solve --solver refractive`).
        self.cornea.validate(self.pupil_sphere_radius_m)?;
        self.camera.validate()?;
        self.slip.validate()?;
        // The camera must sit outside both spheres (with room for the largest slip the
        // mounting perturbation can add), or no ray from it reaches the eye from outside.
        let d = geom::norm(self.camera.position_m);
        let r = self.eye_radius_m.max(self.pupil_sphere_radius_m);
        if d <= r + 3.0 * SQRT_3 * self.slip.mount_translation_sigma_m {
            return Err(GazeError::InvalidRig {
                field: "camera.position_m",
                reason: format!(
                    "the camera centre is {d} m from the eye centre, inside (or within the \
                     mounting tolerance of) the {r} m sphere"
                ),
            });
        }
        // A camera facing away sees no eye: every set it renders is empty of pupils (`run`
        // rendered its training set before the protocol found none).
        let r_cw = &self.camera.rotation_cam_to_world;
        let to_eye = geom::scale(self.camera.position_m, -1.0);
        let depth: f64 = (0..3).map(|i| r_cw[i][2] * to_eye[i]).sum();
        if depth <= 0.0 {
            return Err(GazeError::InvalidRig {
                field: "camera.rotation_cam_to_world",
                reason: format!(
                    "the camera faces away from the eye: the eye centre lies {:e} m behind its \
                     image plane (the third column is the optical axis, towards the eye)",
                    -depth
                ),
            });
        }
        Ok(())
    }

    /// Parses and validates a rig from JSON.
    pub fn from_json(text: &str) -> Result<Self, GazeError> {
        let rig: Rig = serde_json::from_str(text).map_err(|e| GazeError::InvalidRig {
            field: "(json)",
            reason: e.to_string(),
        })?;
        rig.validate()?;
        Ok(rig)
    }

    /// The 3D pupil centre (m) for a unit gaze direction `g` (optical axis).
    pub fn pupil_center(&self, g: Vec3) -> Vec3 {
        geom::scale(g, self.pupil_sphere_radius_m)
    }
}

#[cfg(test)]
mod bad_input_tests {
    use super::*;

    fn field_of(rig: &Rig) -> &'static str {
        match rig.validate() {
            Err(GazeError::InvalidRig { field, .. }) => field,
            other => panic!("expected InvalidRig, got {other:?}"),
        }
    }

    #[test]
    fn wrong_fy_px_is_refused() {
        let mut rig = Rig::default();
        rig.camera.fy_px *= 1.5;
        assert_eq!(field_of(&rig), "camera.fy_px");
    }

    #[test]
    fn impossible_rigs_are_refused() {
        let rig = Rig {
            eye_radius_m: 1e-300,
            ..Rig::default()
        };
        assert_eq!(field_of(&rig), "eye_radius_m");
        let rig = Rig {
            pupil_sphere_radius_m: 1e300,
            ..Rig::default()
        };
        assert_eq!(field_of(&rig), "pupil_sphere_radius_m");
        let mut rig = Rig::default();
        rig.camera.position_m = [0.0, 0.0, 5e-3];
        assert_eq!(field_of(&rig), "camera.position_m");
        let mut rig = Rig::default();
        rig.slip.mount_translation_sigma_m = 1e300;
        assert_eq!(field_of(&rig), "slip.mount_translation_sigma_m");
        let mut rig = Rig::default();
        rig.slip.mount_rotation_sigma_rad = 1e300;
        assert_eq!(field_of(&rig), "slip.mount_rotation_sigma_rad");
        let mut rig = Rig::default();
        rig.slip.pitch_rate_rad_per_m = -1e300;
        assert_eq!(field_of(&rig), "slip.pitch_rate_rad_per_m");
        // The cornea is the rig's too: an index below 1, and a pupil beyond the apex.
        let mut rig = Rig::default();
        rig.cornea.index = 0.5;
        assert_eq!(field_of(&rig), "cornea.index");
        let rig = Rig {
            pupil_sphere_radius_m: 0.02,
            ..Rig::default()
        };
        assert_eq!(field_of(&rig), "cornea.apex_m");
        Rig::default().validate().unwrap();
    }

    /// A sensor wider than any camera's (a helper's audit: 65,536 px of 1 mm, a 65 m sensor,
    /// was taken, and a 20000² px one made `gaze solve` decode a 2.7 GB mask) is refused
    /// naming its longer side; the default's 3.84 mm and a 36 mm full frame are not.
    #[test]
    fn a_sensor_beyond_any_cameras_size_is_refused() {
        let cam = |w: usize, h: usize, pitch: f64| {
            let mut rig = Rig::default();
            let c = &mut rig.camera;
            c.pixel_pitch_m = pitch;
            c.fx_px = c.focal_length_m / pitch;
            c.fy_px = c.fx_px;
            (c.width_px, c.height_px) = (w, h);
            (c.cx_px, c.cy_px) = (w as f64 / 2.0, h as f64 / 2.0);
            rig
        };
        assert_eq!(field_of(&cam(65536, 65536, 1e-3)), "camera.width_px");
        assert_eq!(field_of(&cam(20000, 20000, 12e-6)), "camera.width_px");
        assert_eq!(field_of(&cam(200, 5000, 12e-6)), "camera.height_px");
        cam(6000, 4000, 6e-6).validate().unwrap();
        cam(320, 200, 12e-6).validate().unwrap();
    }
}

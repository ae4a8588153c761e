//! The state vector s = (φ, θ, ω, tx, ty, tz) of C.1 and what it implies for the rig.

use nanoeye_gaze::{GazeError, Mat3, Pose, Rig, Vec3, eye, geom, project};
use serde::{Deserialize, Serialize};

/// One eye/glasses state (C.1): eye azimuth φ and elevation θ (Fick angles of the optical
/// axis, Listing's law), extra torsion ω, and the camera's slippage.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct State {
    /// Eye azimuth φ (rad), positive towards +x.
    pub azimuth_rad: f64,
    /// Eye elevation θ (rad), positive up.
    pub elevation_rad: f64,
    /// Torsion ω (rad) about the line of sight on top of Listing's law.
    pub torsion_rad: f64,
    /// Camera translation (tx, ty, tz) from its nominal centre (m, world frame).
    pub slip_m: Vec3,
    /// Camera rotation vector (rad, world frame, about the camera centre) from the slippage
    /// pitch and the mounting perturbation; zero when absent from a file.
    #[serde(default)]
    pub cam_rot_rad: Vec3,
    /// Lid closure (0 open … 1 closed: a blink or a partial closure); zero when absent from a
    /// file, and then not written, so files of open-eyed states keep their layout.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub lid_closure: f64,
}

fn is_zero(x: &f64) -> bool {
    *x == 0.0
}

impl State {
    /// Unit optical-axis gaze direction.
    pub fn gaze(&self) -> Vec3 {
        eye::gaze_from_angles(self.azimuth_rad, self.elevation_rad)
    }

    /// Eye rotation (Listing's law, then torsion ω).
    pub fn eye_rotation(&self) -> Result<Mat3, GazeError> {
        eye::eye_rotation(self.azimuth_rad, self.elevation_rad, self.torsion_rad)
    }

    /// The camera pose this state puts the rig's camera in.
    pub fn camera_pose(&self, rig: &Rig) -> Pose {
        rig.camera.slipped_pose(self.slip_m, self.cam_rot_rad)
    }

    /// 3D pupil centre (m) on the rig's pupil sphere.
    pub fn pupil_center(&self, rig: &Rig) -> Vec3 {
        rig.pupil_center(self.gaze())
    }

    /// Pixel (u, v) of the (unrefracted) pupil centre in this state's camera.
    pub fn pupil_px(&self, rig: &Rig) -> Result<[f64; 2], GazeError> {
        project(&rig.camera, &self.camera_pose(rig), self.pupil_center(rig))
    }

    /// True when the pupil faces the camera (the camera is in front of the pupil plane).
    pub fn pupil_faces_camera(&self, rig: &Rig) -> bool {
        let p = self.pupil_center(rig);
        let to_cam = geom::sub(self.camera_pose(rig).position, p);
        geom::dot(to_cam, self.gaze()) > 0.0
    }
}

/// Slippage parameters drawn for one glasses placement.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Mounting {
    /// Random rigid translation (m).
    pub translation_m: Vec3,
    /// Random rigid rotation vector (rad).
    pub rotation_rad: Vec3,
}

impl Mounting {
    /// No perturbation.
    pub const NONE: Mounting = Mounting {
        translation_m: [0.0; 3],
        rotation_rad: [0.0; 3],
    };

    /// (slip_m, cam_rot_rad) for slip distance `d_m` along the nasal bridge of `rig`, with the
    /// coupled pitch about the interaural axis and this mounting perturbation.
    pub fn slip(&self, rig: &Rig, d_m: f64) -> (Vec3, Vec3) {
        let s = &rig.slip;
        let slip = geom::add(geom::scale(s.bridge_direction, d_m), self.translation_m);
        let rot = geom::add([s.pitch_rate_rad_per_m * d_m, 0.0, 0.0], self.rotation_rad);
        (slip, rot)
    }
}

//! Errors of the gaze crate: every failure the solver documents, never a panic or a NaN.

/// What can go wrong in rig validation, projection and gaze solving.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GazeError {
    /// The mask sums to zero (or below 1e-12): there is no pupil to take a centroid of.
    #[error("the pupil mask is empty (its sum is {sum}); nothing to take a centroid of")]
    EmptyMask {
        /// Sum of the mask values.
        sum: f64,
    },
    /// A mask value is negative or not finite.
    #[error("pupil mask value at (row {row}, col {col}) is {value}; values must be finite and ≥ 0")]
    InvalidMask {
        /// Row (v) index of the offending value.
        row: usize,
        /// Column (u) index of the offending value.
        col: usize,
        /// The offending value.
        value: f64,
    },
    /// The mask's shape does not match the camera image (or a whole-number downscale of it).
    #[error(
        "mask is {mask_w}×{mask_h} px but the camera image is {cam_w}×{cam_h} px; the mask must \
         be the image size or an exact downscale of it with equal factors in x and y"
    )]
    MaskShape {
        /// Mask width (px).
        mask_w: usize,
        /// Mask height (px).
        mask_h: usize,
        /// Camera width (px).
        cam_w: usize,
        /// Camera height (px).
        cam_h: usize,
    },
    /// An input number (pixel, slippage, direction) is NaN or infinite.
    #[error("{what} is not finite")]
    NonFinite {
        /// Which input.
        what: &'static str,
    },
    /// The back-projected ray passes the eye sphere (or points away from it).
    #[error("the camera ray misses the eye sphere of radius {radius_m} m")]
    RayMissesSphere {
        /// Solver sphere radius (m).
        radius_m: f64,
    },
    /// The back-projected ray does not reach the pupil through the cornea (it meets the sclera
    /// or passes the eye), so the refraction-aware solver has no gaze to return.
    #[error("the camera ray does not reach the pupil through the cornea of radius {radius_m} m")]
    RayMissesCornea {
        /// Cornea radius (m).
        radius_m: f64,
    },
    /// The (slipped) camera centre lies inside or on the eye sphere.
    #[error(
        "the camera centre is {distance_m} m from the eye centre, inside the eye sphere of radius {radius_m} m"
    )]
    CameraInsideSphere {
        /// Distance of the camera centre from the eye centre (m).
        distance_m: f64,
        /// Solver sphere radius (m).
        radius_m: f64,
    },
    /// The point to project lies on or behind the camera's image plane.
    #[error("the point is behind the camera (depth {depth_m} m along the optical axis)")]
    BehindCamera {
        /// Depth along the camera's optical axis (m).
        depth_m: f64,
    },
    /// A gaze direction with no Listing rotation (pointing straight back into the head).
    #[error(
        "gaze direction {gaze:?} is opposite the primary direction; Listing's law is undefined there"
    )]
    OppositeGaze {
        /// The offending unit gaze vector.
        gaze: [f64; 3],
    },
    /// A study or solver parameter (not part of the rig) is out of range.
    #[error("parameter `{name}`: {reason}")]
    InvalidParameter {
        /// Name of the parameter.
        name: &'static str,
        /// What is wrong and what is expected.
        reason: String,
    },
    /// A rig parameter is out of range or inconsistent.
    #[error("rig field `{field}`: {reason}")]
    InvalidRig {
        /// JSON path of the field.
        field: &'static str,
        /// What is wrong and what is expected.
        reason: String,
    },
}

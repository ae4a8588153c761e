//! Eye and camera rig geometry and the geometric gaze solver of Sec. A.4 (S9–S14).
//!
//! Pipeline: soft pupil mask → centroid (S9) → ray through K⁻¹ (S10) from the slipped camera
//! centre T_nom + Δt (S11) → near intersection with the eye sphere (S12–S13) → gaze (S14).
//! Units are SI (metres, radians); image coordinates are pixels with the origin at the
//! top-left pixel's corner. Every failure is a [`GazeError`], never a panic or a NaN.

pub mod bias;
pub mod centroid;
pub mod error;
pub mod eye;
pub mod geom;
pub mod pupil;
pub mod refract;
pub mod rig;
pub mod solver;
pub mod stats;

pub use error::GazeError;
pub use geom::{Mat3, Vec3};
pub use pupil::PupilCentre;
pub use refract::{Cornea, RefractiveSolver, SolverKind, solver_for};
pub use rig::{Camera, Pose, Rig, SlipModel, effective_pixels};
pub use solver::{GazeSolution, GazeSolver, GazeVjp, SphereSolver, back_project, project};
pub use stats::{Summary, angular_error};

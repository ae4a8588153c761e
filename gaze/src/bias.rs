//! Pupil-sphere bias: the angular error the solver makes when its sphere radius differs from
//! the radius the pupil centre really moves on, over a grid of gaze directions.

use crate::error::GazeError;
use crate::eye;
use crate::geom;
use crate::rig::Rig;
use crate::solver::{GazeSolver, SphereSolver, project};
use crate::stats::{Summary, angular_error};
use serde::Serialize;

/// Largest number of samples per axis of a [`GazeGrid`] (16.8 M gaze points per radius).
pub const MAX_GRID_STEPS: usize = 4096;

/// A rectangular grid of Fick gaze angles (rad), inclusive of both ends.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GazeGrid {
    /// Azimuth range (rad).
    pub azimuth: (f64, f64),
    /// Elevation range (rad).
    pub elevation: (f64, f64),
    /// Samples per axis (≥ 2).
    pub steps: usize,
}

impl GazeGrid {
    /// Table S2's anchor gaze range: azimuth −35°…45°, elevation −15°…15°.
    pub fn table_s2(steps: usize) -> Self {
        GazeGrid {
            azimuth: ((-35f64).to_radians(), 45f64.to_radians()),
            elevation: ((-15f64).to_radians(), 15f64.to_radians()),
            steps: steps.max(2),
        }
    }

    /// Every (azimuth, elevation) pair of the grid.
    pub fn points(&self) -> impl Iterator<Item = (f64, f64)> + '_ {
        let n = self.steps.max(2);
        let lerp = move |(a, b): (f64, f64), i: usize| a + (b - a) * i as f64 / (n - 1) as f64;
        (0..n).flat_map(move |i| {
            (0..n).map(move |j| (lerp(self.azimuth, i), lerp(self.elevation, j)))
        })
    }
}

/// Bias statistics for one solver radius.
#[derive(Debug, Clone, Serialize)]
pub struct BiasReport {
    /// Radius the pupil centre truly moves on (m).
    pub true_radius_m: f64,
    /// Radius the solver intersects (m).
    pub solver_radius_m: f64,
    /// Angular error statistics over the grid points in view (deg); absent (not null) in
    /// JSON when no point gave a solution (every ray missed the solver's sphere).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error_deg: Option<Summary>,
    /// Grid points whose pupil projects inside the image.
    pub in_view: usize,
    /// In-view points whose pupil lies beyond the pupil sphere's limb as the camera sees it
    /// (p·(O − p) ≤ 0): no sphere solver can recover them, so they are left out of `error_deg`.
    pub hidden: usize,
    /// Grid points whose ray missed the solver sphere.
    pub missed: usize,
    /// Grid points in total.
    pub total: usize,
}

/// Projects the true pupil (on `rig.pupil_sphere_radius_m`) through the nominal camera for every
/// grid gaze, solves on a sphere of `solver_radius_m`, and summarizes the angular error.
pub fn pupil_sphere_bias(
    rig: &Rig,
    solver_radius_m: f64,
    grid: &GazeGrid,
) -> Result<BiasReport, GazeError> {
    if grid.steps > MAX_GRID_STEPS {
        return Err(GazeError::InvalidParameter {
            name: "steps",
            reason: format!(
                "{} samples per axis exceeds the maximum of {MAX_GRID_STEPS}",
                grid.steps
            ),
        });
    }
    let mut solver_rig = rig.clone();
    solver_rig.eye_radius_m = solver_radius_m;
    let solver = SphereSolver::new(&solver_rig)?;
    let cam = &rig.camera;
    let pose = cam.nominal_pose();
    let (mut errs, mut missed, mut total, mut in_view, mut hidden) = (Vec::new(), 0, 0, 0, 0);
    for (az, el) in grid.points() {
        total += 1;
        let g = eye::gaze_from_angles(az, el);
        let p = rig.pupil_center(g);
        let px = match project(cam, &pose, p) {
            Ok(px) => px,
            Err(_) => continue,
        };
        if !(0.0..=cam.width_px as f64).contains(&px[0])
            || !(0.0..=cam.height_px as f64).contains(&px[1])
        {
            continue;
        }
        in_view += 1;
        if geom::dot(p, geom::sub(pose.position, p)) <= 0.0 {
            hidden += 1;
            continue;
        }
        match solver.solve_pixel(px, [0.0; 3]) {
            Ok(sol) => errs.push(angular_error(sol.gaze, g).to_degrees()),
            Err(_) => missed += 1,
        }
    }
    Ok(BiasReport {
        true_radius_m: rig.pupil_sphere_radius_m,
        solver_radius_m,
        error_deg: Summary::of(&errs),
        in_view,
        hidden,
        missed,
        total,
    })
}

#[cfg(test)]
mod bad_input_tests {
    use super::*;

    #[test]
    fn grid_beyond_the_step_limit_is_refused_before_any_work() {
        let e = pupil_sphere_bias(
            &Rig::default(),
            12e-3,
            &GazeGrid::table_s2(1_000_000_000_000),
        )
        .unwrap_err();
        assert!(
            matches!(e, GazeError::InvalidParameter { name: "steps", .. }),
            "{e}"
        );
    }
}

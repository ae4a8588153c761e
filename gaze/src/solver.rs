//! The geometric gaze solver (S10–S14), forward projection, and the solver's VJP.

use crate::centroid::{self, Centroid};
use crate::error::GazeError;
use crate::eye;
use crate::geom::{self, Mat3, Vec3};
use crate::pupil::{self, PupilCentre};
use crate::rig::{Camera, Pose, Rig};
use faer::{Mat, MatRef};

/// Result of one gaze solve.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GazeSolution {
    /// Pupil centre in camera pixels (u, v) that was back-projected.
    pub pupil_px: [f64; 2],
    /// 3D pupil centre P_3D on the solver sphere (m, world frame), S13.
    pub pupil_3d_m: Vec3,
    /// Optical-axis gaze g = P_3D / |P_3D| (unit), S14.
    pub gaze: Vec3,
    /// Visual axis (unit) when the solver applies the rig's kappa correction.
    pub visual_axis: Option<Vec3>,
    /// Distance s* from the camera centre to P_3D along the ray (m).
    pub ray_length_m: f64,
    /// True when the solver's own model had no exact solution for this ray and `gaze` is its
    /// documented nearest estimate (the refraction-aware solver's unrefracted pupil-sphere
    /// solution, see [`crate::RefractiveSolver`]); the sphere solver never falls back.
    pub fallback: bool,
}

/// Gradients the solver passes upstream.
#[derive(Debug, Clone, PartialEq)]
pub struct GazeVjp {
    /// ∂L/∂(u_p, v_p).
    pub pupil_px: [f64; 2],
    /// ∂L/∂Δt (per metre of slippage).
    pub slip_m: Vec3,
}

/// A gaze estimator: pixel or mask plus slippage in, gaze out.
pub trait GazeSolver {
    /// Solves S10–S14 for pupil centre `pupil_px` (camera pixels) and slippage `slip_m` (m).
    fn solve_pixel(&self, pupil_px: [f64; 2], slip_m: Vec3) -> Result<GazeSolution, GazeError>;

    /// Solves S9–S14 for a soft pupil mask (rows = v, cols = u) and slippage `slip_m` (m).
    fn solve_mask(&self, mask: MatRef<'_, f32>, slip_m: Vec3) -> Result<GazeSolution, GazeError> {
        self.solve_mask_with(mask, slip_m, PupilCentre::Centroid)
    }

    /// Solves S10–S14 for the pupil centre `how` takes from `mask` ([`PupilCentre::Centroid`]
    /// is [`GazeSolver::solve_mask`]).
    fn solve_mask_with(
        &self,
        mask: MatRef<'_, f32>,
        slip_m: Vec3,
        how: PupilCentre,
    ) -> Result<GazeSolution, GazeError> {
        let c = self.mask_centre(mask, how)?;
        self.solve_pixel(c.px, slip_m)
    }

    /// The pupil centre `how` takes from `mask`, in camera pixels (checks the mask's shape
    /// against the camera).
    fn mask_centre(&self, mask: MatRef<'_, f32>, how: PupilCentre) -> Result<Centroid, GazeError>;
}

/// The seed's solver: back-project through K⁻¹, translate the nominal camera by Δt (rotation
/// kept at R_nom, S11) and intersect the ray with a sphere of radius `eye_radius_m` at the
/// origin. All rig-derived constants are computed once here.
#[derive(Debug, Clone)]
pub struct SphereSolver {
    inv_fx: f64,
    inv_fy: f64,
    cx: f64,
    cy: f64,
    width_px: usize,
    height_px: usize,
    position: Vec3,
    rotation: Mat3,
    radius: f64,
    kappa: Option<[f64; 2]>,
}

impl SphereSolver {
    /// A solver for `rig` (validated here); kappa is not applied.
    pub fn new(rig: &Rig) -> Result<Self, GazeError> {
        rig.validate()?;
        let c = &rig.camera;
        Ok(SphereSolver {
            inv_fx: 1.0 / c.fx_px,
            inv_fy: 1.0 / c.fy_px,
            cx: c.cx_px,
            cy: c.cy_px,
            width_px: c.width_px,
            height_px: c.height_px,
            position: c.position_m,
            rotation: c.rotation_cam_to_world,
            radius: rig.eye_radius_m,
            kappa: None,
        })
    }

    /// Also report the visual axis, rotated from the optical axis by the rig's kappa angles.
    pub fn with_kappa(mut self, rig: &Rig) -> Self {
        self.kappa = Some(rig.kappa_rad);
        self
    }

    /// Unit world ray direction for a pixel (S10 then R_nom), with the unnormalized K⁻¹ vector.
    #[inline]
    fn ray(&self, px: [f64; 2]) -> (Vec3, Vec3, f64) {
        let a = [
            (px[0] - self.cx) * self.inv_fx,
            (px[1] - self.cy) * self.inv_fy,
            1.0,
        ];
        let n = geom::norm(a);
        let d_cam = geom::scale(a, 1.0 / n);
        (geom::mul_mv(&self.rotation, d_cam), d_cam, n)
    }

    /// Smaller positive root of |O + s d|² = R² for unit d, without cancellation (S12–S13).
    #[inline]
    fn intersect(&self, o: Vec3, d: Vec3) -> Result<f64, GazeError> {
        let b = geom::dot(o, d);
        let c = (geom::norm(o) - self.radius) * (geom::norm(o) + self.radius);
        if c.is_nan() || c <= 0.0 {
            return Err(GazeError::CameraInsideSphere {
                distance_m: geom::norm(o),
                radius_m: self.radius,
            });
        }
        let disc = b * b - c;
        // b ≥ 0: the sphere is behind the camera; disc < 0: the ray passes it by.
        if disc.is_nan() || disc < 0.0 || b >= 0.0 {
            return Err(GazeError::RayMissesSphere {
                radius_m: self.radius,
            });
        }
        // Roots −b ± √disc; the near one as c / (−b + √disc) has no cancellation.
        Ok(c / (-b + disc.sqrt()))
    }

    fn check_inputs(px: [f64; 2], slip: Vec3) -> Result<(), GazeError> {
        if !(px[0].is_finite() && px[1].is_finite()) {
            return Err(GazeError::NonFinite {
                what: "pupil pixel",
            });
        }
        if !geom::is_finite(slip) {
            return Err(GazeError::NonFinite { what: "slippage" });
        }
        Ok(())
    }

    /// VJP of [`GazeSolver::solve_pixel`]'s optical-axis gaze: ∂L/∂g in, ∂L/∂pixel and ∂L/∂Δt out.
    pub fn vjp_pixel(
        &self,
        pupil_px: [f64; 2],
        slip_m: Vec3,
        grad_gaze: Vec3,
    ) -> Result<GazeVjp, GazeError> {
        Self::check_inputs(pupil_px, slip_m)?;
        let (d, d_cam, n) = self.ray(pupil_px);
        let o = geom::add(self.position, slip_m);
        let s = self.intersect(o, d)?;
        let p = geom::add(o, geom::scale(d, s));
        let pn = geom::norm(p);
        let g = geom::scale(p, 1.0 / pn);
        // g = P/|P|: P̄ = (I − g gᵀ) ḡ / |P|.
        let pbar = geom::scale(
            geom::sub(grad_gaze, geom::scale(g, geom::dot(g, grad_gaze))),
            1.0 / pn,
        );
        // P = O + s d, and s(O, d) from |O + s d|² = R²: ∂s/∂O = −P/(P·d), ∂s/∂d = −s P/(P·d).
        let pd = geom::dot(p, d);
        let sbar = geom::dot(pbar, d);
        let obar = geom::sub(pbar, geom::scale(p, sbar / pd));
        let dbar = geom::sub(geom::scale(pbar, s), geom::scale(p, sbar * s / pd));
        // d = R d_cam, d_cam = a/|a|, a = ((u − cx)/fx, (v − cy)/fy, 1).
        let dcam_bar = geom::mul_mtv(&self.rotation, dbar);
        let abar = geom::scale(
            geom::sub(dcam_bar, geom::scale(d_cam, geom::dot(d_cam, dcam_bar))),
            1.0 / n,
        );
        Ok(GazeVjp {
            pupil_px: [abar[0] * self.inv_fx, abar[1] * self.inv_fy],
            slip_m: obar,
        })
    }

    /// Centroid of `mask` in camera pixels (S9), checking the mask's shape against the camera.
    pub fn mask_centroid(&self, mask: MatRef<'_, f32>) -> Result<Centroid, GazeError> {
        let k = centroid::mask_scale(mask.ncols(), mask.nrows(), self.width_px, self.height_px)?;
        centroid::centroid(mask, k)
    }

    /// VJP of [`GazeSolver::solve_mask`]: ∂L/∂g in, ∂L/∂M and ∂L/∂Δt out.
    pub fn vjp_mask(
        &self,
        mask: MatRef<'_, f32>,
        slip_m: Vec3,
        grad_gaze: Vec3,
    ) -> Result<(Mat<f32>, Vec3), GazeError> {
        let c = self.mask_centroid(mask)?;
        let v = self.vjp_pixel(c.px, slip_m, grad_gaze)?;
        Ok((
            centroid::centroid_vjp(&c, mask.nrows(), mask.ncols(), v.pupil_px),
            v.slip_m,
        ))
    }
}

impl GazeSolver for SphereSolver {
    #[inline]
    fn solve_pixel(&self, pupil_px: [f64; 2], slip_m: Vec3) -> Result<GazeSolution, GazeError> {
        Self::check_inputs(pupil_px, slip_m)?;
        let (d, _, _) = self.ray(pupil_px);
        let o = geom::add(self.position, slip_m);
        let s = self.intersect(o, d)?;
        let p = geom::add(o, geom::scale(d, s));
        let g = geom::scale(p, 1.0 / geom::norm(p));
        let visual_axis = match self.kappa {
            Some(k) => Some(eye::visual_axis(g, k)?),
            None => None,
        };
        Ok(GazeSolution {
            pupil_px,
            pupil_3d_m: p,
            gaze: g,
            visual_axis,
            ray_length_m: s,
            fallback: false,
        })
    }

    fn mask_centre(&self, mask: MatRef<'_, f32>, how: PupilCentre) -> Result<Centroid, GazeError> {
        let k = centroid::mask_scale(mask.ncols(), mask.nrows(), self.width_px, self.height_px)?;
        pupil::centre(mask, k, how)
    }
}

/// Projects world point `p_m` (m) through `camera`'s intrinsics at `pose` to pixel (u, v).
pub fn project(camera: &Camera, pose: &Pose, p_m: Vec3) -> Result<[f64; 2], GazeError> {
    if !geom::is_finite(p_m) {
        return Err(GazeError::NonFinite { what: "3D point" });
    }
    let q = geom::mul_mtv(&pose.rotation, geom::sub(p_m, pose.position));
    if q[2].is_nan() || q[2] <= 0.0 {
        return Err(GazeError::BehindCamera { depth_m: q[2] });
    }
    Ok([
        camera.fx_px * q[0] / q[2] + camera.cx_px,
        camera.fy_px * q[1] / q[2] + camera.cy_px,
    ])
}

/// Unit world direction of the ray through pixel `px` for a camera at `pose`.
pub fn back_project(camera: &Camera, pose: &Pose, px: [f64; 2]) -> Vec3 {
    let a = [
        (px[0] - camera.cx_px) / camera.fx_px,
        (px[1] - camera.cy_px) / camera.fy_px,
        1.0,
    ];
    geom::mul_mv(&pose.rotation, geom::normalize(a))
}

/// Near intersection (m) of the ray `origin + s·dir` (unit `dir`) with the sphere of radius
/// `radius` about the world origin, or `None` when it misses.
pub fn ray_sphere(origin: Vec3, dir: Vec3, radius: f64) -> Option<Vec3> {
    let b = geom::dot(origin, dir);
    let c = (geom::norm(origin) - radius) * (geom::norm(origin) + radius);
    let disc = b * b - c;
    if !(c > 0.0 && disc >= 0.0 && b < 0.0) {
        return None;
    }
    let s = c / (-b + disc.sqrt());
    Some(geom::add(origin, geom::scale(dir, s)))
}

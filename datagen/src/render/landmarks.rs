//! Ground-truth landmarks: eye centre, pupil centre and corneal apex in world and image space,
//! and the apparent (refracted) pupil centre.

use super::Ray;
use super::RenderError;
use super::material::refract;
use super::prim::{Clip, Shape};
use super::scene::{EyeGeometry, Subject};
use super::trace::pixel_dir;
use crate::states::State;
use nanoeye_gaze::{Camera, Pose, Rig, Vec3, geom, project};
use serde::{Deserialize, Serialize};

/// A 3D landmark and its pinhole projection.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Landmark {
    /// World position (m).
    pub world_m: Vec3,
    /// Pixel (u, v), None when behind the camera.
    pub px: Option<[f64; 2]>,
}

/// The landmarks of one frame.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Landmarks {
    /// Eye rotation centre.
    pub eye_center: Landmark,
    /// True pupil centre (on the rig's pupil sphere).
    pub pupil_center: Landmark,
    /// Corneal apex.
    pub cornea_apex: Landmark,
    /// Pixel whose ray, refracted by the cornea, passes through the pupil centre (the apparent
    /// pupil centre); None when no such ray exists.
    pub pupil_center_refracted_px: Option<[f64; 2]>,
}

/// Computes the landmarks of `state` for a subject in `rig`.
pub fn landmarks(rig: &Rig, state: &State, subject: &Subject) -> Result<Landmarks, RenderError> {
    let geo = EyeGeometry::new(rig, subject)?;
    let pose = state.camera_pose(rig);
    let g = state.gaze();
    let mk = |p: Vec3| Landmark {
        world_m: p,
        px: project(&rig.camera, &pose, p).ok(),
    };
    let pupil = mk(geom::scale(g, geo.pupil_plane_m));
    Ok(Landmarks {
        eye_center: mk([0.0; 3]),
        pupil_center: pupil,
        cornea_apex: mk(geom::scale(g, subject.cornea_apex_m)),
        pupil_center_refracted_px: pupil.px.and_then(|px0| {
            refracted_pupil_px(&rig.camera, &pose, &geo, g, subject.cornea_index, px0)
        }),
    })
}

/// Where the ray through pixel `px` meets the pupil plane after refraction at the cornea, in
/// in-plane coordinates (m) about the pupil centre; None if it misses the cornea.
fn plane_hit(
    camera: &Camera,
    pose: &Pose,
    geo: &EyeGeometry,
    g: Vec3,
    n: f64,
    px: [f64; 2],
    e: (Vec3, Vec3),
) -> Option<[f64; 2]> {
    let ray = Ray::new(pose.position, pixel_dir(camera, pose, px));
    let cornea = Shape::Sphere {
        center: geom::scale(g, geo.cornea_center_m),
        radius_m: geo.cornea_radius_m,
        clip: Clip::Plane {
            normal: g,
            offset_m: geo.pupil_plane_m,
            sign: 1.0,
        },
    };
    let t = cornea.intersect(&ray, f64::INFINITY)?;
    let p = ray.at(t);
    let d = refract(ray.dir, cornea.normal(p), 1.0 / n)?;
    let den = geom::dot(d, g);
    if den.abs() < 1e-12 {
        return None;
    }
    let s = (geo.pupil_plane_m - geom::dot(p, g)) / den;
    let q = geom::sub(
        geom::add(p, geom::scale(d, s)),
        geom::scale(g, geo.pupil_plane_m),
    );
    Some([geom::dot(q, e.0), geom::dot(q, e.1)])
}

/// The apparent pupil centre: Newton iteration (finite-difference Jacobian) on the pixel whose
/// refracted ray passes through the pupil centre, started at the unrefracted projection
/// `px0`. Converges to ≪ 1e-6 px in a few steps for the smooth sphere–plane map.
pub fn refracted_pupil_px(
    camera: &Camera,
    pose: &Pose,
    geo: &EyeGeometry,
    g: Vec3,
    n: f64,
    px0: [f64; 2],
) -> Option<[f64; 2]> {
    let a = if g[0].abs() > 0.9 {
        [0.0, 1.0, 0.0]
    } else {
        [1.0, 0.0, 0.0]
    };
    let e1 = geom::normalize(geom::cross(g, a));
    let e = (e1, geom::cross(g, e1));
    let f = |px: [f64; 2]| plane_hit(camera, pose, geo, g, n, px, e);
    let mut px = px0;
    let h = 1e-3;
    for _ in 0..20 {
        let r = f(px)?;
        let rx = f([px[0] + h, px[1]])?;
        let ry = f([px[0], px[1] + h])?;
        let j = [
            [(rx[0] - r[0]) / h, (ry[0] - r[0]) / h],
            [(rx[1] - r[1]) / h, (ry[1] - r[1]) / h],
        ];
        let det = j[0][0] * j[1][1] - j[0][1] * j[1][0];
        if det == 0.0 || !det.is_finite() {
            return None;
        }
        let dx = (j[1][1] * r[0] - j[0][1] * r[1]) / det;
        let dy = (-j[1][0] * r[0] + j[0][0] * r[1]) / det;
        px = [px[0] - dx, px[1] - dy];
        if dx.abs() + dy.abs() < 1e-9 {
            return Some(px);
        }
    }
    None
}

/// Re-aims the eye of `state` so its refracted pupil centre lands on `target_px` (px): Newton
/// in (azimuth, elevation) with a forward-difference Jacobian, torsion and camera kept. Used
/// to make ambiguity pairs coincide in the rendered image, where the cornea shifts the pupil.
/// `Ok(None)` when the pupil leaves view or Newton does not reach 1e-6 px in 16 steps.
pub fn aim_refracted_pupil(
    rig: &Rig,
    state: &State,
    subject: &Subject,
    target_px: [f64; 2],
) -> Result<Option<State>, RenderError> {
    let px_of = |s: &State| -> Result<Option<[f64; 2]>, RenderError> {
        Ok(landmarks(rig, s, subject)?.pupil_center_refracted_px)
    };
    // 1e-6 rad moves the pupil ≈7e-5 px, far above the 1e-9 px the inner Newton resolves.
    const H: f64 = 1e-6;
    let mut s = *state;
    for _ in 0..16 {
        let Some(p) = px_of(&s)? else {
            return Ok(None);
        };
        let r = [p[0] - target_px[0], p[1] - target_px[1]];
        if r[0].hypot(r[1]) < 1e-6 {
            return Ok(Some(s));
        }
        let pa = px_of(&State {
            azimuth_rad: s.azimuth_rad + H,
            ..s
        })?;
        let pe = px_of(&State {
            elevation_rad: s.elevation_rad + H,
            ..s
        })?;
        let (Some(pa), Some(pe)) = (pa, pe) else {
            return Ok(None);
        };
        let j = [
            [(pa[0] - p[0]) / H, (pe[0] - p[0]) / H],
            [(pa[1] - p[1]) / H, (pe[1] - p[1]) / H],
        ];
        let det = j[0][0] * j[1][1] - j[0][1] * j[1][0];
        if det == 0.0 || !det.is_finite() {
            return Ok(None);
        }
        s.azimuth_rad -= (j[1][1] * r[0] - j[0][1] * r[1]) / det;
        s.elevation_rad -= (-j[1][0] * r[0] + j[0][0] * r[1]) / det;
    }
    Ok(None)
}

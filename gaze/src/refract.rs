//! The refraction-aware solver: the camera sees the pupil through the cornea, so the centroid
//! of the visible pupil is the image of the pupil centre's *virtual* image, which lies in front
//! of the real pupil and moves on neither the pupil sphere nor the eyeball. Instead of
//! intersecting the back-projected ray with a sphere (S12–S13), this solver finds the gaze g
//! for which that ray, refracted at the cornea (a sphere centred on g), passes through the pupil
//! centre g·d (d = the rig's pupil-sphere radius): two equations in the two angles of g, solved
//! by Newton from the unrefracted sphere solution. pye3d corrects the same effect with a
//! regression fitted to synthetic eyes; with an explicit cornea model the correction is exact
//! for the model eye and degrades only with the subject's deviation from it.

use crate::centroid::Centroid;
use crate::error::GazeError;
use crate::eye;
use crate::geom::{self, Mat3, Vec3};
use crate::pupil::PupilCentre;
use crate::rig::Rig;
use crate::solver::{GazeSolution, GazeSolver, SphereSolver, ray_sphere};
use faer::MatRef;
use serde::{Deserialize, Serialize};

/// The cornea the refraction-aware solver looks through: a sphere of radius `radius_m` whose
/// apex lies `apex_m` from the eye's rotation centre on the optical axis, of refractive index
/// `index`; it meets the iris plane at the limbus (oracles.md: 7.8 mm, 13.3 mm, 1.376).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Cornea {
    /// Front-surface radius of curvature (m).
    pub radius_m: f64,
    /// Distance of the corneal apex from the rotation centre (m).
    pub apex_m: f64,
    /// Refractive index (cornea and aqueous, one medium).
    pub index: f64,
}

impl Default for Cornea {
    /// The average eye of oracles.md: radius 7.8 mm, apex 13.3 mm, n = 1.376.
    fn default() -> Self {
        Cornea {
            radius_m: 7.8e-3,
            apex_m: 13.3e-3,
            index: 1.376,
        }
    }
}

impl Cornea {
    /// Checks the cornea against a pupil plane `pupil_plane_m` from the rotation centre: the
    /// apex lies beyond the plane and the sphere reaches the plane (a limbus exists).
    pub fn validate(&self, pupil_plane_m: f64) -> Result<(), GazeError> {
        let bad =
            |field: &'static str, reason: String| Err(GazeError::InvalidRig { field, reason });
        if !(self.radius_m.is_finite() && (1e-3..=0.05).contains(&self.radius_m)) {
            return bad(
                "cornea.radius_m",
                format!(
                    "{} m outside the plausible range [0.001, 0.05] m",
                    self.radius_m
                ),
            );
        }
        if !(self.index.is_finite() && (1.0..3.0).contains(&self.index)) {
            return bad("cornea.index", format!("{} outside [1, 3)", self.index));
        }
        if !(self.apex_m.is_finite() && self.apex_m > pupil_plane_m && self.apex_m < 0.1) {
            return bad(
                "cornea.apex_m",
                format!(
                    "{} m must lie beyond the pupil plane at {pupil_plane_m} m (and below 0.1 m)",
                    self.apex_m
                ),
            );
        }
        let h = pupil_plane_m - (self.apex_m - self.radius_m);
        if h.abs() >= self.radius_m {
            return bad(
                "cornea.radius_m",
                format!(
                    "a {} m cornea with its apex at {} m does not reach the pupil plane at \
                     {pupil_plane_m} m",
                    self.radius_m, self.apex_m
                ),
            );
        }
        Ok(())
    }
}

/// Refraction of unit direction `d` at a surface of unit normal `n` (facing the incoming
/// ray) from index n₁ into n₂, `eta` = n₁/n₂; None on total internal reflection.
#[inline]
fn refract(d: Vec3, n: Vec3, eta: f64) -> Option<Vec3> {
    let cos_i = -geom::dot(n, d);
    let k = 1.0 - eta * eta * (1.0 - cos_i * cos_i);
    if k.is_nan() || k < 0.0 {
        return None;
    }
    Some(geom::add(
        geom::scale(d, eta),
        geom::scale(n, eta * cos_i - k.sqrt()),
    ))
}

/// Newton's stopping step (rad) and iteration cap: the residual map is smooth and Newton
/// converges quadratically, so 1e-12 rad is reached in 3–5 steps from the sphere guess.
const STEP_TOL_RAD: f64 = 1e-12;
const MAX_ITER: usize = 40;
/// Forward-difference step (rad) of the Jacobian: residuals are O(1e-3) m with O(1e-2) m/rad
/// slopes, so 1e-7 rad balances truncation (1e-9 relative) and round-off.
const FD_RAD: f64 = 1e-7;

/// The refraction-aware gaze solver (see the module docs). Kappa is not applied unless
/// [`RefractiveSolver::with_kappa`] asks for it.
#[derive(Debug, Clone)]
pub struct RefractiveSolver {
    /// Unrefracted solver on the pupil sphere: centroid, ray and the Newton start.
    sphere: SphereSolver,
    position: Vec3,
    rotation: Mat3,
    inv_fx: f64,
    inv_fy: f64,
    cx: f64,
    cy: f64,
    pupil_plane_m: f64,
    cornea: Cornea,
    kappa: Option<[f64; 2]>,
}

impl RefractiveSolver {
    /// A solver for `rig` (validated here): pupil centre on the rig's pupil sphere, seen through
    /// the rig's cornea.
    pub fn new(rig: &Rig) -> Result<Self, GazeError> {
        rig.validate()?;
        rig.cornea.validate(rig.pupil_sphere_radius_m)?;
        let sphere_rig = Rig {
            eye_radius_m: rig.pupil_sphere_radius_m,
            ..rig.clone()
        };
        let c = &rig.camera;
        Ok(RefractiveSolver {
            sphere: SphereSolver::new(&sphere_rig)?,
            position: c.position_m,
            rotation: c.rotation_cam_to_world,
            inv_fx: 1.0 / c.fx_px,
            inv_fy: 1.0 / c.fy_px,
            cx: c.cx_px,
            cy: c.cy_px,
            pupil_plane_m: rig.pupil_sphere_radius_m,
            cornea: rig.cornea,
            kappa: None,
        })
    }

    /// Also report the visual axis, rotated from the optical axis by the rig's kappa angles.
    pub fn with_kappa(mut self, rig: &Rig) -> Self {
        self.kappa = Some(rig.kappa_rad);
        self
    }

    /// Where the ray o + t·d, refracted at the cornea of an eye looking along unit `g`, meets
    /// the pupil plane, relative to the pupil centre, in the plane basis (e1, e2) (m); None
    /// when the ray misses the corneal cap in front of the iris plane.
    fn plane_residual(&self, o: Vec3, d: Vec3, g: Vec3, e1: Vec3, e2: Vec3) -> Option<[f64; 2]> {
        let k = &self.cornea;
        let centre = geom::scale(g, k.apex_m - k.radius_m);
        let oc = geom::sub(o, centre);
        let b = geom::dot(oc, d);
        let c = (geom::norm(oc) - k.radius_m) * (geom::norm(oc) + k.radius_m);
        let disc = b * b - c;
        if !(c > 0.0 && disc >= 0.0 && b < 0.0) {
            return None;
        }
        let t = c / (-b + disc.sqrt());
        let p = geom::add(o, geom::scale(d, t));
        if geom::dot(p, g) < self.pupil_plane_m {
            // The ray meets the sphere behind the limbus: sclera, not cornea.
            return None;
        }
        let n = geom::scale(geom::sub(p, centre), 1.0 / k.radius_m);
        let dr = refract(d, n, 1.0 / k.index)?;
        let den = geom::dot(dr, g);
        if den.is_nan() || den >= 0.0 {
            return None;
        }
        let s = (self.pupil_plane_m - geom::dot(p, g)) / den;
        let q = geom::sub(
            geom::add(p, geom::scale(dr, s)),
            geom::scale(g, self.pupil_plane_m),
        );
        Some([geom::dot(q, e1), geom::dot(q, e2)])
    }

    /// Unit world ray through `px`.
    #[inline]
    fn ray(&self, px: [f64; 2]) -> Vec3 {
        let a = [
            (px[0] - self.cx) * self.inv_fx,
            (px[1] - self.cy) * self.inv_fy,
            1.0,
        ];
        geom::mul_mv(&self.rotation, geom::normalize(a))
    }

    /// Newton on the gaze g = normalize(g0 + a·t1 + b·t2) for which the refracted ray through
    /// `px` from `o` passes through the pupil centre.
    fn newton(&self, o: Vec3, d: Vec3, g0: Vec3) -> Result<Vec3, GazeError> {
        let helper = if g0[0].abs() > 0.9 {
            [0.0, 1.0, 0.0]
        } else {
            [1.0, 0.0, 0.0]
        };
        let t1 = geom::normalize(geom::cross(g0, helper));
        let t2 = geom::cross(g0, t1);
        let gaze_at = |a: f64, b: f64| {
            geom::normalize(geom::add(
                g0,
                geom::add(geom::scale(t1, a), geom::scale(t2, b)),
            ))
        };
        // The in-plane basis follows g continuously, so the residual is smooth in (a, b).
        let residual = |a: f64, b: f64| {
            let g = gaze_at(a, b);
            let e1 = geom::normalize(geom::sub(t1, geom::scale(g, geom::dot(t1, g))));
            let e2 = geom::cross(g, e1);
            self.plane_residual(o, d, g, e1, e2)
        };
        let miss = || GazeError::RayMissesCornea {
            radius_m: self.cornea.radius_m,
        };
        let (mut a, mut b) = (0.0f64, 0.0f64);
        let mut r = residual(a, b).ok_or_else(miss)?;
        for _ in 0..MAX_ITER {
            let ra = residual(a + FD_RAD, b).ok_or_else(miss)?;
            let rb = residual(a, b + FD_RAD).ok_or_else(miss)?;
            let j = [
                [(ra[0] - r[0]) / FD_RAD, (rb[0] - r[0]) / FD_RAD],
                [(ra[1] - r[1]) / FD_RAD, (rb[1] - r[1]) / FD_RAD],
            ];
            let det = j[0][0] * j[1][1] - j[0][1] * j[1][0];
            if det == 0.0 || !det.is_finite() {
                return Err(miss());
            }
            let da = (j[1][1] * r[0] - j[0][1] * r[1]) / det;
            let db = (-j[1][0] * r[0] + j[0][0] * r[1]) / det;
            // Halve the step while it leaves the cornea (near the limb the cap is narrow).
            let mut lambda = 1.0;
            let mut next = None;
            for _ in 0..30 {
                let (na, nb) = (a - lambda * da, b - lambda * db);
                if let Some(rn) = residual(na, nb) {
                    next = Some((na, nb, rn));
                    break;
                }
                lambda *= 0.5;
            }
            let (na, nb, rn) = next.ok_or_else(miss)?;
            let step = (na - a).hypot(nb - b);
            (a, b, r) = (na, nb, rn);
            if step < STEP_TOL_RAD {
                return Ok(gaze_at(a, b));
            }
        }
        // Not converged to 1e-12 rad: accept only a residual far below a pupil's size.
        if r[0].hypot(r[1]) < 1e-9 {
            Ok(gaze_at(a, b))
        } else {
            Err(miss())
        }
    }
}

impl GazeSolver for RefractiveSolver {
    fn solve_pixel(&self, pupil_px: [f64; 2], slip_m: Vec3) -> Result<GazeSolution, GazeError> {
        if !(pupil_px[0].is_finite() && pupil_px[1].is_finite()) {
            return Err(GazeError::NonFinite {
                what: "pupil pixel",
            });
        }
        if !geom::is_finite(slip_m) {
            return Err(GazeError::NonFinite { what: "slippage" });
        }
        let o = geom::add(self.position, slip_m);
        let d = self.ray(pupil_px);
        // Start from the unrefracted solution; where the ray misses the pupil sphere (the
        // virtual pupil lies outside it near the limb), from the ray's closest approach.
        let g0 = match ray_sphere(o, d, self.pupil_plane_m) {
            Some(p) => geom::normalize(p),
            None => {
                let t = -geom::dot(o, d);
                let p = geom::add(o, geom::scale(d, t.max(0.0)));
                if geom::norm(p) <= 0.0 {
                    return Err(GazeError::RayMissesCornea {
                        radius_m: self.cornea.radius_m,
                    });
                }
                geom::normalize(p)
            }
        };
        // Where no gaze refracts this ray through the pupil centre (the ray meets sclera: the
        // slippage or the centroid is off by a millimetre near the limb), the unrefracted
        // solution is the nearest estimate; it carries the pupil-sphere solver's bias
        // (docs/gaze.md) and is flagged, not dropped.
        let (g, fallback) = match self.newton(o, d, g0) {
            Ok(g) => (g, false),
            Err(GazeError::RayMissesCornea { .. }) => (g0, true),
            Err(e) => return Err(e),
        };
        let visual_axis = match self.kappa {
            Some(k) => Some(eye::visual_axis(g, k)?),
            None => None,
        };
        let p = geom::scale(g, self.pupil_plane_m);
        Ok(GazeSolution {
            pupil_px,
            pupil_3d_m: p,
            gaze: g,
            visual_axis,
            ray_length_m: geom::norm(geom::sub(p, o)),
            fallback,
        })
    }

    fn mask_centre(&self, mask: MatRef<'_, f32>, how: PupilCentre) -> Result<Centroid, GazeError> {
        self.sphere.mask_centre(mask, how)
    }
}

/// Which geometric solver turns a pupil centre into gaze.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SolverKind {
    /// The paper's S12–S14: the ray meets a sphere of radius `eye_radius_m` (seed: 12 mm).
    Sphere,
    /// Refraction-aware: the ray, refracted at the rig's cornea, passes the pupil centre.
    #[default]
    Refractive,
}

impl SolverKind {
    /// Parses "sphere" or "refractive".
    pub fn parse(s: &str) -> Result<Self, GazeError> {
        match s {
            "sphere" => Ok(SolverKind::Sphere),
            "refractive" => Ok(SolverKind::Refractive),
            // The solver is no rig field ("rig field `solver`" misled; a helper's audit).
            _ => Err(GazeError::InvalidParameter {
                name: "solver",
                reason: format!("unknown solver {s:?}; use sphere or refractive"),
            }),
        }
    }

    /// The name `parse` accepts.
    pub fn name(self) -> &'static str {
        match self {
            SolverKind::Sphere => "sphere",
            SolverKind::Refractive => "refractive",
        }
    }
}

/// The solver of kind `kind` for `rig`.
pub fn solver_for(
    rig: &Rig,
    kind: SolverKind,
) -> Result<Box<dyn GazeSolver + Send + Sync>, GazeError> {
    Ok(match kind {
        SolverKind::Sphere => Box::new(SphereSolver::new(rig)?),
        SolverKind::Refractive => Box::new(RefractiveSolver::new(rig)?),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::solver::project;
    use proptest::prelude::*;

    /// The refraction-aware solver for `rig` and the sphere solver on its pupil sphere.
    fn both_solvers(rig: &Rig) -> (RefractiveSolver, SphereSolver) {
        let s = SphereSolver::new(&Rig {
            eye_radius_m: rig.pupil_sphere_radius_m,
            ..rig.clone()
        })
        .unwrap();
        (RefractiveSolver::new(rig).unwrap(), s)
    }

    /// The two names parse; another is refused as a parameter, not as a rig field.
    #[test]
    fn solver_names_parse_and_another_is_no_rig_field() {
        assert_eq!(SolverKind::parse("sphere").unwrap(), SolverKind::Sphere);
        assert_eq!(
            SolverKind::parse("refractive").unwrap(),
            SolverKind::Refractive
        );
        let e = SolverKind::parse("foo").unwrap_err().to_string();
        assert!(e.starts_with("parameter `solver`: unknown solver"), "{e}");
    }

    /// Without refraction (n = 1) the cornea bends nothing, so the solver must agree with the
    /// sphere solver on the pupil sphere: the closed form S12–S13.
    #[test]
    fn without_refraction_it_is_the_pupil_sphere_solver() {
        let rig = Rig {
            cornea: Cornea {
                index: 1.0,
                ..Cornea::default()
            },
            ..Rig::default()
        };
        let (r, s) = both_solvers(&rig);
        let mut n = 0;
        for az in [-30.0f64, -10.0, 0.0, 15.0, 30.0] {
            for el in [-12.0f64, 0.0, 10.0] {
                let g = eye::gaze_from_angles(az.to_radians(), el.to_radians());
                let slip = [0.5e-3, -1e-3, 0.2e-3];
                let pose = rig.camera.slipped_pose(slip, [0.0; 3]);
                let px = project(
                    &rig.camera,
                    &pose,
                    geom::scale(g, rig.pupil_sphere_radius_m),
                )
                .unwrap();
                let (Ok(a), Ok(b)) = (r.solve_pixel(px, slip), s.solve_pixel(px, slip)) else {
                    continue;
                };
                assert!(geom::norm(geom::sub(a.gaze, b.gaze)) < 1e-9, "{az} {el}");
                // Where the camera sees the pupil centre behind the sphere's limb (docs/gaze.md,
                // visibility) both return the near root instead, identically.
                let p = geom::scale(g, rig.pupil_sphere_radius_m);
                if geom::dot(p, geom::sub(pose.position, p)) > 0.0 {
                    assert!(geom::norm(geom::sub(a.gaze, g)) < 1e-9, "{az} {el}");
                }
                n += 1;
            }
        }
        assert!(n >= 12, "only {n} of 15 points seen through the cornea");
    }

    /// Refraction pulls the apparent pupil towards the camera: at primary gaze the sphere
    /// solver's answer is off by degrees, the refraction-aware one is not.
    #[test]
    fn refraction_matters_at_primary_gaze() {
        let rig = Rig::default();
        let (r, s) = both_solvers(&rig);
        // A pixel a refracted ray from the pupil centre reaches: start from the unrefracted
        // projection and let the solver tell us the gaze it implies; then the two must differ.
        let px = project(
            &rig.camera,
            &rig.camera.slipped_pose([0.0; 3], [0.0; 3]),
            [0.0, 0.0, rig.pupil_sphere_radius_m],
        )
        .unwrap();
        let a = r.solve_pixel(px, [0.0; 3]).unwrap();
        let b = s.solve_pixel(px, [0.0; 3]).unwrap();
        let deg = geom::dot(a.gaze, b.gaze)
            .clamp(-1.0, 1.0)
            .acos()
            .to_degrees();
        assert!(deg > 1.0, "refraction moved the answer by only {deg}°");
    }

    /// Where no gaze refracts the ray through the pupil centre (the ray meets the eye across
    /// the limb: a centroid or a slippage a little off), the answer is the unrefracted
    /// pupil-sphere solution, flagged; the true refracted image of the pupil centre never
    /// falls back.
    #[test]
    fn a_ray_past_the_cornea_falls_back_to_the_pupil_sphere_solution_and_says_so() {
        let rig = Rig::default();
        let (r, s) = both_solvers(&rig);
        let c = &rig.camera;
        let (mut exact, mut fell_back) = (0, 0);
        for i in 0..=40 {
            for j in 0..=40 {
                let px = [
                    c.width_px as f64 * i as f64 / 40.0,
                    c.height_px as f64 * j as f64 / 40.0,
                ];
                let Ok(a) = r.solve_pixel(px, [0.0; 3]) else {
                    continue;
                };
                if !a.fallback {
                    exact += 1;
                    continue;
                }
                fell_back += 1;
                assert!((geom::norm(a.gaze) - 1.0).abs() < 1e-12);
                if let Ok(b) = s.solve_pixel(px, [0.0; 3]) {
                    assert!(geom::norm(geom::sub(a.gaze, b.gaze)) < 1e-12, "{px:?}");
                }
            }
        }
        // Over the whole frame most pixels see skin or sclera, not the cornea.
        assert!(
            fell_back > 0 && exact > 0,
            "{exact} exact, {fell_back} fallbacks"
        );
        // The pupil centre at any gaze within ±80°, projected, is always solved exactly.
        let pose = c.slipped_pose([0.0; 3], [0.0; 3]);
        let mut solved = 0;
        for az in (-80i32..=80).step_by(8) {
            for el in (-80i32..=80).step_by(8) {
                let g = eye::gaze_from_angles((az as f64).to_radians(), (el as f64).to_radians());
                let p = geom::scale(g, rig.pupil_sphere_radius_m);
                if let Ok(px) = project(c, &pose, p)
                    && let Ok(a) = r.solve_pixel(px, [0.0; 3])
                {
                    assert!(!a.fallback, "{az} {el}");
                    solved += 1;
                }
            }
        }
        assert!(solved > 300, "only {solved} of 441 gazes solved");
    }

    #[test]
    fn a_bad_cornea_is_named() {
        for (c, field) in [
            (
                Cornea {
                    radius_m: f64::NAN,
                    ..Cornea::default()
                },
                "cornea.radius_m",
            ),
            (
                Cornea {
                    index: 0.5,
                    ..Cornea::default()
                },
                "cornea.index",
            ),
            (
                Cornea {
                    apex_m: 5e-3,
                    ..Cornea::default()
                },
                "cornea.apex_m",
            ),
            (
                Cornea {
                    radius_m: 1.2e-3,
                    ..Cornea::default()
                },
                "cornea.radius_m",
            ),
        ] {
            let rig = Rig {
                cornea: c,
                ..Rig::default()
            };
            match RefractiveSolver::new(&rig) {
                Err(GazeError::InvalidRig { field: f, .. }) => assert_eq!(f, field),
                other => panic!("{c:?}: {other:?}"),
            }
        }
    }

    proptest! {
        /// Any pixel over (and beyond) the image, any slippage up to ±5 mm, any plausible
        /// cornea: a unit gaze vector or an error, never a NaN or a panic.
        #[test]
        fn any_pixel_gives_a_unit_gaze_or_an_error(
            u in -200.0f64..520.0,
            v in -200.0f64..400.0,
            sx in -5e-3f64..5e-3,
            sy in -5e-3f64..5e-3,
            sz in -5e-3f64..5e-3,
            radius in 7.0e-3f64..8.6e-3,
            index in 1.0f64..1.6,
        ) {
            let rig = Rig {
                cornea: Cornea { radius_m: radius, index, ..Cornea::default() },
                ..Rig::default()
            };
            let r = RefractiveSolver::new(&rig).unwrap();
            if let Ok(s) = r.solve_pixel([u, v], [sx, sy, sz]) {
                prop_assert!((geom::norm(s.gaze) - 1.0).abs() < 1e-12);
                prop_assert!(s.ray_length_m.is_finite() && s.ray_length_m > 0.0);
            }
        }
    }
}

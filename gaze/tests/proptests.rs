//! Property tests: extreme but legal inputs give a finite answer or the documented error.

use faer::Mat;
use nanoeye_gaze::{GazeError, GazeSolver, Rig, SphereSolver, angular_error, eye, geom, project};
use proptest::prelude::*;

fn finite_solution_or_documented(r: Result<nanoeye_gaze::GazeSolution, GazeError>) {
    match r {
        Ok(sol) => {
            assert!(geom::is_finite(sol.gaze) && geom::is_finite(sol.pupil_3d_m));
            assert!((geom::norm(sol.gaze) - 1.0).abs() < 1e-12);
            assert!(sol.ray_length_m.is_finite() && sol.ray_length_m > 0.0);
        }
        Err(
            GazeError::RayMissesSphere { .. }
            | GazeError::CameraInsideSphere { .. }
            | GazeError::NonFinite { .. },
        ) => {}
        Err(e) => panic!("undocumented error {e}"),
    }
}

proptest! {
    #[test]
    fn any_pixel_any_slip(u in -1e4f64..1e4, v in -1e4f64..1e4,
                          tx in -0.05f64..0.05, ty in -0.05f64..0.05, tz in -0.05f64..0.05) {
        let rig = Rig::default();
        let solver = SphereSolver::new(&rig).unwrap();
        finite_solution_or_documented(solver.solve_pixel([u, v], [tx, ty, tz]));
    }

    #[test]
    fn grazing_rays(az in -1.5f64..1.5, el in -1.5f64..1.5, eps in -1e-9f64..1e-9) {
        // Aim the ray at a point on the sphere's silhouette (tangent), nudged by eps.
        let rig = Rig::default();
        let solver = SphereSolver::new(&rig).unwrap();
        let o = rig.camera.position_m;
        let r = rig.eye_radius_m;
        let on = geom::normalize(o);
        let mut t = geom::cross(on, eye::gaze_from_angles(az, el));
        if geom::norm(t) < 1e-6 { t = geom::cross(on, [1.0, 0.0, 0.0]); }
        let t = geom::normalize(t);
        let dist = geom::norm(o);
        // Tangent point: at angle acos(r/dist) from the camera direction, in the (on, t) plane.
        let c = r / dist * (1.0 + eps);
        let s = (1.0 - c * c).max(0.0).sqrt();
        let p = geom::add(geom::scale(on, r * c), geom::scale(t, r * s));
        if let Ok(px) = project(&rig.camera, &rig.camera.nominal_pose(), p) {
            finite_solution_or_documented(solver.solve_pixel(px, [0.0; 3]));
        }
    }

    #[test]
    fn one_pixel_masks(row in 0usize..200, col in 0usize..320, val in 1e-6f32..1e6) {
        let rig = Rig::default();
        let solver = SphereSolver::new(&rig).unwrap();
        let mut m = Mat::<f32>::zeros(200, 320);
        m[(row, col)] = val;
        let c = solver.mask_centroid(m.as_ref()).unwrap();
        prop_assert_eq!(c.px, [col as f64 + 0.5, row as f64 + 0.5]);
        finite_solution_or_documented(solver.solve_mask(m.as_ref(), [0.0; 3]));
    }

    #[test]
    fn full_masks_give_image_centre(val in 1e-6f32..1e6) {
        let rig = Rig::default();
        let solver = SphereSolver::new(&rig).unwrap();
        let m = Mat::<f32>::from_fn(50, 80, |_, _| val);
        let c = solver.mask_centroid(m.as_ref()).unwrap();
        prop_assert!((c.px[0] - 160.0).abs() < 1e-9 && (c.px[1] - 100.0).abs() < 1e-9);
        finite_solution_or_documented(solver.solve_mask(m.as_ref(), [0.0; 3]));
    }

    #[test]
    fn round_trip_under_extreme_slip(az in -0.6f64..0.78, el in -0.26f64..0.26,
                                     tx in -0.01f64..0.01, ty in -0.02f64..0.01, tz in -0.01f64..0.02) {
        let mut rig = Rig::default();
        rig.eye_radius_m = rig.pupil_sphere_radius_m;
        let solver = SphereSolver::new(&rig).unwrap();
        let slip = [tx, ty, tz];
        let g = eye::gaze_from_angles(az, el);
        if let Ok(px) = project(&rig.camera, &rig.camera.translated_pose(slip), rig.pupil_center(g)) {
            match solver.solve_pixel(px, slip) {
                // The near intersection can be the other side of the eye only when the pupil is
                // hidden from the camera; a visible pupil must round-trip exactly.
                Ok(sol) => {
                    let d = geom::sub(rig.pupil_center(g), geom::add(rig.camera.position_m, slip));
                    let visible = geom::dot(d, g) < 0.0;
                    if visible {
                        prop_assert!(angular_error(sol.gaze, g) < 1e-8);
                    }
                }
                Err(e) => {
                    let documented = matches!(e, GazeError::CameraInsideSphere { .. } | GazeError::RayMissesSphere { .. });
                    prop_assert!(documented, "undocumented error {}", e);
                }
            }
        }
    }
}

//! Round trips, closed forms and finite-difference checks of the gaze solver.

use faer::Mat;
use nanoeye_gaze::{GazeError, GazeSolver, Rig, SphereSolver, angular_error, eye, geom, project};

fn solver_rig() -> Rig {
    // Solve on the same sphere the pupil moves on, so round trips are exact.
    let mut rig = Rig::default();
    rig.eye_radius_m = rig.pupil_sphere_radius_m;
    rig
}

const SLIPS: [[f64; 3]; 4] = [
    [0.0, 0.0, 0.0],
    [1.5e-3, -2.0e-3, 0.7e-3],
    [-3e-3, 1e-3, 4e-3],
    [0.0, -8e-3, 5e-3],
];

#[test]
fn pixel_gaze_pixel_round_trip() {
    let rig = solver_rig();
    let solver = SphereSolver::new(&rig).unwrap();
    let cam = &rig.camera;
    let mut solved = 0;
    for slip in SLIPS {
        let pose = cam.translated_pose(slip);
        for i in 0..=32 {
            for j in 0..=20 {
                let px = [i as f64 * 10.0, j as f64 * 10.0];
                let Ok(sol) = solver.solve_pixel(px, slip) else {
                    continue;
                };
                solved += 1;
                assert!((geom::norm(sol.pupil_3d_m) - rig.eye_radius_m).abs() < 1e-15);
                let back = project(cam, &pose, sol.pupil_3d_m).unwrap();
                let err = (back[0] - px[0]).hypot(back[1] - px[1]);
                assert!(err < 1e-9, "slip {slip:?} px {px:?}: {err} px");
            }
        }
    }
    // The 10.4 mm sphere at ≈26.5 mm subtends ≈23° half-angle, a disc of ≈70 px radius on
    // the 166.7 px focal length: ≈15 000 px², about 140 of the 33×21 grid
    // points per slip.
    assert!(solved > 400, "only {solved} pixels hit the eye");
}

#[test]
fn gaze_pixel_gaze_round_trip() {
    let rig = solver_rig();
    let solver = SphereSolver::new(&rig).unwrap();
    let cam = &rig.camera;
    let (mut visible, mut hidden) = (0, 0);
    for slip in SLIPS {
        let pose = cam.translated_pose(slip);
        for az in (-35..=45).step_by(10) {
            for el in (-15..=15).step_by(5) {
                let g = eye::gaze_from_angles((az as f64).to_radians(), (el as f64).to_radians());
                let p = rig.pupil_center(g);
                // A pupil beyond the sphere's limb as this camera sees it (p·(O − p) ≤ 0) is
                // not the near root of S13: the geometry cannot recover it, so skip it.
                if geom::dot(p, geom::sub(pose.position, p)) <= 0.0 {
                    hidden += 1;
                    continue;
                }
                let px = project(cam, &pose, p).unwrap();
                let sol = solver.solve_pixel(px, slip).unwrap();
                let err = angular_error(sol.gaze, g);
                assert!(err < 1e-9, "az {az} el {el} slip {slip:?}: {err} rad");
                visible += 1;
            }
        }
    }
    // The camera sits low and to the −x side: only gazes far up and to +x hide the pupil.
    assert!(visible > 4 * hidden, "{visible} visible vs {hidden} hidden");
}

#[test]
fn unknown_slip_biases_gaze() {
    // The round trip is exact only with the right Δt: a 2 mm slip ignored costs degrees,
    // which is what the calibration head is for.
    let rig = solver_rig();
    let solver = SphereSolver::new(&rig).unwrap();
    let slip = [0.0, -2e-3, 0.0];
    let g = eye::gaze_from_angles(-0.1, -0.05);
    let px = project(
        &rig.camera,
        &rig.camera.translated_pose(slip),
        rig.pupil_center(g),
    )
    .unwrap();
    let wrong = solver.solve_pixel(px, [0.0; 3]).unwrap();
    assert!(angular_error(wrong.gaze, g).to_degrees() > 3.0);
}

#[test]
fn listing_torsion_matches_closed_form() {
    // oracles.md: |tan(ψ/2)| = |tan(H/2) tan(V/2)|, with published values.
    for (h, v, psi) in [
        (20.0, 20.0, 3.5616),
        (30.0, 30.0, 8.2132),
        (10.0, 20.0, 1.7676),
        (40.0, 30.0, 11.1404),
    ] {
        let t = eye::listing_torsion(f64::to_radians(h), f64::to_radians(v))
            .unwrap()
            .to_degrees();
        assert!((t.abs() - psi).abs() < 5e-5, "({h},{v}): {t} vs {psi}");
        let closed =
            2.0 * ((h / 2.0f64).to_radians().tan() * (v / 2.0f64).to_radians().tan()).atan();
        assert!((t.abs() - closed.to_degrees()).abs() < 1e-10);
    }
    // Pure horizontal or vertical gaze has no torsion; diagonal quadrants alternate in sign.
    assert!(eye::listing_torsion(0.4, 0.0).unwrap().abs() < 1e-15);
    assert!(eye::listing_torsion(0.0, 0.3).unwrap().abs() < 1e-15);
    let a = eye::listing_torsion(0.3, 0.2).unwrap();
    let b = eye::listing_torsion(-0.3, 0.2).unwrap();
    assert!((a + b).abs() < 1e-15 && a.abs() > 1e-3);
}

#[test]
fn pixel_vjp_matches_finite_differences() {
    let rig = Rig::default();
    let solver = SphereSolver::new(&rig).unwrap();
    let px = [170.3, 60.7];
    let slip = [0.8e-3, -1.1e-3, 0.4e-3];
    let w = [0.3, -0.8, 0.5];
    let loss = |px: [f64; 2], t: [f64; 3]| geom::dot(solver.solve_pixel(px, t).unwrap().gaze, w);
    let v = solver.vjp_pixel(px, slip, w).unwrap();
    let h = 1e-4;
    for k in 0..2 {
        let (mut p1, mut p2) = (px, px);
        p1[k] += h;
        p2[k] -= h;
        let fd = (loss(p1, slip) - loss(p2, slip)) / (2.0 * h);
        assert!(
            (fd - v.pupil_px[k]).abs() < 1e-7 * (1.0 + fd.abs()),
            "px[{k}]: {fd} vs {}",
            v.pupil_px[k]
        );
    }
    let h = 1e-8;
    for k in 0..3 {
        let (mut t1, mut t2) = (slip, slip);
        t1[k] += h;
        t2[k] -= h;
        let fd = (loss(px, t1) - loss(px, t2)) / (2.0 * h);
        assert!(
            (fd - v.slip_m[k]).abs() < 1e-5 * (1.0 + fd.abs()),
            "slip[{k}]: {fd} vs {}",
            v.slip_m[k]
        );
    }
}

#[test]
fn mask_vjp_matches_finite_differences() {
    let rig = Rig::default();
    let solver = SphereSolver::new(&rig).unwrap();
    // A soft disc at a quarter of the camera resolution (80×50 for a 320×200 image).
    let (h, w) = (50, 80);
    let mask = Mat::<f32>::from_fn(h, w, |i, j| {
        let r = ((i as f32 - 18.0).powi(2) + (j as f32 - 44.0).powi(2)).sqrt();
        // A 0.01 floor (a segmenter is never exactly zero) keeps ±eps inside the legal range.
        0.01 + 1.0 / (1.0 + (r - 5.0).exp())
    });
    let slip = [0.0, 1e-3, 0.0];
    let wv = [1.0, 0.5, -0.25];
    let (grad, _) = solver.vjp_mask(mask.as_ref(), slip, wv).unwrap();
    let loss = |m: &Mat<f32>| geom::dot(solver.solve_mask(m.as_ref(), slip).unwrap().gaze, wv);
    let eps = 5e-3f32;
    for (i, j) in [(18, 44), (15, 40), (20, 49), (0, 0)] {
        let mut p = mask.clone();
        p[(i, j)] += eps;
        let mut m = mask.clone();
        m[(i, j)] -= eps;
        let fd = (loss(&p) - loss(&m)) / (2.0 * eps as f64);
        let an = grad[(i, j)] as f64;
        assert!(
            (fd - an).abs() < 2e-3 * an.abs().max(1e-6),
            "({i},{j}): {fd} vs {an}"
        );
    }
}

#[test]
fn documented_errors() {
    let rig = Rig::default();
    let solver = SphereSolver::new(&rig).unwrap();
    assert!(matches!(
        solver.solve_pixel([f64::NAN, 1.0], [0.0; 3]),
        Err(GazeError::NonFinite { .. })
    ));
    assert!(matches!(
        solver.solve_pixel([100.0, 100.0], [f64::INFINITY, 0.0, 0.0]),
        Err(GazeError::NonFinite { .. })
    ));
    // The top-left corner looks past the eye.
    assert!(matches!(
        solver.solve_pixel([0.0, 0.0], [0.0; 3]),
        Err(GazeError::RayMissesSphere { .. })
    ));
    // A slip that puts the camera inside the eye.
    let inside = geom::scale(rig.camera.position_m, -1.0);
    assert!(matches!(
        solver.solve_pixel([160.0, 100.0], inside),
        Err(GazeError::CameraInsideSphere { .. })
    ));
    let empty = Mat::<f32>::zeros(200, 320);
    assert!(matches!(
        solver.solve_mask(empty.as_ref(), [0.0; 3]),
        Err(GazeError::EmptyMask { .. })
    ));
    let odd = Mat::<f32>::ones(100, 100);
    assert!(matches!(
        solver.solve_mask(odd.as_ref(), [0.0; 3]),
        Err(GazeError::MaskShape { .. })
    ));
}

#[test]
fn default_rig_sees_the_pupil_over_table_s2() {
    // The nominal camera must see the pupil for every Table S2 gaze, or the data are useless.
    let rig = Rig::default();
    let pose = rig.camera.nominal_pose();
    for az in (-35..=45).step_by(5) {
        for el in (-15..=15).step_by(5) {
            let g = eye::gaze_from_angles((az as f64).to_radians(), (el as f64).to_radians());
            let px = project(&rig.camera, &pose, rig.pupil_center(g)).unwrap();
            assert!(
                (0.0..320.0).contains(&px[0]) && (0.0..200.0).contains(&px[1]),
                "az {az} el {el}: {px:?}"
            );
        }
    }
}

#[test]
fn rig_json_round_trip_and_validation() {
    let rig = Rig::default();
    let text = serde_json::to_string(&rig).unwrap();
    assert_eq!(Rig::from_json(&text).unwrap(), rig);
    let mut bad: serde_json::Value = serde_json::from_str(&text).unwrap();
    bad["camera"]["fx_px"] = serde_json::json!(100.0);
    let err = Rig::from_json(&bad.to_string()).unwrap_err();
    assert!(matches!(
        err,
        GazeError::InvalidRig {
            field: "camera.fx_px",
            ..
        }
    ));
    // The nominal camera sits at pupil_primary + (−10, −14, +10) mm and looks at the origin.
    let c = &rig.camera;
    let expect = [-10e-3, -14e-3, rig.pupil_sphere_radius_m + 10e-3];
    assert!(geom::norm(geom::sub(c.position_m, expect)) < 1e-15);
    let axis = geom::mul_mv(&c.rotation_cam_to_world, [0.0, 0.0, 1.0]);
    assert!(angular_error(axis, geom::scale(c.position_m, -1.0)) < 1e-12);
}

#[test]
fn kappa_rotates_visual_axis_by_kappa() {
    let rig = Rig {
        kappa_rad: [5f64.to_radians(), 1.5f64.to_radians()],
        ..Rig::default()
    };
    let solver = SphereSolver::new(&rig).unwrap().with_kappa(&rig);
    let sol = solver.solve_pixel([170.0, 60.0], [0.0; 3]).unwrap();
    let v = sol.visual_axis.unwrap();
    let expect = angular_error(
        [0.0, 0.0, 1.0],
        eye::gaze_from_angles(rig.kappa_rad[0], rig.kappa_rad[1]),
    );
    assert!((angular_error(sol.gaze, v) - expect).abs() < 1e-12);
}

#[test]
fn pupil_sphere_bias_vanishes_at_the_true_radius_and_grows_away_from_it() {
    use nanoeye_gaze::bias::{GazeGrid, pupil_sphere_bias};
    let rig = Rig::default();
    let grid = GazeGrid::table_s2(21);
    let exact = pupil_sphere_bias(&rig, rig.pupil_sphere_radius_m, &grid).unwrap();
    let e = exact.error_deg.unwrap();
    assert!(e.max < 1e-9, "bias at the true radius: {} deg", e.max);
    assert_eq!(exact.missed, 0);
    // Only gazes far up and towards +x put the pupil beyond the limb for this camera.
    assert!(exact.hidden < exact.in_view / 5);
    let mean = |r_mm: f64| {
        pupil_sphere_bias(&rig, r_mm * 1e-3, &grid)
            .unwrap()
            .error_deg
            .unwrap()
            .mean
    };
    // Solving on a larger sphere intersects the ray nearer the camera, a growing bias.
    let (m11, m12, m13) = (mean(11.0), mean(12.0), mean(13.0));
    assert!(0.0 < m11 && m11 < m12 && m12 < m13, "{m11} {m12} {m13}");
}

#[test]
fn eye_equivalent_slip_is_the_slip_without_rotation_and_zero_for_a_turn_about_the_eye() {
    let cam = Rig::default().camera;
    for slip in SLIPS {
        assert_eq!(cam.eye_equivalent_slip(slip, [0.0; 3]), slip);
    }
    // The nominal camera carried round the eye centre by W: a gaze rotation in disguise.
    for w in [[0.02, -0.01, 0.03], [-0.3, 0.2, 0.1], [0.0, 0.0, 1e-7]] {
        let wm = geom::rot_from_vector(w);
        let slip = geom::sub(geom::mul_mv(&wm, cam.position_m), cam.position_m);
        let eq = cam.eye_equivalent_slip(slip, w);
        assert!(geom::norm(eq) < 1e-17, "w {w:?}: {eq:?}");
    }
}

/// A camera turned about its own centre, solved with S11's translation only: given the
/// eye-equivalent translation the solver returns the gaze turned back by exactly the camera's
/// rotation (so it errs by at most that angle); given the physical translation it errs by more.
#[test]
fn the_eye_equivalent_slip_costs_the_solver_at_most_the_rotation_angle() {
    let rig = solver_rig();
    let solver = SphereSolver::new(&rig).unwrap();
    let cam = &rig.camera;
    let mut worse = 0;
    let mut n = 0;
    for (k, w) in [
        [0.014, -0.002, 0.022],
        [-0.01, 0.008, 0.0],
        [0.0, 0.03, -0.01],
    ]
    .into_iter()
    .enumerate()
    {
        let wm = geom::rot_from_vector(w);
        let slip = SLIPS[k + 1];
        let pose = cam.slipped_pose(slip, w);
        for az in [-20.0f64, 0.0, 15.0] {
            for el in [-10.0f64, 5.0, 20.0] {
                let g = eye::gaze_from_angles(az.to_radians(), el.to_radians());
                let px = project(cam, &pose, rig.pupil_center(g)).unwrap();
                let eq = solver
                    .solve_pixel(px, cam.eye_equivalent_slip(slip, w))
                    .unwrap();
                let turned = geom::mul_mtv(&wm, g);
                assert!(
                    angular_error(eq.gaze, turned) < 1e-9,
                    "w {w:?} ({az}, {el})"
                );
                assert!(angular_error(eq.gaze, g) <= geom::norm(w) + 1e-12);
                n += 1;
                let phys = solver
                    .solve_pixel(px, slip)
                    .map(|s| angular_error(s.gaze, g));
                if phys.map_or(true, |e| e > angular_error(eq.gaze, g)) {
                    worse += 1;
                }
            }
        }
    }
    assert!(
        worse * 10 >= n * 9,
        "the physical translation did better on {} of {n}",
        n - worse
    );
}

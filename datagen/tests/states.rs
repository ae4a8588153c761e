//! State sampling: TRUNCNORM moments and bounds, set invariants, determinism.

use nanoeye_datagen::states::sets::item_rng;
use nanoeye_datagen::states::{self, Protocol, TableS2, TruncNormal};
use nanoeye_gaze::{Rig, angular_error, geom};
use proptest::prelude::*;

/// Sample mean and variance agree with the analytic moments within 4 standard errors.
fn check_moments(d: &TruncNormal, n: usize, seed: u64) {
    let mut rng = item_rng(seed, 99, 0);
    let xs: Vec<f64> = (0..n).map(|_| d.sample(&mut rng)).collect();
    let (lo, hi) = d.bounds();
    assert!(
        xs.iter().all(|x| (lo..=hi).contains(x)),
        "sample left [{lo}, {hi}]"
    );
    let nf = n as f64;
    let mean = xs.iter().sum::<f64>() / nf;
    let m2 = xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (nf - 1.0);
    let m4 = xs.iter().map(|x| (x - mean).powi(4)).sum::<f64>() / nf;
    let (mu, var) = (d.mean(), d.variance());
    let se_mean = (var / nf).sqrt();
    let se_var = ((m4 - m2 * m2) / nf).sqrt();
    assert!(
        (mean - mu).abs() < 4.0 * se_mean,
        "{d:?}: mean {mean} vs {mu} (se {se_mean})"
    );
    assert!(
        (m2 - var).abs() < 4.0 * se_var,
        "{d:?}: var {m2} vs {var} (se {se_var})"
    );
}

#[test]
fn table_s2_moments() {
    let t = TableS2::paper();
    for (i, d) in [
        t.azimuth,
        t.elevation,
        t.torsion,
        t.slip_anchor,
        t.slip_extra,
    ]
    .iter()
    .enumerate()
    {
        check_moments(d, 40_000, i as u64);
    }
}

#[test]
fn far_tail_moments() {
    // One-sided windows deep in the tails, where CDF inversion would lose every digit.
    for (i, (a, b)) in [
        (8.0, 9.0),
        (8.0, f64::INFINITY),
        (-12.0, -8.0),
        (30.0, 31.0),
        (0.0, 0.01),
    ]
    .into_iter()
    .enumerate()
    {
        let d = TruncNormal::new(1.0, 2.0, 1.0 + 2.0 * a, 1.0 + 2.0 * b).unwrap();
        check_moments(&d, 40_000, 100 + i as u64);
    }
    // Past erfc's range the analytic moments are not computable, but samples still obey bounds.
    let d = TruncNormal::new(0.0, 1.0, 60.0, 61.0).unwrap();
    let mut rng = item_rng(7, 7, 7);
    for _ in 0..1000 {
        let x = d.sample(&mut rng);
        assert!((60.0..=61.0).contains(&x));
    }
}

#[test]
fn invalid_parameters_are_errors() {
    assert!(TruncNormal::new(0.0, 0.0, -1.0, 1.0).is_err());
    assert!(TruncNormal::new(0.0, 1.0, 1.0, 1.0).is_err());
    assert!(TruncNormal::new(0.0, 1.0, 2.0, 1.0).is_err());
    assert!(TruncNormal::new(f64::NAN, 1.0, -1.0, 1.0).is_err());
    assert!(TruncNormal::new(0.0, 1.0, f64::NAN, 1.0).is_err());
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]
    #[test]
    fn bounds_at_eight_sigma(mu in -1e3f64..1e3, sigma in 1e-6f64..1e3, a in -8.0f64..8.0, w in 1e-6f64..16.0, seed: u64) {
        let b = (a + w).min(8.0);
        prop_assume!(b > a);
        let d = TruncNormal::new(mu, sigma, mu + a * sigma, mu + b * sigma).unwrap();
        let mut rng = item_rng(seed, 0, 0);
        for _ in 0..64 {
            let x = d.sample(&mut rng);
            prop_assert!(x.is_finite() && x >= mu + a * sigma && x <= mu + b * sigma);
        }
        prop_assert!(d.mean().is_finite() && d.variance().is_finite() && d.variance() >= 0.0);
    }
}

#[test]
fn ambiguity_pairs_coincide_in_pixel() {
    let rig = Rig::default();
    let pairs = states::ambiguity(&rig, 200, 3).unwrap();
    for p in &pairs {
        let du = p.pupil_px_slip[0] - p.pupil_px_gaze[0];
        let dv = p.pupil_px_slip[1] - p.pupil_px_gaze[1];
        assert!(du.hypot(dv) < 1e-6, "pixels differ by {}", du.hypot(dv));
        // Recompute from the states alone, not the stored pixels.
        let a = p.slip.pupil_px(&rig).unwrap();
        let b = p.gaze.pupil_px(&rig).unwrap();
        assert!((a[0] - b[0]).hypot(a[1] - b[1]) < 1e-6);
        // The gaze member keeps the anchor's camera; the slip member keeps the anchor's eye.
        assert_eq!(p.gaze.slip_m, p.anchor.slip_m);
        assert_eq!(p.slip.azimuth_rad, p.anchor.azimuth_rad);
        // The extra slip moves the camera along the bridge by 0.2–5 mm.
        let extra = geom::norm(geom::sub(p.slip.slip_m, p.anchor.slip_m));
        assert!((0.2e-3 - 1e-12..=5e-3 + 1e-12).contains(&extra), "{extra}");
        // And the matched eye really is rotated.
        assert!(angular_error(p.gaze.gaze(), p.anchor.gaze()) > 0.0);
    }
}

#[test]
fn variational_triplets_stay_local() {
    let rig = Rig::default();
    for t in states::variational(&rig, 100, 5).unwrap() {
        let ds = geom::norm(geom::sub(t.slip_plus.slip_m, t.anchor.slip_m));
        assert!((0.1e-3 - 1e-12..=0.3e-3 + 1e-12).contains(&ds));
        let dp = geom::norm(geom::sub(
            t.gaze_plus.pupil_center(&rig),
            t.anchor.pupil_center(&rig),
        ));
        assert!(dp < 0.31e-3, "gaze+ moves the pupil {dp} m");
        assert_eq!(t.gaze_plus.slip_m, t.anchor.slip_m);
    }
}

#[test]
fn protocol_layout() {
    let rig = Rig::default();
    let p = Protocol::default();
    let caps = states::protocol(&rig, &p, 2, 0).unwrap();
    assert_eq!(caps.len(), 2 * 7 * 49);
    // Grid extremes: ±12.5° horizontally, −12.5°…22.5° vertically (35° shifted up by 5°).
    let az: Vec<f64> = caps.iter().map(|c| c.target_deg[0]).collect();
    let el: Vec<f64> = caps.iter().map(|c| c.target_deg[1]).collect();
    let (amin, amax) = az
        .iter()
        .fold((f64::MAX, f64::MIN), |(a, b), &x| (a.min(x), b.max(x)));
    let (emin, emax) = el
        .iter()
        .fold((f64::MAX, f64::MIN), |(a, b), &x| (a.min(x), b.max(x)));
    assert!((amin + 12.5).abs() < 1e-9 && (amax - 12.5).abs() < 1e-9);
    assert!((emin + 12.5).abs() < 1e-9 && (emax - 22.5).abs() < 1e-9);
    // The line of sight from the eye centre through the pupil hits the target.
    for c in caps.iter().take(49) {
        let g = c.state.gaze();
        let z = rig.pupil_sphere_radius_m + p.distance_m;
        let hit = [g[0] / g[2] * z, g[1] / g[2] * z];
        let want = [
            p.distance_m * c.target_deg[0].to_radians().tan(),
            p.distance_m * c.target_deg[1].to_radians().tan(),
        ];
        assert!((hit[0] - want[0]).abs() < 1e-12 && (hit[1] - want[1]).abs() < 1e-12);
    }
    // Seven stage states, 2.5 mm apart.
    let slips = p.slip_states();
    assert_eq!(slips.len(), 7);
    assert!((geom::norm(slips[1]) - 2.5e-3).abs() < 1e-15);
}

/// A camera turned to face away from the eye (180° about its y axis) sees no pupil: the rig is
/// refused, and so every set (protocol accepted it, and `run` rendered its training set first).
#[test]
fn a_camera_facing_away_has_no_set() {
    let mut rig = Rig::default();
    for row in rig.camera.rotation_cam_to_world.iter_mut() {
        row[0] = -row[0];
        row[2] = -row[2];
    }
    let e = rig.validate().unwrap_err().to_string();
    assert!(e.contains("faces away"), "{e}");
    let p = Protocol::default();
    assert!(states::protocol(&rig, &p, 1, 0).is_err());
    assert!(states::ambiguity(&rig, 1, 0).is_err());
    assert!(states::variational(&rig, 1, 0).is_err());
    // A camera behind the eye, facing its centre: a valid rig, but the pupil is turned away
    // in every capture.
    let mut behind = Rig::default();
    let c = &behind.camera;
    behind.camera = nanoeye_gaze::Camera::look_at(
        c.focal_length_m,
        c.pixel_pitch_m,
        c.width_px,
        c.height_px,
        [0.0, 0.01, -0.05],
        [0.0, 0.0, 0.0],
    )
    .unwrap();
    behind.validate().unwrap();
    let e = states::protocol(&behind, &p, 1, 0).unwrap_err().to_string();
    assert!(e.contains("visible in none"), "{e}");
    // The default rig sees the pupil in every protocol capture.
    let ok = Rig::default();
    assert!(states::protocol(&ok, &p, 1, 0).is_ok());
}

#[test]
fn same_seed_same_items_on_any_thread_count() {
    let rig = Rig::default();
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let a = serde_json::to_string(&states::ambiguity(&rig, 64, 11).unwrap()).unwrap();
            let v = serde_json::to_string(&states::variational(&rig, 64, 11).unwrap()).unwrap();
            let p = serde_json::to_string(
                &states::protocol(&rig, &Protocol::default(), 3, 11).unwrap(),
            )
            .unwrap();
            (a, v, p)
        })
    };
    assert_eq!(run(1), run(4));
    assert_ne!(run(1).0, {
        serde_json::to_string(&states::ambiguity(&rig, 64, 12).unwrap()).unwrap()
    });
}

//! Physics checks of the sensor: photon transfer, energy bookkeeping, determinism, VJP.

use faer::Mat;
use nanoeye_sensor::{CmosSensor, NoiseMode, Sensor, SensorConfig, SensorError, photon_transfer};
use proptest::prelude::*;

#[test]
fn photon_transfer_slope_and_intercept_match_gain_and_read_noise() {
    for quantize in [true, false] {
        let cfg = SensorConfig {
            quantize,
            ..SensorConfig::default()
        };
        let r = photon_transfer(&cfg, 16, 128, 11).unwrap();
        assert!(
            (r.slope - r.slope_expected).abs() < 4.0 * r.slope_se,
            "slope {} vs {} ± {}",
            r.slope,
            r.slope_expected,
            r.slope_se
        );
        assert!(
            (r.intercept - r.intercept_expected).abs() < 4.0 * r.intercept_se,
            "intercept {} vs {} ± {}",
            r.intercept,
            r.intercept_expected,
            r.intercept_se
        );
        // The check has teeth: the standard errors are small against the quantities tested.
        assert!(r.slope_se < 0.01 * r.slope_expected);
        assert!(r.intercept_se < 0.2 * r.intercept_expected);
    }
}

#[test]
fn noise_free_output_is_gain_times_qe_times_integrated_photons() {
    let cfg = SensorConfig {
        noise: NoiseMode::None,
        quantize: false,
        ..SensorConfig::default()
    };
    let s = CmosSensor::new(cfg.clone()).unwrap();
    // 1 µm samples, 3 µm base pitch: 1000 photons per base-pixel area → 1000 per 3 µm pixel.
    let img = Mat::from_fn(30, 30, |_, _| 1000.0f32);
    let (dn, _) = s.forward(&img, 1e-6, 3e-6, 0, 0).unwrap();
    assert_eq!((dn.nrows(), dn.ncols()), (10, 10));
    let want = cfg.black_level_dn + cfg.gain_dn_per_e * cfg.quantum_efficiency * 1000.0;
    assert!((f64::from(dn[(4, 4)]) - want).abs() < 1e-3 * want);
    // 9 µm binning: κ = 9, nine times the photons.
    let (dn9, _) = s.forward(&img, 1e-6, 9e-6, 0, 0).unwrap();
    let want9 = cfg.black_level_dn + cfg.gain_dn_per_e * cfg.quantum_efficiency * 9000.0;
    assert!((f64::from(dn9[(1, 1)]) - want9).abs() < 1e-3 * want9);
}

#[test]
fn same_seed_same_image_other_seed_other_image() {
    let s = CmosSensor::new(SensorConfig::default()).unwrap();
    let img = Mat::from_fn(24, 24, |i, j| 200.0 + (i * j) as f32);
    let (a, _) = s.forward(&img, 3e-6, 3e-6, 5, 9).unwrap();
    let (b, _) = s.forward(&img, 3e-6, 3e-6, 5, 9).unwrap();
    let (c, _) = s.forward(&img, 3e-6, 3e-6, 5, 10).unwrap();
    assert_eq!(a, b);
    assert_ne!(a, c);
}

#[test]
fn saturation_clips_at_full_well_and_adc_range() {
    let cfg = SensorConfig::default();
    let s = CmosSensor::new(cfg.clone()).unwrap();
    let img = Mat::from_fn(8, 8, |_, _| 1e7f32);
    let (dn, tape) = s.forward(&img, 3e-6, 3e-6, 1, 1).unwrap();
    for j in 0..8 {
        for i in 0..8 {
            assert!(f64::from(dn[(i, j)]) <= cfg.max_dn());
        }
    }
    // Saturated pixels pass no gradient.
    let g = s.vjp(&tape, &Mat::from_fn(8, 8, |_, _| 1.0)).unwrap();
    assert_eq!(g.d_image[(3, 3)], 0.0);
}

fn loss(s: &CmosSensor, img: &Mat<f32>, dx: f64, p: f64, w: &Mat<f32>) -> f64 {
    let (dn, _) = s.forward(img, dx, p, 3, 4).unwrap();
    let mut acc = 0.0;
    for j in 0..dn.ncols().min(w.ncols()) {
        for i in 0..dn.nrows().min(w.nrows()) {
            acc += f64::from(w[(i, j)]) * f64::from(dn[(i, j)]);
        }
    }
    acc
}

#[test]
fn vjp_matches_finite_differences_through_reparameterized_noise() {
    // Gaussian (reparameterized) noise, no rounding: the forward map is smooth at fixed seed.
    let cfg = SensorConfig {
        noise: NoiseMode::Gaussian,
        quantize: false,
        ..SensorConfig::default()
    };
    let s = CmosSensor::new(cfg).unwrap();
    let dx = 1e-6;
    // 3.3 µm keeps every pixel edge ≥ 0.1 sample from a kink of the piecewise-linear map.
    let p = 3.3e-6;
    let img = Mat::from_fn(21, 17, |i, j| 300.0 + 40.0 * ((i * 3 + j * 5) % 7) as f32);
    let (dn, tape) = s.forward(&img, dx, p, 3, 4).unwrap();
    let w = Mat::from_fn(dn.nrows(), dn.ncols(), |i, j| {
        ((i + 2 * j) % 5) as f32 - 2.0
    });
    let g = s.vjp(&tape, &w).unwrap();
    let h = 1e-8;
    let fd = (loss(&s, &img, dx, p + h, &w) - loss(&s, &img, dx, p - h, &w)) / (2.0 * h);
    assert!(
        (fd - g.d_p_hat).abs() < 2e-2 * fd.abs().max(1e3),
        "p̂: {fd} vs {}",
        g.d_p_hat
    );
    for &(r, c) in &[(2, 3), (10, 8), (18, 14)] {
        let mut a = img.clone();
        let mut b = img.clone();
        a[(r, c)] += 20.0;
        b[(r, c)] -= 20.0;
        let fd = (loss(&s, &a, dx, p, &w) - loss(&s, &b, dx, p, &w)) / 40.0;
        let an = f64::from(g.d_image[(r, c)]);
        assert!(
            (fd - an).abs() < 1e-2 * an.abs().max(1e-3),
            "({r},{c}): {fd} vs {an}"
        );
    }
}

#[test]
fn the_pitch_only_vjp_gives_the_vjps_bits() {
    // A non-integer pitch (fractional box edges) and a gradient with zeros (the skipped
    // terms): ∂L/∂p̂ alone is the full VJP's, bit for bit, and refuses what it refuses.
    let s = CmosSensor::new(SensorConfig {
        noise: NoiseMode::Gaussian,
        quantize: false,
        ..SensorConfig::default()
    })
    .unwrap();
    let img = Mat::from_fn(23, 19, |i, j| 200.0 + 37.0 * ((i * 7 + j * 3) % 11) as f32);
    let (dn, tape) = s.forward(&img, 1e-6, 2.7e-6, 5, 6).unwrap();
    let w = Mat::from_fn(dn.nrows(), dn.ncols(), |i, j| {
        ((i * 5 + j) % 4) as f32 * 0.3 - 0.45
    });
    let g = s.vjp(&tape, &w).unwrap();
    assert!(g.d_p_hat != 0.0);
    assert_eq!(
        s.pitch_vjp(&tape, &w).unwrap().to_bits(),
        g.d_p_hat.to_bits()
    );
    let bad = Mat::<f32>::zeros(dn.nrows() + 1, dn.ncols());
    assert!(s.vjp(&tape, &bad).is_err() && s.pitch_vjp(&tape, &bad).is_err());
    let nan = Mat::from_fn(dn.nrows(), dn.ncols(), |_, _| f32::NAN);
    assert!(s.vjp(&tape, &nan).is_err() && s.pitch_vjp(&tape, &nan).is_err());
}

#[test]
fn errors_name_the_parameter() {
    let bad = SensorConfig {
        quantum_efficiency: 1.5,
        ..SensorConfig::default()
    };
    match CmosSensor::new(bad) {
        Err(SensorError::InvalidParameter { name, .. }) => assert_eq!(name, "quantum_efficiency"),
        other => panic!("{other:?}"),
    }
    let s = CmosSensor::new(SensorConfig::default()).unwrap();
    let mut img = Mat::from_fn(9, 9, |_, _| 1.0f32);
    img[(2, 2)] = f32::NAN;
    assert!(matches!(
        s.forward(&img, 1e-6, 3e-6, 0, 0),
        Err(SensorError::InvalidImage { .. })
    ));
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(32))]
    #[test]
    fn extreme_inputs_give_finite_bounded_output(
        level in prop_oneof![Just(0.0f32), 1e-30f32..1e-3, 1e-3f32..1e9],
        p_um in 1.0f64..12.0,
        seed in any::<u64>(),
    ) {
        let cfg = SensorConfig::default();
        let s = CmosSensor::new(cfg.clone()).unwrap();
        let img = Mat::from_fn(24, 24, |_, _| level);
        let (dn, tape) = s.forward(&img, 1e-6, p_um * 1e-6, seed, 0).unwrap();
        let g = s.vjp(&tape, &Mat::from_fn(dn.nrows(), dn.ncols(), |_, _| 1.0)).unwrap();
        prop_assert!(g.d_p_hat.is_finite());
        for j in 0..dn.ncols() { for i in 0..dn.nrows() {
            let v = f64::from(dn[(i, j)]);
            prop_assert!(v.is_finite() && v >= 0.0 && v <= cfg.max_dn());
        }}
        for j in 0..24 { for i in 0..24 { prop_assert!(g.d_image[(i, j)].is_finite()); } }
    }
}

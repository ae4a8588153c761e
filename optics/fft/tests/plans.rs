//! The plans `Planner` hands out, checked against the DFT's closed forms. An integration test,
//! not unit tests: a unit-test build compiles this crate a second time, and with it all of
//! rustfft's f32 and f64 code at opt-level 3 (75 s on the 2-core VM), the cost the crate exists
//! to pay once.

use nanoeye_fft::num_complex::Complex;
use nanoeye_fft::{FftDirection, Float, Planner};
use std::sync::Arc;

/// A complex exponential of frequency k0 transforms to len at bin k0 and 0 elsewhere, and the
/// inverse of the transform is len times the input, for lengths of several kinds: 1, powers of
/// two, mixed radices (160, 360), primes (7, 83, 97) and a large prime factor (423 = 9 × 47).
fn delta_and_round_trip<T: Float + Into<f64>>(tol: f64) {
    let mut planner = Planner::<T>::new();
    for len in [1usize, 7, 83, 97, 160, 360, 423, 1024] {
        let k0 = 5 % len;
        let (fwd, inv) = (planner.plan_fft_forward(len), planner.plan_fft_inverse(len));
        assert_eq!((fwd.len(), inv.len()), (len, len));
        assert_eq!(fwd.fft_direction(), FftDirection::Forward);
        assert_eq!(inv.fft_direction(), FftDirection::Inverse);
        let x: Vec<Complex<T>> = (0..len)
            .map(|n| {
                let a = std::f64::consts::TAU * (k0 * n) as f64 / len as f64;
                Complex::new(T::from_f64(a.cos()).unwrap(), T::from_f64(a.sin()).unwrap())
            })
            .collect();
        let mut y = x.clone();
        fwd.process(&mut y);
        for (k, v) in y.iter().enumerate() {
            let want = if k == k0 { len as f64 } else { 0.0 };
            let (re, im): (f64, f64) = (v.re.into(), v.im.into());
            assert!(
                (re - want).abs() < tol * len as f64 && im.abs() < tol * len as f64,
                "len {len} bin {k}: {re} + {im}i, want {want}"
            );
        }
        inv.process(&mut y);
        for (a, b) in x.iter().zip(&y) {
            let (ar, ai): (f64, f64) = (a.re.into(), a.im.into());
            let (br, bi): (f64, f64) = (b.re.into(), b.im.into());
            assert!((br - len as f64 * ar).abs() < tol * len as f64);
            assert!((bi - len as f64 * ai).abs() < tol * len as f64);
        }
    }
}

#[test]
fn f64_plans_give_the_dft_and_its_inverse() {
    delta_and_round_trip::<f64>(1e-12);
}

#[test]
fn f32_plans_give_the_dft_and_its_inverse() {
    delta_and_round_trip::<f32>(2e-5);
}

#[test]
fn a_length_planned_twice_is_the_same_plan() {
    let mut planner = Planner::<f32>::new();
    let (a, b) = (planner.plan_fft_forward(360), planner.plan_fft_forward(360));
    assert!(Arc::ptr_eq(&a, &b));
}

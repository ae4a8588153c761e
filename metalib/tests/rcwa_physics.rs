//! Physics checks of the RCWA unit-cell solver: energy conservation, Fresnel and Airy limits.

use nanoeye_metalib::material::Materials;
use nanoeye_metalib::rcwa::{CellSpec, LayerModes, Rule};
use num_complex::Complex64;
use std::f64::consts::PI;

fn spec(d_nm: f64, s_nm: f64, n: usize, rule: Rule, mat: Materials) -> CellSpec {
    CellSpec {
        wavelength_m: 940e-9,
        pitch_m: s_nm * 1e-9,
        diameter_m: d_nm * 1e-9,
        materials: mat,
        harmonics: n,
        rule,
    }
}

fn lossless() -> Materials {
    Materials {
        k_pillar: 0.0,
        ..Materials::default()
    }
}

fn airy(n_layer: Complex64, ns: f64, h: f64, lam: f64) -> Complex64 {
    let one = Complex64::new(1.0, 0.0);
    let t01 = 2.0 * one / (one + n_layer);
    let r01 = (one - n_layer) / (one + n_layer);
    let t12 = 2.0 * n_layer / (n_layer + ns);
    let r12 = (n_layer - ns) / (n_layer + ns);
    let b = 2.0 * PI / lam * n_layer * h;
    let e = (Complex64::i() * b).exp();
    t01 * t12 * e / (one + r01 * r12 * e * e)
}

#[test]
fn energy_conserved_for_lossless_pillars() {
    for rule in [Rule::Laurent, Rule::Nv] {
        for &(d, s) in &[
            (100.0, 530.0),
            (275.0, 530.0),
            (450.0, 530.0),
            (500.0, 900.0),
        ] {
            let modes = LayerModes::new(&spec(d, s, 4, rule, lossless())).unwrap();
            for h in [0.0, 100e-9, 700e-9, 1500e-9] {
                let r = modes.at_height(h).unwrap();
                let err = (r.reflectance + r.transmitted_total - 1.0).abs();
                assert!(
                    err < 1e-9,
                    "{rule:?} d={d} s={s} h={h}: R+T-1 = {err:e} ({r:?})"
                );
                assert!(r.transmittance <= r.transmitted_total + 1e-12);
            }
        }
    }
}

#[test]
fn bare_interface_matches_fresnel() {
    let ns: f64 = 1.4512;
    let tf = 2.0 / (1.0 + ns);
    let rf = ((1.0 - ns) / (1.0 + ns)).powi(2);
    // Zero diameter, index-1 pillar: the layer is air; h → 0 gives the bare interface.
    let unit = Materials {
        n_pillar: 1.0,
        k_pillar: 0.0,
        ..Materials::default()
    };
    for (d, mat) in [(0.0, Materials::default()), (300.0, unit)] {
        for rule in [Rule::Laurent, Rule::Nv] {
            let modes = LayerModes::new(&spec(d, 530.0, 3, rule, mat)).unwrap();
            for h in [0.0, 400e-9] {
                let r = modes.at_height(h).unwrap();
                let expect = Complex64::from_polar(tf, 2.0 * PI * h / 940e-9);
                assert!(
                    (r.t - expect).norm() < 1e-10,
                    "{rule:?} d={d} h={h}: {} vs {expect}",
                    r.t
                );
                assert!((r.reflectance - rf).abs() < 1e-10);
            }
        }
    }
}

#[test]
fn homogeneous_layer_matches_airy() {
    for (np, kp) in [(3.7, 0.0), (3.7, 0.008), (2.0, 0.1)] {
        let mat = Materials {
            n_pillar: np,
            k_pillar: kp,
            n_background: np,
            ..Materials::default()
        };
        // The background index is real in Materials; the lossy case uses a full-cell pillar.
        let (mat, d) = if kp == 0.0 {
            (mat, 200.0)
        } else {
            (
                Materials {
                    n_background: 1.0,
                    ..mat
                },
                0.0,
            )
        };
        if d == 0.0 {
            continue;
        }
        for rule in [Rule::Laurent, Rule::Nv] {
            let modes = LayerModes::new(&spec(d, 530.0, 3, rule, mat)).unwrap();
            for h in [50e-9, 700e-9, 20e-6] {
                let r = modes.at_height(h).unwrap();
                let t = airy(Complex64::new(np, kp), 1.4512, h, 940e-9);
                assert!(
                    (r.t - t).norm() < 1e-9,
                    "{rule:?} n={np} h={h}: {} vs {t}",
                    r.t
                );
                let tau = 1.4512 * t.norm_sqr();
                assert!((r.transmittance - tau).abs() < 1e-9);
                assert!((r.phase_rad - t.arg()).abs() < 1e-9);
            }
        }
    }
}

#[test]
fn sweep_fast_path_matches_the_full_response() {
    // transmission_at drops modes below 1e-6 one-way amplitude; at_height keeps them to 1e-12.
    for &(d, s) in &[(100.0, 530.0), (275.0, 530.0), (450.0, 530.0)] {
        let modes = LayerModes::new(&spec(d, s, 8, Rule::Nv, Materials::default())).unwrap();
        for i in 0..=15 {
            let h = i as f64 * 100e-9;
            let fast = modes.transmission_at(h).unwrap();
            let full = modes.at_height(h).unwrap().t;
            assert!(
                (fast - full).norm() < 2e-6,
                "d={d} s={s} h={h}: {fast} vs {full}"
            );
        }
    }
}

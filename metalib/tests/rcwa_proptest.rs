//! Stability proptests of the RCWA solver: extreme but legal inputs stay finite and
//! energy-bounded; illegal inputs are errors.

use nanoeye_metalib::material::Materials;
use nanoeye_metalib::rcwa::{CellSpec, LayerModes, Rule};
use proptest::prelude::*;

fn spec(d: f64, s: f64, k: f64, rule: Rule) -> CellSpec {
    CellSpec {
        wavelength_m: 940e-9,
        pitch_m: s,
        diameter_m: d,
        materials: Materials {
            k_pillar: k,
            ..Materials::default()
        },
        harmonics: 2,
        rule,
    }
}

fn check(spec: &CellSpec, h: f64) -> Result<(), TestCaseError> {
    let r = LayerModes::new(spec)
        .map_err(|e| TestCaseError::fail(e.to_string()))?
        .at_height(h)
        .map_err(|e| TestCaseError::fail(e.to_string()))?;
    prop_assert!(r.t.re.is_finite() && r.t.im.is_finite());
    prop_assert!(r.reflectance >= -1e-9 && r.transmitted_total >= -1e-9);
    prop_assert!(r.reflectance + r.transmitted_total <= 1.0 + 1e-8, "{r:?}");
    prop_assert!(r.transmittance <= r.transmitted_total + 1e-9);
    if spec.materials.k_pillar == 0.0 {
        prop_assert!(
            (r.reflectance + r.transmitted_total - 1.0).abs() < 1e-8,
            "{r:?}"
        );
    }
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]

    #[test]
    fn extreme_geometries_are_finite_and_bounded(
        s in 100e-9f64..1000e-9,
        frac in prop_oneof![0.0f64..1e-3, 0.999f64..=1.0, 0.0f64..=1.0],
        k in prop_oneof![Just(0.0f64), 0.0f64..2.0],
        h in prop_oneof![Just(20e-6f64), 0.0f64..2e-6, Just(0.0f64)],
        nv in any::<bool>(),
    ) {
        let rule = if nv { Rule::Nv } else { Rule::Laurent };
        check(&spec(frac * s, s, k, rule), h)?;
    }

    #[test]
    fn illegal_inputs_are_errors(
        s in 100e-9f64..1000e-9,
        excess in 1.001f64..3.0,
        bad in prop_oneof![Just(f64::NAN), Just(f64::INFINITY), -1e-6f64..-1e-12],
    ) {
        prop_assert!(LayerModes::new(&spec(excess * s, s, 0.0, Rule::Nv)).is_err());
        prop_assert!(LayerModes::new(&spec(bad, s, 0.0, Rule::Nv)).is_err());
        prop_assert!(LayerModes::new(&spec(0.5 * s, bad, 0.0, Rule::Nv)).is_err());
        prop_assert!(LayerModes::new(&spec(0.5 * s, s, bad, Rule::Nv)).is_err());
        let m = LayerModes::new(&spec(0.5 * s, s, 0.0, Rule::Nv)).unwrap();
        prop_assert!(m.at_height(bad).is_err());
    }
}

/// Degenerate eigenvalues: a homogeneous layer (pillar index = background index) has
/// degenerate (Ex/Ey, ±m/±n) mode families; the result must still be the exact thin film.
#[test]
fn degenerate_modes_give_the_homogeneous_film() {
    let mat = Materials {
        n_pillar: 2.0,
        k_pillar: 0.0,
        n_background: 2.0,
        ..Materials::default()
    };
    let s = CellSpec {
        wavelength_m: 940e-9,
        pitch_m: 900e-9,
        diameter_m: 400e-9,
        materials: mat,
        harmonics: 3,
        rule: Rule::Nv,
    };
    let r = LayerModes::new(&s).unwrap().at_height(20e-6).unwrap();
    assert!((r.reflectance + r.transmitted_total - 1.0).abs() < 1e-9);
    assert!(r.t.norm().is_finite());
}

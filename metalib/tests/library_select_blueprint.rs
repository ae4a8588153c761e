//! Library inversion, selection criteria, blueprint/GDSII and sweep round trips.

use nanoeye_metalib::blueprint::{self, BlueprintOptions, gds_real8};
use nanoeye_metalib::library::{PillarLibrary, TabulatedLibrary};
use nanoeye_metalib::material::Materials;
use nanoeye_metalib::rcwa::{CellSpec, LayerModes, Rule};
use nanoeye_metalib::select::{Criteria, select_curve, unwrap};
use nanoeye_metalib::sweep::{self, Range, SweepConfig};
use std::f64::consts::PI;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};

fn linear_lib(span: f64) -> TabulatedLibrary {
    let d: Vec<f64> = (0..=40).map(|i| (100.0 + 5.0 * i as f64) * 1e-9).collect();
    // Phase wrapped into (−π, π] to exercise the unwrapping.
    let p: Vec<f64> = (0..=40)
        .map(|i| (span * i as f64 / 40.0 + PI).rem_euclid(2.0 * PI) - PI)
        .collect();
    TabulatedLibrary::new(700e-9, 530e-9, 940e-9, d, &p, vec![0.8; 41], 1.4512).unwrap()
}

#[test]
fn phase_to_diameter_round_trip() {
    let lib = linear_lib(2.2 * PI);
    for k in 0..50 {
        let target = -PI + 2.0 * PI * k as f64 / 50.0;
        let d = lib.diameter_for_phase(target).unwrap();
        let got = lib.response(d).unwrap().arg();
        let err = ((got - target + PI).rem_euclid(2.0 * PI) - PI).abs();
        assert!(err < 1e-9, "target {target}: realised {got}");
        assert!((lib.transmittance(d).unwrap() - 1.4512 * 0.64).abs() < 1e-12);
    }
}

#[test]
fn partial_coverage_snaps_to_nearest_end_and_range_is_checked() {
    let lib = linear_lib(PI); // covers [0, π] only (first sample phase 0)
    let (lo, hi) = lib.diameter_range_m();
    assert_eq!(lib.diameter_for_phase(-0.1).unwrap(), lo);
    assert_eq!(lib.diameter_for_phase(PI + 0.1).unwrap(), hi);
    assert!(lib.response(hi * 1.01).is_err());
    assert!(lib.response(f64::NAN).is_err());
    assert!(lib.diameter_for_phase(f64::INFINITY).is_err());
}

#[test]
fn non_monotonic_or_bad_data_is_rejected() {
    let d = vec![100e-9, 110e-9, 120e-9];
    assert!(
        TabulatedLibrary::new(
            7e-7,
            5e-7,
            9e-7,
            d.clone(),
            &[0.0, 0.5, 0.2],
            vec![1.0; 3],
            1.0
        )
        .is_err()
    );
    assert!(
        TabulatedLibrary::new(
            7e-7,
            5e-7,
            9e-7,
            vec![1e-7, 1e-7, 2e-7],
            &[0.0, 0.5, 0.9],
            vec![1.0; 3],
            1.0
        )
        .is_err()
    );
    assert!(
        TabulatedLibrary::new(
            7e-7,
            5e-7,
            9e-7,
            d,
            &[0.0, f64::NAN, 0.9],
            vec![1.0; 3],
            1.0
        )
        .is_err()
    );
    let csv = "diameter_nm,phase_rad,transmittance\n100,0.0,0.95\n150,1.0,0.95\n200,2.0,0.92\n";
    let lib = TabulatedLibrary::from_csv(csv, 7e-7, 5e-7, 9.4e-7, 1.4512).unwrap();
    assert!((lib.diameter_for_phase(1.5).unwrap() - 175e-9).abs() < 1e-15);
    assert!((lib.transmittance(150e-9).unwrap() - 0.95).abs() < 1e-12);
    assert!(TabulatedLibrary::from_csv("100,0,0.9\n150,x,0.9\n", 7e-7, 5e-7, 9.4e-7, 1.0).is_err());
    // Rows outside physical ranges (an audit: each was accepted and reached the blueprint),
    // and a first line that is no header, are refused naming the line.
    for (bad, line) in [
        ("100,0,0.9\n150,1,2.0\n", "line 2"),
        ("100,0,0.9\n150,1e308,0.9\n", "line 2"),
        ("1e-308,0,0.9\n150,1,0.9\n", "line 1"),
        ("a,b,c\n100,0,0.9\n150,1,0.9\n", "line 1"),
    ] {
        let e = TabulatedLibrary::from_csv(bad, 7e-7, 5e-7, 9.4e-7, 1.0)
            .err()
            .unwrap_or_else(|| panic!("{bad:?} accepted"))
            .to_string();
        assert!(e.contains(line), "{bad:?}: {e}");
    }
}

#[test]
fn selection_criteria() {
    let d: Vec<f64> = (0..=100).map(|i| (100.0 + 2.0 * i as f64) * 1e-9).collect();
    // 7 rad over 200 nm: 2.0°/nm, well below 9°/nm.
    let phase: Vec<f64> = (0..=100)
        .map(|i| (7.0 * i as f64 / 100.0 + PI).rem_euclid(2.0 * PI) - PI)
        .collect();
    let mut tau = vec![0.95; 101];
    let c = Criteria::default();
    let s = select_curve(7e-7, 5.3e-7, &d, &phase, &tau, &c);
    assert!(s.viable && (s.phase_coverage_rad - 7.0).abs() < 1e-9);
    assert!((s.diameter_min_m - 100e-9).abs() < 1e-15 && (s.diameter_max_m - 300e-9).abs() < 1e-15);
    // One rejected diameter in the middle (200 nm) removes 195..205 nm and splits the run.
    tau[50] = 0.5;
    let s = select_curve(7e-7, 5.3e-7, &d, &phase, &tau, &c);
    assert!(!s.viable);
    assert!((s.diameter_max_m - 194e-9).abs() < 1e-15 || (s.diameter_min_m - 206e-9).abs() < 1e-15);
    // 0.2 rad per 2 nm (5.7°/nm) is admissible; 0.4 rad per 2 nm (11.5°/nm) is not.
    let ok: Vec<f64> = (0..=100).map(|i| 0.2 * i as f64).collect();
    let s = select_curve(7e-7, 5.3e-7, &d, &ok, &[0.95; 101], &c);
    assert!(
        s.viable && (s.phase_coverage_rad - 20.0).abs() < 1e-9,
        "{s:?}"
    );
    let steep: Vec<f64> = (0..=100).map(|i| 0.4 * i as f64).collect();
    let s = select_curve(7e-7, 5.3e-7, &d, &steep, &[0.95; 101], &c);
    assert!(!s.viable && s.phase_coverage_rad == 0.0, "{s:?}");
    assert_eq!(unwrap(&[3.0, -3.0]), vec![3.0, 2.0 * PI - 3.0]);
}

#[test]
fn gdsii_stream_structure() {
    // real8 of 1e-10 and 1e-4 decode back.
    for x in [1e-10, 1e-4, 1.0, 0.0625] {
        let b = gds_real8(x);
        let e = (b[0] & 0x7f) as i32 - 64;
        let mut m = 0u64;
        for &v in &b[1..] {
            m = (m << 8) | v as u64;
        }
        let back = m as f64 / 2f64.powi(56) * 16f64.powi(e);
        assert!((back - x).abs() <= 1e-15 * x.abs().max(1e-300));
    }
    let lib = linear_lib(2.2 * PI);
    let phase: Vec<f64> = (0..25)
        .map(|k| (k as f64 * 0.7).rem_euclid(2.0 * PI) - PI)
        .collect();
    let opt = BlueprintOptions {
        circle_vertices: 16,
        ..Default::default()
    };
    let bp = blueprint::invert_phase_map(&lib, &phase, 5, 5, &opt).unwrap();
    // Inscribed circle of a 5×5 map (radius 2.5 sites) keeps 21 of 25 sites.
    assert_eq!(bp.pillars, 21);
    // 1 nm diameter grid on a 5 nm sampled linear library: error ≤ slope·0.5 nm.
    let slope = 2.2 * PI / 200e-9;
    assert!(
        bp.max_phase_error_rad <= slope * 0.5e-9 + 1e-9,
        "{}",
        bp.max_phase_error_rad
    );
    let gds = blueprint::gdsii(&bp, 530e-9, &opt).unwrap();
    let (mut pos, mut boundaries, mut xy_points) = (0, 0, Vec::new());
    while pos + 4 <= gds.len() {
        let len = u16::from_be_bytes([gds[pos], gds[pos + 1]]) as usize;
        let kind = gds[pos + 2];
        if kind == 0x08 {
            boundaries += 1;
        }
        if kind == 0x10 {
            xy_points.push((len - 4) / 8);
        }
        pos += len;
    }
    assert_eq!(pos, gds.len());
    assert_eq!(boundaries, 21);
    assert!(xy_points.iter().all(|&n| n == 17));
}

#[test]
fn sweep_matches_direct_solves_and_round_trips_npy() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = SweepConfig {
        heights_m: Range {
            start: 300e-9,
            stop: 700e-9,
            step: 400e-9,
        },
        pitches_m: Range {
            start: 400e-9,
            stop: 530e-9,
            step: 130e-9,
        },
        fractions: Range {
            start: 0.2,
            stop: 0.6,
            step: 0.2,
        },
        harmonics: 2,
        rule: Rule::Nv,
        ..Default::default()
    };
    let m = sweep::run_sweep(&cfg, dir.path(), &|_, _| {}).unwrap();
    assert_eq!(m.shape, [2, 2, 3]);
    assert_eq!(m.failed_cells, 0);
    let data = sweep::load_sweep(dir.path()).unwrap();
    let spec = CellSpec {
        wavelength_m: 940e-9,
        pitch_m: 530e-9,
        diameter_m: 0.4 * 530e-9,
        materials: Materials::default(),
        harmonics: 2,
        rule: Rule::Nv,
    };
    let modes = LayerModes::new(&spec).unwrap();
    let k = data.idx(1, 1, 1);
    // The sweep stores exactly the fast path's value...
    let t = modes.transmission_at(700e-9).unwrap();
    assert!((data.phase[k] - t.arg()).abs() < 1e-12);
    assert!((data.transmittance[k] - modes.transmittance_of(t)).abs() < 1e-12);
    // ...which keeps modes down to 1e-6 one-way amplitude instead of the full solve's 1e-12.
    let r = modes.at_height(700e-9).unwrap();
    assert!((data.phase[k] - r.phase_rad).abs() < 1e-5);
    assert!((data.transmittance[k] - r.transmittance).abs() < 1e-5);
    // Re-running on a complete directory with the same parameters solves nothing: every cell
    // comes back restored and the arrays are the same; others are refused.
    let counts = |cfg: &SweepConfig| {
        let (solved, restored) = (AtomicU64::new(0), AtomicU64::new(0));
        let m = sweep::run_sweep(cfg, dir.path(), &|n, r| {
            if r { &restored } else { &solved }.fetch_add(n, Relaxed);
        })
        .unwrap();
        (m, solved.into_inner(), restored.into_inner())
    };
    let cells = data.phase.len() as u64;
    let (again, solved, restored) = counts(&cfg);
    assert_eq!((solved, restored), (0, cells));
    assert_eq!(again.shape, m.shape);
    let back = sweep::load_sweep(dir.path()).unwrap();
    assert_eq!(back.phase, data.phase);
    // A complete manifest whose arrays are gone is not trusted: the sweep is solved again.
    std::fs::remove_file(dir.path().join("t_im.npy")).unwrap();
    let (_, solved, restored) = counts(&cfg);
    assert_eq!((solved, restored), (cells, 0));
    assert_eq!(sweep::load_sweep(dir.path()).unwrap().t_im, data.t_im);
    let other = SweepConfig {
        harmonics: 3,
        ..cfg
    };
    assert!(sweep::run_sweep(&other, dir.path(), &|_, _| {}).is_err());
}

/// The CLI builds ranges as nm × 1e-9; a resumed sweep compares them with the manifest's copy,
/// so JSON must give back the exact f64 (serde_json's default parser was 1 ulp off for
/// 500 × 1e-9 and refused to resume).
#[test]
fn sweep_ranges_survive_the_manifest_exactly_so_a_sweep_resumes() {
    for nm in 1..=2000 {
        let v = nm as f64 * 1e-9;
        let back: f64 = serde_json::from_str(&serde_json::to_string(&v).unwrap()).unwrap();
        assert_eq!(back.to_bits(), v.to_bits(), "{nm} nm");
    }
    let dir = tempfile::tempdir().unwrap();
    let cfg = SweepConfig {
        heights_m: Range {
            start: 700.0 * 1e-9,
            stop: 700.0 * 1e-9,
            step: 10.0 * 1e-9,
        },
        pitches_m: Range {
            start: 500.0 * 1e-9,
            stop: 510.0 * 1e-9,
            step: 10.0 * 1e-9,
        },
        fractions: Range {
            start: 0.3,
            stop: 0.3,
            step: 0.005,
        },
        harmonics: 1,
        rule: Rule::Nv,
        ..Default::default()
    };
    sweep::run_sweep(&cfg, dir.path(), &|_, _| {}).unwrap();
    assert!(sweep::run_sweep(&cfg, dir.path(), &|_, _| {}).is_ok());
}

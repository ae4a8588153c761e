//! `--material` on `nanoeye metalib cell|sweep|blueprint` and `metalib material-study`
//! (issue 19, section 2).

mod common;

use common::nanoeye;
use std::process::Output;

fn json(out: &Output) -> serde_json::Value {
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).expect("JSON on stdout")
}

/// `metalib cell` at the paper's (h, s) = (700, 530) nm and a 200 nm pillar, then `more`.
fn cell<'a>(more: &[&'a str]) -> Vec<&'a str> {
    let mut v = common::CELL.to_vec();
    v.extend_from_slice(more);
    v
}

#[test]
fn an_unknown_material_is_refused_naming_the_flag_and_the_known_names() {
    let d = tempfile::tempdir().unwrap();
    for args in [
        cell(&["--material", "unobtainium"]),
        vec![
            "metalib",
            "sweep",
            "--out",
            "s",
            "--heights-nm",
            "700:700:10",
            "--pitches-nm",
            "530:530:10",
            "--material",
            "unobtainium",
        ],
        vec!["metalib", "material-study", "--materials", "unobtainium"],
    ] {
        let out = nanoeye(&args, d.path());
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{args:?}");
        assert!(!err.contains("panicked"), "{err}");
        assert!(err.contains("--material"), "{args:?}: {err}");
        for name in nanoeye_metalib::dispersion::names() {
            assert!(err.contains(&name), "{args:?}: {err} lacks {name}");
        }
    }
    assert!(!d.path().join("s").exists(), "nothing written on refusal");
    // A wavelength outside the table is refused naming both flags.
    let out = nanoeye(
        &cell(&["--material", "green-2008-csi", "--wavelength-nm", "500"]),
        d.path(),
    );
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("--material") && err.contains("--wavelength-nm"));
    // Without a material, the default (a-Si at 940 nm) is refused at another wavelength (it
    // was used as it is: n 3.7, k 0.008 at 100 and 5000 nm, a helper's audit); explicit
    // indices, or a table holding the wavelength, are taken.
    for w in ["500", "1500"] {
        let out = nanoeye(&cell(&["--wavelength-nm", w]), &std::env::temp_dir());
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            !out.status.success() && err.contains("--wavelength-nm: the default pillar index"),
            "{err}"
        );
    }
    let v = json(&nanoeye(
        &cell(&[
            "--wavelength-nm",
            "1064",
            "--n-pillar",
            "3.6",
            "--k-pillar",
            "0.004",
            "--json",
        ]),
        &std::env::temp_dir(),
    ));
    assert_eq!(v["n_pillar"], 3.6);
    let v = json(&nanoeye(
        &cell(&[
            "--wavelength-nm",
            "1064",
            "--material",
            "pierce-spicer-1972",
            "--json",
        ]),
        &std::env::temp_dir(),
    ));
    assert!(v["n_pillar"].as_f64().unwrap() != 3.7, "{v}");
}

#[test]
fn a_named_material_sets_the_pillar_index_and_explicit_flags_override_it() {
    let d = tempfile::tempdir().unwrap();
    let with = |extra: &[&str]| {
        let mut a = cell(&["--harmonics", "1", "--json"]);
        a.extend_from_slice(extra);
        json(&nanoeye(&a, d.path()))
    };
    let v = with(&["--material", "green-2008-csi"]);
    assert_eq!(v["n_pillar"], 3.595);
    assert_eq!(v["k_pillar"], 1.3689e-3);
    assert_eq!(v["material"], "green-2008-csi");
    assert!(
        with(&[]).get("material").is_none(),
        "no null key without --material"
    );
    let v = with(&["--material", "green-2008-csi", "--k-pillar", "0"]);
    assert_eq!(
        (v["n_pillar"].as_f64(), v["k_pillar"].as_f64()),
        (Some(3.595), Some(0.0))
    );
    // The same indices given explicitly give the same cell.
    let a = with(&["--material", "karaman-2025-asi"]);
    let b = with(&["--n-pillar", "3.979189", "--k-pillar", "0"]);
    assert_eq!(a["t_re"], b["t_re"]);
    assert_eq!(a["t_im"], b["t_im"]);
}

#[test]
fn the_sweep_manifest_records_the_material_and_a_resume_with_another_is_refused() {
    let d = tempfile::tempdir().unwrap();
    let sweep = |material: &str| {
        nanoeye(
            &[
                "metalib",
                "sweep",
                "--out",
                "s",
                "--heights-nm",
                "700:700:10",
                "--pitches-nm",
                "530:530:10",
                "--fractions",
                "0.3:0.4:0.1",
                "--harmonics",
                "1",
                "--material",
                material,
            ],
            d.path(),
        )
    };
    assert!(sweep("karaman-2025-asi").status.success());
    let m: serde_json::Value =
        serde_json::from_slice(&std::fs::read(d.path().join("s/manifest.json")).unwrap()).unwrap();
    assert_eq!(m["config"]["material"], "karaman-2025-asi");
    assert_eq!(m["config"]["materials"]["n_pillar"], 3.979189);
    assert!(
        sweep("karaman-2025-asi").status.success(),
        "same material resumes"
    );
    let out = sweep("green-2008-csi");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success()
            && err.contains("different parameters")
            && err.contains("`materials`")
            && err.contains("`material`"),
        "{err}"
    );
    // The finished sweep is left as it was (a refused run made it an empty partial/, a
    // helper's audit).
    assert!(!d.path().join("s/partial").exists());
}

#[test]
fn a_tiny_material_study_reports_every_variant_for_every_point() {
    let d = tempfile::tempdir().unwrap();
    let v = json(&nanoeye(
        &[
            "metalib",
            "material-study",
            "--json",
            "--harmonics",
            "1",
            "--fractions",
            "0.1:0.9:0.1",
            "--heights-nm",
            "690:710:10",
            "--n-values",
            "3.5:3.6:0.1",
            "--k-values",
            "0",
            "--materials",
            "green-2008-csi",
        ],
        d.path(),
    ));
    let points = v["points"].as_array().unwrap();
    assert_eq!(points.len(), 3, "one material + two grid points");
    assert_eq!(points[0]["source"], "green-2008-csi");
    assert_eq!(points[0]["n"], 3.595);
    let nv = v["variants"].as_array().unwrap().len();
    assert!(nv >= 7);
    for p in points {
        assert_eq!(p["variants"].as_array().unwrap().len(), nv);
        for o in p["variants"].as_array().unwrap() {
            assert!(o["coverage_rad"].as_f64().unwrap().is_finite());
        }
    }
    let out = nanoeye(
        &[
            "metalib",
            "material-study",
            "--height-nm",
            "705",
            "--heights-nm",
            "690:710:10",
        ],
        d.path(),
    );
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--height-nm"));
    // An absurd grid is refused up front instead of running for days.
    let out = nanoeye(
        &[
            "metalib",
            "material-study",
            "--n-values",
            "1:100:0.1",
            "--k-values",
            "0,1,2,3,4,5,6,7",
        ],
        d.path(),
    );
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--n-values"));
}

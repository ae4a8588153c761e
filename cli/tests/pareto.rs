//! `nanoeye search pareto` end to end on a tiny trained run: points and fronts as documented,
//! the chain settings the run was trained with, `--head-refit` scoring the same subnets
//! with BN over every frame and the calibration head's output layer refitted, and a partial
//! state continued (a changed or broken one refused).

mod common;

use common::{TINY_CHAIN, TINY_TRAIN, nanoeye, tiny_dataset_of};
use serde_json::Value;
use std::path::Path;

/// `search pareto` of `subnets` subnets on `run` (dataset `ds`) with `extra` flags.
fn pareto_run(p: &Path, subnets: &str, extra: &[&str]) -> std::process::Output {
    pareto_runs(p, "run", subnets, extra)
}

/// `search pareto` of `subnets` subnets on the runs `runs` (dataset `ds`) with `extra` flags.
fn pareto_runs(p: &Path, runs: &str, subnets: &str, extra: &[&str]) -> std::process::Output {
    let args: Vec<&str> = [
        "search",
        "pareto",
        "--runs",
        runs,
        "--dataset",
        "ds",
        "--subnets",
        subnets,
    ]
    .into_iter()
    .chain(extra.iter().copied())
    .collect();
    nanoeye(&args, p)
}

/// The run's own chain (the flags it was trained with).
const RUN_CHAIN: [&str; 4] = ["--aperture-step-um", "10", "--exposure-ms", "0.0004"];

/// `subnets` subnets of `run` with its own chain and `extra`, refused: its stderr.
fn pareto_refused(p: &Path, subnets: &str, extra: &[&str]) -> String {
    let o = pareto_run(p, subnets, &[&RUN_CHAIN[..], extra].concat());
    assert!(!o.status.success(), "{extra:?} was not refused");
    String::from_utf8_lossy(&o.stderr).to_string()
}

/// Three subnets with the run's own chain; returns the printed JSON.
fn pareto(p: &Path, extra: &[&str]) -> Value {
    pareto_of(p, "run", extra)
}

/// [`pareto`] on the runs `runs`.
fn pareto_of(p: &Path, runs: &str, extra: &[&str]) -> Value {
    let o = pareto_runs(p, runs, "3", &[&RUN_CHAIN[..], &["--json"], extra].concat());
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    serde_json::from_slice(&o.stdout).expect("JSON")
}

fn points(v: &Value, key: &str) -> Vec<(u64, f64)> {
    v["lenses"][0][key]
        .as_array()
        .expect(key)
        .iter()
        .map(|q| (q["macs"].as_u64().unwrap(), q["v_deg"].as_f64().unwrap()))
        .collect()
}

#[test]
fn pareto_scores_subnets_of_a_trained_run_with_and_without_the_head_refit() {
    let root = tempfile::tempdir().unwrap();
    let p = root.path();
    // Two ambiguity items, six frames: the refit's leave-one-out error needs three.
    assert!(nanoeye(&tiny_dataset_of("ds", "2"), p).status.success());
    let train: Vec<&str> = [&["search", "train"][..], &TINY_CHAIN]
        .concat()
        .into_iter()
        .chain(TINY_TRAIN)
        .chain(["--out", "run"])
        .collect();
    let o = nanoeye(&train, p);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));

    let plain = pareto(p, &["--plot", "plain.svg"]);
    let pts = points(&plain, "points");
    assert_eq!(pts.len(), 3);
    for &(macs, v) in &pts {
        assert!(macs > 0 && v.is_finite() && v >= 0.0, "{macs} {v}");
    }
    // The front: points of the set, MACs ascending, V strictly falling, and no point of the
    // set beats a front point in both.
    let front = points(&plain, "front");
    assert!(!front.is_empty());
    for w in front.windows(2) {
        assert!(w[0].0 < w[1].0 && w[0].1 > w[1].1, "{front:?}");
    }
    for f in &front {
        assert!(pts.contains(f));
        assert!(
            !pts.iter()
                .any(|q| q.0 <= f.0 && q.1 < f.1 || q.0 < f.0 && q.1 <= f.1)
        );
    }
    let svg = std::fs::read_to_string(p.join("plain.svg")).unwrap();
    assert!(svg.starts_with("<svg") && svg.contains("polyline"));
    assert!(
        svg.contains("median V"),
        "the legend names the bootstrap's median"
    );

    // The state keeps every subnet's error (an angle, 0–180°) on each of the 6 frames; V is
    // their mean (a failed frame counted 90°), and the bootstrap's median of V brackets the
    // median of the three points, over resamples of its 2 items.
    let sp = p.join("plain.state.json");
    let st: Value = serde_json::from_slice(&std::fs::read(&sp).unwrap()).unwrap();
    let errs: Vec<Vec<f64>> = serde_json::from_value(st["frame_errors"][0].clone()).unwrap();
    assert_eq!(errs.len(), 3);
    for (e, &(_, v)) in errs.iter().zip(&pts) {
        assert_eq!(e.len(), 6);
        assert!(e.iter().all(|x| (0.0..=180.0).contains(x)), "{e:?}");
        assert!(
            (e.iter().sum::<f64>() / 6.0 - v).abs() <= 1e-12 * v.max(1.0),
            "{e:?} {v}"
        );
    }
    let b = &plain["bootstrap"];
    assert_eq!(
        (
            b["frames"].as_u64(),
            b["items"].as_u64(),
            b["draws"].as_u64()
        ),
        (Some(6), Some(2), Some(1000))
    );
    let m = &b["median_v"][0];
    let mut vs: Vec<f64> = pts.iter().map(|q| q.1).collect();
    vs.sort_by(f64::total_cmp);
    assert_eq!(m["value"].as_f64(), Some(vs[1]));
    let (lo, hi) = (m["lo"].as_f64().unwrap(), m["hi"].as_f64().unwrap());
    assert!(lo <= vs[1] && vs[1] <= hi, "{m}");
    // Without resamples, no bootstrap in the output.
    let none = pareto(p, &["--plot", "plain.svg", "--bootstrap", "0"]);
    assert!(none.get("bootstrap").is_none());
    let svg = std::fs::read_to_string(p.join("plain.svg")).unwrap();
    assert!(!svg.contains("median V"));
    assert_eq!(points(&none, "points"), pts);

    // Runs of one lens joined by `+` are averaged subnet by subnet: a run and its copy
    // average to the run's own points exactly ((x + x) / 2 = x, MACs too), and the
    // seed-by-seed paired differences of two such lenses are exactly 0, one per seed. (Copies:
    // the same run given twice is refused, as it compared a lens with itself.)
    for copy in ["run2", "run3", "run4"] {
        common::copy_dir(&p.join("run"), &p.join(copy));
    }
    let dup = pareto_runs(
        p,
        "run+run2,run/",
        "3",
        &[&RUN_CHAIN[..], &["--plot", "x.svg"]].concat(),
    );
    let err = String::from_utf8_lossy(&dup.stderr);
    assert!(
        !dup.status.success() && err.contains("'run' and 'run/' are the same run"),
        "{err}"
    );
    // Outputs inside an input's tree are refused before any scoring (the plot replaced the
    // run's own loss.svg; a helper's audit).
    let loss = std::fs::read(p.join("run/loss.svg")).unwrap();
    for (plot, flag) in [("run/loss.svg", "--runs"), ("ds/p.svg", "--dataset")] {
        let err = pareto_refused(p, "3", &["--plot", plot]);
        assert!(
            err.contains(&format!("--plot: '{plot}' lies inside {flag}")),
            "{err}"
        );
    }
    let err = pareto_refused(p, "3", &["--plot", "x.svg", "--state", "run/s.json"]);
    assert!(
        err.contains("--state: 'run/s.json' lies inside --runs"),
        "{err}"
    );
    assert_eq!(std::fs::read(p.join("run/loss.svg")).unwrap(), loss);
    assert!(!p.join("ds/p.svg").exists() && !p.join("run/s.json").exists());
    let seeds = pareto_of(p, "run+run2,run3+run4", &["--plot", "seeds.svg"]);
    assert_eq!(points(&seeds, "points"), pts);
    assert_eq!(seeds["lenses"][0]["run"], "run+run2");
    assert_eq!(
        seeds["lenses"][1]["runs"],
        serde_json::json!(["run3", "run4"])
    );
    assert_eq!(
        seeds["seed_differences"]["run+run2 - run3+run4"],
        serde_json::json!([0.0, 0.0])
    );
    assert_eq!(
        seeds["seed_intervals"]["run+run2 - run3+run4"],
        serde_json::json!({"value": 0.0, "lo": 0.0, "hi": 0.0, "seeds": 2})
    );
    assert_eq!(plain["lenses"][0]["runs"], serde_json::json!(["run"]));
    assert!(plain.get("seed_intervals").is_none());
    // `--reuse`: a run scored in another state with the same inputs is taken from it, not
    // scored again. A copy of the plain state with its first subnet's errors set to 1°
    // gives that subnet V = 1 exactly in the averaged lens (its own score is other).
    let mut doctored: Value =
        serde_json::from_slice(&std::fs::read(p.join("plain.state.json")).unwrap()).unwrap();
    assert_ne!(doctored["lenses"][0][0]["v_deg"], Value::from(1.0));
    doctored["lenses"][0][0]["v_deg"] = 1.0.into();
    doctored["frame_errors"][0][0] = Value::from(vec![1.0; 6]);
    // A state edited to hold what no scoring writes is refused naming --state, with the
    // bootstrap on or off (an error of 1e308 was blamed on --bootstrap, or with --bootstrap 0
    // printed as V = 1.7e307, exit 0; MACs 0 and too few frame errors were taken).
    type Edit = fn(&mut Value);
    let edits: [Edit; 4] = [
        |s| s["frame_errors"][0][1][0] = 1e308.into(),
        |s| s["frame_errors"][0][1][0] = (-1.0).into(),
        |s| s["lenses"][0][1]["macs"] = 0.into(),
        |s| s["frame_errors"][0][1] = Value::from(vec![1.0; 2]),
    ];
    for (i, edit) in edits.iter().enumerate() {
        let mut bad = doctored.clone();
        edit(&mut bad);
        std::fs::write(p.join("bad.json"), serde_json::to_vec(&bad).unwrap()).unwrap();
        for boot in ["0", "10"] {
            let args = [
                "--plot",
                "bad.svg",
                "--state",
                "bad.json",
                "--bootstrap",
                boot,
            ];
            let err = pareto_refused(p, "3", &args);
            assert!(
                err.contains("--state") && err.contains("no score a search writes"),
                "{i}: {err}"
            );
        }
    }
    std::fs::write(
        p.join("doctored.json"),
        serde_json::to_vec(&doctored).unwrap(),
    )
    .unwrap();
    let reused = pareto_of(
        p,
        "run+run2,run3+run4",
        &[
            "--plot",
            "reused.svg",
            "--reuse",
            "doctored.json",
            "--bootstrap",
            "0",
        ],
    );
    let rp = points(&reused, "points");
    assert_eq!(rp[0], (pts[0].0, 1.0));
    assert_eq!(rp[1..], pts[1..]);
    // A state of other inputs (BN over two batches), or none: refused naming --reuse.
    let three_state = p.join("three.state.json");
    assert!(!three_state.exists());
    let o = pareto_run(
        p,
        "3",
        &[
            &RUN_CHAIN[..],
            &[
                "--bn-batches",
                "3",
                "--plot",
                "three.svg",
                "--reuse",
                "doctored.json",
            ],
        ]
        .concat(),
    );
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("--reuse") && err.contains("--bn-batches"),
        "{err}"
    );
    assert!(!three_state.exists(), "nothing scored before the refusal");
    let err = pareto_refused(p, "3", &["--plot", "x.svg", "--reuse", "nope.json"]);
    assert!(
        err.contains("--reuse") && err.contains("nope.json"),
        "{err}"
    );
    assert!(plain.get("seed_differences").is_none());

    // The state beside the plot holds the points; cut back to the first one (a run killed
    // after one subnet), the rerun scores the other two to the same numbers and errors.
    let mut st: Value = serde_json::from_slice(&std::fs::read(&sp).unwrap()).unwrap();
    assert_eq!(st["lenses"][0].as_array().unwrap().len(), 3);
    let whole = st.clone();
    st["lenses"][0].as_array_mut().unwrap().truncate(1);
    st["frame_errors"][0].as_array_mut().unwrap().truncate(1);
    std::fs::write(&sp, serde_json::to_vec(&st).unwrap()).unwrap();
    assert_eq!(points(&pareto(p, &["--plot", "plain.svg"]), "points"), pts);
    let again: Value = serde_json::from_slice(&std::fs::read(&sp).unwrap()).unwrap();
    assert_eq!(again, whole);
    // The same run and set named otherwise (./run, ./ds) resume that state too: they are
    // compared by content, and the state then records the paths as given.
    std::fs::write(&sp, serde_json::to_vec(&st).unwrap()).unwrap();
    let args = [
        &[
            "search",
            "pareto",
            "--runs",
            "./run",
            "--dataset",
            "./ds",
            "--subnets",
            "3",
        ][..],
        &RUN_CHAIN[..],
        &["--json", "--plot", "plain.svg"],
    ]
    .concat();
    let o = nanoeye(&args, p);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let v: Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(points(&v, "points"), pts);
    let moved: Value = serde_json::from_slice(&std::fs::read(&sp).unwrap()).unwrap();
    assert_eq!(moved["lenses"], whole["lenses"]);
    assert_eq!(moved["frame_errors"], whole["frame_errors"]);
    assert_eq!(moved["key"]["runs"][0][0], "./run");
    assert_eq!(moved["key"]["dataset"][0], "./ds");
    std::fs::write(&sp, serde_json::to_vec(&whole).unwrap()).unwrap();
    // A state without the per-frame errors (an older nanoeye's): refused, not mixed.
    let mut old = whole.clone();
    old.as_object_mut().unwrap().remove("frame_errors");
    std::fs::write(&sp, serde_json::to_vec(&old).unwrap()).unwrap();
    let err = pareto_refused(p, "3", &["--plot", "plain.svg"]);
    assert!(
        err.contains("per-frame errors") && err.contains("plain.state.json"),
        "{err}"
    );
    std::fs::write(&sp, serde_json::to_vec(&whole).unwrap()).unwrap();
    // Other inputs against that state: refused, naming what differs, the state kept.
    let rerun = |subnets: &str| pareto_refused(p, subnets, &["--plot", "plain.svg"]);
    let before = std::fs::read(&sp).unwrap();
    let err = rerun("2");
    assert!(
        err.contains("--state") && err.contains("--subnets"),
        "{err}"
    );
    assert_eq!(std::fs::read(&sp).unwrap(), before);
    // A state that is not one: refused naming --state.
    std::fs::write(&sp, &before[..before.len() / 2]).unwrap();
    let err = rerun("3");
    assert!(
        err.contains("--state") && err.contains("plain.state.json"),
        "{err}"
    );

    // BN over two batches (four of the six frames) instead of every frame (the default): the
    // same subnets and MACs, other V; refused against the every-frame state, naming the flag.
    let two = pareto(p, &["--bn-batches", "2", "--plot", "two.svg"]);
    let tp = points(&two, "points");
    assert_eq!(
        (&two["bn_batches"], &plain["bn_batches"], &two["head_refit"]),
        (&Value::from(2), &Value::from("all"), &Value::from(false))
    );
    assert_eq!(
        tp.iter().map(|q| q.0).collect::<Vec<_>>(),
        pts.iter().map(|q| q.0).collect::<Vec<_>>()
    );
    assert_ne!(tp, pts, "BN over fewer frames changed no score");
    std::fs::write(&sp, serde_json::to_vec(&whole).unwrap()).unwrap();
    let err = pareto_refused(p, "3", &["--bn-batches", "2", "--plot", "plain.svg"]);
    assert!(err.contains("--bn-batches"), "{err}");
    // A state written before `--bn-batches` (no `bn_batches` in its key) is one of 2
    // batches, the count then fixed: it resumes with `--bn-batches 2`, its points as they
    // were, and is refused under the new default, naming the flag.
    let tsp = p.join("two.state.json");
    let mut older: Value = serde_json::from_slice(&std::fs::read(&tsp).unwrap()).unwrap();
    older["key"].as_object_mut().unwrap().remove("bn_batches");
    std::fs::write(&tsp, serde_json::to_vec(&older).unwrap()).unwrap();
    let again = pareto(p, &["--bn-batches", "2", "--plot", "two.svg"]);
    assert_eq!(points(&again, "points"), tp);
    let err = pareto_refused(p, "3", &["--plot", "two.svg"]);
    assert!(err.contains("--bn-batches"), "{err}");
    // More BN batches than the kept inputs' budget: refused naming the flag, no state left.
    let huge = ["--bn-batches", "18446744073709551615", "--plot", "huge.svg"];
    let err = pareto_refused(p, "3", &huge);
    assert!(err.contains("--bn-batches") && err.contains("MiB"), "{err}");
    assert!(!p.join("huge.state.json").exists());
    // A chain other than the one the run was trained with (its inputs.json): refused naming
    // the flag (an audit: --exposure-ms 0.4 scored the run through another camera, exit 0).
    let o = pareto_run(
        p,
        "3",
        &[
            "--aperture-step-um",
            "10",
            "--exposure-ms",
            "0.4",
            "--plot",
            "exp.svg",
        ],
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && err.contains("--exposure-ms"),
        "{err}"
    );
    assert!(!p.join("exp.state.json").exists());

    // The refit scores the same subnets (same MACs): the same
    // numbers on a second run, and other V than the trained head's.
    let refit = pareto(p, &["--head-refit", "--plot", "refit.svg"]);
    let rp = points(&refit, "points");
    assert_eq!(
        (&refit["bn_batches"], &refit["head_refit"]),
        (&Value::Null, &Value::from(true))
    );
    assert_eq!(
        rp,
        points(
            &pareto(p, &["--head-refit", "--plot", "again.svg"]),
            "points"
        )
    );
    assert_eq!(
        rp.iter().map(|q| q.0).collect::<Vec<_>>(),
        pts.iter().map(|q| q.0).collect::<Vec<_>>()
    );
    assert_ne!(rp, pts, "the refit changed no score");

    // Read with another chain than the run's: refused, naming the flags to set.
    let o = pareto_run(p, "1", &[]);
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("--aperture-step-um"), "{err}");

    // A truncated search state: refused naming it, not replaced by uniform draws.
    std::fs::write(p.join("run/rea_state.json"), "{\"evaluated\": [").unwrap();
    let err = pareto_refused(p, "1", &[]);
    assert!(
        err.contains("--runs") && err.contains("rea_state.json"),
        "{err}"
    );
}

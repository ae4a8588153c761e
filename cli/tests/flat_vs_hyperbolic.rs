//! Issue 14's control, as a slow test: the supernet trained behind a flat phase (no lens: the
//! bare aperture) segments the pupil worse on held-out ambiguity pairs (C.3) than the same
//! training behind the fixed hyperbolic lens, for N_max and N_min and two training seeds.
//! At CI size neither network learns to segment yet (docs/run.md, "Flat vs hyperbolic"), so
//! this runs the documented size, about 10 min on 2 cores:
//! `cargo test --release -p nanoeye-cli --test flat_vs_hyperbolic -- --ignored --nocapture`.

mod common;

use common::nanoeye;
use std::path::Path;

/// `search train` behind `lens` (fixed) with `seed`, validated after BN statistics from
/// `bn` (`--bn-batches`: a finished run is only re-evaluated); returns (Dice N_max, Dice
/// N_min) and prints the row of docs/run.md's table.
fn train(p: &Path, lens: &str, seed: u32, bn: &str) -> (f64, f64) {
    let out = format!("{lens}-{seed}");
    let seed = seed.to_string();
    let o = nanoeye(
        &[
            "search",
            "train",
            "--dataset",
            "train",
            "--val",
            "val",
            "--lens",
            lens,
            "--fixed-lens",
            "--steps",
            "150",
            "--batch",
            "4",
            "--random-subnets",
            "0",
            "--lr-net",
            "4e-3",
            "--pitch-um",
            "14",
            "--pitch-range-um",
            "12:24",
            "--seed",
            &seed,
            "--weights-seed",
            &seed,
            "--bn-batches",
            bn,
            "--out",
            &out,
            "--json",
        ],
        p,
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let r: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let m = &r["max_subnet"];
    let f = |v: &serde_json::Value| v.as_f64().unwrap();
    println!(
        "| {lens} | {seed} | {bn} | {:.2}° | {:.2}° | {:.3} | {:.3} | {:.2} | {:.2} | {:.0} s |",
        f(&m["v_deg"]),
        f(&r["v_deg"]),
        f(&m["dice"]),
        f(&r["dice"]),
        f(&m["slip_mse"]),
        f(&r["slip_mse"]),
        f(&r["seconds"])
    );
    (f(&m["dice"]), f(&r["dice"]))
}

#[test]
#[ignore = "about 10 min on 2 cores; run with --release -- --ignored (module docs)"]
fn a_flat_phase_segments_worse_than_the_hyperbolic_lens_once_trained() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    for (set_seed, n, out) in [("0", "40", "train"), ("7", "12", "val")] {
        let o = nanoeye(
            &[
                "datagen",
                "render",
                "--set",
                "ambiguity",
                "--n",
                n,
                "--seed",
                set_seed,
                "--width",
                "320",
                "--height",
                "200",
                "--spp",
                "4",
                "--out",
                out,
            ],
            p,
        );
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    }
    println!(
        "| lens | seed | BN | V N_max | V N_min | Dice N_max | Dice N_min | slip MSE N_max | N_min | time |"
    );
    for seed in [0, 1] {
        let flat = train(p, "flat", seed, "all");
        let hyp = train(p, "hyperbolic", seed, "all");
        // The same trained networks after BN from two batches, as validated until the
        // thirty-eighth session: printed, not asserted.
        train(p, "flat", seed, "2");
        train(p, "hyperbolic", seed, "2");
        assert!(
            hyp.0 > flat.0 && hyp.1 > flat.1,
            "seed {seed}: Dice behind the hyperbolic lens {hyp:?}, behind the flat phase {flat:?}"
        );
    }
}

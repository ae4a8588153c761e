//! Kill-at-random-points test for every resumable job (issue 19, "Checks"): `fisher init`,
//! `datagen render`, `metalib sweep`, `search train`, `search rea`, `search pareto` and
//! `nanoeye run`, each on a tiny configuration. Each job runs once uninterrupted into
//! directory A; then, for each of a few kill points spread over A's wall time (seeded, so every
//! run of the test uses the same fractions of it), a fresh directory B is given the same
//! command, the process is sent SIGKILL at that point, and the same command is run again: it
//! must exit 0 on that first rerun, and B's files must equal A's byte for byte, leftover
//! temporary files included.
//!
//! Only the timing fields the docs name are left out of the comparison: `seconds` and
//! `seconds_per_step` in
//! `search train`'s metrics.json (docs/run.md), and for `nanoeye run` the stage times
//! (`stages.json`, the `stages` and `seconds` of result.json, and report.html, whose stage table
//! shows them). Every command runs in its own directory with relative paths, so paths written
//! into the outputs (`out` in result.json) agree.

mod common;

use common::{BIN, TINY_CHAIN, copy_dir, tiny_dataset, tree};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// Longest a tiny job may take (the debug build on a busy 2-core machine).
const DEADLINE: Duration = Duration::from_secs(400);

fn spawn(args: &[&str], cwd: &Path, log: &Path) -> Child {
    Command::new(BIN)
        .args(args)
        .current_dir(cwd)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(log).unwrap())
        .spawn()
        .expect("spawn nanoeye")
}

/// Runs `args` in `cwd` to completion; fails unless it exits 0. Returns its wall time.
fn run_ok(args: &[&str], cwd: &Path) -> Duration {
    let logs = tempfile::tempdir().unwrap();
    let log = logs.path().join("stderr");
    let t0 = Instant::now();
    let mut child = spawn(args, cwd, &log);
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        if t0.elapsed() > DEADLINE {
            let _ = child.kill();
            let _ = child.wait();
            panic!("{args:?} in {} runs past {DEADLINE:?}", cwd.display());
        }
        std::thread::sleep(Duration::from_millis(10));
    };
    assert!(
        status.success(),
        "{args:?} in {}: {status:?}\n{}",
        cwd.display(),
        std::fs::read_to_string(&log).unwrap_or_default()
    );
    t0.elapsed()
}

/// Starts `args` in `cwd` and sends SIGKILL after `delay`. `Ok` when it was killed while
/// running; `Err(wall)` when it finished first (after `wall`), so was not interrupted.
fn kill_after(args: &[&str], cwd: &Path, delay: Duration) -> Result<(), Duration> {
    let logs = tempfile::tempdir().unwrap();
    let mut child = spawn(args, cwd, &logs.path().join("stderr"));
    let t0 = Instant::now();
    while t0.elapsed() < delay {
        if child.try_wait().unwrap().is_some() {
            return Err(t0.elapsed());
        }
        std::thread::sleep(Duration::from_millis(2));
    }
    // Child::kill is SIGKILL on Unix: no destructor, no flush, no cleanup.
    let running = child.try_wait().unwrap().is_none();
    let _ = child.kill();
    let status = child.wait().unwrap();
    if running && !status.success() {
        Ok(())
    } else {
        Err(t0.elapsed())
    }
}

/// Timing the docs name, left out of the comparison.
#[derive(Default)]
struct Timing {
    /// Files that only hold or show timings.
    files: &'static [&'static str],
    /// (JSON file, top-level keys holding timings).
    keys: &'static [(&'static str, &'static [&'static str])],
}

/// `bytes` of `file` with the timing keys removed (the bytes as they are for other files).
fn comparable(file: &Path, bytes: &[u8], timing: &Timing) -> Vec<u8> {
    for (f, keys) in timing.keys {
        if file == Path::new(f) {
            let mut v: serde_json::Value =
                serde_json::from_slice(bytes).unwrap_or_else(|e| panic!("{}: {e}", file.display()));
            for k in *keys {
                assert!(
                    v.as_object_mut().unwrap().remove(*k).is_some(),
                    "{} has no {k}",
                    file.display()
                );
            }
            return serde_json::to_vec(&v).unwrap();
        }
    }
    bytes.to_vec()
}

fn assert_same_outputs(a: &Path, b: &Path, timing: &Timing, what: &str) {
    let (ta, tb) = (tree(a), tree(b));
    let only = |x: &BTreeMap<PathBuf, Vec<u8>>, y: &BTreeMap<PathBuf, Vec<u8>>| {
        x.keys()
            .filter(|k| !y.contains_key(*k))
            .cloned()
            .collect::<Vec<_>>()
    };
    let (only_a, only_b) = (only(&ta, &tb), only(&tb, &ta));
    assert!(
        only_a.is_empty() && only_b.is_empty(),
        "{what}: files only in the uninterrupted run {only_a:?}, only in the resumed run {only_b:?}"
    );
    for (k, va) in &ta {
        if timing.files.iter().any(|f| k == Path::new(f)) {
            continue;
        }
        assert!(
            comparable(k, va, timing) == comparable(k, &tb[k], timing),
            "{what}: {} differs after the resume",
            k.display()
        );
    }
}

/// Fractions of the wall time at which to kill: one in each of `n` equal slices of its first
/// 80 %, at a seeded place inside the slice (SplitMix64).
fn kill_fractions(n: usize, seed: u64) -> Vec<f64> {
    let mut s = seed;
    (0..n)
        .map(|k| {
            s = s.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = s;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            z ^= z >> 31;
            let u = (z >> 11) as f64 / (1u64 << 53) as f64;
            // Within the first 80 %: a run on a less busy machine may finish sooner.
            0.8 * (k as f64 + 0.1 + 0.8 * u) / n as f64
        })
        .collect()
}

/// One resumable job: its command, the directory it writes (relative to its cwd), how to
/// prepare a cwd, and the timing its outputs hold.
struct Job<'a> {
    name: &'a str,
    args: &'a [&'a str],
    out: &'a str,
    setup: &'a dyn Fn(&Path),
    timing: Timing,
    kills: usize,
    seed: u64,
}

/// Runs the job uninterrupted, then killed at each kill point and resumed; compares.
/// Returns the uninterrupted run's directory (for a job that builds on it).
fn check_job(job: &Job, root: &Path) -> PathBuf {
    let a = root.join(format!("{}-a", job.name));
    std::fs::create_dir_all(&a).unwrap();
    (job.setup)(&a);
    let wall = run_ok(job.args, &a);
    let mut landed = Vec::new();
    for (k, f) in kill_fractions(job.kills, job.seed).into_iter().enumerate() {
        let (b, killed) = killed_run(job, root, k, wall.mul_f64(f), f);
        if let Some(delay) = killed {
            landed.push(format!("{delay:.2?}"));
        }
        run_ok(job.args, &b);
        assert_same_outputs(
            &a.join(job.out),
            &b.join(job.out),
            &job.timing,
            &format!("{} killed at {killed:.2?} of {wall:.2?}", job.name),
        );
        // Compared: gone, so the test holds two runs on disk at a time, not one per kill
        // (the main job's runs hold their checkpoints and datasets).
        std::fs::remove_dir_all(&b).unwrap();
    }
    eprintln!(
        "{}: uninterrupted {wall:.2?}; killed at {landed:?} and resumed to the same bytes",
        job.name
    );
    assert!(
        !landed.is_empty(),
        "{}: every run finished before its kill point",
        job.name
    );
    a
}

/// Kill point `k` of `job`: a fresh directory set up, the job started and killed after
/// `delay`; returns the directory and the delay at which it was killed (None: it finished
/// first every time). The uninterrupted run may have shared the cores with other tests and
/// this one not, so a run that finishes before its kill point is redone, killed at the same
/// `fraction` of its own wall time (three tries).
fn killed_run(
    job: &Job,
    root: &Path,
    k: usize,
    mut delay: Duration,
    fraction: f64,
) -> (PathBuf, Option<Duration>) {
    for attempt in 0.. {
        let b = root.join(format!("{}-b{k}-{attempt}", job.name));
        std::fs::create_dir_all(&b).unwrap();
        (job.setup)(&b);
        match kill_after(job.args, &b, delay) {
            Ok(()) => return (b, Some(delay)),
            Err(_) if attempt == 2 => return (b, None),
            Err(own) => {
                std::fs::remove_dir_all(&b).unwrap();
                delay = own.mul_f64(fraction)
            }
        }
    }
    unreachable!()
}

fn no_setup(_: &Path) {}

/// A 1-item (2-frame) ambiguity dataset at 80 × 50, the search jobs' input.
fn render_dataset(cwd: &Path) {
    run_ok(&tiny_dataset("ds"), cwd);
}

#[test]
fn fisher_init_resumes_to_the_same_bytes() {
    let root = tempfile::tempdir().unwrap();
    check_job(
        &Job {
            name: "fisher-init",
            args: &[
                "fisher",
                "init",
                "--out",
                "fi",
                "--aperture-step-um",
                "10",
                "--window-px",
                "9",
                "--depths-mm",
                "20:23:1",
                "--iterations",
                "40",
                "--checkpoint-every",
                "1",
            ],
            out: "fi",
            setup: &no_setup,
            timing: Timing::default(),
            kills: 6,
            seed: 1,
        },
        root.path(),
    );
}

#[test]
fn datagen_render_resumes_to_the_same_bytes() {
    let root = tempfile::tempdir().unwrap();
    check_job(
        &Job {
            name: "render",
            args: &[
                "datagen",
                "render",
                "--set",
                "ambiguity",
                "--n",
                "4",
                "--width",
                "120",
                "--height",
                "75",
                "--spp",
                "1",
                "--out",
                "ds",
            ],
            out: "ds",
            setup: &no_setup,
            timing: Timing::default(),
            kills: 6,
            seed: 2,
        },
        root.path(),
    );
}

#[test]
fn metalib_sweep_resumes_to_the_same_bytes() {
    let root = tempfile::tempdir().unwrap();
    check_job(
        &Job {
            name: "sweep",
            args: &[
                "metalib",
                "sweep",
                "--out",
                "sw",
                "--heights-nm",
                "300:700:100",
                "--pitches-nm",
                "300:900:50",
                "--fractions",
                "0.2:0.8:0.1",
                "--harmonics",
                "5",
            ],
            out: "sw",
            setup: &no_setup,
            timing: Timing::default(),
            kills: 6,
            seed: 3,
        },
        root.path(),
    );
}

#[test]
fn search_train_and_rea_resume_to_the_same_bytes() {
    let root = tempfile::tempdir().unwrap();
    let train: Vec<&str> = [&["search", "train"][..], &TINY_CHAIN]
        .concat()
        .into_iter()
        .chain([
            "--steps",
            "4",
            "--batch",
            "3",
            "--random-subnets",
            "0",
            "--pitch-range-um",
            "48:120",
            "--checkpoint-every",
            "1",
            "--out",
            "run",
        ])
        .collect();
    let trained = check_job(
        &Job {
            name: "search-train",
            args: &train,
            out: "run",
            setup: &render_dataset,
            timing: Timing {
                files: &[],
                keys: &[("metrics.json", &["seconds", "seconds_per_step"])],
            },
            kills: 3,
            seed: 4,
        },
        root.path(),
    );
    // The search continues the trained run in place (rea_state.json, rea.jsonl).
    let rea: Vec<&str> = [&["search", "rea"][..], &TINY_CHAIN]
        .concat()
        .into_iter()
        .chain([
            "--run",
            "run",
            "--population",
            "3",
            "--cycles",
            "3",
            "--tournament",
            "2",
            "--epochs",
            "0",
            // BN over two batches (the default is every frame, which the main job's kills
            // below take): that path resumes to the same bytes too.
            "--bn-batches",
            "2",
        ])
        .collect();
    let from_trained = |cwd: &Path| {
        copy_dir(&trained.join("ds"), &cwd.join("ds"));
        copy_dir(&trained.join("run"), &cwd.join("run"));
    };
    let searched = check_job(
        &Job {
            name: "search-rea",
            args: &rea,
            out: "run",
            setup: &from_trained,
            timing: Timing {
                files: &[],
                keys: &[("metrics.json", &["seconds", "seconds_per_step"])],
            },
            kills: 3,
            seed: 5,
        },
        root.path(),
    );
    // A resume with a chain setting or data other than the search began with is refused
    // (rea_inputs.json), and changes nothing.
    let before = tree(&searched);
    for (more, flag) in [
        (&["--base-pitch-um", "1"][..], "--base-pitch-um"),
        (&["--val", "ds"][..], "--val"),
    ] {
        let args: Vec<&str> = rea.iter().copied().chain(more.iter().copied()).collect();
        let out = common::nanoeye(&args, &searched);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            !out.status.success() && err.contains(flag) && err.contains("differs from the run"),
            "{more:?}: {err}"
        );
    }
    assert!(
        tree(&searched) == before,
        "a refused resume changed the run"
    );
    // The same without rea_inputs.json (refused from rea_state.json's own record), then
    // without the run's inputs.json too (--base-pitch-um refused from the checkpoint's
    // record): both went on, one scoring candidates on other data (a helper's audit).
    let hide = |name: &str| {
        let (from, to) = (searched.join(name), searched.join(format!("{name}.kept")));
        std::fs::rename(&from, &to).unwrap();
        (from, to)
    };
    let hidden = [hide("run/rea_inputs.json"), hide("run/inputs.json")];
    for (more, flag, whose) in [
        (
            &["--base-pitch-um", "1"][..],
            "--base-pitch-um",
            "checkpoint.bin records",
        ),
        (&["--val", "ds"][..], "--val", "rea_state.json records"),
    ] {
        let args: Vec<&str> = rea.iter().copied().chain(more.iter().copied()).collect();
        let out = common::nanoeye(&args, &searched);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            !out.status.success() && err.contains(flag) && err.contains(whose),
            "{more:?}: {err}"
        );
    }
    for (from, to) in hidden {
        std::fs::rename(to, from).unwrap();
    }
    assert!(
        tree(&searched) == before,
        "a refused resume changed the run"
    );
    // A finished search resumed with its history deleted writes it again, the same bytes
    // (it reported the file and left it missing).
    std::fs::remove_file(searched.join("run/rea.jsonl")).unwrap();
    let out = common::nanoeye(&rea, &searched);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(tree(&searched) == before, "the history was not restored");
    // An edited state is refused by what no search writes (a helper's audit: an empty
    // population panicked drawing a tournament, a repeated history was reported as more
    // cycles than asked for, a fitness of 1e308 was picked as best), and changes nothing.
    let sp = searched.join("run/rea_state.json");
    let state = std::fs::read(&sp).unwrap();
    let st: serde_json::Value = serde_json::from_slice(&state).unwrap();
    type Edit = fn(&mut serde_json::Value);
    let edits: [(Edit, &str); 3] = [
        (|s| s["population"] = serde_json::json!([]), "population"),
        (
            |s| {
                let h = s["history"].as_array().unwrap().clone();
                s["history"] = serde_json::json!([h.clone(), h].concat());
            },
            "cycle records",
        ),
        (
            |s| s["evaluated"][1]["fitness"] = serde_json::json!(1e308),
            "score",
        ),
    ];
    for (edit, why) in edits {
        let mut s = st.clone();
        edit(&mut s);
        std::fs::write(&sp, s.to_string()).unwrap();
        let out = common::nanoeye(&rea, &searched);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            !out.status.success() && err.contains("rea_state.json") && err.contains(why),
            "{why}: {err}"
        );
    }
    std::fs::write(&sp, &state).unwrap();
    assert!(
        tree(&searched) == before,
        "a refused resume changed the run"
    );
    // --pitch-um is not rea's (each candidate starts from the run's p̂): another value resumes
    // the finished search, with a note, to the same history.
    let mut other = rea.clone();
    let at = other.iter().position(|&a| a == "--pitch-um").unwrap() + 1;
    other[at] = "61";
    let jsonl = std::fs::read(searched.join("run/rea.jsonl")).unwrap();
    let out = common::nanoeye(&other, &searched);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert!(
        err.contains("--pitch-um 61 is not used by search rea"),
        "{err}"
    );
    assert_eq!(
        std::fs::read(searched.join("run/rea.jsonl")).unwrap(),
        jsonl
    );
    // The Pareto points of the search's subnets and uniform draws; the run and its copy, so
    // that a kill can leave one lens finished and the next one partial in the state.
    let pareto: Vec<&str> = [&["search", "pareto"][..], &TINY_CHAIN[4..]]
        .concat()
        .into_iter()
        .chain([
            "--runs",
            "run,run2",
            "--dataset",
            "ds",
            "--subnets",
            "5",
            "--plot",
            "pa/pareto.svg",
        ])
        .collect();
    let from_searched = |cwd: &Path| {
        copy_dir(&searched.join("ds"), &cwd.join("ds"));
        copy_dir(&searched.join("run"), &cwd.join("run"));
        copy_dir(&searched.join("run"), &cwd.join("run2"));
    };
    check_job(
        &Job {
            name: "search-pareto",
            args: &pareto,
            out: "pa",
            setup: &from_searched,
            timing: Timing::default(),
            kills: 3,
            seed: 6,
        },
        root.path(),
    );
}

/// The main job on the tiny configuration of main_job.rs (its 3 × 3 protocol grid, fewer
/// training frames): about 15 s in the debug build, so one kill point.
#[test]
fn the_main_job_resumes_to_the_same_bytes() {
    let root = tempfile::tempdir().unwrap();
    let config = |cwd: &Path| {
        std::fs::write(
            cwd.join("tiny.json"),
            r#"{"width_px": 80, "height_px": 50, "spp": 1, "train_items": 3, "val_items": 2,
            "protocol_subjects": 1, "protocol_grid": 3, "train_steps": 2, "batch": 3,
            "random_subnets": 0,
            "pitch_init_um": 60.0, "pitch_range_um": [48.0, 120.0], "rea_cycles": 1,
            "rea_population": 2, "rea_tournament": 2, "rea_epochs": 1.0, "final_steps": 2,
            "aperture_step_um": 10.0, "exposure_ms": 0.0004, "head_widths": [32, 16],
            "sequence_frames": 5}"#,
        )
        .unwrap();
    };
    check_job(
        &Job {
            name: "run",
            args: &["run", "--config", "tiny.json", "--out", "r"],
            out: "r",
            setup: &config,
            timing: Timing {
                files: &["stages.json", "report.html"],
                keys: &[("result.json", &["stages", "seconds"])],
            },
            kills: 1,
            seed: 6,
        },
        root.path(),
    );
}

/// A kill between an atomic writer's temporary file and its rename leaves
/// `.nanoeye-tmp-<pid>-…` (the stage crates' writers used tempfile's `.tmpXXXXXX` names, which
/// a rerun never removed: search train's checkpoint.bin left one). Every resumable job removes
/// those of dead processes anywhere in its output tree, also where only a stage crate writes.
#[test]
fn temp_files_of_a_killed_run_are_removed_on_resume() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    let stale = ".nanoeye-tmp-4294967295-abcdef";
    for (args, dir) in [
        (
            &[
                "fisher",
                "init",
                "--out",
                "fi",
                "--aperture-step-um",
                "50",
                "--window-px",
                "3",
                "--iterations",
                "1",
            ][..],
            "fi/checkpoint",
        ),
        (&tiny_dataset("ds"), "ds/frames"),
        (
            &[
                "metalib",
                "sweep",
                "--out",
                "sw",
                "--heights-nm",
                "300:500:200",
                "--pitches-nm",
                "300:400:100",
                "--fractions",
                "0.2:0.5:0.3",
                "--harmonics",
                "1",
            ],
            // partial/ goes once the sweep completes; the manifest's directory stays.
            "sw",
        ),
    ] {
        run_ok(args, p);
        let left = p.join(dir).join(stale);
        std::fs::write(&left, b"cut off").unwrap();
        run_ok(args, p);
        assert!(!left.exists(), "{args:?} kept {}", left.display());
    }
}

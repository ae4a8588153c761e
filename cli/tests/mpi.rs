//! Distributed runs (cargo feature `mpi`): `mpirun -np 2 nanoeye …` writes byte for byte what
//! one process writes, for the sweep, dataset rendering, PSF stacks, training and the search; a
//! failing or killed rank ends the run and leaves its finished share for the resume.
//! Needs OpenMPI's `mpirun` on PATH (docs/mpi.md); run with
//! `cargo test -p nanoeye-cli --features mpi --test mpi`.
#![cfg(feature = "mpi")]

mod common;

use common::{BIN, TINY_CHAIN, copy_dir, tiny_dataset, tree};
use std::path::Path;
use std::process::{Command, Output};

/// `nanoeye args` on one process, without mpirun.
fn single(args: &[&str], cwd: &Path) -> Output {
    let o = Command::new(BIN)
        .args(args)
        .current_dir(cwd)
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "single {args:?}: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    o
}

/// `mpirun -np n nanoeye args` (root allowed: CI runs as root; oversubscribed: 2 cores).
fn mpirun(n: usize, args: &[&str], cwd: &Path) -> Output {
    Command::new("mpirun")
        .args([
            "-np",
            &n.to_string(),
            "--oversubscribe",
            "--allow-run-as-root",
        ])
        .args(["--mca", "btl", "self,vader"])
        .arg(BIN)
        .args(args)
        .current_dir(cwd)
        .env("RAYON_NUM_THREADS", "1")
        // Containers often forbid the cross-memory attach OpenMPI's shared memory tries first.
        .env("OMPI_MCA_btl_vader_single_copy_mechanism", "none")
        .output()
        .expect("mpirun on PATH (apt-get install openmpi-bin)")
}

fn ok(o: Output, what: &str) -> Output {
    assert!(
        o.status.success(),
        "{what}: {}\n{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    o
}

fn assert_same_tree(a: &Path, b: &Path) {
    let (ta, tb) = (tree(a), tree(b));
    assert_eq!(
        ta.keys().collect::<Vec<_>>(),
        tb.keys().collect::<Vec<_>>(),
        "file lists differ"
    );
    for (k, v) in &ta {
        assert!(v == &tb[k], "{} differs", k.display());
    }
}

const SWEEP: [&str; 8] = [
    "--heights-nm",
    "300:700:200",
    "--pitches-nm",
    "300:600:100",
    "--fractions",
    "0.2:0.8:0.3",
    "--harmonics",
    "3",
];

#[test]
fn sweep_on_two_ranks_is_byte_identical_and_resumes_a_killed_share() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    single(
        &[&["metalib", "sweep", "--out", "one"][..], &SWEEP].concat(),
        p,
    );
    ok(
        mpirun(
            2,
            &[&["metalib", "sweep", "--out", "two"][..], &SWEEP].concat(),
            p,
        ),
        "mpirun sweep",
    );
    assert_same_tree(&p.join("one"), &p.join("two"));

    // A run whose rank 1 fails (its first checkpoint target is a directory) ends with that
    // rank's message; every block left on disk is whole (a block of 3 heights × 3 fractions
    // is 24 + 9 × 32 bytes), and the rerun resumes from them to the same bytes. The cost plan
    // gives rank 1 pitches 1 and 2.
    let partial = p.join("three/partial");
    std::fs::create_dir_all(partial.join("pitch_0001.bin")).unwrap();
    let o = mpirun(
        2,
        &[&["metalib", "sweep", "--out", "three"][..], &SWEEP].concat(),
        p,
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success());
    assert!(err.contains("error (rank 1 of 2)"), "{err}");
    assert!(err.contains("pitch_0001.bin"), "{err}");
    assert!(only_whole_blocks(&partial, 9));
    std::fs::remove_dir(partial.join("pitch_0001.bin")).unwrap();
    let o = ok(
        mpirun(
            2,
            &[
                &["metalib", "sweep", "--out", "three", "--json"][..],
                &SWEEP,
            ]
            .concat(),
            p,
        ),
        "resumed sweep",
    );
    let m: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(m["complete"], true);
    assert_same_tree(&p.join("one"), &p.join("three"));
}

#[test]
fn render_and_psf_on_two_ranks_are_byte_identical() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    single(&tiny_dataset("one"), p);
    ok(mpirun(2, &tiny_dataset("two"), p), "mpirun render");
    assert_same_tree(&p.join("one"), &p.join("two"));

    let psf = [
        "optics",
        "psf",
        "--depths-mm",
        "17:26:3",
        "--window-px",
        "16",
        "--aperture-mm",
        "0.3",
        "--sample-um",
        "3",
        "--out",
    ];
    single(&[&psf[..], &["one_psf"]].concat(), p);
    // A command that does not split its work refuses to run on two ranks.
    let o = mpirun(2, &["rig", "show"], p);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && err.contains("runs on one process"),
        "{err}"
    );
    ok(
        mpirun(2, &[&psf[..], &["two_psf"]].concat(), p),
        "mpirun psf",
    );
    assert_same_tree(&p.join("one_psf"), &p.join("two_psf"));
}

fn render_dataset(p: &Path) {
    single(&tiny_dataset("ds"), p);
}

fn train_args(out: &str) -> Vec<&str> {
    [
        &["search", "train"][..],
        &TINY_CHAIN,
        &[
            "--steps",
            "2",
            "--batch",
            "3",
            "--random-subnets",
            "0",
            "--pitch-range-um",
            "48:120",
            "--checkpoint-every",
            "1",
            "--json",
            "--out",
            out,
        ],
    ]
    .concat()
}

/// A run's metrics.json (or printed JSON) without its timings (and the ranks' timings).
fn without_timing(bytes: &[u8]) -> serde_json::Value {
    let mut v: serde_json::Value = serde_json::from_slice(bytes).unwrap();
    let m = v.as_object_mut().unwrap();
    m.remove("seconds").unwrap();
    m.remove("seconds_per_step").unwrap();
    m.remove("mpi");
    v
}

/// Every file of two training runs equal byte for byte, metrics.json up to its wall time.
fn assert_same_run(a: &Path, b: &Path) {
    let (ta, tb) = (tree(a), tree(b));
    assert_eq!(
        ta.keys().collect::<Vec<_>>(),
        tb.keys().collect::<Vec<_>>(),
        "file lists differ"
    );
    for (k, v) in &ta {
        if k == Path::new("metrics.json") {
            assert_eq!(without_timing(v), without_timing(&tb[k]), "metrics.json");
        } else {
            assert!(v == &tb[k], "{} differs", k.display());
        }
    }
}

#[test]
fn train_on_two_ranks_is_byte_identical() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    render_dataset(p);
    let one = single(&train_args("one"), p);
    // Each step's PSF stack and PSF VJP split over depth between the ranks.
    let two = ok(mpirun(2, &train_args("two"), p), "mpirun train");
    assert_same_run(&p.join("one"), &p.join("two"));
    for f in ["checkpoint.bin", "phase.npy", "history.jsonl"] {
        assert!(p.join("two").join(f).is_file(), "{f}");
    }
    // Rank 0 alone prints; each step all-gathered its PSF stack and its PSF VJP.
    assert_eq!(without_timing(&one.stdout), without_timing(&two.stdout));
    let m: serde_json::Value = serde_json::from_slice(&two.stdout).unwrap();
    assert_eq!(m["mpi"]["ranks"], 2);
    assert_eq!(m["mpi"]["step_all_gathers"], 4);
    // The finished run again on two ranks: rank 0 reads the checkpoint and sends it to rank 1
    // (which would otherwise compute its share of the validation's PSFs from the initial lens).
    let again = ok(mpirun(2, &train_args("two"), p), "mpirun train (resume)");
    assert!(String::from_utf8_lossy(&again.stderr).contains("resuming"));
    assert_same_run(&p.join("one"), &p.join("two"));
}

#[test]
fn search_on_two_and_three_ranks_gives_the_sequential_result() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    render_dataset(p);
    single(&train_args("run1"), p);
    copy_dir(&p.join("run1"), &p.join("run2"));
    copy_dir(&p.join("run1"), &p.join("run3"));
    // One epoch of fine-tuning per candidate, on the worker that evaluates it.
    let rea = |run: &'static str| {
        [
            &["search", "rea"][..],
            &TINY_CHAIN,
            &[
                "--run",
                run,
                "--population",
                "3",
                "--cycles",
                "3",
                "--tournament",
                "2",
                "--epochs",
                "1",
                "--json",
            ],
        ]
        .concat()
    };
    single(&rea("run1"), p);
    // Rank 0 and one worker; rank 0 and two workers (results can come back out of order).
    ok(mpirun(2, &rea("run2"), p), "mpirun -np 2 rea");
    ok(mpirun(3, &rea("run3"), p), "mpirun -np 3 rea");
    for run in ["run2", "run3"] {
        for f in ["rea_state.json", "rea.jsonl"] {
            assert!(
                std::fs::read(p.join("run1").join(f)).unwrap()
                    == std::fs::read(p.join(run).join(f)).unwrap(),
                "{run}/{f} differs"
            );
        }
    }
}

/// Ranks of `nanoeye` running in `cwd`: (pid, rank) from each process's
/// OMPI_COMM_WORLD_RANK.
fn ranks_in(cwd: &Path) -> Vec<(u32, usize)> {
    let mut out = Vec::new();
    for e in std::fs::read_dir("/proc").unwrap().flatten() {
        let Ok(pid) = e.file_name().to_string_lossy().parse::<u32>() else {
            continue;
        };
        let (Ok(cmd), Ok(dir), Ok(env)) = (
            std::fs::read(format!("/proc/{pid}/cmdline")),
            std::fs::read_link(format!("/proc/{pid}/cwd")),
            std::fs::read(format!("/proc/{pid}/environ")),
        ) else {
            continue;
        };
        if !cmd.starts_with(BIN.as_bytes()) || dir != cwd {
            continue;
        }
        let rank = env
            .split(|&b| b == 0)
            .filter_map(|kv| kv.strip_prefix(b"OMPI_COMM_WORLD_RANK="))
            .find_map(|r| String::from_utf8_lossy(r).parse().ok());
        if let Some(r) = rank {
            out.push((pid, r));
        }
    }
    out
}

/// The pitch block checkpoints in `partial` (their temporary files, named `.nanoeye-tmp-…`,
/// left out).
fn blocks_in(partial: &Path) -> usize {
    std::fs::read_dir(partial).map_or(0, |d| {
        d.flatten()
            .filter(|e| {
                let n = e.file_name().to_string_lossy().into_owned();
                n.starts_with("pitch_") && n.ends_with(".bin") && e.path().is_file()
            })
            .count()
    })
}

/// Whether every file in `partial` but the temporary ones is a whole block of `cells` cells
/// (directories are left out):
/// 24 bytes of header and hash around 32 per cell (metalib's sweep checkpoints).
fn only_whole_blocks(partial: &Path, cells: u64) -> bool {
    std::fs::read_dir(partial).unwrap().flatten().all(|e| {
        let n = e.file_name().to_string_lossy().into_owned();
        n.starts_with(".nanoeye-tmp-")
            || e.path().is_dir()
            || (n.starts_with("pitch_")
                && n.ends_with(".bin")
                && e.metadata().is_ok_and(|m| m.len() == 24 + 32 * cells))
    })
}

/// `kill -9` of rank 1 while a two-rank sweep runs ends the job (mpirun names the rank) and
/// leaves only complete blocks; the same command resumes them to one process's bytes.
#[test]
fn a_sweep_whose_rank_is_killed_resumes_to_the_same_bytes() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    // 16 pitches of 9 heights and 17 fractions at 5 harmonics: 8 blocks of ~0.4 s per rank
    // (a few seconds), so rank 1 dies mid-run.
    let sweep = |out: &'static str| {
        [
            "metalib",
            "sweep",
            "--heights-nm",
            "300:700:50",
            "--pitches-nm",
            "300:900:40",
            "--fractions",
            "0.1:0.9:0.05",
            "--harmonics",
            "5",
            "--out",
            out,
        ]
    };
    single(&sweep("one"), p);
    let mut job = Command::new("mpirun")
        .args(["-np", "2", "--oversubscribe", "--allow-run-as-root"])
        .args(["--mca", "btl", "self,vader"])
        .arg(BIN)
        .args(sweep("killed"))
        .current_dir(p)
        .env("RAYON_NUM_THREADS", "1")
        .env("OMPI_MCA_btl_vader_single_copy_mechanism", "none")
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("mpirun on PATH");
    // Once the first block is on disk, rank 1 dies.
    let partial = p.join("killed/partial");
    let t0 = std::time::Instant::now();
    while blocks_in(&partial) == 0 {
        assert!(
            job.try_wait().unwrap().is_none(),
            "the sweep ended before its first block"
        );
        assert!(t0.elapsed().as_secs() < 120, "no block after 2 minutes");
        std::thread::sleep(std::time::Duration::from_millis(5));
    }
    let victim = ranks_in(&p.canonicalize().unwrap())
        .into_iter()
        .find(|&(_, r)| r == 1)
        .expect("rank 1 running")
        .0;
    let killed = Command::new("kill")
        .args(["-9", &victim.to_string()])
        .status()
        .unwrap();
    assert!(killed.success());
    let o = job.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "the job survived its rank: {err}");
    assert!(err.contains("rank 1"), "{err}");
    assert!(err.contains("signal 9") || err.contains("Killed"), "{err}");
    // 9 heights × 17 fractions per block.
    assert!(blocks_in(&partial) >= 1);
    assert!(only_whole_blocks(&partial, 153));
    assert!(
        !p.join("killed/phase.npy").exists(),
        "the killed job wrote its arrays: kill it earlier"
    );
    ok(mpirun(2, &sweep("killed"), p), "resumed sweep");
    assert_same_tree(&p.join("one"), &p.join("killed"));
}

//! Distributed runs (cargo feature `mpi`): `mpirun -np 2 nanoeye …` writes byte for byte what
//! one process writes, for the sweep, dataset rendering, PSF stacks and the search; a failing
//! rank ends the run with its message and leaves its finished share for the resume.
//! Needs OpenMPI's `mpirun` on PATH (docs/mpi.md); run with
//! `cargo test -p nanoeye-cli --features mpi --test mpi`.
#![cfg(feature = "mpi")]

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

const BIN: &str = env!("CARGO_BIN_EXE_nanoeye");

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

/// Every file under `dir` (relative path → bytes).
fn tree(dir: &Path) -> BTreeMap<PathBuf, Vec<u8>> {
    let mut out = BTreeMap::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else {
                let rel = p.strip_prefix(dir).unwrap().to_path_buf();
                out.insert(rel, std::fs::read(&p).unwrap());
            }
        }
    }
    out
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
    // rank's message; every block left on disk is complete (it has its side file), and the
    // rerun resumes from them to the same bytes. The cost plan gives rank 1 pitches 1 and 2.
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
    for e in std::fs::read_dir(&partial).unwrap() {
        let f = e.unwrap().path();
        if f.extension().is_some_and(|x| x == "bin") && f.is_file() {
            assert!(f.with_extension("fnv").exists(), "{}", f.display());
        }
    }
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
    let render = |out: &'static str| {
        [
            "datagen",
            "render",
            "--set",
            "ambiguity",
            "--n",
            "1",
            "--width",
            "80",
            "--height",
            "50",
            "--spp",
            "1",
            "--out",
            out,
        ]
    };
    single(&render("one"), p);
    ok(mpirun(2, &render("two"), p), "mpirun render");
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

#[test]
fn search_on_three_ranks_gives_the_sequential_result() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    single(
        &[
            "datagen",
            "render",
            "--set",
            "ambiguity",
            "--n",
            "1",
            "--width",
            "80",
            "--height",
            "50",
            "--spp",
            "1",
            "--out",
            "ds",
        ],
        p,
    );
    let chain = [
        "--dataset",
        "ds",
        "--pitch-um",
        "60",
        "--aperture-step-um",
        "10",
        "--exposure-ms",
        "0.0004",
    ];
    single(
        &[
            &["search", "train"][..],
            &chain,
            &[
                "--steps",
                "1",
                "--batch",
                "3",
                "--random-subnets",
                "0",
                "--pitch-range-um",
                "48:120",
                "--out",
                "run1",
            ],
        ]
        .concat(),
        p,
    );
    copy_dir(&p.join("run1"), &p.join("run2"));
    let rea = |run: &'static str| {
        [
            &["search", "rea"][..],
            &chain,
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
                "0",
                "--json",
            ],
        ]
        .concat()
    };
    single(&rea("run1"), p);
    // Rank 0 and two workers: results can come back out of order.
    ok(mpirun(3, &rea("run2"), p), "mpirun rea");
    for f in ["rea_state.json", "rea.jsonl"] {
        assert!(
            std::fs::read(p.join("run1").join(f)).unwrap()
                == std::fs::read(p.join("run2").join(f)).unwrap(),
            "{f} differs"
        );
    }
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        if e.path().is_dir() {
            copy_dir(&e.path(), &to.join(e.file_name()));
        } else {
            std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
        }
    }
}

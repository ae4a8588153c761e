//! Set-up shared by the CLI's integration tests: running the binary, the tiny dataset the
//! search jobs read, reading an output tree back, and hand-made input files.
// Each test binary compiles this module and uses only part of it.
#![allow(dead_code)]

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// The `nanoeye` binary under test.
pub const BIN: &str = env!("CARGO_BIN_EXE_nanoeye");

/// `nanoeye args` in `cwd`, its output captured (whatever the exit status).
pub fn nanoeye(args: &[&str], cwd: &Path) -> Output {
    Command::new(BIN)
        .args(args)
        .current_dir(cwd)
        .output()
        .expect("run nanoeye")
}

/// `datagen render` arguments of a 1-item (3-frame: anchor, slip, gaze) ambiguity dataset at
/// 80 × 50, 1 spp, written to `out`: the search jobs' smallest input.
pub fn tiny_dataset(out: &str) -> [&str; 14] {
    tiny_dataset_of(out, "1")
}

/// [`tiny_dataset`] with `items` ambiguity items (three frames each).
pub fn tiny_dataset_of<'a>(out: &'a str, items: &'a str) -> [&'a str; 14] {
    [
        "datagen",
        "render",
        "--set",
        "ambiguity",
        "--n",
        items,
        "--width",
        "80",
        "--height",
        "50",
        "--spp",
        "1",
        "--out",
        out,
    ]
}

/// Camera-chain flags the search jobs' tests use on [`tiny_dataset`]`("ds")`.
pub const TINY_CHAIN: [&str; 8] = [
    "--dataset",
    "ds",
    "--pitch-um",
    "60",
    "--aperture-step-um",
    "10",
    "--exposure-ms",
    "0.0004",
];

/// `metalib cell` at the paper's (h, s) = (700, 530) nm and a 200 nm pillar.
pub const CELL: [&str; 8] = [
    "metalib",
    "cell",
    "--height-nm",
    "700",
    "--pitch-nm",
    "530",
    "--diameter-nm",
    "200",
];

/// `search train` flags of a two-step run on [`TINY_CHAIN`] (no random subnets, p̂ within the
/// tiny chain's grids).
pub const TINY_TRAIN: [&str; 8] = [
    "--steps",
    "2",
    "--batch",
    "2",
    "--random-subnets",
    "0",
    "--pitch-range-um",
    "48:120",
];

/// Every file under `dir`: relative path → bytes.
pub fn tree(dir: &Path) -> BTreeMap<PathBuf, Vec<u8>> {
    let mut out = BTreeMap::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else {
                out.insert(
                    p.strip_prefix(dir).unwrap().to_path_buf(),
                    std::fs::read(&p).unwrap(),
                );
            }
        }
    }
    out
}

/// Copies directory `from` (recursively) to `to`.
pub fn copy_dir(from: &Path, to: &Path) {
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

/// A 2-D float64 C-order NPY file.
pub fn npy_f64(rows: usize, cols: usize, data: &[f64]) -> Vec<u8> {
    let mut header =
        format!("{{'descr': '<f8', 'fortran_order': False, 'shape': ({rows}, {cols}), }}");
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    for v in data {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out
}

/// Makes a FIFO at `path` (the inputs that must be refused, not read forever).
pub fn mkfifo(path: &Path) {
    let made = Command::new("mkfifo")
        .arg(path)
        .status()
        .expect("run mkfifo");
    assert!(made.success(), "mkfifo {}", path.display());
}

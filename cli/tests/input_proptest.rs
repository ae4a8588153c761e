//! Property tests over the CLI's input families (issue 19, "Checks"): random numbers, `a:b:step`
//! ranges and lists, files (random bytes, truncations and byte edits of a valid file) and JSON
//! (structural mutations of a valid rig, `--arch` and `--state`) given to fast subcommands of
//! the built binary. Every case ends in one of two ways:
//! - exit status 1 or 2, nothing on stdout, an error on stderr that names the flag (or the key
//!   or file), and nothing written where `--out` points; or
//! - exit status 0 with JSON on stdout that parses, holds no null where a number is promised,
//!   and passes the command's physical checks (energies and transmittances in [0, 1], unit gaze
//!   vectors, counts that add up, MACs between the smallest and largest subnet's, …);
//!
//! never a panic, an abort, a hang (each process is killed and the case fails after
//! [`DEADLINE`]) or a temporary file left behind.
//!
//! Flags whose value sets the amount of work (counts, aperture and period sizes, the length of
//! a range) draw either from a cheap legal band or from values that must be refused: a legal
//! request that is merely large (a 10 mm aperture, 5000 depth planes) is slow by design and not
//! a defect, and it would make this test's time depend on the draw.
//!
//! `PROPTEST_CASES=1000 cargo test -p nanoeye-cli --test input_proptest` searches harder
//! (about 3 min in the debug build on 2 cores).

mod common;

use common::npy_f64;
use nanoeye_metalib::rcwa::ENERGY_TOLERANCE;
use proptest::prelude::*;
use proptest::sample::Index;
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

use common::BIN;
/// A fast subcommand that runs longer than this hangs.
const DEADLINE: Duration = Duration::from_secs(20);

struct Outcome {
    code: i32,
    stdout: String,
    stderr: String,
}

/// Runs `nanoeye args` in `cwd` with a deadline; stdout and stderr go to files outside `cwd`.
fn run(args: &[String], cwd: &Path) -> Outcome {
    let cap = tempfile::tempdir().unwrap();
    let (so, se) = (cap.path().join("stdout"), cap.path().join("stderr"));
    let mut child = Command::new(BIN)
        .args(args)
        .current_dir(cwd)
        .stdin(Stdio::null())
        .stdout(std::fs::File::create(&so).unwrap())
        .stderr(std::fs::File::create(&se).unwrap())
        .env("RUST_BACKTRACE", "0")
        .spawn()
        .expect("spawn nanoeye");
    let t0 = Instant::now();
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        if t0.elapsed() > DEADLINE {
            let _ = child.kill();
            let _ = child.wait();
            panic!("{args:?} hangs: killed after {DEADLINE:?}");
        }
        std::thread::sleep(Duration::from_millis(5));
    };
    let read = |p: &Path| String::from_utf8_lossy(&std::fs::read(p).unwrap()).into_owned();
    let (stdout, stderr) = (read(&so), read(&se));
    let Some(code) = status.code() else {
        panic!("{args:?} died by a signal ({status:?}): {stderr}");
    };
    Outcome {
        code,
        stdout,
        stderr,
    }
}

/// Every path under `dir`, relative.
fn tree(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).into_iter().flatten().flatten() {
            let p = e.path();
            out.push(p.strip_prefix(dir).unwrap().to_path_buf());
            if p.is_dir() {
                stack.push(p);
            }
        }
    }
    out
}

/// Every JSON document on stdout (one, pretty or not, or one per line).
fn documents(stdout: &str) -> Result<Vec<Value>, String> {
    serde_json::Deserializer::from_str(stdout)
        .into_iter::<Value>()
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| format!("stdout is not JSON ({e}): {stdout}"))
}

/// Fails on a null anywhere except under a key in `nullable`.
fn no_null(v: &Value, nullable: &[&str], at: &str) -> Result<(), String> {
    match v {
        Value::Null => Err(format!("null at {at}")),
        Value::Array(a) => a
            .iter()
            .enumerate()
            .try_for_each(|(i, x)| no_null(x, nullable, &format!("{at}[{i}]"))),
        Value::Object(m) => m.iter().try_for_each(|(k, x)| {
            if x.is_null() && nullable.contains(&k.as_str()) {
                Ok(())
            } else {
                no_null(x, nullable, &format!("{at}.{k}"))
            }
        }),
        _ => Ok(()),
    }
}

/// Physical checks of a success's stdout documents (and of its files under the cwd).
type Validator<'a> = &'a dyn Fn(&[Value], &Path) -> Result<(), String>;

/// What a case accepts.
struct Expect<'a> {
    /// A refusal must name one of these (the flag, a key, the file).
    names: &'a [&'a str],
    /// Keys whose value may be null by the output's format.
    nullable: &'a [&'a str],
    valid: Validator<'a>,
}

/// Runs one case and checks it; returns whether it succeeded.
fn check(args: &[String], cwd: &Path, e: &Expect) -> bool {
    let before = tree(cwd);
    let o = run(args, cwd);
    let after = tree(cwd);
    assert!(
        !after.iter().any(|p| p
            .file_name()
            .is_some_and(|n| n.to_string_lossy().starts_with(".nanoeye-tmp-"))),
        "{args:?} left a temporary file: {after:?}"
    );
    assert!(
        !o.stderr.contains("panicked"),
        "{args:?} panicked: {}",
        o.stderr
    );
    match o.code {
        0 => {
            let docs = documents(&o.stdout).unwrap_or_else(|m| panic!("{args:?}: {m}"));
            assert!(!docs.is_empty(), "{args:?}: exit 0 with no output");
            for d in &docs {
                no_null(d, e.nullable, "$")
                    .unwrap_or_else(|m| panic!("{args:?}: {m} in {}", o.stdout));
            }
            (e.valid)(&docs, cwd)
                .unwrap_or_else(|m| panic!("{args:?}: physically invalid: {m}\n{}", o.stdout));
            true
        }
        1 | 2 => {
            assert!(
                o.stdout.is_empty(),
                "{args:?} failed after printing: {}",
                o.stdout
            );
            assert!(
                e.names.iter().any(|n| o.stderr.contains(n)),
                "{args:?}: the error names none of {:?}: {}",
                e.names,
                o.stderr
            );
            assert_eq!(
                before, after,
                "{args:?} was refused but wrote files: {}",
                o.stderr
            );
            false
        }
        c => panic!("{args:?}: exit status {c}: {}", o.stderr),
    }
}

fn strings(v: &[&str]) -> Vec<String> {
    v.iter().map(|s| s.to_string()).collect()
}

fn num(v: &Value, k: &str) -> Result<f64, String> {
    v[k].as_f64()
        .filter(|x| x.is_finite())
        .ok_or_else(|| format!("{k} is not a finite number in {v}"))
}

fn within(x: f64, lo: f64, hi: f64, what: &str) -> Result<(), String> {
    if (lo..=hi).contains(&x) {
        Ok(())
    } else {
        Err(format!("{what} = {x} outside [{lo}, {hi}]"))
    }
}

/// Every number in `v` is finite and ≥ 0.
fn non_negative(v: &Value, at: &str) -> Result<(), String> {
    match v {
        Value::Number(n) => within(n.as_f64().unwrap(), 0.0, f64::MAX, at),
        Value::Array(a) => a
            .iter()
            .enumerate()
            .try_for_each(|(i, x)| non_negative(x, &format!("{at}[{i}]"))),
        Value::Object(m) => m
            .iter()
            .try_for_each(|(k, x)| non_negative(x, &format!("{at}.{k}"))),
        _ => Ok(()),
    }
}

fn one(docs: &[Value]) -> Result<&Value, String> {
    match docs {
        [d] => Ok(d),
        _ => Err(format!("{} documents, expected one", docs.len())),
    }
}

// ---- validators -------------------------------------------------------------------------

fn valid_macs(docs: &[Value], _: &Path) -> Result<(), String> {
    let d = one(docs)?;
    let macs = d["macs"].as_u64().ok_or("macs")?;
    let k = &d["per_kind"];
    let sum: u64 = ["pointwise", "depthwise", "se", "other"]
        .iter()
        .map(|n| k[n].as_u64().unwrap_or(u64::MAX / 8))
        .sum();
    if macs == 0 || sum != macs || d["params"].as_u64().is_none_or(|p| p == 0) {
        return Err(format!("macs {macs}, parts sum {sum}"));
    }
    Ok(())
}

fn valid_ptc(docs: &[Value], _: &Path) -> Result<(), String> {
    let d = one(docs)?;
    for k in ["slope", "intercept"] {
        num(d, k)?;
    }
    within(
        num(d, "slope_expected")?,
        f64::MIN_POSITIVE,
        f64::MAX,
        "slope_expected",
    )?;
    within(
        num(d, "intercept_expected")?,
        0.0,
        f64::MAX,
        "intercept_expected",
    )
}

fn valid_safety(docs: &[Value], _: &Path) -> Result<(), String> {
    non_negative(one(docs)?, "$")
}

fn valid_listing(docs: &[Value], _: &Path) -> Result<(), String> {
    within(num(one(docs)?, "torsion_deg")?, -90.0, 90.0, "torsion_deg")
}

/// Gaze bias reports: counts add up, statistics ordered and within [0°, 180°].
fn valid_bias(docs: &[Value], _: &Path) -> Result<(), String> {
    let d = one(docs)?;
    let reports = d["reports"].as_array().ok_or("reports")?;
    if reports.is_empty() {
        return Err("no report".into());
    }
    for r in reports {
        let c = |k: &str| r[k].as_u64().ok_or(format!("{k} in {r}"));
        let (total, in_view, hidden, missed) =
            (c("total")?, c("in_view")?, c("hidden")?, c("missed")?);
        let n = r["error_deg"]["n"].as_u64().unwrap_or(0);
        if in_view > total || hidden + missed + n != in_view {
            return Err(format!("counts do not add up: {r}"));
        }
        within(
            num(r, "solver_radius_m")?,
            f64::MIN_POSITIVE,
            1.0,
            "solver_radius_m",
        )?;
        if let Some(s) = r["error_deg"].as_object() {
            let g = |k: &str| s[k].as_f64().unwrap_or(f64::NAN);
            let (mean, median, p95, max) = (g("mean"), g("median"), g("p95"), g("max"));
            within(max, 0.0, 180.0, "max error")?;
            within(mean, 0.0, max + 1e-9, "mean error")?;
            if !(median <= p95 + 1e-9 && p95 <= max + 1e-9) {
                return Err(format!("unordered statistics: {r}"));
            }
        }
    }
    Ok(())
}

/// A cell is passive within the solver's own energy slack (a truncated RCWA with Li's
/// factorization conserves energy only approximately; the solver refuses beyond the slack).
fn valid_cell(docs: &[Value], _: &Path) -> Result<(), String> {
    let d = one(docs)?;
    let tol = ENERGY_TOLERANCE;
    let (tau, r, t) = (
        num(d, "transmittance")?,
        num(d, "reflectance")?,
        num(d, "transmitted_total")?,
    );
    within(tau, -tol, t + tol, "zero-order transmittance")?;
    within(r, -tol, 1.0 + tol, "reflectance")?;
    within(t, -tol, 1.0 + tol, "transmitted total")?;
    within(r + t, 0.0, 1.0 + tol, "R + T (a passive cell)")?;
    let phase = num(d, "phase_rad")?;
    within(
        phase,
        -std::f64::consts::PI - 1e-12,
        std::f64::consts::PI + 1e-12,
        "phase",
    )?;
    let (tr, ti) = (num(d, "t_re")?, num(d, "t_im")?);
    if tr.hypot(ti) > 1e3 {
        return Err(format!("|t| = {}", tr.hypot(ti)));
    }
    Ok(())
}

fn valid_states(docs: &[Value], cwd: &Path) -> Result<(), String> {
    let d = one(docs)?;
    let lines = d["lines"].as_u64().ok_or("lines")?;
    let text = std::fs::read_to_string(cwd.join("s.jsonl")).map_err(|e| e.to_string())?;
    if text.lines().count() as u64 != lines {
        return Err(format!(
            "{lines} lines reported, the file has {}",
            text.lines().count()
        ));
    }
    for l in text.lines() {
        let v: Value = serde_json::from_str(l).map_err(|e| format!("{e}: {l}"))?;
        no_null(&v, &[], "line")?;
    }
    Ok(())
}

/// A PSF stack: energy in [0, 1] per plane, peak ≤ energy, the files written.
fn valid_psf(docs: &[Value], cwd: &Path) -> Result<(), String> {
    let d = one(docs)?;
    let planes = d["planes"].as_array().ok_or("planes")?;
    let depths = d["depths_m"].as_array().ok_or("depths_m")?;
    if planes.is_empty() || planes.len() != depths.len() {
        return Err(format!(
            "{} planes for {} depths",
            planes.len(),
            depths.len()
        ));
    }
    within(num(d, "pitch_m")?, f64::MIN_POSITIVE, 1.0, "pitch_m")?;
    for p in planes {
        let e = num(p, "energy")?;
        within(e, 0.0, 1.0 + 1e-6, "energy in the window")?;
        within(num(p, "peak")?, 0.0, e + 1e-12, "peak")?;
        within(num(p, "rms_radius_px")?, 0.0, f64::MAX, "rms radius")?;
        within(num(p, "depth_m")?, f64::MIN_POSITIVE, 1e3, "depth")?;
    }
    for f in ["o/psf.npy", "o/montage.png"] {
        if !cwd.join(f).is_file() {
            return Err(format!("{f} missing"));
        }
    }
    Ok(())
}

fn valid_fisher(docs: &[Value], _: &Path) -> Result<(), String> {
    let d = one(docs)?;
    for r in d["results"].as_array().ok_or("results")? {
        within(num(r, "fisher_z")?, 0.0, f64::MAX, "fisher_z")?;
    }
    non_negative(&d["retained"], "retained")
}

// ---- value strategies -------------------------------------------------------------------

/// Number texts every numeric flag must survive.
const SPECIAL: &[&str] = &[
    "0",
    "-0",
    "-1",
    "1",
    "NaN",
    "nan",
    "inf",
    "-inf",
    "infinity",
    "1e308",
    "-1e308",
    "1e-300",
    "-1e-300",
    "4.9e-324",
    "18446744073709551615",
    "18446744073709551616",
    "9223372036854775808",
    "-9223372036854775808",
    "1e20",
    "abc",
    "",
    " 7",
    "1,5",
    "0x10",
    "1_000",
    "+2",
    "1e",
    ".",
];

fn special() -> BoxedStrategy<String> {
    prop::sample::select(SPECIAL).prop_map(String::from).boxed()
}

fn fmt_f64() -> impl Fn(f64) -> String + Clone {
    |v: f64| format!("{v}")
}

/// Any number text at all: for flags whose value does not set the amount of work.
fn any_number() -> BoxedStrategy<String> {
    prop_oneof![
        2 => special(),
        2 => any::<f64>().prop_map(fmt_f64()),
        1 => any::<f64>().prop_map(|v| format!("{v:e}")),
        1 => any::<u64>().prop_map(|v| v.to_string()),
        1 => any::<i64>().prop_map(|v| v.to_string()),
        2 => (-1e3..1e3f64).prop_map(fmt_f64()),
        1 => (0u64..64).prop_map(|v| v.to_string()),
    ]
    .boxed()
}

/// Magnitudes far outside any physical band, either sign.
fn extreme() -> BoxedStrategy<f64> {
    (any::<bool>(), any::<bool>(), 20.0..308.0f64)
        .prop_map(|(neg, tiny, e)| {
            let m = if tiny { 10f64.powf(-e) } else { 10f64.powf(e) };
            if neg { -m } else { m }
        })
        .boxed()
}

/// A cost-setting real flag: the specials, extremes, or the cheap band [lo, hi].
fn band(lo: f64, hi: f64) -> BoxedStrategy<String> {
    prop_oneof![
        2 => special(),
        2 => extreme().prop_map(fmt_f64()),
        3 => (lo..hi).prop_map(fmt_f64()),
    ]
    .boxed()
}

/// A cost-setting count: the specials, counts in lo..=hi, or beyond 2^32.
fn count(lo: u64, hi: u64) -> BoxedStrategy<String> {
    prop_oneof![
        2 => special(),
        3 => (lo..=hi).prop_map(|v| v.to_string()),
        1 => (1u64 << 32..=u64::MAX).prop_map(|v| v.to_string()),
        1 => (-1000i64..0).prop_map(|v| v.to_string()),
    ]
    .boxed()
}

/// A validator as a plain function.
type Check = fn(&[Value], &Path) -> Result<(), String>;

/// One numeric flag of one command.
struct Target {
    args: &'static [&'static str],
    flag: &'static str,
    value: fn() -> BoxedStrategy<String>,
    nullable: &'static [&'static str],
    valid: Check,
}

const PSF: &[&str] = &[
    "optics",
    "psf",
    "--depths-mm",
    "20:22:1",
    "--window-px",
    "16",
    "--aperture-mm",
    "0.3",
    "--sample-um",
    "3",
    "--out",
    "o",
    "--json",
];
const CELL: &[&str] = &[
    "metalib",
    "cell",
    "--json",
    "--harmonics",
    "2",
    "--height-nm",
    "700",
    "--pitch-nm",
    "530",
    "--diameter-nm",
    "200",
];

/// `args` without `flag` and its value (the target sets it).
fn without(args: &[&str], flag: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut skip = false;
    for a in args {
        if skip {
            skip = false;
        } else if *a == flag {
            skip = true;
        } else {
            out.push(a.to_string());
        }
    }
    out
}

fn t(
    args: &'static [&'static str],
    flag: &'static str,
    value: fn() -> BoxedStrategy<String>,
    valid: Check,
) -> Target {
    Target {
        args,
        flag,
        value,
        nullable: &[],
        valid,
    }
}

fn targets() -> Vec<Target> {
    let mut v = Vec::new();
    for flag in ["--resolution", "--in-channels"] {
        for arch in [
            &["nets", "macs", "--json", "--arch", "max"][..],
            &["nets", "macs", "--json", "--arch", "min"],
            &["nets", "macs", "--json", "--arch", "large"],
        ] {
            // MobileNetV3 large takes no --in-channels (refused whatever its value).
            if flag == "--in-channels" && arch.contains(&"large") {
                continue;
            }
            v.push(t(arch, flag, any_number, valid_macs));
        }
    }
    let ptc: &[&str] = &["sensor", "ptc", "--json", "--side-px", "8", "--levels", "4"];
    v.push(t(ptc, "--levels", || count(0, 64), valid_ptc));
    v.push(t(ptc, "--side-px", || count(0, 32), valid_ptc));
    v.push(t(ptc, "--read-noise-e", any_number, valid_ptc));
    v.push(t(ptc, "--gain-dn-per-e", any_number, valid_ptc));
    v.push(t(ptc, "--seed", any_number, valid_ptc));
    for flag in [
        "--ambient-mw-cm2",
        "--eye-relief-cm",
        "--exposure-ms",
        "--ambient-band-fraction",
        "--outdoor-mw-cm2",
    ] {
        v.push(t(&["safety", "--json"], flag, any_number, valid_safety));
    }
    let listing: &[&str] = &[
        "datagen",
        "listing",
        "--json",
        "--azimuth-deg",
        "10",
        "--elevation-deg",
        "5",
    ];
    v.push(t(listing, "--azimuth-deg", any_number, valid_listing));
    v.push(t(listing, "--elevation-deg", any_number, valid_listing));
    let bias: &[&str] = &["gaze", "bias", "--json", "--steps", "3"];
    v.push(Target {
        nullable: &["error_deg"],
        ..t(bias, "--steps", || count(0, 24), valid_bias)
    });
    v.push(Target {
        nullable: &["error_deg"],
        ..t(bias, "--solver-radii-mm", any_number, valid_bias)
    });
    for flag in [
        "--height-nm",
        "--pitch-nm",
        "--diameter-nm",
        "--wavelength-nm",
    ] {
        v.push(t(CELL, flag, any_number, valid_cell));
    }
    for flag in [
        "--n-pillar",
        "--k-pillar",
        "--n-substrate",
        "--n-background",
    ] {
        v.push(t(CELL, flag, any_number, valid_cell));
    }
    v.push(t(CELL, "--harmonics", || count(0, 4), valid_cell));
    for set in [
        &[
            "datagen",
            "states",
            "--json",
            "--out",
            "s.jsonl",
            "--n",
            "2",
            "--set",
            "ambiguity",
        ][..],
        &[
            "datagen",
            "states",
            "--json",
            "--out",
            "s.jsonl",
            "--n",
            "2",
            "--set",
            "variational",
        ],
        &[
            "datagen", "states", "--json", "--out", "s.jsonl", "--n", "1", "--set", "protocol",
        ],
    ] {
        v.push(t(set, "--n", || count(0, 4), valid_states));
        v.push(t(set, "--seed", any_number, valid_states));
        // Refused on the pair sets unless 7, on the protocol outside 2–7.
        v.push(t(set, "--protocol-grid", || count(0, 9), valid_states));
    }
    v.push(t(PSF, "--aperture-mm", || band(0.02, 0.6), valid_psf));
    v.push(t(PSF, "--sample-um", || band(1.0, 60.0), valid_psf));
    v.push(t(PSF, "--window-px", || count(0, 48), valid_psf));
    v.push(t(PSF, "--period-mm", || band(0.3, 1.5), valid_psf));
    v.push(t(PSF, "--sensor-mm", || band(0.01, 100.0), valid_psf));
    v.push(t(PSF, "--wavelength-nm", || band(100.0, 2e4), valid_psf));
    v.push(t(PSF, "--pitch-um", || band(0.5, 100.0), valid_psf));
    v.push(t(PSF, "--focus-mm", any_number, valid_psf));
    let fc: &[&str] = &[
        "fisher",
        "compare",
        "--json",
        "--lenses",
        "hyperbolic,double-helix",
        "--depths-mm",
        "20:22:1",
        "--pitch-um",
        "3,9",
        "--window-px",
        "9",
        "--aperture-step-um",
        "50",
        "--montage",
        "m.png",
    ];
    v.push(t(fc, "--photons", any_number, valid_fisher));
    v.push(t(fc, "--pitch-um", || band(3.0, 30.0), valid_fisher));
    v
}

// ---- ranges ---------------------------------------------------------------------------

/// A range or list text: mostly `a:b:step` with parts from `part` and `step`, also one part,
/// two, four, and stray separators.
fn range_text(part: BoxedStrategy<String>, step: BoxedStrategy<String>) -> BoxedStrategy<String> {
    prop_oneof![
        8 => (part.clone(), part.clone(), step.clone())
            .prop_map(|(a, b, c)| format!("{a}:{b}:{c}")),
        1 => part.clone(),
        1 => (part.clone(), part.clone()).prop_map(|(a, b)| format!("{a}:{b}")),
        1 => (part.clone(), part.clone(), step, part)
            .prop_map(|(a, b, c, d)| format!("{a}:{b}:{c}:{d}")),
        1 => prop::sample::select(&[":", "::", "1::2", ":1:1", "1:2:", " : : "][..])
            .prop_map(String::from),
    ]
    .boxed()
}

/// Range parts: the specials (with their extremes), or the band [lo, hi]; steps at least a
/// sixteenth of the band (or a special, or a tiny positive step whose count must be refused).
fn range_in(lo: f64, hi: f64) -> BoxedStrategy<String> {
    let part = prop_oneof![1 => special(), 4 => (lo..hi).prop_map(fmt_f64())].boxed();
    let step = prop_oneof![
        1 => special(),
        1 => (20.0..300.0f64).prop_map(|e| format!("{:e}", 10f64.powf(-e))),
        4 => ((hi - lo) / 16.0..(hi - lo)).prop_map(fmt_f64()),
    ]
    .boxed();
    range_text(part, step)
}

/// Numbers in `a:b:c`: first, last and spacing when it parses as a grid (the test's reading).
fn parsed_range(text: &str, scale: f64) -> Option<(f64, f64, f64)> {
    let p: Vec<f64> = text
        .split(':')
        .map(|s| s.trim().parse::<f64>().ok())
        .collect::<Option<_>>()?;
    match p[..] {
        [a] => Some((a * scale, a * scale, 0.0)),
        [a, b, c] => Some((a * scale, b * scale, c * scale)),
        _ => None,
    }
}

/// Values printed for a range lie on its grid: the first at `a`, increasing by `step`, ≤ `b`.
fn on_grid(values: &[f64], (a, b, step): (f64, f64, f64)) -> Result<(), String> {
    let tol = 1e-9 * a.abs().max(b.abs()).max(1e-300);
    if values.is_empty() || (values[0] - a).abs() > tol {
        return Err(format!("{values:?} does not start at {a}"));
    }
    for (i, w) in values.iter().enumerate() {
        let expect = a + i as f64 * step;
        if (w - expect).abs() > tol.max(1e-9 * expect.abs()) || *w > b + tol {
            return Err(format!("{values:?} is not the grid {a}:{b}:{step}"));
        }
    }
    Ok(())
}

// ---- files ----------------------------------------------------------------------------

/// One edit of a file's bytes.
#[derive(Debug, Clone)]
enum Edit {
    Truncate(Index),
    Flip(Index, u8),
    Set(Index, u8),
    Insert(Index, Vec<u8>),
    Delete(Index, Index),
    Replace(Vec<u8>),
    Duplicate(Index, Index),
}

fn edit() -> impl Strategy<Value = Edit> {
    let interesting = prop::sample::select(
        &[
            b'\n', b'\r', 0, 0xFF, 0xEF, b'"', b'{', b'}', b'[', b']', b',', b':', b'-', b'e',
            b'9', b' ', 0x80, b'\\',
        ][..],
    );
    prop_oneof![
        any::<Index>().prop_map(Edit::Truncate),
        (any::<Index>(), 1u8..=255).prop_map(|(i, m)| Edit::Flip(i, m)),
        (any::<Index>(), interesting).prop_map(|(i, b)| Edit::Set(i, b)),
        (any::<Index>(), prop::collection::vec(any::<u8>(), 1..16))
            .prop_map(|(i, b)| Edit::Insert(i, b)),
        (any::<Index>(), any::<Index>()).prop_map(|(i, j)| Edit::Delete(i, j)),
        prop::collection::vec(any::<u8>(), 0..200).prop_map(Edit::Replace),
        (any::<Index>(), any::<Index>()).prop_map(|(i, j)| Edit::Duplicate(i, j)),
    ]
}

fn apply(valid: &[u8], edits: &[Edit]) -> Vec<u8> {
    let mut b = valid.to_vec();
    for e in edits {
        let n = b.len();
        let at = |i: &Index| if n == 0 { 0 } else { i.index(n + 1) };
        match e {
            Edit::Truncate(i) => b.truncate(at(i)),
            Edit::Flip(i, m) if n > 0 => b[i.index(n)] ^= m,
            Edit::Set(i, v) if n > 0 => b[i.index(n)] = *v,
            Edit::Insert(i, x) => {
                let k = at(i);
                b.splice(k..k, x.iter().copied());
            }
            Edit::Delete(i, j) => {
                let (x, y) = (at(i), at(j));
                b.drain(x.min(y)..x.max(y));
            }
            Edit::Replace(x) => b = x.clone(),
            Edit::Duplicate(i, j) => {
                let (x, y) = (at(i), at(j));
                let part = b[x.min(y)..x.max(y)].to_vec();
                b.extend(part);
            }
            _ => {}
        }
    }
    b
}

/// The input lines `gaze solve` answers, by line number: every line except the UTF-8 ones
/// that are blank once the line ending (and, on line 1, a byte-order mark) is removed.
fn answered_lines(bytes: &[u8]) -> Vec<usize> {
    let mut out = Vec::new();
    let mut lines: Vec<&[u8]> = bytes.split(|b| *b == b'\n').collect();
    if lines.last().is_some_and(|l| l.is_empty()) {
        lines.pop();
    }
    for (k, l) in lines.iter().enumerate() {
        let mut l = l.strip_suffix(b"\r").unwrap_or(l);
        if k == 0 {
            l = l.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(l);
        }
        match std::str::from_utf8(l) {
            Ok(s) if s.trim().is_empty() => {}
            _ => out.push(k + 1),
        }
    }
    out
}

fn unit(v: &Value) -> Result<(), String> {
    let g: Vec<f64> = serde_json::from_value(v.clone()).map_err(|e| format!("{e}: {v}"))?;
    let n = g.iter().map(|x| x * x).sum::<f64>().sqrt();
    if g.len() == 3 && (n - 1.0).abs() < 1e-9 {
        Ok(())
    } else {
        Err(format!("not a unit 3-vector: {v}"))
    }
}

/// `gaze solve`'s answer: one line per answered input line, a unit gaze or a per-line error
/// that names its line.
fn valid_solve(docs: &[Value], lines: &[usize]) -> Result<(), String> {
    if docs.len() != lines.len() {
        return Err(format!("{} answers for input lines {lines:?}", docs.len()));
    }
    for (d, n) in docs.iter().zip(lines) {
        if let Some(e) = d.get("error") {
            let e = e.as_str().ok_or("error is not a string")?;
            if !e.starts_with(&format!("line {n}:")) {
                return Err(format!("input line {n} answered by '{e}'"));
            }
        } else {
            unit(&d["gaze"])?;
            for k in ["pupil_3d_m", "pupil_px"] {
                let v = d[k].as_array().ok_or(format!("{k} in {d}"))?;
                if v.iter().any(|x| !x.as_f64().is_some_and(f64::is_finite)) {
                    return Err(format!("{k} in {d}"));
                }
            }
            if let Some(v) = d.get("visual_axis") {
                unit(v)?;
            }
        }
    }
    Ok(())
}

/// A valid 8×8 grey PNG with a dark disc (a pupil mask).
fn mask_png() -> Vec<u8> {
    let img = image::GrayImage::from_fn(8, 8, |x, y| {
        let r2 = (x as i32 - 4).pow(2) + (y as i32 - 4).pow(2);
        image::Luma([if r2 < 6 { 255 } else { 0 }])
    });
    let mut b = Vec::new();
    img.write_to(&mut std::io::Cursor::new(&mut b), image::ImageFormat::Png)
        .unwrap();
    b
}

const QUERIES: &str = "{\"pupil_px\":[160,100]}\n{\"pupil_px\":[150.5,90],\"slip_m\":[0.001,0,-0.002]}\n\
{\"mask_png\":\"m.png\"}\n\n{\"pupil_px\":[170,110],\"slip_m\":[0,0.0005,0]}\n";

// ---- JSON mutations -------------------------------------------------------------------

/// A JSON value put in place of another (`"__raw:X"` strings become the raw token X).
fn replacement() -> BoxedStrategy<Value> {
    let raw = prop::sample::select(&["NaN", "Infinity", "-Infinity", "1e999", "-1e999", "nan"][..])
        .prop_map(|t| Value::String(format!("__raw:{t}")));
    prop_oneof![
        3 => prop::sample::select(
            &[0.0, -0.0, -1.0, 1.0, 1e308, -1e308, 1e-300, -1e-300, 5e-324, 1.8446744073709552e19,
              0.5, 2.0, 1e6, -1e6][..]
        )
        .prop_map(Value::from),
        2 => any::<f64>().prop_filter("finite", |v| v.is_finite()).prop_map(Value::from),
        1 => any::<u64>().prop_map(Value::from),
        1 => any::<i64>().prop_map(Value::from),
        1 => raw,
        1 => prop_oneof![
            Just(Value::Null),
            Just(Value::Bool(true)),
            Just(Value::String("x".into())),
            Just(serde_json::json!([])),
            Just(serde_json::json!({})),
            Just(serde_json::json!([1.0])),
            Just(serde_json::json!([0.0, 0.0, 0.0, 0.0])),
        ],
    ]
    .boxed()
}

/// One structural edit of a JSON document.
#[derive(Debug, Clone)]
enum JsonEdit {
    /// Replace the value at a path.
    Replace(Index, Value),
    /// Scale the number at a path.
    Scale(Index, f64),
    /// Remove the key or element at a path.
    Remove(Index),
    /// Add an unknown key to an object at a path.
    Unknown(Index),
}

fn json_edit() -> impl Strategy<Value = JsonEdit> {
    prop_oneof![
        3 => (any::<Index>(), replacement()).prop_map(|(i, v)| JsonEdit::Replace(i, v)),
        3 => (
            any::<Index>(),
            prop::sample::select(&[-1.0, 0.0, 1e-3, 0.5, 1.0 + 1e-9, 2.0, 1e3, 1e300][..])
        )
            .prop_map(|(i, f)| JsonEdit::Scale(i, f)),
        1 => any::<Index>().prop_map(JsonEdit::Remove),
        1 => any::<Index>().prop_map(JsonEdit::Unknown),
    ]
}

/// JSON pointers of every value under `v` (the root excluded).
fn paths(v: &Value, at: String, out: &mut Vec<String>) {
    match v {
        Value::Object(m) => {
            for (k, x) in m {
                let p = format!("{at}/{k}");
                out.push(p.clone());
                paths(x, p, out);
            }
        }
        Value::Array(a) => {
            for (i, x) in a.iter().enumerate() {
                let p = format!("{at}/{i}");
                out.push(p.clone());
                paths(x, p, out);
            }
        }
        _ => {}
    }
}

/// The edited document's text (raw tokens such as NaN put in place).
fn mutate(valid: &Value, edits: &[JsonEdit]) -> String {
    let mut v = valid.clone();
    for e in edits {
        let mut ps = Vec::new();
        paths(&v, String::new(), &mut ps);
        if ps.is_empty() {
            break;
        }
        let pick = |i: &Index| ps[i.index(ps.len())].clone();
        match e {
            JsonEdit::Replace(i, x) => *v.pointer_mut(&pick(i)).unwrap() = x.clone(),
            JsonEdit::Scale(i, f) => {
                let p = pick(i);
                let t = v.pointer_mut(&p).unwrap();
                if let Some(x) = t.as_f64()
                    && let Some(n) = serde_json::Number::from_f64(x * f)
                {
                    *t = Value::Number(n);
                }
            }
            JsonEdit::Remove(i) => {
                let p = pick(i);
                let (parent, last) = p.rsplit_once('/').unwrap();
                match v.pointer_mut(parent).unwrap() {
                    Value::Object(m) => {
                        m.remove(last);
                    }
                    Value::Array(a) => {
                        a.remove(last.parse::<usize>().unwrap());
                    }
                    _ => unreachable!(),
                }
            }
            JsonEdit::Unknown(i) => {
                let p = pick(i);
                let (parent, _) = p.rsplit_once('/').unwrap();
                if let Value::Object(m) = v.pointer_mut(parent).unwrap() {
                    m.insert("unknown_key".into(), Value::from(1.0));
                }
            }
        }
    }
    let mut text = v.to_string();
    for t in ["NaN", "Infinity", "-Infinity", "1e999", "-1e999", "nan"] {
        text = text.replace(&format!("\"__raw:{t}\""), t);
    }
    text
}

/// An accepted rig file is printed back as it was read: when the file is JSON with exactly
/// the built-in rig's keys, every value is the file's (nothing clamped, normalized or
/// defaulted in silence).
fn printed_as_read(printed: &Value, file: &[u8]) -> Result<(), String> {
    let Ok(read) = serde_json::from_slice::<Value>(file) else {
        return Ok(());
    };
    let (mut a, mut b) = (Vec::new(), Vec::new());
    paths(&read, String::new(), &mut a);
    paths(default_rig(), String::new(), &mut b);
    a.sort();
    b.sort();
    if a == b && !same_json(printed, &read) {
        return Err(format!("the accepted rig {printed} differs from the file"));
    }
    Ok(())
}

/// Equal as JSON with every number compared as f64 (1 and 1.0 are the same value).
fn same_json(a: &Value, b: &Value) -> bool {
    match (a, b) {
        (Value::Number(x), Value::Number(y)) => x.as_f64() == y.as_f64(),
        (Value::Array(x), Value::Array(y)) => {
            x.len() == y.len() && x.iter().zip(y).all(|(p, q)| same_json(p, q))
        }
        (Value::Object(x), Value::Object(y)) => {
            x.len() == y.len()
                && x.iter()
                    .all(|(k, p)| y.get(k).is_some_and(|q| same_json(p, q)))
        }
        _ => a == b,
    }
}

fn default_rig() -> &'static Value {
    static RIG: OnceLock<Value> = OnceLock::new();
    RIG.get_or_init(|| {
        let d = tempfile::tempdir().unwrap();
        let o = run(&strings(&["rig", "show", "--json"]), d.path());
        assert_eq!(o.code, 0, "{}", o.stderr);
        serde_json::from_str(&o.stdout).unwrap()
    })
}

/// A valid supernet subnet (kernel, expansion per layer, depth per stage, resolution scale).
fn valid_arch() -> Value {
    serde_json::json!({
        "kernel": [3, 5, 7, 3, 5, 7, 3, 5, 7, 3, 5, 7, 3, 5, 7, 3, 5, 7, 3, 5],
        "expand": [3, 4, 6, 3, 4, 6, 3, 4, 6, 3, 4, 6, 3, 4, 6, 3, 4, 6, 3, 4],
        "depth": [2, 3, 4, 2, 3],
        "resolution_scale": 0.8,
    })
}

/// MACs of the smallest and largest subnet at 224 px.
fn macs_bounds() -> (u64, u64) {
    static B: OnceLock<(u64, u64)> = OnceLock::new();
    *B.get_or_init(|| {
        let d = tempfile::tempdir().unwrap();
        let m = |arch: &str| {
            let o = run(
                &strings(&["nets", "macs", "--json", "--arch", arch]),
                d.path(),
            );
            assert_eq!(o.code, 0, "{}", o.stderr);
            serde_json::from_str::<Value>(&o.stdout).unwrap()["macs"]
                .as_u64()
                .unwrap()
        };
        (m("min"), m("max"))
    })
}

fn valid_arch_macs(docs: &[Value], cwd: &Path) -> Result<(), String> {
    valid_macs(docs, cwd)?;
    let (lo, hi) = macs_bounds();
    within(
        docs[0]["macs"].as_u64().unwrap() as f64,
        lo as f64,
        hi as f64,
        "subnet MACs",
    )
}

const STATE: &str = r#"{"azimuth_rad":0.1,"elevation_rad":-0.1,"torsion_rad":0.01,"slip_m":[0.001,0,-0.002],"cam_rot_rad":[0.01,0,0],"lid_closure":0.2}"#;

fn valid_glb(docs: &[Value], cwd: &Path) -> Result<(), String> {
    let d = one(docs)?;
    let b = std::fs::read(cwd.join("s.glb")).map_err(|e| e.to_string())?;
    if &b[0..4] != b"glTF"
        || u32::from_le_bytes(b[8..12].try_into().unwrap()) as usize != b.len()
        || d["bytes"].as_u64() != Some(b.len() as u64)
    {
        return Err("not a whole GLB file".into());
    }
    Ok(())
}

// ---- the properties -------------------------------------------------------------------

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    /// Numbers: one numeric flag of one fast command set to any number text.
    #[test]
    fn numbers_are_refused_by_flag_or_give_valid_results(
        (k, value) in (0..targets().len()).prop_flat_map(|k| (Just(k), (targets()[k].value)()))
    ) {
        let t = &targets()[k];
        let d = tempfile::tempdir().unwrap();
        let mut args = without(t.args, t.flag);
        args.push(format!("{}={value}", t.flag));
        check(&args, d.path(), &Expect { names: &[t.flag], nullable: t.nullable, valid: &t.valid });
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(32))]

    /// Ranges: depth planes of a PSF stack; the printed depths are the range's grid.
    #[test]
    fn psf_depth_ranges(r in range_in(15.0, 30.0)) {
        let d = tempfile::tempdir().unwrap();
        let mut args = without(PSF, "--depths-mm");
        args.push(format!("--depths-mm={r}"));
        let valid = |docs: &[Value], cwd: &Path| {
            valid_psf(docs, cwd)?;
            let z: Vec<f64> = serde_json::from_value(docs[0]["depths_m"].clone())
                .map_err(|e| e.to_string())?;
            on_grid(&z, parsed_range(&r, 1e-3).ok_or("printed depths for an unparsable range")?)
        };
        check(&args, d.path(), &Expect { names: &["--depths-mm"], nullable: &[], valid: &valid });
    }

    /// Ranges: one axis of a sweep, solved (one harmonic) into --out; the manifest is complete.
    #[test]
    fn sweep_axis_ranges(
        axis in 0usize..3,
        r in prop_oneof![range_in(100.0, 1500.0), range_in(300.0, 900.0), range_in(0.1, 0.9)],
    ) {
        let d = tempfile::tempdir().unwrap();
        let mut args = strings(&[
            "metalib", "sweep", "--json", "--harmonics", "1", "--out", "sw",
            "--heights-nm", "700:700:10", "--pitches-nm", "530:530:10", "--fractions", "0.4:0.4:0.1",
        ]);
        let flag = ["--heights-nm", "--pitches-nm", "--fractions"][axis];
        args = without(&args.iter().map(String::as_str).collect::<Vec<_>>(), flag);
        args.push(format!("{flag}={r}"));
        let valid = |docs: &[Value], cwd: &Path| {
            let m = one(docs)?;
            let shape: Vec<u64> = serde_json::from_value(m["shape"].clone())
                .map_err(|e| format!("shape: {e}"))?;
            let n = parsed_range(&r, 1.0).ok_or("a sweep of an unparsable range")?;
            let count = ((n.1 - n.0) / n.2 + 1e-9).floor() as u64 + 1;
            if m["complete"] != true || shape.iter().product::<u64>() != count.max(1) {
                return Err(format!("shape {shape:?} for {count} values"));
            }
            for f in ["manifest.json", "phase.npy", "transmittance.npy", "t_re.npy", "t_im.npy"] {
                if !cwd.join("sw").join(f).is_file() {
                    return Err(format!("{f} missing"));
                }
            }
            Ok(())
        };
        check(&args, d.path(), &Expect { names: &[flag], nullable: &[], valid: &valid });
    }

    /// Ranges: any text as a sweep axis, planned over 2 ranks (no solving).
    #[test]
    fn sweep_plan_ranges(
        axis in 0usize..3,
        r in prop_oneof![
            range_in(100.0, 1500.0),
            range_in(0.1, 0.9),
            "[0-9:.eE+ -]{0,14}",
        ],
    ) {
        let d = tempfile::tempdir().unwrap();
        let flag = ["--heights-nm", "--pitches-nm", "--fractions"][axis];
        let args = vec![
            "metalib".into(), "sweep".into(), "--plan-ranks".into(), "2".into(),
            format!("{flag}={r}"),
        ];
        let valid = |docs: &[Value], _: &Path| {
            let p = one(docs)?;
            within(num(p, "imbalance")?, 1.0 - 1e-12, 2.0 + 1e-12, "imbalance of 2 shares")?;
            let shares = p["pitches_nm"].as_array().ok_or("pitches_nm")?;
            if shares.len() != 2 {
                return Err("not 2 shares".into());
            }
            Ok(())
        };
        check(&args, d.path(), &Expect { names: &[flag], nullable: &[], valid: &valid });
    }

    /// Ranges and lists: Fisher depth ranges and the bias study's solver radii.
    #[test]
    fn fisher_depths_and_bias_radii(
        depths in range_in(15.0, 30.0),
        radii in prop::collection::vec(band(5.0, 20.0), 1..4),
    ) {
        let d = tempfile::tempdir().unwrap();
        let mut args = strings(&[
            "fisher", "compare", "--json", "--lenses", "hyperbolic", "--pitch-um", "3,9",
            "--window-px", "9", "--aperture-step-um", "50", "--montage", "m.png",
        ]);
        args.push(format!("--depths-mm={depths}"));
        check(&args, d.path(), &Expect { names: &["--depths-mm"], nullable: &[], valid: &valid_fisher });
        let radii = radii.join(",");
        let args = vec![
            "gaze".into(), "bias".into(), "--json".into(), "--steps".into(), "3".into(),
            format!("--solver-radii-mm={radii}"),
        ];
        check(&args, d.path(), &Expect {
            names: &["--solver-radii-mm"], nullable: &["error_deg"], valid: &valid_bias,
        });
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(32))]

    /// Files: a JSONL query file (and the mask PNG it names) with random edits; the batch
    /// answers every non-blank line with a unit gaze or an error naming that line.
    #[test]
    fn gaze_solve_answers_every_line_of_an_edited_query_file(
        q_edits in prop::collection::vec(edit(), 0..4),
        png_edits in prop::collection::vec(edit(), 0..3),
        refractive in any::<bool>(),
        to_file in any::<bool>(),
    ) {
        let d = tempfile::tempdir().unwrap();
        let q = apply(QUERIES.as_bytes(), &q_edits);
        std::fs::write(d.path().join("q.jsonl"), &q).unwrap();
        std::fs::write(d.path().join("m.png"), apply(&mask_png(), &png_edits)).unwrap();
        let mut args = strings(&["gaze", "solve", "--input", "q.jsonl", "--kappa"]);
        if refractive {
            args.extend(strings(&["--solver", "refractive"]));
        }
        if to_file {
            args.extend(strings(&["--out", "r.jsonl"]));
        }
        let lines = answered_lines(&q);
        let valid = |docs: &[Value], cwd: &Path| {
            if to_file {
                // stdout was empty: documents() found nothing; read the file instead.
                let text = std::fs::read_to_string(cwd.join("r.jsonl")).map_err(|e| e.to_string())?;
                let docs = documents(&text)?;
                for x in &docs {
                    no_null(x, &[], "$")?;
                }
                valid_solve(&docs, &lines)
            } else {
                valid_solve(docs, &lines)
            }
        };
        if lines.is_empty() {
            // Nothing to answer: refused naming --input, nothing printed or written.
            let o = run(&args, d.path());
            prop_assert!(!o.stderr.contains("panicked"), "{}", o.stderr);
            prop_assert_eq!(o.code, 1, "{}", o.stderr);
            prop_assert!(o.stderr.contains("--input"), "{}", o.stderr);
            prop_assert!(o.stdout.trim().is_empty(), "{}", o.stdout);
            prop_assert!(!d.path().join("r.jsonl").exists());
        } else if to_file {
            // The answer goes to the file; stdout stays empty, so check by hand. A file with
            // no valid query is refused naming --input, and nothing is written.
            let o = run(&args, d.path());
            prop_assert!(!o.stderr.contains("panicked"), "{}", o.stderr);
            prop_assert!(o.stdout.is_empty());
            if o.code == 1 {
                prop_assert!(o.stderr.contains("--input"), "{}", o.stderr);
                prop_assert!(!d.path().join("r.jsonl").exists());
            } else {
                prop_assert_eq!(o.code, 0, "{}", o.stderr);
                valid(&[], d.path()).unwrap();
            }
        } else {
            check(&args, d.path(), &Expect { names: &["--input"], nullable: &[], valid: &valid });
        }
    }

    /// Files: an edited rig file, `--arch` file, phase map (NPY) and library CSV.
    #[test]
    fn edited_rig_arch_npy_and_csv_files(
        which in 0usize..4,
        edits in prop::collection::vec(edit(), 1..4),
    ) {
        let d = tempfile::tempdir().unwrap();
        let p = d.path();
        match which {
            0 => {
                let rig = serde_json::to_vec_pretty(default_rig()).unwrap();
                let edited = apply(&rig, &edits);
                std::fs::write(p.join("r.json"), &edited).unwrap();
                let args = strings(&["rig", "show", "--json", "--rig", "r.json"]);
                check(&args, p, &Expect { names: &["--rig"], nullable: &[], valid: &|docs, _| {
                    printed_as_read(one(docs)?, &edited)
                }});
            }
            1 => {
                let arch = valid_arch().to_string();
                std::fs::write(p.join("a.json"), apply(arch.as_bytes(), &edits)).unwrap();
                let args = strings(&["nets", "macs", "--json", "--arch", "file:a.json"]);
                check(&args, p, &Expect { names: &["--arch"], nullable: &[], valid: &valid_arch_macs });
            }
            2 => {
                // A 100 × 100 phase map: the PSF command's 0.3 mm aperture at 3 µm.
                let phase: Vec<f64> = (0..100 * 100)
                    .map(|i| ((i % 100) as f64 - 50.0).powi(2) * 1e-3 + (i / 100) as f64 * 1e-2)
                    .collect();
                std::fs::write(p.join("p.npy"), apply(&npy_f64(100, 100, &phase), &edits)).unwrap();
                let mut args = without(PSF, "--lens");
                args.push("--lens=file:p.npy".into());
                check(&args, p, &Expect { names: &["--lens"], nullable: &[], valid: &valid_psf });
            }
            _ => {
                let csv: String = (0..32)
                    .map(|i| format!("{},{},0.95\n", 100.0 + 10.0 * i as f64, 0.2 * i as f64))
                    .collect();
                std::fs::write(p.join("lib.csv"), apply(csv.as_bytes(), &edits)).unwrap();
                std::fs::write(p.join("phase.npy"), npy_f64(2, 3, &[0.0, 1.0, 2.0, 3.0, 4.0, 5.0])).unwrap();
                let args = strings(&[
                    "metalib", "blueprint", "--json", "--phase", "phase.npy", "--height-nm", "700",
                    "--pitch-nm", "500", "--out", "bp", "--library-csv", "lib.csv",
                    "--square-aperture",
                ]);
                let valid = |docs: &[Value], cwd: &Path| {
                    let b = one(docs)?;
                    let (lo, hi) = (num(b, "diameter_min_nm")?, num(b, "diameter_max_nm")?);
                    within(lo, 0.0, hi, "smallest diameter")?;
                    within(hi, lo, 500.0, "largest diameter (pitch 500 nm)")?;
                    let (rms, max) = (num(b, "rms_phase_error_rad")?, num(b, "max_phase_error_rad")?);
                    within(max, 0.0, std::f64::consts::PI + 1e-9, "max phase error")?;
                    within(rms, 0.0, max + 1e-12, "rms phase error")?;
                    within(b["pillars"].as_u64().ok_or("pillars")? as f64, 0.0, 6.0, "pillars")?;
                    for f in ["diameters.npy", "layout.gds", "preview.png"] {
                        if !cwd.join("bp").join(f).is_file() {
                            return Err(format!("{f} missing"));
                        }
                    }
                    Ok(())
                };
                check(&args, p, &Expect { names: &["--library-csv"], nullable: &[], valid: &valid });
            }
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(32))]

    /// JSON: a mutated rig is refused naming --rig, or accepted as written (printed back
    /// unchanged) and used by the solver, the bias study and the state sampler.
    #[test]
    fn mutated_rigs(edits in prop::collection::vec(json_edit(), 1..4)) {
        let d = tempfile::tempdir().unwrap();
        let p = d.path();
        let text = mutate(default_rig(), &edits);
        std::fs::write(p.join("r.json"), &text).unwrap();
        let names: &[&str] = &["--rig"];
        let printed_back = |docs: &[Value], _: &Path| printed_as_read(one(docs)?, text.as_bytes());
        let accepted = check(&strings(&["rig", "show", "--json", "--rig", "r.json"]), p,
            &Expect { names, nullable: &[], valid: &printed_back });
        std::fs::write(p.join("q.jsonl"), QUERIES).unwrap();
        std::fs::write(p.join("m.png"), mask_png()).unwrap();
        let lines = answered_lines(QUERIES.as_bytes());
        let solved = check(&strings(&["gaze", "solve", "--kappa", "--input", "q.jsonl", "--rig", "r.json"]), p,
            &Expect { names, nullable: &[], valid: &|docs, _| valid_solve(docs, &lines) });
        let biased = check(&strings(&["gaze", "bias", "--json", "--steps", "3", "--rig", "r.json"]), p,
            &Expect { names, nullable: &["error_deg"], valid: &valid_bias });
        // The sampler may refuse a valid rig whose camera never sees the pupil (naming --rig).
        let sampled = check(
            &strings(&["datagen", "states", "--json", "--set", "ambiguity", "--n", "2",
                       "--out", "s.jsonl", "--rig", "r.json"]), p,
            &Expect { names, nullable: &[], valid: &valid_states });
        // One validation: a rig the loader refuses is refused by every command.
        prop_assert!(accepted || !(solved || biased || sampled), "{}", text);
        prop_assert_eq!(accepted, solved, "{}", text);
    }

    /// JSON: a mutated `--arch` is refused naming --arch, or costs between the smallest and
    /// the largest subnet.
    #[test]
    fn mutated_arch(edits in prop::collection::vec(json_edit(), 1..4)) {
        let d = tempfile::tempdir().unwrap();
        let text = mutate(&valid_arch(), &edits);
        std::fs::write(d.path().join("a.json"), &text).unwrap();
        check(&strings(&["nets", "macs", "--json", "--arch", "file:a.json"]), d.path(),
            &Expect { names: &["--arch"], nullable: &[], valid: &valid_arch_macs });
    }

    /// JSON: a mutated `--state` for the GLB export is refused naming --state or the key, or
    /// gives a whole GLB file.
    #[test]
    fn mutated_export_state(edits in prop::collection::vec(json_edit(), 1..3)) {
        let d = tempfile::tempdir().unwrap();
        let text = mutate(&serde_json::from_str(STATE).unwrap(), &edits);
        let args = vec![
            "datagen".into(), "export".into(), "--json".into(), "--out".into(), "s.glb".into(),
            format!("--state={text}"),
        ];
        check(&args, d.path(), &Expect {
            names: &["--state", "azimuth_rad", "elevation_rad", "torsion_rad", "slip_m",
                     "cam_rot_rad", "lid_closure"],
            nullable: &[],
            valid: &valid_glb,
        });
    }
}

//! Bad-input regressions (issue 19, section 3): every refused request exits non-zero with a
//! message naming the flag, never panics, and leaves no partial output behind.

mod common;

use common::{nanoeye, npy_f64, tiny_dataset, tiny_dataset_of};
use std::path::Path;

/// Runs `args`, expects a clean refusal that names `flag`.
fn refused(args: &[&str], flag: &str, cwd: &Path) -> String {
    let out = nanoeye(args, cwd);
    let err = String::from_utf8_lossy(&out.stderr).to_string();
    assert!(!out.status.success(), "{args:?} succeeded: {err}");
    assert!(!err.contains("panicked"), "{args:?} panicked: {err}");
    assert!(
        err.contains(flag),
        "{args:?}: error does not name {flag}: {err}"
    );
    err
}

/// `out` of a command that must have succeeded; its stderr in the failure message.
fn succeeded(out: std::process::Output) -> std::process::Output {
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

fn entries(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .map(|r| {
            r.flatten()
                .map(|e| e.file_name().to_string_lossy().into_owned())
                .collect()
        })
        .unwrap_or_default();
    v.sort();
    v
}

#[test]
fn huge_counts_are_refused_naming_the_flag() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    let max = "18446744073709551615";
    let tera = "1000000000000";
    for (args, flag) in [
        (
            vec![
                "nets",
                "fit-toy",
                "--steps",
                "1",
                "--batch",
                "2",
                "--size-px",
                max,
                "--min-only",
            ],
            "--size-px",
        ),
        (
            vec!["nets", "fit-toy", "--batch", tera, "--min-only"],
            "--batch",
        ),
        (
            vec!["nets", "fit-toy", "--size-px", "100000000", "--min-only"],
            "--size-px",
        ),
        (
            vec!["nets", "fit-toy", "--batch", "1", "--size-px", "16"],
            "--batch",
        ),
        (vec!["nets", "fit-toy", "--lr", "1e30"], "--lr"),
        (
            vec!["nets", "macs", "--arch", "max", "--resolution", max],
            "--resolution",
        ),
        (
            vec!["nets", "macs", "--arch", "large", "--resolution", max],
            "--resolution",
        ),
        (
            vec!["nets", "macs", "--arch", "max", "--in-channels", max],
            "--in-channels",
        ),
        // Ignored before: MobileNetV3 is counted for 3-channel images.
        (
            vec!["nets", "macs", "--arch", "large", "--in-channels", "1"],
            "--in-channels",
        ),
        (
            vec!["sensor", "ptc", "--levels", max, "--side-px", "8"],
            "--levels",
        ),
        (vec!["sensor", "ptc", "--levels", tera], "--levels"),
        (
            vec![
                "sensor",
                "ptc",
                "--gain-dn-per-e",
                "1e-10",
                "--side-px",
                "8",
                "--json",
            ],
            "--gain-dn-per-e",
        ),
        (
            vec![
                "datagen",
                "states",
                "--set",
                "ambiguity",
                "--n",
                tera,
                "--out",
                "s.jsonl",
            ],
            "--n",
        ),
        (
            vec![
                "datagen", "states", "--set", "protocol", "--n", tera, "--out", "s.jsonl",
            ],
            "--n",
        ),
        (vec!["run", "--subjects", tera], "--subjects"),
        (vec!["gaze", "bias", "--steps", tera], "--steps"),
        // The same sweep twice: its rows were printed twice (a helper's audit).
        (
            vec!["gaze", "bias", "--steps", "2", "--solver-radii-mm=10,11,10"],
            "--solver-radii-mm: 10 mm is given twice",
        ),
        (
            vec![
                "metalib",
                "sweep",
                "--harmonics",
                "2",
                "--out",
                "sw",
                "--heights-nm",
                "700:700:10",
                "--pitches-nm",
                "530:530:10",
                "--fractions",
                "0.1:0.9:1e-300",
            ],
            "--fractions",
        ),
        (
            vec![
                "metalib",
                "sweep",
                "--harmonics",
                "2",
                "--out",
                "sw",
                "--heights-nm",
                "0:1e9:1e-300",
                "--pitches-nm",
                "530:530:10",
                "--fractions",
                "0.1:0.9:0.4",
            ],
            "--heights-nm",
        ),
        (
            vec![
                "metalib",
                "cell",
                "--wavelength-nm",
                "1e12",
                "--height-nm",
                "700",
                "--pitch-nm",
                "530",
                "--diameter-nm",
                "200",
            ],
            "--wavelength-nm",
        ),
        (
            vec![
                "metalib",
                "cell",
                "--wavelength-nm",
                "0.001",
                "--height-nm",
                "700",
                "--pitch-nm",
                "530",
                "--diameter-nm",
                "200",
            ],
            "--wavelength-nm",
        ),
        (
            vec![
                "metalib",
                "select",
                "--sweep",
                "none",
                "--mark-pitch-nm",
                "NaN",
            ],
            "--mark-pitch-nm",
        ),
        (
            vec![
                "fisher",
                "compare",
                "--photons",
                "1e308",
                "--montage",
                "m.png",
            ],
            "--photons",
        ),
        (vec!["fisher", "compare", "--montage", "m.jpg"], "--montage"),
        // Planes 1e-11 mm apart: ∂PSF/∂z was round-off, fisher_z 0 or 8e8 with exit 0.
        (
            vec![
                "fisher",
                "compare",
                "--depths-mm",
                "20:20.00000000001:1e-11",
                "--montage",
                "m.png",
            ],
            "--depths-mm: neighbouring depths",
        ),
        (
            vec![
                "fisher",
                "init",
                "--depths-mm",
                "20:20.0000001:0.0000001",
                "--out",
                "fi",
            ],
            "--depths-mm: neighbouring depths",
        ),
        // Named `--pitch` (no such flag) before.
        (
            vec!["metalib", "material-study", "--pitch-nm", "1e300", "--json"],
            "--pitch-nm",
        ),
        // Not a regular file: `/dev/zero` was read until memory ran out.
        (vec!["nets", "macs", "--arch", "file:/dev/zero"], "--arch"),
        (
            vec![
                "optics",
                "psf",
                "--lens",
                "file:/dev/zero",
                "--out",
                "x.npy",
            ],
            "--lens",
        ),
        // 9001 planes of 1024²: an audit saw a failed allocation's panic, then a hang.
        (
            vec![
                "fisher",
                "compare",
                "--window-px",
                "1024",
                "--depths-mm",
                "17:26:0.001",
                "--montage",
                "m.png",
            ],
            "--depths-mm/--window-px",
        ),
        (
            vec![
                "fisher",
                "init",
                "--window-px",
                "1024",
                "--depths-mm",
                "17:26:0.001",
                "--out",
                "fi",
            ],
            "--depths-mm/--window-px",
        ),
        (
            vec!["fisher", "init", "--pitch-um", "1e9", "--out", "fi"],
            "--pitch-um",
        ),
    ] {
        refused(&args, flag, p);
    }
    assert!(entries(p).is_empty(), "partial outputs: {:?}", entries(p));
}

#[test]
fn impossible_psf_requests_are_refused_without_writing() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    let base = [
        "optics",
        "psf",
        "--depths-mm",
        "20:22:1",
        "--window-px",
        "16",
        "--out",
        "o",
    ];
    for (extra, flag) in [
        (
            vec![
                "--aperture-mm",
                "0.1",
                "--sample-um",
                "2",
                "--period-mm",
                "1e17",
            ],
            "--period-mm",
        ),
        (
            vec![
                "--aperture-mm",
                "0.1",
                "--sample-um",
                "2",
                "--period-mm",
                "1e16",
            ],
            "--period-mm",
        ),
        (
            vec![
                "--aperture-mm",
                "0.1",
                "--sample-um",
                "2",
                "--pitch-um",
                "6.9359757717147935e+19",
            ],
            "--pitch-um",
        ),
        (vec!["--aperture-mm", "1e-300"], "--aperture-mm"),
        (vec!["--sample-um", "1e308"], "--sample-um"),
        // The folded grid of the default period beyond the model's: named only the pitch,
        // window and period flags, not the sampling that made it.
        (vec!["--sample-um", "0.07"], "--sample-um"),
        (vec!["--sensor-mm", "1e308"], "--sensor-mm"),
        (
            vec!["--aperture-mm", "0.1", "--period-mm", "0.01"],
            "--period-mm",
        ),
    ] {
        let args: Vec<&str> = base.iter().copied().chain(extra).collect();
        refused(&args, flag, p);
    }
    // A phase map of another size: both sizes named; an NPY map has no pitch, so none is
    // printed as the map's (the asked-for pitch was, as if it were the file's).
    let n = 16usize;
    let head = format!("{{'descr': '<f8', 'fortran_order': False, 'shape': ({n}, {n}), }}");
    let head = format!("{head:<117}\n");
    let mut npy = b"\x93NUMPY\x01\x00".to_vec();
    npy.extend((head.len() as u16).to_le_bytes());
    npy.extend(head.as_bytes());
    npy.extend(vec![0u8; 8 * n * n]);
    std::fs::write(p.join("ph16.npy"), npy).unwrap();
    let args = [
        "--lens",
        "file:ph16.npy",
        "--aperture-mm",
        "0.1",
        "--sample-um",
        "2",
    ];
    let args: Vec<&str> = base.iter().copied().chain(args).collect();
    let err = refused(&args, "--lens", p);
    assert!(
        err.contains("16×16") && err.contains("50×50") && !err.contains("pitch 0."),
        "{err}"
    );
    assert!(!p.join("o/psf.npy").exists());
}

#[test]
fn a_rig_with_a_wrong_fy_or_the_camera_inside_the_eye_is_refused() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    let out = succeeded(nanoeye(&["rig", "show", "--json"], p));
    let rig: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let mut bad = rig.clone();
    bad["camera"]["fy_px"] = serde_json::json!(200.0);
    std::fs::write(p.join("fy.json"), bad.to_string()).unwrap();
    refused(
        &["gaze", "bias", "--rig", "fy.json", "--steps", "3"],
        "fy_px",
        p,
    );
    // A valid rig whose 1×1-pixel camera sees the pupil at no gaze: gaze bias printed a
    // table of dashes with exit 0 (a helper's audit); datagen states refused it already.
    let cam = rig["camera"].clone();
    let mut one = rig.clone();
    let c = &mut one["camera"];
    // Pixels four times as large (within the rig's pitch range), the image one of them.
    let scale = 4.0;
    c["width_px"] = serde_json::json!(1);
    c["height_px"] = serde_json::json!(1);
    c["pixel_pitch_m"] = serde_json::json!(cam["pixel_pitch_m"].as_f64().unwrap() * scale);
    c["fx_px"] = serde_json::json!(cam["fx_px"].as_f64().unwrap() / scale);
    c["fy_px"] = serde_json::json!(cam["fy_px"].as_f64().unwrap() / scale);
    c["cx_px"] = serde_json::json!(0.5);
    c["cy_px"] = serde_json::json!(0.5);
    std::fs::write(p.join("one.json"), one.to_string()).unwrap();
    succeeded(nanoeye(&["rig", "show", "--rig", "one.json"], p));
    refused(
        &["gaze", "bias", "--rig", "one.json", "--steps", "3"],
        "--rig: the camera sees the pupil at none",
        p,
    );
    let mut bad = rig.clone();
    bad["camera"]["position_m"] = serde_json::json!([0.0, 0.0, 0.001]);
    std::fs::write(p.join("in.json"), bad.to_string()).unwrap();
    refused(&["run", "--rig", "in.json"], "position_m", p);
    // A camera facing away from the eye (the identity rotation: optical axis +z, the eye
    // behind): `run` rendered its training set before finding no pupil (a fourth audit).
    let mut away = rig.clone();
    away["camera"]["rotation_cam_to_world"] =
        serde_json::json!([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]);
    std::fs::write(p.join("away.json"), away.to_string()).unwrap();
    refused(
        &["rig", "show", "--rig", "away.json"],
        "rotation_cam_to_world",
        p,
    );
    refused(
        &["run", "--rig", "away.json", "--out", "ra"],
        "rotation_cam_to_world",
        p,
    );
    assert!(!p.join("ra").exists());
    // A metre and beyond is a unit mistake (1e308 printed as inf), as is a principal point
    // far off the image.
    for (key, v, field) in [
        (
            "height_px",
            serde_json::json!(4_000_000_000u64),
            "height_px",
        ),
        (
            "position_m",
            serde_json::json!([0.0, 0.0, 1e308]),
            "position_m",
        ),
        (
            "position_m",
            serde_json::json!([0.0, 0.0, 2.0]),
            "position_m",
        ),
        ("cx_px", serde_json::json!(1e300), "cx_px"),
    ] {
        let mut bad = rig.clone();
        bad["camera"][key] = v;
        std::fs::write(p.join("far.json"), bad.to_string()).unwrap();
        refused(&["rig", "show", "--rig", "far.json"], field, p);
    }
    let mut bad = rig.clone();
    bad["slip"]["mount_rotation_sigma_rad"] = serde_json::json!(-0.1);
    std::fs::write(p.join("sig.json"), bad.to_string()).unwrap();
    refused(
        &["rig", "show", "--rig", "sig.json"],
        "mount_rotation_sigma_rad",
        p,
    );
    let mut bad = rig;
    bad["eye_radius_m"] = serde_json::json!(1e-300);
    std::fs::write(p.join("tiny.json"), bad.to_string()).unwrap();
    refused(&["rig", "show", "--rig", "tiny.json"], "eye_radius_m", p);
}

/// An audit's findings (fifty-first session): a crafted NPY header (2³²×2³², which overflowed
/// inside the NPY parser), FIFOs given as a rig or a state (which blocked), and numbers that
/// failed later naming another flag or none.
#[test]
fn crafted_headers_fifos_and_out_of_range_numbers_are_refused_by_name() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    let head = "{'descr': '<f8', 'fortran_order': False, 'shape': (4294967296, 4294967296), }";
    let pad = 16 - (10 + head.len() + 1) % 16;
    let mut npy = b"\x93NUMPY\x01\x00".to_vec();
    npy.extend(((head.len() + pad + 1) as u16).to_le_bytes());
    npy.extend(
        head.bytes()
            .chain(std::iter::repeat_n(b' ', pad))
            .chain([b'\n']),
    );
    npy.extend([0u8; 16]);
    std::fs::write(p.join("huge.npy"), npy).unwrap();
    let e = refused(
        &["optics", "psf", "--lens", "file:huge.npy", "--out", "ps"],
        "--lens",
        p,
    );
    // Named by its shape: beyond the aperture grid's 20000², or (since the NPY preamble is
    // checked first) beyond what the file's 16 bytes of data hold.
    assert!(e.contains("4294967296"), "{e}");
    // A header that claims less than the file holds (a 2×2 header over five values): the
    // first four were taken as the map, exit 0 (a helper's audit).
    std::fs::write(
        p.join("long.npy"),
        common::npy_f64(2, 2, &[0.0, 1.0, 2.0, 3.0, 4.0]),
    )
    .unwrap();
    let e = refused(
        &["optics", "psf", "--lens", "file:long.npy", "--out", "ps"],
        "--lens",
        p,
    );
    assert!(e.contains("does not describe the data"), "{e}");
    // The blueprint's reader too: the wrapped count read as an empty 2³²×2³² map, which
    // panicked indexing it after a sweep.
    let e = refused(
        &[
            "metalib",
            "blueprint",
            "--phase",
            "huge.npy",
            "--height-nm",
            "600",
            "--pitch-nm",
            "450",
            "--out",
            "bp",
        ],
        "--phase",
        p,
    );
    assert!(e.contains("values"), "{e}");
    #[cfg(unix)]
    refused(
        &[
            "metalib",
            "blueprint",
            "--phase",
            "/dev/zero",
            "--height-nm",
            "600",
            "--pitch-nm",
            "450",
            "--out",
            "bp",
        ],
        "--phase",
        p,
    );
    assert!(!p.join("bp").exists());
    #[cfg(unix)]
    {
        common::mkfifo(&p.join("fifo"));
        refused(&["rig", "show", "--rig", "fifo"], "--rig", p);
        refused(&["gaze", "bias", "--rig", "fifo"], "--rig", p);
        refused(
            &["datagen", "export", "--state", "fifo", "--out", "e.glb"],
            "--state",
            p,
        );
        // A fourth audit's reading: these were read to their end too.
        refused(&["run", "--config", "fifo", "--out", "rf"], "--config", p);
        refused(
            &[
                "datagen",
                "render",
                "--set",
                "ambiguity",
                "--n",
                "1",
                "--rig",
                "fifo",
                "--out",
                "dr",
            ],
            "--rig",
            p,
        );
    }
    // The mesh's unit without a mesh was ignored.
    refused(
        &[
            "datagen",
            "render",
            "--set",
            "ambiguity",
            "--n",
            "1",
            "--mesh-units",
            "m",
            "--out",
            "dr",
        ],
        "--mesh-units",
        p,
    );
    assert!(!p.join("rf").exists() && !p.join("dr").exists());
    let radii: Vec<String> = (0..65)
        .map(|i| format!("{}", 9.0 + 0.01 * i as f64))
        .collect();
    let radii = radii.join(",");
    refused(
        &["gaze", "bias", "--steps", "3", "--solver-radii-mm", &radii],
        "--solver-radii-mm",
        p,
    );
    refused(
        &["fisher", "compare", "--photons", "5e-324"],
        "--photons",
        p,
    );
    refused(
        &["fisher", "compare", "--aperture-step-um", "1000"],
        "--aperture-step-um",
        p,
    );
    // Lengths far below any optics (a fourth audit): each gave planes of zeros with exit 0,
    // or failed naming another flag.
    for (args, flag) in [
        (
            &["optics", "psf", "--pitch-um=1e-30", "--out", "ps"][..],
            "--pitch-um",
        ),
        (
            &["optics", "psf", "--depths-mm=1e-308", "--out", "ps"],
            "--depths-mm",
        ),
        (
            &["optics", "psf", "--focus-mm=1e-300", "--out", "ps"],
            "--focus-mm",
        ),
        (
            &["optics", "psf", "--sensor-mm=1e-9", "--out", "ps"],
            "--sensor-mm",
        ),
        (
            &["optics", "psf", "--aperture-mm=1e308", "--out", "ps"],
            "--aperture-mm",
        ),
        (
            &["optics", "psf", "--pitch-um=1e308", "--out", "ps"],
            "--pitch-um",
        ),
        (
            &[
                "datagen",
                "render",
                "--set",
                "ambiguity",
                "--n",
                "1",
                "--width",
                "1",
                "--height",
                "50",
                "--spp",
                "1",
                "--out",
                "dw",
            ],
            "--width",
        ),
        (
            &[
                "fisher",
                "compare",
                "--depths-mm=1e-308:1:0.5",
                "--montage",
                "fm.png",
            ],
            "--depths-mm",
        ),
    ] {
        refused(args, flag, p);
    }
    // A value given twice was computed and reported twice.
    refused(
        &[
            "fisher",
            "compare",
            "--pitch-um",
            "3,9,9",
            "--montage",
            "fm.png",
        ],
        "--pitch-um",
        p,
    );
    refused(
        &[
            "fisher",
            "compare",
            "--lenses",
            "hyperbolic,hyperbolic",
            "--montage",
            "fm.png",
        ],
        "--lenses",
        p,
    );
    // A value Rust prints in full (1e308 is 309 digits) is written in scientific notation.
    let e = refused(
        &["fisher", "init", "--pitch-um", "1e308", "--out", "fl"],
        "--pitch-um",
        p,
    );
    assert!(e.contains("got 1e308") && e.len() < 200, "{e}");
    // A pitch far below a pixel leaves no PSF in the window: fisher_z 0 with exit 0 before.
    refused(
        &[
            "fisher",
            "compare",
            "--pitch-um",
            "3,1e-308",
            "--montage",
            "fm.png",
        ],
        "--pitch-um",
        p,
    );
    assert!(!p.join("fm.png").exists());
    refused(
        &["fisher", "init", "--lr-rad", "1e308", "--out", "fl"],
        "--lr-rad",
        p,
    );
    assert!(!p.join("fl").exists() && !p.join("ps").exists() && !p.join("e.glb").exists());
}

/// Output into a pipe whose reader has gone (`nanoeye … | head`): the process ends by SIGPIPE,
/// as other Unix tools do; it panicked on the write's EPIPE (an audit).
#[cfg(unix)]
#[test]
fn a_closed_stdout_ends_the_process_quietly() {
    use std::os::unix::process::ExitStatusExt;
    let d = tempfile::tempdir().unwrap();
    // Far more output than a pipe buffers (64 KiB on Linux): the writes fail once the reader
    // has gone, whenever it goes (a short output could all be buffered before the reader
    // closed, and the process end with 0: a flaky test).
    let q = "{\"pupil_px\":[160,100],\"slip_m\":[0,0,0]}\n".repeat(5000);
    std::fs::write(d.path().join("q.jsonl"), q).unwrap();
    let mut child = std::process::Command::new(common::BIN)
        .args(["gaze", "solve", "--input", "q.jsonl"])
        .current_dir(d.path())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    drop(child.stdout.take());
    let out = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!err.contains("panicked"), "{err}");
    assert_eq!(out.status.signal(), Some(13), "{:?}: {err}", out.status);
}

#[test]
fn gaze_solve_refuses_a_file_without_a_query_and_answers_misses() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    // No line is a query: refused naming --input and the first line, nothing written.
    std::fs::write(p.join("q.jsonl"), "{\"pupil\":[1,2]}\n\nnot json\n").unwrap();
    let err = refused(
        &["gaze", "solve", "--input", "q.jsonl", "--out", "r.jsonl"],
        "--input",
        p,
    );
    assert!(
        err.contains("line 1") && err.contains("none of its 2"),
        "{err}"
    );
    assert!(!p.join("r.jsonl").exists());
    // An empty or blank file (one blank line, exit 0, before) and --out naming the query
    // file (it was replaced by the answers) are refused.
    std::fs::write(p.join("blank.jsonl"), "\n  \n").unwrap();
    refused(
        &[
            "gaze",
            "solve",
            "--input",
            "blank.jsonl",
            "--out",
            "r.jsonl",
        ],
        "--input",
        p,
    );
    assert!(!p.join("r.jsonl").exists());
    refused(
        &["gaze", "solve", "--input", "q.jsonl", "--out", "q.jsonl"],
        "--out",
        p,
    );
    assert!(
        std::fs::read_to_string(p.join("q.jsonl"))
            .unwrap()
            .contains("not json")
    );
    // Queries whose rays all miss the eye (the camera slipped 1 m away) are answered, one
    // error line each, with exit 0: a query without a gaze is not bad input.
    std::fs::write(
        p.join("q.jsonl"),
        "{\"pupil_px\":[160,100],\"slip_m\":[1,0,0]}\n{\"pupil_px\":[0,0],\"slip_m\":[1,0,0]}\n",
    )
    .unwrap();
    let out = succeeded(nanoeye(&["gaze", "solve", "--input", "q.jsonl"], p));
    let text = String::from_utf8(out.stdout).unwrap();
    assert_eq!(text.lines().count(), 2, "{text}");
    assert!(
        text.lines()
            .all(|l| l.contains("\"error\"") && l.contains("misses")),
        "{text}"
    );
    // A slip of 1e200 m overflowed the refraction-aware solver into a zero gaze and a null
    // visual axis, printed with exit 0: now the line names slip_m (a helper's audit).
    std::fs::write(
        p.join("huge.jsonl"),
        "{\"pupil_px\":[160,100],\"slip_m\":[1e200,1e200,1e200]}\n",
    )
    .unwrap();
    let args = [
        "gaze",
        "solve",
        "--input",
        "huge.jsonl",
        "--solver",
        "refractive",
        "--kappa",
    ];
    let err = refused(&args, "slip_m", p);
    assert!(!err.contains("null"), "{err}");
    // --out at the rig or at a query's mask, a FIFO as --input or as a mask: refused (the
    // rig and the mask were replaced by the answers; the FIFOs blocked).
    let rig = succeeded(nanoeye(&["rig", "show", "--json"], p)).stdout;
    std::fs::write(p.join("rig.json"), &rig).unwrap();
    let args = [
        "gaze",
        "solve",
        "--input",
        "huge.jsonl",
        "--rig",
        "rig.json",
        "--out",
        "rig.json",
    ];
    refused(&args, "--out", p);
    assert_eq!(std::fs::read(p.join("rig.json")).unwrap(), rig);
    image::GrayImage::new(320, 200)
        .save(p.join("m.png"))
        .unwrap();
    std::fs::write(p.join("mq.jsonl"), "{\"mask_png\":\"m.png\"}\n").unwrap();
    let m = std::fs::read(p.join("m.png")).unwrap();
    refused(
        &["gaze", "solve", "--input", "mq.jsonl", "--out", "m.png"],
        "--out",
        p,
    );
    assert_eq!(std::fs::read(p.join("m.png")).unwrap(), m);
    for f in ["fifo.jsonl", "fifo.png"] {
        common::mkfifo(&p.join(f));
    }
    refused(
        &["gaze", "solve", "--input", "fifo.jsonl"],
        "regular file",
        p,
    );
    std::fs::write(p.join("fq.jsonl"), "{\"mask_png\":\"fifo.png\"}\n").unwrap();
    refused(&["gaze", "solve", "--input", "fq.jsonl"], "regular file", p);
}

#[test]
fn gaze_solve_reports_a_non_utf8_line_and_goes_on_and_strips_a_bom() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    std::fs::write(
        p.join("q.jsonl"),
        b"\xEF\xBB\xBF{\"pupil_px\":[160,100]}\n{\"pupil_px\":[1\xff0,100]}\r\n{\"pupil_px\":[150,100]}\n",
    )
    .unwrap();
    let out = succeeded(nanoeye(&["gaze", "solve", "--input", "q.jsonl"], p));
    let text = String::from_utf8(out.stdout).unwrap();
    let lines: Vec<serde_json::Value> = text
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.len(), 3, "{text}");
    assert!(lines[0]["gaze"].is_array(), "{text}");
    assert!(
        lines[1]["error"].as_str().unwrap().contains("line 2"),
        "{text}"
    );
    assert!(lines[2]["gaze"].is_array(), "{text}");
}

#[cfg(unix)]
#[test]
fn out_at_a_symlink_is_refused_and_dead_temp_files_are_removed() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    std::fs::write(p.join("real.jsonl"), b"keep").unwrap();
    std::os::unix::fs::symlink("real.jsonl", p.join("link.jsonl")).unwrap();
    refused(
        &[
            "datagen",
            "states",
            "--set",
            "variational",
            "--n",
            "1",
            "--out",
            "link.jsonl",
        ],
        "symbolic link",
        p,
    );
    assert_eq!(std::fs::read(p.join("real.jsonl")).unwrap(), b"keep");
    assert!(
        std::fs::symlink_metadata(p.join("link.jsonl"))
            .unwrap()
            .file_type()
            .is_symlink()
    );
    // A temp file left by a killed run (its process id no longer exists).
    let stale = p.join(".nanoeye-tmp-4294967295-abcdef");
    std::fs::write(&stale, b"partial").unwrap();
    succeeded(nanoeye(
        &[
            "datagen",
            "states",
            "--set",
            "variational",
            "--n",
            "1",
            "--out",
            "s.jsonl",
        ],
        p,
    ));
    assert!(!stale.exists());
    assert!(
        entries(p).iter().all(|n| !n.starts_with(".nanoeye-tmp-")),
        "{:?}",
        entries(p)
    );
}

#[test]
fn blueprint_validates_everything_before_writing() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    std::fs::write(
        p.join("phase.npy"),
        npy_f64(2, 2, &[0.0, 1.0, 2.0, f64::NAN]),
    )
    .unwrap();
    let csv: String = (0..32)
        .map(|i| format!("{},{},0.95\n", 100.0 + 10.0 * i as f64, 0.2 * i as f64))
        .collect();
    std::fs::write(p.join("lib.csv"), csv).unwrap();
    let base = [
        "metalib",
        "blueprint",
        "--phase",
        "phase.npy",
        "--height-nm",
        "700",
        "--pitch-nm",
        "500",
        "--out",
        "bp",
        "--library-csv",
        "lib.csv",
        "--square-aperture",
    ];
    let with =
        |extra: &[&'static str]| -> Vec<&str> { base.iter().chain(extra).copied().collect() };
    refused(&with(&["--circle-vertices", "4"]), "--circle-vertices", p);
    assert!(!p.join("bp").exists());
    // The diameter step is named by its own flag (not by --phase, where it failed before).
    for step in ["1e300", "-1", "nan", "1e-308"] {
        let arg = format!("--diameter-step-nm={step}");
        let args: Vec<&str> = base.iter().copied().chain([arg.as_str()]).collect();
        refused(&args, "--diameter-step-nm", p);
        assert!(!p.join("bp").exists());
    }
    // Library diameters up to 410 nm on a 300 nm pitch: pillars would overlap.
    let mut narrow = base.to_vec();
    narrow[6] = "300";
    refused(&narrow, "--pitch-nm", p);
    assert!(!p.join("bp").exists());
    // --sweep and --library-csv conflict (clap usage error).
    refused(&with(&["--sweep", "sw"]), "--sweep", p);
    std::fs::write(
        p.join("inf.npy"),
        npy_f64(2, 2, &[0.0, f64::INFINITY, 2.0, 1.0]),
    )
    .unwrap();
    let mut inf = base.to_vec();
    inf[3] = "inf.npy";
    refused(&inf, "--phase", p);
    // Without a library the slice is swept into OUT/library_sweep; one of other settings there
    // is refused naming --out (it named `out`, an audit's finding).
    succeeded(nanoeye(
        &[
            "metalib",
            "sweep",
            "--harmonics",
            "2",
            "--out",
            "bq/library_sweep",
            "--heights-nm",
            "700:700:10",
            "--pitches-nm",
            "530:530:10",
            "--fractions",
            "0.1:0.9:0.4",
        ],
        p,
    ));
    let mut swept: Vec<&str> = base[..10].to_vec();
    swept[9] = "bq";
    swept.extend(["--square-aperture", "--harmonics", "2"]);
    let err = refused(&swept, "--out", p);
    assert!(err.contains("--height-nm"), "{err}");
    assert_eq!(entries(&p.join("bq")), ["library_sweep"]);
    // A directory where an output goes, or a file as --out: refused before the slice is
    // swept (a helper's audit: 161 cells were solved into OUT/library_sweep first).
    std::fs::create_dir_all(p.join("bd/diameters.npy")).unwrap();
    swept[9] = "bd";
    let err = refused(&swept, "--out", p);
    assert!(err.contains("diameters.npy"), "{err}");
    assert_eq!(entries(&p.join("bd")), ["diameters.npy"]);
    std::fs::write(p.join("bf"), b"").unwrap();
    swept[9] = "bf";
    let err = refused(&swept, "--out", p);
    assert!(err.contains("not a directory"), "{err}");
    let ok = nanoeye(&base, p);
    assert!(
        ok.status.success(),
        "{}",
        String::from_utf8_lossy(&ok.stderr)
    );
    assert_eq!(
        entries(&p.join("bp")),
        ["diameters.npy", "layout.gds", "preview.png"]
    );
    // An input where an output goes, also through a directory not made yet (a helper's
    // audit: --phase OUT/diameters.npy was replaced, exit 0): refused before any work.
    std::fs::copy(p.join("phase.npy"), p.join("bp/diameters.npy")).unwrap();
    let mut over = base.to_vec();
    over[3] = "bp/diameters.npy";
    for out in ["bp", "bp/new/.."] {
        over[9] = out;
        refused(&over, "would replace --phase", p);
    }
    let mut over = base.to_vec();
    over[11] = "bp/layout.gds";
    refused(&over, "would replace --library-csv", p);
    // A layout beyond the memory there is: weighed before it is built (a helper's audit: a
    // 2500² map's 2.7 GB GDS aborted an allocation under ulimit -v). 1000² pillars of 64
    // vertices are about 0.5 GB, against a 100 MB cap.
    std::fs::write(
        p.join("big.npy"),
        npy_f64(1000, 1000, &vec![1.0; 1_000_000]),
    )
    .unwrap();
    let mut big = base.to_vec();
    big[3] = "big.npy";
    big[9] = "bbig";
    let out = with_memory(&big, "1e8", p);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "ran under a 100 MB cap");
    assert!(
        err.contains("--phase/--circle-vertices") && err.contains("GiB"),
        "{err}"
    );
    assert!(!p.join("bbig").exists());
    assert_eq!(
        std::fs::read(p.join("bp/diameters.npy")).unwrap(),
        std::fs::read(p.join("phase.npy")).unwrap()
    );
    assert_eq!(
        entries(&p.join("bp")),
        ["diameters.npy", "layout.gds", "preview.png"]
    );
}

#[test]
fn arch_json_with_an_unknown_key_is_refused() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    let arch = serde_json::json!({
        "kernel": vec![3; 20], "expand": vec![3; 20], "depth": vec![2; 5],
        "resolution_scale": 0.5, "kernal": [3],
    });
    std::fs::write(p.join("a.json"), arch.to_string()).unwrap();
    refused(&["nets", "macs", "--arch", "file:a.json"], "--arch", p);
    // A byte-order mark first (an editor's): read past, as the JSONL readers do, for an arch
    // and a rig alike (both were refused).
    let mut arch = arch;
    arch.as_object_mut().unwrap().remove("kernal");
    std::fs::write(p.join("b.json"), format!("\u{feff}{arch}")).unwrap();
    succeeded(nanoeye(&["nets", "macs", "--arch", "file:b.json"], p));
    let rig = succeeded(nanoeye(&["rig", "show", "--json"], p)).stdout;
    let mut bom = "\u{feff}".as_bytes().to_vec();
    bom.extend(rig);
    std::fs::write(p.join("rig.json"), bom).unwrap();
    succeeded(nanoeye(&["rig", "show", "--rig", "rig.json"], p));
}

#[test]
fn fisher_init_resume_refuses_changed_parameters_and_keeps_one_checkpoint_file() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    let base = [
        "fisher",
        "init",
        "--out",
        "fi",
        "--aperture-step-um",
        "50",
        "--window-px",
        "3",
    ];
    let base_with = |extra: &[&'static str]| base.iter().chain(extra).copied().collect::<Vec<_>>();
    let run = |extra: &[&'static str]| nanoeye(&base_with(extra), p);
    succeeded(run(&["--iterations", "1"]));
    assert_eq!(entries(&p.join("fi/checkpoint")), ["checkpoint.bin"]);
    for (extra, flag) in [
        (["--lr-rad", "0.1"], "--lr-rad"),
        (["--pitch-um", "6"], "--pitch-um"),
        (["--photons", "1e6"], "--photons"),
        (["--depths-mm", "17:20:1.5"], "--depths-mm"),
    ] {
        let args: Vec<&str> = base
            .iter()
            .copied()
            .chain(["--iterations", "2"])
            .chain(extra)
            .collect();
        refused(&args, flag, p);
    }
    // The PSF window is not in the checkpoint's config: inputs.json holds it.
    let mut args = base.to_vec();
    args[7] = "5";
    args.extend(["--iterations", "2"]);
    let e = refused(&args, "--window-px", p);
    assert!(e.contains("differs from the run being resumed"), "{e}");
    // Nor is the aperture step: 51 µm gives the same 20-sample grid as 50 µm (an audit: it
    // resumed), so inputs.json holds the step itself.
    let mut args = base.to_vec();
    args[5] = "51";
    args.extend(["--iterations", "2"]);
    let e = refused(&args, "--aperture-step-um", p);
    assert!(e.contains("differs from the run being resumed"), "{e}");
    // Without inputs.json the checkpoint's own record refuses them (a helper's audit: the
    // resume went on and rewrote inputs.json with the new window).
    let rec = std::fs::read(p.join("fi/inputs.json")).unwrap();
    std::fs::remove_file(p.join("fi/inputs.json")).unwrap();
    let mut args = base.to_vec();
    args[7] = "5";
    args.extend(["--iterations", "2"]);
    let e = refused(&args, "--window-px", p);
    assert!(e.contains("differs from the checkpoint"), "{e}");
    std::fs::write(p.join("fi/inputs.json"), rec).unwrap();
    // A resumed run reports the run's first iteration, not the resuming process's: the same
    // as a run that stops there.
    let first = |out: std::process::Output| {
        let v: serde_json::Value = serde_json::from_slice(&succeeded(out).stdout).unwrap();
        v["l_init_first"].as_f64().unwrap()
    };
    let mut fresh = base.to_vec();
    fresh[3] = "fj";
    fresh.extend(["--iterations", "1", "--json"]);
    let a = first(nanoeye(&fresh, p));
    assert_eq!(first(run(&["--iterations", "2", "--json"])), a);
    // Fewer iterations than the checkpoint has done: refused, outputs untouched (they were
    // rewritten, exit 0, reporting 2 for a request of 1).
    let before = common::tree(&p.join("fi"));
    let e = refused(&base_with(&["--iterations", "1"]), "--iterations", p);
    assert!(e.contains("fewer than the 2"), "{e}");
    assert!(common::tree(&p.join("fi")) == before, "outputs changed");
    // A record of inputs that is no JSON object is refused, not read as recording nothing.
    std::fs::write(p.join("fi/inputs.json"), "[9, 10.0]").unwrap();
    let e = refused(&base_with(&["--iterations", "3"]), "--out", p);
    assert!(e.contains("not a JSON object"), "{e}");
    std::fs::write(p.join("fi/inputs.json"), &before[Path::new("inputs.json")]).unwrap();
    // A corrupted checkpoint is refused, not resumed.
    let ck = p.join("fi/checkpoint/checkpoint.bin");
    let mut bytes = std::fs::read(&ck).unwrap();
    let k = bytes.len() / 2;
    bytes[k] ^= 0x10;
    std::fs::write(&ck, bytes).unwrap();
    refused(
        &base
            .iter()
            .copied()
            .chain(["--iterations", "2"])
            .collect::<Vec<_>>(),
        "checksum",
        p,
    );
}

#[test]
fn datagen_render_names_n_blink_fraction_and_protocol_grid_and_refuses_a_symlinked_manifest() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    refused(
        &[
            "datagen",
            "render",
            "--set",
            "ambiguity",
            "--n",
            "1000000000000",
            "--out",
            "x",
        ],
        "--n",
        p,
    );
    for (set, name, value) in [
        ("envelope", "--blink-fraction", "1.5"),
        ("envelope", "--blink-fraction", "NaN"),
        ("envelope", "--blink-fraction", "-0.1"),
        ("ambiguity", "--blink-fraction", "0.5"),
        ("protocol", "--protocol-grid", "1"),
        ("protocol", "--protocol-grid", "8"),
        ("protocol", "--protocol-grid", "-1"),
        ("envelope", "--protocol-grid", "3"),
    ] {
        let flag = format!("{name}={value}");
        refused(
            &[
                "datagen", "render", "--set", set, "--n", "1", &flag, "--out", "b",
            ],
            name,
            p,
        );
    }
    assert!(!p.join("b").exists(), "nothing written before the check");
    std::fs::create_dir(p.join("ds")).unwrap();
    std::os::unix::fs::symlink(p.join("elsewhere"), p.join("ds/dataset.json")).unwrap();
    refused(&tiny_dataset("ds"), "--out", p);
    assert!(!p.join("elsewhere").exists());
    assert!(
        std::fs::symlink_metadata(p.join("ds/dataset.json"))
            .unwrap()
            .file_type()
            .is_symlink()
    );
}

#[test]
fn datagen_states_takes_a_coarser_protocol_grid_and_names_bad_ones() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    for (set, value) in [
        ("protocol", "0"),
        ("protocol", "1"),
        ("protocol", "8"),
        ("protocol", "-1"),
        ("protocol", "NaN"),
        ("ambiguity", "3"),
        ("variational", "2"),
    ] {
        let flag = format!("--protocol-grid={value}");
        refused(
            &[
                "datagen", "states", "--set", set, "--n", "1", &flag, "--out", "s.jsonl",
            ],
            "--protocol-grid",
            p,
        );
    }
    assert!(!p.join("s.jsonl").exists(), "nothing written when refused");
    let lines = |grid: &str, out: &str| -> Vec<serde_json::Value> {
        let args = [
            "datagen",
            "states",
            "--set",
            "protocol",
            "--n",
            "1",
            "--protocol-grid",
            grid,
            "--out",
            out,
        ];
        succeeded(nanoeye(&args, p));
        std::fs::read_to_string(p.join(out))
            .unwrap()
            .lines()
            .map(|l| serde_json::from_str(l).unwrap())
            .collect()
    };
    let paper = lines("7", "g7.jsonl");
    assert_eq!(paper.len(), 343, "D.4: 7 slip states × 49 targets");
    for g in [2u64, 3, 4] {
        let coarse = lines(&g.to_string(), "g.jsonl");
        // 7 slip states × G² targets over the same span.
        assert_eq!(coarse.len() as u64, 7 * g * g);
        // Row r, column c of the G × G grid is row k·r, column k·c of D.4's 7 × 7 grid.
        let k = 6 / (g - 1);
        for c in &coarse {
            let (t, s) = (c["target_index"].as_u64().unwrap(), &c["slip_index"]);
            assert!(t < g * g, "target {t} of a {g} × {g} grid");
            let t7 = 7 * k * (t / g) + k * (t % g);
            let twin = paper
                .iter()
                .find(|q| q["target_index"] == t7 && &q["slip_index"] == s)
                .unwrap();
            assert_eq!(
                c["target_deg"], twin["target_deg"],
                "G {g}, target {t}, slip {s}"
            );
        }
    }
    // The default, 7, given on a set without a grid is the default: accepted.
    let args = [
        "datagen",
        "states",
        "--set",
        "ambiguity",
        "--n",
        "1",
        "--protocol-grid",
        "7",
        "--out",
        "a.jsonl",
    ];
    succeeded(nanoeye(&args, p));
    assert!(p.join("a.jsonl").is_file());
}

#[test]
fn sim_and_search_loss_name_their_bad_flags() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    let ok = nanoeye(&tiny_dataset("ds"), p);
    assert!(ok.status.success());
    for (args, flag) in [
        (vec!["sim", "--dataset", "nope", "--out", "o"], "--dataset"),
        (
            vec!["sim", "--dataset", "ds", "--pitch-um", "1", "--out", "o"],
            "--pitch-um",
        ),
        (
            vec!["sim", "--dataset", "ds", "--pitch-um", "NaN", "--out", "o"],
            "--pitch-um",
        ),
        (
            vec!["sim", "--dataset", "ds", "--pitch-um", "1e30", "--out", "o"],
            "--pitch-um",
        ),
        (
            vec!["sim", "--dataset", "ds", "--exposure-ms=-1", "--out", "o"],
            "--exposure-ms",
        ),
        (
            vec![
                "sim",
                "--dataset",
                "ds",
                "--lens",
                "file:nope.npy",
                "--out",
                "o",
            ],
            "--lens",
        ),
        (
            vec!["sim", "--dataset", "ds", "--frames", "2:1", "--out", "o"],
            "--frames",
        ),
        // Not used by this lens, but no value: it exited 0 (an audit, fifty-fifth session).
        (
            vec![
                "search",
                "train",
                "--dataset",
                "ds",
                "--lens",
                "hyperbolic",
                "--fisher-photons",
                "NaN",
                "--out",
                "o",
            ],
            "--fisher-photons",
        ),
        // It trained a step, then failed naming the rig's pixel pitch (an audit).
        (
            vec![
                "search",
                "train",
                "--dataset",
                "ds",
                "--pitch-range-um",
                "48:1e9",
                "--out",
                "o",
            ],
            "--pitch-range-um",
        ),
        // A fourth audit: a base coarser than the dataset's pixels, and an aperture step
        // finer than the grid allows, were named as chain parameters.
        (
            vec![
                "sim",
                "--dataset",
                "ds",
                "--base-pitch-um",
                "1000",
                "--out",
                "o",
            ],
            "--base-pitch-um",
        ),
        (
            vec![
                "sim",
                "--dataset",
                "ds",
                "--aperture-step-um=1e-308",
                "--out",
                "o",
            ],
            "--aperture-step-um",
        ),
        // An audit: 1e-300 µm passed as positive and wrote NaN frames with exit 0; 1e9 µm
        // failed naming `frames` (every layer's gain NaN).
        (
            vec![
                "sim",
                "--dataset",
                "ds",
                "--base-pitch-um",
                "1e-300",
                "--out",
                "o",
            ],
            "--base-pitch-um",
        ),
        (
            vec![
                "sim",
                "--dataset",
                "ds",
                "--aperture-step-um",
                "1e9",
                "--out",
                "o",
            ],
            "--aperture-step-um",
        ),
        // Finer than the PSF model's folded grid holds (but above the flag's own floor): it
        // was named `period_m`, a parameter the chain has no flag for.
        (
            vec![
                "sim",
                "--dataset",
                "ds",
                "--aperture-step-um",
                "0.07",
                "--out",
                "o",
            ],
            "--aperture-step-um: the period",
        ),
        (
            vec!["search", "loss", "--dataset", "ds", "--frames", "0:99"],
            "--frames",
        ),
        (
            vec!["search", "loss", "--dataset", "ds", "--subnet", "mid"],
            "--subnet",
        ),
        (
            vec!["search", "loss", "--dataset", "ds", "--phase", "nope.npy"],
            "--phase",
        ),
        (
            vec!["search", "loss", "--dataset", "ds", "--lambda-slip", "NaN"],
            "--lambda-slip",
        ),
        (
            vec![
                "search",
                "train",
                "--dataset",
                "ds",
                "--slip-axis-weights",
                "1,2",
                "--out",
                "o",
            ],
            "--slip-axis-weights",
        ),
        (
            vec![
                "search",
                "train",
                "--dataset",
                "ds",
                "--slip-axis-weights=1,-1,1",
                "--out",
                "o",
            ],
            "--slip-axis-weights",
        ),
        (
            vec![
                "search",
                "train",
                "--dataset",
                "ds",
                "--bn-batches",
                "0",
                "--out",
                "o",
            ],
            "--bn-batches",
        ),
        // A count whose inputs cannot be held: refused before training, not after it.
        (
            vec![
                "search",
                "train",
                "--dataset",
                "ds",
                "--bn-batches",
                "1000000000",
                "--out",
                "o",
            ],
            "--bn-batches",
        ),
    ] {
        refused(&args, flag, p);
    }
    // φ's basis, schedule and window: refused naming the flag (the first two by clap).
    let phase_flags: [(&str, &[&str]); 3] = [
        (
            "--phase-basis",
            &[
                "zernike:0",
                "zernike:21",
                "zernike:-1",
                "zernike:1.5",
                "zernike:nan",
                "zernike",
                "Zernike:4",
                "",
            ],
        ),
        (
            "--phase-schedule",
            &[
                "cosine:0",
                "cosine:-0.5",
                "cosine:1.5",
                "cosine:nan",
                "cosine:inf",
                "cosine:",
                "linear",
                "",
            ],
        ),
        (
            "--phase-every",
            &["0", "1.5", "nan", "10000001", "18446744073709551616", ""],
        ),
    ];
    for (flag, values) in phase_flags {
        for &v in values {
            let args = ["search", "train", "--dataset", "ds", flag, v, "--out", "o"];
            refused(&args, flag, p);
        }
    }
    let args = [
        "search",
        "train",
        "--dataset",
        "ds",
        "--phase-every=-1",
        "--out",
        "o",
    ];
    refused(&args, "--phase-every", p);
    assert!(!p.join("o").exists(), "a refused sim must write nothing");
    std::fs::write(p.join("file"), b"").unwrap();
    refused(
        &[
            "sim",
            "--dataset",
            "ds",
            "--pitch-um",
            "48",
            "--out",
            "file",
        ],
        "--out",
        p,
    );
    // A failure met while imaging (a layer not finite, found when the pass reads the
    // frame's file; S1 found it before the layers were range-checked on load, and named
    // "frame 0" — the file's name names it now) leaves no empty output directory behind.
    let bad = tiny_dataset("bad");
    assert!(nanoeye(&bad, p).status.success());
    let layers = p.join("bad/frames/000000_layers.npy");
    let mut bytes = std::fs::read(&layers).unwrap();
    let n = bytes.len();
    bytes[n - 4..].copy_from_slice(&f32::NAN.to_le_bytes());
    std::fs::write(&layers, bytes).unwrap();
    let sim = ["sim", "--dataset", "bad", "--pitch-um", "48", "--out", "o"];
    let err = refused(&sim, "frames/000000_layers.npy", p);
    assert!(err.contains("NaN"), "{err}");
    assert!(
        !p.join("o").exists(),
        "a failed sim must leave no directory"
    );
    // Nor the missing parents of its --out (the first of two new levels was left).
    let sim = [
        "sim",
        "--dataset",
        "bad",
        "--pitch-um",
        "48",
        "--out",
        "n1/n2",
    ];
    refused(&sim, "frames/000000_layers.npy", p);
    assert!(!p.join("n1").exists(), "a failed sim left --out's parent");
    // search loss --grad-out at a directory: refused before the frames are imaged (the check
    // after the work met frame 0's error first; on a good set the work was done for nothing).
    std::fs::create_dir(p.join("gdir")).unwrap();
    let loss = [
        "search",
        "loss",
        "--dataset",
        "bad",
        "--frames",
        "0:1",
        "--pitch-um",
        "48",
        "--grad-out",
        "gdir",
    ];
    let err = refused(&loss, "--grad-out", p);
    assert!(!err.contains("000000_layers"), "{err}");
    // Refused before the run is read: --head-refit on a set too small for its leave-one-out
    // error, --fit-pitch without a budget (it would do nothing).
    let two = [
        "datagen", "render", "--set", "envelope", "--n", "2", "--width", "80", "--height", "50",
        "--spp", "1", "--out", "ds2",
    ];
    assert!(nanoeye(&two, p).status.success());
    // Another set rendered into that directory is refused naming the set, with both values,
    // before the frame count it implies (the first differing key once named only `frames`).
    let mut other = two;
    other[3] = "ambiguity";
    let err = refused(
        &other,
        "`set`: \"envelope\" there, \"ambiguity\" now; `frames`",
        p,
    );
    assert!(err.contains("--out"), "{err}");
    for flag in ["--head-refit", "--fit-pitch"] {
        let rea = ["search", "rea", "--dataset", "ds2", "--run", "nope", flag];
        refused(&rea, flag, p);
    }
    // --bn-batches: parsed before the run is read; meaningless with the refit, so refused.
    for value in ["0", "-1", "two", "1.5", "ALL"] {
        let rea = ["search", "rea", "--dataset", "ds2", "--run", "nope"];
        refused(
            &[&rea[..], &["--bn-batches", value]].concat(),
            "--bn-batches",
            p,
        );
    }
    let rea = [
        "search",
        "rea",
        "--dataset",
        "ds2",
        "--run",
        "nope",
        "--head-refit",
    ];
    refused(
        &[&rea[..], &["--bn-batches", "4"]].concat(),
        "--bn-batches",
        p,
    );
    // pareto: the refit's set, the chain settings named like everywhere else, and outputs that
    // are directories, before any run is read.
    for (flag, value) in [
        ("--head-refit", "--json"),
        ("--aperture-step-um", "0"),
        ("--exposure-ms", "0"),
        ("--base-pitch-um", "nan"),
        ("--plot", "."),
        ("--state", "."),
        ("--state", "pareto.svg"),
        ("--bootstrap", "2000000"),
        ("--bn-batches", "0"),
        ("--bn-batches", "-1"),
        ("--bn-batches", "two"),
    ] {
        let pareto = ["search", "pareto", "--runs", "nope", "--dataset", "ds2"];
        let e = refused(&[&pareto[..], &[flag, value]].concat(), flag, p);
        // `--plot .` by its own check, not the state's ("--state: . is also --plot", which
        // names --plot too; a helper's review of the tests).
        if value == "." {
            assert!(e.contains(&format!("{flag}: '.' names a directory")), "{e}");
        }
        // BN batches mean nothing with the refit (it takes every frame): refused, not ignored.
        if flag == "--head-refit" {
            let both = [&pareto[..], &[flag, "--bn-batches", "4"]].concat();
            refused(&both, "--bn-batches", p);
        }
    }
    // An empty run in a lens's `+` list or between commas: refused naming --runs.
    for runs in ["nope+,x", "x,,y", "+"] {
        let args = ["search", "pareto", "--runs", runs, "--dataset", "ds2"];
        refused(&args, "--runs", p);
    }
}

#[test]
fn run_refuses_a_bad_config_before_any_work_or_output() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    for (cfg, key) in [
        (r#"{"train_steps": 0}"#, "steps"),
        (r#"{"width_px": 0}"#, "width"),
        (r#"{"pitch_range_um": [24, 12]}"#, "pitch_range_um"),
        (r#"{"pitch_range_um": [3, 12]}"#, "pitch_range_um"),
        (r#"{"rea_population": 0}"#, "population"),
        (r#"{"rea_tournament": 9}"#, "tournament"),
        (r#"{"sequence_frames": 100000000}"#, "sequence_frames"),
        (r#"{"lr_net": 1e300}"#, "lr_net"),
        (r#"{"bogus": 1}"#, "bogus"),
        (r#"{"train_items": "#, "--config"),
        (r#"{"train_items": 0}"#, "train_items"),
        (r#"{"train_set": "protocol"}"#, "train_set"),
        (r#"{"train_blink_fraction": 1.5}"#, "train_blink_fraction"),
        (r#"{"protocol_grid": 1}"#, "protocol_grid"),
        (r#"{"protocol_grid": 8}"#, "protocol_grid"),
        (r#"{"protocol_grid": -3}"#, "protocol_grid"),
        (r#"{"protocol_grid": null}"#, "protocol_grid"),
        (r#"{"final_phase_lr_scale": -0.1}"#, "final_phase_lr_scale"),
        (r#"{"final_phase_lr_scale": 2}"#, "final_phase_lr_scale"),
        (r#"{"final_phase_lr_scale": null}"#, "final_phase_lr_scale"),
        (r#"{"slip_target": null}"#, "slip_target"),
        (r#"{"slip_target": -1}"#, "slip_target"),
        (r#"{"slip_target": "eye"}"#, "slip_target"),
        (r#"{"seed": 1, "solver": 0}"#, "solver"),
        (r#"{"slip_axis_weights": [4, -1, 1]}"#, "slip_axis_weights"),
        (r#"{"slip_axis_weights": [4, 1]}"#, "slip_axis_weights"),
        (r#"{"slip_head_refit": 1}"#, "slip_head_refit"),
        (r#"{"slip_head_refit": null}"#, "slip_head_refit"),
        (r#"{"rea_head_refit": "yes"}"#, "rea_head_refit"),
        (r#"{"phase_basis": "zernike:0"}"#, "phase_basis"),
        (r#"{"phase_basis": "zernike:99"}"#, "phase_basis"),
        (r#"{"phase_basis": 8}"#, "phase_basis"),
        (r#"{"phase_basis": null}"#, "phase_basis"),
        (r#"{"phase_basis": "pixel"}"#, "phase_basis"),
        (r#"{"phase_schedule": "cosine:0"}"#, "phase_schedule"),
        (r#"{"phase_schedule": "cosine:2"}"#, "phase_schedule"),
        (r#"{"phase_schedule": 0.5}"#, "phase_schedule"),
        (r#"{"phase_schedule": null}"#, "phase_schedule"),
        (r#"{"phase_schedule": "cosine:1e999"}"#, "phase_schedule"),
        (r#"{"phase_every": 0}"#, "phase_every"),
        (r#"{"phase_every": -2}"#, "phase_every"),
        (r#"{"phase_every": 2.5}"#, "phase_every"),
        (r#"{"phase_every": null}"#, "phase_every"),
        (r#"{"learned_lens": "bogus"}"#, "learned_lens"),
        (r#"{"learned_lens": null}"#, "learned_lens"),
        (r#"{"learned_lens": 1}"#, "learned_lens"),
        (
            r#"{"learned_lens": "embedding", "embed_triplets": 3}"#,
            "embed_triplets",
        ),
        (
            r#"{"learned_lens": "embedding", "embed_triplets": 1e9}"#,
            "embed_triplets",
        ),
        (
            r#"{"learned_lens": "embedding", "embed_steps": 100000000}"#,
            "embed_steps",
        ),
        (
            r#"{"learned_lens": "embedding", "embed_lr_rad": 0}"#,
            "embed_lr_rad",
        ),
        (
            r#"{"learned_lens": "embedding", "embed_lr_rad": -1}"#,
            "embed_lr_rad",
        ),
        (r#"{"embed_lr_rad": null}"#, "embed_lr_rad"),
        (
            r#"{"learned_lens": "joint", "embed_weight": 0}"#,
            "embed_weight",
        ),
        (
            r#"{"learned_lens": "joint", "embed_weight": -1}"#,
            "embed_weight",
        ),
        (
            r#"{"learned_lens": "joint", "embed_weight": 1e4}"#,
            "embed_weight",
        ),
        (r#"{"embed_weight": null}"#, "embed_weight"),
        (r#"{"embed_weight": "10"}"#, "embed_weight"),
        (
            r#"{"learned_lens": "joint", "embed_triplets": 3}"#,
            "embed_triplets",
        ),
        (r#"{"phase_every": 100000000}"#, "phase_every"),
        (r#"{"rea_bn_batches": 0}"#, "rea_bn_batches"),
        (r#"{"rea_bn_batches": -1}"#, "rea_bn_batches"),
        (r#"{"rea_bn_batches": 1.5}"#, "rea_bn_batches"),
        (r#"{"rea_bn_batches": "ALL"}"#, "rea_bn_batches"),
        (r#"{"rea_bn_batches": null}"#, "rea_bn_batches"),
        // 1e9 batches of 4 frames cannot be held: refused with the MiB needed, not allocated.
        (r#"{"rea_bn_batches": 1000000000}"#, "rea_bn_batches"),
        (
            r#"{"rea_bn_batches": 18446744073709551615}"#,
            "rea_bn_batches",
        ),
        (r#"{"train_items": 2}"#, "slip_head_refit"),
        (
            r#"{"train_items": 2, "slip_head_refit": false, "rea_head_refit": true}"#,
            "train_items",
        ),
        (
            r#"{"train_set": "ambiguity", "train_blink_fraction": 0.1}"#,
            "train_blink_fraction",
        ),
        // A mistyped width: refused, not a failed 64 GB allocation (an audit saw SIGABRT).
        (r#"{"head_widths": [100000000, 100000000]}"#, "head_widths"),
        (r#"{"head_widths": [0, 16]}"#, "head_widths"),
        // 4096 frames a batch through three chains: refused with the GiB it needs.
        (r#"{"batch": 4096}"#, "batch"),
        (r#"{"aperture_step_um": 1e4}"#, "aperture_step_um"),
        (r#"{"pitch_range_um": [12, 1e9]}"#, "pitch_range_um"),
        // The other sets' seeds are seed + 1 … seed + 4 (this overflowed).
        (r#"{"seed": 18446744073709551615}"#, "seed"),
        // An array would be read into the keys by position (`[7]` was seed 7).
        ("[7]", "JSON object"),
        ("[]", "JSON object"),
        // Two bad keys: the one serde's error is about is named (a rig given as a
        // configuration named `camera` and printed `eye_radius_m`'s error).
        (
            r#"{"zeta": 1, "alpha": 2}"#,
            "key \"zeta\": unknown field `zeta`",
        ),
        (r#"{"seed": "x", "batch": "y"}"#, "key \"seed\""),
    ] {
        std::fs::write(p.join("c.json"), cfg).unwrap();
        let err = refused(&["run", "--config", "c.json", "--out", "r"], "--config", p);
        assert!(err.contains(key), "{cfg}: {err}");
        assert!(
            !p.join("r").exists(),
            "{cfg}: a refused run must write nothing"
        );
    }
    // TOML can write NaN and infinities: refused for every key, used by this configuration or
    // not (an audit: `embed_weight = nan` was written to config.json as null, which no resume
    // could read back).
    for (cfg, key) in [
        ("embed_weight = nan", "embed_weight"),
        ("embed_lr_rad = inf", "embed_lr_rad"),
        (
            "slip_axis_weights = [1.0, nan, 1.0]",
            "slip_axis_weights[1]",
        ),
    ] {
        std::fs::write(p.join("c.toml"), cfg).unwrap();
        let err = refused(&["run", "--config", "c.toml", "--out", "r"], "--config", p);
        assert!(
            err.contains(key) && err.contains("not a finite"),
            "{cfg}: {err}"
        );
        assert!(!p.join("r").exists());
        refused(&["run", "--config", "c.toml", "--print-config"], key, p);
    }
}

/// A directory holding a run's results or checkpoints but no config.json is not resumed: which
/// configuration made them is unknown, and a resume would report them under another's (an
/// audit: a copied run without config.json was "complete" under seed 7 with seed 0's numbers).
#[test]
fn run_refuses_a_run_directory_without_its_configuration() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    for f in ["result.json", "runs"] {
        let r = p.join(format!("r_{}", f.replace('.', "_")));
        std::fs::create_dir_all(&r).unwrap();
        if f == "runs" {
            std::fs::create_dir_all(r.join("runs/learned")).unwrap();
        } else {
            std::fs::write(r.join(f), "{}").unwrap();
        }
        let out = r.to_str().unwrap();
        let err = refused(&["run", "--set", "seed=7", "--out", out], "--out", p);
        assert!(err.contains("config.json") && err.contains(f), "{err}");
        assert!(!r.join("config.json").exists(), "nothing written");
    }
}

/// `run --set KEY=VALUE` replaces one key over the defaults and `--config` (the file's value
/// too), reads VALUE as JSON or else as a string, and refuses what it cannot apply naming
/// `--set` and the key, before any work or output.
#[test]
fn run_set_overrides_one_key_and_refuses_bad_ones_naming_it() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    std::fs::write(p.join("c.json"), r#"{"seed": 5, "train_steps": 7}"#).unwrap();
    let out = succeeded(nanoeye(
        &[
            "run",
            "--print-config",
            "--config",
            "c.json",
            "--set",
            "seed=3",
            "--set",
            "phase_schedule=cosine:0.25",
            "--set",
            "pitch_range_um=[12, 20]",
            "--set",
            "solver=\"sphere\"",
        ],
        p,
    ));
    let cfg: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(cfg["seed"], 3, "--set wins over the file");
    assert_eq!(cfg["train_steps"], 7, "the file's other keys stay");
    assert_eq!(cfg["phase_schedule"], "cosine:0.25");
    assert_eq!(cfg["pitch_range_um"], serde_json::json!([12.0, 20.0]));
    assert_eq!(cfg["solver"], "sphere");
    std::fs::write(p.join("r.json"), "{}").unwrap();
    for (sets, key) in [
        (&["seed"][..], "seed"),
        (&["=3"], "=3"),
        (&["bogus=1"], "bogus"),
        (&["seed=1", "seed=2"], "seed"),
        (&["seed=-1"], "seed"),
        (&["seed=1e999"], "seed"),
        (&["seed="], "seed"),
        (&["lr_net=nan"], "lr_net"),
        (&["slip_target=null"], "slip_target"),
        (&["phase_schedule=cosine:0"], "phase_schedule"),
        (&["pitch_range_um=[24, 12]"], "pitch_range_um"),
        (&["train_steps=0"], "train_steps"),
        (&["rig=5"], "rig"),
    ] {
        let mut args = vec!["run", "--out", "r"];
        for s in sets {
            args.extend(["--set", s]);
        }
        let err = refused(&args, "--set", p);
        assert!(err.contains(key), "{sets:?}: {err}");
        assert!(
            !p.join("r").exists(),
            "{sets:?}: a refused run must write nothing"
        );
    }
    // A configuration the job would refuse is not printed as if it would run.
    let err = refused(
        &["run", "--print-config", "--set", "train_steps=0"],
        "--set",
        p,
    );
    assert!(err.contains("train_steps"), "{err}");
    // A long value is not echoed whole (a 100 kB one was, twice: 200 kB of stderr).
    let big = format!("seed={}", "x".repeat(100_000));
    let err = refused(&["run", "--out", "r", "--set", &big], "--set seed", p);
    assert!(err.len() < 4096, "{} bytes of error", err.len());
    assert!(err.contains("characters]"), "{err}");
    // And not by clap either, whose usage errors keep their exit status 2.
    let bad = "x".repeat(100_000);
    let out = nanoeye(&["optics", "psf", "--pitch-um", &bad, "--out", "o"], p);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(err.len() < 4096 && err.contains("--pitch-um"), "{err}");
    // A rig that parses but fails its checks was named as --config's.
    let shown = nanoeye(&["rig", "show", "--json"], p);
    let good = String::from_utf8(shown.stdout).unwrap();
    let bad = good
        .trim()
        .replace("\"eye_radius_m\":0.012", "\"eye_radius_m\":-1");
    assert_ne!(bad, good.trim(), "the default rig's eye radius is 12 mm");
    let set = format!("rig={bad}");
    let err = refused(&["run", "--out", "r", "--set", &set], "--set rig", p);
    assert!(
        err.contains("eye_radius_m") && !err.contains("--config"),
        "{err}"
    );
    assert!(!p.join("r").exists());
    let both = ["run", "--out", "r", "--rig", "r.json", "--set", "rig=null"];
    let err = refused(&both, "--rig", p);
    assert!(err.contains("--set rig"), "{err}");
    assert!(!p.join("r").exists());
}

#[test]
fn datagen_export_refuses_bad_states_and_writes_a_glb() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    let ok_state = r#"{"azimuth_rad":0.1,"elevation_rad":-0.1,"torsion_rad":0,"slip_m":[0,0,0]}"#;
    for (state, flag) in [
        (r#"{"azimuth_rad":0.1}"#, "--state"),
        (
            r#"{"azimuth_rad":2,"elevation_rad":0,"torsion_rad":0,"slip_m":[0,0,0]}"#,
            "azimuth_rad",
        ),
        (
            r#"{"azimuth_rad":0,"elevation_rad":1e300,"torsion_rad":0,"slip_m":[0,0,0]}"#,
            "elevation_rad",
        ),
        (
            r#"{"azimuth_rad":0,"elevation_rad":0,"torsion_rad":0,"slip_m":[0,0,0],"lid_closure":3}"#,
            "lid_closure",
        ),
        // A vector by its components (its length overflowed and was shown as `inf`).
        (
            r#"{"azimuth_rad":0,"elevation_rad":0,"torsion_rad":0,"slip_m":[1e300,0,0]}"#,
            "slip_m: [1e300, 0.0, 0.0] has length inf",
        ),
        ("missing.json", "--state"),
        // A state laid out as an array, inline: named as such (it was looked for as a file
        // named '[0.1,…]'; a helper's audit).
        ("[0.1, 0.2, 0.0, [0, 0, 0]]", "a JSON object"),
        // A misspelt key was ignored (an audit).
        (
            r#"{"azimuth_rad":0,"elevation_rad":0,"torsion_rad":0,"slip_m":[0,0,0],"lid_closur":0.5}"#,
            "lid_closur",
        ),
    ] {
        refused(
            &["datagen", "export", "--state", state, "--out", "s.glb"],
            flag,
            p,
        );
    }
    refused(
        &["datagen", "export", "--state", ok_state, "--out", "s.png"],
        "--out",
        p,
    );
    assert!(entries(p).is_empty(), "nothing written: {:?}", entries(p));
    succeeded(nanoeye(
        &[
            "datagen",
            "export",
            "--subject",
            "3",
            "--state",
            ok_state,
            "--out",
            "s.glb",
            "--json",
        ],
        p,
    ));
    let bytes = std::fs::read(p.join("s.glb")).unwrap();
    assert_eq!(&bytes[0..4], b"glTF");
    assert_eq!(
        u32::from_le_bytes(bytes[8..12].try_into().unwrap()) as usize,
        bytes.len()
    );
    // Every key a state has, the optional ones included, is known.
    let full = r#"{"azimuth_rad":0,"elevation_rad":0,"torsion_rad":0,"slip_m":[0,0,0],"cam_rot_rad":[0,0,0],"lid_closure":0}"#;
    succeeded(nanoeye(
        &["datagen", "export", "--state", full, "--out", "f.glb"],
        p,
    ));
}

/// Defects the input property test (cli/tests/input_proptest.rs) found: each was a panic, a
/// hang, or an error that named another flag (or none).
#[test]
fn inputs_found_by_the_property_test_are_refused_naming_their_flag() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    let psf = ["optics", "psf", "--out", "o"];
    let fc = [
        "fisher",
        "compare",
        "--window-px",
        "9",
        "--aperture-step-um",
        "50",
        "--montage",
        "m.png",
    ];
    let cell = [
        "metalib",
        "cell",
        "--height-nm",
        "700",
        "--diameter-nm",
        "200",
    ];
    for (args, flag) in [
        // A range count beyond usize overflowed (a panic in debug builds, an empty range in
        // release builds); 2 million depth planes ran for hours.
        ("--depths-mm=0:1e300:1e-300", "--depths-mm"),
        ("--depths-mm=-1e308:1e308:1", "--depths-mm"),
        ("--depths-mm=20:22:1e-6", "--depths-mm"),
        // Positive in mm, 0 in m.
        ("--sensor-mm=4.9e-324", "--sensor-mm"),
        // Subnormal in m: printed as a pitch no physical check accepts.
        ("--pitch-um=1.1452463331739244e-302", "--pitch-um"),
        ("--aperture-mm=18446744073709551615", "--aperture-mm"),
    ] {
        refused(&[&psf[..], &["--window-px", "16", args]].concat(), flag, p);
    }
    // A flag that shapes another lens than the one chosen was silently ignored.
    for (args, flag) in [
        (vec!["--dh-zones=0"], "--dh-zones"),
        (vec!["--lens=double-helix", "--focus-mm=20"], "--focus-mm"),
        (vec!["--lens=file:p.npy", "--dh-zones=4"], "--dh-zones"),
    ] {
        refused(&[&psf[..], &args].concat(), flag, p);
        assert!(!p.join("o").exists());
    }
    // 1001 planes of 1024² pixels: 4 GiB of stack and a 1 GB montage.
    refused(
        &[&psf[..], &["--window-px", "1024", "--depths-mm=20:30:0.01"]].concat(),
        "--depths-mm/--window-px",
        p,
    );
    for (args, flag) in [
        (vec!["--depths-mm=4.9e-324:15:1"], "--depths-mm"),
        (vec!["--depths-mm=-1e308:15:1e-20"], "--depths-mm"),
        (vec!["--pitch-um=1e20"], "--pitch-um"),
        (
            vec!["--pitch-um=3,100", "--depths-mm=20:22:1"],
            "--pitch-um",
        ),
    ] {
        refused(&[&fc[..], &args].concat(), flag, p);
    }
    for (args, flag) in [
        // (n + ik)² overflowed, 1/ε overflowed: a "numerical failure" naming no flag.
        (vec!["--pitch-nm=530", "--n-pillar=7e239"], "--n-pillar"),
        (
            vec!["--pitch-nm=530", "--n-background=3e-124"],
            "--n-background",
        ),
        (vec!["--pitch-nm=530", "--k-pillar=1e300"], "--k-pillar"),
        // "--pitch: …" and "--diameter-nm: … exceeds the pitch".
        (vec!["--pitch-nm=0"], "--pitch-nm"),
        (vec!["--pitch-nm=1"], "--pitch-nm"),
        (vec!["--pitch-nm=1"], "--diameter-nm"),
    ] {
        refused(&[&cell[..], &args].concat(), flag, p);
    }
    // "invalid parameter `fractions`" (plan) and "--out sw: …" (sweep) named no flag.
    refused(
        &[
            "metalib",
            "sweep",
            "--plan-ranks",
            "2",
            "--fractions=100:100:1",
        ],
        "--fractions",
        p,
    );
    refused(
        &[
            "metalib",
            "sweep",
            "--out",
            "sw",
            "--harmonics",
            "1",
            "--heights-nm",
            "700:700:10",
            "--pitches-nm",
            "530:530:10",
            "--fractions=0.5:1.5:0.5",
        ],
        "--fractions",
        p,
    );
    // No flat-field level below saturation: named the sensor's full well, not a flag; then
    // the flags with a library parameter's name (`full_well_e`) and no figure of theirs.
    let err = refused(
        &[
            "sensor",
            "ptc",
            "--side-px",
            "8",
            "--levels",
            "4",
            "--read-noise-e=977",
        ],
        "--read-noise-e",
        p,
    );
    assert!(
        err.contains("977") && err.contains("full well") && !err.contains("full_well_e"),
        "{err}"
    );
    // A valid rig whose camera never sees the pupil: the sampler's error named no input.
    let out = nanoeye(&["rig", "show", "--json"], p);
    let mut rig: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    rig["camera"]["cy_px"] = serde_json::json!(0.0);
    std::fs::write(p.join("cy.json"), rig.to_string()).unwrap();
    assert!(
        nanoeye(&["rig", "show", "--rig", "cy.json"], p)
            .status
            .success()
    );
    refused(
        &[
            "datagen",
            "states",
            "--set",
            "ambiguity",
            "--n",
            "2",
            "--out",
            "s.jsonl",
            "--rig",
            "cy.json",
        ],
        "--rig",
        p,
    );
    assert_eq!(entries(p), ["cy.json"], "a refused command wrote files");
}

/// A stage's error reaches the user once: the wrapping errors carried it both in their message
/// and as `source()`, so `{:#}` printed "i/o error on …missing.npy: No such file…" three times.
#[test]
fn a_wrapped_stage_error_is_printed_once() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    assert!(nanoeye(&tiny_dataset("ds"), p).status.success());
    let err = refused(
        &[
            "sim",
            "--dataset",
            "ds",
            "--lens",
            "file:missing.npy",
            "--pitch-um",
            "6",
            "--out",
            "s",
            "--json",
        ],
        "--lens",
        p,
    );
    assert_eq!(err.matches("missing.npy").count(), 1, "{err}");
    assert!(!p.join("s").exists(), "{:?}", entries(p));
}

/// A dataset's stored layers hold premultiplied radiance (finite, ≥ 0) and coverage (a
/// fraction of samples): an edited file with α = 5 imaged 4.96e8 electrons and radiance −1000
/// a black frame, exit 0 (a helper's audit). Refused naming the file, the layer and the value.
#[test]
fn layers_holding_impossible_radiance_or_coverage_are_refused() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    assert!(nanoeye(&tiny_dataset("ds"), p).status.success());
    fn sim(ds: &str) -> Vec<&str> {
        let mut a = common::TINY_CHAIN.to_vec();
        a[1] = ds;
        [&["sim"][..], &a, &["--noise", "off", "--out", "so"]].concat()
    }
    succeeded(nanoeye(&sim("ds"), p));
    // Layer 0's radiance plane first, then its coverage (80 × 50 values each).
    for (name, at, v, says) in [
        ("neg", 0usize, -1000.0f32, "radiance of -1000"),
        ("nan", 7, f32::NAN, "radiance of NaN"),
        ("alpha", 4000, 5.0, "coverage of 5"),
        ("alphaneg", 4001, -0.5, "coverage of -0.5"),
    ] {
        common::copy_dir(&p.join("ds"), &p.join(name));
        let f = p.join(name).join("frames/000000_layers.npy");
        let mut b = std::fs::read(&f).unwrap();
        let data = 10 + u16::from_le_bytes([b[8], b[9]]) as usize;
        b[data + 4 * at..][..4].copy_from_slice(&v.to_le_bytes());
        std::fs::write(&f, b).unwrap();
        let e = refused(&sim(name), "000000_layers.npy", p);
        assert!(e.contains(says) && e.contains("layer 0"), "{name}: {e}");
    }
}

#[test]
fn search_embed_runs_resumes_and_names_its_bad_flags() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    let mut tv = tiny_dataset("tv");
    tv[3] = "variational";
    tv[5] = "2";
    assert!(nanoeye(&tv, p).status.success());
    assert!(nanoeye(&tiny_dataset("ds"), p).status.success());
    let run = |extra: &[&str]| {
        let mut a = vec!["search", "embed", "--dataset", "tv"];
        // TINY_CHAIN's camera flags, on the triplets.
        a.extend(&common::TINY_CHAIN[2..]);
        a.extend(["--steps", "2", "--batch", "2", "--out", "e", "--json"]);
        // A flag already there takes the new value (given twice, clap's own error would
        // name it whatever the value).
        let mut rest = extra;
        while let [f, v, tail @ ..] = rest {
            match a.iter().position(|x| x == f) {
                Some(i) if f.starts_with("--") => {
                    a[i + 1] = v;
                    rest = tail;
                }
                _ => break,
            }
        }
        a.extend(rest);
        a.into_iter().map(String::from).collect::<Vec<_>>()
    };
    fn args(v: &[String]) -> Vec<&str> {
        v.iter().map(String::as_str).collect()
    }
    for (extra, flag) in [
        (vec!["--steps", "10000001"], "--steps"),
        (vec!["--batch", "0"], "--batch"),
        (vec!["--batch", "3"], "--batch"),
        (vec!["--lr-phase-rad", "nan"], "--lr-phase-rad"),
        (vec!["--lr-phase-rad=-1"], "--lr-phase-rad"),
        (vec!["--w-sens", "0", "--w-orth", "0"], "--w-sens"),
        (vec!["--w-orth=-1"], "--w-orth"),
        (vec!["--w-sens", "inf"], "--w-sens"),
        (vec!["--checkpoint-every", "0"], "--checkpoint-every"),
        (vec!["--eval-chunk", "0"], "--eval-chunk"),
        (vec!["--lens", "file:nope.npy"], "--lens"),
        (vec!["--lens", "concave"], "--lens"),
        (vec!["--dataset", "ds"], "--dataset"),
        (vec!["--pitch-um", "nan"], "--pitch-um"),
        // Finer than the native grid, and beyond the sensor: named, and nothing written (a
        // helper's audit: `invalid \`pitch\`` and a rig field, after e/ held two files).
        (vec!["--pitch-um", "1"], "--pitch-um"),
        (vec!["--pitch-um", "100000"], "--pitch-um"),
    ] {
        let v = run(&extra);
        refused(&args(&v), flag, p);
        assert!(!p.join("e").exists(), "{extra:?} wrote e/");
    }
    let ok = nanoeye(&args(&run(&[])), p);
    assert!(
        ok.status.success(),
        "{}",
        String::from_utf8_lossy(&ok.stderr)
    );
    let out: serde_json::Value = serde_json::from_slice(&ok.stdout).unwrap();
    assert_eq!(out["steps"], 2);
    assert_eq!(out["triplets"], 2);
    for k in ["loss", "l_sens", "l_orth", "crlb_slip_um", "crlb_gaze_deg"] {
        for s in ["init", "final"] {
            assert!(
                out[s][k].as_f64().is_some_and(f64::is_finite),
                "{s}.{k}: {out}"
            );
        }
    }
    for f in [
        "checkpoint.bin",
        "phase.npy",
        "history.jsonl",
        "embed.svg",
        "metrics.json",
        "init.json",
        "lens.json",
        "inputs.json",
    ] {
        assert!(p.join("e").join(f).is_file(), "{f} missing");
    }
    let hist = std::fs::read_to_string(p.join("e/history.jsonl")).unwrap();
    assert_eq!(hist.lines().count(), 2);
    let phase = std::fs::read(p.join("e/phase.npy")).unwrap();
    // The same command again: nothing left to run, the same lens and bounds.
    let again = nanoeye(&args(&run(&[])), p);
    assert!(again.status.success());
    let out2: serde_json::Value = serde_json::from_slice(&again.stdout).unwrap();
    assert_eq!(out2["final"], out["final"]);
    assert_eq!(std::fs::read(p.join("e/phase.npy")).unwrap(), phase);
    // Another rate or another starting lens is refused, naming it; nothing is changed.
    refused(&args(&run(&["--lr-phase-rad", "0.01"])), "lr_rad", p);
    refused(&args(&run(&["--lens", "double-helix"])), "--lens", p);
    // So is a chain setting the checkpoint does not hold (inputs.json).
    let e = refused(&args(&run(&["--base-pitch-um", "1"])), "--base-pitch-um", p);
    assert!(e.contains("differs from the run being resumed"), "{e}");
    assert_eq!(std::fs::read(p.join("e/phase.npy")).unwrap(), phase);
    // A run killed before its first checkpoint leaves init.json alone: another lens started
    // there computes its own bounds (an audit: it reported the killed run's).
    std::fs::create_dir_all(p.join("k")).unwrap();
    std::fs::copy(p.join("e/init.json"), p.join("k/init.json")).unwrap();
    let mut v = run(&["--lens", "double-helix"]);
    let k = v.iter().position(|a| a == "e").unwrap();
    v[k] = "k".into();
    let dh = nanoeye(&args(&v), p);
    let dh: serde_json::Value = serde_json::from_slice(&succeeded(dh).stdout).unwrap();
    assert_ne!(
        dh["init"], out["init"],
        "the hyperbolic run's bounds reported"
    );
    // The hyperbolic run's checkpoint copied over the double-helix run's: its records there
    // (lens.json, inputs.json) are not its own, so it is refused naming the key (it resumed,
    // reporting the hyperbolic run's lens as the double-helix run's).
    std::fs::copy(p.join("e/checkpoint.bin"), p.join("k/checkpoint.bin")).unwrap();
    let e = refused(&args(&v), "other inputs", p);
    assert!(e.contains("`lens`"), "{e}");
    // A starting lens that is one of the run's outputs is refused before the steps (it was
    // replaced by the run's phase map, exit 0), and so is a directory where an output goes
    // (found after the training, with the checkpoint written).
    std::fs::create_dir_all(p.join("l")).unwrap();
    std::fs::copy(p.join("e/phase.npy"), p.join("l/phase.npy")).unwrap();
    let mut v = run(&["--lens", "file:l/phase.npy"]);
    let k = v.iter().position(|a| a == "e").unwrap();
    v[k] = "l".into();
    let e = refused(&args(&v), "--out", p);
    assert!(e.contains("phase.npy is --lens"), "{e}");
    assert_eq!(std::fs::read(p.join("l/phase.npy")).unwrap(), phase);
    assert_eq!(entries(&p.join("l")), ["phase.npy"]);
    std::fs::create_dir_all(p.join("m/metrics.json")).unwrap();
    let mut v = run(&[]);
    v[k] = "m".into();
    let e = refused(&args(&v), "--out metrics.json", p);
    assert!(e.contains("directory"), "{e}");
    assert_eq!(entries(&p.join("m")), ["metrics.json"]);
}

#[test]
fn search_train_embedding_term_runs_resumes_and_names_its_bad_flags() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    for (name, seed) in [("tv", "1"), ("tw", "2")] {
        let mut tv = tiny_dataset(name);
        tv[3] = "variational";
        tv[5] = "2";
        let mut a: Vec<&str> = tv.to_vec();
        a.extend(["--seed", seed]);
        assert!(nanoeye(&a, p).status.success());
    }
    assert!(nanoeye(&tiny_dataset("ds"), p).status.success());
    let run = |extra: &[&str]| {
        let mut a = vec!["search", "train"];
        a.extend(common::TINY_CHAIN);
        a.extend(common::TINY_TRAIN);
        a.extend(["--out", "o", "--json"]);
        a.extend(extra);
        a.into_iter().map(String::from).collect::<Vec<_>>()
    };
    fn args(v: &[String]) -> Vec<&str> {
        v.iter().map(String::as_str).collect()
    }
    // `plus` leaves out --embed-batch (4 by default, more than the set's 2 triplets): each
    // case is refused by the setting it names, before the triplet count is looked at.
    let base = ["--embed-weight", "1", "--embed-triplets", "tv"];
    let with = [&base[..], &["--embed-batch", "2"]].concat();
    let plus = |more: &[&'static str]| -> Vec<&'static str> { [&base[..], more].concat() };
    for (extra, flag) in [
        (vec!["--embed-weight", "nan"], "--embed-weight"),
        (
            vec!["--embed-weight=-1", "--embed-triplets", "tv"],
            "--embed-weight",
        ),
        (
            vec!["--embed-weight", "2000", "--embed-triplets", "tv"],
            "--embed-weight",
        ),
        (vec!["--embed-weight", "1"], "--embed-triplets"),
        (vec!["--embed-triplets", "tv"], "--embed-weight"),
        (plus(&["--fixed-lens"]), "--embed-weight"),
        (plus(&["--embed-batch", "0"]), "--embed-batch"),
        (plus(&["--embed-batch", "3"]), "--embed-batch"),
        (
            vec!["--embed-weight", "1", "--embed-triplets", "tv"],
            "--embed-batch",
        ),
        (
            plus(&["--embed-w-sens", "0", "--embed-w-orth", "0"]),
            "--embed-w-sens",
        ),
        (plus(&["--embed-w-orth", "inf"]), "--embed-w-orth"),
        (
            vec!["--embed-weight", "1", "--embed-triplets", "ds"],
            "--embed-triplets",
        ),
        (
            vec!["--embed-weight", "1", "--embed-triplets", "nope"],
            "--embed-triplets",
        ),
    ] {
        let v = run(&extra);
        refused(&args(&v), flag, p);
        assert!(!p.join("o").exists(), "{extra:?} wrote o/");
    }
    let ok = nanoeye(&args(&run(&with)), p);
    assert!(
        ok.status.success(),
        "{}",
        String::from_utf8_lossy(&ok.stderr)
    );
    let hist = std::fs::read_to_string(p.join("o/history.jsonl")).unwrap();
    assert_eq!(hist.lines().count(), 2);
    for l in hist.lines() {
        let r: serde_json::Value = serde_json::from_str(l).unwrap();
        assert!(r["embed_loss"].as_f64().is_some_and(f64::is_finite), "{l}");
    }
    let phase = std::fs::read(p.join("o/phase.npy")).unwrap();
    // The same command again: nothing left to run, the same lens.
    assert!(nanoeye(&args(&run(&with)), p).status.success());
    assert_eq!(std::fs::read(p.join("o/phase.npy")).unwrap(), phase);
    // Another weight or another triplet set is refused, naming it; nothing is changed.
    refused(
        &args(&run(&[
            "--embed-weight",
            "2",
            "--embed-triplets",
            "tv",
            "--embed-batch",
            "2",
        ])),
        "embed_weight",
        p,
    );
    refused(
        &args(&run(&[
            "--embed-weight",
            "1",
            "--embed-triplets",
            "tw",
            "--embed-batch",
            "2",
        ])),
        "--embed-triplets",
        p,
    );
    // Without the term: the run's triplet set is part of its lens.
    refused(&args(&run(&[])), "--embed-triplets", p);
    // The data and the chain's settings no checkpoint holds are the run's too (inputs.json).
    for (more, flag) in [
        (["--base-pitch-um", "1"], "--base-pitch-um"),
        (["--val", "tv"], "--val"),
    ] {
        let e = refused(&args(&run(&[&with[..], &more[..]].concat())), flag, p);
        assert!(e.contains("differs from the run being resumed"), "{e}");
    }
    // The same path holding another triplet set (tw's, rendered with another seed): refused by
    // its digest, not accepted by its name.
    std::fs::rename(p.join("tv"), p.join("tv_orig")).unwrap();
    std::fs::rename(p.join("tw"), p.join("tv")).unwrap();
    let e = refused(&args(&run(&with)), "--embed-triplets", p);
    assert!(e.contains("differs from the run being resumed"), "{e}");
    std::fs::rename(p.join("tv"), p.join("tw")).unwrap();
    std::fs::rename(p.join("tv_orig"), p.join("tv")).unwrap();
    assert!(nanoeye(&args(&run(&with)), p).status.success());
    assert_eq!(std::fs::read(p.join("o/phase.npy")).unwrap(), phase);
    // A checkpoint copied from another run's --out, whose records beside it are not its own,
    // is refused naming what differs (it resumed, mixing two runs); so is an empty one, which
    // no save writes (it was taken for none and overwritten).
    let mut o2 = run(&[&with[..], &["--val", "tv"][..]].concat());
    let k = o2.iter().position(|a| a == "o").unwrap();
    o2[k] = "o2".into();
    succeeded(nanoeye(&args(&o2), p));
    let ck2 = p.join("o2/checkpoint.bin");
    std::fs::copy(p.join("o/checkpoint.bin"), &ck2).unwrap();
    let e = refused(&args(&o2), "other inputs", p);
    assert!(e.contains("`val`"), "{e}");
    std::fs::write(&ck2, b"").unwrap();
    refused(&args(&o2), "is empty", p);
    assert_eq!(std::fs::read(&ck2).unwrap(), b"");
}

#[test]
fn compare_names_what_it_cannot_read_and_writes_nothing_then() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    // A finished run as `nanoeye run` leaves it: today's default configuration and a result.
    let cfg = nanoeye(&["run", "--print-config"], p);
    assert!(cfg.status.success());
    std::fs::create_dir_all(p.join("r0")).unwrap();
    std::fs::write(p.join("r0/config.json"), &cfg.stdout).unwrap();
    let result = serde_json::json!({"protocol": {
        "learned": {"mean_deg": 9.5}, "hyperbolic": {"mean_deg": 9.0},
        "double_helix": {"mean_deg": 8.0}}});
    std::fs::write(p.join("r0/result.json"), result.to_string()).unwrap();
    let ok = nanoeye(&["compare", "r0", "--json"], p);
    assert!(
        ok.status.success(),
        "{}",
        String::from_utf8_lossy(&ok.stderr)
    );
    let c: serde_json::Value = serde_json::from_slice(&ok.stdout).unwrap();
    assert_eq!(c["groups"][0]["learned_minus"][1]["mean"], 1.5);
    let before = entries(p);
    refused(&["compare"], "RUNS", p);
    refused(&["compare", "nowhere"], "nowhere: no config.json", p);
    refused(&["compare", "r0", "r0"], "same configuration and seed 0", p);
    refused(&["compare", "r0", "--metric", "nan"], "--metric", p);
    refused(
        &["compare", "r0", "--metric", "dice"],
        "protocol.learned.dice",
        p,
    );
    refused(&["compare", "r0", "--svg", "r0"], "--svg", p);
    refused(
        &["compare", "r0", "--svg", "r0/config.json/c.svg"],
        "--svg",
        p,
    );
    std::fs::create_dir_all(p.join("r1")).unwrap();
    std::fs::write(p.join("r1/config.json"), &cfg.stdout).unwrap();
    refused(&["compare", "r0", "r1"], "r1: no result.json", p);
    std::fs::write(p.join("r1/result.json"), "{\"protocol\": {}").unwrap();
    refused(&["compare", "r1"], "r1/result.json: not JSON", p);
    // --svg at a run's own file: refused, the run intact (the plot replaced result.json).
    for name in ["result.json", "config.json"] {
        let target = format!("r0/{name}");
        let before = std::fs::read(p.join(&target)).unwrap();
        refused(&["compare", "r0", "--svg", &target], "--svg", p);
        assert_eq!(std::fs::read(p.join(&target)).unwrap(), before);
    }
    // Nor any other place in a run (it replaced a lens's rig.json, which `track` then refused;
    // a helper's audit, fifty-fifth session).
    std::fs::create_dir_all(p.join("r0/runs/learned")).unwrap();
    std::fs::write(p.join("r0/runs/learned/rig.json"), b"{}").unwrap();
    for target in [
        "r0/runs/learned/rig.json",
        "r0/plot.svg",
        "./r0/../r0/stages.json",
    ] {
        refused(
            &["compare", "r0", "--svg", target],
            "lies inside the run",
            p,
        );
    }
    assert_eq!(
        std::fs::read(p.join("r0/runs/learned/rig.json")).unwrap(),
        b"{}"
    );
    assert!(!p.join("r0/plot.svg").exists() && !p.join("r0/stages.json").exists());
    // A demo or a Dice a job cannot have written: refused by key (a demo of 1e308 printed
    // its mean as null and inf with exit 0), and a pitch of 0.
    for (extra, key) in [
        (
            serde_json::json!({"demo_sequence": {"mean_deg": 1e308}}),
            "demo_sequence.mean_deg",
        ),
        (
            serde_json::json!({"demo_sequence": {"mean_deg": -1}}),
            "demo_sequence.mean_deg",
        ),
        (serde_json::json!({"pitch_um": 0.0}), "pitch_um"),
    ] {
        let mut r = result.clone();
        r.as_object_mut()
            .unwrap()
            .extend(extra.as_object().unwrap().clone());
        std::fs::write(p.join("r1/result.json"), r.to_string()).unwrap();
        refused(&["compare", "r1"], key, p);
    }
    let mut r = result.clone();
    for (lens, dice) in [("learned", 7.0), ("hyperbolic", 0.7), ("double_helix", 0.7)] {
        r["protocol"][lens]["dice"] = serde_json::json!(dice);
    }
    std::fs::write(p.join("r1/result.json"), r.to_string()).unwrap();
    refused(
        &["compare", "r1", "--metric", "dice"],
        "protocol.learned.dice",
        p,
    );
    // A run file that is a FIFO: refused, not read forever.
    std::fs::remove_file(p.join("r1/result.json")).unwrap();
    common::mkfifo(&p.join("r1/result.json"));
    refused(&["compare", "r1"], "not a regular file", p);
    assert_eq!(
        entries(p),
        before.into_iter().chain(["r1".into()]).collect::<Vec<_>>()
    );
}

/// `metalib select` marks a cell of the sweep: a mark given off the sweep's grid is refused
/// naming its flag (it was drawn at the nearest cell, however far); the default snaps to the
/// nearest pair; the JSON leaves out what a pair does not have rather than writing null.
#[test]
fn select_marks_a_pair_of_the_sweep_and_writes_no_null() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    let sweep = nanoeye(
        &[
            "metalib",
            "sweep",
            "--out",
            "sw",
            "--harmonics",
            "1",
            "--heights-nm",
            "600:800:100",
            "--pitches-nm",
            "500:500:10",
            "--fractions",
            "0.3:0.5:0.1",
        ],
        p,
    );
    assert!(
        sweep.status.success(),
        "{}",
        String::from_utf8_lossy(&sweep.stderr)
    );
    fn select<'a>(extra: &[&'a str]) -> Vec<&'a str> {
        let mut args = vec!["metalib", "select", "--sweep", "sw", "--json"];
        args.extend_from_slice(extra);
        args
    }
    for (flag, v) in [
        ("--mark-height-nm", "12345"),
        ("--mark-height-nm", "650"),
        ("--mark-pitch-nm", "1e300"),
    ] {
        let err = refused(&select(&[flag, v]), flag, p);
        assert!(
            err.contains("600 … 800 nm") || err.contains("500 … 500 nm"),
            "{err}"
        );
    }
    for extra in [
        &[][..],
        &["--mark-height-nm", "800", "--mark-pitch-nm", "500"],
    ] {
        let out = nanoeye(&select(extra), p);
        assert!(
            out.status.success(),
            "{extra:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        let text = String::from_utf8(out.stdout).unwrap();
        let v: serde_json::Value = serde_json::from_str(&text).unwrap();
        assert_eq!(v["pairs"].as_object().unwrap().len(), 3, "{text}");
        assert!(!text.contains("null"), "{text}");
    }
}

/// `nanoeye args` in `cwd` with environment variable `var` set to `bytes`.
fn with_env(var: &str, args: &[&str], bytes: &str, cwd: &Path) -> std::process::Output {
    std::process::Command::new(common::BIN)
        .args(args)
        .current_dir(cwd)
        .env(var, bytes)
        .output()
        .expect("run nanoeye")
}

/// `nanoeye args` in `cwd` with the memory budget capped at `bytes`.
fn with_memory(args: &[&str], bytes: &str, cwd: &Path) -> std::process::Output {
    with_env("NANOEYE_MEMORY_BYTES", args, bytes, cwd)
}

/// Under `ulimit -v` a plan may take half what the limit leaves: the allocator reserves
/// address space ahead of use (sim's peaked at 2.0–2.6× its resident set), and `sim
/// --aperture-step-um 0.2`, estimated at 3.56 GiB, passed the check under a 3.81 GiB limit and
/// aborted on an allocation with a backtrace (a helper's audit). Here 0.25 µm samples are
/// estimated at 1.96 GiB on two threads, under a 2.86 GiB limit (the code before ran it):
/// refused before any work, naming the flag.
#[cfg(target_os = "linux")]
#[test]
fn under_an_address_space_limit_a_plan_takes_half_of_what_it_leaves() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    assert!(nanoeye(&tiny_dataset("ds"), p).status.success());
    let out = std::process::Command::new("sh")
        .arg("-c")
        .arg(format!(
            "ulimit -v 3000000 && exec '{}' sim --dataset ds --pitch-um 48 \
             --aperture-step-um 0.25 --out so",
            common::BIN
        ))
        .current_dir(p)
        .output()
        .expect("run sh");
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(
        err.contains("--aperture-step-um: needs about") && err.contains("ulimit -v"),
        "{err}"
    );
    assert_eq!(entries(p), ["ds"], "a refused command wrote something");
}

#[test]
fn aperture_sampling_beyond_the_memory_is_refused_before_any_work() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    assert!(nanoeye(&tiny_dataset("ds"), p).status.success());
    // 0.25 µm samples a 1 mm aperture 4000 × 4000 times: gigabytes, against a 200 MB cap.
    let cases: [(&[&str], &str); 6] = [
        (
            &["run", "--set", "aperture_step_um=0.25", "--out", "ro"],
            "aperture_step_um",
        ),
        (
            &["optics", "psf", "--sample-um", "0.25", "--out", "ps"],
            "--sample-um",
        ),
        (
            &[
                "fisher",
                "compare",
                "--aperture-step-um",
                "0.25",
                "--montage",
                "m.png",
            ],
            "--aperture-step-um",
        ),
        (
            &[
                "fisher",
                "init",
                "--aperture-step-um",
                "0.25",
                "--out",
                "fi",
            ],
            "--aperture-step-um",
        ),
        (
            &[
                "sim",
                "--dataset",
                "ds",
                "--pitch-um",
                "12",
                "--aperture-step-um",
                "0.25",
                "--out",
                "so",
            ],
            "--aperture-step-um",
        ),
        (
            &[
                "search",
                "train",
                "--dataset",
                "ds",
                "--aperture-step-um",
                "0.25",
                "--steps",
                "1",
                "--out",
                "st",
            ],
            "--aperture-step-um",
        ),
    ];
    for (args, flag) in cases {
        let out = with_memory(args, "2e8", p);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{args:?} ran under a 200 MB cap");
        assert!(err.contains(flag) && err.contains("GiB"), "{args:?}: {err}");
        assert!(!err.contains("panicked"), "{args:?}: {err}");
    }
    assert_eq!(entries(p), ["ds"], "a refused command wrote something");
    // The default sampling fits the same cap, and a cap that is no number is named.
    succeeded(with_memory(
        &["optics", "psf", "--depths-mm", "20", "--out", "ps"],
        "2e8",
        p,
    ));
    let out = with_memory(&["optics", "psf", "--out", "ps2"], "lots", p);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("NANOEYE_MEMORY_BYTES"));
    // The RCWA at the most harmonics allowed (40 orders: 4.5 GB a solve): an allocation
    // failure inside the eigen-solver panicked under ulimit -v (a helper's audit). Refused
    // under a 1 GB cap before any solve, naming --harmonics; 10 orders fit the same cap.
    let h40 =
        |cmd: &[&'static str]| -> Vec<&'static str> { [cmd, &["--harmonics", "40"]].concat() };
    for args in [
        h40(&[&common::CELL[..], &["--json"]].concat()),
        h40(&[
            "metalib",
            "sweep",
            "--heights-nm",
            "700:700:10",
            "--pitches-nm",
            "530:530:10",
            "--fractions",
            "0.3:0.4:0.1",
            "--out",
            "sw",
        ]),
        h40(&["metalib", "material-study", "--json"]),
    ] {
        let out = with_memory(&args, "1e9", p);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{args:?} ran under a 1 GB cap");
        assert!(
            err.contains("--harmonics") && err.contains("GiB") && !err.contains("panicked"),
            "{args:?}: {err}"
        );
    }
    assert!(!p.join("sw").exists());
    let ok = [&common::CELL[..], &["--harmonics", "10", "--json"]].concat();
    succeeded(with_memory(&ok, "1e9", p));
}

#[test]
fn fisher_init_checks_every_output_before_writing_any() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    let init = |out: &'static str| {
        let args = [
            "fisher",
            "init",
            "--out",
            out,
            "--aperture-step-um",
            "50",
            "--window-px",
            "3",
            "--iterations",
            "1",
        ];
        refused(&args, "--out", p)
    };
    std::fs::create_dir_all(p.join("fi/history.json")).unwrap();
    let e = init("fi");
    assert!(e.contains("history.json"), "{e}");
    assert_eq!(entries(&p.join("fi")), ["history.json"], "{e}");
    // The checkpoint's place too, which is written first (a file there failed after the work).
    std::fs::create_dir_all(p.join("fc")).unwrap();
    std::fs::write(p.join("fc/checkpoint"), b"").unwrap();
    let e = init("fc");
    assert!(e.contains("checkpoint"), "{e}");
    assert_eq!(entries(&p.join("fc")), ["checkpoint"], "{e}");
}

/// A sweep directory's files as an attacker or a failed copy leaves them: refused naming
/// `--sweep`, never hung on or allocated for; the figure set and the study's JSON complete.
#[test]
fn metalib_select_and_study_refuse_crafted_sweeps_and_print_no_null() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    let sweep = |out: &str, heights: &str, fractions: &str| {
        let args = [
            "metalib",
            "sweep",
            "--out",
            out,
            "--harmonics",
            "1",
            "--heights-nm",
            heights,
            "--pitches-nm",
            "500:500:10",
            "--fractions",
            fractions,
        ];
        succeeded(nanoeye(&args, p));
    };
    sweep("sw", "700:700.4:0.2", "0.3:0.5:0.1");
    let select = |dir: &str| {
        let figures = format!("{dir}_fig");
        let args = [
            "metalib",
            "select",
            "--sweep",
            dir,
            "--figures",
            &figures,
            "--json",
        ];
        nanoeye(&args, p)
    };
    // Pairs 0.2 nm apart keep their own keys (whole nm merged them into one).
    let out = succeeded(select("sw"));
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let keys: Vec<&String> = v["pairs"].as_object().unwrap().keys().collect();
    assert_eq!(keys, ["700.2x500", "700.4x500", "700x500"], "{v}");
    // One diameter: figures drawn around it, not "no finite points to plot".
    sweep("one", "700:700:10", "0.5:0.5:0.1");
    let out = succeeded(select("one"));
    assert!(!String::from_utf8_lossy(&out.stdout).contains("null"));
    // Zero height alone (the bare substrate, legal in a sweep): figures without a marked
    // pillar, not an error about an internal `mark` (a helper's audit).
    sweep("zero", "0:0:10", "0.3:0.5:0.1");
    let out = succeeded(select("zero"));
    assert!(!String::from_utf8_lossy(&out.stdout).contains("null"));
    // A blueprint from the sweep reads its cells: a solver flag that contradicts the sweep
    // is refused naming it (ignored before, the output the sweep's; a helper's audit), one
    // that agrees with it is taken, and so is none.
    std::fs::write(p.join("ph.npy"), npy_f64(2, 2, &[0.0, 1.0, 2.0, 3.0])).unwrap();
    let bp = |extra: &[&str]| {
        let mut a = vec![
            "metalib",
            "blueprint",
            "--sweep",
            "sw",
            "--phase",
            "ph.npy",
            "--height-nm",
            "700",
            "--pitch-nm",
            "500",
            "--square-aperture",
            "--out",
            "bp",
        ];
        a.extend(extra);
        nanoeye(&a, p)
    };
    for (extra, flag) in [
        (&["--harmonics", "5"][..], "--harmonics"),
        (&["--rule", "laurent"], "--rule"),
        (&["--material", "green-2008-csi"], "--material"),
        (&["--n-pillar", "2"], "--n-pillar"),
        (&["--n-substrate", "3"], "--n-substrate"),
    ] {
        let out = bp(extra);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{extra:?} was ignored");
        assert!(
            err.contains(flag) && err.contains("solves nothing"),
            "{err}"
        );
        assert!(!p.join("bp").exists());
    }
    succeeded(bp(&["--harmonics", "1"]));
    succeeded(bp(&[]));

    let copy = |name: &str| {
        let to = p.join(name);
        std::fs::create_dir(&to).unwrap();
        for f in [
            "manifest.json",
            "phase.npy",
            "transmittance.npy",
            "t_re.npy",
            "t_im.npy",
        ] {
            std::fs::copy(p.join("sw").join(f), to.join(f)).unwrap();
        }
        to
    };
    let manifest = std::fs::read_to_string(p.join("sw/manifest.json")).unwrap();
    let edited = |f: &dyn Fn(&mut serde_json::Value)| {
        let mut m: serde_json::Value = serde_json::from_str(&manifest).unwrap();
        f(&mut m);
        m.to_string()
    };
    // A 27-byte phase.npy whose version-2 header claims 4 GiB (npyz allocated it: abort).
    let huge = copy("huge");
    let mut npy = b"\x93NUMPY\x02\x00".to_vec();
    npy.extend(0xFFFF_FFF0u32.to_le_bytes());
    npy.extend(b"{'descr': '<f8'");
    std::fs::write(huge.join("phase.npy"), npy).unwrap();
    let err = String::from_utf8_lossy(&select("huge").stderr).to_string();
    assert!(err.contains("--sweep") && err.contains("header"), "{err}");
    for (name, m, what) in [
        // Heights of 1e300 m hung the plotting of their axis; 1 m was reported viable.
        (
            "tall",
            edited(&|m| {
                m["config"]["heights_m"] =
                    serde_json::json!({"start": 1e300, "stop": 1e300, "step": 1e-7})
            }),
            "heights",
        ),
        (
            "wide",
            edited(&|m| {
                m["config"]["fractions"] = serde_json::json!({"start": 5, "stop": 50, "step": 5})
            }),
            "fractions",
        ),
        (
            "future",
            edited(&|m| m["version"] = serde_json::json!(999)),
            "version",
        ),
    ] {
        std::fs::write(copy(name).join("manifest.json"), m).unwrap();
        let out = select(name);
        let err = String::from_utf8_lossy(&out.stderr).to_string();
        assert!(!out.status.success(), "{name}: {err}");
        assert!(
            err.contains("--sweep") && err.contains(what),
            "{name}: {err}"
        );
        assert!(!p.join(format!("{name}_fig")).exists(), "{name}");
    }
    // The manifest a FIFO: refused, not read forever.
    let fifo = copy("fifo");
    std::fs::remove_file(fifo.join("manifest.json")).unwrap();
    common::mkfifo(&fifo.join("manifest.json"));
    refused(
        &["metalib", "select", "--sweep", "fifo", "--json"],
        "regular file",
        p,
    );

    // material-study: an index without a 2π window leaves its keys out (they were null), and
    // heights × diameters beyond what one index's curves may hold are refused by flag.
    let study = [
        "metalib",
        "material-study",
        "--harmonics",
        "1",
        "--fractions",
        "0.1:0.9:0.1",
        "--n-values",
        "1.5:1.5:1",
        "--k-values",
        "0",
        "--materials",
        "none",
        "--heights-nm",
        "700:700:10",
        "--json",
    ];
    let out = succeeded(nanoeye(&study, p));
    let text = String::from_utf8_lossy(&out.stdout).to_string();
    assert!(
        !text.contains("null") && !text.contains("min_transmittance_2pi"),
        "{text}"
    );
    let mut big = study;
    big[13] = "0:99999:1";
    big[5] = "0.1:0.9:0.0005";
    refused(&big, "--heights-nm", p);
    let mut tall = study.to_vec();
    tall.splice(12..14, ["--heights-nm=-100:700:100"]);
    let err = refused(&tall, "--heights-nm", p);
    assert!(err.contains("-100"), "{err}");
}

/// A helper's audit (fifty-third session): datagen's outputs that replaced its inputs, state
/// keys not named, and a resume that trusted frame records and files it had not written.
#[test]
fn datagen_refuses_its_inputs_as_output_and_renders_a_tampered_frame_again() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    let rig = succeeded(nanoeye(&["rig", "show", "--json"], p)).stdout;
    std::fs::write(p.join("rig_in.json"), &rig).unwrap();
    let states = [
        "datagen",
        "states",
        "--set",
        "ambiguity",
        "--n",
        "1",
        "--rig",
        "rig_in.json",
        "--out",
        "rig_in.json",
    ];
    refused(&states, "--out", p);
    assert_eq!(std::fs::read(p.join("rig_in.json")).unwrap(), rig);
    let state = r#"{"azimuth_rad": 0.1, "elevation_rad": 0, "torsion_rad": 0, "slip_m": [0, 0, 0], "cam_rot_rad": [0, 0, 0], "lid_closure": 0}"#;
    std::fs::write(p.join("st.glb"), state).unwrap();
    let export = ["datagen", "export", "--state", "st.glb", "--out", "st.glb"];
    refused(&export, "--out", p);
    assert_eq!(std::fs::read_to_string(p.join("st.glb")).unwrap(), state);
    std::fs::write(p.join("rig.glb"), &rig).unwrap();
    refused(
        &["datagen", "export", "--rig", "rig.glb", "--out", "rig.glb"],
        "--out",
        p,
    );
    let null = state.replace("\"azimuth_rad\": 0.1", "\"azimuth_rad\": null");
    refused(
        &["datagen", "export", "--state", &null, "--out", "o.glb"],
        "azimuth_rad",
        p,
    );
    let twice = state.replace(
        "\"lid_closure\": 0",
        "\"lid_closure\": 0, \"lid_closure\": 1",
    );
    refused(
        &["datagen", "export", "--state", &twice, "--out", "o.glb"],
        "duplicate",
        p,
    );
    assert!(!p.join("o.glb").exists());
    // The same inputs through a directory that does not exist yet (a helper's audit: the check
    // did not see `new/../rig_in.json` as rig_in.json, and the command made `new` and replaced
    // the rig, exit 0); and outputs that are a directory or a FIFO, named as --out.
    let mut through = states;
    through[9] = "new/../rig_in.json";
    refused(&through, "is --rig", p);
    assert_eq!(std::fs::read(p.join("rig_in.json")).unwrap(), rig);
    refused(
        &[
            "datagen",
            "export",
            "--state",
            "st.glb",
            "--out",
            "x/../st.glb",
        ],
        "is --state",
        p,
    );
    assert_eq!(std::fs::read_to_string(p.join("st.glb")).unwrap(), state);
    refused(
        &[
            "datagen",
            "export",
            "--rig",
            "rig.glb",
            "--out",
            "y/./../rig.glb",
        ],
        "is --rig",
        p,
    );
    assert_eq!(std::fs::read(p.join("rig.glb")).unwrap(), rig);
    std::fs::create_dir(p.join("adir")).unwrap();
    common::mkfifo(&p.join("fifo.jsonl"));
    for out in ["adir", "fifo.jsonl"] {
        let mut a = states;
        a[9] = out;
        refused(&a, "--out: ", p);
    }
    std::fs::create_dir(p.join("d.glb")).unwrap();
    refused(&["datagen", "export", "--out", "d.glb"], "--out: ", p);

    // A record copied over another frame's, and a frame's radiance deleted: both frames are
    // rendered again on the rerun, and frames.jsonl names each of the three frames once.
    succeeded(nanoeye(&tiny_dataset("ds"), p));
    let f = p.join("ds/frames");
    let radiance = std::fs::read(f.join("000001_radiance.npy")).unwrap();
    std::fs::copy(f.join("000000.json"), f.join("000001.json")).unwrap();
    std::fs::remove_file(f.join("000000_radiance.npy")).unwrap();
    let out = succeeded(nanoeye(&tiny_dataset("ds"), p));
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["frames_written"], 2, "{v}");
    assert_eq!(
        std::fs::read(f.join("000001_radiance.npy")).unwrap(),
        radiance
    );
    let frames: Vec<u64> = std::fs::read_to_string(p.join("ds/frames.jsonl"))
        .unwrap()
        .lines()
        .map(|l| {
            serde_json::from_str::<serde_json::Value>(l).unwrap()["frame"]
                .as_u64()
                .unwrap()
        })
        .collect();
    assert_eq!(frames, [0, 1, 2]);
    // A manifest that is not text is refused, not overwritten as absent.
    std::fs::write(p.join("ds/dataset.json"), b"\xff\xfe").unwrap();
    refused(&tiny_dataset("ds"), "dataset manifest", p);
    assert_eq!(
        std::fs::read(p.join("ds/dataset.json")).unwrap(),
        b"\xff\xfe"
    );
}

/// A command's --out that is a rendered dataset (its --dataset, say) is refused before any
/// work: `search train`, `fisher init` and `run` wrote into the data they read (a helper's
/// audit, fifty-third session), and it changes nothing there.
#[test]
fn an_out_that_is_a_dataset_is_refused() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    succeeded(nanoeye(&tiny_dataset("ds"), p));
    let before = common::tree(&p.join("ds"));
    let train: Vec<&str> = [
        &["search", "train"][..],
        &common::TINY_CHAIN,
        &common::TINY_TRAIN,
    ]
    .concat()
    .into_iter()
    .chain(["--out", "ds"])
    .collect();
    // Nor a directory inside it (`--out ds/frames` wrote a run into the dataset; a helper's
    // audit, fifty-fifth session).
    let mut inside = train.clone();
    *inside.last_mut().unwrap() = "ds/frames/run";
    for args in [
        train,
        inside,
        vec!["fisher", "init", "--iterations", "1", "--out", "ds"],
        vec!["fisher", "init", "--iterations", "1", "--out", "ds/f"],
        vec!["run", "--out", "ds"],
    ] {
        let err = refused(&args, "--out", p);
        assert!(err.contains("dataset directory"), "{args:?}: {err}");
    }
    assert!(common::tree(&p.join("ds")) == before);
}

/// A helper's audit of the chain's commands (fifty-third session): a crafted dataset (a slab
/// index beyond its count panicked; a FIFO blocked; a NaN mask reached sim's output, exit 0)
/// and outputs that replaced their inputs.
#[test]
fn crafted_datasets_and_outputs_over_inputs_are_refused_by_the_chain_commands() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    succeeded(nanoeye(&tiny_dataset("ds"), p));
    let copy = |name: &str| {
        let to = p.join(name);
        for sub in ["", "frames"] {
            std::fs::create_dir_all(to.join(sub)).unwrap();
            for e in std::fs::read_dir(p.join("ds").join(sub)).unwrap().flatten() {
                if e.path().is_file() {
                    std::fs::copy(e.path(), to.join(sub).join(e.file_name())).unwrap();
                }
            }
        }
        to
    };
    let chain = |ds: &str| -> Vec<String> {
        common::TINY_CHAIN
            .iter()
            .map(|s| {
                if *s == "ds" {
                    ds.to_string()
                } else {
                    s.to_string()
                }
            })
            .collect()
    };
    let sim = |ds: &str, out: &str| -> Vec<String> {
        let mut v = vec!["sim".to_string()];
        v.extend(chain(ds));
        v.extend(["--out".into(), out.into()]);
        v
    };
    let refused_s = |args: &[String], what: &str| {
        let a: Vec<&str> = args.iter().map(String::as_str).collect();
        refused(&a, what, p)
    };
    // A slab index of 99 of 8.
    let bad = copy("idx");
    let lines = std::fs::read_to_string(bad.join("frames.jsonl")).unwrap();
    let mut recs: Vec<serde_json::Value> = lines
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    let k = recs[0]["layers"].as_array().unwrap().len() - 1;
    recs[0]["layers"][k]["index"] = serde_json::json!(99);
    let text: String = recs.iter().map(|r| format!("{r}\n")).collect();
    std::fs::write(bad.join("frames.jsonl"), text).unwrap();
    let err = refused_s(&sim("idx", "o1"), "layers[].index");
    assert!(!err.contains("panicked"), "{err}");
    assert!(!p.join("o1").exists());
    // frames.jsonl a FIFO.
    let fifo = copy("fifo");
    std::fs::remove_file(fifo.join("frames.jsonl")).unwrap();
    common::mkfifo(&fifo.join("frames.jsonl"));
    refused_s(&sim("fifo", "o2"), "regular file");
    // A NaN in a pupil mask.
    let nan = copy("nan");
    let mp = nan.join("frames/000000_masks.npy");
    let mut b = std::fs::read(&mp).unwrap();
    let at = b.len() - 40;
    b[at..at + 4].copy_from_slice(&f32::NAN.to_le_bytes());
    std::fs::write(&mp, b).unwrap();
    refused_s(&sim("nan", "o3"), "coverage");
    // Outputs over inputs: sim into its dataset, --grad-out at --phase or inside the dataset.
    let before = common::tree(&p.join("ds"));
    refused_s(&sim("ds", "ds"), "dataset directory");
    let zeros = {
        let n = 100usize;
        let head = format!("{{'descr': '<f8', 'fortran_order': False, 'shape': ({n}, {n}), }}");
        let head = format!("{head:<117}\n");
        let mut v = b"\x93NUMPY\x01\x00".to_vec();
        v.extend((head.len() as u16).to_le_bytes());
        v.extend(head.as_bytes());
        v.extend(vec![0u8; 8 * n * n]);
        v
    };
    std::fs::write(p.join("p.npy"), &zeros).unwrap();
    let mut loss: Vec<String> = vec!["search".into(), "loss".into()];
    loss.extend(chain("ds"));
    loss.extend(["--phase".into(), "p.npy".into(), "--grad-out".into()]);
    let mut at_phase = loss.clone();
    at_phase.push("p.npy".into());
    refused_s(&at_phase, "--grad-out");
    assert_eq!(std::fs::read(p.join("p.npy")).unwrap(), zeros);
    let mut inside = loss.clone();
    inside.push("ds/frames/000000_layers.npy".into());
    refused_s(&inside, "inside --dataset");
    assert!(common::tree(&p.join("ds")) == before);
    // search pareto --plot at an input (it replaced a run's checkpoint.bin, exit 0).
    let pareto = [
        "search",
        "pareto",
        "--runs",
        "nope",
        "--dataset",
        "ds",
        "--plot",
    ];
    let err = refused(&[&pareto[..], &["ds/dataset.json"]].concat(), "--plot", p);
    assert!(err.contains("lies inside --dataset"), "{err}");
    std::fs::write(p.join("notes.txt"), b"mine").unwrap();
    let err = refused(&[&pareto[..], &["notes.txt"]].concat(), "--plot", p);
    assert!(err.contains("not an SVG"), "{err}");
    assert_eq!(std::fs::read(p.join("notes.txt")).unwrap(), b"mine");
    assert!(common::tree(&p.join("ds")) == before);
    // fisher compare: depths beyond any scene (1e300 mm gave every fisher_z 0, exit 0).
    let args = [
        "fisher",
        "compare",
        "--depths-mm",
        "1e300:2e300:1e300",
        "--pitch-um",
        "12",
        "--montage",
        "m.png",
    ];
    refused(&args, "--depths-mm", p);
}

/// A mask downscaled by one factor in x and y is read as docs/formats.md says (it was refused
/// as "not the camera image's size"): the same disc at 320×200, 160×100 and 80×50 gives the
/// same pupil centre in camera pixels; a mask with unequal factors or larger than the image is
/// refused naming both sizes.
#[test]
fn gaze_solve_reads_a_downscaled_mask_and_refuses_other_sizes() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    // A disc centred at camera pixel (150, 90), radius 16 px, drawn at 1/k scale.
    let disc = |k: u32, w: u32, h: u32| {
        image::GrayImage::from_fn(w, h, |x, y| {
            let (u, v) = ((x as f64 + 0.5) * k as f64, (y as f64 + 0.5) * k as f64);
            let inside = (u - 150.0).powi(2) + (v - 90.0).powi(2) < 16.0f64.powi(2);
            image::Luma([if inside { 255 } else { 0 }])
        })
    };
    let mut q = String::new();
    for (k, w, h) in [(1, 320, 200), (2, 160, 100), (4, 80, 50)] {
        disc(k, w, h).save(p.join(format!("m{k}.png"))).unwrap();
        q += &format!("{{\"mask_png\":\"m{k}.png\"}}\n");
    }
    std::fs::write(p.join("q.jsonl"), &q).unwrap();
    let out = succeeded(nanoeye(&["gaze", "solve", "--input", "q.jsonl"], p));
    let rows: Vec<serde_json::Value> = String::from_utf8(out.stdout)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(rows.len(), 3);
    for r in &rows {
        let px: Vec<f64> = serde_json::from_value(r["pupil_px"].clone()).unwrap();
        // The disc's pixel centres are symmetric about (150, 90) at every scale.
        assert!(
            (px[0] - 150.0).abs() < 1e-9 && (px[1] - 90.0).abs() < 1e-9,
            "{r}"
        );
    }
    for (w, h) in [(160, 200), (640, 400), (321, 200)] {
        image::GrayImage::new(w, h).save(p.join("bad.png")).unwrap();
        std::fs::write(p.join("b.jsonl"), "{\"mask_png\":\"bad.png\"}\n").unwrap();
        let out = nanoeye(&["gaze", "solve", "--input", "b.jsonl"], p);
        // One query line, no valid one: the line's error goes to stderr, exit non-zero.
        let text = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{w}×{h}: {text}");
        assert!(
            text.contains(&format!("mask is {w}×{h} px")) && text.contains("320×200"),
            "{w}×{h}: {text}"
        );
    }
}

/// `datagen listing` names the angle at fault (both flags were named whichever was wrong).
#[test]
fn datagen_listing_names_the_angle_at_fault() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    for (az, el, flag, other) in [
        ("100", "0", "--azimuth-deg", "--elevation-deg"),
        ("10", "-90", "--elevation-deg", "--azimuth-deg"),
        ("NaN", "0", "--azimuth-deg", "--elevation-deg"),
    ] {
        let args = [
            "datagen",
            "listing",
            "--azimuth-deg",
            az,
            "--elevation-deg",
            el,
        ];
        let err = refused(&args, flag, p);
        assert!(!err.contains(other), "{err}");
    }
}

/// A struct given as an array of its fields is refused naming where (serde reads a struct
/// from an array by position: a rig, a gaze query, an Arch and a state written as arrays were
/// taken; a helper's audit), and the object forms still work.
#[test]
fn arrays_in_place_of_objects_are_refused_naming_where() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    let shown = succeeded(nanoeye(&["rig", "show", "--json"], p)).stdout;
    let rig: serde_json::Value = serde_json::from_slice(&shown).unwrap();
    let fields = |v: &serde_json::Value| -> serde_json::Value {
        v.as_object().unwrap().values().cloned().collect()
    };
    let mut nested = rig.clone();
    nested["camera"] = fields(&rig["camera"]);
    let write = |name: &str, v: &serde_json::Value| {
        std::fs::write(p.join(name), v.to_string()).unwrap();
    };
    write("rig.json", &rig);
    write("flat.json", &fields(&rig));
    write("nested.json", &nested);
    write("cfg.json", &serde_json::json!({ "rig": nested }));
    std::fs::write(p.join("q.jsonl"), "[[160,100],null,[0,0,0]]\n").unwrap();
    std::fs::write(p.join("a.json"), "[[3],[3],[2],0.5]").unwrap();
    std::fs::write(p.join("s.json"), "[0,0,0,[0,0,0],[0,0,0]]").unwrap();
    let set = format!("rig={nested}");
    for (args, flag, place) in [
        (vec!["rig", "show", "--rig", "flat.json"], "--rig", ""),
        (
            vec!["rig", "show", "--rig", "nested.json"],
            "--rig",
            "camera: ",
        ),
        (
            vec!["run", "--print-config", "--set", &set],
            "--set rig",
            "camera: ",
        ),
        (
            vec!["run", "--print-config", "--config", "cfg.json"],
            "--config",
            "rig/camera: ",
        ),
        (vec!["gaze", "solve", "--input", "q.jsonl"], "--input", ""),
        (vec!["nets", "macs", "--arch", "file:a.json"], "--arch", ""),
        (
            vec!["datagen", "export", "--state", "s.json", "--out", "s.glb"],
            "--state",
            "",
        ),
    ] {
        let err = refused(&args, flag, p);
        let want = format!("{place}a JSON object {{\"key\": value, …}} is expected");
        assert!(
            err.contains(&want) && err.contains("not an array"),
            "{args:?}: {err}"
        );
    }
    assert!(!p.join("s.glb").exists());
    succeeded(nanoeye(&["rig", "show", "--rig", "rig.json"], p));
    write("cfg.json", &serde_json::json!({ "rig": rig }));
    succeeded(nanoeye(
        &["run", "--print-config", "--config", "cfg.json"],
        p,
    ));
}

/// A rig's or a state's value of the wrong type or length is named by its path (serde's error
/// gave a line and column only, and called an array one element too long "trailing
/// characters"; a helper's audit).
#[test]
fn a_bad_value_in_a_rig_or_state_is_named_by_its_path() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    let shown = succeeded(nanoeye(&["rig", "show", "--json"], p)).stdout;
    let rig: serde_json::Value = serde_json::from_slice(&shown).unwrap();
    type Edit = fn(&mut serde_json::Value);
    let edits: [(Edit, &str); 3] = [
        (
            |r| r["kappa_rad"] = serde_json::json!([0, 0, 0]),
            "rig field `kappa_rad`: invalid length 3",
        ),
        (
            |r| r["camera"]["cx_px"] = serde_json::Value::Null,
            "rig field `camera.cx_px`: invalid type: null",
        ),
        (
            |r| r["cornea"]["index"] = "a".into(),
            "rig field `cornea.index`: invalid type: string",
        ),
    ];
    for (edit, want) in edits {
        let mut r = rig.clone();
        edit(&mut r);
        std::fs::write(p.join("e.json"), r.to_string()).unwrap();
        let err = refused(&["rig", "show", "--rig", "e.json"], want, p);
        assert!(!err.contains("line 1"), "{err}");
        let set = format!("rig={r}");
        refused(&["run", "--print-config", "--set", &set], want, p);
    }
    std::fs::write(
        p.join("s.json"),
        r#"{"azimuth_rad":0,"elevation_rad":0,"torsion_rad":0,"slip_m":[0,0,0,0]}"#,
    )
    .unwrap();
    let args = ["datagen", "export", "--state", "s.json", "--out", "s.glb"];
    refused(&args, "--state: key 'slip_m': invalid length 4", p);
}

/// `nanoeye args` in `cwd` with the free disk space capped at `bytes`.
fn with_disk(args: &[&str], bytes: &str, cwd: &Path) -> std::process::Output {
    with_env("NANOEYE_DISK_BYTES", args, bytes, cwd)
}

/// The number `text` prints between `before` and `after` (a panic naming the text if none).
fn number_between(text: &str, before: &str, after: &str) -> f64 {
    text.split(before)
        .nth(1)
        .and_then(|r| r.split(after).next())
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("no number between {before:?} and {after:?} in: {text}"))
}

/// The main job writes about 4.4 GB at its defaults (session 56's CI failed on a full disk):
/// a disk that cannot hold its rendered sets' arrays and its models is refused before
/// anything is written, and what --out already holds counts as written (a resume reuses it).
#[test]
fn run_refuses_a_disk_its_rendered_sets_cannot_fit() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    // The defaults' sets: (240 + 96 + 343 + 60) frames × 4 planes × 320 × 200 × 4 bytes.
    let sets = 739.0 * 4.0 * 320.0 * 200.0 * 4.0 / 1e9;
    let out = with_disk(&["run", "--out", "r"], "1e6", p);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{err}");
    assert!(
        err.contains(&format!(
            "rendered sets (at least {sets:.2} GB) and models ("
        )),
        "{err}"
    );
    // The models: two trainer checkpoints and three tracker networks per lens, 0.80 GB of
    // runs/ on disk after the sixtieth session's default job (the estimate leaves out the
    // small files).
    let models = number_between(&err, "models (", " GB)");
    assert!((0.6..=0.8).contains(&models), "{err}");
    let least = number_between(&err, "writes at least ", " GB under r (0.00 GB of it there");
    assert!((least - (sets + models)).abs() <= 0.011, "{err}");
    assert!(err.contains("0.00 GB are free there"), "{err}");
    assert!(err.contains("protocol_subjects"), "{err}");
    assert!(!p.join("r").exists(), "a refused run wrote something");
    // `least` − 0.06 GB already under --out (a sparse file: its length counts, not its
    // blocks) and 0.02 GB free: still short. At `least` it fits, and the next check speaks:
    // the file is named `runs`, which --out may not hold without a configuration.
    std::fs::create_dir_all(p.join("r2")).unwrap();
    let pad = std::fs::File::create(p.join("r2/runs")).unwrap();
    pad.set_len(((least - 0.06) * 1e9) as u64).unwrap();
    let out = with_disk(&["run", "--out", "r2"], "2e7", p);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{err}");
    assert!(
        err.contains(&format!("({:.2} GB of it there already)", least - 0.06)),
        "{err}"
    );
    pad.set_len((least * 1e9) as u64).unwrap();
    let out = with_disk(&["run", "--out", "r2"], "2e7", p);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{err}");
    assert!(!err.contains("GB are free"), "{err}");
    // With all eight depth layers of every frame kept they would not: a warning.
    let most = 739.0 * 20.0 * 320.0 * 200.0 * 4.0 / 1e9 + (least - sets);
    let said = number_between(&err, "may write up to ", " GB under r2");
    assert!((said - most).abs() <= 0.011, "{err}");
    assert!(
        err.contains("holds a run's `runs` but no config.json"),
        "{err}"
    );
    assert!(
        !p.join("r2/config.json").exists(),
        "a refused run wrote its configuration"
    );
    // A resume is checked after its configuration: another configuration is named as such,
    // and the same one is refused for the disk it still needs.
    let printed = nanoeye(&["run", "--print-config", "--set", "seed=5"], p);
    assert!(printed.status.success());
    std::fs::create_dir_all(p.join("r4")).unwrap();
    std::fs::write(p.join("r4/config.json"), &printed.stdout).unwrap();
    let out = with_disk(&["run", "--out", "r4"], "1e6", p);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{err}");
    assert!(
        err.contains("another configuration") && err.contains("seed"),
        "{err}"
    );
    let out = with_disk(&["run", "--out", "r4", "--set", "seed=5"], "1e6", p);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{err}");
    assert!(err.contains("0.00 GB are free there"), "{err}");
    // `datagen render` too: 200 ambiguity items are 600 frames of 4 planes at 80 × 50.
    let out = with_disk(&tiny_dataset_of("ds", "200"), "1e6", p);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{err}");
    assert!(
        err.contains("datagen render: writes at least 0.04 GB under ds"),
        "{err}"
    );
    assert!(!p.join("ds").exists(), "a refused render wrote something");
    // A cap that is no number is named.
    let out = with_disk(&["run", "--out", "r3"], "lots", p);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("NANOEYE_DISK_BYTES"));
}

//! `nanoeye run` end to end on a tiny configuration: every stage runs, the numbers come from
//! the chain (the learned and baseline lenses give different protocol errors), the report's
//! images exist, and a second call reports the finished run without redoing it.

mod common;

use std::path::PathBuf;
use std::process::Command;

/// The smallest configuration that runs every stage: the protocol on a 3 × 3 grid of targets
/// (7 × 9 frames; D.4's 7 × 7 grid would be 343, most of a tiny job's time).
const TINY: &str = r#"{"width_px": 80, "height_px": 50, "spp": 1, "train_items": 6, "val_items": 2,
    "protocol_subjects": 1, "protocol_grid": 3, "train_steps": 2, "batch": 3, "random_subnets": 0,
    "pitch_init_um": 60.0, "pitch_range_um": [48.0, 120.0], "rea_cycles": 1,
    "rea_population": 2, "rea_tournament": 2, "rea_epochs": 1.0, "final_steps": 2,
    "aperture_step_um": 10.0, "exposure_ms": 0.0004, "head_widths": [32, 16],
    "sequence_frames": 5, "train_blink_fraction": 0.5}"#;

/// `nanoeye run --json` on [`TINY`] with 3 Fisher iterations and the keys `extra` (`"k": v, `
/// each) in `dir/NAME/`; asserts it succeeds and returns its result and directory.
fn tiny_job(dir: &std::path::Path, name: &str, extra: &str) -> (serde_json::Value, PathBuf) {
    let cfg = dir.join(format!("{name}.json"));
    let text = TINY.replacen('{', &format!("{{\"fisher_iterations\": 3, {extra}"), 1);
    std::fs::write(&cfg, text).unwrap();
    let out = dir.join(name);
    let o = run_json(&cfg, &out);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    (serde_json::from_slice(&o.stdout).unwrap(), out)
}

/// `nanoeye run --json --config CFG --out OUT`.
fn run_json(cfg: &std::path::Path, out: &std::path::Path) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_nanoeye"))
        .args(["run", "--json", "--config"])
        .arg(cfg)
        .arg("--out")
        .arg(out)
        .output()
        .unwrap()
}

/// A training driven to divergence (every learning rate at the accepted maximum) stops at
/// the protocol stage naming the learning rates, exit non-zero, and writes no result with
/// nulls in it (an audit: exit 0, `slip_rmse_mm` null in result.json, protocol.jsonl and
/// demo.jsonl tracking slippage [null, null, null]).
#[test]
fn a_diverged_training_is_an_error_not_a_result_with_nulls() {
    let d = tempfile::tempdir().unwrap();
    let cfg = d.path().join("div.json");
    let text = TINY.replacen(
        '{',
        "{\"fisher_iterations\": 0, \"lr_net\": 1000, \"lr_pitch_um\": 1000, \
         \"lr_phase_rad\": 1000, \"slip_head_refit\": false, \"rea_head_refit\": false, ",
        1,
    );
    std::fs::write(&cfg, text).unwrap();
    let out = d.path().join("run");
    let o = run_json(&cfg, &out);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "{err}");
    assert!(!err.contains("panicked"), "{err}");
    assert!(err.contains("finite") && err.contains("lr_net"), "{err}");
    assert!(o.stdout.is_empty());
    for f in ["result.json", "report.html", "demo.jsonl"] {
        assert!(!out.join(f).exists(), "{f} written");
    }
    for lens in ["learned", "hyperbolic", "double_helix"] {
        let p = out.join(format!("runs/{lens}/protocol.jsonl"));
        if let Ok(t) = std::fs::read_to_string(&p) {
            assert!(!t.contains("null,null,null"), "{lens}: {t}");
        }
    }
}

#[test]
fn the_main_job_runs_end_to_end_on_a_tiny_config() {
    let d = tempfile::tempdir().unwrap();
    let cfg = d.path().join("tiny.json");
    std::fs::write(&cfg, TINY).unwrap();
    let out = d.path().join("run");
    let run = || {
        Command::new(env!("CARGO_BIN_EXE_nanoeye"))
            .args(["run", "--json", "--config"])
            .arg(&cfg)
            .arg("--out")
            .arg(&out)
            .output()
            .unwrap()
    };
    let o = run();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    let r: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    for k in ["render", "fisher", "train", "rea", "finetune", "protocol"] {
        assert!(r["stages"][k].as_f64().is_some(), "stage {k} missing: {r}");
    }
    // Blinks reach the training frames only: lid closures in 0.2–1 there, open lids elsewhere.
    let closures = |set: &str| -> Vec<f64> {
        let text =
            std::fs::read_to_string(out.join("data").join(set).join("frames.jsonl")).unwrap();
        text.lines()
            .map(|l| {
                let f: serde_json::Value = serde_json::from_str(l).unwrap();
                f["state"]["lid_closure"].as_f64().unwrap_or(0.0)
            })
            .collect()
    };
    let train = closures("train");
    assert!(train.iter().any(|&c| c >= 0.2), "{train:?}");
    assert!(
        train.iter().all(|&c| c == 0.0 || (0.2..=1.0).contains(&c)),
        "{train:?}"
    );
    for set in ["val", "protocol", "sequence"] {
        assert!(closures(set).iter().all(|&c| c == 0.0), "{set}");
    }
    let p = &r["protocol"];
    for lens in [
        "learned",
        "hyperbolic",
        "double_helix",
        "geometric_no_slip",
        "solver_true_mask_true_slip",
        "sphere_solver_true_mask_true_slip",
        "solver_true_mask_eye_equivalent_slip",
        "network_mask_true_slip",
        "true_mask_network_slip",
    ] {
        let s = &p[lens];
        assert_eq!(s["frames"], 63, "{lens}");
        assert!(s["fallbacks"].as_u64().unwrap() <= 63, "{lens}");
        let per_slip = s["per_slip"].as_array().unwrap();
        assert_eq!(per_slip.len(), 7);
        for (k, e) in per_slip.iter().enumerate() {
            assert_eq!(
                (&e["slip_state"], &e["frames"]),
                (&k.into(), &9.into()),
                "{lens}"
            );
        }
        let m = s["mean_deg"].as_f64().unwrap();
        assert!(m.is_finite() && (0.0..=90.0).contains(&m), "{lens}: {m}");
    }
    for lens in ["learned", "hyperbolic", "double_helix"] {
        let (dice, slip) = (
            p[lens]["dice"].as_f64().unwrap(),
            p[lens]["slip_rmse_mm"].as_f64().unwrap(),
        );
        assert!((0.0..=1.0).contains(&dice), "{lens}: dice {dice}");
        assert!(slip.is_finite() && slip >= 0.0, "{lens}: slip {slip}");
        // Frame by frame: the recorded slippage errors give back the summary's RMSE.
        let rows: Vec<serde_json::Value> =
            std::fs::read_to_string(out.join(format!("runs/{lens}/protocol.jsonl")))
                .unwrap()
                .lines()
                .map(|l| serde_json::from_str(l).unwrap())
                .collect();
        assert_eq!(rows.len(), 63, "{lens}");
        for (k, r) in rows.iter().enumerate() {
            assert_eq!(r["slip_state"], k / 9, "{lens}: frame {k}");
        }
        let ms: f64 = rows
            .iter()
            .map(|r| {
                (0..3)
                    .map(|a| {
                        let d = r["tracked_slip_mm"][a].as_f64().unwrap()
                            - r["true_slip_mm"][a].as_f64().unwrap();
                        d * d
                    })
                    .sum::<f64>()
            })
            .sum::<f64>()
            / 63.0;
        assert!(
            (ms.sqrt() - slip).abs() < 1e-4 * (1.0 + slip),
            "{lens}: protocol.jsonl gives {} mm, the summary {slip} mm",
            ms.sqrt()
        );
        // The head's output layer solved on every training frame (search::headfit): its
        // leave-one-out error can only exceed its error on the frames it was fitted to.
        let fit = &p[lens]["slip_head_fit"];
        assert_eq!(
            fit["frames"].as_u64(),
            Some(train.len() as u64),
            "{lens}: {fit}"
        );
        for a in 0..3 {
            let f = fit["rmse_fit_mm"][a].as_f64().unwrap();
            let l = fit["loo_rmse_mm"][a].as_f64().unwrap();
            assert!(f.is_finite() && l.is_finite() && l >= f, "{lens}: {fit}");
        }
        // The deployed model: the selected subnet fine-tuned behind this lens.
        assert!(
            out.join(format!("runs/{lens}/selected.bin")).exists(),
            "{lens}"
        );
    }
    // The learned lens started from the Fisher initialization (A.2).
    assert!(out.join("runs/learned/fisher_phase.npy").exists());
    // Different lenses through the same chain give different errors.
    assert_ne!(p["learned"]["mean_deg"], p["double_helix"]["mean_deg"]);
    assert_ne!(p["hyperbolic"]["mean_deg"], p["double_helix"]["mean_deg"]);
    assert!(r["macs"].as_u64().unwrap() > 0);
    assert_eq!(r["demo_sequence"]["frames"], 5);
    let demo: Vec<serde_json::Value> = std::fs::read_to_string(out.join("demo.jsonl"))
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(demo.len(), 5);
    // Each frame carries the true and the estimated slippage; their RMSE is the summary's.
    let mut sq = 0.0;
    for d in &demo {
        for a in 0..3 {
            let t = d["true_slip_mm"][a].as_f64().unwrap();
            let e = d["tracked_slip_mm"][a].as_f64().unwrap();
            assert!(e.is_finite());
            assert!((t - d["slip_m"][a].as_f64().unwrap() * 1e3).abs() < 1e-9);
            sq += (e - t) * (e - t);
        }
    }
    let rmse = r["demo_sequence"]["slip_rmse_mm"].as_f64().unwrap();
    assert!(
        (rmse - (sq / 5.0).sqrt()).abs() < 1e-3 * (1.0 + rmse),
        "{rmse}"
    );
    let html = std::fs::read_to_string(out.join("report.html")).unwrap();
    assert!(html.contains("data:image/png;base64,") && html.contains("<svg"));
    assert!(html.contains("Slippage estimate"));
    assert!(html.contains("The slippage the calibration head read"));
    // The report states this run's own sizes (the test's config), not the default's.
    assert!(
        html.contains(
            "This run: 6 training frames (50 % of them in a blink or partial closure) rendered at 80×50, 2 sandwich steps"
        ),
        "scale paragraph"
    );
    assert_eq!(
        html.matches("<img").count(),
        10,
        "three phase maps and their difference, three PSF strips, three example strips"
    );
    for lens in ["learned", "hyperbolic", "double_helix"] {
        for f in ["psfs.png", "examples.png"] {
            let p = out.join(format!("runs/{lens}/{f}"));
            let img = image::open(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
            assert!(img.width() > 0 && img.height() > 0);
        }
    }
    assert_eq!(r["psf_depths_mm"].as_array().unwrap().len(), 8);
    // The tracker on the protocol frames imaged through the learned lens at the learned p̂.
    let bin = env!("CARGO_BIN_EXE_nanoeye");
    let pitch = r["pitch_um"].as_f64().unwrap().to_string();
    let sim = d.path().join("sim");
    let o = Command::new(bin)
        .args([
            "sim",
            "--frames",
            "0:3",
            "--exposure-ms",
            "0.0004",
            "--aperture-step-um",
            "10",
        ])
        .args(["--pitch-um", &pitch, "--dataset"])
        .arg(out.join("data/protocol"))
        .arg("--lens")
        .arg(format!(
            "file:{}",
            out.join("runs/learned/phase.npy").display()
        ))
        .arg("--out")
        .arg(&sim)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let frames = d.path().join("frames");
    std::fs::create_dir(&frames).unwrap();
    std::fs::copy(sim.join("sensor.npy"), frames.join("a.npy")).unwrap();
    std::fs::write(frames.join("b.npy"), b"not an npy file").unwrap();
    // `nanoeye track` on the learned run with `extra` flags, the frames in `dir`.
    let track = |extra: &[&str], dir: &std::path::Path| {
        Command::new(bin)
            .arg("track")
            .args(extra)
            .arg("--model")
            .arg(out.join("runs/learned"))
            .arg("--frames")
            .arg(dir)
            .output()
            .unwrap()
    };
    let o = track(&[], &frames);
    // The tracker goes on past a file that is not a frame, then names it and exits non-zero.
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("1 input frame(s)") && err.contains("b.npy"),
        "{err}"
    );
    let lines: Vec<serde_json::Value> = String::from_utf8_lossy(&o.stdout)
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.len(), 4, "3 frames and one error line");
    // The run's subnet, and the min and max subnets, carry BN statistics recalibrated for
    // them; any other subnet does not, and the tracker says so (it still tracks).
    assert!(!String::from_utf8_lossy(&o.stderr).contains("warning"));
    let arch_file = d.path().join("arch.json");
    std::fs::copy(out.join("runs/learned/tracker_arch.json"), &arch_file).unwrap();
    let file_subnet = format!("file:{}", arch_file.display());
    for subnet in ["min", "max", file_subnet.as_str()] {
        let o = track(&["--subnet", subnet], &sim);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let err = String::from_utf8_lossy(&o.stderr);
        let warned = err.contains(&format!("--subnet {subnet}")) && err.contains("recalibrated");
        assert_eq!(warned, subnet.starts_with("file:"), "{subnet}: {err}");
    }
    // Each frame gives a unit gaze vector, or (a barely trained network may find no pupil)
    // a per-frame error line; never a crash.
    for l in &lines[..3] {
        if let Some(e) = l["error"].as_str() {
            assert!(!e.is_empty());
            continue;
        }
        let g: Vec<f64> = serde_json::from_value(l["gaze"].clone()).unwrap();
        let n = g.iter().map(|v| v * v).sum::<f64>().sqrt();
        assert!((n - 1.0).abs() < 1e-9, "{l}");
        assert!(l["latency_us"].as_u64().is_some());
        // The slippage estimate is marked in or out of the 30 mm range by its length.
        let s: Vec<f64> = serde_json::from_value(l["slip_m"].clone()).unwrap();
        let len = s.iter().map(|v| v * v).sum::<f64>().sqrt();
        assert_eq!(l["slip_in_range"].as_bool(), Some(len <= 0.030), "{l}");
    }
    assert!(
        lines[3]["error"].as_str().unwrap().contains("b.npy"),
        "{}",
        lines[3]
    );
    // sim's own output directory tracks as its frames: the ground-truth mask.npy beside them
    // is not a frame.
    let o = track(&[], &sim);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let sources: Vec<String> = String::from_utf8_lossy(&o.stdout)
        .lines()
        .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap()["source"].to_string())
        .collect();
    assert_eq!(sources.len(), 3, "{sources:?}");
    assert!(
        sources.iter().all(|s| s.contains("sensor.npy")),
        "{sources:?}"
    );
    // Frames outside the ADC's range (here every value's sign flipped) are not this sensor's:
    // each gets an error line and the tracker exits non-zero.
    let neg = d.path().join("negative");
    std::fs::create_dir(&neg).unwrap();
    let mut b = std::fs::read(sim.join("sensor.npy")).unwrap();
    assert_eq!(&b[..8], b"\x93NUMPY\x01\x00", "an NPY 1.0 file");
    let start = 10 + u16::from_le_bytes([b[8], b[9]]) as usize;
    for v in b[start..].chunks_exact_mut(4) {
        v[3] ^= 0x80;
    }
    std::fs::write(neg.join("sensor.npy"), &b).unwrap();
    let o = track(&[], &neg);
    assert!(!o.status.success());
    let out_lines = String::from_utf8_lossy(&o.stdout);
    assert_eq!(out_lines.lines().count(), 3, "{out_lines}");
    assert!(
        out_lines
            .lines()
            .all(|l| l.contains("outside the sensor's range")),
        "{out_lines}"
    );
    // PNG frames: 8- and 16-bit grayscale go through (an upper-case extension too); colour is
    // refused rather than converted by luma, another size is refused from the header before
    // the image is decoded, and a FIFO is not opened.
    let meta: serde_json::Value =
        serde_json::from_slice(&std::fs::read(sim.join("sim.json")).unwrap()).unwrap();
    let (h, w) = (
        meta["height"].as_u64().unwrap() as u32,
        meta["width"].as_u64().unwrap() as u32,
    );
    let pngs = d.path().join("pngs");
    std::fs::create_dir(&pngs).unwrap();
    image::GrayImage::new(w, h)
        .save(pngs.join("a_gray8.png"))
        .unwrap();
    image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::new(w, h)
        .save_with_format(pngs.join("b_gray16.PNG"), image::ImageFormat::Png)
        .unwrap();
    image::RgbImage::new(w, h)
        .save(pngs.join("c_rgb.png"))
        .unwrap();
    image::GrayImage::new(4000, 4000)
        .save(pngs.join("d_big.png"))
        .unwrap();
    common::mkfifo(&pngs.join("e_fifo.png"));
    let o = track(&[], &pngs);
    assert!(!o.status.success());
    let lines: Vec<serde_json::Value> = String::from_utf8_lossy(&o.stdout)
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.len(), 5, "{lines:?}");
    // Tracked (a gaze, or the chain's own per-frame error, with a latency) ...
    for l in &lines[..2] {
        assert!(l["latency_us"].as_u64().is_some(), "{l}");
    }
    // ... or refused as input, without one.
    for (l, why) in lines[2..]
        .iter()
        .zip(["not colour", "sensor grid", "regular file"])
    {
        assert!(l["latency_us"].is_null(), "{l}");
        assert!(l["error"].as_str().unwrap().contains(why), "{why}: {l}");
    }
    // `--subnet best` without the run's tracker files takes the search's pick from
    // rea_state.json; one that cannot be read is an error naming it, not the min subnet.
    let bare = d.path().join("bare");
    std::fs::create_dir_all(&bare).unwrap();
    for f in ["selected.bin", "rig.json"] {
        std::fs::copy(out.join("runs/learned").join(f), bare.join(f)).unwrap();
    }
    std::fs::write(bare.join("rea_state.json"), "{\"evaluated\": [").unwrap();
    let o = Command::new(bin)
        .args(["track", "--subnet", "best", "--model"])
        .arg(&bare)
        .arg("--frames")
        .arg(&frames)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && err.contains("rea_state.json"),
        "{err}"
    );
    assert!(o.stdout.is_empty());
    // A bad stdin header gives an error line, not a crash.
    let mut child = Command::new(bin)
        .args(["track", "--stdin", "--model"])
        .arg(out.join("runs/learned"))
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    {
        use std::io::Write;
        let mut si = child.stdin.take().unwrap();
        si.write_all(b"JUNKJUNKJUNKJUNK").unwrap();
    }
    let o = child.wait_with_output().unwrap();
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stdout).contains("NEYE"));
    // No frame at all is refused, as `--frames` with none is (it exited 0 with no line).
    let o = Command::new(bin)
        .args(["track", "--stdin", "--model"])
        .arg(out.join("runs/learned"))
        .stdin(std::process::Stdio::null())
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && err.contains("--stdin: the input ended"),
        "{err}"
    );
    assert!(o.stdout.is_empty());

    // Finished: the second call reports the same result without redoing any stage.
    let again = run();
    assert!(again.status.success());
    let r2: serde_json::Value = serde_json::from_slice(&again.stdout).unwrap();
    assert_eq!(r2, r);
    // A finished run's result.json edited to hold a null (or not an object) is refused, not
    // printed with exit 0 (a helper's audit).
    let rp = out.join("result.json");
    let kept = std::fs::read(&rp).unwrap();
    let mut edited = r.clone();
    edited["v_deg"] = serde_json::Value::Null;
    for text in [edited.to_string(), "\"hello\"".into()] {
        std::fs::write(&rp, text).unwrap();
        let o = run();
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success() && err.contains("is corrupt"), "{err}");
        assert!(o.stdout.is_empty());
    }
    std::fs::write(&rp, kept).unwrap();
    // `--set` to the value the run has is the same configuration; to another value it is not.
    let with_set = |kv: &str| {
        Command::new(env!("CARGO_BIN_EXE_nanoeye"))
            .args(["run", "--json", "--set", kv, "--config"])
            .arg(&cfg)
            .arg("--out")
            .arg(&out)
            .output()
            .unwrap()
    };
    let same = with_set("seed=0");
    assert!(
        same.status.success(),
        "{}",
        String::from_utf8_lossy(&same.stderr)
    );
    assert_eq!(
        serde_json::from_slice::<serde_json::Value>(&same.stdout).unwrap(),
        r
    );
    let other = with_set("seed=1");
    assert!(!other.status.success());
    let err = String::from_utf8_lossy(&other.stderr);
    assert!(
        err.contains("another configuration") && err.contains("`seed`: 0 in the run, 1 now"),
        "{err}"
    );
    // Another configuration in the same directory is refused.
    // (a valid configuration, so it is the directory check that refuses it)
    let tiny = std::fs::read_to_string(&cfg).unwrap();
    std::fs::write(&cfg, tiny.replacen('{', r#"{"seed": 1, "#, 1)).unwrap();
    let o = run();
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("--out"));
    // So is a run begun by a version without one of today's keys (its default may differ).
    std::fs::write(&cfg, &tiny).unwrap();
    let cpath = out.join("config.json");
    let mut written: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&cpath).unwrap()).unwrap();
    written.as_object_mut().unwrap().remove("rea_fit_pitch");
    std::fs::write(&cpath, written.to_string()).unwrap();
    let o = run();
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("without `rea_fit_pitch`"));
}

/// `search train --lens init` starts from the same Fisher initialization as `nanoeye run`'s
/// learned lens (same chain, pitch and iterations give the same bytes), and a resume from
/// another initialization is refused.
#[test]
fn search_train_lens_init_is_the_main_jobs_fisher_phase() {
    let d = tempfile::tempdir().unwrap();
    let bin = env!("CARGO_BIN_EXE_nanoeye");
    let (_, out) = tiny_job(d.path(), "run", "");
    // `search train` on the run's training set with the run's chain and pitch.
    let train = |lens: &[&str], run: &std::path::Path| {
        Command::new(bin)
            .args(["search", "train", "--steps", "1", "--batch", "3"])
            .args(["--random-subnets", "0", "--pitch-um", "60"])
            .args(["--pitch-range-um", "48:120", "--aperture-step-um", "10"])
            .args(["--exposure-ms", "0.0004", "--lens"])
            .args(lens)
            .arg("--dataset")
            .arg(out.join("data/train"))
            .arg("--out")
            .arg(run)
            .output()
            .unwrap()
    };
    let run = d.path().join("train");
    let o = train(&["init", "--fisher-iterations", "3"], &run);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let mine = std::fs::read(run.join("fisher_phase.npy")).unwrap();
    let main_job = std::fs::read(out.join("runs/learned/fisher_phase.npy")).unwrap();
    assert!(mine == main_job, "the two Fisher initializations differ");
    // Not the hyperbolic phase it started from.
    let hyp = d.path().join("hyp");
    let o = train(&["hyperbolic", "--fixed-lens"], &hyp);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(std::fs::read(hyp.join("phase.npy")).unwrap() != mine);
    let o = train(&["init", "--fisher-iterations", "4"], &run);
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("--lens"), "{err}");
    // A run killed before its first checkpoint leaves fisher_phase.npy without one: a rerun
    // with other flags computes its own (an audit: it started from the killed run's phase).
    let killed = d.path().join("killed");
    std::fs::create_dir_all(&killed).unwrap();
    std::fs::copy(
        run.join("fisher_phase.npy"),
        killed.join("fisher_phase.npy"),
    )
    .unwrap();
    let o = train(&["init", "--fisher-iterations", "1"], &killed);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let one = std::fs::read(killed.join("fisher_phase.npy")).unwrap();
    assert!(
        one != mine,
        "the 3-iteration phase was reused for a 1-iteration run"
    );
}

/// `learned_lens: "embedding"`: the learned lens is `search embed`'s, to the byte, from the
/// job's Fisher phase on the job's triplets, and stays fixed while the network trains.
#[test]
fn the_main_jobs_embedding_lens_is_search_embeds_and_stays_fixed() {
    let d = tempfile::tempdir().unwrap();
    let bin = env!("CARGO_BIN_EXE_nanoeye");
    let (r, out) = tiny_job(
        d.path(),
        "run",
        r#""learned_lens": "embedding", "embed_triplets": 4, "embed_steps": 2, "#,
    );
    assert!(r["stages"]["embed"].as_f64().is_some(), "{r}");
    let e = &r["learned_lens_embedding"];
    for s in ["init", "final"] {
        assert_eq!(e[s]["triplets"], 4);
        assert!(e[s]["loss"].as_f64().is_some_and(f64::is_finite), "{e}");
    }
    let lens = std::fs::read(out.join("runs/learned/embed_phase.npy")).unwrap();
    assert!(lens != std::fs::read(out.join("runs/learned/fisher_phase.npy")).unwrap());
    // Fixed through the sandwich training.
    assert!(lens == std::fs::read(out.join("runs/learned/phase.npy")).unwrap());
    let fisher = out.join("runs/learned/fisher_phase.npy");
    let o = Command::new(bin)
        .args([
            "search",
            "embed",
            "--steps",
            "2",
            "--batch",
            "4",
            "--pitch-um",
            "60",
        ])
        .args(["--lr-phase-rad", "0.05", "--aperture-step-um", "10"])
        .args(["--exposure-ms", "0.0004", "--seed", "0", "--json", "--lens"])
        .arg(format!("file:{}", fisher.display()))
        .arg("--dataset")
        .arg(out.join("data/triplets"))
        .arg("--out")
        .arg(d.path().join("embed"))
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(lens == std::fs::read(d.path().join("embed/phase.npy")).unwrap());
}

/// `learned_lens: "joint"`: the learned lens trains on the task plus the embedding objective on
/// the job's triplets (every step records it; the fixed lenses' do not), ends elsewhere than
/// the same job on the task alone, and the result reports the objective before and after.
#[test]
fn the_main_jobs_joint_lens_trains_on_the_embedding_term_too() {
    let d = tempfile::tempdir().unwrap();
    let job = |extra: &str, name: &str| tiny_job(d.path(), name, extra);
    let (r, out) = job(
        r#""learned_lens": "joint", "embed_triplets": 4, "embed_weight": 5.0, "#,
        "joint",
    );
    assert!(r["stages"]["embed_eval"].as_f64().is_some(), "{r}");
    assert!(r["stages"].get("embed").is_none(), "{r}");
    let e = &r["learned_lens_embedding"];
    assert_eq!(e["learned_lens"], "joint");
    assert_eq!(e["embed_weight"], 5.0);
    for s in ["init", "final"] {
        assert_eq!(e[s]["triplets"], 4);
        assert!(e[s]["loss"].as_f64().is_some_and(f64::is_finite), "{e}");
    }
    let lines = |name: &str| {
        std::fs::read_to_string(out.join(format!("runs/{name}/history.jsonl")))
            .unwrap()
            .lines()
            .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
            .collect::<Vec<_>>()
    };
    let learned = lines("learned");
    assert_eq!(learned.len(), 2);
    assert!(
        learned
            .iter()
            .all(|h| h["embed_loss"].as_f64().is_some_and(f64::is_finite))
    );
    assert!(
        lines("hyperbolic")
            .iter()
            .all(|h| h.get("embed_loss").is_none())
    );
    let (plain, plain_out) = job("", "trained");
    assert!(plain.get("learned_lens_embedding").is_none());
    // The same Fisher start, another lens after training.
    let read = |o: &std::path::Path, f: &str| std::fs::read(o.join(f)).unwrap();
    let fisher = "runs/learned/fisher_phase.npy";
    assert!(read(&out, fisher) == read(&plain_out, fisher));
    // Two deterministic jobs that differ in μ alone: had the term not acted, the same bytes.
    let phase = "runs/learned/phase.npy";
    assert!(read(&out, phase) != read(&plain_out, phase));
    let fixed = "runs/hyperbolic/checkpoint.bin";
    assert!(read(&out, fixed) == read(&plain_out, fixed));
    // `nanoeye compare` reads both finished jobs back: two groups told apart by the keys that
    // differ, each run's errors as result.json has them, and B − A seed by seed.
    let svg = d.path().join("cmp.svg");
    let o = Command::new(env!("CARGO_BIN_EXE_nanoeye"))
        .args(["compare", "--json", "--svg"])
        .args([&svg, &out, &plain_out])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let c: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let lenses = ["learned", "hyperbolic", "double_helix"];
    assert_eq!(c["lenses"], serde_json::json!(lenses));
    let differs: Vec<&String> = c["groups"][0]["differs"]
        .as_object()
        .unwrap()
        .keys()
        .collect();
    assert_eq!(differs, ["embed_triplets", "embed_weight", "learned_lens"]);
    assert_eq!(c["groups"][1]["differs"]["learned_lens"], "trained");
    for (k, (res, run)) in [(&r, &c["runs"][0]), (&plain, &c["runs"][1])]
        .into_iter()
        .enumerate()
    {
        for (l, lens) in lenses.iter().enumerate() {
            assert_eq!(
                run["values"][l], res["protocol"][lens]["mean_deg"],
                "run {k}"
            );
        }
        assert_eq!(run["macs"], res["macs"]);
    }
    let v = &c["versus"][0];
    let learned =
        |res: &serde_json::Value| res["protocol"]["learned"]["mean_deg"].as_f64().unwrap();
    assert_eq!(
        v["per_lens"][0]["mean"].as_f64().unwrap(),
        learned(&plain) - learned(&r)
    );
    assert!(std::fs::read_to_string(&svg).unwrap().starts_with("<svg"));
}

//! `nanoeye sim` on a dataset of more frames than one chunk: the streamed NPYs hold every frame
//! in order, a frame's image does not depend on the call that made it, and sim.json records
//! what made them.

mod common;

use common::{TINY_CHAIN, nanoeye, tiny_dataset_of};
use serde_json::Value;
use std::path::Path;

/// An f32 NPY file's shape and values.
fn read_npy(p: &Path) -> (Vec<u64>, Vec<f32>) {
    let bytes = std::fs::read(p).unwrap();
    let npy = npyz::NpyFile::new(&bytes[..]).unwrap();
    let shape = npy.shape().to_vec();
    (shape, npy.into_vec().unwrap())
}

fn sim(frames: &str, out: &str, cwd: &Path, extra: &[&str]) -> Value {
    let mut args = TINY_CHAIN.to_vec();
    args.splice(0..0, ["sim"]);
    args.extend(["--seed", "3", "--frames", frames, "--out", out, "--json"]);
    args.extend(extra);
    let o = nanoeye(&args, cwd);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    let printed: Value = serde_json::from_slice(&o.stdout).unwrap();
    let file: Value =
        serde_json::from_str(&std::fs::read_to_string(cwd.join(out).join("sim.json")).unwrap())
            .unwrap();
    assert_eq!(printed, file);
    printed
}

#[test]
fn sim_streams_every_frame_in_order_and_records_its_settings() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    // Nine ambiguity items: 18 frames, two chunks of the chain's 16.
    assert!(nanoeye(&tiny_dataset_of("ds", "9"), p).status.success());
    let all = sim("0:18", "all", p, &[]);
    for (k, v) in [
        ("frames", Value::from(18)),
        ("lens", Value::from("hyperbolic")),
        ("noise", Value::from("on")),
        ("seed", Value::from(3)),
        ("exposure_ms", Value::from(0.0004)),
        ("aperture_step_um", Value::from(10.0)),
        ("frame_range", serde_json::json!([0, 18])),
        ("unit", Value::from("DN")),
        ("dataset", Value::from("ds")),
    ] {
        assert_eq!(all[k], v, "{k} in {all}");
    }
    // The sensor's default base pitch (3 µm), not the dataset's 48 µm pixels.
    assert_eq!(all["base_pitch_um"], Value::from(3.0), "{all}");
    let (h, w) = (
        all["height"].as_u64().unwrap(),
        all["width"].as_u64().unwrap(),
    );
    let (shape, sensor) = read_npy(&p.join("all/sensor.npy"));
    assert_eq!(shape, [18, h, w]);
    // Poisson electrons read out as whole DN, none negative.
    assert!(sensor.iter().all(|v| *v >= 0.0 && v.fract() == 0.0));
    let (mshape, masks) = read_npy(&p.join("all/mask.npy"));
    assert_eq!(mshape, [18, h, w]);
    assert!(masks.iter().all(|v| (0.0..=1.0).contains(v)));
    assert!(masks.iter().any(|v| *v > 0.0), "some pupil in view");
    let targets = std::fs::read_to_string(p.join("all/targets.jsonl")).unwrap();
    assert_eq!(targets.lines().count(), 18);
    // A frame alone (one in each chunk) is the same frame, noise and all: each frame's noise
    // stream is its own, and the streamed files keep the frames' order.
    let plane = (h * w) as usize;
    for k in [0usize, 17] {
        let one = format!("one{k}");
        let r = sim(&format!("{k}:{}", k + 1), &one, p, &[]);
        assert_eq!(r["frame_range"], serde_json::json!([k, k + 1]));
        let (s1, v1) = read_npy(&p.join(&one).join("sensor.npy"));
        let (_, m1) = read_npy(&p.join(&one).join("mask.npy"));
        assert_eq!(s1, [1, h, w]);
        let at = k * plane..(k + 1) * plane;
        assert!(v1 == sensor[at.clone()], "frame {k}'s image differs");
        assert!(m1 == masks[at], "frame {k}'s mask differs");
        let line = std::fs::read_to_string(p.join(&one).join("targets.jsonl")).unwrap();
        assert_eq!(line.trim(), targets.lines().nth(k).unwrap());
    }
    // A re-run that fails while imaging (frame 17's layers cut short, in the second chunk)
    // leaves the directory's set whole: sim.json and the files it vouches for unchanged.
    let before = common::tree(&p.join("all"));
    let lp = p.join("ds/frames/000017_layers.npy");
    let bytes = std::fs::read(&lp).unwrap();
    std::fs::write(&lp, &bytes[..bytes.len() / 2]).unwrap();
    let mut args = TINY_CHAIN.to_vec();
    args.splice(0..0, ["sim"]);
    args.extend(["--frames", "0:18", "--out", "all"]);
    let o = nanoeye(&args, p);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && err.contains("000017_layers.npy"),
        "{err}"
    );
    assert!(
        common::tree(&p.join("all")) == before,
        "the old set changed"
    );
    std::fs::write(&lp, bytes).unwrap();
    // Another base pitch is recorded as given, and replaces the directory's set.
    let six = sim("0:2", "all", p, &["--base-pitch-um", "6"]);
    assert_eq!(six["base_pitch_um"], Value::from(6.0), "{six}");
    assert_eq!(read_npy(&p.join("all/sensor.npy")).0, [2, h, w]);
}

/// An output target that cannot be replaced is refused before any frame is imaged: with a
/// directory at OUT/sim.json, sensor.npy, mask.npy and targets.jsonl were written first and
/// the run failed at its end.
#[test]
fn an_unwritable_output_is_refused_before_imaging() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    assert!(nanoeye(&tiny_dataset_of("ds", "1"), p).status.success());
    for name in ["sim.json", "targets.jsonl"] {
        let out = p.join(format!("o_{name}"));
        std::fs::create_dir_all(out.join(name)).unwrap();
        let mut args = TINY_CHAIN.to_vec();
        args.splice(0..0, ["sim"]);
        let o_arg = out.display().to_string();
        args.extend(["--frames", "0:2", "--out", &o_arg]);
        let o = nanoeye(&args, p);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success());
        assert!(err.contains(&format!("--out {name}")), "{err}");
        for written in ["sensor.npy", "mask.npy", "targets.jsonl"] {
            if written != name {
                assert!(
                    !out.join(written).exists(),
                    "{written} written before refusing"
                );
            }
        }
    }
}

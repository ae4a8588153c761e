//! Dataset writer: schema, determinism (same seed → identical bytes), resumption.

use nanoeye_datagen::render::dataset::rig_at_size;
use nanoeye_datagen::render::{DatasetOptions, LayerSpec, RenderSet, SceneSource, write_dataset};
use nanoeye_gaze::Rig;
use std::path::Path;

fn opts(dir: &Path, seed: u64) -> DatasetOptions {
    DatasetOptions {
        set: RenderSet::Ambiguity,
        n: 1,
        seed,
        width_px: 64,
        height_px: 40,
        spp: 1,
        out_dir: dir.to_path_buf(),
        rig: Rig::default(),
        source: SceneSource::Procedural,
        progress: false,
        layers: LayerSpec::default(),
        blink_fraction: 0.0,
        protocol_grid: nanoeye_datagen::states::PROTOCOL_GRID,
    }
}

fn files(dir: &Path) -> Vec<(String, Vec<u8>)> {
    let mut v: Vec<_> = walk(dir)
        .into_iter()
        .map(|p| {
            (
                p.strip_prefix(dir).unwrap().display().to_string(),
                std::fs::read(&p).unwrap(),
            )
        })
        .collect();
    v.sort();
    v
}

fn walk(d: &Path) -> Vec<std::path::PathBuf> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(d).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            out.extend(walk(&p))
        } else {
            out.push(p)
        }
    }
    out
}

#[test]
fn dataset_is_deterministic_resumable_and_follows_the_schema() {
    let a = tempfile::tempdir().unwrap();
    let b = tempfile::tempdir().unwrap();
    let sa = write_dataset(&opts(a.path(), 5)).unwrap();
    assert_eq!((sa.written, sa.skipped), (3, 0));
    write_dataset(&opts(b.path(), 5)).unwrap();
    let (fa, fb) = (files(a.path()), files(b.path()));
    assert_eq!(
        fa.len(),
        1 + 1 + 1 + 3 * 8,
        "dataset.json, frames.jsonl, contact sheet, 3 frames × 8 files"
    );
    assert_eq!(fa, fb, "same seed must give identical files");

    // Resume: delete one frame's record; only that frame is rendered again, same bytes.
    std::fs::remove_file(a.path().join("frames/000001.json")).unwrap();
    let s2 = write_dataset(&opts(a.path(), 5)).unwrap();
    assert_eq!((s2.written, s2.skipped), (1, 2));
    assert_eq!(files(a.path()), fb);

    let text = std::fs::read_to_string(a.path().join("frames.jsonl")).unwrap();
    let lines: Vec<serde_json::Value> = text
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.len(), 3);
    let roles: Vec<_> = lines
        .iter()
        .map(|l| l["role"].as_str().unwrap().to_string())
        .collect();
    assert_eq!(roles, ["anchor", "slip", "gaze"]);
    for (i, l) in lines.iter().enumerate() {
        assert_eq!(l["frame"], i);
        for key in [
            "state",
            "gaze",
            "pupil_center_px",
            "pupil_center_refracted_px",
            "landmarks",
            "files",
        ] {
            assert!(!l[key].is_null(), "missing {key}");
        }
        for f in [
            "preview",
            "radiance",
            "depth",
            "mask_visible_pupil",
            "mask_pupil",
            "layers",
            "masks",
        ] {
            assert!(a.path().join(l["files"][f].as_str().unwrap()).exists());
        }
    }
    // The gaze member is re-aimed so both members' pupils, seen through the cornea, land on
    // the same pixel (to the 1e-6 px of the Newton solve).
    let px = |i: usize, k: usize| lines[i]["pupil_center_refracted_px"][k].as_f64().unwrap();
    assert!((px(1, 0) - px(2, 0)).abs() < 1e-5 && (px(1, 1) - px(2, 1)).abs() < 1e-5);
    // Radiance NPY holds 64×40 f32.
    let npy = std::fs::read(
        a.path()
            .join(lines[0]["files"]["radiance"].as_str().unwrap()),
    )
    .unwrap();
    assert!(npy.len() > 64 * 40 * 4);
}

#[test]
fn bad_size_names_the_flag() {
    let e = rig_at_size(&Rig::default(), 320, 100)
        .unwrap_err()
        .to_string();
    assert!(e.contains("height"), "{e}");
    let e = rig_at_size(&Rig::default(), 0, 100)
        .unwrap_err()
        .to_string();
    assert!(e.contains("width"), "{e}");
}

/// `blink_fraction`: that share of envelope frames (within 4 binomial standard deviations over
/// 400 frames) gets a lid closure in BLINK_CLOSURE, drawn on a stream of its own, so every
/// subject and every other state field is the one of the default (no blinks) plan; the
/// manifest records the fraction only when it is not 0 (old datasets stay readable and equal),
/// and an out-of-range fraction or one on another set is refused.
#[test]
fn blink_fraction_closes_that_share_of_envelope_lids_and_changes_nothing_else() {
    use nanoeye_datagen::render::{BLINK_CLOSURE, RenderSet, plan_dataset};
    let dir = tempfile::tempdir().unwrap();
    let base = DatasetOptions {
        set: RenderSet::Envelope,
        n: 400,
        ..opts(dir.path(), 3)
    };
    let open = plan_dataset(&base).unwrap();
    let frac = 0.3;
    let blink = plan_dataset(&DatasetOptions {
        blink_fraction: frac,
        ..base.clone()
    })
    .unwrap();
    let mut closed = 0;
    for (a, b) in open.planned.iter().zip(&blink.planned) {
        assert_eq!(a.subject, b.subject);
        assert_eq!(a.state.lid_closure, 0.0);
        let mut s = b.state;
        if s.lid_closure != 0.0 {
            assert!(BLINK_CLOSURE.contains(&s.lid_closure), "{}", s.lid_closure);
            closed += 1;
            s.lid_closure = 0.0;
        }
        assert_eq!(s, a.state);
    }
    let sd = (400.0 * frac * (1.0 - frac)).sqrt();
    assert!(
        (closed as f64 - 400.0 * frac).abs() < 4.0 * sd,
        "{closed} of 400"
    );
    let text = serde_json::to_string(&open.manifest).unwrap();
    assert!(!text.contains("blink"), "{text}");
    assert_eq!(blink.manifest.blink_fraction, frac);
    for (set, f) in [
        (RenderSet::Envelope, 1.5),
        (RenderSet::Envelope, f64::NAN),
        (RenderSet::Ambiguity, 0.5),
    ] {
        let e = plan_dataset(&DatasetOptions {
            set,
            n: 2,
            blink_fraction: f,
            ..base.clone()
        })
        .unwrap_err();
        assert!(e.to_string().contains("blink_fraction"), "{e}");
    }
}

/// A variational set's manifest says its triplets share their pixel samples; one begun before
/// (no such key) is refused on resume, naming the key, rather than completed with frames
/// whose samples differ.
#[test]
fn a_variational_render_begun_with_per_frame_samples_is_not_resumed() {
    let d = tempfile::tempdir().unwrap();
    let o = DatasetOptions {
        set: RenderSet::Variational,
        ..opts(d.path(), 2)
    };
    write_dataset(&o).unwrap();
    let path = d.path().join("dataset.json");
    let text = std::fs::read_to_string(&path).unwrap();
    let mut m: serde_json::Value = serde_json::from_str(&text).unwrap();
    assert_eq!(m["triplet_samples_shared"], true);
    m.as_object_mut().unwrap().remove("triplet_samples_shared");
    std::fs::write(&path, serde_json::to_string(&m).unwrap()).unwrap();
    let e = write_dataset(&o).unwrap_err().to_string();
    assert!(e.contains("`triplet_samples_shared`"), "{e}");
    // Other sets do not carry the key.
    let a = tempfile::tempdir().unwrap();
    write_dataset(&opts(a.path(), 2)).unwrap();
    let t = std::fs::read_to_string(a.path().join("dataset.json")).unwrap();
    assert!(!t.contains("triplet_samples_shared"));
}

/// Options a render would refuse are refused before the output directory is touched, so the
/// corrected command is a first render, not a resume with other parameters.
#[test]
fn a_refused_render_writes_nothing_and_the_corrected_one_runs() {
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("out");
    for (bad, what) in [
        (
            DatasetOptions {
                spp: 0,
                ..opts(&out, 1)
            },
            "spp",
        ),
        (
            DatasetOptions {
                spp: 1 << 17,
                ..opts(&out, 1)
            },
            "spp",
        ),
        (
            DatasetOptions {
                layers: LayerSpec {
                    count: 0,
                    ..LayerSpec::default()
                },
                ..opts(&out, 1)
            },
            "layers",
        ),
    ] {
        let e = write_dataset(&bad).unwrap_err().to_string();
        assert!(e.contains(what), "{e}");
        assert!(!out.exists(), "{e}: {:?}", walk(&out));
    }
    write_dataset(&opts(&out, 1)).unwrap();
    assert!(out.join("dataset.json").is_file());
}

#[test]
fn the_array_bytes_estimate_is_what_the_writer_writes() {
    use nanoeye_datagen::render::dataset::dataset_array_bytes;
    let d = tempfile::tempdir().unwrap();
    let o = DatasetOptions {
        set: RenderSet::Envelope,
        n: 3,
        ..opts(d.path(), 2)
    };
    let (least, most) = dataset_array_bytes(&o).unwrap();
    write_dataset(&o).unwrap();
    let all = files(d.path());
    let written: u64 = all
        .iter()
        .filter(|(p, _)| p.ends_with(".npy"))
        .map(|(_, b)| {
            let c = nanoeye_npy::claim(b, b.len() as u64).unwrap().unwrap();
            c.data_bytes as u64
        })
        .sum();
    // Exactly the least plus two planes per kept layer, as the frames' records list them.
    let kept: usize = all
        .iter()
        .filter(|(p, _)| p.starts_with("frames/") && p.ends_with(".json"))
        .map(|(_, b)| {
            let r: serde_json::Value = serde_json::from_slice(b).unwrap();
            r["layers"].as_array().unwrap().len()
        })
        .sum();
    assert!(kept > 0, "no layer kept");
    let plane = 64 * 40 * 4;
    assert_eq!(written, least + 2 * plane * kept as u64);
    assert!(
        least < written && written <= most,
        "{least} {written} {most}"
    );
    assert_eq!(
        most - least,
        3 * 2 * plane * LayerSpec::default().count as u64
    );
}

/// `protocol_grid` G: the protocol set's G × G targets span D.4's extremes (G = 3 gives the
/// 7 × 7 grid's corner, edge-centre and centre targets, bit for bit, at the same stage
/// positions and mounting), 7 × G² frames per subject; the manifest records G only when it is
/// not 7 (the paper's datasets keep their layout), a resume with another grid is refused
/// naming the key, and a grid outside 2–7 or on another set is refused.
#[test]
fn a_coarser_protocol_grid_takes_the_paper_grids_targets_and_is_recorded() {
    use nanoeye_datagen::render::{open_dataset, plan_dataset};
    let dir = tempfile::tempdir().unwrap();
    let paper = DatasetOptions {
        set: RenderSet::Protocol,
        n: 1,
        ..opts(dir.path(), 5)
    };
    let coarse = DatasetOptions {
        protocol_grid: 3,
        ..paper.clone()
    };
    let (p7, p3) = (
        plan_dataset(&paper).unwrap(),
        plan_dataset(&coarse).unwrap(),
    );
    assert_eq!((p7.planned.len(), p3.planned.len()), (343, 63));
    assert_eq!((p7.manifest.frames, p3.manifest.frames), (343, 63));
    for (i, f) in p3.planned.iter().enumerate() {
        let (slip, row, col) = (i / 9, (i % 9) / 3, i % 3);
        let g = &p7.planned[slip * 49 + 3 * row * 7 + 3 * col].state;
        let s = &f.state;
        assert_eq!(
            (s.azimuth_rad, s.elevation_rad, s.slip_m, s.cam_rot_rad),
            (g.azimuth_rad, g.elevation_rad, g.slip_m, g.cam_rot_rad),
            "frame {i}"
        );
        assert_eq!(f.subject, p7.planned[0].subject);
    }
    let text = serde_json::to_string(&p7.manifest).unwrap();
    assert!(!text.contains("protocol_grid"), "{text}");
    assert_eq!(p3.manifest.protocol_grid, 3);
    // Written and reopened: the same grid resumes, another is refused.
    open_dataset(&coarse).unwrap();
    open_dataset(&coarse).unwrap();
    let e = open_dataset(&paper).unwrap_err().to_string();
    assert!(e.contains("protocol_grid"), "{e}");
    for (set, g) in [
        (RenderSet::Protocol, 1),
        (RenderSet::Protocol, 8),
        (RenderSet::Protocol, usize::MAX),
        (RenderSet::Envelope, 3),
    ] {
        let e = plan_dataset(&DatasetOptions {
            set,
            protocol_grid: g,
            ..paper.clone()
        })
        .unwrap_err()
        .to_string();
        assert!(e.contains("protocol_grid"), "{set:?} {g}: {e}");
    }
}

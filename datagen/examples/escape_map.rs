//! Where do primary rays leave the procedural scene without a hit? Reads a dataset's
//! frames.jsonl (states and subjects), shoots one ray through each pixel centre of the default
//! rig's camera and prints, per frame, the fraction that meets nothing, their mean, and where
//! the escaping rays cross a 60 mm sphere about the rotation centre (azimuth a = atan2(x, z),
//! + nasal, and elevation, in 20° bins, most populated first).
//!
//! Usage: `cargo run --release -p nanoeye-datagen --example escape_map -- DIR/frames.jsonl`

use nanoeye_datagen::render::{Light, Ray, Subject, procedural_scene, trace::pixel_dir};
use nanoeye_datagen::states::State;
use nanoeye_gaze::{Rig, geom};
use std::collections::BTreeMap;

fn main() {
    let path = std::env::args()
        .nth(1)
        .expect("usage: escape_map DIR/frames.jsonl");
    let text = std::fs::read_to_string(&path).expect("read frames.jsonl");
    let rig = Rig::default();
    let (w, h) = (rig.camera.width_px, rig.camera.height_px);
    let mut bins: BTreeMap<(i32, i32), usize> = BTreeMap::new();
    let mut fractions = Vec::new();
    for line in text.lines() {
        let v: serde_json::Value = serde_json::from_str(line).expect("frames.jsonl line");
        let state: State = serde_json::from_value(v["state"].clone()).expect("state");
        let subject = Subject::from_seed(v["subject"].as_u64().expect("subject seed"));
        let pose = state.camera_pose(&rig);
        let scene =
            procedural_scene(&rig, &state, &subject, Light::near_camera(&pose)).expect("scene");
        let mut missed = 0usize;
        for row in 0..h {
            for col in 0..w {
                let d = pixel_dir(&rig.camera, &pose, [col as f64 + 0.5, row as f64 + 0.5]);
                let ray = Ray::new(pose.position, d);
                if scene.closest(&ray, f64::INFINITY, 0xff).is_some() {
                    continue;
                }
                missed += 1;
                let o = pose.position;
                let b = geom::dot(o, d);
                let c = geom::dot(o, o) - 0.06f64.powi(2);
                let p = ray.at(-b + (b * b - c).sqrt());
                let a = p[0].atan2(p[2]).to_degrees();
                let e = (p[1] / 0.06).clamp(-1.0, 1.0).asin().to_degrees();
                let key = (
                    (a / 20.0).floor() as i32 * 20,
                    (e / 20.0).floor() as i32 * 20,
                );
                *bins.entry(key).or_default() += 1;
            }
        }
        let f = missed as f64 / (w * h) as f64;
        println!("frame {} rays without a hit {f:.4}", v["frame"]);
        fractions.push(f);
    }
    let n = fractions.len().max(1) as f64;
    println!(
        "mean {:.4}, worst {:.4} over {} frames",
        fractions.iter().sum::<f64>() / n,
        fractions.iter().copied().fold(0.0, f64::max),
        fractions.len()
    );
    let mut v: Vec<_> = bins.into_iter().collect();
    v.sort_by_key(|x| std::cmp::Reverse(x.1));
    for ((a, e), c) in v.iter().take(10) {
        println!(
            "azimuth [{a}°, {}°) elevation [{e}°, {}°): {c} rays",
            a + 20,
            e + 20
        );
    }
}

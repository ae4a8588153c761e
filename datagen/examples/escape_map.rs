//! Where do primary rays leave the procedural scene without a hit? Opens a dataset written by
//! `nanoeye datagen render` (its rig, states and subjects), shoots one ray through each pixel
//! centre of the dataset's camera and prints, per frame, the fraction that meets nothing, their
//! mean, and where the escaping rays cross a 60 mm sphere about the rotation centre (azimuth
//! a = atan2(x, z), + nasal, and elevation, in 20° bins, most populated first).
//!
//! Usage: `cargo run --release -p nanoeye-datagen --example escape_map -- DIR`

use nanoeye_datagen::render::{Dataset, Light, Ray, Subject, procedural_scene, trace::pixel_dir};
use nanoeye_gaze::geom;
use std::collections::BTreeMap;

/// Radius (m) of the sphere about the rotation centre on which escaping rays are binned.
const SPHERE_M: f64 = 0.06;

fn main() {
    let Some(dir) = std::env::args().nth(1) else {
        eprintln!("usage: escape_map DIR (a dataset written by `nanoeye datagen render`)");
        std::process::exit(2);
    };
    let ds = Dataset::open(std::path::Path::new(&dir)).unwrap_or_else(|e| {
        eprintln!("escape_map: {dir}: {e}");
        std::process::exit(1);
    });
    let rig = &ds.manifest.rig;
    let (w, h) = (rig.camera.width_px, rig.camera.height_px);
    let mut bins: BTreeMap<(i32, i32), usize> = BTreeMap::new();
    let mut fractions = Vec::new();
    for rec in &ds.records {
        let pose = rec.state.camera_pose(rig);
        let subject = Subject::from_seed(rec.subject);
        let scene = procedural_scene(rig, &rec.state, &subject, Light::near_camera(&pose))
            .unwrap_or_else(|e| {
                eprintln!("escape_map: frame {}: {e}", rec.frame);
                std::process::exit(1);
            });
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
                let c = geom::dot(o, o) - SPHERE_M * SPHERE_M;
                let p = ray.at(-b + (b * b - c).sqrt());
                let a = p[0].atan2(p[2]).to_degrees();
                let e = (p[1] / SPHERE_M).clamp(-1.0, 1.0).asin().to_degrees();
                let key = (
                    (a / 20.0).floor() as i32 * 20,
                    (e / 20.0).floor() as i32 * 20,
                );
                *bins.entry(key).or_default() += 1;
            }
        }
        let f = missed as f64 / (w * h) as f64;
        println!("frame {} rays without a hit {f:.4}", rec.frame);
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

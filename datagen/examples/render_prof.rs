//! Profiling harness for `perf record`: builds the render bench's scene (rig default, default
//! subject, φ = −5°, θ = −3°) or renders it at 320×200, 4 spp, N times, and prints the mean
//! time. Unlike criterion it runs one case only, so a profile holds nothing else; with
//! `RAYON_NUM_THREADS=1` its timings are less disturbed by other work on a shared machine.
//! `NOLASH=1` removes the lashes (what they cost).
//!
//! Usage: `cargo run --release -p nanoeye-datagen --example render_prof -- build|render [N]`

use nanoeye_datagen::render::{Light, RenderOptions, Subject, procedural_scene, render};
use nanoeye_datagen::states::State;
use nanoeye_gaze::Rig;

fn main() {
    let mode = std::env::args().nth(1).unwrap_or("render".into());
    let n: usize = std::env::args().nth(2).map_or(20, |s| s.parse().unwrap());
    let rig = Rig::default();
    let st = State {
        azimuth_rad: -5f64.to_radians(),
        elevation_rad: -3f64.to_radians(),
        torsion_rad: 0.0,
        slip_m: [0.0; 3],
        cam_rot_rad: [0.0; 3],
        lid_closure: 0.0,
    };
    let pose = st.camera_pose(&rig);
    let light = Light::near_camera(&pose);
    let mut sub = Subject::default();
    if std::env::var("NOLASH").is_ok() {
        sub.lashes_upper = 0;
        sub.lashes_lower = 0;
    }
    let scene = procedural_scene(&rig, &st, &sub, light).unwrap();
    eprintln!(
        "prims {} nodes {} depth {}",
        scene.prims.len(),
        scene.bvh.nodes.len(),
        scene.bvh.depth()
    );
    let t = std::time::Instant::now();
    for _ in 0..n {
        if mode == "build" {
            std::hint::black_box(procedural_scene(&rig, &st, &Subject::default(), light).unwrap());
        } else {
            std::hint::black_box(
                render(
                    &scene,
                    &rig.camera,
                    &pose,
                    &RenderOptions {
                        spp: 4,
                        seed: 1,
                        ..Default::default()
                    },
                )
                .unwrap(),
            );
        }
    }
    eprintln!(
        "{mode}: {:.2} ms",
        t.elapsed().as_secs_f64() * 1e3 / n as f64
    );
}

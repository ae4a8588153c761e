//! Renderer throughput: frames/s of the procedural eye region at 320×200 and 640×400 for 1, 4,
//! 16 spp and at the 1280×800 native grid for 4 spp, and the time to build a frame's scene (face
//! mesh, lashes, BVH). The noise column of docs/benchmarks.md is printed once per case.

use criterion::{Criterion, criterion_group, criterion_main};
use nanoeye_datagen::render::{Light, RenderOptions, Subject, procedural_scene, render};
use nanoeye_datagen::states::State;
use nanoeye_gaze::Rig;
use std::hint::black_box;

fn state() -> State {
    State {
        azimuth_rad: -5f64.to_radians(),
        elevation_rad: -3f64.to_radians(),
        torsion_rad: 0.0,
        slip_m: [0.0; 3],
        cam_rot_rad: [0.0; 3],
        lid_closure: 0.0,
    }
}

fn bench(c: &mut Criterion) {
    let rig = Rig::default();
    let st = state();
    let pose = st.camera_pose(&rig);
    let scene =
        procedural_scene(&rig, &st, &Subject::default(), Light::near_camera(&pose)).expect("scene");
    let mut g = c.benchmark_group("render");
    g.sample_size(10);
    let light = Light::near_camera(&pose);
    g.bench_function("scene_build", |bch| {
        bch.iter(|| {
            procedural_scene(&rig, black_box(&st), &Subject::default(), light).expect("scene")
        })
    });
    let cases: [(usize, f64, &[usize]); 3] = [
        (320, 12e-6, &[1, 4, 16]),
        (640, 6e-6, &[1, 4, 16]),
        (1280, 3e-6, &[4]),
    ];
    for (w, pitch, spps) in cases {
        let cam = rig.camera.with_pitch(pitch).expect("camera");
        for &spp in spps {
            // Noise: RMS pixel difference between two seeds, relative to the mean radiance.
            let a = render(
                &scene,
                &cam,
                &pose,
                &RenderOptions {
                    spp,
                    seed: 1,
                    ..Default::default()
                },
            )
            .expect("render");
            let b = render(
                &scene,
                &cam,
                &pose,
                &RenderOptions {
                    spp,
                    seed: 2,
                    ..Default::default()
                },
            )
            .expect("render");
            let (mut d2, mut m, mut n) = (0.0f64, 0.0f64, 0.0f64);
            for i in 0..a.radiance.nrows() {
                for j in 0..a.radiance.ncols() {
                    let (x, y) = (a.radiance[(i, j)] as f64, b.radiance[(i, j)] as f64);
                    // Glint pixels (≫ diffuse) would dominate; keep the diffuse range.
                    if x < 5.0 && y < 5.0 {
                        d2 += (x - y) * (x - y);
                        m += x;
                        n += 1.0;
                    }
                }
            }
            eprintln!(
                "noise {w}px {spp}spp: pixel std between seeds / mean = {:.4}",
                (d2 / n / 2.0).sqrt() / (m / n)
            );
            g.bench_function(format!("{w}x{}_{spp}spp", cam.height_px), |bch| {
                bch.iter(|| {
                    render(
                        black_box(&scene),
                        &cam,
                        &pose,
                        &RenderOptions {
                            spp,
                            seed: 1,
                            ..Default::default()
                        },
                    )
                    .expect("render")
                })
            });
        }
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);

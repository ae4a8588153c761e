//! Renderer physics: analytic ray–primitive hits, depth = hit distance, Lambertian radiance in
//! closed form, BVH = brute force, depth-layer conservation, refracted pupil centroid.

use faer::Mat;
use nanoeye_datagen::render::prim::{Clip, Shape};
use nanoeye_datagen::render::scene::{LAYER_ALL, LAYER_EYE, LAYER_SKIN, Prim};
use nanoeye_datagen::render::trace::pixel_dir;
use nanoeye_datagen::render::{
    Light, Material, MaterialKind, Ray, RayTracer, RenderOptions, Renderer, Scene, Subject,
    landmarks, procedural_scene, render,
};
use nanoeye_datagen::states::{self, State};
use nanoeye_gaze::{Camera, Pose, Rig, geom};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn skin(albedo: f64) -> Material {
    Material::lambertian(MaterialKind::Skin, albedo)
}

fn centroid(m: &Mat<f32>) -> [f64; 2] {
    let (mut s, mut sx, mut sy) = (0.0, 0.0, 0.0);
    for i in 0..m.nrows() {
        for j in 0..m.ncols() {
            let w = m[(i, j)] as f64;
            s += w;
            sx += w * (j as f64 + 0.5);
            sy += w * (i as f64 + 0.5);
        }
    }
    [sx / s, sy / s]
}

#[test]
fn ray_sphere_and_disc_hits_match_closed_form() {
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    for _ in 0..2000 {
        let c = [
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        ];
        let r: f64 = rng.random_range(0.01..0.5);
        let o = [
            rng.random_range(-3.0..3.0),
            rng.random_range(-3.0..3.0),
            rng.random_range(-3.0..3.0),
        ];
        let d = geom::normalize([
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        ]);
        let ray = Ray::new(o, d);
        let s = Shape::Sphere {
            center: c,
            radius_m: r,
            clip: Clip::None,
        };
        // Closed form: |o + t d − c|² = r², smallest positive root.
        let oc = geom::sub(o, c);
        let b = geom::dot(oc, d);
        let disc = b * b - (geom::dot(oc, oc) - r * r);
        let expect = if disc < 0.0 {
            None
        } else {
            [-b - disc.sqrt(), -b + disc.sqrt()]
                .into_iter()
                .find(|t| *t > 1e-9)
        };
        match (s.intersect(&ray, f64::INFINITY), expect) {
            (Some(t), Some(e)) => {
                assert!((t - e).abs() < 1e-12 * (1.0 + e), "{t} vs {e}");
                assert!((geom::norm(geom::sub(ray.at(t), c)) - r).abs() < 1e-12);
            }
            (None, None) => {}
            (a, b) => panic!("sphere hit {a:?} vs closed form {b:?}"),
        }
        // Disc through c with normal n: t = n·(c − o)/(n·d), inside r.
        let n = geom::normalize([
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            1.0,
        ]);
        let disc_shape = Shape::Disc {
            center: c,
            normal: n,
            r_in_m: 0.0,
            r_out_m: r,
        };
        let t_plane = geom::dot(n, geom::sub(c, o)) / geom::dot(n, d);
        let inside = t_plane > 1e-9 && geom::norm(geom::sub(ray.at(t_plane), c)) <= r;
        match disc_shape.intersect(&ray, f64::INFINITY) {
            Some(t) => {
                assert!(inside);
                assert!((t - t_plane).abs() < 1e-12 * (1.0 + t_plane));
            }
            None => {
                assert!(!inside || (geom::norm(geom::sub(ray.at(t_plane), c)) - r).abs() < 1e-12)
            }
        }
    }
}

#[test]
fn bvh_closest_hit_equals_brute_force() {
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    let mut prims = Vec::new();
    for _ in 0..500 {
        let p = [
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        ];
        let e = |rng: &mut ChaCha8Rng| {
            [
                rng.random_range(-0.1..0.1),
                rng.random_range(-0.1..0.1),
                rng.random_range(-0.1..0.1),
            ]
        };
        let v = [p, geom::add(p, e(&mut rng)), geom::add(p, e(&mut rng))];
        prims.push(Prim {
            shape: Shape::Triangle { v },
            material: 0,
            layer: LAYER_SKIN,
        });
    }
    for k in 0..50 {
        prims.push(Prim {
            shape: Shape::Sphere {
                center: [
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                ],
                radius_m: 0.05,
                clip: Clip::None,
            },
            material: 0,
            layer: if k % 2 == 0 { LAYER_EYE } else { LAYER_SKIN },
        });
    }
    let light = Light::isotropic([0.0, 0.0, 5.0], 0.01, 1.0);
    let scene = Scene::new(prims.clone(), vec![skin(0.5)], light, 1.376).unwrap();
    assert!(scene.bvh.depth() > 3, "the BVH must actually split");
    for _ in 0..3000 {
        let o = [
            rng.random_range(-2.0..2.0),
            rng.random_range(-2.0..2.0),
            rng.random_range(-2.0..2.0),
        ];
        let d = [
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        ];
        let ray = Ray::new(o, d);
        for mask in [LAYER_ALL, LAYER_EYE] {
            let brute = prims
                .iter()
                .enumerate()
                .filter(|(_, p)| p.layer & mask != 0)
                .filter_map(|(i, p)| p.shape.intersect(&ray, f64::INFINITY).map(|t| (i, t)))
                .min_by(|a, b| a.1.total_cmp(&b.1));
            let got = scene
                .closest(&ray, f64::INFINITY, mask)
                .map(|h| (h.prim as usize, h.t));
            assert_eq!(got.map(|g| g.1), brute.map(|b| b.1));
            assert_eq!(
                scene.occluded(&ray, 10.0, mask),
                brute.is_some_and(|b| b.1 < 10.0)
            );
        }
    }
}

fn test_camera(w: usize, h: usize) -> (Camera, Pose) {
    let cam = Camera::look_at(2e-3, 12e-6, w, h, [0.0, 0.0, 0.0], [0.0, 0.0, 1.0]).unwrap();
    let pose = cam.nominal_pose();
    (cam, pose)
}

#[test]
fn depth_map_equals_hit_distances_for_plane_and_sphere() {
    let (cam, pose) = test_camera(64, 40);
    // A plane (large disc) at z = 30 mm and a sphere of radius 4 mm at z = 20 mm.
    let (zp, c, r) = (30e-3, [1e-3, 0.5e-3, 20e-3], 4e-3);
    let prims = vec![
        Prim {
            shape: Shape::Disc {
                center: [0.0, 0.0, zp],
                normal: [0.0, 0.0, -1.0],
                r_in_m: 0.0,
                r_out_m: 1.0,
            },
            material: 0,
            layer: LAYER_SKIN,
        },
        Prim {
            shape: Shape::Sphere {
                center: c,
                radius_m: r,
                clip: Clip::None,
            },
            material: 0,
            layer: LAYER_SKIN,
        },
    ];
    let light = Light::near_camera(&pose);
    let scene = Scene::new(prims, vec![skin(0.5)], light, 1.376).unwrap();
    let f = render(&scene, &cam, &pose, &RenderOptions::default()).unwrap();
    let mut on_sphere = 0;
    for i in 0..40 {
        for j in 0..64 {
            let d = geom::normalize(pixel_dir(&cam, &pose, [j as f64 + 0.5, i as f64 + 0.5]));
            let b = geom::dot(d, c);
            let disc = b * b - (geom::dot(c, c) - r * r);
            let expect = if disc >= 0.0 {
                on_sphere += 1;
                b - disc.sqrt()
            } else {
                zp / d[2]
            };
            let got = f.depth_m[(i, j)] as f64;
            assert!(
                (got - expect).abs() < 1e-6 * expect,
                "pixel ({j},{i}): {got} vs {expect}"
            );
        }
    }
    assert!(on_sphere > 100, "the sphere must cover part of the image");
    // Layers of 2 mm from 10 to 50 mm: the sphere (16–20 mm) and the plane (30 mm to ~40 mm)
    // fill a few slabs; the slabs between them and beyond are empty and flagged.
    let opts = RenderOptions {
        spp: 2,
        layers: nanoeye_datagen::render::LayerSpec {
            count: 20,
            near_m: 10e-3,
            far_m: 50e-3,
        },
        ..Default::default()
    };
    let f = render(&scene, &cam, &pose, &opts).unwrap();
    let flags: Vec<bool> = f.layers.layers.iter().map(|l| l.empty).collect();
    for (k, l) in f.layers.layers.iter().enumerate() {
        let any = (0..40).any(|i| (0..64).any(|j| l.alpha[(i, j)] > 0.0));
        assert_eq!(l.empty, !any, "layer {k}");
    }
    assert!(
        flags[0..3].iter().all(|e| *e),
        "nothing nearer than 16 mm: {flags:?}"
    );
    assert!(!flags[3] && !flags[10], "sphere front and plane: {flags:?}");
    assert!(
        flags[6..10].iter().all(|e| *e),
        "gap between sphere and plane: {flags:?}"
    );
    assert!(
        flags[17..].iter().all(|e| *e),
        "nothing beyond ~44 mm: {flags:?}"
    );
}

#[test]
fn lambertian_plane_radiance_matches_closed_form() {
    // L = ρ/π · I cosθ / d² for a point-like emitter (0.5 µm radius: finite-size error ≪ 1e-6).
    let (cam, pose) = test_camera(32, 20);
    let (zp, rho, intensity) = (25e-3, 0.4, 2e-3);
    let lp = [3e-3, -2e-3, 0.0];
    let prims = vec![Prim {
        shape: Shape::Disc {
            center: [0.0, 0.0, zp],
            normal: [0.0, 0.0, -1.0],
            r_in_m: 0.0,
            r_out_m: 1.0,
        },
        material: 0,
        layer: LAYER_SKIN,
    }];
    let light = Light::isotropic(lp, 0.5e-6, intensity);
    let scene = Scene::new(prims, vec![skin(rho)], light, 1.376).unwrap();
    let f = render(
        &scene,
        &cam,
        &pose,
        &RenderOptions {
            spp: 1,
            ..Default::default()
        },
    )
    .unwrap();
    for (i, j) in [(0, 0), (10, 16), (19, 31), (5, 25)] {
        let d = geom::normalize(pixel_dir(&cam, &pose, [j as f64 + 0.5, i as f64 + 0.5]));
        let p = geom::scale(d, zp / d[2]);
        let l = geom::sub(lp, p);
        let dist = geom::norm(l);
        let expect = rho / std::f64::consts::PI * intensity * (-l[2] / dist) / (dist * dist);
        let got = f.radiance[(i, j)] as f64;
        assert!(
            (got - expect).abs() < 1e-5 * expect,
            "({j},{i}): {got} vs {expect}"
        );
    }
}

#[test]
fn shadowed_point_receives_no_direct_light() {
    // A 1 mm sphere halfway between a point-like emitter at x = −3 mm and the plane z = 30 mm
    // casts an umbra of radius 2 mm centred at x = +3 mm; the camera's own view of the plane is
    // blocked within 2 mm of the axis, so x = 4 mm is visible and in the umbra.
    let (cam, pose) = test_camera(64, 40);
    let prims = vec![
        Prim {
            shape: Shape::Disc {
                center: [0.0, 0.0, 30e-3],
                normal: [0.0, 0.0, -1.0],
                r_in_m: 0.0,
                r_out_m: 1.0,
            },
            material: 0,
            layer: LAYER_SKIN,
        },
        Prim {
            shape: Shape::Sphere {
                center: [0.0, 0.0, 15e-3],
                radius_m: 1e-3,
                clip: Clip::None,
            },
            material: 0,
            layer: LAYER_SKIN,
        },
    ];
    let light = Light::isotropic([-3e-3, 0.0, 0.0], 1e-6, 1e-3);
    let scene = Scene::new(prims, vec![skin(0.5)], light, 1.376).unwrap();
    let f = render(
        &scene,
        &cam,
        &pose,
        &RenderOptions {
            spp: 1,
            ..Default::default()
        },
    )
    .unwrap();
    let px = nanoeye_gaze::project(&cam, &pose, [4e-3, 0.0, 30e-3]).unwrap();
    let (i, j) = (px[1] as usize, px[0] as usize);
    let range = geom::norm([4e-3, 0.0, 30e-3]);
    assert!(
        (f.depth_m[(i, j)] as f64 - range).abs() < 1e-4,
        "the plane is visible there"
    );
    assert_eq!(f.radiance[(i, j)], 0.0, "umbra must be black");
    assert!(f.radiance[(i, 2)] > 0.0, "lit plane far from the umbra");
}

fn primary_state() -> State {
    State {
        azimuth_rad: -5f64.to_radians(),
        elevation_rad: -3f64.to_radians(),
        torsion_rad: 0.0,
        slip_m: [0.0; 3],
        cam_rot_rad: [0.0; 3],
        lid_closure: 0.0,
    }
}

#[test]
fn depth_layers_conserve_radiance_and_coverage() {
    let rig = Rig::default();
    let st = primary_state();
    let pose = st.camera_pose(&rig);
    let scene =
        procedural_scene(&rig, &st, &Subject::default(), Light::near_camera(&pose)).unwrap();
    let opts = RenderOptions {
        spp: 2,
        ..Default::default()
    };
    let cam = rig.camera.with_pitch(48e-6).unwrap(); // 80×50 keeps the test fast
    // Through the stage trait, as a pipeline holding a `dyn Renderer` would call it.
    let stage: &dyn Renderer = &RayTracer { opts };
    let f = stage.render(&scene, &cam, &pose).unwrap();
    for l in &f.layers.layers {
        let any = (0..l.alpha.nrows()).any(|i| (0..l.alpha.ncols()).any(|j| l.alpha[(i, j)] > 0.0));
        assert_eq!(l.empty, !any);
    }
    for i in 0..f.radiance.nrows() {
        for j in 0..f.radiance.ncols() {
            let sl: f64 = f
                .layers
                .layers
                .iter()
                .map(|l| l.radiance[(i, j)] as f64)
                .sum();
            let sa: f64 = f.layers.layers.iter().map(|l| l.alpha[(i, j)] as f64).sum();
            let r = f.radiance[(i, j)] as f64;
            assert!(
                (sl - r).abs() <= 1e-5 * r.abs().max(1e-12),
                "Σ L_k = {sl} vs {r}"
            );
            // Sample 0's depth is finite iff it met a surface; the coverage then sums to 1
            // unless some other sample escaped past the face plane (image corners).
            if f.depth_m[(i, j)].is_finite() {
                assert!(sa > 0.0 && sa <= 1.0 + 1e-6, "Σ α_k = {sa}");
            }
            assert!(sa <= 1.0 + 1e-6);
        }
    }
}

/// Renders `st` at 320×200 with 4 spp and returns (visible mask, pupil mask, refracted px,
/// unrefracted px).
fn pupil_render(
    rig: &Rig,
    st: &State,
    subject: &Subject,
) -> (Mat<f32>, Mat<f32>, [f64; 2], [f64; 2]) {
    let pose = st.camera_pose(rig);
    let scene = procedural_scene(rig, st, subject, Light::near_camera(&pose)).unwrap();
    let f = render(
        &scene,
        &rig.camera,
        &pose,
        &RenderOptions {
            spp: 4,
            ..Default::default()
        },
    )
    .unwrap();
    let lm = landmarks(rig, st, subject).unwrap();
    (
        f.mask_visible_pupil,
        f.mask_pupil,
        lm.pupil_center_refracted_px.unwrap(),
        lm.pupil_center.px.unwrap(),
    )
}

fn same_mask(a: &Mat<f32>, b: &Mat<f32>) -> bool {
    (0..a.nrows()).all(|i| (0..a.ncols()).all(|j| a[(i, j)] == b[(i, j)]))
}

#[test]
fn visible_pupil_centroid_matches_refracted_projection() {
    let rig = Rig::default();
    let subject = Subject::default();
    for st in [
        primary_state(),
        State {
            azimuth_rad: 10f64.to_radians(),
            elevation_rad: 5f64.to_radians(),
            ..primary_state()
        },
    ] {
        let (vis, pup, refr, unrefr) = pupil_render(&rig, &st, &subject);
        assert!(
            same_mask(&vis, &pup),
            "lids must not occlude in this test state"
        );
        let c = centroid(&vis);
        let err = ((c[0] - refr[0]).powi(2) + (c[1] - refr[1]).powi(2)).sqrt();
        let shift = ((refr[0] - unrefr[0]).powi(2) + (refr[1] - unrefr[1]).powi(2)).sqrt();
        eprintln!(
            "state {st:?}: centroid {c:?}, refracted {refr:?} (err {err:.3} px), unrefracted {unrefr:?} (shift {shift:.2} px)"
        );
        assert!(
            err < 0.5,
            "centroid {c:?} vs refracted projection {refr:?}: {err} px"
        );
        // The cornea magnifies and shifts the pupil: the refracted centre is measurably
        // different from the pinhole projection of the true centre.
        assert!(shift > 0.5, "refraction shift {shift} px");
    }
}

/// Rendered (slip, gaze) centroids and refracted landmark pixels of the first unoccluded pairs.
/// (slip centroid, gaze centroid, slip refracted px, gaze refracted px).
type PairPx = ([f64; 2], [f64; 2], [f64; 2], [f64; 2]);

fn pair_centroids(subject: &Subject, max: usize) -> Vec<PairPx> {
    let rig = Rig::default();
    let pairs = states::ambiguity(&rig, 6, 7).unwrap();
    let mut out = Vec::new();
    for p in &pairs {
        let (vs, ps, rs, _) = pupil_render(&rig, &p.slip, subject);
        let (vg, pg, rg, _) = pupil_render(&rig, &p.gaze, subject);
        if !(same_mask(&vs, &ps) && same_mask(&vg, &pg)) {
            continue; // a lid occludes one member
        }
        out.push((centroid(&vs), centroid(&vg), rs, rg));
        if out.len() == max {
            break;
        }
    }
    assert!(!out.is_empty(), "no unoccluded pair among {}", pairs.len());
    out
}

fn dist(a: [f64; 2], b: [f64; 2]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)).sqrt()
}

#[test]
fn ambiguity_pair_centroids_agree_without_refraction() {
    // With n = 1 the cornea is transparent: the pair's pupils project onto the same pixel by
    // construction, so the rendered centroids must agree.
    let subject = Subject {
        cornea_index: 1.0,
        ..Subject::default()
    };
    for (a, b, _, _) in pair_centroids(&subject, 2) {
        let d = dist(a, b);
        eprintln!("n = 1 pair: slip {a:?} gaze {b:?}: {d:.3} px");
        assert!(d < 0.5, "ambiguity pair centroids differ by {d} px");
    }
}

#[test]
fn ambiguity_pair_centroid_difference_is_the_refraction_difference() {
    // With the refracting cornea the pair's apparent pupils differ (the view through the
    // cornea differs between a moved camera and a rotated eye); the rendered difference must
    // equal the difference of the refracted-centre landmarks within 0.5 px.
    for (a, b, ra, rb) in pair_centroids(&Subject::default(), 2) {
        let rendered = [a[0] - b[0], a[1] - b[1]];
        let predicted = [ra[0] - rb[0], ra[1] - rb[1]];
        let e = dist(rendered, predicted);
        eprintln!(
            "n = 1.376 pair: centroid difference {:.3} px, refracted-landmark difference {:.3} px, mismatch {e:.3} px",
            dist(a, b),
            dist(ra, rb)
        );
        assert!(e < 0.5, "rendered {rendered:?} vs predicted {predicted:?}");
    }
}

#[test]
fn ambiguity_pair_centroids_agree_once_matched_through_the_cornea() {
    // The dataset re-aims the `gaze` member so its refracted pupil centre lands on the `slip`
    // member's: with the refracting cornea the rendered pupils then coincide, as C.3 intends.
    use nanoeye_datagen::render::SceneSource;
    use nanoeye_datagen::render::dataset::{RenderSet, plan};
    let rig = Rig::default();
    let frames = plan(
        RenderSet::Ambiguity,
        &rig,
        &SceneSource::Procedural,
        6,
        7,
        states::PROTOCOL_GRID,
    )
    .unwrap();
    let mut checked = 0;
    for item in frames.chunks(3) {
        let (slip, gaze) = (&item[1], &item[2]);
        assert_eq!((slip.role, gaze.role), ("slip", "gaze"));
        let subject = Subject::from_seed(slip.subject);
        let (vs, ps, rs, _) = pupil_render(&rig, &slip.state, &subject);
        let (vg, pg, rg, _) = pupil_render(&rig, &gaze.state, &subject);
        assert!(dist(rs, rg) < 1e-5, "refracted centres {rs:?} vs {rg:?}");
        if !(same_mask(&vs, &ps) && same_mask(&vg, &pg)) {
            continue; // a lid occludes one member
        }
        let d = dist(centroid(&vs), centroid(&vg));
        eprintln!("n = 1.376, refracted match: centroids differ by {d:.3} px");
        assert!(d < 0.5, "ambiguity pair centroids differ by {d} px");
        checked += 1;
        if checked == 2 {
            break;
        }
    }
    assert!(checked > 0, "no unoccluded pair");
}

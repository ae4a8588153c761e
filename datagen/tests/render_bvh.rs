//! The ray–scene queries behind the renderer's speed: on the procedural face (skin, lash
//! ribbons, eye), the BVH's nearest hit equals brute force over every primitive for every
//! class mask (the few-primitive eye scan included), any-hit agrees with nearest-hit, and a
//! degenerate tree deeper than the traversal stack still finds every hit.

use nanoeye_datagen::render::bvh::Bvh;
use nanoeye_datagen::render::prim::Aabb;
use nanoeye_datagen::render::scene::{LAYER_ALL, LAYER_CORNEA, LAYER_EYE, LAYER_SKIN, Scene};
use nanoeye_datagen::render::{Light, Ray, Subject, procedural_scene};
use nanoeye_datagen::states::State;
use nanoeye_gaze::{Rig, Vec3, geom};
use proptest::prelude::*;
use std::sync::OnceLock;

const MASKS: [u8; 6] = [
    LAYER_ALL,
    LAYER_SKIN,
    LAYER_EYE,
    LAYER_EYE | LAYER_CORNEA,
    LAYER_EYE | LAYER_SKIN,
    LAYER_ALL & !LAYER_CORNEA,
];

/// Face scenes of two subjects in two states (gaze down with a half-closed lid, gaze up).
fn scenes() -> &'static [(Scene, Vec3)] {
    static S: OnceLock<Vec<(Scene, Vec3)>> = OnceLock::new();
    S.get_or_init(|| {
        let rig = Rig::default();
        [
            (Subject::default(), -15.0, 8.0, 0.5),
            (Subject::from_seed(11), 10.0, 20.0, 0.0),
        ]
        .into_iter()
        .map(|(subject, az, el, closure)| {
            let st = State {
                azimuth_rad: f64::to_radians(az),
                elevation_rad: f64::to_radians(el),
                torsion_rad: 0.0,
                slip_m: [0.0; 3],
                cam_rot_rad: [0.0; 3],
                lid_closure: closure,
            };
            let pose = st.camera_pose(&rig);
            let light = Light::near_camera(&pose);
            let scene = procedural_scene(&rig, &st, &subject, light).expect("scene");
            (scene, pose.position)
        })
        .collect()
    })
}

/// Nearest hit over every primitive of `mask`: (distance, primitives at that distance).
fn brute(scene: &Scene, ray: &Ray, mask: u8) -> Option<(f64, Vec<u32>)> {
    let mut best: Option<(f64, Vec<u32>)> = None;
    for (i, p) in scene.prims.iter().enumerate() {
        if p.layer & mask == 0 {
            continue;
        }
        if let Some(t) = p.shape.intersect(ray, f64::INFINITY) {
            match &mut best {
                Some((tb, v)) if t == *tb => v.push(i as u32),
                Some((tb, _)) if t > *tb => {}
                _ => best = Some((t, vec![i as u32])),
            }
        }
    }
    best
}

fn check_ray(scene: &Scene, ray: &Ray, t_cut: f64) -> Result<usize, TestCaseError> {
    let mut hits = 0;
    for mask in MASKS {
        let want = brute(scene, ray, mask);
        let got = scene.closest(ray, f64::INFINITY, mask);
        match (&got, &want) {
            (None, None) => {}
            (Some(h), Some((t, prims))) => {
                prop_assert_eq!(h.t, *t, "mask {}: distance", mask);
                prop_assert!(
                    prims.contains(&h.prim),
                    "mask {mask}: prim {} not in {prims:?}",
                    h.prim
                );
                hits += 1;
            }
            _ => prop_assert!(false, "mask {mask}: BVH {got:?} vs brute force {want:?}"),
        }
        // Any-hit before t_cut ⇔ the nearest hit lies before it.
        let occluded = scene.occluded(ray, t_cut, mask);
        prop_assert_eq!(
            occluded,
            want.as_ref().is_some_and(|(t, _)| *t < t_cut),
            "mask {}: any-hit below {}",
            mask,
            t_cut
        );
    }
    Ok(hits)
}

fn unit(v: [f64; 3]) -> Vec3 {
    geom::normalize(v)
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    /// Camera-like rays (from around the camera towards the eye region) and shadow-like rays
    /// (from a surface point towards the LED): BVH = brute force, any = nearest.
    #[test]
    fn face_bvh_equals_brute_force_and_any_hit_agrees(
        which in 0usize..2,
        offsets in prop::collection::vec(
            ([-3e-3f64..3e-3, -3e-3f64..3e-3, -3e-3f64..3e-3],
             [-18e-3f64..18e-3, -14e-3f64..14e-3, 0.0f64..16e-3],
             0.0f64..1.2),
            16,
        ),
    ) {
        let (scene, cam) = &scenes()[which];
        let mut hits = 0;
        for (o, target, cut) in offsets {
            let origin = geom::add(*cam, o);
            let ray = Ray::new(origin, unit(geom::sub(target, origin)));
            // t_cut spans misses and hits around the first surface (~15–40 mm away).
            hits += check_ray(scene, &ray, 1e-3 + cut * 40e-3)?;
            // A shadow ray from the first surface hit towards the emitter.
            if let Some(h) = scene.closest(&ray, f64::INFINITY, LAYER_ALL) {
                let p = ray.at(h.t);
                let mut n = scene.prims[h.prim as usize].shape.normal(p);
                if geom::dot(n, ray.dir) > 0.0 {
                    n = geom::scale(n, -1.0);
                }
                let from = geom::add(p, geom::scale(n, 1e-8));
                let to_light = geom::sub(scene.light.position_m, from);
                let shadow = Ray::new(from, to_light);
                hits += check_ray(scene, &shadow, geom::norm(to_light))?;
            }
        }
        // The rays must actually meet the face, not only miss it.
        prop_assert!(hits > 0);
    }
}

/// Unit boxes along the x axis at x = 20^k: every split can only take the farthest box off
/// the rest (all other centroids share the first of the 12 bins), so the tree is a chain about
/// as deep as there are boxes, deeper than the traversal's 64-entry stack (and beyond f32
/// range, where the packed boxes widen to infinity). A ray along the axis meets both children
/// at every level, so the walk must finish through its spill and still find every nearest hit
/// and any-hit.
#[test]
fn a_tree_deeper_than_the_stack_still_finds_every_hit() {
    let x = |k: usize| 20f64.powi(k as i32);
    let bounds: Vec<Aabb> = (0..100)
        .map(|k| Aabb {
            min: [x(k), -1.0, -1.0],
            max: [x(k) + 1.0, 1.0, 1.0],
        })
        .collect();
    let bvh = Bvh::build(&bounds);
    assert!(bvh.depth() > 80, "depth {}", bvh.depth());
    // Rays along +x from before box k0, and slanted ones leaving through the side.
    for (k0, dy) in [(0usize, 0.0), (20, 0.0), (70, 0.0), (3, 1e-3), (10, 1e-200)] {
        let ray = Ray::new([x(k0) - 0.25, 0.0, 0.0], [1.0, dy, 0.0]);
        // Per leaf, the nearest box below t_max, the lowest slot on a tie.
        let hit = |first: u32, count: u32, t_max: f64| {
            let mut best: Option<(u32, f64)> = None;
            for s in first..first + count {
                let tm = best.map_or(t_max, |b| b.1);
                if let Some(t) = bounds[bvh.order[s as usize] as usize].hit(&ray, tm) {
                    best = Some((s, t));
                }
            }
            best
        };
        let want = bounds
            .iter()
            .enumerate()
            .filter_map(|(i, b)| b.hit(&ray, f64::INFINITY).map(|t| (i, t)))
            .min_by(|a, b| a.1.total_cmp(&b.1));
        let got = bvh
            .closest(&ray, f64::INFINITY, hit)
            .map(|(s, t)| (bvh.order[s as usize] as usize, t));
        assert_eq!(got, want, "ray from box {k0}");
        // Any-hit of one box only: the farthest is pushed first (at the root), a box just
        // past the ray's first one is pushed ~90 levels down, beyond the fixed stack.
        for target in [bounds.len() - 1, k0 + 5] {
            let only = |first: u32, count: u32, t_max: f64| {
                (first..first + count).any(|s| {
                    bvh.order[s as usize] as usize == target
                        && bounds[target].hit(&ray, t_max).is_some()
                })
            };
            assert_eq!(
                bvh.any(&ray, f64::INFINITY, only),
                bounds[target].hit(&ray, f64::INFINITY).is_some(),
                "ray from box {k0}, box {target}"
            );
        }
    }
}

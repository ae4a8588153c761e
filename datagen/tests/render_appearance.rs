//! Appearance physics of the eye region: glints where the law of reflection puts the LED's
//! image on the cornea and on the tear film of the sclera, lash shadows where lash geometry
//! blocks the LED, and the skin micro-texture's variance at its documented scales.

use nanoeye_datagen::render::material::{SkinTexture, TEAR_FILM_INDEX};
use nanoeye_datagen::render::prim::{Clip, Shape, perpendicular_basis};
use nanoeye_datagen::render::scene::{LAYER_ALL, LAYER_EYE, Prim, Scene};
use nanoeye_datagen::render::{
    Frame, Light, Material, MaterialKind, Ray, RenderOptions, Subject, procedural_parts,
    procedural_scene, render,
};
use nanoeye_datagen::states::State;
use nanoeye_gaze::{Camera, Pose, Rig, Vec3, geom};

fn state(az_deg: f64, el_deg: f64) -> State {
    State {
        azimuth_rad: az_deg.to_radians(),
        elevation_rad: el_deg.to_radians(),
        torsion_rad: 0.0,
        slip_m: [0.0; 3],
        cam_rot_rad: [0.0; 3],
        lid_closure: 0.0,
    }
}

/// Image point (px, origin at the top-left corner) of world point `p`.
fn project(cam: &Camera, pose: &Pose, p: Vec3) -> [f64; 2] {
    let a = geom::mul_mtv(&pose.rotation, geom::sub(p, pose.position));
    [
        cam.cx_px + cam.fx_px * a[0] / a[2],
        cam.cy_px + cam.fy_px * a[1] / a[2],
    ]
}

/// The point of the sphere (centre `c`, radius `r`) where a mirror reflects a ray from `light`
/// into `eye`: its normal bisects the directions to both (damped fixed-point iteration).
fn mirror_point(c: Vec3, r: f64, eye: Vec3, light: Vec3) -> Vec3 {
    let mut n = geom::normalize(geom::sub(eye, c));
    for _ in 0..5000 {
        let g = geom::add(c, geom::scale(n, r));
        let bis = geom::normalize(geom::add(
            geom::normalize(geom::sub(eye, g)),
            geom::normalize(geom::sub(light, g)),
        ));
        n = geom::normalize(geom::add(n, bis));
    }
    let g = geom::add(c, geom::scale(n, r));
    let n = geom::normalize(geom::sub(g, c));
    let (to_e, to_l) = (
        geom::normalize(geom::sub(eye, g)),
        geom::normalize(geom::sub(light, g)),
    );
    // Law of reflection: equal angles, and n, to_e, to_l coplanar.
    assert!((geom::dot(n, to_e) - geom::dot(n, to_l)).abs() < 1e-10);
    assert!(geom::dot(n, geom::cross(to_e, to_l)).abs() < 1e-10);
    g
}

fn median(f: &Frame) -> f64 {
    let mut v: Vec<f32> = (0..f.radiance.ncols())
        .flat_map(|j| (0..f.radiance.nrows()).map(move |i| (i, j)))
        .map(|(i, j)| f.radiance[(i, j)])
        .collect();
    v.sort_by(f32::total_cmp);
    v[v.len() / 2] as f64
}

/// Brightness-weighted centre of the pixels above half the maximum within `half` pixels of
/// `at`, and that maximum.
fn blob(f: &Frame, at: [f64; 2], half: i64) -> ([f64; 2], f64) {
    let (h, w) = (f.radiance.nrows() as i64, f.radiance.ncols() as i64);
    let (cx, cy) = (at[0].floor() as i64, at[1].floor() as i64);
    let pix = || {
        (cy - half..=cy + half)
            .flat_map(move |i| (cx - half..=cx + half).map(move |j| (i, j)))
            .filter(move |&(i, j)| i >= 0 && j >= 0 && i < h && j < w)
    };
    let max = pix()
        .map(|(i, j)| f.radiance[(i as usize, j as usize)] as f64)
        .fold(0.0, f64::max);
    let (mut s, mut sx, mut sy) = (0.0, 0.0, 0.0);
    for (i, j) in pix() {
        let v = f.radiance[(i as usize, j as usize)] as f64;
        if v > 0.5 * max {
            s += v;
            sx += v * (j as f64 + 0.5);
            sy += v * (i as f64 + 0.5);
        }
    }
    ([sx / s, sy / s], max)
}

/// The corneal glint of the procedural eye lies at the image of the cornea-sphere point whose
/// normal bisects camera and LED, and outshines the diffuse eye region.
#[test]
fn corneal_glint_lies_where_the_law_of_reflection_puts_the_led() {
    let rig = Rig::default();
    let subject = Subject::default();
    let opts = RenderOptions {
        spp: 4,
        seed: 1,
        ..Default::default()
    };
    for (az, el) in [(-5.0, -3.0), (0.0, 15.0), (10.0, 20.0), (-15.0, 10.0)] {
        let st = state(az, el);
        let pose = st.camera_pose(&rig);
        let light = Light::near_camera(&pose);
        let parts = procedural_parts(&rig, &st, &subject).unwrap();
        let g = parts.geometry;
        let scene = procedural_scene(&rig, &st, &subject, light).unwrap();
        let f = render(&scene, &rig.camera, &pose, &opts).unwrap();
        let diffuse = median(&f);
        // Cornea: its sphere's centre rotates with the eye.
        let c = geom::mul_mv(&parts.rotation, [0.0, 0.0, g.cornea_center_m]);
        let gc = mirror_point(c, g.cornea_radius_m, pose.position, light.position_m);
        let want = project(&rig.camera, &pose, gc);
        let (got, max) = blob(&f, want, 4);
        eprintln!("({az}, {el}): cornea glint {got:?} vs {want:?}, {max} vs median {diffuse}");
        assert!(
            // 10×: the median is lit skin now that the face fills the frame (it was 30× while
            // about half the frame was empty background at zero radiance).
            max > 10.0 * diffuse,
            "({az}, {el}): no glint near {want:?}: {max} vs median {diffuse}"
        );
        let err = geom::norm([got[0] - want[0], got[1] - want[1], 0.0]);
        assert!(
            err < 1.0,
            "({az}, {el}): glint at {got:?}, law of reflection {want:?}"
        );
    }
}

/// Unpolarised Fresnel reflectance from index 1 into `n` at incidence cosine `c`.
fn fresnel_ref(c: f64, n: f64) -> f64 {
    let s = (1.0 - c * c).sqrt() / n;
    let ct = (1.0 - s * s).sqrt();
    let rs = (c - n * ct) / (c + n * ct);
    let rp = (n * c - ct) / (n * c + ct);
    0.5 * (rs * rs + rp * rp)
}

/// The tear film (the wet coat of sclera, lid margin and caruncle): on a wet sphere the LED's
/// mirror image sits where the law of reflection puts it, with the radiance of the emitter
/// times the film's Fresnel reflectance on top of the (1 − F)-weighted diffuse light. A camera
/// with 3 µm pixels at 2 mm focal length resolves the image (~12 px across), so its centre
/// pixel is all glint.
#[test]
fn tear_film_glint_has_the_mirror_position_and_fresnel_radiance() {
    let cam = Camera::look_at(2e-3, 3e-6, 300, 300, [0.0; 3], [0.0, 0.0, 1.0]).unwrap();
    let pose = cam.nominal_pose();
    let (c, r) = ([2e-3, -0.5e-3, 25e-3], 12e-3);
    let light = Light::isotropic([4e-3, 0.0, 0.0], 0.5e-3, 1e-3);
    let wet = Material {
        coat_index: TEAR_FILM_INDEX,
        ..Material::lambertian(MaterialKind::Sclera, 0.5)
    };
    let sphere = Prim {
        shape: Shape::Sphere {
            center: c,
            radius_m: r,
            clip: Clip::None,
        },
        material: 0,
        layer: LAYER_EYE,
    };
    let scene = Scene::new(vec![sphere], vec![wet], light, 1.376).unwrap();
    let opts = RenderOptions {
        spp: 16,
        ..Default::default()
    };
    let f = render(&scene, &cam, &pose, &opts).unwrap();
    let g = mirror_point(c, r, pose.position, light.position_m);
    let want = project(&cam, &pose, g);
    let (got, _) = blob(&f, want, 20);
    let err = geom::norm([got[0] - want[0], got[1] - want[1], 0.0]);
    assert!(
        err < 1.0,
        "tear-film glint at {got:?}, law of reflection {want:?}"
    );
    // Radiance at the centre: F·L_emitter + (1 − F)·diffuse, the diffuse part read 20 px
    // beside the image towards the image centre (the same surface, 1.7° away).
    let px = |q: [f64; 2]| f.radiance[(q[1] as usize, q[0] as usize)] as f64;
    let centre = px(want);
    let side = px([want[0] - 20.0 * (want[0] - 150.0).signum(), want[1]]);
    let cos_i = geom::dot(
        geom::normalize(geom::sub(g, c)),
        geom::normalize(geom::sub(pose.position, g)),
    );
    let fr = fresnel_ref(cos_i, TEAR_FILM_INDEX);
    let expect = fr * light.radiance_toward(g) + (1.0 - fr) * side;
    eprintln!("glint centre {centre}, expected {expect} (F = {fr:.5}), diffuse {side}");
    assert!(centre > 10.0 * side, "no glint: {centre} vs diffuse {side}");
    assert!(
        (centre - expect).abs() < 0.02 * expect,
        "glint radiance {centre} vs F·L + (1 − F)·diffuse = {expect}"
    );
}

/// Pixels whose surface point has a lash between it and the LED are darker than the same
/// pixels with the lashes removed; pixels with no lash towards any part of the LED (and none
/// in their footprint) keep their radiance.
#[test]
fn lashes_shadow_exactly_where_they_block_the_led() {
    let rig = Rig::default();
    let opts = RenderOptions {
        spp: 8,
        seed: 3,
        ..Default::default()
    };
    let with = Subject {
        lash_length_upper_m: 11e-3,
        lash_length_lower_m: 7.5e-3,
        ..Subject::default()
    };
    let without = Subject {
        lashes_upper: 0,
        lashes_lower: 0,
        ..with
    };
    let (mut dark, mut lit) = ((0.0, 0.0, 0usize), (0.0, 0.0, 0usize));
    for (az, el) in [(-5.0, -3.0), (0.0, 10.0), (5.0, -15.0)] {
        let st = state(az, el);
        let pose = st.camera_pose(&rig);
        let light = Light::near_camera(&pose);
        let a = procedural_scene(&rig, &st, &with, light).unwrap();
        let b = procedural_scene(&rig, &st, &without, light).unwrap();
        // The lashes alone, to ask which surface points they hide the LED from.
        let parts = procedural_parts(&rig, &st, &with).unwrap();
        let lash_prims: Vec<Prim> = parts
            .face
            .iter()
            .filter(|p| parts.materials[p.material as usize].kind == MaterialKind::Lash)
            .copied()
            .collect();
        assert!(!lash_prims.is_empty());
        let lashes = Scene::new(lash_prims, parts.materials.clone(), light, 1.376).unwrap();
        let fa = render(&a, &rig.camera, &pose, &opts).unwrap();
        let fb = render(&b, &rig.camera, &pose, &opts).unwrap();
        for i in 0..fa.radiance.nrows() {
            for j in 0..fa.radiance.ncols() {
                let (da, db) = (fa.depth_m[(i, j)], fb.depth_m[(i, j)]);
                // Same first surface (not a lash) and a diffuse one lit by the LED.
                if !(da.is_finite() && da == db) {
                    continue;
                }
                let dir = nanoeye_datagen::render::trace::pixel_dir(
                    &rig.camera,
                    &pose,
                    [j as f64 + 0.5, i as f64 + 0.5],
                );
                let ray = Ray::new(pose.position, dir);
                let h = b.closest(&ray, f64::INFINITY, LAYER_ALL).unwrap();
                let kind = b.material(h.prim).kind;
                if kind == MaterialKind::Cornea || kind == MaterialKind::Pupil {
                    continue;
                }
                let (ra, rb) = (fa.radiance[(i, j)] as f64, fb.radiance[(i, j)] as f64);
                if !(0.05..=5.0).contains(&rb) {
                    continue; // unlit or a glint
                }
                let p = ray.at(h.t);
                let mut n = b.prims[h.prim as usize].shape.normal(p);
                if geom::dot(n, ray.dir) > 0.0 {
                    n = geom::scale(n, -1.0);
                }
                let from = geom::add(p, geom::scale(n, 1e-8));
                let lash_between = |q: Vec3| {
                    let to = geom::sub(q, from);
                    lashes.occluded(&Ray::new(from, to), geom::norm(to), LAYER_ALL)
                };
                // Blocked: a lash on the way to the LED's centre. Clear: none on the way to
                // the centre or to any of 12 points of the disc's rim (so no penumbra), and
                // no lash in the pixel's footprint (its jittered samples see the same surface).
                let blocked = lash_between(light.position_m);
                let w = geom::normalize(geom::sub(light.position_m, from));
                let (e1, e2) = perpendicular_basis(w);
                let clear = !blocked
                    && (0..12).all(|k| {
                        let a = std::f64::consts::TAU * k as f64 / 12.0;
                        let q = geom::add(
                            light.position_m,
                            geom::add(
                                geom::scale(e1, light.radius_m * a.cos()),
                                geom::scale(e2, light.radius_m * a.sin()),
                            ),
                        );
                        !lash_between(q)
                    })
                    && (i.saturating_sub(1)..(i + 2).min(fa.radiance.nrows())).all(|ii| {
                        (j.saturating_sub(1)..(j + 2).min(fa.radiance.ncols()))
                            .all(|jj| fa.depth_m[(ii, jj)] == fb.depth_m[(ii, jj)])
                    });
                if !blocked && !clear {
                    continue;
                }
                let acc = if blocked { &mut dark } else { &mut lit };
                acc.0 += ra;
                acc.1 += rb;
                acc.2 += 1;
            }
        }
    }
    let (rd, rl) = (dark.0 / dark.1, lit.0 / lit.1);
    eprintln!(
        "lash-blocked pixels: {} at {rd:.3} of their lash-free radiance; clear: {} at {rl:.3}",
        dark.2, lit.2
    );
    assert!(
        dark.2 >= 30,
        "too few lash-shadowed pixels to judge: {}",
        dark.2
    );
    assert!(rd < 0.8, "lash shadows too faint: {rd}");
    assert!(
        (0.98..1.02).contains(&rl),
        "pixels the lashes do not shadow changed: {rl}"
    );
}

/// The skin texture varies at its documented scales: smooth below the 0.25 mm pore/wrinkle
/// cell, decorrelated across it, more variance added up to the 1.2 mm blotches, independent
/// beyond; its spread scales with the amplitude.
#[test]
fn skin_micro_texture_has_variance_at_the_stated_scales() {
    let tex = SkinTexture {
        seed: 5,
        amplitude: 0.2,
    };
    let step = 0.01e-3;
    let n = 6000; // 60 mm per line
    let lines: Vec<Vec<f64>> = (0..20)
        .map(|l| {
            let y = 1.7e-3 * l as f64;
            (0..n)
                .map(|k| tex.factor([step * k as f64, y, 0.3e-3 * l as f64]))
                .collect()
        })
        .collect();
    let all: Vec<f64> = lines.iter().flatten().copied().collect();
    let mean = all.iter().sum::<f64>() / all.len() as f64;
    let var = all.iter().map(|f| (f - mean).powi(2)).sum::<f64>() / all.len() as f64;
    let sd = var.sqrt();
    assert!((mean - 1.0).abs() < 0.02, "mean factor {mean}");
    assert!(
        (0.15..0.6).contains(&(sd / tex.amplitude)),
        "spread {sd} for amplitude {}",
        tex.amplitude
    );
    // Structure function over 2σ²: 0 for identical, 1 for independent values.
    let d = |lag_m: f64| {
        let k = (lag_m / step).round() as usize;
        let (mut s, mut c) = (0.0, 0.0);
        for l in &lines {
            for x in 0..n - k {
                s += (l[x + k] - l[x]).powi(2);
                c += 1.0;
            }
        }
        s / c / (2.0 * var)
    };
    let (d_fine, d_cell, d_blotch, d_far) = (d(0.02e-3), d(0.25e-3), d(1.2e-3), d(10e-3));
    eprintln!("D(0.02) {d_fine:.3}  D(0.25) {d_cell:.3}  D(1.2) {d_blotch:.3}  D(10) {d_far:.3}");
    assert!(d_fine < 0.05, "texture not smooth below its cell: {d_fine}");
    assert!(d_cell > 0.3, "no variance at the 0.25 mm scale: {d_cell}");
    assert!(
        d_blotch > d_cell + 0.1,
        "no extra variance up to 1.2 mm: {d_blotch}"
    );
    assert!(
        (0.75..1.25).contains(&d_far),
        "not independent at 10 mm: {d_far}"
    );
    // Amplitude 0 is no texture.
    let flat = SkinTexture {
        seed: 5,
        amplitude: 0.0,
    };
    assert!((0..100).all(|k| flat.factor([1e-4 * k as f64, 0.0, 0.0]) == 1.0));
}

//! glTF 2.0 (GLB) export of the procedural eye region: the face posed for a state, the eye at
//! primary gaze under a node that poses it, the camera and the illuminator, with named
//! materials. Exact analytic spheres and discs ride along in node extras, so loading the file
//! back through [`super::mesh::Mesh`] renders the procedural scene's depth exactly; viewers
//! show the tessellations. Layout: docs/formats.md ("Eye-region glTF").

use super::RenderError;
use super::prim::{Clip, Shape};
use super::scene::{Light, MATERIAL_NAMES, Prim, ProceduralParts, Subject, procedural_parts};
use crate::states::State;
use nanoeye_gaze::{Mat3, Rig, Vec3, geom};
use serde_json::{Value, json};

/// Tessellation of spheres for viewers: latitude bands and longitude segments.
const SPHERE_BANDS: usize = 48;
const SPHERE_SEGMENTS: usize = 96;
/// Segments of a tessellated disc.
const DISC_SEGMENTS: usize = 96;

/// Unit quaternion (x, y, z, w) of rotation matrix `m` (rows).
pub fn quaternion(m: &Mat3) -> [f64; 4] {
    let t = m[0][0] + m[1][1] + m[2][2];
    let q = if t > 0.0 {
        let s = 0.5 / (t + 1.0).sqrt();
        [
            (m[2][1] - m[1][2]) * s,
            (m[0][2] - m[2][0]) * s,
            (m[1][0] - m[0][1]) * s,
            0.25 / s,
        ]
    } else if m[0][0] > m[1][1] && m[0][0] > m[2][2] {
        let s = 2.0 * (1.0 + m[0][0] - m[1][1] - m[2][2]).sqrt();
        [
            0.25 * s,
            (m[0][1] + m[1][0]) / s,
            (m[0][2] + m[2][0]) / s,
            (m[2][1] - m[1][2]) / s,
        ]
    } else if m[1][1] > m[2][2] {
        let s = 2.0 * (1.0 + m[1][1] - m[0][0] - m[2][2]).sqrt();
        [
            (m[0][1] + m[1][0]) / s,
            0.25 * s,
            (m[1][2] + m[2][1]) / s,
            (m[0][2] - m[2][0]) / s,
        ]
    } else {
        let s = 2.0 * (1.0 + m[2][2] - m[0][0] - m[1][1]).sqrt();
        [
            (m[0][2] + m[2][0]) / s,
            (m[1][2] + m[2][1]) / s,
            0.25 * s,
            (m[1][0] - m[0][1]) / s,
        ]
    };
    let n = (q.iter().map(|x| x * x).sum::<f64>()).sqrt();
    q.map(|x| x / n)
}

/// Binary buffer and the JSON arrays that index it.
#[derive(Default)]
struct Builder {
    bin: Vec<u8>,
    views: Vec<Value>,
    accessors: Vec<Value>,
    meshes: Vec<Value>,
}

impl Builder {
    fn view(&mut self, bytes: &[u8], target: u32) -> usize {
        while !self.bin.len().is_multiple_of(4) {
            self.bin.push(0);
        }
        let offset = self.bin.len();
        self.bin.extend_from_slice(bytes);
        self.views.push(
            json!({"buffer": 0, "byteOffset": offset, "byteLength": bytes.len(), "target": target}),
        );
        self.views.len() - 1
    }

    /// One triangle primitive (unshared vertices) as accessors; returns the primitive JSON.
    fn primitive(&mut self, tris: &[[Vec3; 3]], material: usize) -> Value {
        let mut pos = Vec::with_capacity(tris.len() * 36);
        let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
        for t in tris {
            for p in t {
                for a in 0..3 {
                    let x = p[a] as f32;
                    lo[a] = lo[a].min(x);
                    hi[a] = hi[a].max(x);
                    pos.extend_from_slice(&x.to_le_bytes());
                }
            }
        }
        let n = tris.len() * 3;
        let idx: Vec<u8> = (0..n as u32).flat_map(|i| i.to_le_bytes()).collect();
        let pv = self.view(&pos, 34962);
        let iv = self.view(&idx, 34963);
        self.accessors
            .push(json!({"bufferView": pv, "componentType": 5126, "count": n,
            "type": "VEC3", "min": lo, "max": hi}));
        let pa = self.accessors.len() - 1;
        self.accessors
            .push(json!({"bufferView": iv, "componentType": 5125, "count": n, "type": "SCALAR"}));
        let ia = self.accessors.len() - 1;
        json!({"attributes": {"POSITION": pa}, "indices": ia, "material": material, "mode": 4})
    }

    fn mesh(&mut self, name: &str, primitives: Vec<Value>) -> usize {
        self.meshes
            .push(json!({"name": name, "primitives": primitives}));
        self.meshes.len() - 1
    }
}

/// Triangles approximating a (possibly clipped) sphere or disc, for viewers.
fn tessellate(shape: &Shape) -> Vec<[Vec3; 3]> {
    use std::f64::consts::{PI, TAU};
    match *shape {
        Shape::Sphere {
            center,
            radius_m,
            clip,
        } => {
            let pt = |i: usize, j: usize| {
                let th = PI * i as f64 / SPHERE_BANDS as f64;
                let ph = TAU * j as f64 / SPHERE_SEGMENTS as f64;
                geom::add(
                    center,
                    geom::scale(
                        [th.sin() * ph.cos(), th.sin() * ph.sin(), th.cos()],
                        radius_m,
                    ),
                )
            };
            let keep = |t: &[Vec3; 3]| match clip {
                Clip::None => true,
                Clip::Plane {
                    normal,
                    offset_m,
                    sign,
                } => {
                    let c = geom::scale(geom::add(geom::add(t[0], t[1]), t[2]), 1.0 / 3.0);
                    sign * (geom::dot(normal, c) - offset_m) >= 0.0
                }
            };
            let mut out = Vec::new();
            for i in 0..SPHERE_BANDS {
                for j in 0..SPHERE_SEGMENTS {
                    let (a, b, c, d) = (pt(i, j), pt(i, j + 1), pt(i + 1, j), pt(i + 1, j + 1));
                    for t in [[a, c, d], [a, d, b]] {
                        if keep(&t) {
                            out.push(t);
                        }
                    }
                }
            }
            out
        }
        Shape::Disc {
            center,
            normal,
            r_in_m,
            r_out_m,
        } => {
            let (e1, e2) = super::prim::perpendicular_basis(normal);
            let pt = |r: f64, k: usize| {
                let ph = TAU * k as f64 / DISC_SEGMENTS as f64;
                geom::add(
                    center,
                    geom::add(geom::scale(e1, r * ph.cos()), geom::scale(e2, r * ph.sin())),
                )
            };
            let mut out = Vec::new();
            for k in 0..DISC_SEGMENTS {
                let (o0, o1) = (pt(r_out_m, k), pt(r_out_m, k + 1));
                if r_in_m > 0.0 {
                    let (i0, i1) = (pt(r_in_m, k), pt(r_in_m, k + 1));
                    out.push([i0, o0, o1]);
                    out.push([i0, o1, i1]);
                } else {
                    out.push([center, o0, o1]);
                }
            }
            out
        }
        Shape::Triangle { v } => vec![v],
    }
}

/// The exact definition of an analytic shape for `extras.nanoeye` (m).
fn shape_extras(shape: &Shape) -> Option<Value> {
    match *shape {
        Shape::Sphere {
            center,
            radius_m,
            clip,
        } => {
            let clip = match clip {
                Clip::None => Value::Null,
                Clip::Plane {
                    normal,
                    offset_m,
                    sign,
                } => json!({"normal": normal, "offset": offset_m, "sign": sign}),
            };
            Some(json!({"sphere": {"center": center, "radius": radius_m, "clip": clip}}))
        }
        Shape::Disc {
            center,
            normal,
            r_in_m,
            r_out_m,
        } => Some(
            json!({"disc": {"center": center, "normal": normal, "r_in": r_in_m, "r_out": r_out_m}}),
        ),
        Shape::Triangle { .. } => None,
    }
}

/// The glTF materials of the procedural scene (grey base colour = NIR albedo).
fn materials(parts: &ProceduralParts) -> Vec<Value> {
    parts
        .materials
        .iter()
        .zip(MATERIAL_NAMES)
        .map(|(m, name)| {
            let wet = m.coat_index > 0.0 || name == "cornea";
            let alpha = if name == "cornea" { 0.15 } else { 1.0 };
            let a = m.albedo as f32;
            let mut v = json!({
                "name": name,
                "doubleSided": true,
                "pbrMetallicRoughness": {
                    "baseColorFactor": [a, a, a, alpha],
                    "metallicFactor": 0.0,
                    "roughnessFactor": if wet { 0.1 } else { 0.6 },
                },
                "extras": {"nanoeye_material": {"albedo_940nm": m.albedo, "coat_index": m.coat_index}},
            });
            if name == "cornea" {
                v["alphaMode"] = json!("BLEND");
            }
            v
        })
        .collect()
}

/// Writes the procedural eye region of `subject` in `state`, seen by `rig`'s camera at the
/// state's pose and lit by `light`, as a GLB file's bytes.
pub fn export_glb(
    rig: &Rig,
    state: &State,
    subject: &Subject,
    light: &Light,
) -> Result<Vec<u8>, RenderError> {
    let parts = procedural_parts(rig, state, subject)?;
    let pose = state.camera_pose(rig);
    let mut b = Builder::default();
    let mut nodes: Vec<Value> = Vec::new();
    let mut root: Vec<usize> = Vec::new();

    // Face triangles grouped by material, one mesh; analytic face parts as their own nodes.
    let mut by_material: Vec<Vec<[Vec3; 3]>> = vec![Vec::new(); parts.materials.len()];
    let mut face_children = Vec::new();
    for p in &parts.face {
        match p.shape {
            Shape::Triangle { v } => by_material[p.material as usize].push(v),
            _ => face_children.push(analytic_node(&mut b, &mut nodes, p)),
        }
    }
    let prims: Vec<Value> = by_material
        .iter()
        .enumerate()
        .filter(|(_, t)| !t.is_empty())
        .map(|(m, t)| b.primitive(t, m))
        .collect();
    let face_mesh = b.mesh("face", prims);
    nodes.push(json!({"name": "face", "mesh": face_mesh, "children": face_children}));
    root.push(nodes.len() - 1);

    // The eye at primary gaze under the node that poses it.
    let eye_children: Vec<usize> = parts
        .eye_rest
        .iter()
        .map(|p| analytic_node(&mut b, &mut nodes, p))
        .collect();
    nodes.push(json!({
        "name": "eye",
        "rotation": quaternion(&parts.rotation),
        "children": eye_children,
        "extras": {"nanoeye": {"role": "eye_pose"}},
    }));
    root.push(nodes.len() - 1);

    // Camera: glTF cameras look along −z with +y up; ours along +z with +y down.
    let flip = [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]];
    let cam_rot = geom::mul_mm(&pose.rotation, &flip);
    let c = &rig.camera;
    let (w, h) = (c.width_px as f64, c.height_px as f64);
    nodes.push(json!({
        "name": "camera",
        "camera": 0,
        "translation": pose.position,
        "rotation": quaternion(&cam_rot),
        "extras": {"nanoeye_camera": {"fx_px": c.fx_px, "fy_px": c.fy_px, "cx_px": c.cx_px,
            "cy_px": c.cy_px, "width_px": c.width_px, "height_px": c.height_px,
            "frame": "OpenCV (x right, y down, z forward); this node's axes are glTF's"}},
    }));
    root.push(nodes.len() - 1);
    nodes.push(json!({
        "name": "illuminator",
        "translation": light.position_m,
        "extensions": {"KHR_lights_punctual": {"light": 0}},
        "extras": {"nanoeye_light": {"radius_m": light.radius_m,
            "intensity_w_per_sr": light.intensity_w_per_sr, "wavelength_m": 940e-9}},
    }));
    root.push(nodes.len() - 1);

    let doc = json!({
        "asset": {"version": "2.0", "generator": "nanoeye datagen export"},
        "extensionsUsed": ["KHR_lights_punctual"],
        "extensions": {"KHR_lights_punctual": {"lights": [{
            "name": "nir_illuminator", "type": "point", "color": [1.0, 1.0, 1.0],
            // 940 nm has no luminous efficacy; viewers get the radiant intensity × 683 lm/W.
            "intensity": light.intensity_w_per_sr * 683.0,
        }]}},
        "scene": 0,
        "scenes": [{"name": "eye_region", "nodes": root,
            "extras": {"nanoeye_state": state, "nanoeye_subject": subject,
                "nanoeye_units": "metres; eye frame of docs/renderer.md"}}],
        "nodes": nodes,
        "meshes": b.meshes,
        "materials": materials(&parts),
        "cameras": [{"name": "eye_camera", "type": "perspective", "perspective": {
            "yfov": 2.0 * (0.5 * h / c.fy_px).atan(),
            "aspectRatio": (w / c.fx_px) / (h / c.fy_px),
            "znear": 1e-3, "zfar": 1.0}}],
        "accessors": b.accessors,
        "bufferViews": b.views,
        "buffers": [{"byteLength": b.bin.len()}],
    });
    Ok(glb(&doc, b.bin))
}

/// A node holding an analytic primitive: its tessellation for viewers and the exact shape in
/// extras.
fn analytic_node(b: &mut Builder, nodes: &mut Vec<Value>, p: &Prim) -> usize {
    let name = MATERIAL_NAMES[p.material as usize];
    let prim = b.primitive(&tessellate(&p.shape), p.material as usize);
    let mesh = b.mesh(name, vec![prim]);
    let mut node = json!({"name": name, "mesh": mesh});
    if let Some(x) = shape_extras(&p.shape) {
        node["extras"] = json!({"nanoeye": x});
    }
    nodes.push(node);
    nodes.len() - 1
}

/// GLB container: 12-byte header, JSON chunk (space-padded), BIN chunk (zero-padded).
fn glb(doc: &Value, mut bin: Vec<u8>) -> Vec<u8> {
    let mut js = doc.to_string().into_bytes();
    while !js.len().is_multiple_of(4) {
        js.push(b' ');
    }
    while !bin.len().is_multiple_of(4) {
        bin.push(0);
    }
    let total = 12 + 8 + js.len() + 8 + bin.len();
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(b"glTF");
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&(total as u32).to_le_bytes());
    out.extend_from_slice(&(js.len() as u32).to_le_bytes());
    out.extend_from_slice(b"JSON");
    out.extend_from_slice(&js);
    out.extend_from_slice(&(bin.len() as u32).to_le_bytes());
    out.extend_from_slice(b"BIN\0");
    out.extend_from_slice(&bin);
    out
}

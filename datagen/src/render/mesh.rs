//! User meshes: OBJ (tobj) and glTF/GLB (gltf), metres or millimetres, materials mapped onto
//! the documented set by name ([`MaterialKind::from_name`]).

use super::RenderError;
use super::material::{Material, MaterialKind};
use super::prim::{Clip, Shape};
use super::scene::{Light, Prim, Scene, layer_of, rotate_shape};
use crate::states::State;
use nanoeye_gaze::{Vec3, geom};
use std::path::Path;

/// Length unit of a mesh file's coordinates.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MeshUnits {
    /// Metres.
    Metres,
    /// Millimetres.
    Millimetres,
}

impl MeshUnits {
    fn scale(self) -> f64 {
        match self {
            MeshUnits::Metres => 1.0,
            MeshUnits::Millimetres => 1e-3,
        }
    }
}

/// A triangle mesh in the eye frame at primary gaze (m), one material class per triangle,
/// plus the analytic primitives a glTF file names in its nodes' extras (docs/formats.md).
#[derive(Debug, Clone, Default)]
pub struct Mesh {
    /// Triangles (vertices in m).
    pub triangles: Vec<[Vec3; 3]>,
    /// Class of each triangle.
    pub kinds: Vec<MaterialKind>,
    /// Analytic spheres and discs (m) with their class.
    pub shapes: Vec<(Shape, MaterialKind)>,
}

/// What a glTF node's `extras.nanoeye` says (docs/formats.md).
#[derive(Debug, serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct NodeExtras {
    /// "eye_pose": the node's own transform poses the eye for viewers; loading ignores it,
    /// since the renderer poses the eye from each state.
    #[serde(default)]
    role: Option<String>,
    /// An exact sphere replacing the node's tessellation.
    #[serde(default)]
    sphere: Option<SphereExtras>,
    /// An exact disc or annulus replacing the node's tessellation.
    #[serde(default)]
    disc: Option<DiscExtras>,
}

#[derive(Debug, serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct SphereExtras {
    center: [f64; 3],
    radius: f64,
    /// Keeps the points p with sign·(normal·p − offset) ≥ 0.
    #[serde(default)]
    clip: Option<PlaneExtras>,
}

#[derive(Debug, serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct PlaneExtras {
    normal: [f64; 3],
    offset: f64,
    sign: f64,
}

#[derive(Debug, serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct DiscExtras {
    center: [f64; 3],
    normal: [f64; 3],
    r_in: f64,
    r_out: f64,
}

#[derive(Debug, serde::Deserialize)]
struct Extras {
    #[serde(default)]
    nanoeye: Option<NodeExtras>,
}

/// The analytic shape of `x` under world transform `m` (rigid, else an error) in units `s`.
fn analytic_shape(
    x: &NodeExtras,
    m: &[[f64; 4]; 4],
    s: f64,
    name: &str,
) -> Result<Option<Shape>, RenderError> {
    if x.sphere.is_none() && x.disc.is_none() {
        return Ok(None);
    }
    // Columns of the linear part must be orthonormal: spheres and discs stay what they are.
    for a in 0..3 {
        for b in 0..3 {
            let d: f64 = (0..3).map(|r| m[a][r] * m[b][r]).sum();
            let want = if a == b { 1.0 } else { 0.0 };
            if (d - want).abs() > 1e-5 {
                return Err(mesh_err(
                    name,
                    "an analytic shape (extras.nanoeye) sits under a non-rigid transform",
                ));
            }
        }
    }
    let point = |p: [f64; 3]| geom::scale(apply4(m, p), s);
    let dir = |v: [f64; 3]| {
        let d = [0, 1, 2].map(|r| m[0][r] * v[0] + m[1][r] * v[1] + m[2][r] * v[2]);
        // A unit normal stays bit for bit what the file says (exact round trips).
        let n = geom::norm(d);
        if (n - 1.0).abs() < 1e-12 {
            d
        } else {
            geom::scale(d, 1.0 / n)
        }
    };
    let finite = |v: &[f64]| v.iter().all(|x| x.is_finite());
    let shape = if let Some(sp) = &x.sphere {
        if !(finite(&sp.center) && sp.radius.is_finite() && sp.radius > 0.0) {
            return Err(mesh_err(
                name,
                "extras.nanoeye.sphere: non-finite or non-positive",
            ));
        }
        let clip = match &sp.clip {
            None => Clip::None,
            Some(c) => {
                if !(finite(&c.normal) && c.offset.is_finite() && (c.sign == 1.0 || c.sign == -1.0))
                    || geom::norm(c.normal) == 0.0
                {
                    return Err(mesh_err(name, "extras.nanoeye.sphere.clip: bad plane"));
                }
                let n = dir(c.normal);
                // The plane n·p = offset moves with the transform's translation.
                let t = [m[3][0], m[3][1], m[3][2]];
                Clip::Plane {
                    normal: n,
                    offset_m: (c.offset + geom::dot(n, t)) * s,
                    sign: c.sign,
                }
            }
        };
        Shape::Sphere {
            center: point(sp.center),
            radius_m: sp.radius * s,
            clip,
        }
    } else if let Some(d) = &x.disc {
        if !(finite(&d.center)
            && finite(&d.normal)
            && geom::norm(d.normal) > 0.0
            && d.r_in.is_finite()
            && d.r_out.is_finite()
            && 0.0 <= d.r_in
            && d.r_in < d.r_out)
        {
            return Err(mesh_err(
                name,
                "extras.nanoeye.disc: need finite 0 ≤ r_in < r_out",
            ));
        }
        Shape::Disc {
            center: point(d.center),
            normal: dir(d.normal),
            r_in_m: d.r_in * s,
            r_out_m: d.r_out * s,
        }
    } else {
        return Ok(None);
    };
    Ok(Some(shape))
}

/// Largest triangle count accepted (guards memory on hostile files).
pub const MAX_TRIANGLES: usize = 20_000_000;

fn mesh_err(path: &str, reason: impl std::fmt::Display) -> RenderError {
    RenderError::Mesh {
        path: path.to_string(),
        reason: reason.to_string(),
    }
}

impl Mesh {
    /// Loads `.obj`, `.gltf` or `.glb` by extension.
    pub fn load(path: &Path, units: MeshUnits) -> Result<Mesh, RenderError> {
        let name = path.display().to_string();
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(|e| e.to_ascii_lowercase());
        let bytes = std::fs::read(path).map_err(|e| mesh_err(&name, e))?;
        match ext.as_deref() {
            Some("obj") => {
                let dir = path.parent().map(Path::to_path_buf).unwrap_or_default();
                Mesh::from_obj_bytes(&bytes, units, &name, Some(&dir))
            }
            Some("gltf") | Some("glb") => {
                // External buffers resolve relative to the file, so use the path-based importer.
                let r = std::panic::catch_unwind(|| gltf::import(path));
                match r {
                    Ok(Ok((doc, buffers, _))) => Mesh::from_gltf_doc(&doc, &buffers, units, &name),
                    Ok(Err(e)) => Err(mesh_err(&name, e)),
                    Err(_) => Err(mesh_err(&name, "glTF importer failed on malformed data")),
                }
            }
            _ => Err(mesh_err(
                &name,
                "unknown extension (expected .obj, .gltf or .glb)",
            )),
        }
    }

    /// Parses OBJ text; `.mtl` libraries are looked up in `mtl_dir` (none: materials come from
    /// object names only).
    pub fn from_obj_bytes(
        bytes: &[u8],
        units: MeshUnits,
        name: &str,
        mtl_dir: Option<&Path>,
    ) -> Result<Mesh, RenderError> {
        let opts = tobj::LoadOptions {
            triangulate: true,
            single_index: false,
            ignore_points: true,
            ignore_lines: true,
        };
        let mut reader = std::io::BufReader::new(bytes);
        let loaded = std::panic::catch_unwind(move || {
            tobj::load_obj_buf(&mut reader, &opts, |p| match mtl_dir {
                Some(d) => tobj::load_mtl(d.join(p)),
                None => Err(tobj::LoadError::OpenFileFailed),
            })
        });
        let (models, materials) = match loaded {
            Ok(Ok(x)) => x,
            Ok(Err(e)) => return Err(mesh_err(name, e)),
            Err(_) => return Err(mesh_err(name, "OBJ parser failed on malformed data")),
        };
        let materials = materials.unwrap_or_default();
        let s = units.scale();
        let mut mesh = Mesh::default();
        for m in &models {
            let label = m
                .mesh
                .material_id
                .and_then(|i| materials.get(i))
                .map(|mt| mt.name.clone())
                .unwrap_or_else(|| m.name.clone());
            let kind = MaterialKind::from_name(&label);
            let pos = &m.mesh.positions;
            let idx = &m.mesh.indices;
            if idx.len() % 3 != 0 {
                return Err(mesh_err(
                    name,
                    format!("object {}: index count not a multiple of 3", m.name),
                ));
            }
            for tri in idx.chunks_exact(3) {
                let mut v = [[0.0; 3]; 3];
                for (k, &i) in tri.iter().enumerate() {
                    let i = i as usize;
                    let p = pos
                        .get(3 * i..3 * i + 3)
                        .ok_or_else(|| mesh_err(name, format!("vertex index {i} out of range")))?;
                    v[k] = [p[0] as f64 * s, p[1] as f64 * s, p[2] as f64 * s];
                }
                mesh.push(v, kind, name)?;
            }
        }
        mesh.finish(name)
    }

    /// Parses a self-contained glTF (embedded data URIs) or GLB from bytes.
    pub fn from_gltf_bytes(
        bytes: &[u8],
        units: MeshUnits,
        name: &str,
    ) -> Result<Mesh, RenderError> {
        match std::panic::catch_unwind(|| gltf::import_slice(bytes)) {
            Ok(Ok((doc, buffers, _))) => Mesh::from_gltf_doc(&doc, &buffers, units, name),
            Ok(Err(e)) => Err(mesh_err(name, e)),
            Err(_) => Err(mesh_err(name, "glTF importer failed on malformed data")),
        }
    }

    fn from_gltf_doc(
        doc: &gltf::Document,
        buffers: &[gltf::buffer::Data],
        units: MeshUnits,
        name: &str,
    ) -> Result<Mesh, RenderError> {
        let s = units.scale();
        let mut mesh = Mesh::default();
        let scene = doc.default_scene().or_else(|| doc.scenes().next());
        let mut stack: Vec<(gltf::Node, [[f64; 4]; 4])> = match scene {
            Some(sc) => sc.nodes().map(|n| (n, IDENTITY4)).collect(),
            None => doc.nodes().map(|n| (n, IDENTITY4)).collect(),
        };
        let mut visited = 0usize;
        while let Some((node, parent)) = stack.pop() {
            visited += 1;
            if visited > 1_000_000 {
                return Err(mesh_err(name, "node hierarchy too large or cyclic"));
            }
            let extras: Option<NodeExtras> = match node.extras() {
                Some(raw) => {
                    serde_json::from_str::<Extras>(raw.get())
                        .map_err(|e| mesh_err(name, format!("node extras: {e}")))?
                        .nanoeye
                }
                None => None,
            };
            let pose_only = extras.as_ref().and_then(|x| x.role.as_deref()) == Some("eye_pose");
            let local = node.transform().matrix().map(|c| c.map(|x| x as f64));
            let world = if pose_only {
                parent
            } else {
                mul4(&parent, &local)
            };
            for c in node.children() {
                stack.push((c, world));
            }
            let Some(gm) = node.mesh() else { continue };
            if let Some(shape) = match &extras {
                Some(x) => analytic_shape(x, &world, s, name)?,
                None => None,
            } {
                let label = gm
                    .primitives()
                    .next()
                    .and_then(|p| p.material().name().map(str::to_string))
                    .or_else(|| gm.name().map(str::to_string))
                    .or_else(|| node.name().map(str::to_string))
                    .unwrap_or_default();
                mesh.shapes.push((shape, MaterialKind::from_name(&label)));
                continue;
            }
            for prim in gm.primitives() {
                if prim.mode() != gltf::mesh::Mode::Triangles {
                    continue;
                }
                let label = prim
                    .material()
                    .name()
                    .map(str::to_string)
                    .or_else(|| gm.name().map(str::to_string))
                    .or_else(|| node.name().map(str::to_string))
                    .unwrap_or_default();
                let kind = MaterialKind::from_name(&label);
                let reader = prim.reader(|b| buffers.get(b.index()).map(|d| d.0.as_slice()));
                let positions: Vec<[f32; 3]> = match reader.read_positions() {
                    Some(p) => p.collect(),
                    None => return Err(mesh_err(name, "triangle primitive without POSITION")),
                };
                let indices: Vec<u32> = match reader.read_indices() {
                    Some(i) => i.into_u32().collect(),
                    None => (0..positions.len() as u32).collect(),
                };
                for tri in indices.chunks_exact(3) {
                    let mut v = [[0.0; 3]; 3];
                    for (k, &i) in tri.iter().enumerate() {
                        let p = positions.get(i as usize).ok_or_else(|| {
                            mesh_err(name, format!("vertex index {i} out of range"))
                        })?;
                        let q = apply4(&world, [p[0] as f64, p[1] as f64, p[2] as f64]);
                        v[k] = geom::scale(q, s);
                    }
                    mesh.push(v, kind, name)?;
                }
            }
        }
        mesh.finish(name)
    }

    fn push(&mut self, v: [Vec3; 3], kind: MaterialKind, name: &str) -> Result<(), RenderError> {
        if !v.iter().all(|p| geom::is_finite(*p)) {
            return Err(mesh_err(name, "non-finite vertex coordinate"));
        }
        if self.triangles.len() >= MAX_TRIANGLES {
            return Err(mesh_err(
                name,
                format!("more than {MAX_TRIANGLES} triangles"),
            ));
        }
        self.triangles.push(v);
        self.kinds.push(kind);
        Ok(())
    }

    fn finish(self, name: &str) -> Result<Mesh, RenderError> {
        if self.triangles.is_empty() && self.shapes.is_empty() {
            return Err(mesh_err(name, "no triangles"));
        }
        Ok(self)
    }

    /// The scene of this mesh in `state`: triangles and shapes of eye classes (sclera, iris,
    /// pupil, cornea) rotate with the eye about the world origin; skin and lashes stay put.
    pub fn scene(
        &self,
        state: &State,
        light: Light,
        cornea_index: f64,
    ) -> Result<Scene, RenderError> {
        let r = state.eye_rotation()?;
        let kinds = [
            MaterialKind::Skin,
            MaterialKind::Sclera,
            MaterialKind::Iris,
            MaterialKind::Pupil,
            MaterialKind::Cornea,
            MaterialKind::Lash,
        ];
        let albedo = [0.5, 0.6, 0.3, 0.02, 0.0, 0.1];
        let materials = kinds
            .iter()
            .zip(albedo)
            .map(|(&kind, albedo)| Material::lambertian(kind, albedo))
            .collect();
        let slot = |kind: MaterialKind| kinds.iter().position(|k| *k == kind).unwrap_or(0) as u16;
        let prims = self
            .triangles
            .iter()
            .zip(&self.kinds)
            .map(|(t, &kind)| (Shape::Triangle { v: *t }, kind))
            .chain(self.shapes.iter().copied())
            .map(|(shape, kind)| Prim {
                shape: if kind.is_eye() {
                    rotate_shape(&shape, &r)
                } else {
                    shape
                },
                material: slot(kind),
                layer: layer_of(kind),
            })
            .collect();
        Scene::new(prims, materials, light, cornea_index)
    }
}

const IDENTITY4: [[f64; 4]; 4] = [
    [1.0, 0.0, 0.0, 0.0],
    [0.0, 1.0, 0.0, 0.0],
    [0.0, 0.0, 1.0, 0.0],
    [0.0, 0.0, 0.0, 1.0],
];

// glTF matrices are column-major: m[col][row].
fn mul4(a: &[[f64; 4]; 4], b: &[[f64; 4]; 4]) -> [[f64; 4]; 4] {
    let mut c = [[0.0; 4]; 4];
    for (col, cc) in c.iter_mut().enumerate() {
        for (row, x) in cc.iter_mut().enumerate() {
            *x = (0..4).map(|k| a[k][row] * b[col][k]).sum();
        }
    }
    c
}

fn apply4(m: &[[f64; 4]; 4], p: Vec3) -> Vec3 {
    [0, 1, 2].map(|r| m[0][r] * p[0] + m[1][r] * p[1] + m[2][r] * p[2] + m[3][r])
}

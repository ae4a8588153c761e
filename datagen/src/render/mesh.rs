//! User meshes: OBJ (tobj) and glTF/GLB (gltf), metres or millimetres, materials mapped onto
//! the documented set by name ([`MaterialKind::from_name`]).

use super::RenderError;
use super::material::{Material, MaterialKind};
use super::prim::Shape;
use super::scene::{Light, Prim, Scene, layer_of};
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

/// A triangle mesh in the eye frame at primary gaze (m), one material class per triangle.
#[derive(Debug, Clone, Default)]
pub struct Mesh {
    /// Triangles (vertices in m).
    pub triangles: Vec<[Vec3; 3]>,
    /// Class of each triangle.
    pub kinds: Vec<MaterialKind>,
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
            let local = node.transform().matrix().map(|c| c.map(|x| x as f64));
            let world = mul4(&parent, &local);
            for c in node.children() {
                stack.push((c, world));
            }
            let Some(gm) = node.mesh() else { continue };
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
        if self.triangles.is_empty() {
            return Err(mesh_err(name, "no triangles"));
        }
        Ok(self)
    }

    /// The scene of this mesh in `state`: triangles of eye classes (sclera, iris, pupil,
    /// cornea) rotate with the eye about the world origin; skin stays put.
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
        ];
        let albedo = [0.5, 0.65, 0.3, 0.02, 0.0];
        let materials = kinds
            .iter()
            .zip(albedo)
            .map(|(&kind, albedo)| Material {
                kind,
                albedo,
                iris: None,
            })
            .collect();
        let prims = self
            .triangles
            .iter()
            .zip(&self.kinds)
            .map(|(t, &kind)| {
                let v = if kind.is_eye() {
                    t.map(|p| geom::mul_mv(&r, p))
                } else {
                    *t
                };
                Prim {
                    shape: Shape::Triangle { v },
                    material: kinds.iter().position(|k| *k == kind).unwrap_or(0) as u16,
                    layer: layer_of(kind),
                }
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

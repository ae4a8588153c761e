//! User meshes: OBJ (tobj) and glTF/GLB (gltf), metres or millimetres, materials mapped onto
//! the documented set by name ([`MaterialKind::from_name`]).

use super::RenderError;
use super::material::{Material, MaterialKind};
use super::prim::{Clip, Shape};
use super::scene::{Light, Prim, Scene, layer_of, rotate_shape};
use crate::states::State;
use nanoeye_gaze::{Vec3, geom};
use std::path::{Path, PathBuf};

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
            // Scaled by its largest component first: |n|² of [1.7e308, 1.7e308, 0] overflowed
            // and the disc's normal became [0, 0, 0].
            let big = d.iter().fold(0.0f64, |a, x| a.max(x.abs()));
            let d = geom::scale(d, 1.0 / big);
            geom::scale(d, 1.0 / geom::norm(d))
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
                    || c.normal.iter().all(|&x| x == 0.0)
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
        // A normal of zero length, or one whose components underflow to it.
        if !(finite(&d.normal) && d.normal.iter().any(|&c| c != 0.0)) {
            return Err(mesh_err(
                name,
                "extras.nanoeye.disc: need a finite non-zero normal",
            ));
        }
        if !(finite(&d.center)
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

/// Largest mesh file read (bytes): 20 M triangles of OBJ text are about 2 GB.
const MAX_MESH_BYTES: u64 = 4 << 30;
/// Largest material library (`.mtl`) read (bytes).
const MAX_MTL_BYTES: u64 = 16 << 20;

/// The bytes of a regular file of at most `max` bytes (a FIFO blocked the read, `/dev/zero`
/// was read until memory ran out), or why not.
fn read_regular(path: &Path, max: u64) -> Result<Vec<u8>, String> {
    let meta = std::fs::metadata(path).map_err(|e| e.to_string())?;
    if !meta.is_file() {
        return Err("not a regular file".into());
    }
    if meta.len() > max {
        return Err(format!("{} bytes, more than {max}", meta.len()));
    }
    std::fs::read(path).map_err(|e| e.to_string())
}

/// A URI's percent-escapes decoded as the glTF importer decodes them (an escape that is not
/// two hex digits stays as it is); None where the result is not UTF-8 (the importer
/// panicked on `%FF%FE.bin`).
fn percent_decoded(uri: &str) -> Option<String> {
    let b = uri.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        let hex = |c: u8| (c as char).to_digit(16);
        match (
            b[i],
            b.get(i + 1).copied().and_then(hex),
            b.get(i + 2).copied().and_then(hex),
        ) {
            (b'%', Some(h), Some(l)) => {
                out.push((h * 16 + l) as u8);
                i += 3;
            }
            (c, _, _) => {
                out.push(c);
                i += 1;
            }
        }
    }
    String::from_utf8(out).ok()
}

/// A glTF or GLB's document and buffers, its images left alone (nothing here uses them; a
/// corrupt texture failed a valid mesh). An external buffer (resolved from `base`) must be a
/// regular file no longer than its `byteLength` and 1 MiB of slack: the importer read any
/// file whole, whatever length the buffer declared (a 44-byte buffer over a 5 GB file aborted
/// the process) and followed FIFOs and `/dev/zero`. Without `base`, external references are
/// an error. Panics of the parser on malformed data are caught by the caller.
fn gltf_parts(
    bytes: &[u8],
    base: Option<&Path>,
    name: &str,
) -> Result<(gltf::Document, Vec<gltf::buffer::Data>), RenderError> {
    // From the bytes already read: the path-based reader allocated a GLB header's claimed
    // length (a 624-byte file claiming 4 GiB aborted the process).
    let g = gltf::Gltf::from_slice(bytes).map_err(|e| mesh_err(name, e))?;
    let mut blob = g.blob;
    let doc = g.document;
    let mut buffers = Vec::with_capacity(doc.buffers().len());
    for b in doc.buffers() {
        let fail = |why: String| mesh_err(name, format!("buffer {}: {why}", b.index()));
        if let (gltf::buffer::Source::Uri(uri), Some(base)) = (b.source(), base) {
            let file = if let Some(p) = uri.strip_prefix("file://").or(uri.strip_prefix("file:")) {
                Some(PathBuf::from(p))
            } else if uri.contains(':') {
                None // data: URIs (bounded by the file), or a scheme the importer refuses
            } else {
                let rel = percent_decoded(uri)
                    .ok_or_else(|| fail(format!("uri '{uri}' is not UTF-8 once decoded")))?;
                Some(base.join(rel))
            };
            if let Some(file) = file {
                let meta = std::fs::metadata(&file).map_err(|e| fail(format!("{uri}: {e}")))?;
                let most = b.length() as u64 + (1 << 20);
                if !meta.is_file() || meta.len() > most {
                    return Err(fail(format!(
                        "{uri}: not a regular file of at most its byteLength {} (+1 MiB)",
                        b.length()
                    )));
                }
            }
        }
        let data = gltf::buffer::Data::from_source_and_blob(b.source(), base, &mut blob)
            .map_err(|e| fail(e.to_string()))?;
        if data.len() < b.length() {
            return Err(fail(format!(
                "{} bytes, its byteLength says {}",
                data.len(),
                b.length()
            )));
        }
        buffers.push(data);
    }
    Ok((doc, buffers))
}

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
        let bytes = read_regular(path, MAX_MESH_BYTES).map_err(|e| mesh_err(&name, e))?;
        let dir = path.parent().map(Path::to_path_buf).unwrap_or_default();
        match ext.as_deref() {
            Some("obj") => Mesh::from_obj_bytes(&bytes, units, &name, Some(&dir)),
            Some("gltf") | Some("glb") => {
                // External buffers resolve relative to the file.
                let r = std::panic::catch_unwind(|| gltf_parts(&bytes, Some(&dir), &name));
                match r {
                    Ok(Ok((doc, buffers))) => Mesh::from_gltf_doc(&doc, &buffers, units, &name),
                    Ok(Err(e)) => Err(e),
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
        // A material library is read as the mesh is: a regular file of bounded size (a FIFO
        // blocked, `/dev/zero` aborted the process), and one that cannot be read is an error
        // naming it (every triangle was classed by object name alone, silently).
        let mtl_error = std::cell::RefCell::new(None::<RenderError>);
        let loaded = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            tobj::load_obj_buf(&mut reader, &opts, |p| {
                let Some(d) = mtl_dir else {
                    return Err(tobj::LoadError::OpenFileFailed);
                };
                match read_regular(&d.join(p), MAX_MTL_BYTES) {
                    Ok(b) => tobj::load_mtl_buf(&mut std::io::BufReader::new(&b[..])),
                    Err(e) => {
                        let why = format!("mtllib {}: {e}", p.display());
                        *mtl_error.borrow_mut() = Some(mesh_err(name, why));
                        Err(tobj::LoadError::OpenFileFailed)
                    }
                }
            })
        }));
        let (models, materials) = match loaded {
            Ok(Ok(x)) => x,
            Ok(Err(e)) => return Err(mesh_err(name, e)),
            Err(_) => return Err(mesh_err(name, "OBJ parser failed on malformed data")),
        };
        if let Some(e) = mtl_error.into_inner() {
            return Err(e);
        }
        let materials = materials.map_err(|e| mesh_err(name, format!("mtllib: {e}")))?;
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
        match std::panic::catch_unwind(|| gltf_parts(bytes, None, name)) {
            Ok(Ok((doc, buffers))) => Mesh::from_gltf_doc(&doc, &buffers, units, name),
            Ok(Err(e)) => Err(e),
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
        // glTF's nodes form disjoint trees (2.0 spec, 3.5.3): a node under two parents, or a
        // scene's root that is also a child, would be drawn twice per path — 20 levels of
        // [child, child] in a 1.4 KB file asked for 2.4 GB of triangles.
        let scene = doc.default_scene().or_else(|| doc.scenes().next());
        let mut parents = vec![0usize; doc.nodes().len()];
        for n in doc.nodes() {
            for c in n.children() {
                parents[c.index()] += 1;
            }
        }
        // The roots: the scene's, or without a scene every node no other node holds.
        let roots: Vec<gltf::Node> = match scene {
            Some(sc) => sc.nodes().collect(),
            None => doc.nodes().filter(|n| parents[n.index()] == 0).collect(),
        };
        for n in &roots {
            parents[n.index()] += 1;
        }
        if let Some(i) = parents.iter().position(|&k| k > 1) {
            return Err(mesh_err(
                name,
                format!("node {i} has more than one parent (glTF nodes form disjoint trees)"),
            ));
        }
        let mut stack: Vec<(gltf::Node, [[f64; 4]; 4])> =
            roots.into_iter().map(|n| (n, IDENTITY4)).collect();
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
                // Counts checked before the reader collects them: a sparse accessor of 760
                // bytes claimed 3e9 positions (36 GB asked for at once).
                for a in prim
                    .get(&gltf::Semantic::Positions)
                    .into_iter()
                    .chain(prim.indices())
                {
                    if a.count() > 3 * MAX_TRIANGLES {
                        return Err(mesh_err(
                            name,
                            format!(
                                "accessor {} holds {} values, more than {MAX_TRIANGLES} \
                                 triangles need",
                                a.index(),
                                a.count()
                            ),
                        ));
                    }
                }
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

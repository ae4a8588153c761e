//! Mesh loading: a cube from OBJ and from glTF renders with the right depth; malformed and
//! truncated files give errors, never panics.

use nanoeye_datagen::render::{Light, Mesh, MeshUnits, RenderOptions, render};
use nanoeye_datagen::states::State;
use nanoeye_gaze::{Camera, geom};
use proptest::prelude::*;

/// Unit cube [-0.5, 0.5]³ (mm) as OBJ, object named "skin_cube".
const CUBE_OBJ: &str = "o skin_cube
v -0.5 -0.5 -0.5
v 0.5 -0.5 -0.5
v 0.5 0.5 -0.5
v -0.5 0.5 -0.5
v -0.5 -0.5 0.5
v 0.5 -0.5 0.5
v 0.5 0.5 0.5
v -0.5 0.5 0.5
f 1 2 3 4
f 5 8 7 6
f 1 5 6 2
f 2 6 7 3
f 3 7 8 4
f 4 8 5 1
";

const CUBE_POS: [[f32; 3]; 8] = [
    [-0.5, -0.5, -0.5],
    [0.5, -0.5, -0.5],
    [0.5, 0.5, -0.5],
    [-0.5, 0.5, -0.5],
    [-0.5, -0.5, 0.5],
    [0.5, -0.5, 0.5],
    [0.5, 0.5, 0.5],
    [-0.5, 0.5, 0.5],
];
const CUBE_IDX: [u16; 36] = [
    0, 1, 2, 0, 2, 3, 4, 7, 6, 4, 6, 5, 0, 4, 5, 0, 5, 1, 1, 5, 6, 1, 6, 2, 2, 6, 7, 2, 7, 3, 3, 7,
    4, 3, 4, 0,
];

fn base64(data: &[u8]) -> String {
    const T: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut s = String::new();
    for c in data.chunks(3) {
        let b = [c[0], *c.get(1).unwrap_or(&0), *c.get(2).unwrap_or(&0)];
        let n = (b[0] as u32) << 16 | (b[1] as u32) << 8 | b[2] as u32;
        for k in 0..4 {
            if k <= c.len() {
                s.push(T[(n >> (18 - 6 * k) & 63) as usize] as char);
            } else {
                s.push('=');
            }
        }
    }
    s
}

/// The same cube as a self-contained glTF (data URI buffer), translated by the node to
/// (0, 0, 0) – identity – with material "skin".
fn cube_gltf() -> String {
    let mut bin = Vec::new();
    for p in CUBE_POS {
        for x in p {
            bin.extend_from_slice(&x.to_le_bytes());
        }
    }
    for i in CUBE_IDX {
        bin.extend_from_slice(&i.to_le_bytes());
    }
    let uri = format!("data:application/octet-stream;base64,{}", base64(&bin));
    format!(
        r#"{{"asset":{{"version":"2.0"}},"scene":0,"scenes":[{{"nodes":[0]}}],
"nodes":[{{"mesh":0}}],
"materials":[{{"name":"skin"}}],
"meshes":[{{"name":"cube","primitives":[{{"attributes":{{"POSITION":0}},"indices":1,"material":0}}]}}],
"buffers":[{{"byteLength":{len},"uri":"{uri}"}}],
"bufferViews":[{{"buffer":0,"byteOffset":0,"byteLength":96}},{{"buffer":0,"byteOffset":96,"byteLength":72}}],
"accessors":[{{"bufferView":0,"componentType":5126,"count":8,"type":"VEC3","min":[-0.5,-0.5,-0.5],"max":[0.5,0.5,0.5]}},
{{"bufferView":1,"componentType":5123,"count":36,"type":"SCALAR"}}]}}"#,
        len = bin.len()
    )
}

fn check_cube_render(mesh: &Mesh) {
    assert_eq!(mesh.triangles.len(), 12);
    // The cube is in mm: its corners are at ±0.5 mm.
    let max = mesh
        .triangles
        .iter()
        .flatten()
        .map(|p| p[0].abs().max(p[1].abs()).max(p[2].abs()))
        .fold(0.0, f64::max);
    assert!((max - 0.5e-3).abs() < 1e-12);
    // Camera 5 mm in front of the +z face looking at it.
    let cam = Camera::look_at(2e-3, 48e-6, 40, 30, [0.0, 0.0, 5e-3], [0.0, 0.0, 0.0]).unwrap();
    let pose = cam.nominal_pose();
    let st = State {
        azimuth_rad: 0.0,
        elevation_rad: 0.0,
        torsion_rad: 0.0,
        slip_m: [0.0; 3],
        cam_rot_rad: [0.0; 3],
        lid_closure: 0.0,
    };
    let scene = mesh.scene(&st, Light::near_camera(&pose), 1.376).unwrap();
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
    // Centre pixel ray hits the +z face (z = 0.5 mm) at distance 4.5 mm / cos.
    let (i, j) = (15, 20);
    let d = geom::normalize(nanoeye_datagen::render::trace::pixel_dir(
        &cam,
        &pose,
        [j as f64 + 0.5, i as f64 + 0.5],
    ));
    let expect = 4.5e-3 / -d[2];
    assert!(
        (f.depth_m[(i, j)] as f64 - expect).abs() < 1e-9,
        "{} vs {expect}",
        f.depth_m[(i, j)]
    );
    assert!(f.radiance[(i, j)] > 0.0);
    // A corner pixel looks past the cube.
    assert!(f.depth_m[(0, 0)].is_infinite());
}

#[test]
fn cube_loads_from_obj_and_renders() {
    let mesh = Mesh::from_obj_bytes(
        CUBE_OBJ.as_bytes(),
        MeshUnits::Millimetres,
        "cube.obj",
        None,
    )
    .unwrap();
    check_cube_render(&mesh);
}

#[test]
fn cube_loads_from_gltf_and_renders() {
    let text = cube_gltf();
    let mesh = Mesh::from_gltf_bytes(text.as_bytes(), MeshUnits::Millimetres, "cube.gltf").unwrap();
    check_cube_render(&mesh);
}

#[test]
fn cube_loads_from_files_by_extension() {
    let dir = tempfile::tempdir().unwrap();
    let obj = dir.path().join("cube.obj");
    std::fs::write(&obj, CUBE_OBJ).unwrap();
    check_cube_render(&Mesh::load(&obj, MeshUnits::Millimetres).unwrap());
    let gl = dir.path().join("cube.gltf");
    std::fs::write(&gl, cube_gltf()).unwrap();
    check_cube_render(&Mesh::load(&gl, MeshUnits::Millimetres).unwrap());
    let bad = dir.path().join("cube.stl");
    std::fs::write(&bad, "solid").unwrap();
    assert!(Mesh::load(&bad, MeshUnits::Metres).is_err());
}

#[test]
fn empty_and_out_of_range_meshes_are_errors() {
    assert!(Mesh::from_obj_bytes(b"", MeshUnits::Metres, "e.obj", None).is_err());
    assert!(Mesh::from_obj_bytes(b"v 0 0 0\nf 1 2 3\n", MeshUnits::Metres, "r.obj", None).is_err());
    assert!(
        Mesh::from_obj_bytes(
            b"v nan 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
            MeshUnits::Metres,
            "n.obj",
            None
        )
        .is_err()
    );
    assert!(Mesh::from_gltf_bytes(b"{}", MeshUnits::Metres, "e.gltf").is_err());
}

/// What a helper's audit found (fifty-third session): inputs that hung, aborted or multiplied
/// the geometry, each an error naming the file or the part of it at fault.
#[test]
fn hostile_mesh_files_are_errors_not_hangs_or_aborts() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let err = |p: &std::path::Path| {
        Mesh::load(p, MeshUnits::Millimetres)
            .unwrap_err()
            .to_string()
    };
    let fifo = |p: &std::path::Path| {
        let made = std::process::Command::new("mkfifo")
            .arg(p)
            .status()
            .unwrap();
        assert!(made.success());
    };
    // A FIFO as the mesh, as its material library, as a glTF's external buffer (each
    // blocked); /dev/zero as the mesh or behind a `file://` buffer (read without end).
    fifo(&d.join("fifo.obj"));
    assert!(err(&d.join("fifo.obj")).contains("regular file"));
    std::fs::write(d.join("m.obj"), format!("mtllib fifo.mtl\n{CUBE_OBJ}")).unwrap();
    fifo(&d.join("fifo.mtl"));
    let e = err(&d.join("m.obj"));
    assert!(
        e.contains("mtllib fifo.mtl") && e.contains("regular file"),
        "{e}"
    );
    std::os::unix::fs::symlink("/dev/zero", d.join("zero.obj")).unwrap();
    assert!(err(&d.join("zero.obj")).contains("regular file"));
    let cube = cube_gltf();
    let data_uri = cube
        .split("\"uri\":\"")
        .nth(1)
        .unwrap()
        .split('"')
        .next()
        .unwrap();
    for (file, uri, why) in [
        ("f.gltf", "fifo.bin", "regular file"),
        ("z.gltf", "file:///dev/zero", "regular file"),
        ("p.gltf", "%FF%FE.bin", "not UTF-8"),
    ] {
        if uri == "fifo.bin" {
            fifo(&d.join(uri));
        }
        std::fs::write(d.join(file), cube.replace(data_uri, uri)).unwrap();
        let e = err(&d.join(file));
        assert!(e.contains("buffer 0") && e.contains(why), "{file}: {e}");
    }
    // An external buffer far longer than its byteLength (the importer read a 5 GB file whole
    // for a buffer of 44 bytes): refused from its length, nothing read.
    let f = std::fs::File::create(d.join("long.bin")).unwrap();
    f.set_len(10 << 20).unwrap();
    std::fs::write(d.join("l.gltf"), cube.replace(data_uri, "long.bin")).unwrap();
    assert!(err(&d.join("l.gltf")).contains("byteLength"));
    // A missing material library is an error, not triangles classed by object name alone.
    std::fs::write(d.join("miss.obj"), format!("mtllib gone.mtl\n{CUBE_OBJ}")).unwrap();
    assert!(err(&d.join("miss.obj")).contains("mtllib gone.mtl"));
    // A sparse POSITION accessor claiming 3e9 values in 760 bytes (36 GB asked for).
    let sparse = cube.replace(
        r#"{"bufferView":0,"componentType":5126,"count":8,"type":"VEC3","#,
        r#"{"componentType":5126,"count":3000000000,"type":"VEC3","sparse":{"count":1,"indices":{"bufferView":1,"componentType":5123},"values":{"bufferView":0}},"#,
    );
    assert_ne!(sparse, cube);
    let e = Mesh::from_gltf_bytes(sparse.as_bytes(), MeshUnits::Metres, "s.gltf")
        .unwrap_err()
        .to_string();
    assert!(e.contains("3000000000"), "{e}");
    // Node 0 holds node 1 twice: nodes form trees, and a chain of such nodes multiplied the
    // triangles by 2 per level (20 levels in 1.4 KB asked for 2.4 GB).
    let dag = cube.replace(
        r#""nodes":[{"mesh":0}]"#,
        r#""nodes":[{"children":[1,1]},{"mesh":0}]"#,
    );
    assert_ne!(dag, cube);
    let e = Mesh::from_gltf_bytes(dag.as_bytes(), MeshUnits::Metres, "d.gltf")
        .unwrap_err()
        .to_string();
    assert!(e.contains("node 1 has more than one parent"), "{e}");
    // The same node as a tree (one child) loads as the cube.
    let tree = cube.replace(
        r#""nodes":[{"mesh":0}]"#,
        r#""nodes":[{"children":[1]},{"mesh":0}]"#,
    );
    check_cube_render(
        &Mesh::from_gltf_bytes(tree.as_bytes(), MeshUnits::Millimetres, "t.gltf").unwrap(),
    );
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    #[test]
    fn random_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..512)) {
        let _ = Mesh::from_obj_bytes(&bytes, MeshUnits::Metres, "r.obj", None);
        let _ = Mesh::from_gltf_bytes(&bytes, MeshUnits::Metres, "r.gltf");
    }

    #[test]
    fn truncated_files_error_or_load_never_panic(cut in 0usize..2000, flip in 0usize..2000, byte in any::<u8>()) {
        let obj = CUBE_OBJ.as_bytes();
        let o = &obj[..cut.min(obj.len())];
        if let Ok(m) = Mesh::from_obj_bytes(o, MeshUnits::Metres, "t.obj", None) {
            prop_assert!(m.triangles.iter().flatten().all(|p| geom::is_finite(*p)));
        }
        let gl = cube_gltf().into_bytes();
        let g = &gl[..cut.min(gl.len())];
        prop_assert!(cut >= gl.len() || Mesh::from_gltf_bytes(g, MeshUnits::Metres, "t.gltf").is_err());
        let mut flipped = gl.clone();
        let k = flip % flipped.len();
        flipped[k] = byte;
        let _ = Mesh::from_gltf_bytes(&flipped, MeshUnits::Metres, "f.gltf");
        let mut fo = obj.to_vec();
        let k = flip % fo.len();
        fo[k] = byte;
        let _ = Mesh::from_obj_bytes(&fo, MeshUnits::Metres, "f.obj", None);
    }
}

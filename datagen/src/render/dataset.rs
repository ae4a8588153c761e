//! The dataset writer: renders a state set frame by frame into a directory (PNG preview, NPY
//! radiance and depth, mask PNGs, one JSON line per frame in frames.jsonl, a contact sheet).
//! Resumable: a frame whose record exists is skipped. Deterministic: same inputs → same bytes.
//! Format: docs/renderer.md.

use super::RenderError;
use super::landmarks::{Landmarks, aim_refracted_pupil, landmarks};
use super::mesh::Mesh;
use super::scene::{Light, Subject, procedural_scene};
use super::trace::{Frame, LayerSpec, RenderOptions, render};
use crate::states::{self, Protocol, State};
use faer::Mat;
use nanoeye_gaze::{Rig, Vec3};
use rand::Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::io::Write;
use std::path::{Path, PathBuf};

/// Which state set to render.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum RenderSet {
    /// Ambiguity pairs: frames anchor, slip, gaze per pair (3 per item).
    Ambiguity,
    /// Variational triplets: anchor, slip+, gaze+ (3 per item).
    Variational,
    /// Acquisition protocol: `n` subjects × 7 stage positions × `protocol_grid`² targets
    /// (D.4: 49).
    Protocol,
    /// A video-like sequence of `n` frames of one subject: gaze on a smooth Lissajous path
    /// (azimuth ±20°, elevation 5° ± 8°) while the glasses drift 0 → 3 mm down the nasal bridge.
    Sequence,
    /// `n` frames, one subject each, spanning the protocol's gaze range and stage slippage on top
    /// of Table S2's bridge slip (`states::envelope`): training data for the D.4 evaluation.
    Envelope,
}

/// Where the geometry comes from.
#[derive(Debug, Clone)]
pub enum SceneSource {
    /// The procedural eye region, one [`Subject`] per item drawn from the seed.
    Procedural,
    /// A user mesh (eye classes rotate with the eye); landmarks use the default subject.
    Mesh(Mesh),
}

/// Everything `write_dataset` needs.
#[derive(Debug, Clone)]
pub struct DatasetOptions {
    /// The set.
    pub set: RenderSet,
    /// Items (pairs, triplets or protocol subjects).
    pub n: usize,
    /// Seed of the states, subjects and pixel samples.
    pub seed: u64,
    /// Image width (px); the rig's sensor is resampled to it.
    pub width_px: usize,
    /// Image height (px); must keep the rig's aspect ratio (±1 px).
    pub height_px: usize,
    /// Samples per pixel.
    pub spp: usize,
    /// Output directory.
    pub out_dir: PathBuf,
    /// The rig.
    pub rig: Rig,
    /// Geometry source.
    pub source: SceneSource,
    /// Draw a progress bar on stderr.
    pub progress: bool,
    /// Depth layers (the non-empty ones are written per frame).
    pub layers: LayerSpec,
    /// Share (0–1) of the envelope set's frames caught in a blink or partial closure: their
    /// `lid_closure` is uniform in [`BLINK_CLOSURE`]; 0 keeps every lid open (the default).
    pub blink_fraction: f64,
    /// Targets per side of the protocol set's grid (2–[`states::PROTOCOL_GRID`]; D.4's 7 ×
    /// 7 is [`states::PROTOCOL_GRID`], the only value the other sets take).
    pub protocol_grid: usize,
}

/// Range of `lid_closure` drawn for a blinking frame (see [`DatasetOptions::blink_fraction`]):
/// from a lid lowered over the upper iris to fully closed.
pub const BLINK_CLOSURE: std::ops::Range<f64> = 0.2..1.0;

/// Paths of one frame's files, relative to the dataset directory.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FrameFiles {
    /// 8-bit tone-mapped preview PNG.
    pub preview: String,
    /// f32 radiance NPY (height × width, W/(m²·sr)).
    pub radiance: String,
    /// f32 depth NPY (height × width, m; inf = no surface).
    pub depth: String,
    /// 8-bit visible-pupil coverage PNG.
    pub mask_visible_pupil: String,
    /// 8-bit unoccluded-pupil coverage PNG.
    pub mask_pupil: String,
    /// f32 NPY [K', 2, H, W]: premultiplied radiance (W/(m²·sr)) and coverage of each
    /// non-empty depth layer, in the order of the record's `layers` (absent in datasets written
    /// before layers were stored).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub layers: Option<String>,
    /// f32 NPY [2, H, W]: exact visible-pupil and unoccluded-pupil coverage.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub masks: Option<String>,
}

/// One non-empty depth layer of a frame, as stored: its index among the K slabs and its bounds.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LayerInfo {
    /// Slab index k (0 = nearest).
    pub index: usize,
    /// Near bound of the slab (m of ray distance).
    pub near_m: f64,
    /// Far bound of the slab (m of ray distance).
    pub far_m: f64,
}

/// Version of the dataset layout written by [`write_dataset`] (dataset.json).
pub const DATASET_FORMAT: u32 = 3;

/// DIR/dataset.json: everything that determines the dataset's bytes, so a resume with other
/// parameters is refused and a reader knows the native grid and the illuminator.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DatasetManifest {
    /// Layout version ([`DATASET_FORMAT`]).
    pub format: u32,
    /// The set.
    pub set: RenderSet,
    /// Items.
    pub n: usize,
    /// Seed.
    pub seed: u64,
    /// Samples per pixel.
    pub spp: usize,
    /// Depth-layer slabs.
    pub layers: LayerSpec,
    /// Geometry source: `"procedural"` or `"mesh:<path>"`.
    pub source: String,
    /// The rig at the rendered size: its camera is the native grid (pixel pitch, size,
    /// intrinsics) of every image in the dataset.
    pub rig: Rig,
    /// Radiant intensity of the renderer's illuminator towards the nominal corneal apex (W/sr;
    /// its beam's on-axis value × cos⁴ of the apex's angle off the axis); radiance scales
    /// linearly in it.
    pub light_intensity_w_per_sr: f64,
    /// Frames in the dataset.
    pub frames: usize,
    /// Share of envelope frames drawn with a blink or partial closure (absent: 0).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub blink_fraction: f64,
    /// True where a variational triplet's three frames share their pixel samples (rendered
    /// since 2026-12-03; [`pixel_seed`]); absent (false) where every frame has its own — so a
    /// render resumed across that change is refused rather than mixed.
    #[serde(default, skip_serializing_if = "is_false")]
    pub triplet_samples_shared: bool,
    /// Targets per side of a protocol set's grid (absent: D.4's 7, the only value written
    /// without the key, so datasets of the paper's grid keep their layout).
    #[serde(
        default = "paper_protocol_grid",
        skip_serializing_if = "is_paper_protocol_grid"
    )]
    pub protocol_grid: usize,
}

fn paper_protocol_grid() -> usize {
    states::PROTOCOL_GRID
}

fn is_paper_protocol_grid(g: &usize) -> bool {
    *g == states::PROTOCOL_GRID
}

fn is_false(b: &bool) -> bool {
    !*b
}

fn is_zero(x: &f64) -> bool {
    *x == 0.0
}

/// One line of frames.jsonl.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct FrameRecord {
    /// Frame index.
    pub frame: usize,
    /// Item index in the set (pair, triplet or protocol capture).
    pub item: usize,
    /// Role in the item: anchor/slip/gaze, anchor/slip_plus/gaze_plus, or capture.
    pub role: String,
    /// Subject seed (procedural appearance).
    pub subject: u64,
    /// The state.
    pub state: State,
    /// Unit optical-axis gaze.
    pub gaze: Vec3,
    /// Pinhole projection of the true pupil centre (px).
    pub pupil_center_px: Option<[f64; 2]>,
    /// Apparent pupil centre through the cornea (px).
    pub pupil_center_refracted_px: Option<[f64; 2]>,
    /// Landmarks.
    pub landmarks: Landmarks,
    /// Files.
    pub files: FrameFiles,
    /// The non-empty depth layers stored in `files.layers`, near to far.
    #[serde(default)]
    pub layers: Vec<LayerInfo>,
    /// Visible share of the pupil: Σ visible-pupil mask / Σ unoccluded-pupil mask (lids and
    /// lashes hide the rest); None where no pupil is in view.
    #[serde(default)]
    pub pupil_visible_fraction: Option<f64>,
}

/// What `write_dataset` did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct DatasetSummary {
    /// Frames rendered now.
    pub written: usize,
    /// Frames found complete and skipped.
    pub skipped: usize,
}

/// One planned frame.
#[derive(Debug, Clone, Copy)]
pub struct PlannedFrame {
    /// Item index.
    pub item: usize,
    /// Role name.
    pub role: &'static str,
    /// Subject seed.
    pub subject: u64,
    /// State.
    pub state: State,
}

/// The frames of a set, in file order. In an ambiguity pair the `gaze` member is re-aimed so
/// its *refracted* pupil centre lands where the `slip` member's does (the state set matches
/// the pinhole projections; the cornea shifts them differently), so the two rendered pupils
/// coincide; where that Newton solve fails the pinhole match is kept. `protocol_grid` is the
/// protocol set's targets per side (2–[`states::PROTOCOL_GRID`], refused otherwise); the other
/// sets ignore it.
pub fn plan(
    set: RenderSet,
    rig: &Rig,
    source: &SceneSource,
    n: usize,
    seed: u64,
    protocol_grid: usize,
) -> Result<Vec<PlannedFrame>, RenderError> {
    let subj = |item: usize| seed.wrapping_mul(0x2545_F491_4F6C_DD1D) ^ item as u64;
    let mut out = Vec::new();
    match set {
        RenderSet::Ambiguity => {
            for (i, p) in states::ambiguity(rig, n, seed)?.into_iter().enumerate() {
                let subject = subject_of(source, subj(i));
                let target = landmarks(rig, &p.slip, &subject)?.pupil_center_refracted_px;
                let gaze = match target {
                    Some(t) => aim_refracted_pupil(rig, &p.gaze, &subject, t)?.unwrap_or(p.gaze),
                    None => p.gaze,
                };
                for (role, state) in [("anchor", p.anchor), ("slip", p.slip), ("gaze", gaze)] {
                    out.push(PlannedFrame {
                        item: i,
                        role,
                        subject: subj(i),
                        state,
                    });
                }
            }
        }
        RenderSet::Variational => {
            for (i, t) in states::variational(rig, n, seed)?.into_iter().enumerate() {
                for (role, state) in [
                    ("anchor", t.anchor),
                    ("slip_plus", t.slip_plus),
                    ("gaze_plus", t.gaze_plus),
                ] {
                    out.push(PlannedFrame {
                        item: i,
                        role,
                        subject: subj(i),
                        state,
                    });
                }
            }
        }
        RenderSet::Protocol => {
            let p = Protocol {
                grid: protocol_grid,
                ..Protocol::default()
            };
            for (i, c) in states::protocol(rig, &p, n, seed)?.into_iter().enumerate() {
                out.push(PlannedFrame {
                    item: i,
                    role: "capture",
                    subject: subj(c.subject),
                    state: c.state,
                });
            }
        }
        RenderSet::Envelope => {
            for (i, state) in states::envelope(rig, &Protocol::default(), n, seed)?
                .into_iter()
                .enumerate()
            {
                out.push(PlannedFrame {
                    item: i,
                    role: "envelope",
                    subject: subj(i),
                    state,
                });
            }
        }
        RenderSet::Sequence => {
            if n > states::MAX_SET_ITEMS {
                return Err(RenderError::Invalid {
                    what: "n",
                    reason: format!(
                        "{n} sequence frames requested, at most {}",
                        states::MAX_SET_ITEMS
                    ),
                });
            }
            for i in 0..n {
                let t = i as f64 / n.max(1) as f64;
                let tau = std::f64::consts::TAU;
                let (slip_m, cam_rot_rad) = states::Mounting::NONE.slip(rig, 3e-3 * t);
                out.push(PlannedFrame {
                    item: i,
                    role: "sequence",
                    subject: subj(0),
                    state: State {
                        azimuth_rad: 20f64.to_radians() * (tau * t).sin(),
                        elevation_rad: (5.0 + 8.0 * (2.0 * tau * t).sin()).to_radians(),
                        torsion_rad: 0.0,
                        slip_m,
                        cam_rot_rad,
                        lid_closure: 0.0,
                    },
                });
            }
        }
    }
    Ok(out)
}

/// The rig with its camera resampled to `width_px` × `height_px` over the same sensor.
pub fn rig_at_size(rig: &Rig, width_px: usize, height_px: usize) -> Result<Rig, RenderError> {
    if width_px == 0 || width_px > 16384 {
        return Err(RenderError::Invalid {
            what: "width",
            reason: format!("must be in 1..=16384, got {width_px}"),
        });
    }
    let pitch = rig.camera.pixel_pitch_m * rig.camera.width_px as f64 / width_px as f64;
    let mut cam = rig.camera.with_pitch(pitch)?;
    // Keep the principal point centred when the requested size differs by a rounding pixel.
    cam.cx_px += 0.5 * (width_px as f64 - cam.width_px as f64);
    cam.width_px = width_px;
    if cam.height_px.abs_diff(height_px) > 1 {
        return Err(RenderError::Invalid {
            what: "height",
            reason: format!(
                "{height_px} px breaks the rig's aspect ratio (expected {} px for width {width_px})",
                cam.height_px
            ),
        });
    }
    cam.cy_px += 0.5 * (height_px as f64 - cam.height_px as f64);
    cam.height_px = height_px;
    Ok(Rig {
        camera: cam,
        ..rig.clone()
    })
}

fn io_err(path: &Path, source: std::io::Error) -> RenderError {
    RenderError::Io {
        path: path.display().to_string(),
        cause: source,
    }
}

/// Writes `bytes` to `path` atomically (temporary file in the same directory, then rename).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), RenderError> {
    // Renaming over a symlink, pipe, device or directory would replace that node silently.
    if let Ok(m) = std::fs::symlink_metadata(path)
        && !m.file_type().is_file()
    {
        return Err(RenderError::Invalid {
            what: "out",
            reason: format!(
                "'{}' exists and is not a regular file; refusing to replace it",
                path.display()
            ),
        });
    }
    let dir = path.parent().unwrap_or(Path::new("."));
    // Named `.nanoeye-tmp-<pid>-…`: the CLI removes those a killed process left behind.
    let mut b = tempfile::Builder::new();
    // A temporary file is created owner-only (0600); an output is an ordinary file, so ask
    // for 0666 and let the umask take its share, as `File::create` would.
    #[cfg(unix)]
    b.permissions(std::os::unix::fs::PermissionsExt::from_mode(0o666));
    let mut tmp = b
        .prefix(&format!(".nanoeye-tmp-{}-", std::process::id()))
        .tempfile_in(dir)
        .map_err(|e| io_err(path, e))?;
    tmp.write_all(bytes).map_err(|e| io_err(path, e))?;
    tmp.persist(path).map_err(|e| io_err(path, e.error))?;
    Ok(())
}

/// NPY bytes (little-endian f32, C order) of a matrix.
pub fn npy_bytes(m: &Mat<f32>) -> Result<Vec<u8>, RenderError> {
    use npyz::WriterBuilder;
    let mut buf = Vec::new();
    let enc = |e: std::io::Error| RenderError::Encode {
        path: "(npy)".into(),
        reason: e.to_string(),
    };
    let mut w = npyz::WriteOptions::<f32>::new()
        .default_dtype()
        .shape(&[m.nrows() as u64, m.ncols() as u64])
        .writer(&mut buf)
        .begin_nd()
        .map_err(enc)?;
    for i in 0..m.nrows() {
        for j in 0..m.ncols() {
            w.push(&m[(i, j)]).map_err(enc)?;
        }
    }
    w.finish().map_err(enc)?;
    Ok(buf)
}

/// PNG bytes of 8-bit grey levels (row-major, width × height).
pub fn png_bytes(gray: Vec<u8>, width: usize, height: usize) -> Result<Vec<u8>, RenderError> {
    let img = image::GrayImage::from_raw(width as u32, height as u32, gray).ok_or_else(|| {
        RenderError::Encode {
            path: "(png)".into(),
            reason: "buffer size does not match the image size".into(),
        }
    })?;
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png)
        .map_err(|e| RenderError::Encode {
            path: "(png)".into(),
            reason: e.to_string(),
        })?;
    Ok(out.into_inner())
}

/// 8-bit preview: radiance over the 99th percentile (glints saturate), then gamma 1/2.2.
pub fn tone_map(m: &Mat<f32>) -> Vec<u8> {
    let mut v: Vec<f32> = (0..m.nrows())
        .flat_map(|i| (0..m.ncols()).map(move |j| (i, j)))
        .map(|(i, j)| m[(i, j)])
        .collect();
    let mut sorted: Vec<f32> = v.iter().copied().filter(|x| x.is_finite()).collect();
    sorted.sort_by(f32::total_cmp);
    let white = sorted
        .get(sorted.len() * 99 / 100)
        .copied()
        .unwrap_or(1.0)
        .max(1e-30);
    for x in &mut v {
        *x = (*x / white).clamp(0.0, 1.0).powf(1.0 / 2.2) * 255.0;
    }
    v.into_iter().map(|x| x.round() as u8).collect()
}

fn mask_png(m: &Mat<f32>) -> Result<Vec<u8>, RenderError> {
    let g = (0..m.nrows())
        .flat_map(|i| (0..m.ncols()).map(move |j| (i, j)))
        .map(|(i, j)| (m[(i, j)].clamp(0.0, 1.0) * 255.0).round() as u8)
        .collect();
    png_bytes(g, m.ncols(), m.nrows())
}

/// The appearance a frame is rendered with: the seeded subject for the procedural eye, the
/// default subject's optics for a mesh.
fn subject_of(source: &SceneSource, seed: u64) -> Subject {
    match source {
        SceneSource::Procedural => Subject::from_seed(seed),
        SceneSource::Mesh(_) => Subject::default(),
    }
}

/// Renders one planned frame.
pub fn render_planned(
    rig: &Rig,
    source: &SceneSource,
    f: &PlannedFrame,
    spp: usize,
    seed: u64,
    layers: LayerSpec,
) -> Result<(Frame, Landmarks), RenderError> {
    let pose = f.state.camera_pose(rig);
    let light = Light::near_camera(&pose);
    let subject = subject_of(source, f.subject);
    let scene = match source {
        SceneSource::Procedural => procedural_scene(rig, &f.state, &subject, light)?,
        SceneSource::Mesh(m) => m.scene(&f.state, light, subject.cornea_index)?,
    };
    let opts = RenderOptions { spp, seed, layers };
    let frame = render(&scene, &rig.camera, &pose, &opts)?;
    Ok((frame, landmarks(rig, &f.state, &subject)?))
}

/// The manifest `write_dataset` writes for `opts` (rig resampled to the rendered size).
pub fn manifest_for(opts: &DatasetOptions) -> Result<DatasetManifest, RenderError> {
    let g = opts.protocol_grid;
    let max = states::PROTOCOL_GRID;
    if opts.set == RenderSet::Protocol && !(2..=max).contains(&g) {
        return Err(RenderError::Invalid {
            what: "protocol_grid",
            reason: format!("{g} targets per side, must be 2–{max} (D.4's grid is {max}×{max})"),
        });
    }
    if opts.set != RenderSet::Protocol && g != max {
        return Err(RenderError::Invalid {
            what: "protocol_grid",
            reason: format!("{g}: only the protocol set has a target grid"),
        });
    }
    let rig = rig_at_size(&opts.rig, opts.width_px, opts.height_px)?;
    let frames = match opts.set {
        RenderSet::Ambiguity | RenderSet::Variational => opts.n.saturating_mul(3),
        RenderSet::Protocol => opts.n.saturating_mul(7 * g * g),
        RenderSet::Sequence | RenderSet::Envelope => opts.n,
    };
    Ok(DatasetManifest {
        format: DATASET_FORMAT,
        set: opts.set,
        n: opts.n,
        seed: opts.seed,
        spp: opts.spp,
        layers: opts.layers,
        source: match &opts.source {
            SceneSource::Procedural => "procedural".into(),
            SceneSource::Mesh(m) => format!("mesh:{}:{:016x}", m.triangles.len(), mesh_hash(m)),
        },
        light_intensity_w_per_sr: Light::near_camera(&rig.camera.nominal_pose())
            .intensity_toward([0.0, 0.0, Subject::default().cornea_apex_m]),
        rig,
        frames,
        blink_fraction: opts.blink_fraction,
        triplet_samples_shared: opts.set == RenderSet::Variational,
        protocol_grid: opts.protocol_grid,
    })
}

/// Bytes of array data (NPY payloads, headers excluded) `write_dataset` writes for `opts`, as
/// (least, most): every frame writes its radiance, depth and two masks (four f32 planes) and
/// its non-empty depth layers (two f32 planes each): least with none kept, most with all
/// `layers.count`. Previews, mask PNGs and records add about 1 % at the default size.
pub fn dataset_array_bytes(opts: &DatasetOptions) -> Result<(u64, u64), RenderError> {
    let m = manifest_for(opts)?;
    let plane = (m.rig.camera.width_px as u64)
        .saturating_mul(m.rig.camera.height_px as u64)
        .saturating_mul(4);
    let frames = m.frames as u64;
    let least = frames.saturating_mul(plane.saturating_mul(4));
    let layers = frames.saturating_mul(plane.saturating_mul(2 * opts.layers.count as u64));
    Ok((least, least.saturating_add(layers)))
}

/// FNV-1a over the mesh's vertex bits and classes: identifies the geometry a dataset used.
fn mesh_hash(m: &Mesh) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    let mut eat = |x: u64| {
        for b in x.to_le_bytes() {
            h ^= b as u64;
            h = h.wrapping_mul(0x0100_0000_01b3);
        }
    };
    for (t, k) in m.triangles.iter().zip(&m.kinds) {
        for v in t.iter().flatten() {
            eat(v.to_bits());
        }
        eat(*k as u64);
    }
    h
}

/// Every field in which two configurations (serialised to JSON objects) differ, for a refused
/// resume: `` `name`: A there, B now `` for a number, string or flag, `` `name` `` alone for a
/// nested value, separated by "; ", the field `first` (when given) ahead of the others
/// ("unreadable" when either is not an object). Also the wording of search's refusals.
pub fn field_differences(
    was: &impl serde::Serialize,
    now: &impl serde::Serialize,
    first: Option<&str>,
) -> String {
    use serde_json::Value;
    let (Ok(Value::Object(a)), Ok(Value::Object(b))) =
        (serde_json::to_value(was), serde_json::to_value(now))
    else {
        return String::from("unreadable");
    };
    let nested = |v: Option<&Value>| v.is_some_and(|v| v.is_object() || v.is_array());
    let show = |v: Option<&Value>| v.map_or_else(|| String::from("none"), Value::to_string);
    let mut keys: Vec<&String> = a
        .keys()
        .chain(b.keys().filter(|k| !a.contains_key(*k)))
        .collect();
    keys.sort_by_key(|k| Some(k.as_str()) != first);
    keys.into_iter()
        .filter(|k| a.get(*k) != b.get(*k))
        .map(|k| {
            let (x, y) = (a.get(k), b.get(k));
            if nested(x) || nested(y) {
                format!("`{k}`")
            } else {
                format!("`{k}`: {} there, {} now", show(x), show(y))
            }
        })
        .collect::<Vec<_>>()
        .join("; ")
}

/// Refuses to add frames to a directory rendered with other parameters, naming every field
/// that differs. A directory without dataset.json but with frames is refused too (unknown origin).
fn check_existing(dir: &Path, manifest: &DatasetManifest) -> Result<(), RenderError> {
    let path = dir.join("dataset.json");
    // Only a missing manifest is absent: one that cannot be read (a FIFO blocked, `/dev/zero`
    // was read until memory ran out, bytes that are not text were overwritten) is refused.
    let read = match std::fs::symlink_metadata(&path) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Err(e),
        _ => {
            let meta = std::fs::metadata(&path).map_err(|e| io_err(&path, e))?;
            if !meta.is_file() || meta.len() > MAX_RECORD_BYTES {
                return Err(RenderError::Invalid {
                    what: "out",
                    reason: format!(
                        "{} is not a regular file of at most {MAX_RECORD_BYTES} bytes; render \
                         into a new directory",
                        path.display()
                    ),
                });
            }
            Ok(std::fs::read(&path).map_err(|e| io_err(&path, e))?)
        }
    };
    match read.map(|b| String::from_utf8_lossy(&b).into_owned()) {
        Ok(text) => {
            let old: DatasetManifest =
                serde_json::from_str(&text).map_err(|e| RenderError::Invalid {
                    what: "out",
                    reason: format!(
                        "{} is not a dataset manifest of this version ({e}); render into a new directory",
                        path.display()
                    ),
                })?;
            let a = serde_json::to_value(&old).unwrap_or_default();
            let b = serde_json::to_value(manifest).unwrap_or_default();
            if a != b {
                return Err(RenderError::Invalid {
                    what: "out",
                    reason: format!(
                        "{} holds a dataset rendered with other parameters ({}); resuming would \
                         mix two runs: use a new --out directory",
                        dir.display(),
                        // The set first: it decides the others (e.g. `frames`).
                        field_differences(&a, &b, Some("set"))
                    ),
                });
            }
            Ok(())
        }
        Err(_) => {
            let frames = dir.join("frames");
            let has_frames = std::fs::read_dir(&frames)
                .map(|mut d| d.next().is_some())
                .unwrap_or(false);
            if has_frames {
                return Err(RenderError::Invalid {
                    what: "out",
                    reason: format!(
                        "{} holds frames but no dataset.json (an older or foreign dataset); use a new --out directory",
                        dir.display()
                    ),
                });
            }
            Ok(())
        }
    }
}

/// NPY bytes (little-endian f32, C order) of `planes` stacked along a leading axis of
/// `groups` × (planes per group): shape [groups, per, H, W] or [per, H, W] when `groups` is None.
fn npy_stack(planes: &[&Mat<f32>], groups: Option<usize>) -> Result<Vec<u8>, RenderError> {
    use npyz::WriterBuilder;
    let (h, w) = planes
        .first()
        .map_or((0, 0), |m| (m.nrows() as u64, m.ncols() as u64));
    let shape: Vec<u64> = match groups {
        Some(g) => vec![g as u64, (planes.len() / g.max(1)) as u64, h, w],
        None => vec![planes.len() as u64, h, w],
    };
    let enc = |e: std::io::Error| RenderError::Encode {
        path: "(npy)".into(),
        reason: e.to_string(),
    };
    let mut buf = Vec::with_capacity(planes.len() * (h * w) as usize * 4 + 128);
    let mut wr = npyz::WriteOptions::<f32>::new()
        .default_dtype()
        .shape(&shape)
        .writer(&mut buf)
        .begin_nd()
        .map_err(enc)?;
    for m in planes {
        for i in 0..m.nrows() {
            for j in 0..m.ncols() {
                wr.push(&m[(i, j)]).map_err(enc)?;
            }
        }
    }
    wr.finish().map_err(enc)?;
    Ok(buf)
}

/// A dataset's manifest and its frames in file order: what every process rendering a share of
/// it needs.
#[derive(Debug, Clone)]
pub struct DatasetPlan {
    /// The manifest (dataset.json).
    pub manifest: DatasetManifest,
    /// The frames, in file order.
    pub planned: Vec<PlannedFrame>,
}

/// The manifest and frames `write_dataset` renders for `opts`, without touching the disk.
pub fn plan_dataset(opts: &DatasetOptions) -> Result<DatasetPlan, RenderError> {
    let manifest = manifest_for(opts)?;
    if opts.spp == 0 {
        return Err(RenderError::Invalid {
            what: "spp",
            reason: "must be ≥ 1".into(),
        });
    }
    let b = opts.blink_fraction;
    if !(0.0..=1.0).contains(&b) {
        return Err(RenderError::Invalid {
            what: "blink_fraction",
            reason: format!("must be in [0, 1], got {b}"),
        });
    }
    if b > 0.0 && opts.set != RenderSet::Envelope {
        return Err(RenderError::Invalid {
            what: "blink_fraction",
            reason: "only the envelope set samples lid closures".into(),
        });
    }
    let mut planned = plan(
        opts.set,
        &manifest.rig,
        &opts.source,
        opts.n,
        opts.seed,
        opts.protocol_grid,
    )?;
    if b > 0.0 {
        // A stream of its own per item, so the states and subjects are those of b = 0.
        for f in &mut planned {
            let mut rng = states::sets::item_rng(opts.seed, 7, f.item as u64);
            if rng.random::<f64>() < b {
                f.state.lid_closure = rng.random_range(BLINK_CLOSURE);
            }
        }
    }
    let manifest = DatasetManifest {
        frames: planned.len(),
        ..manifest
    };
    Ok(DatasetPlan { manifest, planned })
}

/// [`plan_dataset`], then opens `opts.out_dir` for it: refuses a directory holding a dataset
/// rendered with other parameters and writes dataset.json. A distributed run calls it on one
/// process only.
pub fn open_dataset(opts: &DatasetOptions) -> Result<DatasetPlan, RenderError> {
    let p = plan_dataset(opts)?;
    // Everything a render would refuse, refused before the directory is touched: a manifest
    // written for a render that cannot run would make the corrected command a "resume with
    // other parameters".
    RenderOptions {
        spp: opts.spp,
        seed: opts.seed,
        layers: opts.layers,
    }
    .validate()?;
    check_frame_memory(
        &p.manifest.rig.camera,
        opts.layers.count,
        available_memory(),
    )?;
    check_existing(&opts.out_dir, &p.manifest)?;
    let fdir = opts.out_dir.join("frames");
    std::fs::create_dir_all(&fdir).map_err(|e| io_err(&fdir, e))?;
    let mtext = serde_json::to_string_pretty(&p.manifest).map_err(|e| RenderError::Encode {
        path: "dataset.json".into(),
        reason: e.to_string(),
    })?;
    write_atomic(&opts.out_dir.join("dataset.json"), mtext.as_bytes())?;
    Ok(p)
}

/// Renders the set into `opts.out_dir`; frames whose record file exists are skipped. A
/// directory holding a dataset rendered with other parameters is refused.
pub fn write_dataset(opts: &DatasetOptions) -> Result<DatasetSummary, RenderError> {
    let p = open_dataset(opts)?;
    let all: Vec<usize> = (0..p.planned.len()).collect();
    let summary = render_frames(opts, &p, &all, opts.progress)?;
    finish_dataset(opts, &p)?;
    Ok(summary)
}

/// Largest frame record read (bytes): a state, landmarks and file names, a few KB.
const MAX_RECORD_BYTES: u64 = 1 << 20;

/// The complete record of frame `i` of `plan` in `dir`: its record file is a regular file that
/// parses, describes frame `i` as planned (item, role, subject, state) with this frame's file
/// names, and each of its files is a regular file (each NPY's preamble within its length).
/// None otherwise, and the frame is rendered again (it depends only on its index): a record
/// copied from frame 0 to frame 1 was kept, giving frames.jsonl frame 0 twice; a deleted
/// radiance file left a dataset without it; a FIFO in place of a record blocked the resume.
fn finished_record(dir: &Path, i: usize, plan: &PlannedFrame) -> Option<String> {
    let path = dir.join(format!("frames/{i:06}.json"));
    let meta = std::fs::metadata(&path).ok()?;
    if !meta.is_file() || meta.len() > MAX_RECORD_BYTES {
        return None;
    }
    let text = std::fs::read_to_string(&path).ok()?;
    let r: FrameRecord = serde_json::from_str(&text).ok()?;
    let planned = r.frame == i
        && r.item == plan.item
        && r.role == plan.role
        && r.subject == plan.subject
        && r.state == plan.state;
    let stem = format!("frames/{i:06}");
    let f = &r.files;
    let named = [
        (&f.preview, "_preview.png"),
        (&f.radiance, "_radiance.npy"),
        (&f.depth, "_depth.npy"),
        (&f.mask_visible_pupil, "_mask_visible_pupil.png"),
        (&f.mask_pupil, "_mask_pupil.png"),
    ]
    .into_iter()
    .chain(f.layers.iter().map(|l| (l, "_layers.npy")))
    .chain(f.masks.iter().map(|m| (m, "_masks.npy")))
    .all(|(name, suffix)| *name == format!("{stem}{suffix}") && file_intact(&dir.join(name)));
    (planned && named).then_some(text)
}

/// Whether a frame's file is a regular file and, for an NPY, holds the data its preamble
/// claims.
fn file_intact(path: &Path) -> bool {
    if !std::fs::metadata(path).is_ok_and(|m| m.is_file()) {
        return false;
    }
    if path.extension().is_some_and(|e| e == "npy") {
        return matches!(nanoeye_npy::check_file(path), Ok(Ok(Some(_))));
    }
    true
}

/// Renders frames `frames` (indices into `plan.planned`) of a dataset opened by
/// [`open_dataset`], skipping those whose record file exists. Each frame's files depend only
/// on its index, so shares rendered by different processes make the same dataset.
pub fn render_frames(
    opts: &DatasetOptions,
    plan: &DatasetPlan,
    frames: &[usize],
    progress: bool,
) -> Result<DatasetSummary, RenderError> {
    let fdir = opts.out_dir.join("frames");
    std::fs::create_dir_all(&fdir).map_err(|e| io_err(&fdir, e))?;
    if let Some(&i) = frames.iter().find(|&&i| i >= plan.planned.len()) {
        return Err(RenderError::Invalid {
            what: "frames",
            reason: format!("frame {i} out of 0..{}", plan.planned.len()),
        });
    }
    check_frame_memory(
        &plan.manifest.rig.camera,
        opts.layers.count,
        available_memory(),
    )?;
    let bar = if progress {
        indicatif::ProgressBar::new(frames.len() as u64)
    } else {
        indicatif::ProgressBar::hidden()
    };
    let (mut written, mut skipped) = (0, 0);
    // Frames in groups of one per thread, each frame's rows parallel inside: a frame's serial
    // parts (scene build, PNG and NPY encoding, writes) then overlap another frame's work
    // instead of leaving a core idle. A frame's content depends only on its index, and a group
    // bounds the frames held in memory at once.
    let group_len = frames_in_flight(
        rayon::current_num_threads(),
        &plan.manifest.rig.camera,
        opts.layers.count,
    );
    for group in frames.chunks(group_len) {
        let done: Vec<Result<bool, RenderError>> = group
            .par_iter()
            .map(|&i| {
                let r = render_one(opts, plan, i);
                bar.inc(1);
                r
            })
            .collect();
        for d in done {
            if d? {
                written += 1;
            } else {
                skipped += 1;
            }
        }
    }
    bar.finish_and_clear();
    Ok(DatasetSummary { written, skipped })
}

/// Most bytes of frames in flight at once in [`render_frames`].
const FRAMES_IN_FLIGHT_BYTES: usize = 2 << 30;

/// Bytes one frame holds while it is rendered and written: its interleaved sample buffer, the
/// planes gathered from it and their encodings, about three times (4 + 2K) f32 per pixel.
fn frame_bytes(camera: &nanoeye_gaze::Camera, layers: usize) -> usize {
    camera
        .width_px
        .saturating_mul(camera.height_px)
        .saturating_mul(4 + 2 * layers)
        .saturating_mul(3 * std::mem::size_of::<f32>())
        .max(1)
}

/// Frames [`render_frames`] renders at once: one per thread, as many as fit in
/// [`FRAMES_IN_FLIGHT_BYTES`] (at least one).
fn frames_in_flight(threads: usize, camera: &nanoeye_gaze::Camera, layers: usize) -> usize {
    threads
        .min(FRAMES_IN_FLIGHT_BYTES / frame_bytes(camera, layers))
        .max(1)
}

/// Memory the system can still give this process (bytes): the lesser of Linux's
/// `MemAvailable` and what this process's memory control groups still allow
/// ([`super::cgroup::memory_left`]); None where neither can be read.
pub fn available_memory() -> Option<usize> {
    let machine = proc_bytes("/proc/meminfo", "MemAvailable:");
    let group = super::cgroup::memory_left();
    match (machine, group) {
        (Some(a), Some(b)) => Some(a.min(b)),
        (a, b) => a.or(b),
    }
}

/// The value of a `KEY:   N kB` line of a /proc file (`/proc/meminfo`, `/proc/self/status`),
/// in bytes; None where the file or the line cannot be read.
pub fn proc_bytes(path: &str, key: &str) -> Option<usize> {
    let text = std::fs::read_to_string(path).ok()?;
    let kb: usize = text
        .lines()
        .find_map(|l| l.strip_prefix(key))?
        .trim()
        .strip_suffix("kB")?
        .trim()
        .parse()
        .ok()?;
    Some(kb.saturating_mul(1024))
}

/// Refuses a frame size that cannot fit in `available` bytes (None: not known, not checked):
/// a width off by a digit would otherwise end in the kernel's out-of-memory kill, not an error.
fn check_frame_memory(
    camera: &nanoeye_gaze::Camera,
    layers: usize,
    available: Option<usize>,
) -> Result<(), RenderError> {
    let need = frame_bytes(camera, layers);
    match available {
        Some(have) if need > have => Err(RenderError::Invalid {
            what: "width",
            reason: format!(
                "a {}×{} px frame with {layers} depth layers needs about {:.1} GB while rendered, \
                 and this machine has {:.1} GB available: lower the width and height (or the \
                 layer count)",
                camera.width_px,
                camera.height_px,
                need as f64 / 1e9,
                have as f64 / 1e9
            ),
        }),
        _ => Ok(()),
    }
}

/// The seed of frame `i`'s pixel samples (item `item` of `set`). A variational triplet's three
/// frames share their item's samples (common random numbers), so the finite differences the
/// triplet exists for (C.2) hold the change of the scene, not the renderer's sampling noise;
/// every other frame has its own.
pub fn pixel_seed(set: RenderSet, seed: u64, i: usize, item: usize) -> u64 {
    match set {
        RenderSet::Variational => {
            seed ^ (item as u64)
                .wrapping_add(1 << 62)
                .wrapping_mul(0xE703_7ED1_A0B4_28DB)
        }
        _ => seed ^ (i as u64).wrapping_mul(0xA076_1D64_78BD_642F),
    }
}

/// Renders and writes frame `i` of `plan` (record last); false when it was already complete.
fn render_one(opts: &DatasetOptions, plan: &DatasetPlan, i: usize) -> Result<bool, RenderError> {
    let rig = &plan.manifest.rig;
    let f = &plan.planned[i];
    let stem = format!("frames/{i:06}");
    let record_path = opts.out_dir.join(format!("{stem}.json"));
    if finished_record(&opts.out_dir, i, f).is_some() {
        return Ok(false);
    }
    let pixel_seed = pixel_seed(opts.set, opts.seed, i, f.item);
    let (frame, lm) = render_planned(rig, &opts.source, f, opts.spp, pixel_seed, opts.layers)?;
    let files = FrameFiles {
        preview: format!("{stem}_preview.png"),
        radiance: format!("{stem}_radiance.npy"),
        depth: format!("{stem}_depth.npy"),
        mask_visible_pupil: format!("{stem}_mask_visible_pupil.png"),
        mask_pupil: format!("{stem}_mask_pupil.png"),
        layers: Some(format!("{stem}_layers.npy")),
        masks: Some(format!("{stem}_masks.npy")),
    };
    let (w, h) = (rig.camera.width_px, rig.camera.height_px);
    let put = |rel: &str, bytes: Vec<u8>| write_atomic(&opts.out_dir.join(rel), &bytes);
    put(&files.preview, png_bytes(tone_map(&frame.radiance), w, h)?)?;
    put(&files.radiance, npy_bytes(&frame.radiance)?)?;
    put(&files.depth, npy_bytes(&frame.depth_m)?)?;
    put(
        &files.mask_visible_pupil,
        mask_png(&frame.mask_visible_pupil)?,
    )?;
    put(&files.mask_pupil, mask_png(&frame.mask_pupil)?)?;
    let kept: Vec<(usize, &super::trace::DepthLayer)> = frame
        .layers
        .layers
        .iter()
        .enumerate()
        .filter(|(_, l)| !l.empty)
        .collect();
    let planes: Vec<&Mat<f32>> = kept
        .iter()
        .flat_map(|(_, l)| [&l.radiance, &l.alpha])
        .collect();
    if let Some(p) = &files.layers {
        put(p, npy_stack(&planes, Some(kept.len()))?)?;
    }
    if let Some(p) = &files.masks {
        put(
            p,
            npy_stack(&[&frame.mask_visible_pupil, &frame.mask_pupil], None)?,
        )?;
    }
    let rec = FrameRecord {
        frame: i,
        item: f.item,
        role: f.role.to_string(),
        subject: f.subject,
        state: f.state,
        gaze: f.state.gaze(),
        pupil_center_px: lm.pupil_center.px,
        pupil_center_refracted_px: lm.pupil_center_refracted_px,
        landmarks: lm,
        files,
        layers: kept
            .iter()
            .map(|(k, l)| LayerInfo {
                index: *k,
                near_m: l.near_m,
                far_m: l.far_m,
            })
            .collect(),
        pupil_visible_fraction: visible_fraction(&frame.mask_visible_pupil, &frame.mask_pupil),
    };
    let line = serde_json::to_string(&rec).map_err(|e| RenderError::Encode {
        path: record_path.display().to_string(),
        reason: e.to_string(),
    })?;
    // The record is written last: its presence marks the frame complete.
    write_atomic(&record_path, line.as_bytes())?;
    Ok(true)
}

/// Writes frames.jsonl (every frame's record, in order) and the contact sheet once every
/// frame of the plan is on disk; names the first frame that is not.
pub fn finish_dataset(opts: &DatasetOptions, plan: &DatasetPlan) -> Result<(), RenderError> {
    let mut lines = String::new();
    for i in 0..plan.planned.len() {
        let text = finished_record(&opts.out_dir, i, &plan.planned[i]).ok_or_else(|| {
            RenderError::Invalid {
                what: "out",
                reason: format!(
                    "frame {i}'s record {} is missing or unreadable (every process must write to \
                 the same directory)",
                    opts.out_dir.join(format!("frames/{i:06}.json")).display()
                ),
            }
        })?;
        lines.push_str(text.trim_end());
        lines.push('\n');
    }
    write_atomic(&opts.out_dir.join("frames.jsonl"), lines.as_bytes())?;
    contact_sheet(
        &opts.out_dir,
        plan.planned.len(),
        plan.manifest.rig.camera.width_px,
        plan.manifest.rig.camera.height_px,
    )
}

/// contact_sheet.png: the first ≤ 64 previews, 8 per row, each downsampled to ≤ 160 px wide.
fn contact_sheet(dir: &Path, frames: usize, w: usize, h: usize) -> Result<(), RenderError> {
    let n = frames.min(64);
    if n == 0 {
        return Ok(());
    }
    let step = w.div_ceil(160).max(1);
    let (tw, th) = (w.div_ceil(step), h.div_ceil(step));
    let cols = n.min(8);
    let rows = n.div_ceil(cols);
    let (sw, sh) = (cols * tw, rows * th);
    let mut sheet = vec![0u8; sw * sh];
    for i in 0..n {
        let p = dir.join(format!("frames/{i:06}_preview.png"));
        let img = image::open(&p)
            .map_err(|e| RenderError::Encode {
                path: p.display().to_string(),
                reason: e.to_string(),
            })?
            .to_luma8();
        let (x0, y0) = ((i % cols) * tw, (i / cols) * th);
        for y in 0..th {
            for x in 0..tw {
                let (sx, sy) = ((x * step) as u32, (y * step) as u32);
                if sx < img.width() && sy < img.height() {
                    sheet[(y0 + y) * sw + x0 + x] = img.get_pixel(sx, sy)[0];
                }
            }
        }
    }
    write_atomic(&dir.join("contact_sheet.png"), &png_bytes(sheet, sw, sh)?)
}

/// Σ visible / Σ unoccluded pupil coverage, None when the unoccluded pupil is out of view.
fn visible_fraction(visible: &Mat<f32>, unoccluded: &Mat<f32>) -> Option<f64> {
    let sum = |m: &Mat<f32>| {
        let mut s = 0.0f64;
        for j in 0..m.ncols() {
            for i in 0..m.nrows() {
                s += m[(i, j)] as f64;
            }
        }
        s
    };
    let total = sum(unoccluded);
    (total > 0.0).then(|| (sum(visible) / total).min(1.0))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A dataset's files have the mode `File::create` gives under this umask, not a
    /// temporary file's 0600 (a rendered dataset was owner-only).
    #[cfg(unix)]
    #[test]
    fn an_atomic_write_has_the_mode_file_create_gives() {
        let dir = tempfile::tempdir().unwrap();
        use std::os::unix::fs::PermissionsExt;
        let mode = |p: &Path| std::fs::metadata(p).unwrap().permissions().mode() & 0o777;
        let plain = dir.path().join("plain");
        std::fs::write(&plain, b"x").unwrap();
        let out = dir.path().join("frames.jsonl");
        write_atomic(&out, b"x").unwrap();
        assert_eq!(mode(&out), mode(&plain));
    }

    /// A variational triplet's frames share their pixel samples, triplets do not; every other
    /// set keeps one seed per frame (the bits of datasets rendered before).
    #[test]
    fn a_triplet_shares_its_pixel_samples_and_other_frames_do_not() {
        let v = |i: usize| pixel_seed(RenderSet::Variational, 7, i, i / 3);
        assert_eq!(v(0), v(1));
        assert_eq!(v(1), v(2));
        assert_ne!(v(2), v(3));
        assert_ne!(v(0), v(300));
        for set in [
            RenderSet::Ambiguity,
            RenderSet::Envelope,
            RenderSet::Protocol,
        ] {
            assert_ne!(pixel_seed(set, 7, 0, 0), pixel_seed(set, 7, 1, 0));
            assert_eq!(
                pixel_seed(set, 7, 5, 1),
                7 ^ 5u64.wrapping_mul(0xA076_1D64_78BD_642F)
            );
        }
    }

    /// A frame larger than the memory available is refused, one that fits is not; without a
    /// figure for the available memory nothing is refused.
    #[test]
    fn frames_that_cannot_fit_in_memory_are_refused_before_rendering() {
        let cam = Rig::default().camera;
        let need = frame_bytes(&cam, 8);
        // (4 + 2·8) f32 three times over per pixel.
        assert_eq!(need, cam.width_px * cam.height_px * 20 * 12);
        assert!(check_frame_memory(&cam, 8, Some(need)).is_ok());
        assert!(check_frame_memory(&cam, 8, None).is_ok());
        let e = check_frame_memory(&cam, 8, Some(need - 1)).unwrap_err();
        assert!(e.to_string().contains("width and height"), "{e}");
        // This machine's own figure, when it has one, is finite and a frame of the default
        // size fits in it.
        if let Some(have) = available_memory() {
            assert!(have > need, "{have} bytes available");
        }
    }

    /// One frame per thread at the main job's size; at 1280×800 with 8 layers (≈ 246 MB a
    /// frame) the 2 GiB bound keeps 8 of 64 threads' frames; never fewer than one, whatever
    /// the size.
    #[test]
    fn frames_in_flight_is_bounded_by_memory() {
        let mut cam = Rig::default().camera;
        (cam.width_px, cam.height_px) = (320, 200);
        assert_eq!(frames_in_flight(2, &cam, 8), 2);
        assert_eq!(frames_in_flight(64, &cam, 8), 64);
        (cam.width_px, cam.height_px) = (1280, 800);
        assert_eq!(frames_in_flight(64, &cam, 8), 8);
        (cam.width_px, cam.height_px) = (usize::MAX, usize::MAX);
        assert_eq!(frames_in_flight(64, &cam, 256), 1);
        assert_eq!(frames_in_flight(0, &cam, 8), 1);
    }
}

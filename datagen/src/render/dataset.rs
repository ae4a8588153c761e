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
    /// Acquisition protocol: `n` subjects × 7 stage positions × 49 targets.
    Protocol,
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
    /// Depth layers (not written to disk; kept for API symmetry with [`render`]).
    pub layers: LayerSpec,
}

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
}

/// One line of frames.jsonl.
#[derive(Debug, Clone, Serialize)]
pub struct FrameRecord {
    /// Frame index.
    pub frame: usize,
    /// Item index in the set (pair, triplet or protocol capture).
    pub item: usize,
    /// Role in the item: anchor/slip/gaze, anchor/slip_plus/gaze_plus, or capture.
    pub role: &'static str,
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
/// coincide; where that Newton solve fails the pinhole match is kept.
pub fn plan(
    set: RenderSet,
    rig: &Rig,
    source: &SceneSource,
    n: usize,
    seed: u64,
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
            for (i, c) in states::protocol(rig, &Protocol::default(), n, seed)?
                .into_iter()
                .enumerate()
            {
                out.push(PlannedFrame {
                    item: i,
                    role: "capture",
                    subject: subj(c.subject),
                    state: c.state,
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
    cam.height_px = height_px;
    Ok(Rig {
        camera: cam,
        ..rig.clone()
    })
}

fn io_err(path: &Path, source: std::io::Error) -> RenderError {
    RenderError::Io {
        path: path.display().to_string(),
        source,
    }
}

/// Writes `bytes` to `path` atomically (temporary file in the same directory, then rename).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), RenderError> {
    let dir = path.parent().unwrap_or(Path::new("."));
    let mut tmp = tempfile::NamedTempFile::new_in(dir).map_err(|e| io_err(path, e))?;
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

/// Renders the set into `opts.out_dir`; frames whose record file exists are skipped.
pub fn write_dataset(opts: &DatasetOptions) -> Result<DatasetSummary, RenderError> {
    let rig = rig_at_size(&opts.rig, opts.width_px, opts.height_px)?;
    if opts.spp == 0 {
        return Err(RenderError::Invalid {
            what: "spp",
            reason: "must be ≥ 1".into(),
        });
    }
    let planned = plan(opts.set, &rig, &opts.source, opts.n, opts.seed)?;
    let fdir = opts.out_dir.join("frames");
    std::fs::create_dir_all(&fdir).map_err(|e| io_err(&fdir, e))?;
    let bar = if opts.progress {
        indicatif::ProgressBar::new(planned.len() as u64)
    } else {
        indicatif::ProgressBar::hidden()
    };
    let (mut written, mut skipped) = (0, 0);
    let mut lines = String::new();
    for (i, f) in planned.iter().enumerate() {
        let stem = format!("frames/{i:06}");
        let record_path = opts.out_dir.join(format!("{stem}.json"));
        let done = std::fs::read_to_string(&record_path)
            .ok()
            .filter(|t| serde_json::from_str::<serde_json::Value>(t).is_ok());
        if let Some(text) = done {
            lines.push_str(text.trim_end());
            lines.push('\n');
            skipped += 1;
            bar.inc(1);
            continue;
        }
        let pixel_seed = opts.seed ^ (i as u64).wrapping_mul(0xA076_1D64_78BD_642F);
        let (frame, lm) = render_planned(&rig, &opts.source, f, opts.spp, pixel_seed, opts.layers)?;
        let files = FrameFiles {
            preview: format!("{stem}_preview.png"),
            radiance: format!("{stem}_radiance.npy"),
            depth: format!("{stem}_depth.npy"),
            mask_visible_pupil: format!("{stem}_mask_visible_pupil.png"),
            mask_pupil: format!("{stem}_mask_pupil.png"),
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
        let rec = FrameRecord {
            frame: i,
            item: f.item,
            role: f.role,
            subject: f.subject,
            state: f.state,
            gaze: f.state.gaze(),
            pupil_center_px: lm.pupil_center.px,
            pupil_center_refracted_px: lm.pupil_center_refracted_px,
            landmarks: lm,
            files,
        };
        let line = serde_json::to_string(&rec).map_err(|e| RenderError::Encode {
            path: record_path.display().to_string(),
            reason: e.to_string(),
        })?;
        // The record is written last: its presence marks the frame complete.
        write_atomic(&record_path, line.as_bytes())?;
        lines.push_str(&line);
        lines.push('\n');
        written += 1;
        bar.inc(1);
    }
    bar.finish_and_clear();
    write_atomic(&opts.out_dir.join("frames.jsonl"), lines.as_bytes())?;
    contact_sheet(
        &opts.out_dir,
        planned.len(),
        rig.camera.width_px,
        rig.camera.height_px,
    )?;
    Ok(DatasetSummary { written, skipped })
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

//! Reading a rendered dataset back: the manifest, the frame records of frames.jsonl, and per
//! frame the depth layers (L_k, α_k) and the exact pupil masks, so training never re-renders;
//! and a seeded, shuffled batcher over one or more datasets.

use super::RenderError;
use super::dataset::{DATASET_FORMAT, DatasetManifest, FrameRecord, LayerInfo};
use super::trace::LayerSpec;
use faer::Mat;
use rand::SeedableRng;
use rand::seq::SliceRandom;
use rand_chacha::ChaCha8Rng;
use std::path::{Path, PathBuf};

/// Largest image side accepted from a file (guards memory on corrupt headers).
const MAX_SIDE: u64 = 16384;

/// A dataset directory opened for reading.
#[derive(Debug, Clone)]
pub struct Dataset {
    /// Directory.
    pub dir: PathBuf,
    /// Its manifest (native grid, layers, illuminator).
    pub manifest: DatasetManifest,
    /// One record per frame, in frame order.
    pub records: Vec<FrameRecord>,
}

/// A frame's data as stored: the non-empty layers (near to far) and the pupil masks.
#[derive(Debug, Clone)]
pub struct StoredFrame {
    /// Stored layers with their slab (near to far).
    pub layers: Vec<StoredLayer>,
    /// Fraction of samples that see the pupil (lids occluding), H×W.
    pub mask_visible_pupil: Mat<f32>,
    /// Fraction of samples that would see the pupil without skin, H×W.
    pub mask_pupil: Mat<f32>,
}

/// One stored depth layer.
#[derive(Debug, Clone)]
pub struct StoredLayer {
    /// Slab index and bounds.
    pub info: LayerInfo,
    /// Premultiplied radiance L_k (W/(m²·sr)), H×W.
    pub radiance: Mat<f32>,
    /// Coverage α_k, H×W.
    pub alpha: Mat<f32>,
}

fn invalid(path: &Path, reason: impl std::fmt::Display) -> RenderError {
    RenderError::Encode {
        path: path.display().to_string(),
        reason: reason.to_string(),
    }
}

/// Reads an f32 NPY file; returns (shape, data in C order).
pub fn read_npy_f32(path: &Path) -> Result<(Vec<u64>, Vec<f32>), RenderError> {
    let bytes = std::fs::read(path).map_err(|e| RenderError::Io {
        path: path.display().to_string(),
        cause: e,
    })?;
    let npy = npyz::NpyFile::new(&bytes[..]).map_err(|e| invalid(path, e))?;
    let shape = npy.shape().to_vec();
    if shape.iter().any(|&d| d > MAX_SIDE * MAX_SIDE) {
        return Err(invalid(path, format!("implausible shape {shape:?}")));
    }
    if npy.order() != npyz::Order::C {
        return Err(invalid(path, "Fortran-ordered arrays are not supported"));
    }
    let data: Vec<f32> = npy
        .into_vec()
        .map_err(|e| invalid(path, format!("not a little-endian f32 array ({e})")))?;
    let n: u64 = shape.iter().product();
    if data.len() as u64 != n {
        return Err(invalid(path, "data length does not match the shape"));
    }
    Ok((shape, data))
}

fn plane(data: &[f32], offset: usize, h: usize, w: usize) -> Mat<f32> {
    Mat::from_fn(h, w, |i, j| data[offset + i * w + j])
}

impl Dataset {
    /// Opens `dir`: parses dataset.json and frames.jsonl (a leading byte-order mark is
    /// ignored; a malformed line is an error naming its number).
    pub fn open(dir: &Path) -> Result<Dataset, RenderError> {
        let mpath = dir.join("dataset.json");
        let text = std::fs::read_to_string(&mpath).map_err(|e| RenderError::Io {
            path: format!(
                "{} (is this a directory written by `nanoeye datagen render`?)",
                mpath.display()
            ),
            cause: e,
        })?;
        let manifest: DatasetManifest = serde_json::from_str(text.trim_start_matches('\u{feff}'))
            .map_err(|e| invalid(&mpath, e))?;
        if manifest.format != DATASET_FORMAT {
            return Err(invalid(
                &mpath,
                format!(
                    "dataset format {} is not {DATASET_FORMAT}: re-render it",
                    manifest.format
                ),
            ));
        }
        manifest.rig.validate()?;
        let jpath = dir.join("frames.jsonl");
        let text = std::fs::read_to_string(&jpath).map_err(|e| RenderError::Io {
            path: format!(
                "{} (an interrupted render? re-run it to finish)",
                jpath.display()
            ),
            cause: e,
        })?;
        let mut records = Vec::new();
        for (i, line) in text.trim_start_matches('\u{feff}').lines().enumerate() {
            if line.trim().is_empty() {
                continue;
            }
            let rec: FrameRecord = serde_json::from_str(line)
                .map_err(|e| invalid(&jpath, format!("line {}: {e}", i + 1)))?;
            if rec.frame != records.len() {
                return Err(invalid(
                    &jpath,
                    format!("line {}: frame {} out of order", i + 1, rec.frame),
                ));
            }
            records.push(rec);
        }
        if records.len() != manifest.frames {
            return Err(invalid(
                &jpath,
                format!(
                    "{} records for {} frames in dataset.json (an interrupted render? re-run it)",
                    records.len(),
                    manifest.frames
                ),
            ));
        }
        Ok(Dataset {
            dir: dir.to_path_buf(),
            manifest,
            records,
        })
    }

    /// Frames in the dataset.
    pub fn len(&self) -> usize {
        self.records.len()
    }

    /// True when the dataset holds no frame.
    pub fn is_empty(&self) -> bool {
        self.records.is_empty()
    }

    /// Native image size (rows, cols).
    pub fn shape(&self) -> (usize, usize) {
        let c = &self.manifest.rig.camera;
        (c.height_px, c.width_px)
    }

    /// The depth-layer slabs of the renderer.
    pub fn layer_spec(&self) -> LayerSpec {
        self.manifest.layers
    }

    /// Loads frame `i`'s layers and masks.
    pub fn load(&self, i: usize) -> Result<StoredFrame, RenderError> {
        let rec = self.records.get(i).ok_or_else(|| RenderError::Invalid {
            what: "frame",
            reason: format!("{i} is beyond the dataset's {} frames", self.len()),
        })?;
        let (h, w) = self.shape();
        let (Some(lp), Some(mp)) = (&rec.files.layers, &rec.files.masks) else {
            return Err(invalid(
                &self.dir,
                "frames without stored depth layers (rendered by an older version): re-render",
            ));
        };
        let lpath = self.dir.join(lp);
        let (shape, data) = read_npy_f32(&lpath)?;
        let k = rec.layers.len();
        if shape != [k as u64, 2, h as u64, w as u64] {
            return Err(invalid(
                &lpath,
                format!("shape {shape:?}, expected [{k}, 2, {h}, {w}]"),
            ));
        }
        let layers = rec
            .layers
            .iter()
            .enumerate()
            .map(|(j, info)| StoredLayer {
                info: *info,
                radiance: plane(&data, (2 * j) * h * w, h, w),
                alpha: plane(&data, (2 * j + 1) * h * w, h, w),
            })
            .collect();
        let mpath = self.dir.join(mp);
        let (shape, data) = read_npy_f32(&mpath)?;
        if shape != [2, h as u64, w as u64] {
            return Err(invalid(
                &mpath,
                format!("shape {shape:?}, expected [2, {h}, {w}]"),
            ));
        }
        Ok(StoredFrame {
            layers,
            mask_visible_pupil: plane(&data, 0, h, w),
            mask_pupil: plane(&data, h * w, h, w),
        })
    }
}

/// A (dataset, frame) pair.
pub type FrameRef = (usize, usize);

/// Seeded shuffled batches over the frames of several datasets: epoch e is the permutation
/// drawn from ChaCha8(seed, stream e), cut into batches in order (the last one may be short).
/// Deterministic and independent of thread count (nothing here runs in parallel).
#[derive(Debug, Clone)]
pub struct Batcher {
    frames: Vec<FrameRef>,
    batch: usize,
    seed: u64,
}

impl Batcher {
    /// All frames of datasets with `lens[d]` frames each, in batches of `batch`.
    pub fn new(lens: &[usize], batch: usize, seed: u64) -> Result<Batcher, RenderError> {
        if batch == 0 {
            return Err(RenderError::Invalid {
                what: "batch",
                reason: "must be ≥ 1".into(),
            });
        }
        let frames: Vec<FrameRef> = lens
            .iter()
            .enumerate()
            .flat_map(|(d, &n)| (0..n).map(move |i| (d, i)))
            .collect();
        if frames.is_empty() {
            return Err(RenderError::Invalid {
                what: "dataset",
                reason: "no frames to batch".into(),
            });
        }
        Ok(Batcher {
            frames,
            batch,
            seed,
        })
    }

    /// Batches per epoch.
    pub fn batches_per_epoch(&self) -> usize {
        self.frames.len().div_ceil(self.batch)
    }

    /// The frame order of `epoch`.
    pub fn epoch(&self, epoch: u64) -> Vec<FrameRef> {
        let mut rng = ChaCha8Rng::seed_from_u64(self.seed);
        rng.set_stream(epoch);
        let mut v = self.frames.clone();
        v.shuffle(&mut rng);
        v
    }

    /// Batch number `step` counted across epochs (step / batches_per_epoch is the epoch).
    pub fn batch(&self, step: u64) -> Vec<FrameRef> {
        let per = self.batches_per_epoch() as u64;
        let order = self.epoch(step / per);
        let b = (step % per) as usize * self.batch;
        order[b..(b + self.batch).min(order.len())].to_vec()
    }
}

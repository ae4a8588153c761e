//! Reading a rendered dataset back: the manifest, the frame records of frames.jsonl, and per
//! frame the depth layers (L_k, α_k) and the exact pupil masks, so training never re-renders;
//! and a seeded, shuffled batcher over one or more datasets.

use super::RenderError;
use super::dataset::{DATASET_FORMAT, DatasetManifest, FrameRecord, LayerInfo};
use super::trace::LayerSpec;
use faer::{Mat, MatRef};
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

/// One stored depth layer. Its planes are kept row by row, as the file holds them: S1 packs a
/// layer into its row-major grid, which from row-major planes is a stream and from column-major
/// ones a transposition (docs/bench/chain.md).
#[derive(Debug, Clone)]
pub struct StoredLayer {
    /// Slab index and bounds.
    pub info: LayerInfo,
    /// The radiance plane's transpose (W×H), so that its rows are contiguous.
    radiance_t: Mat<f32>,
    /// The coverage plane's transpose (W×H).
    alpha_t: Mat<f32>,
}

impl StoredLayer {
    /// A layer from its H×W radiance and coverage planes (copied into row-major storage).
    pub fn new(info: LayerInfo, radiance: MatRef<'_, f32>, alpha: MatRef<'_, f32>) -> Self {
        Self {
            info,
            radiance_t: radiance.transpose().to_owned(),
            alpha_t: alpha.transpose().to_owned(),
        }
    }

    /// Premultiplied radiance L_k (W/(m²·sr)), H×W, rows contiguous.
    pub fn radiance(&self) -> MatRef<'_, f32> {
        self.radiance_t.transpose()
    }

    /// Coverage α_k, H×W, rows contiguous.
    pub fn alpha(&self) -> MatRef<'_, f32> {
        self.alpha_t.transpose()
    }
}

/// Largest coverage a stored layer may hold: a fraction of samples, summed in f32 from
/// 1/spp per sample, so it may pass 1 by the sum's round-off (spp · 2⁻²⁴ at most).
const MAX_COVERAGE: f32 = 1.0 + 1e-4;

/// The first value of a plane that `ok` refuses (NaN included where `ok` compares). Each
/// column is first checked whole without an early exit, which vectorises (a `find` does
/// not: the search took a third of a paper-size frame's load), and searched only if it fails.
fn first_outside(m: &Mat<f32>, ok: impl Fn(f32) -> bool) -> Option<f32> {
    (0..m.ncols())
        .map(|j| m.col_as_slice(j))
        .filter(|c| !c.iter().fold(true, |all, &v| all & ok(v)))
        .find_map(|c| c.iter().copied().find(|&v| !ok(v)))
}

fn invalid(path: &Path, reason: impl std::fmt::Display) -> RenderError {
    RenderError::Encode {
        path: path.display().to_string(),
        reason: reason.to_string(),
    }
}

/// The shape of an NPY file's array, refused when implausibly large or not in C order.
fn c_order_shape<R: std::io::Read>(
    path: &Path,
    npy: &npyz::NpyFile<R>,
) -> Result<Vec<u64>, RenderError> {
    let shape = npy.shape().to_vec();
    if shape.iter().any(|&d| d > MAX_SIDE * MAX_SIDE) {
        return Err(invalid(path, format!("implausible shape {shape:?}")));
    }
    if npy.order() != npyz::Order::C {
        return Err(invalid(path, "Fortran-ordered arrays are not supported"));
    }
    Ok(shape)
}

/// Refuses what the NPY parser must not be given: a file that is not regular (a FIFO blocks
/// the read, `/dev/zero` never ends it) and a preamble whose claims the file cannot hold
/// ([`nanoeye_npy::check`]: npyz allocates a claimed header length and multiplies the
/// dimensions unchecked).
fn check_npy_file(path: &Path) -> Result<(), RenderError> {
    let io = |e: std::io::Error| RenderError::Io {
        path: path.display().to_string(),
        cause: e,
    };
    if !std::fs::metadata(path).map_err(io)?.is_file() {
        return Err(invalid(path, "not a regular file"));
    }
    nanoeye_npy::check_file(path)
        .map_err(io)?
        .map_err(|why| invalid(path, why))?;
    Ok(())
}

/// Reads an f32 NPY file; returns (shape, data in C order).
pub fn read_npy_f32(path: &Path) -> Result<(Vec<u64>, Vec<f32>), RenderError> {
    check_npy_file(path)?;
    let bytes = std::fs::read(path).map_err(|e| RenderError::Io {
        path: path.display().to_string(),
        cause: e,
    })?;
    let npy = npyz::NpyFile::new(&bytes[..]).map_err(|e| invalid(path, e))?;
    let shape = c_order_shape(path, &npy)?;
    let data: Vec<f32> = npy
        .into_vec()
        .map_err(|e| invalid(path, format!("not a little-endian f32 array ({e})")))?;
    // In u128: a crafted header's dimensions multiply past u64 (and wrap in the NPY parser).
    let n: u128 = shape.iter().map(|&d| u128::from(d)).product();
    if data.len() as u128 != n {
        return Err(invalid(path, "data length does not match the shape"));
    }
    Ok((shape, data))
}

/// Rows of a plane read from the file at once by [`read_npy_planes`]: the rows (160 KB at
/// 1280 columns) stay in cache while each column takes its 32 values.
const READ_ROWS: usize = 32;

/// Reads an f32 NPY file (C order) whose shape must be `expect` = [.., H, W] straight into its
/// H×W planes, in file order. The data is streamed through a buffer of `READ_ROWS` rows: no
/// copy of the whole file (64 MB per frame at 1280×800 with 8 layers) is made, and no
/// element-by-element transposition of one runs down its columns.
pub fn read_npy_planes(path: &Path, expect: &[u64]) -> Result<Vec<Mat<f32>>, RenderError> {
    read_planes(path, expect, false)
}

/// [`read_npy_planes`] without the transposition: each plane comes back as its transpose, a
/// W×H matrix whose columns are the plane's rows (the file's order, a copy per row).
pub fn read_npy_plane_rows(path: &Path, expect: &[u64]) -> Result<Vec<Mat<f32>>, RenderError> {
    read_planes(path, expect, true)
}

/// The planes of [`read_npy_planes`], or their transposes with `transposed`.
fn read_planes(
    path: &Path,
    expect: &[u64],
    transposed: bool,
) -> Result<Vec<Mat<f32>>, RenderError> {
    use std::io::Read;
    let io = |e: std::io::Error| RenderError::Io {
        path: path.display().to_string(),
        cause: e,
    };
    check_npy_file(path)?;
    let file = std::fs::File::open(path).map_err(io)?;
    // A buffer for the header: the planes' reads of READ_ROWS rows are larger for planes 128
    // or more values wide, so they go from the kernel straight into `buf` instead of through
    // a second copy (after the few bytes read with the header).
    let mut rd = std::io::BufReader::with_capacity(1 << 14, file);
    let npy = npyz::NpyFile::new(&mut rd).map_err(|e| invalid(path, e))?;
    let shape = c_order_shape(path, &npy)?;
    let little = match npy.dtype() {
        npyz::DType::Plain(t) if t.to_string() == "<f4" => true,
        npyz::DType::Plain(t) if t.to_string() == ">f4" => false,
        d => {
            return Err(invalid(
                path,
                format!("not an f32 array (dtype {})", d.descr()),
            ));
        }
    };
    if shape != expect || expect.len() < 2 {
        return Err(invalid(
            path,
            format!("shape {shape:?}, expected {expect:?}"),
        ));
    }
    let (h, w) = (
        expect[expect.len() - 2] as usize,
        expect[expect.len() - 1] as usize,
    );
    let count = expect[..expect.len() - 2].iter().product::<u64>() as usize;
    let rd = npy.into_inner();
    let mut buf = vec![0u8; READ_ROWS * w * 4];
    let mut planes = Vec::with_capacity(count);
    let (rows, cols) = if transposed { (w, h) } else { (h, w) };
    for _ in 0..count {
        // Every value is written below before the matrix takes its shape: no zeroing first
        // (a paper-size frame's 18 planes are 72 MB of memset otherwise).
        let mut m = Mat::<f32>::with_capacity(rows, cols);
        let (base, stride) = (m.as_ptr_mut(), m.col_stride() as usize);
        let col = |j: usize| {
            debug_assert!(j < cols && stride >= rows);
            // SAFETY: column j < cols of the allocation (stride ≥ rows values apart, col
            // capacity ≥ cols); as MaybeUninit, nothing unwritten is read, and each call's
            // slice is dropped before the next.
            unsafe {
                std::slice::from_raw_parts_mut(
                    base.add(j * stride).cast::<std::mem::MaybeUninit<f32>>(),
                    rows,
                )
            }
        };
        for r0 in (0..h).step_by(READ_ROWS) {
            let nr = READ_ROWS.min(h - r0);
            let bytes = &mut buf[..nr * w * 4];
            rd.read_exact(bytes).map_err(|e| {
                if e.kind() == std::io::ErrorKind::UnexpectedEof {
                    invalid(path, "data length does not match the shape")
                } else {
                    io(e)
                }
            })?;
            let value = |at: usize| {
                let b: [u8; 4] = bytes[at * 4..][..4].try_into().expect("four bytes");
                match little {
                    true => f32::from_le_bytes(b),
                    false => f32::from_be_bytes(b),
                }
            };
            if transposed {
                // A file row is a column here: a straight copy, four bytes to a value, which
                // vectorises (indexing the buffer per value did not).
                let rows = bytes.chunks_exact((w * 4).max(1));
                for (r, src) in rows.enumerate() {
                    let col = col(r0 + r).iter_mut();
                    let src = src.chunks_exact(4).map(|b| [b[0], b[1], b[2], b[3]]);
                    match little {
                        true => col.zip(src).for_each(|(v, b)| {
                            v.write(f32::from_le_bytes(b));
                        }),
                        false => col.zip(src).for_each(|(v, b)| {
                            v.write(f32::from_be_bytes(b));
                        }),
                    }
                }
            } else {
                for j in 0..w {
                    for (r, v) in col(j)[r0..r0 + nr].iter_mut().enumerate() {
                        v.write(value(r * w + j));
                    }
                }
            }
        }
        // SAFETY: rows ≤ row capacity and cols ≤ col capacity (reserved above), and every
        // value is written: each of the h file rows fills its w values (a column when
        // transposed, a row across the w columns otherwise).
        unsafe { m.set_dims(rows, cols) };
        planes.push(m);
    }
    Ok(planes)
}

/// The text of a regular file of at most `max` bytes (a FIFO blocked, `/dev/zero` was read
/// until memory ran out).
fn read_text(path: &Path, max: u64) -> std::io::Result<String> {
    let meta = std::fs::metadata(path)?;
    if !meta.is_file() || meta.len() > max {
        return Err(std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            format!("not a regular file of at most {max} bytes"),
        ));
    }
    std::fs::read_to_string(path)
}

impl Dataset {
    /// Opens `dir`: parses dataset.json and frames.jsonl (a leading byte-order mark is
    /// ignored; a malformed line is an error naming its number).
    pub fn open(dir: &Path) -> Result<Dataset, RenderError> {
        let mpath = dir.join("dataset.json");
        let text = read_text(&mpath, 1 << 20).map_err(|e| RenderError::Io {
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
        // The renderer's own bounds: a count of 10⁷ slabs was believed and allocated for.
        let ls = manifest.layers;
        let finite = ls.near_m.is_finite() && ls.far_m.is_finite();
        if !((1..=256).contains(&ls.count) && finite && ls.near_m < ls.far_m) {
            return Err(invalid(
                &mpath,
                format!("layers: need 1 ≤ count ≤ 256 and finite near < far, got {ls:?}"),
            ));
        }
        let jpath = dir.join("frames.jsonl");
        let text = read_text(&jpath, 4 << 30).map_err(|e| RenderError::Io {
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
            // Slabs of this dataset, near to far, each once: an index of 99 (of 8) panicked
            // indexing the chain's PSFs.
            let mut last = None;
            for l in &rec.layers {
                if l.index >= ls.count || last.is_some_and(|k| l.index <= k) {
                    return Err(invalid(
                        &jpath,
                        format!(
                            "line {}: layers[].index {} is not a new slab of the {} (near to far)",
                            i + 1,
                            l.index,
                            ls.count
                        ),
                    ));
                }
                last = Some(l.index);
            }
            // The frame's files inside the dataset (one named `../other/…` was read).
            let f = &rec.files;
            let inside = |p: &String| {
                Path::new(p)
                    .components()
                    .all(|c| matches!(c, std::path::Component::Normal(_)))
            };
            if !f.layers.iter().chain(&f.masks).all(inside) {
                return Err(invalid(
                    &jpath,
                    format!("line {}: files outside the dataset directory", i + 1),
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
        let k = rec.layers.len();
        let planes = read_npy_plane_rows(&lpath, &[k as u64, 2, h as u64, w as u64])?;
        let mut planes = planes.into_iter();
        let layers: Vec<StoredLayer> = rec
            .layers
            .iter()
            .map(|info| {
                let radiance_t = planes.next().expect("2k planes checked");
                let alpha_t = planes.next().expect("2k planes checked");
                StoredLayer {
                    info: *info,
                    radiance_t,
                    alpha_t,
                }
            })
            .collect();
        // Premultiplied radiance finite and ≥ 0, coverage a fraction of samples: an edited
        // file with every α at 5 imaged 4.96e8 electrons, and radiance −1000 a black frame,
        // exit 0 (a helper's audit; a NaN was refused only in the optics, naming a kernel).
        for l in &layers {
            let li = l.info.index;
            if let Some(v) = first_outside(&l.radiance_t, |v| v.is_finite() && v >= 0.0) {
                return Err(invalid(
                    &lpath,
                    format!("layer {li} holds a radiance of {v}; radiance is finite and ≥ 0"),
                ));
            }
            if let Some(v) = first_outside(&l.alpha_t, |v| (0.0..=MAX_COVERAGE).contains(&v)) {
                return Err(invalid(
                    &lpath,
                    format!("layer {li} holds a coverage of {v}, outside [0, 1]"),
                ));
            }
        }
        let mpath = self.dir.join(mp);
        let masks = read_npy_planes(&mpath, &[2, h as u64, w as u64])?;
        let [mask_visible_pupil, mask_pupil]: [Mat<f32>; 2] =
            masks.try_into().expect("two planes checked");
        // Coverage in [0, 1]: a NaN (or −5) in an edited mask reached sim's mask.npy, exit 0.
        for m in [&mask_visible_pupil, &mask_pupil] {
            for j in 0..m.ncols() {
                if let Some(v) = m.col(j).iter().find(|v| !(0.0..=1.0).contains(*v)) {
                    return Err(invalid(
                        &mpath,
                        format!("a pupil coverage of {v}, outside [0, 1]"),
                    ));
                }
            }
        }
        Ok(StoredFrame {
            layers,
            mask_visible_pupil,
            mask_pupil,
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

#[cfg(test)]
mod tests {
    use super::*;

    /// NPY bytes of `data` with shape `shape` and dtype `descr` ("<f4" or ">f4").
    fn npy(shape: &[u64], data: &[f32], descr: &str) -> Vec<u8> {
        use npyz::WriterBuilder;
        let mut buf = Vec::new();
        let dtype = npyz::DType::Plain(descr.parse().unwrap());
        let mut w = npyz::WriteOptions::<f32>::new()
            .dtype(dtype)
            .shape(shape)
            .writer(&mut buf)
            .begin_nd()
            .unwrap();
        for v in data {
            w.push(v).unwrap();
        }
        w.finish().unwrap();
        buf
    }

    fn streamed_planes_equal_the_whole_file_read_at(dir: &Path, h: usize, w: usize) {
        let shape = [3u64, 2, h as u64, w as u64];
        let data: Vec<f32> = (0..6 * h * w)
            .map(|i| (i as f32 * 0.37).sin() * 1e3 + i as f32 * 1e-3)
            .collect();
        for descr in ["<f4", ">f4"] {
            let p = dir.join(format!("x{}.npy", &descr[..1] == "<"));
            std::fs::write(&p, npy(&shape, &data, descr)).unwrap();
            let planes = read_npy_planes(&p, &shape).unwrap();
            let rows = read_npy_plane_rows(&p, &shape).unwrap();
            let (s, whole) = read_npy_f32(&p).unwrap();
            assert_eq!(s, shape);
            assert_eq!((planes.len(), rows.len()), (6, 6));
            for (k, (m, t)) in planes.iter().zip(&rows).enumerate() {
                assert_eq!((t.nrows(), t.ncols()), (w, h));
                for i in 0..h {
                    for j in 0..w {
                        let at = whole[k * h * w + i * w + j].to_bits();
                        assert_eq!(m[(i, j)].to_bits(), at, "{descr} plane {k} ({i}, {j})");
                        assert_eq!(t[(j, i)].to_bits(), at, "{descr} rows {k} ({i}, {j})");
                    }
                }
            }
        }
    }

    /// Planes of 37×53 and 37×150 (more than one block of rows, not a multiple of it; a
    /// block of the wider ones is larger than the header's buffer, so its reads bypass it)
    /// in both byte orders equal the whole-file read, element for element; a short file,
    /// another shape and another dtype are errors naming the file.
    #[test]
    fn streamed_planes_equal_the_whole_file_read() {
        let dir = tempfile::tempdir().unwrap();
        for w in [150usize, 53] {
            streamed_planes_equal_the_whole_file_read_at(dir.path(), 37, w);
        }
        let (h, w) = (37usize, 53usize);
        let shape = [3u64, 2, h as u64, w as u64];
        let p = dir.path().join("xtrue.npy");
        let bytes = std::fs::read(&p).unwrap();
        let short = dir.path().join("short.npy");
        std::fs::write(&short, &bytes[..bytes.len() - 4]).unwrap();
        // Refused by the preamble's check, before the parser, for the data it lacks.
        let e = read_npy_planes(&short, &shape).unwrap_err().to_string();
        assert!(
            e.contains("short.npy") && e.contains("bytes of data"),
            "{e}"
        );
        let e = read_npy_plane_rows(&short, &shape).unwrap_err().to_string();
        assert!(
            e.contains("short.npy") && e.contains("bytes of data"),
            "{e}"
        );
        let e = read_npy_planes(&p, &[3, 2, h as u64, w as u64 + 1])
            .unwrap_err()
            .to_string();
        assert!(e.contains("xtrue.npy") && e.contains("expected"), "{e}");
        let f8 = dir.path().join("f8.npy");
        let mut buf = Vec::new();
        {
            use npyz::WriterBuilder;
            let mut wr = npyz::WriteOptions::<f64>::new()
                .default_dtype()
                .shape(&[2, 2])
                .writer(&mut buf)
                .begin_nd()
                .unwrap();
            for v in [1.0f64, 2.0, 3.0, 4.0] {
                wr.push(&v).unwrap();
            }
            wr.finish().unwrap();
        }
        std::fs::write(&f8, buf).unwrap();
        let e = read_npy_planes(&f8, &[2, 2]).unwrap_err().to_string();
        assert!(e.contains("f8.npy") && e.contains("f32"), "{e}");
    }
}

//! `nanoeye track`: sensor frames in, gaze out, one JSON line per frame (docs/run.md, "`nanoeye track`").
//!
//! Model: a run directory of `search train` or `nanoeye run` (its `checkpoint.bin`, `rig.json`
//! and, when present, the REA's selection in `rea_state.json`). Frames: DN images on the
//! model's p̂ grid — NPY (f32 or f64, [H, W] or [N, H, W], e.g. `nanoeye sim`'s sensor.npy),
//! 8- or 16-bit grayscale PNG (full scale mapped to the ADC range), or raw frames on stdin,
//! each a 16-byte header
//! `NEYE`, u32 LE width, u32 LE height, u32 LE 0, then width·height f32 LE DN values.

use anyhow::{Context, Result, bail};
use clap::Args;
use faer::Mat;
use nanoeye_gaze::{GazeSolver, PupilCentre, Rig, solver_for};
use nanoeye_nets::{Arch, Inference};
use nanoeye_sensor::SensorConfig;
use std::io::{BufWriter, Read, Write};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Largest recalibrated network file read from a run (bytes): the supernet's weights, tens of
/// MB at the default sizes.
const MAX_NET_BYTES: u64 = 4 << 30;
/// Largest search state read from a run (bytes): the evaluated subnets' records.
const MAX_STATE_BYTES: u64 = 256 << 20;

/// `nanoeye track` options.
#[derive(Debug, Args)]
pub struct TrackArgs {
    /// Run directory (checkpoint.bin, rig.json).
    #[arg(long)]
    model: PathBuf,
    /// Directory of frames (.npy, .png), read in name order; in a `nanoeye sim` output
    /// directory (it holds sim.json), its sensor.npy only.
    #[arg(long, conflicts_with = "stdin")]
    frames: Option<PathBuf>,
    /// Read raw frames from standard input (header NEYE, u32 w, u32 h, u32 0, f32 DN).
    #[arg(long)]
    stdin: bool,
    /// Subnet: best (the REA's choice, else min), min, max or file:ARCH.json.
    #[arg(long, default_value = "best")]
    subnet: String,
    /// One JSON object per line (the default and only output format; kept for scripts).
    #[arg(long)]
    json_lines: bool,
}

struct Model {
    /// The selected subnet compiled for batch-1 inference on the sensor grid.
    inf: Inference,
    /// Normalised network input and sigmoid mask, reused across frames.
    x: Vec<f32>,
    probs: Mat<f32>,
    solver: Box<dyn GazeSolver + Send + Sync>,
    /// How the solver takes the pupil centre from the mask (the run's `pupil_centre`).
    centre: PupilCentre,
    shape: (usize, usize),
    black: f32,
    span: f32,
    max_dn: f32,
}

fn load(a: &TrackArgs) -> Result<Model> {
    // `nanoeye run` leaves the selected subnet fine-tuned (with its final φ and p̂) in
    // selected.bin; a `search train` run has only checkpoint.bin.
    let sel = a.model.join("selected.bin");
    let ck = if sel.exists() {
        sel
    } else {
        a.model.join("checkpoint.bin")
    };
    let (mut net, pitch_um, tcfg) = nanoeye_search::load_model(&ck)
        .with_context(|| format!("--model {}", a.model.display()))?;
    // `nanoeye run` leaves the selected subnet with BN recalibrated exactly (tracker_net.bin);
    // without it the running statistics of training are used.
    let tuned = a.model.join("tracker_net.bin");
    let tuned_arch = a.model.join("tracker_arch.json");
    let have_tuned = tuned.exists() && tuned_arch.exists();
    // ... and the min and max subnets of the same weights with their own statistics.
    let recalibrated = match a.subnet.as_str() {
        "best" if have_tuned => Some(tuned.clone()),
        "min" | "max" => {
            Some(a.model.join(format!("tracker_net_{}.bin", a.subnet))).filter(|p| p.exists())
        }
        _ => None,
    };
    if let Some(p) = &recalibrated {
        // Regular files of bounded size, like every file of the run read here: a FIFO blocked
        // the read and `/dev/zero` was read until memory ran out.
        let b = crate::util::read_small(p, MAX_NET_BYTES)
            .with_context(|| format!("--model {}", p.display()))?;
        nanoeye_nets::checkpoint::from_bytes(&mut net, &b)
            .with_context(|| format!("--model {}", p.display()))?;
    }
    let rig_text =
        crate::util::read_small_text(&a.model.join("rig.json"), crate::util::MAX_ARCH_BYTES)
            .with_context(|| {
                format!(
                    "--model {}: rig.json (re-run `search train`)",
                    a.model.display()
                )
            })?;
    let rig0 =
        Rig::from_json(&rig_text).with_context(|| format!("--model {}", a.model.display()))?;
    let cam = rig0
        .camera
        .with_pitch(pitch_um * 1e-6)
        .with_context(|| format!("--model {}: p̂ {pitch_um} µm", a.model.display()))?;
    let shape = (cam.height_px, cam.width_px);
    let rig = Rig {
        camera: cam,
        ..rig0
    };
    let arch = match a.subnet.as_str() {
        "min" => Arch::min(),
        "max" => Arch::max(),
        "best" if have_tuned => {
            let t = crate::util::read_small_text(&tuned_arch, crate::util::MAX_ARCH_BYTES)
                .with_context(|| format!("--model {}", tuned_arch.display()))?;
            crate::util::arch_layout(&t)
                .with_context(|| format!("--model {}", tuned_arch.display()))?;
            serde_json::from_str(&t).with_context(|| format!("--model {}", tuned_arch.display()))?
        }
        "best" => best_arch(&a.model)?.unwrap_or_else(Arch::min),
        s => {
            let p = s
                .strip_prefix("file:")
                .with_context(|| format!("--subnet: '{s}' is not best, min, max or file:A.json"))?;
            let t = crate::util::read_small_text(Path::new(p), crate::util::MAX_ARCH_BYTES)
                .with_context(|| format!("--subnet {p}"))?;
            crate::util::arch_layout(&t).with_context(|| format!("--subnet {p}"))?;
            let a: Arch = serde_json::from_str(&t).with_context(|| format!("--subnet {p}"))?;
            a.validate().with_context(|| format!("--subnet {p}"))?;
            a
        }
    };
    if recalibrated.is_none() {
        // Supernet BN statistics are a running mixture over every subnet trained; only
        // `nanoeye run`'s tracker_net*.bin hold statistics recalibrated for one subnet (B.6).
        eprintln!(
            "warning: --subnet {}: batch norms use the training run's running statistics, not \
             ones recalibrated for this subnet (only best, min and max of a `nanoeye run` output \
             are recalibrated); expect larger errors than the run's reports",
            a.subnet
        );
    }
    let s = SensorConfig::default();
    let inf = Inference::new(&net, &arch, shape.0, shape.1)
        .with_context(|| format!("--model {}", a.model.display()))?;
    Ok(Model {
        inf,
        x: vec![0.0; shape.0 * shape.1],
        probs: Mat::zeros(shape.0, shape.1),
        // The solver the run was validated with (refraction-aware unless it said otherwise).
        solver: solver_for(&rig, tcfg.solver)?,
        centre: tcfg.pupil_centre,
        shape,
        black: s.black_level_dn as f32,
        span: (s.max_dn() - s.black_level_dn) as f32,
        max_dn: s.max_dn() as f32,
    })
}

/// The subnet `search rea` deploys from RUN/rea_state.json (`search::rea::pick_best`: the best
/// fitness within the budget), `None` without a search; a state that cannot be read is an
/// error, not the min subnet in its place.
fn best_arch(run: &Path) -> Result<Option<Arch>> {
    let p = run.join("rea_state.json");
    let Some(text) = crate::util::read_record(&p, MAX_STATE_BYTES)
        .with_context(|| format!("--model: {}", p.display()))?
    else {
        return Ok(None);
    };
    let st: nanoeye_search::ReaState = serde_json::from_str(&text)
        .with_context(|| format!("--model: {} is not a search state", p.display()))?;
    Ok(
        nanoeye_search::rea::pick_best(&st.evaluated, st.config.budget_macs)
            .map(|i| i.arch.clone()),
    )
}

/// A frame source: (name, DN image) or a per-frame error.
type Frame = std::result::Result<(String, Mat<f32>), String>;

/// Passes each frame of an [H, W] or [N, H, W] f32/f64 NPY at `path` to `f`, read one frame
/// at a time: a `nanoeye sim` of 100,000 frames is gigabytes (all of it was read at once, and
/// copied twice). A file that cannot be read gives one error frame; a file cut short, an error
/// frame where its data ends.
fn npy_frames(
    path: &Path,
    grid: (usize, usize),
    mut f: impl FnMut(Frame) -> Result<()>,
) -> Result<()> {
    let name = path.display().to_string();
    let mut rd = match open_npy(path) {
        Ok(v) => v,
        Err(e) => return f(Err(format!("{name}: {e}"))),
    };
    let (n, h, w) = match rd.shape[..] {
        [h, w] => (1, h, w),
        [n, h, w] => (n, h, w),
        _ => {
            return f(Err(format!(
                "{name}: shape {:?} is not [H, W] or [N, H, W]",
                rd.shape
            )));
        }
    };
    // Before a frame's buffer is allocated (a 128-byte header claiming 65536² frames asked for
    // 16 GiB): frames of another size are one error for the file, not one per frame.
    if let Some(e) = off_grid((h, w), grid) {
        return f(Err(format!("{name}: {e}")));
    }
    let mut plane = vec![0f32; h * w];
    for k in 0..n {
        let label = if n == 1 {
            name.clone()
        } else {
            format!("{name}[{k}]")
        };
        if let Err(e) = rd.read_into(&mut plane) {
            return f(Err(format!("{label}: {e}")));
        }
        f(Ok((label, Mat::from_fn(h, w, |i, j| plane[i * w + j]))))?;
    }
    Ok(())
}

/// An NPY file's shape and a reader of its values as f32, in C order.
struct NpyStream {
    shape: Vec<usize>,
    values: Box<dyn Iterator<Item = std::io::Result<f32>>>,
}

impl NpyStream {
    /// Fills `out` with the next `out.len()` values.
    fn read_into(&mut self, out: &mut [f32]) -> Result<()> {
        const CUT: &str = "the file ends before its shape's last value";
        for v in out.iter_mut() {
            *v = match self.values.next() {
                Some(Ok(v)) => v,
                Some(Err(e)) if e.kind() == std::io::ErrorKind::UnexpectedEof => bail!(CUT),
                Some(Err(e)) => return Err(e.into()),
                None => bail!(CUT),
            };
        }
        Ok(())
    }
}

/// Opens an NPY file of frames: a regular file whose shape has at most three dimensions of at
/// most 65536, in C order, f32 or f64.
fn open_npy(path: &Path) -> Result<NpyStream> {
    // A FIFO or a device named *.npy would be read without end.
    if !std::fs::metadata(path)?.is_file() {
        bail!("not a regular file");
    }
    // Before the NPY parser allocates the header length it reads and multiplies the
    // dimensions unchecked. A file cut short passes: its frames up to the cut are read.
    if let Some(c) = nanoeye_npy::claim_file(path)?.map_err(anyhow::Error::msg)? {
        let d = c.dims;
        if d.len() > 3 || d.iter().any(|&v| v == 0 || v > 1 << 16) {
            bail!("implausible shape {d:?}");
        }
    }
    let rd = std::io::BufReader::with_capacity(1 << 16, std::fs::File::open(path)?);
    let npy = npyz::NpyFile::new(rd)?;
    let shape: Vec<usize> = npy.shape().iter().map(|&d| d as usize).collect();
    if shape.iter().any(|&d| d == 0 || d > 1 << 16) || shape.len() > 3 {
        bail!("implausible shape {shape:?}");
    }
    if npy.order() != npyz::Order::C {
        bail!("Fortran-ordered arrays are not supported");
    }
    let descr = npy.dtype().descr();
    let values: Box<dyn Iterator<Item = std::io::Result<f32>>> = if descr.contains("f8") {
        Box::new(npy.data::<f64>()?.map(|v| v.map(|v| v as f32)))
    } else {
        Box::new(npy.data::<f32>()?)
    };
    Ok(NpyStream { shape, values })
}

/// Why a frame of `frame` = (rows, columns) cannot go through a model whose sensor grid at p̂
/// is `grid`; None where they agree.
fn off_grid(frame: (usize, usize), grid: (usize, usize)) -> Option<String> {
    (frame != grid).then(|| {
        format!(
            "frame is {}×{}, the model's sensor grid at p̂ is {}×{}",
            frame.1, frame.0, grid.1, grid.0
        )
    })
}

/// A grayscale PNG (8 or 16 bits) as DN: full scale maps to the ADC's `max_dn`. Its size is
/// read from the header and checked against `grid` before the image is decoded (a 519 KB PNG
/// of 23100² pixels was decoded, copied and converted — 3 GB — before its size was compared);
/// colour is refused rather than converted by luma, and 16 bits are kept (they were cut to 8).
fn png_frame(path: &Path, max_dn: f32, grid: (usize, usize)) -> Frame {
    let name = path.display().to_string();
    let fail = |e: &dyn std::fmt::Display| format!("{name}: {e}");
    // A FIFO named *.png would block the decoder.
    if !std::fs::metadata(path).map_err(|e| fail(&e))?.is_file() {
        return Err(fail(&"not a regular file"));
    }
    let open = || {
        image::ImageReader::open(path)
            .and_then(|r| r.with_guessed_format())
            .map_err(|e| fail(&e))
    };
    let (w, h) = open()?.into_dimensions().map_err(|e| fail(&e))?;
    if let Some(e) = off_grid((h as usize, w as usize), grid) {
        return Err(fail(&e));
    }
    let dn = |v: f32, full: f32| v / full * max_dn;
    let m = match open()?.decode().map_err(|e| fail(&e))? {
        image::DynamicImage::ImageLuma8(g) => Mat::from_fn(h as usize, w as usize, |i, j| {
            dn(f32::from(g.get_pixel(j as u32, i as u32)[0]), 255.0)
        }),
        image::DynamicImage::ImageLuma16(g) => Mat::from_fn(h as usize, w as usize, |i, j| {
            dn(f32::from(g.get_pixel(j as u32, i as u32)[0]), 65535.0)
        }),
        other => {
            return Err(fail(&format!(
                "a {:?} image; frames are 8- or 16-bit grayscale (a sensor's DN), not colour",
                other.color()
            )));
        }
    };
    Ok((name, m))
}

/// Whether a file extension is `want`, in any case (`F.PNG` was skipped).
fn is_ext(ext: &std::ffi::OsStr, want: &str) -> bool {
    ext.to_str().is_some_and(|e| e.eq_ignore_ascii_case(want))
}

fn stdin_frame(r: &mut impl Read) -> Option<Frame> {
    let mut hdr = [0u8; 16];
    // End of input only between frames: a header cut short is an error, not the end.
    let mut got = 0;
    while got < hdr.len() {
        match r.read(&mut hdr[got..]) {
            Ok(0) if got == 0 => return None,
            Ok(0) => {
                return Some(Err(format!(
                    "stdin: truncated frame header ({got} of 16 bytes)"
                )));
            }
            Ok(n) => got += n,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Some(Err(format!("stdin: {e}"))),
        }
    }
    if &hdr[..4] != b"NEYE" {
        return Some(Err("stdin: frame header does not start with NEYE".into()));
    }
    let w = u32::from_le_bytes(hdr[4..8].try_into().expect("4")) as usize;
    let h = u32::from_le_bytes(hdr[8..12].try_into().expect("4")) as usize;
    if w == 0 || h == 0 || w > 1 << 14 || h > 1 << 14 {
        return Some(Err(format!("stdin: implausible frame size {w}×{h}")));
    }
    let reserved = u32::from_le_bytes(hdr[12..16].try_into().expect("4"));
    if reserved != 0 {
        return Some(Err(format!(
            "stdin: the header's fourth field is {reserved}, must be 0 (reserved)"
        )));
    }
    let mut buf = vec![0u8; w * h * 4];
    if let Err(e) = r.read_exact(&mut buf) {
        return Some(Err(format!("stdin: truncated frame ({e})")));
    }
    let m = Mat::from_fn(h, w, |i, j| {
        let k = (i * w + j) * 4;
        f32::from_le_bytes(buf[k..k + 4].try_into().expect("4"))
    });
    Some(Ok(("stdin".into(), m)))
}

/// Why a frame gave no gaze: its input was not a valid frame for this model, or the chain
/// found no solution in a valid frame (no pupil, say).
enum FrameError {
    Input(String),
    Solve(String),
}

/// Slippage (m, the estimate's length) past which a frame's estimate is marked out of range:
/// the supplement's datasets slip at most 25 mm (Table S2: the anchor's ≤ 20 mm along the
/// bridge plus slip+'s ≤ 5 mm) and the main job's training envelope at most about 25.6 mm
/// (20 mm along the bridge plus the stage's box, x ±2.5 mm and z ±5 mm). Past 30 mm the frame
/// is unlike anything the network learned from (noise frames gave estimates of kilometres).
const SLIP_RANGE_M: f64 = 0.030;

/// Whether slippage estimate `s` (m) lies within [`SLIP_RANGE_M`] (false for a NaN).
fn slip_in_range(s: &[f64]) -> bool {
    s.iter().map(|v| v * v).sum::<f64>().sqrt() <= SLIP_RANGE_M
}

fn track_one(m: &mut Model, img: &Mat<f32>) -> Result<serde_json::Value, FrameError> {
    let (h, w) = m.shape;
    if let Some(e) = off_grid((img.nrows(), img.ncols()), m.shape) {
        return Err(FrameError::Input(e));
    }
    for i in 0..h {
        for j in 0..w {
            let v = img[(i, j)];
            if !v.is_finite() {
                return Err(FrameError::Input(format!("non-finite value at ({i}, {j})")));
            }
            // The ADC gives 0 ..= max DN; a value outside is not this sensor's frame.
            if !(0.0..=m.max_dn).contains(&v) {
                return Err(FrameError::Input(format!(
                    "value {v} DN at ({i}, {j}) is outside the sensor's range 0..={} DN",
                    m.max_dn
                )));
            }
            m.x[i * w + j] = (v - m.black) / m.span;
        }
    }
    let o = m
        .inf
        .run(&m.x)
        .map_err(|e| FrameError::Solve(e.to_string()))?;
    // The pupil centre is taken from the soft mask, as in training and evaluation. Confidence: the largest pupil
    // probability in the frame (a frame without any confident pupil pixel says so).
    let mut conf = 0.0f32;
    for i in 0..h {
        for j in 0..w {
            let p = 1.0 / (1.0 + (-o.mask_logits[i * w + j]).exp());
            m.probs[(i, j)] = p;
            conf = conf.max(p);
        }
    }
    let slip = o.slip.map(|v| v as f64 * 1e-3);
    let sol = m
        .solver
        .solve_mask_with(m.probs.as_ref(), slip, m.centre)
        .map_err(|e| FrameError::Solve(e.to_string()))?;
    let conf = conf as f64;
    Ok(serde_json::json!({
        "gaze": sol.gaze,
        "pupil_px": sol.pupil_px,
        "slip_m": slip,
        "slip_in_range": slip_in_range(&slip),
        "confidence": conf,
        "fallback": sol.fallback,
    }))
}

/// Runs `nanoeye track`.
pub fn track(a: TrackArgs) -> Result<()> {
    let mut m = load(&a)?;
    if a.frames.is_none() && !a.stdin {
        bail!("--frames DIR or --stdin: say where the frames come from");
    }
    let (max_dn, grid) = (m.max_dn, m.shape);
    let out = std::io::stdout();
    let mut out = BufWriter::new(out.lock());
    // Frames that were not valid input (the first one's index, source and reason, and how
    // many): the tracker goes on past them, then exits non-zero.
    let mut invalid: Option<(usize, String, String)> = None;
    let mut n_invalid = 0usize;
    let mut far = SlipTally::default();
    let mut emit = |i: usize, name: &str, f: std::result::Result<Mat<f32>, String>| -> Result<()> {
        let t = Instant::now();
        let ran = f.is_ok();
        let r = match f {
            Ok(img) => track_one(&mut m, &img),
            Err(e) => Err(FrameError::Input(e)),
        };
        let us = t.elapsed().as_micros() as u64;
        let r = r.map_err(|e| match e {
            FrameError::Input(e) => {
                n_invalid += 1;
                invalid.get_or_insert_with(|| (i, name.to_string(), e.clone()));
                e
            }
            FrameError::Solve(e) => e,
        });
        let line = match r {
            Ok(mut v) => {
                far.note(i, &v);
                v["frame"] = i.into();
                v["source"] = name.into();
                v["latency_us"] = us.into();
                v
            }
            // The time spent on a frame that failed counts too (a tracker's budget is per
            // frame, found or not).
            Err(e) => {
                let mut v = serde_json::json!({"frame": i, "source": name, "error": e});
                if ran {
                    v["latency_us"] = us.into();
                }
                v
            }
        };
        writeln!(out, "{line}")?;
        Ok(())
    };
    let mut i = 0;
    if let Some(dir) = &a.frames {
        let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
            .with_context(|| format!("--frames {}", dir.display()))?
            .flatten()
            .map(|e| e.path())
            .filter(|p| {
                p.extension()
                    .is_some_and(|e| is_ext(e, "npy") || is_ext(e, "png"))
            })
            .collect();
        // A `nanoeye sim` output directory also holds the ground-truth masks (mask.npy); they
        // are not frames, and tracking them would report nonsense gaze for every one.
        if dir.join("sim.json").is_file() {
            let before = files.len();
            files.retain(|p| p.file_name().is_some_and(|n| n == "sensor.npy"));
            if files.len() < before {
                eprintln!(
                    "--frames {}: a `nanoeye sim` output (sim.json); tracking only sensor.npy",
                    dir.display()
                );
            }
        }
        files.sort();
        if files.is_empty() {
            bail!("--frames {}: no .npy or .png files", dir.display());
        }
        for p in files {
            let mut one = |f: Frame| -> Result<()> {
                match f {
                    Ok((name, img)) => emit(i, &name, Ok(img))?,
                    Err(e) => emit(i, &p.display().to_string(), Err(e))?,
                }
                i += 1;
                Ok(())
            };
            if p.extension().is_some_and(|e| is_ext(e, "png")) {
                one(png_frame(&p, max_dn, grid))?;
            } else {
                npy_frames(&p, grid, one)?;
            }
        }
    } else {
        let stdin = std::io::stdin();
        let mut r = stdin.lock();
        while let Some(f) = stdin_frame(&mut r) {
            let bad = f.is_err();
            match f {
                Ok((name, img)) => emit(i, &name, Ok(img))?,
                Err(e) => emit(i, "stdin", Err(e))?,
            }
            i += 1;
            if bad {
                // A broken header desynchronises the stream: stop after reporting it.
                break;
            }
        }
        // As `--frames` with no frame file: nothing tracked is not a success (it exited 0
        // with no line; a helper's audit).
        if i == 0 {
            bail!("--stdin: the input ended before its first frame; nothing to track");
        }
    }
    out.flush()?;
    if let Some(w) = far.warning() {
        eprintln!("{w}");
    }
    if let Some((i, name, e)) = invalid {
        let e = e.strip_prefix(&format!("{name}: ")).unwrap_or(&e);
        bail!(
            "{n_invalid} input frame(s) were not valid frames for this model (each has its error line); the first, frame {i} from {name}: {e}"
        );
    }
    Ok(())
}

/// Tracked frames whose slippage estimate left [`SLIP_RANGE_M`]: how many, of how many, and
/// the first one's index, for one line on stderr after the stream (each frame's line says it
/// too, but a reader of a long stream should not have to scan for it).
#[derive(Default)]
struct SlipTally {
    tracked: usize,
    far: usize,
    first: Option<usize>,
}

impl SlipTally {
    /// Counts frame `i`'s result line `v`.
    fn note(&mut self, i: usize, v: &serde_json::Value) {
        self.tracked += 1;
        if v["slip_in_range"] == false {
            self.far += 1;
            self.first.get_or_insert(i);
        }
    }

    /// The warning, when any tracked frame's slippage was out of range.
    fn warning(&self) -> Option<String> {
        let first = self.first?;
        Some(format!(
            "warning: {} of {} tracked frames estimated a slippage beyond {:.0} mm (first: frame \
             {first}), outside what the model was trained on; their gaze is an extrapolation",
            self.far,
            self.tracked,
            SLIP_RANGE_M * 1e3
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The stream's warning counts the frames out of range and names the first; none is
    /// printed when every frame is in range.
    #[test]
    fn the_tally_counts_frames_with_slippage_out_of_range() {
        let mut t = SlipTally::default();
        t.note(0, &serde_json::json!({"slip_in_range": true}));
        t.note(1, &serde_json::json!({"slip_in_range": true}));
        assert_eq!(t.warning(), None);
        t.note(2, &serde_json::json!({"slip_in_range": false}));
        t.note(3, &serde_json::json!({"slip_in_range": true}));
        t.note(4, &serde_json::json!({"slip_in_range": false}));
        let w = t.warning().expect("a warning");
        assert!(w.contains("2 of 5 tracked frames"), "{w}");
        assert!(w.contains("beyond 30 mm (first: frame 2)"), "{w}");
    }

    /// Table S2's largest slip (25 mm) is in range, kilometres and NaN are not.
    #[test]
    fn slippage_past_30_mm_is_out_of_range() {
        assert!(slip_in_range(&[0.0, -0.020, 0.005]));
        assert!(slip_in_range(&[0.018, 0.0, -0.0239]));
        assert!(!slip_in_range(&[0.018, 0.0, -0.0241]));
        assert!(!slip_in_range(&[2e3, 0.0, 0.0]));
        assert!(!slip_in_range(&[f64::NAN, 0.0, 0.0]));
    }

    /// A raw frame: header with `reserved` in its fourth field, then w·h DN values.
    fn raw(w: u32, h: u32, reserved: u32, dn: f32) -> Vec<u8> {
        let mut b = b"NEYE".to_vec();
        for v in [w, h, reserved] {
            b.extend(v.to_le_bytes());
        }
        for _ in 0..w * h {
            b.extend(dn.to_le_bytes());
        }
        b
    }

    fn frames(bytes: &[u8]) -> Vec<Frame> {
        let mut r = std::io::Cursor::new(bytes);
        std::iter::from_fn(|| stdin_frame(&mut r))
            .take(10)
            .collect()
    }

    #[test]
    fn stdin_ends_only_between_frames_and_checks_the_reserved_field() {
        assert!(frames(&[]).is_empty());
        let one = raw(3, 2, 0, 7.0);
        let f = frames(&one);
        assert_eq!(f.len(), 1);
        let (name, m) = f[0].as_ref().unwrap();
        assert_eq!(
            (name.as_str(), m.nrows(), m.ncols(), m[(1, 2)]),
            ("stdin", 2, 3, 7.0)
        );
        // A header cut short, alone or after a whole frame, is an error, not the end.
        for tail in [&b"XYZW"[..], b"N", b"NEYE\x40\x01"] {
            let mut b = one.clone();
            b.extend_from_slice(tail);
            let f = frames(&b);
            assert_eq!(f.len(), 2, "{tail:?}");
            let e = f[1].as_ref().unwrap_err();
            assert!(
                e.contains(&format!("truncated frame header ({} of 16", tail.len())),
                "{e}"
            );
            assert!(frames(tail)[0].is_err());
        }
        let e = frames(&raw(3, 2, 7, 1.0)).remove(0).unwrap_err();
        assert!(e.contains("fourth field is 7, must be 0"), "{e}");
    }

    /// An NPY v1 file of `descr` ('<f4' or '<f8') with `shape` and `values` (as written: the
    /// data may be cut short of the shape).
    fn npy(descr: &str, shape: &[usize], values: &[f64]) -> Vec<u8> {
        let dims: Vec<String> = shape.iter().map(|d| format!("{d}, ")).collect();
        let mut head = format!(
            "{{'descr': '{descr}', 'fortran_order': False, 'shape': ({}), }}",
            dims.concat()
        );
        while (10 + head.len() + 1) % 16 != 0 {
            head.push(' ');
        }
        head.push('\n');
        let mut b = b"\x93NUMPY\x01\x00".to_vec();
        b.extend((head.len() as u16).to_le_bytes());
        b.extend(head.as_bytes());
        for &v in values {
            if descr == "<f4" {
                b.extend((v as f32).to_le_bytes());
            } else {
                b.extend(v.to_le_bytes());
            }
        }
        b
    }

    fn npy_file_frames(bytes: &[u8]) -> Vec<Frame> {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("f.npy");
        std::fs::write(&p, bytes).unwrap();
        let mut out = Vec::new();
        npy_frames(&p, (2, 2), |f| {
            out.push(f);
            Ok(())
        })
        .unwrap();
        out
    }

    #[test]
    fn npy_frames_stream_one_frame_at_a_time_and_name_a_cut_file() {
        let values: Vec<f64> = (0..12).map(f64::from).collect();
        for descr in ["<f4", "<f8"] {
            // Three 2×2 frames, row-major: frame k's (i, j) is 4k + 2i + j.
            let f = npy_file_frames(&npy(descr, &[3, 2, 2], &values));
            assert_eq!(f.len(), 3);
            for (k, fr) in f.iter().enumerate() {
                let (name, m) = fr.as_ref().unwrap();
                assert!(name.ends_with(&format!("f.npy[{k}]")), "{name}");
                assert_eq!(m[(1, 0)], (4 * k + 2) as f32);
            }
            // Cut in the third frame: two frames, then an error naming the third.
            let f = npy_file_frames(&npy(descr, &[3, 2, 2], &values[..10]));
            assert_eq!(f.len(), 3);
            assert!(f[1].is_ok());
            let e = f[2].as_ref().unwrap_err();
            assert!(e.contains("f.npy[2]") && e.contains("ends before"), "{e}");
        }
        // One [H, W] frame keeps the file's name; a 4-D shape is one error.
        let f = npy_file_frames(&npy("<f4", &[2, 2], &values[..4]));
        assert!(f[0].as_ref().unwrap().0.ends_with("f.npy"));
        let f = npy_file_frames(&npy("<f4", &[1, 1, 2, 2], &values[..4]));
        assert_eq!(f.len(), 1);
        assert!(f[0].is_err());
        // Frames of another size than the model's grid: one error for the file, before a
        // frame's buffer is allocated (a header alone claiming 65536² frames asked for 16 GiB).
        for shape in [&[65536usize, 65536][..], &[4, 3, 3]] {
            let f = npy_file_frames(&npy("<f4", shape, &[]));
            assert_eq!(f.len(), 1, "{shape:?}");
            let e = f[0].as_ref().unwrap_err();
            assert!(e.contains("sensor grid at p̂ is 2×2"), "{e}");
        }
    }
}

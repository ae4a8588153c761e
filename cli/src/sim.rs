//! `nanoeye sim`: a rendered dataset through the simulated camera (lens → S1 → sensor at p̂),
//! and `nanoeye search loss`: the task loss of a subnet on the chain's output with ∂L/∂φ and
//! ∂L/∂p̂ (docs/chain.md).

use crate::util;
use anyhow::{Context, Result, bail};
use clap::{Args, Subcommand};
use faer::Mat;
use nanoeye_datagen::render::Dataset;
use nanoeye_nets::{Arch, BnMode, Supernet, SupernetConfig};
use nanoeye_optics::{PhaseMap, PsfUsage};
use nanoeye_search::train::MAX_FACTOR;
use nanoeye_search::{CameraChain, ChainConfig, LensSpec, task_loss};
use nanoeye_sensor::NoiseMode;
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Finest base pitch (µm) `--base-pitch-um` takes (and `fisher compare --pitch-um`): finer than
/// any sensor's pixel; far finer, the box integrator's (sample/base)² factor overflows.
pub const MIN_BASE_PITCH_UM: f64 = 0.1;

/// Largest number of frames one `sim` or `search loss` call processes (memory bound).
const MAX_FRAMES: usize = 100_000;

/// Noise switch.
#[derive(Debug, Clone, Copy, clap::ValueEnum)]
pub enum OnOff {
    /// Shot and read noise (`sim`: Poisson, integer DN; `search loss`: Gaussian
    /// reparameterised shot noise, differentiable, no rounding).
    On,
    /// Mean signal, no noise.
    Off,
}

/// Options shared by `sim` and `search loss`.
#[derive(Debug, Args)]
pub struct ChainArgs {
    /// Dataset directory written by `nanoeye datagen render`.
    #[arg(long)]
    pub dataset: PathBuf,
    /// Effective pixel pitch p̂ (µm), between the dataset's pitch and the sensor size, and at
    /// most 1000 (the rig's largest plausible pixel) [default: 9].
    #[arg(long)]
    pub pitch_um: Option<f64>,
    #[command(flatten)]
    pub camera: CameraArgs,
}

impl ChainArgs {
    /// p̂ (µm) without `--pitch-um`.
    pub const DEFAULT_PITCH_UM: f64 = 9.0;

    /// p̂ (µm): `--pitch-um` or [`Self::DEFAULT_PITCH_UM`].
    pub fn pitch_um(&self) -> f64 {
        self.pitch_um.unwrap_or(Self::DEFAULT_PITCH_UM)
    }

    /// What a resumable run on this chain records to check a resume ([`util::check_inputs`]):
    /// the camera flags ([`CAMERA_KEYS`]), the digest of `--dataset` and, given `val` (the
    /// `--val` flag's set, or `None` for none), `"val"`: its digest or null.
    pub fn inputs(&self, val: Option<Option<&Path>>) -> Result<serde_json::Value> {
        let mut v = self.camera.record();
        v["dataset"] = serde_json::json!(util::dataset_digest("--dataset", &self.dataset)?);
        if let Some(val) = val {
            v["val"] = match val {
                Some(p) => serde_json::json!(util::dataset_digest("--val", p)?),
                None => serde_json::Value::Null,
            };
        }
        Ok(v)
    }

    /// Opens the dataset and builds the chain for `usage`, naming the flag behind a bad value.
    pub fn build(&self, usage: PsfUsage) -> Result<(Dataset, CameraChain)> {
        let ds = Dataset::open(&self.dataset)
            .with_context(|| format!("--dataset {}", self.dataset.display()))?;
        let p = self.pitch_um();
        if !(p.is_finite() && p > 0.0) {
            bail!("--pitch-um: must be positive, got {p}");
        }
        let chain = self.camera.chain(&ds, usage)?;
        Ok((ds, chain))
    }
}

/// Refuses an aperture step (µm) that is not positive or is coarser than an eighth of the
/// aperture, which samples no lens (a step beyond the aperture leaves one sample whose weight
/// can be 0, and every gain NaN); `what` names the setting.
pub fn check_aperture_step(what: &str, step_um: f64) -> Result<()> {
    if !(step_um.is_finite() && step_um > 0.0) {
        bail!("{what}: must be positive, got {step_um}");
    }
    let aperture_um = nanoeye_search::Radiometry::default().aperture_m * 1e6;
    let coarsest = aperture_um / 8.0;
    if step_um > coarsest {
        bail!(
            "{what}: at most {coarsest} µm (an eighth of the {} mm aperture), got {step_um}",
            aperture_um * 1e-3
        );
    }
    // The aperture grid's bound (20000 samples across), named here rather than as a chain
    // parameter.
    let finest = aperture_um / 20000.0;
    if step_um < finest {
        bail!(
            "{what}: at least {finest} µm (20000 samples across the {} mm aperture), got {step_um:e}",
            aperture_um * 1e-3
        );
    }
    Ok(())
}

/// Refuses camera flags other than those `run` (a `search train` output) was trained with, as
/// its inputs.json records them, or without that file its checkpoint's own record (a run with
/// neither, begun before they existed, is not checked); `flag` names the run's flag (`--run`,
/// `--runs`).
pub fn check_trained_with(run: &Path, camera: &CameraArgs, flag: &str) -> Result<()> {
    let mut path = run.join("inputs.json");
    let now = camera.record();
    let ck = run.join("checkpoint.bin");
    let had =
        match util::read_record(&path, util::MAX_RECORD_BYTES).with_context(|| flag.to_string())? {
            Some(text) => Some(
                serde_json::from_str(&text)
                    .with_context(|| format!("{flag}: {} is not JSON", path.display()))?,
            ),
            // inputs.json deleted: rea and pareto scored on another chain than the training's,
            // exit 0 (a helper's audit), where `search train` itself refused from the checkpoint.
            None if ck.is_file() => {
                path = ck.clone();
                nanoeye_search::train::read_inputs(&ck)
                    .with_context(|| format!("{flag} {}", run.display()))?
            }
            None => None,
        };
    let diff = had.and_then(|h| util::value_difference(&h, &now, &CAMERA_KEYS));
    if let Some((f, key, old, new)) = diff {
        bail!(
            "{f}: differs from the run's training ({} records {key} = {old}, this command \
             gives {new}); the chain must be the one the run was trained with",
            path.display()
        );
    }
    Ok(())
}

/// The keys of [`CameraArgs::record`] and their flags.
pub const CAMERA_KEYS: [(&str, &str); 3] = [
    ("aperture_step_um", "--aperture-step-um"),
    ("exposure_ms", "--exposure-ms"),
    ("base_pitch_um", "--base-pitch-um"),
];

/// The camera chain's settings besides p̂: the metasurface's sampling, the exposure and the
/// sensor's base pitch (a trained run is evaluated with the settings it was trained with).
#[derive(Debug, Args)]
pub struct CameraArgs {
    /// Metasurface sampling step (µm); a phase-map file must be sampled on this grid.
    #[arg(long, default_value_t = 1.5)]
    pub aperture_step_um: f64,
    /// Exposure time (ms).
    #[arg(long, default_value_t = 0.1)]
    pub exposure_ms: f64,
    /// Sensor base pitch (µm): κ = (p̂/base)²; the dataset's pitch must be at least this.
    #[arg(long)]
    pub base_pitch_um: Option<f64>,
}

impl CameraArgs {
    /// These settings as a run records them to check a resume ([`util::check_inputs`] with
    /// [`CAMERA_KEYS`]).
    pub fn record(&self) -> serde_json::Value {
        serde_json::json!({
            "aperture_step_um": self.aperture_step_um,
            "exposure_ms": self.exposure_ms,
            "base_pitch_um": self.base_pitch_um,
        })
    }

    /// The chain for `ds` used as `usage` says (its PSF model weighed against the memory
    /// there is first), naming the flag behind a bad value.
    pub fn chain(&self, ds: &Dataset, usage: PsfUsage) -> Result<CameraChain> {
        let mut cfg = ChainConfig::default();
        check_aperture_step("--aperture-step-um", self.aperture_step_um)?;
        cfg.aperture_step_m = self.aperture_step_um * 1e-6;
        if !(self.exposure_ms.is_finite() && self.exposure_ms > 0.0 && self.exposure_ms <= 1000.0) {
            bail!(
                "--exposure-ms: must lie in (0, 1000], got {}",
                self.exposure_ms
            );
        }
        cfg.radiometry.exposure_s = self.exposure_ms * 1e-3;
        let native = ds.manifest.rig.camera.pixel_pitch_m;
        cfg.sensor.base_pitch = match self.base_pitch_um {
            // The dataset's pixels must be at least as fine as the sensor's (the chain refused
            // a coarser base naming only its parameters).
            Some(b)
                if b.is_finite() && b >= MIN_BASE_PITCH_UM && b * 1e-6 <= native * (1.0 + 1e-9) =>
            {
                b * 1e-6
            }
            Some(b) if b.is_finite() && b >= MIN_BASE_PITCH_UM => bail!(
                "--base-pitch-um: at most the dataset's {} µm pixels (it was rendered at that \
                 pitch), got {b}",
                native * 1e6
            ),
            Some(b) => bail!(
                "--base-pitch-um: must be at least {MIN_BASE_PITCH_UM} µm (a sensor pixel), got {b}"
            ),
            // The physical sensor's 3 µm, unless the dataset was rendered finer.
            None => cfg.sensor.base_pitch.min(native),
        };
        check_psf_memory(&cfg, ds, usage, 1)?;
        CameraChain::for_dataset(ds, cfg).map_err(chain_error)
    }
}

/// A chain's refusal, naming the flag behind it where one is: the PSF model's period follows
/// from the aperture and its sampling (the chain has no period of its own), so a folded grid
/// beyond the model's is `--aperture-step-um`'s (0.07 µm named `period_m`).
fn chain_error(e: nanoeye_search::SearchError) -> anyhow::Error {
    match &e {
        nanoeye_search::SearchError::Optics(nanoeye_optics::OpticsError::InvalidParameter {
            name: "period_m",
            reason,
        }) => anyhow::anyhow!("--aperture-step-um: {reason}"),
        _ => anyhow::Error::from(e).context("--dataset / chain parameters"),
    }
}

/// Refuses `copies` chains for `ds` with `cfg` whose PSF models, used as `usage` says, would
/// need more memory than there is ([`util::check_memory`]), before any is built.
pub fn check_psf_memory(
    cfg: &ChainConfig,
    ds: &Dataset,
    usage: PsfUsage,
    copies: usize,
) -> Result<()> {
    let one = CameraChain::psf_memory_bytes(
        ds.manifest.rig.camera.pixel_pitch_m,
        ds.layer_spec().count,
        cfg,
        rayon::current_num_threads(),
        usage,
    )
    .map_err(chain_error)?;
    util::check_memory(
        "--aperture-step-um",
        one.saturating_mul(copies as u64),
        "give a coarser --aperture-step-um",
    )
}

/// `nanoeye sim` options.
#[derive(Debug, Args)]
pub struct SimArgs {
    #[command(flatten)]
    chain: ChainArgs,
    /// Lens: hyperbolic, double-helix, flat (no lens) or file:PHASE.npy.
    #[arg(long, default_value = "hyperbolic")]
    lens: LensSpec,
    /// Sensor noise (on: Poisson + read noise, output in DN; off: mean photo-electrons).
    #[arg(long, value_enum, default_value = "on")]
    noise: OnOff,
    /// Noise seed.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Frames A:B (end exclusive); default all.
    #[arg(long)]
    frames: Option<String>,
    /// Output directory (sensor.npy, mask.npy, targets.jsonl, sim.json).
    #[arg(long)]
    out: PathBuf,
    /// Print JSON.
    #[arg(long)]
    json: bool,
}

/// `nanoeye search` subcommands.
#[derive(Debug, Subcommand)]
pub enum SearchCmd {
    /// Task loss of one subnet on the chain's output, with ∂L/∂φ and ∂L/∂p̂.
    Loss(LossArgs),
    /// Sandwich-rule co-design training of lens, pitch and supernet (S22).
    Train(Box<crate::train::TrainArgs>),
    /// Regularized evolution over subnets with inner-loop fine-tuning (S16–S21).
    Rea(crate::train::ReaArgs),
    /// The lens optimised for the optical embedding (S15) on variational triplets.
    Embed(crate::embed::EmbedArgs),
    /// Accuracy–compute Pareto fronts of several trained lenses (B.6, Fig. 8).
    Pareto(crate::pareto::ParetoArgs),
}

/// `nanoeye search loss` options.
#[derive(Debug, Args)]
pub struct LossArgs {
    #[command(flatten)]
    chain: ChainArgs,
    /// Frames A:B (end exclusive).
    #[arg(long, default_value = "0:2")]
    frames: String,
    /// Phase map (rad) NPY on the aperture grid, or hyperbolic / double-helix.
    #[arg(long, default_value = "hyperbolic")]
    phase: String,
    /// Subnet: min, max or file:ARCH.json.
    #[arg(long, default_value = "min")]
    subnet: String,
    /// Seed of the supernet's initial weights.
    #[arg(long, default_value_t = 0)]
    weights_seed: u64,
    /// Seed of the (Gaussian, pathwise) sensor noise; `--noise off` for the mean signal.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Sensor noise in the loss (on: Gaussian reparameterized shot noise + read noise).
    #[arg(long, value_enum, default_value = "on")]
    noise: OnOff,
    /// Weight λ_slip of the slippage MSE (per mm²).
    #[arg(long, default_value_t = 0.1)]
    lambda_slip: f64,
    /// Write ∂L/∂φ (rad⁻¹, the phase map's shape) to this NPY file.
    #[arg(long)]
    grad_out: Option<PathBuf>,
    /// Print JSON.
    #[arg(long)]
    json: bool,
}

fn parse_frames(flag: &str, text: &str, n: usize) -> Result<Vec<usize>> {
    let (a, b) = text
        .split_once(':')
        .with_context(|| format!("{flag}: expected A:B, got '{text}'"))?;
    let a: usize = a
        .trim()
        .parse()
        .with_context(|| format!("{flag}: bad start '{a}'"))?;
    let b: usize = b
        .trim()
        .parse()
        .with_context(|| format!("{flag}: bad end '{b}'"))?;
    if a >= b || b > n {
        bail!("{flag}: {a}:{b} must satisfy A < B ≤ {n} (frames in the dataset)");
    }
    if b - a > MAX_FRAMES {
        bail!("{flag}: at most {MAX_FRAMES} frames per call");
    }
    Ok((a..b).collect())
}

/// An NPY writer of `n` f32 planes of `shape` (C order) into `w`.
fn npy_planes<W: std::io::Write>(
    w: W,
    n: usize,
    shape: (usize, usize),
) -> Result<npyz::NpyWriter<f32, W>> {
    use npyz::WriterBuilder;
    Ok(npyz::WriteOptions::<f32>::new()
        .default_dtype()
        .shape(&[n as u64, shape.0 as u64, shape.1 as u64])
        .writer(w)
        .begin_nd()?)
}

/// Images `ids` through the chain in chunks of 16 frames, streaming the sensor images and the
/// masks into OUT/sensor.npy and OUT/mask.npy (each moved into place once complete: memory
/// stays one chunk's, whatever the number of frames); returns targets.jsonl's lines.
#[allow(clippy::too_many_arguments)]
fn write_frames(
    a: &SimArgs,
    ds: &Dataset,
    chain: &CameraChain,
    map: &PhaseMap,
    ids: &[usize],
    shape: (usize, usize),
    p_hat: f64,
    noise: NoiseMode,
) -> Result<String> {
    let create = |name: &str| {
        util::AtomicFile::create(&a.out.join(name)).with_context(|| format!("--out {name}"))
    };
    let (mut sensor_f, mut mask_f) = (create("sensor.npy")?, create("mask.npy")?);
    let mut lines = String::new();
    {
        let mut sensor = npy_planes(sensor_f.writer(), ids.len(), shape)?;
        let mut masks = npy_planes(mask_f.writer(), ids.len(), shape)?;
        let bar = match std::io::stderr().is_terminal() && !a.json {
            true => indicatif::ProgressBar::new(ids.len() as u64),
            false => indicatif::ProgressBar::hidden(),
        };
        // The stack covers every slab used so far, so a chunk with fewer slabs asks for the
        // same stack, which the chain keeps, instead of a new one.
        let mut need = vec![false; chain.depths_m().len()];
        let mut done = 0;
        for chunk in ids.chunks(16) {
            let frames = chain.load(ds, chunk)?;
            need.iter_mut()
                .zip(chain.active(&frames))
                .for_each(|(n, a)| *n |= a);
            let psfs = chain.psfs(map, &need).context("--lens")?;
            // Nothing differentiates a simulation: no S1 tape (and no S1 image cache).
            let fwd = chain.forward_with(&frames, &psfs, p_hat, noise, a.seed, false)?;
            let (h, w) = fwd.grid.shape();
            if (h, w) != shape {
                bail!("the p̂ grid is {h}×{w}, expected {}×{}", shape.0, shape.1);
            }
            for (b, f) in frames.iter().enumerate() {
                let img = match noise {
                    NoiseMode::None => &fwd.electrons[b],
                    _ => &fwd.dn[b],
                };
                if img.col_iter().any(|c| c.iter().any(|v| !v.is_finite())) {
                    bail!(
                        "frame {} (plane {} of sensor.npy): its sensor image holds a \
                         non-finite value: check --base-pitch-um, --exposure-ms and --lens",
                        ids[done + b],
                        done + b
                    );
                }
                for i in 0..h {
                    for j in 0..w {
                        sensor.push(&img[(i, j)])?;
                    }
                }
                for &v in fwd.mask.image(b) {
                    masks.push(&v)?;
                }
                let line = serde_json::json!({
                    "frame": f.record.frame,
                    "slip_m": f.record.state.slip_m,
                    "gaze": f.record.gaze,
                    "pupil_center_px": fwd.pupil_center_px[b],
                });
                lines.push_str(&line.to_string());
                lines.push('\n');
            }
            done += frames.len();
            bar.set_position(done as u64);
        }
        bar.finish_and_clear();
        sensor.finish()?;
        masks.finish()?;
    }
    // sim.json removed before the first file is replaced and written last: it is what readers
    // (`track --frames`) trust, so a run that fails between the four files leaves none that
    // vouches for a mixture, and one that fails before leaves the old set whole.
    let summary = a.out.join("sim.json");
    if summary.exists() {
        std::fs::remove_file(&summary)
            .with_context(|| format!("--out: cannot replace {}", summary.display()))?;
    }
    sensor_f.commit()?;
    mask_f.commit()?;
    Ok(lines)
}

/// NPY bytes of an f64 matrix (C order).
pub fn npy_mat64(m: &Mat<f64>) -> Result<Vec<u8>> {
    use npyz::WriterBuilder;
    let mut buf = Vec::new();
    let mut wr = npyz::WriteOptions::<f64>::new()
        .default_dtype()
        .shape(&[m.nrows() as u64, m.ncols() as u64])
        .writer(&mut buf)
        .begin_nd()?;
    for i in 0..m.nrows() {
        for j in 0..m.ncols() {
            wr.push(&m[(i, j)])?;
        }
    }
    wr.finish()?;
    Ok(buf)
}

/// Runs `nanoeye sim`.
pub fn sim(a: SimArgs) -> Result<()> {
    let t0 = Instant::now();
    let (ds, mut chain) = a.chain.build(PsfUsage::Once)?;
    // Each frame is imaged once: S1 images kept for a next forward would only take memory.
    chain.set_s1_cache(false);
    let ids = match &a.frames {
        Some(t) => parse_frames("--frames", t, ds.len())?,
        // "Default all": a dataset past the bound is refused, not cut short silently.
        None if ds.len() > MAX_FRAMES => bail!(
            "--frames: the dataset holds {} frames, more than the {MAX_FRAMES} one call \
             images; give --frames A:B (e.g. 0:{MAX_FRAMES}) and run the rest in other calls",
            ds.len()
        ),
        None => (0..ds.len()).collect(),
    };
    let r = &chain.config().radiometry;
    let map = a
        .lens
        .phase_map(chain.aperture_grid(), r.wavelength_m, r.sensor_distance_m)
        .context("--lens")?;
    let noise = match a.noise {
        OnOff::On => NoiseMode::Poisson,
        OnOff::Off => NoiseMode::None,
    };
    let p_hat = a.chain.pitch_um() * 1e-6;
    // Validate the pitch before any work.
    let shape = chain.native().at(p_hat).context("--pitch-um")?.shape();
    if a.out.exists() && !a.out.is_dir() {
        bail!("--out {}: exists and is not a directory", a.out.display());
    }
    util::check_not_dataset(&a.out)?;
    // Every output's target before the imaging, not only the two opened first: a directory
    // at OUT/sim.json was refused after every frame had been imaged.
    for name in ["sensor.npy", "mask.npy", "targets.jsonl", "sim.json"] {
        util::check_output_target(&a.out.join(name)).with_context(|| format!("--out {name}"))?;
    }
    // An output replacing the lens it was computed from (file:OUT/sensor.npy).
    if let LensSpec::File(f) = &a.lens {
        for name in ["sensor.npy", "mask.npy", "targets.jsonl", "sim.json"] {
            if util::same_file(&a.out.join(name), f) {
                bail!(
                    "--out: its {name} is --lens {}; give another --out",
                    f.display()
                );
            }
        }
    }
    // A run that fails while imaging leaves no directory it created, --out's missing parents
    // included, innermost first (its temporary files go first; `remove_dir` takes only an
    // empty one).
    let created: Vec<PathBuf> = a
        .out
        .ancestors()
        .take_while(|d| !d.as_os_str().is_empty() && !d.exists())
        .map(Path::to_path_buf)
        .collect();
    let written = write_frames(&a, &ds, &chain, &map, &ids, shape, p_hat, noise);
    if written.is_err() {
        for d in &created {
            let _ = std::fs::remove_dir(d);
        }
    }
    let lines = written?;
    util::write_atomic(&a.out.join("targets.jsonl"), lines.as_bytes())?;
    let summary_path = a.out.join("sim.json");
    let (first, end) = (ids.first().copied(), ids.last().map(|l| l + 1));
    let summary = serde_json::json!({
        "frames": ids.len(),
        "height": shape.0,
        "width": shape.1,
        "pitch_m": p_hat,
        "unit": if matches!(noise, NoiseMode::None) { "mean photo-electrons" } else { "DN" },
        "dataset": a.chain.dataset.display().to_string(),
        "frame_range": [first.unwrap_or(0), end.unwrap_or(0)],
        "lens": a.lens.to_string(),
        "noise": if matches!(noise, NoiseMode::None) { "off" } else { "on" },
        "seed": a.seed,
        "exposure_ms": a.chain.camera.exposure_ms,
        "aperture_step_um": a.chain.camera.aperture_step_um,
        "base_pitch_um": chain.config().sensor.base_pitch * 1e6,
        "seconds": t0.elapsed().as_secs_f64(),
    });
    util::write_atomic(
        &summary_path,
        serde_json::to_string_pretty(&summary)?.as_bytes(),
    )?;
    if a.json {
        println!("{summary}");
    } else {
        println!(
            "{} frames → {}×{} at {} µm in {:.2} s; wrote {}",
            summary["frames"],
            shape.0,
            shape.1,
            a.chain.pitch_um(),
            summary["seconds"].as_f64().unwrap_or(0.0),
            a.out.display()
        );
    }
    Ok(())
}

fn parse_subnet(text: &str) -> Result<Arch> {
    match text {
        "min" => Ok(Arch::min()),
        "max" => Ok(Arch::max()),
        _ => {
            let Some(p) = text.strip_prefix("file:") else {
                bail!("--subnet: '{text}' is not min, max or file:ARCH.json");
            };
            let s = util::read_small_text(Path::new(p), util::MAX_ARCH_BYTES)
                .with_context(|| format!("--subnet {p}"))?;
            let a: Arch = serde_json::from_str(&s).with_context(|| format!("--subnet {p}"))?;
            a.validate().with_context(|| format!("--subnet {p}"))?;
            Ok(a)
        }
    }
}

/// Runs `nanoeye search …`.
pub fn search(cmd: SearchCmd) -> Result<()> {
    match cmd {
        SearchCmd::Loss(a) => loss(a),
        SearchCmd::Train(a) => crate::train::train(*a),
        SearchCmd::Rea(a) => crate::train::rea(a),
        SearchCmd::Pareto(a) => crate::pareto::pareto(a),
        SearchCmd::Embed(a) => crate::embed::embed(a),
    }
}

fn loss(a: LossArgs) -> Result<()> {
    let t0 = Instant::now();
    let (ds, chain) = a.chain.build(PsfUsage::Training)?;
    let ids = parse_frames("--frames", &a.frames, ds.len())?;
    let arch = parse_subnet(&a.subnet)?;
    // `search train`'s bound: far beyond it the loss's gradient overflows in the chain's
    // backward (1e300 was refused there, naming the sensor's image, not this flag).
    if !(a.lambda_slip.is_finite() && (0.0..=MAX_FACTOR).contains(&a.lambda_slip)) {
        bail!(
            "--lambda-slip: must be finite in [0, {MAX_FACTOR}], got {}",
            a.lambda_slip
        );
    }
    let lens: LensSpec = match a.phase.as_str() {
        "hyperbolic" | "double-helix" => a.phase.parse().map_err(anyhow::Error::msg)?,
        p => LensSpec::File(PathBuf::from(p.strip_prefix("file:").unwrap_or(p))),
    };
    let r = &chain.config().radiometry;
    let map = lens
        .phase_map(chain.aperture_grid(), r.wavelength_m, r.sensor_distance_m)
        .context("--phase")?;
    let p_hat = a.chain.pitch_um() * 1e-6;
    chain.native().at(p_hat).context("--pitch-um")?;
    // Where the gradient goes, checked before the work (a directory there was found after).
    if let Some(p) = &a.grad_out {
        util::check_output_target(p).with_context(|| format!("--grad-out {}", p.display()))?;
        // Not an input: the phase map, or a file of the dataset (a layers file was replaced).
        if matches!(&lens, LensSpec::File(f) if util::same_file(p, f)) {
            bail!(
                "--grad-out: '{}' is --phase; give another path",
                p.display()
            );
        }
        let within = |d: &Path| {
            let parent = p.parent().filter(|q| !q.as_os_str().is_empty());
            let parent = util::resolved(parent.unwrap_or(Path::new(".")));
            matches!((parent, d.canonicalize()), (Some(x), Ok(y)) if x.starts_with(&y))
        };
        if within(&ds.dir) {
            bail!(
                "--grad-out: '{}' lies inside --dataset {}; give another path",
                p.display(),
                ds.dir.display()
            );
        }
    }
    let noise = match a.noise {
        OnOff::On => NoiseMode::Gaussian,
        OnOff::Off => NoiseMode::None,
    };
    let mut t = Instant::now();
    let mut lap = || {
        let s = t.elapsed().as_secs_f64();
        t = Instant::now();
        s
    };
    let frames = chain.load(&ds, &ids)?;
    let t_load = lap();
    let psfs = chain
        .psfs(&map, &chain.active(&frames))
        .context("--phase")?;
    let t_psf = lap();
    let fwd = chain.forward(&frames, &psfs, p_hat, noise, a.seed)?;
    let t_fwd = lap();
    let mut net = Supernet::new(SupernetConfig::default(), a.weights_seed)?;
    net.zero_grad();
    let (l, task) = task_loss(
        &mut net,
        std::slice::from_ref(&arch),
        &fwd.input,
        &fwd.mask,
        &fwd.slip_mm,
        [a.lambda_slip; 3],
        BnMode::Train,
    )?;
    let t_net = lap();
    let mut acc = chain.accumulator();
    chain.backward(&frames, &psfs, &fwd, &task.input, &mut acc)?;
    chain.target_backward(&frames, &fwd, &task.mask, &mut acc)?;
    let t_bwd = lap();
    let g = chain.finish(&map, &psfs, acc)?;
    let t_vjp = lap();
    for (name, v) in [("loss", l.total), ("d_pitch", g.p_hat)] {
        if !v.is_finite() {
            bail!("{name} is not finite ({v}); check --exposure-ms and --pitch-um");
        }
    }
    // Checked before --grad-out is written, so that no gradient file with NaN is left behind.
    let phase = &g.phase_rad;
    if (0..phase.ncols()).any(|j| (0..phase.nrows()).any(|i| !phase[(i, j)].is_finite())) {
        bail!("∂L/∂φ is not finite everywhere; check --exposure-ms and --pitch-um");
    }
    if let Some(p) = &a.grad_out {
        util::write_atomic(p, &npy_mat64(&g.phase_rad)?)
            .with_context(|| format!("--grad-out {}", p.display()))?;
    }
    let out = serde_json::json!({
        "loss": l.total,
        "seg": l.seg,
        "calib": l.calib,
        "d_pitch": g.p_hat,
        "frames": ids.len(),
        "height": fwd.grid.shape().0,
        "width": fwd.grid.shape().1,
        "seconds": t0.elapsed().as_secs_f64(),
        "timing_s": {
            "load": t_load, "psf_stack": t_psf, "chain_forward": t_fwd,
            "network_forward_backward": t_net, "chain_backward": t_bwd, "psf_vjp": t_vjp,
        },
    });
    if a.json {
        println!("{out}");
    } else {
        println!(
            "loss {:.6} (seg {:.6}, calib {:.6} mm²), dL/dp̂ {:.6e} /m",
            l.total, l.seg, l.calib, g.p_hat
        );
    }
    Ok(())
}

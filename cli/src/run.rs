//! `nanoeye run`: the paper end to end on a small built-in default (docs/run.md). Renders the
//! training, validation and acquisition-protocol sets; trains the supernet with the sandwich
//! rule behind the co-designed lens (φ and p̂ learned) and behind the fixed hyperbolic and
//! double-helix lenses; runs a short regularized evolution on the co-designed run; evaluates
//! the protocol set (D.4: 49 targets × 7 slippage states) through the whole chain — rendered
//! layers → lens → sensor → network → S9 → S10–S14 with the predicted slippage — and writes
//! DIR/result.json and DIR/report.html. Every stage resumes: rendered frames, checkpoints and
//! the search state are kept, and a stage whose output exists is not redone.

use crate::util;
use anyhow::{Context, Result, bail};
use clap::Args;
use faer::Mat;
use nanoeye_datagen::render::{
    Dataset, DatasetOptions, LayerSpec, RenderSet, SceneSource, write_dataset,
};
use nanoeye_datagen::states::PROTOCOL_GRID;
use nanoeye_gaze::{PupilCentre, Rig, SolverKind};
use nanoeye_nets::Arch;
use nanoeye_search::{
    BnBatches, CameraChain, ChainConfig, EmbedConfig, EmbedWeights, Embedder, LensSpec, PhaseBasis,
    PhaseSchedule, Rea, ReaConfig, ReaState, SlipTarget, SolverInput, TrainConfig, Trainer,
};
use serde::{Deserialize, Serialize};
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

/// Which state set the supernet trains on.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum TrainSet {
    /// The protocol's gaze range and stage slippage on top of Table S2's bridge slip.
    Envelope,
    /// Table S2's ambiguity pairs.
    Ambiguity,
}

// By hand so that a wrong value names its key: serde_json's unknown-variant error does not.
impl<'de> Deserialize<'de> for TrainSet {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let s = String::deserialize(d)?;
        match s.as_str() {
            "envelope" => Ok(TrainSet::Envelope),
            "ambiguity" => Ok(TrainSet::Ambiguity),
            _ => Err(serde::de::Error::custom(format!(
                "train_set must be \"envelope\" or \"ambiguity\", got {s:?}"
            ))),
        }
    }
}

/// How the main job designs the learned lens.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum LearnedLens {
    /// The Fisher initialization, then trained with the network by the sandwich rule.
    Trained,
    /// The Fisher initialization, then the optical-embedding objective (S15) on variational
    /// triplets (`search embed`), then kept fixed while the network trains.
    Embedding,
    /// The Fisher initialization, then trained with the network by the sandwich rule on the
    /// task loss plus `embed_weight` times the embedding objective on variational triplets.
    Joint,
}

impl<'de> Deserialize<'de> for LearnedLens {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let s = String::deserialize(d)?;
        match s.as_str() {
            "trained" => Ok(LearnedLens::Trained),
            "embedding" => Ok(LearnedLens::Embedding),
            "joint" => Ok(LearnedLens::Joint),
            _ => Err(serde::de::Error::custom(format!(
                "learned_lens must be \"trained\", \"embedding\" or \"joint\", got {s:?}"
            ))),
        }
    }
}

/// The main job's configuration; `nanoeye run --print-config` lists every default.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RunConfig {
    /// Seed of every set, subject, batch, subnet and noise draw.
    pub seed: u64,
    /// Rendered (native) image width (px) over the rig's sensor; 320 → 12 µm pixels.
    pub width_px: usize,
    /// Rendered image height (px).
    pub height_px: usize,
    /// Samples per pixel of the renderer.
    pub spp: usize,
    /// Training set: "envelope" (frames spanning the protocol's gaze range and stage slippage on
    /// top of Table S2's bridge slip) or "ambiguity" (Table S2's pairs, 3 frames each).
    pub train_set: TrainSet,
    /// Training items: frames (envelope) or pairs (ambiguity).
    pub train_items: usize,
    /// Share (0–1) of the envelope training frames caught in a blink or partial closure
    /// (`lid_closure` uniform in 0.2–1); validation, protocol and sequence stay open-eyed.
    pub train_blink_fraction: f64,
    /// Validation items (V of S17/S19, which the REA selects on), from the training set's kind
    /// with another seed: frames (envelope) or pairs (ambiguity).
    pub val_items: usize,
    /// Subjects of the acquisition protocol (7 slippage states × protocol_grid² targets each).
    pub protocol_subjects: usize,
    /// Targets per side of the protocol's grid, 2–7 (D.4: 7, i.e. 49 targets; fewer give a
    /// quicker, coarser protocol over the same 25° × 35° span).
    pub protocol_grid: usize,
    /// Fisher-initialization iterations of the learned lens (A.2, `fisher init`'s L_init on the
    /// chain's PSF model, depth slabs and initial p̂, from the hyperbolic phase); 0 starts the
    /// learned lens from the hyperbolic one.
    pub fisher_iterations: usize,
    /// Point-source photons per exposure of the Fisher initialization's noise model.
    pub fisher_photons: f64,
    /// How the learned lens is designed: "trained" (the Fisher initialization, then trained
    /// with the network by the sandwich rule) or "embedding" (the Fisher initialization, then
    /// `embed_steps` Adam steps of the optical-embedding objective S15 on `embed_triplets`
    /// variational triplets at `pitch_init_um`, then kept fixed while the network trains and
    /// in the REA's fine-tunes; docs/run.md) or "joint" (the Fisher initialization, then
    /// trained with the network on the sandwich loss + `embed_weight`·L_embed).
    pub learned_lens: LearnedLens,
    /// Variational triplets rendered for `learned_lens` "embedding" or "joint" (at least 4: a
    /// step's batch).
    pub embed_triplets: usize,
    /// Weight μ of the embedding objective in the learned lens's loss (`learned_lens: "joint"`).
    pub embed_weight: f64,
    /// Adam steps of the embedding objective.
    pub embed_steps: usize,
    /// The embedding objective's phase learning rate (rad per step).
    pub embed_lr_rad: f64,
    /// Sandwich training steps per lens.
    pub train_steps: usize,
    /// Frames per batch.
    pub batch: usize,
    /// Random subnets per sandwich step.
    pub random_subnets: usize,
    /// Network learning rate.
    pub lr_net: f64,
    /// Phase learning rate (rad per step).
    pub lr_phase_rad: f64,
    /// What the learned lens's phase steps are taken in: "pixels" (every aperture sample, the
    /// supplement's φ_opt) or "zernike:N" (the Zernike modes of radial order 1..=N over the
    /// aperture; docs/run.md).
    pub phase_basis: PhaseBasis,
    /// How the learned lens's phase rate moves over the sandwich steps: "constant", "cosine"
    /// or "cosine:F" (decay to zero over the first fraction F of the steps, φ fixed after;
    /// docs/run.md).
    pub phase_schedule: PhaseSchedule,
    /// Sandwich steps per step of the learned lens's phase (M): φ fixed over each window of M
    /// steps, then one step by the mean of their gradients (docs/run.md).
    pub phase_every: usize,
    /// Pitch learning rate (µm per step).
    pub lr_pitch_um: f64,
    /// Slippage loss weight (per mm²).
    pub lambda_slip: f64,
    /// Relative weight of the slippage axes (x, y, z) in the slippage loss.
    pub slip_axis_weights: [f64; 3],
    /// Initial effective pitch (µm).
    pub pitch_init_um: f64,
    /// Effective pitch range (µm).
    pub pitch_range_um: [f64; 2],
    /// REA cycles.
    pub rea_cycles: usize,
    /// REA population.
    pub rea_population: usize,
    /// REA tournament size.
    pub rea_tournament: usize,
    /// REA inner-loop epochs.
    pub rea_epochs: f64,
    /// Fine-tuning steps of the selected subnet behind each lens before the protocol (S16's
    /// inner loop, run longer: the deployed model; the baselines' lenses stay fixed).
    pub final_steps: usize,
    /// The learned lens's phase rate in that fine-tune, as a fraction of `lr_phase_rad`
    /// (0.25, the fine-tune's fraction of every rate; 0 keeps φ where training left it while
    /// the network and p̂ fine-tune; docs/run.md).
    pub final_phase_lr_scale: f64,
    /// MAC budget of the search.
    pub budget_macs: u64,
    /// Budget penalty γ.
    pub gamma: f64,
    /// Metasurface sampling step (µm).
    pub aperture_step_um: f64,
    /// Exposure (ms).
    pub exposure_ms: f64,
    /// Supernet calibration-head widths [1×1 expansion, hidden] (960, 1280 in OFA).
    pub head_widths: [usize; 2],
    /// The eye–camera rig (`None`: the built-in rig; `--rig FILE` sets it).
    pub rig: Option<Rig>,
    /// Frames of the video-like demo sequence (smooth gaze path, glasses drifting 3 mm).
    pub sequence_frames: usize,
    /// Gaze solver: "refractive" (the pupil seen through the rig's cornea) or "sphere" (S12's
    /// sphere of radius `rig.eye_radius_m`, the paper's seed).
    pub solver: SolverKind,
    /// What the calibration head learns: "translation" (the camera's, as S11 is written) or
    /// "eye_equivalent" (its rotation folded in about the eye centre, docs/gaze.md).
    pub slip_target: SlipTarget,
    /// Solve the calibration head's output layer in closed form on the training frames before
    /// the protocol (ridge, weight by leave-one-out error: `search::headfit`), for every
    /// deployed subnet; false keeps the trained layer.
    pub slip_head_refit: bool,
    /// Score the REA's candidates as the protocol stage deploys the pick (BN statistics over
    /// every training frame, head refit); off by default (docs/run.md).
    pub rea_head_refit: bool,
    /// What each REA candidate's BN statistics are computed over before its V, without
    /// `rea_head_refit`: "all", every training frame once, or a count of training batches
    /// (docs/run.md).
    pub rea_bn_batches: BnBatches,
    /// Start each REA candidate's fine-tune, and the final one behind each lens, at the
    /// smallest p̂ of `pitch_range_um` at which the subnet fits `budget_macs` (docs/run.md).
    pub rea_fit_pitch: bool,
    /// How the solver takes the pupil centre from a mask: "centroid" (S9) or "ellipse_if_cut"
    /// (S9 unless the pupil reaches the frame's edge, then the centre of the ellipse fitted to
    /// its boundary inside the frame; docs/gaze.md).
    pub pupil_centre: PupilCentre,
}

impl Default for RunConfig {
    fn default() -> Self {
        RunConfig {
            seed: 0,
            width_px: 320,
            height_px: 200,
            spp: 2,
            train_set: TrainSet::Envelope,
            train_items: 240,
            train_blink_fraction: 0.0,
            // 24 until 2026-11-29: on 24 frames seed 1's REA picked a 31 M MAC subnet at
            // V 21.7° that 96 frames score 27.5° (docs/run.md, twenty-first session).
            val_items: 96,
            protocol_subjects: 1,
            protocol_grid: PROTOCOL_GRID,
            fisher_iterations: 40,
            fisher_photons: 1e5,
            learned_lens: LearnedLens::Trained,
            embed_triplets: 48,
            embed_weight: 10.0,
            embed_steps: 80,
            embed_lr_rad: 0.05,
            train_steps: 200,
            batch: 4,
            // S22 with two random subnets besides N_max and N_min (the default): with
            // none, the subnets between the extremes were untrained slices, 100 of them on
            // the ambiguity pairs 22–28° median against 15–19° with two, for 10–14 % more job
            // time (docs/run.md, twenty-fourth session).
            random_subnets: 2,
            lr_net: 4e-3,
            lr_phase_rad: 2e-2,
            phase_basis: PhaseBasis::Pixels,
            phase_schedule: PhaseSchedule::Constant,
            phase_every: 1,
            lr_pitch_um: 5e-2,
            lambda_slip: 0.3,
            slip_axis_weights: [1.0; 3],
            pitch_init_um: 14.0,
            pitch_range_um: [12.0, 24.0],
            rea_cycles: 4,
            rea_population: 4,
            rea_tournament: 2,
            rea_epochs: 0.1,
            final_steps: 40,
            final_phase_lr_scale: FINAL_LR_SCALE,
            budget_macs: 40_000_000,
            gamma: 10.0,
            aperture_step_um: 1.5,
            exposure_ms: 0.1,
            head_widths: [960, 1280],
            rig: None,
            sequence_frames: 60,
            solver: SolverKind::Refractive,
            slip_target: SlipTarget::Translation,
            slip_head_refit: true,
            rea_head_refit: false,
            // 2 batches until 2026-12-02: the candidates' V moved 1–3° on average against
            // every frame, and seed 3's pick was over the budget by 0.1° of fitness; every
            // frame adds a chain pass per candidate (docs/run.md, thirty-eighth session).
            rea_bn_batches: BnBatches::All,
            // Without it the hinge alone moves p̂ by about 0.0125 µm a step in the final 40
            // (Adam, 0.25 × 0.05 µm), and the job's pick cost 83–160 M MACs against the 40 M
            // budget on three of four seeds (docs/run.md, twenty-fifth session).
            rea_fit_pitch: true,
            pupil_centre: PupilCentre::Centroid,
        }
    }
}

/// Main job options.
#[derive(Args)]
pub struct RunArgs {
    /// Output directory (resumable); default `nanoeye-run-<seed>`.
    #[arg(long)]
    out: Option<PathBuf>,
    /// Configuration file (JSON or TOML); missing keys take the defaults.
    #[arg(long)]
    config: Option<PathBuf>,
    /// One configuration key over the defaults and --config, as KEY=VALUE; VALUE is read as
    /// JSON, or else as a string (`--set seed=3 --set phase_schedule=cosine:0.25`). Repeatable.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    set: Vec<String>,
    /// Print the configuration (defaults merged with --config and --set) as JSON and exit.
    #[arg(long)]
    print_config: bool,
    /// Rig JSON file (default: the built-in rig); overrides the configuration's `rig`.
    #[arg(long)]
    rig: Option<PathBuf>,
    /// Print the result as JSON.
    #[arg(long)]
    json: bool,
}

/// Learning rate of the final fine-tune relative to the training peak (the REA's inner loop
/// uses 0.1 for its few steps).
const FINAL_LR_SCALE: f64 = 0.25;

/// The main job's lenses: (name in result.json and runs/, lens spec); the learned lens first.
pub(crate) const LENSES: [(&str, &str); 3] = [
    ("learned", "hyperbolic"),
    ("hyperbolic", "hyperbolic"),
    ("double_helix", "double-helix"),
];

/// The camera chain's settings of a job whose renders have pixels of `native_pitch_m` (m):
/// the one place both its memory check and its chains take them from.
fn chain_config(cfg: &RunConfig, native_pitch_m: f64) -> ChainConfig {
    let mut c = ChainConfig {
        aperture_step_m: cfg.aperture_step_um * 1e-6,
        slip_target: cfg.slip_target,
        ..ChainConfig::default()
    };
    c.radiometry.exposure_s = cfg.exposure_ms * 1e-3;
    c.sensor.base_pitch = c.sensor.base_pitch.min(native_pitch_m);
    c
}

fn load_config(p: Option<&Path>) -> Result<RunConfig> {
    let Some(p) = p else {
        return Ok(RunConfig::default());
    };
    // A small regular file: a FIFO would block, /dev/zero be read without end.
    let text = util::read_small_text(p, util::MAX_ARCH_BYTES)
        .with_context(|| format!("--config {}", p.display()))?;
    let text = text.as_str();
    let is_toml = p.extension().is_some_and(|e| e == "toml");
    let cfg: RunConfig = if is_toml {
        toml::from_str(text).with_context(|| format!("--config {}", p.display()))?
    } else if !text.trim_start().starts_with('{') {
        // serde would read an array into the configuration's keys by position.
        bail!(
            "--config {}: a run configuration is a JSON object ({{\"key\": value, …}})",
            p.display()
        );
    } else {
        if let Ok(v) = serde_json::from_str::<serde_json::Value>(text)
            && let Some(m) = util::array_for_object(&config_template()?, &v)
        {
            bail!("--config {}: {m}", p.display());
        }
        serde_json::from_str(text).map_err(|e| match bad_json_key(text, &e) {
            Some(k) => anyhow::anyhow!("--config {}: key \"{k}\": {e}", p.display()),
            None => anyhow::anyhow!("--config {}: {e}", p.display()),
        })?
    };
    Ok(cfg)
}

/// The configuration's layout with every optional part present (the rig), for
/// [`util::array_for_object`].
fn config_template() -> Result<serde_json::Value> {
    Ok(serde_json::to_value(RunConfig {
        rig: Some(Rig::default()),
        ..RunConfig::default()
    })?)
}

/// `cfg` with each `KEY=VALUE` of `sets` in place of its key: VALUE as JSON where it parses
/// (numbers, booleans, arrays, null, quoted strings), else as the string itself, so that
/// `phase_schedule=cosine:0.25` needs no quotes. An unknown key, a key set twice and a value
/// its key does not take are refused naming `--set KEY`.
fn apply_sets(cfg: RunConfig, sets: &[String]) -> Result<RunConfig> {
    if sets.is_empty() {
        return Ok(cfg);
    }
    let base = serde_json::to_value(&cfg)?;
    let mut merged = base.clone();
    let Some(obj) = merged.as_object_mut() else {
        bail!("--set: the configuration is not a JSON object");
    };
    let mut seen = std::collections::HashSet::new();
    for s in sets {
        let Some((key, text)) = s.split_once('=').filter(|(k, _)| !k.is_empty()) else {
            bail!("--set {s:?}: expected KEY=VALUE, e.g. --set seed=3");
        };
        if !obj.contains_key(key) {
            bail!(
                "--set {key}: no such configuration key; `nanoeye run --print-config` lists them"
            );
        }
        if !seen.insert(key) {
            bail!("--set {key}: given twice");
        }
        let value = serde_json::from_str::<serde_json::Value>(text)
            .unwrap_or_else(|_| serde_json::Value::String(text.to_string()));
        if let Some(m) = util::array_for_object(&config_template()?[key], &value) {
            bail!("--set {key}: {m}");
        }
        // Alone over the base, so that the error names this key and no other.
        let mut one = base.clone();
        one[key] = value.clone();
        serde_json::from_value::<RunConfig>(one).map_err(|e| {
            // A rig's bad value named by its path (serde's error names none).
            let at = (key == "rig")
                .then(|| util::failing_path(&Rig::default(), &value))
                .flatten();
            match at {
                Some((path, why)) => anyhow::anyhow!("--set rig: rig field `{path}`: {why}"),
                None => anyhow::anyhow!("--set {key}={text}: {e}"),
            }
        })?;
        obj.insert(key.to_string(), value);
    }
    serde_json::from_value(merged).context("--set: the merged configuration")
}

/// The key of a JSON object that `err` (the whole object's error) is about: the key that
/// alone gives the same error, else the first (in key order) that does not deserialize on its
/// own (serde's error for an enum given a number or null names only a column). The object's
/// keys come back sorted, not in the file's order: a file with two bad keys (a rig given as a
/// configuration) named one key and printed the other's error.
fn bad_json_key(text: &str, err: &serde_json::Error) -> Option<String> {
    let serde_json::Value::Object(m) = serde_json::from_str(text).ok()? else {
        return None;
    };
    let full = err.to_string();
    let what = full.split(" at line ").next().unwrap_or(&full);
    let bad: Vec<(String, String)> = m
        .into_iter()
        .filter_map(|(k, v)| {
            let one = serde_json::Value::Object([(k.clone(), v)].into_iter().collect());
            let e = serde_json::from_value::<RunConfig>(one).err()?;
            Some((k, e.to_string()))
        })
        .collect();
    bad.iter()
        .find(|(_, e)| e == what)
        .or(bad.first())
        .map(|(k, _)| k.clone())
}

fn check(cfg: &RunConfig) -> Result<()> {
    // Any key, used by this configuration or not: a NaN or an infinity would be written to
    // config.json as null, which no resume can read back.
    let optional: &[&str] = if cfg.rig.is_none() { &["rig"] } else { &[] };
    if let Some(k) = util::first_null(&serde_json::to_value(cfg)?, optional) {
        bail!("--config: `{k}` is not a finite number");
    }
    // The validation, protocol, sequence and triplet sets take seed + 1 … seed + 4.
    if cfg.seed > u64::MAX - 4 {
        bail!(
            "--config: seed must be at most {} (the other sets take seed + 1 to seed + 4), got {}",
            u64::MAX - 4,
            cfg.seed
        );
    }
    if cfg.train_items == 0 || cfg.val_items == 0 || cfg.protocol_subjects == 0 {
        bail!("--config: train_items, val_items and protocol_subjects must be at least 1");
    }
    if cfg.train_items > 100_000 || cfg.val_items > 100_000 || cfg.protocol_subjects > 1000 {
        bail!("--config: at most 100000 training items or pairs and 1000 protocol subjects");
    }
    if !(2..=PROTOCOL_GRID).contains(&cfg.protocol_grid) {
        bail!(
            "--config: protocol_grid must be 2–{PROTOCOL_GRID} targets per side (D.4's grid is \
             {PROTOCOL_GRID}×{PROTOCOL_GRID}), got {}",
            cfg.protocol_grid
        );
    }
    if (cfg.slip_head_refit || cfg.rea_head_refit) && cfg.train_items < 3 {
        bail!(
            "--config: train_items must be at least 3 for the head refit's leave-one-out error \
             (got {}); or set slip_head_refit and rea_head_refit to false",
            cfg.train_items
        );
    }
    let b = cfg.train_blink_fraction;
    if !(0.0..=1.0).contains(&b) {
        bail!("--config: train_blink_fraction must lie in [0, 1], got {b:?}");
    }
    if b > 0.0 && cfg.train_set != TrainSet::Envelope {
        bail!(
            "--config: train_blink_fraction needs train_set \"envelope\" (the ambiguity set's pairs are open-eyed by definition)"
        );
    }
    let max_w = nanoeye_nets::arch::MAX_WIDTH;
    if cfg.head_widths.iter().any(|&w| w == 0 || w > max_w) {
        bail!(
            "--config: head_widths must each be 1..={max_w}, got {:?}",
            cfg.head_widths
        );
    }
    if cfg.spp == 0 || cfg.spp > 1024 {
        bail!("--config: spp must be 1..=1024");
    }
    if cfg.learned_lens != LearnedLens::Trained
        && !(EMBED_BATCH..=100_000).contains(&cfg.embed_triplets)
    {
        bail!(
            "--config: embed_triplets must lie in {EMBED_BATCH}..=100000 (a step takes \
             {EMBED_BATCH}), got {}",
            cfg.embed_triplets
        );
    }
    if cfg.learned_lens == LearnedLens::Joint {
        let mu = cfg.embed_weight;
        if !(mu.is_finite() && mu > 0.0 && mu <= 1e3) {
            bail!(
                "--config: embed_weight must lie in (0, 1000] for learned_lens \"joint\", got {mu:?}"
            );
        }
    }
    if cfg.learned_lens == LearnedLens::Embedding {
        embed_config(cfg).validate().map_err(|e| match e {
            nanoeye_search::SearchError::Param { name: "steps", .. } => {
                anyhow::anyhow!("--config: embed_steps: {e}")
            }
            nanoeye_search::SearchError::Param { name: "lr_rad", .. } => {
                anyhow::anyhow!("--config: embed_lr_rad: {e}")
            }
            _ => anyhow::anyhow!("--config: {e}"),
        })?;
    }
    if !(cfg.exposure_ms.is_finite() && cfg.exposure_ms > 0.0 && cfg.exposure_ms <= 1000.0) {
        bail!("--config: exposure_ms must lie in (0, 1000]");
    }
    crate::sim::check_aperture_step("--config: aperture_step_um", cfg.aperture_step_um)?;
    if cfg.sequence_frames == 0 || cfg.sequence_frames > 100_000 {
        bail!("--config: sequence_frames must be 1..=100000");
    }
    if cfg.final_steps > 1_000_000 {
        bail!("--config: final_steps must be at most 1000000");
    }
    let f = cfg.final_phase_lr_scale;
    if !(0.0..=1.0).contains(&f) {
        bail!(
            "--config: final_phase_lr_scale must lie in [0, 1] (a fraction of lr_phase_rad), \
             got {f:?}"
        );
    }
    crate::fisher::check_init_budget(
        cfg.fisher_iterations,
        cfg.fisher_photons,
        ["--config: fisher_iterations", "--config: fisher_photons"],
    )?;
    // Everything a later stage would refuse is refused here, before any work or output.
    let camera = nanoeye_datagen::render::dataset::rig_at_size(
        &cfg.rig.clone().unwrap_or_default(),
        cfg.width_px,
        cfg.height_px,
    )
    .context("--config: width_px/height_px")?
    .camera;
    let native = camera.pixel_pitch_m * 1e6;
    if cfg.pitch_range_um[0] < native * (1.0 - 1e-9) {
        bail!(
            "--config: pitch_range_um starts at {} µm, finer than the {native:.3} µm pixels of a \
             {}×{} render",
            cfg.pitch_range_um[0],
            cfg.width_px,
            cfg.height_px
        );
    }
    // The three lenses train and are evaluated at once, each with `batch` frames.
    util::check_batch_memory("--config", cfg.batch, 3, cfg.width_px, cfg.height_px)?;
    // And each with its chain's PSF model: weighed at the job's layers and aperture sampling.
    let need = CameraChain::psf_memory_bytes(
        camera.pixel_pitch_m,
        LayerSpec::default().count,
        &chain_config(cfg, camera.pixel_pitch_m),
        rayon::current_num_threads(),
        nanoeye_optics::PsfUsage::Training,
    )
    .context("--config: aperture_step_um")?;
    util::check_memory(
        "--config: aperture_step_um",
        need.saturating_mul(3),
        "give a coarser aperture_step_um",
    )?;
    train_config(cfg, false, learned_embed_weight(cfg))
        .validate()
        .map_err(|e| {
            config_key(
                e,
                &[("steps", "train_steps"), ("n_random", "random_subnets")],
            )
        })
        .context("--config (training)")?;
    // The REA's network inputs are largest at the finest p̂ a candidate may reach.
    let grid = nanoeye_search::NativeGrid::new(camera)?;
    // p̂ may reach the range's top: the sensor must hold at least a pixel of it.
    grid.at(cfg.pitch_range_um[1] * 1e-6).with_context(|| {
        format!(
            "--config: pitch_range_um ends at {} µm, beyond what a {}×{} render holds",
            cfg.pitch_range_um[1], cfg.width_px, cfg.height_px
        )
    })?;
    cfg.rea_bn_batches
        .check_fits_from(cfg.batch, &grid, cfg.pitch_range_um[0] * 1e-6)
        .context("--config: rea_bn_batches")?;
    rea_config(cfg)
        .validate()
        .map_err(|e| {
            config_key(
                e,
                &[
                    ("cycles", "rea_cycles"),
                    ("epochs", "rea_epochs"),
                    ("population", "rea_population"),
                    ("tournament", "rea_tournament"),
                ],
            )
        })
        .context("--config (search)")?;
    Ok(())
}

/// A stage's refusal of its parameter `name` as the configuration key the user wrote (`keys`:
/// (stage's name, key) pairs; other names are the keys already).
fn config_key(e: nanoeye_search::SearchError, keys: &[(&str, &str)]) -> anyhow::Error {
    let key = match &e {
        nanoeye_search::SearchError::Param { name, .. } => {
            keys.iter().find(|(n, _)| n == name).map(|(_, k)| *k)
        }
        _ => None,
    };
    match key {
        Some(k) => anyhow::anyhow!("{k}: {e}"),
        None => e.into(),
    }
}

/// Triplets per step of the learned lens's embedding objective.
const EMBED_BATCH: usize = 4;

/// The embedding objective's settings (`learned_lens: "embedding"`).
fn embed_config(cfg: &RunConfig) -> EmbedConfig {
    EmbedConfig {
        steps: cfg.embed_steps,
        batch: EMBED_BATCH,
        lr_rad: cfg.embed_lr_rad,
        pitch_um: cfg.pitch_init_um,
        seed: cfg.seed,
        weights: EmbedWeights::default(),
    }
}

/// μ of the learned lens's embedding term: `embed_weight` for `learned_lens: "joint"`, else 0.
fn learned_embed_weight(cfg: &RunConfig) -> f64 {
    if cfg.learned_lens == LearnedLens::Joint {
        cfg.embed_weight
    } else {
        0.0
    }
}

/// The sandwich-training configuration of each lens, with the embedding term at weight
/// `embed_weight` (0: the task alone).
fn train_config(cfg: &RunConfig, fixed_lens: bool, embed_weight: f64) -> TrainConfig {
    TrainConfig {
        steps: cfg.train_steps,
        batch: cfg.batch,
        n_random: cfg.random_subnets,
        lr_net: cfg.lr_net,
        lr_phase_rad: cfg.lr_phase_rad,
        phase_basis: cfg.phase_basis,
        phase_schedule: cfg.phase_schedule,
        phase_every: cfg.phase_every,
        lr_pitch_um: cfg.lr_pitch_um,
        lambda_slip: cfg.lambda_slip,
        slip_axis_weights: cfg.slip_axis_weights,
        pitch_init_um: cfg.pitch_init_um,
        pitch_range_um: cfg.pitch_range_um,
        fixed_lens,
        seed: cfg.seed,
        weights_seed: cfg.seed,
        supernet: nanoeye_nets::SupernetConfig {
            head_expand: cfg.head_widths[0],
            head_hidden: cfg.head_widths[1],
            ..nanoeye_nets::SupernetConfig::default()
        },
        solver: cfg.solver,
        pupil_centre: cfg.pupil_centre,
        embed_weight,
        embed_batch: EMBED_BATCH,
        embed_terms: nanoeye_search::EmbedWeights::default(),
    }
}

/// The evolutionary search's configuration.
fn rea_config(cfg: &RunConfig) -> ReaConfig {
    ReaConfig {
        cycles: cfg.rea_cycles,
        population: cfg.rea_population,
        tournament: cfg.rea_tournament,
        epochs: cfg.rea_epochs,
        gamma: cfg.gamma,
        budget_macs: cfg.budget_macs,
        seed: cfg.seed,
        head_refit: cfg.rea_head_refit,
        fit_pitch: cfg.rea_fit_pitch,
        recal_batches: cfg.rea_bn_batches,
        ..ReaConfig::default()
    }
}

/// Stage times, kept across resumes.
#[derive(Default, Serialize, Deserialize)]
struct Stages(std::collections::BTreeMap<String, f64>);

/// Statistics over frames; a frame the solver could not solve (no pupil found, ray misses the
/// sphere) counts as 90°, as in V, and is also counted in `failures`.
fn summarize(errs: &[Option<f64>]) -> serde_json::Value {
    let mut v: Vec<f64> = errs
        .iter()
        .map(|e| e.unwrap_or(nanoeye_search::train::FAILED_FRAME_DEG))
        .collect();
    v.sort_by(f64::total_cmp);
    let failures = errs.iter().filter(|e| e.is_none()).count();
    if v.is_empty() {
        v.push(90.0);
    }
    let q = |p: f64| v[((v.len() - 1) as f64 * p).round() as usize];
    serde_json::json!({
        "mean_deg": v.iter().sum::<f64>() / v.len() as f64,
        "median_deg": q(0.5),
        "p95_deg": q(0.95),
        "failures": failures,
        "frames": errs.len(),
    })
}

/// Frames where the solver gave its flagged fallback estimate.
fn fallbacks(e: &nanoeye_search::FrameEval) -> usize {
    e.fallback.iter().filter(|&&f| f).count()
}

/// [`summarize`] over every protocol frame and per slippage state; `targets` per subject
/// and slippage state.
fn protocol_summary(errs: &[Option<f64>], targets: usize) -> serde_json::Value {
    let mut s = summarize(errs);
    // Protocol order: subject, slip state (7), target.
    let per_slip: Vec<serde_json::Value> = (0..7)
        .map(|k| {
            let e: Vec<Option<f64>> = errs
                .iter()
                .enumerate()
                .filter(|(i, _)| (i / targets) % 7 == k)
                .map(|(_, e)| *e)
                .collect();
            let mut r = summarize(&e);
            r["slip_state"] = k.into();
            r
        })
        .collect();
    s["per_slip"] = per_slip.into();
    s
}

/// Renders (or resumes) set `set` into `dir`; `blink_fraction` as in `DatasetOptions`.
fn render(
    dir: &Path,
    set: RenderSet,
    items: (usize, u64, f64),
    cfg: &RunConfig,
) -> Result<Dataset> {
    write_dataset(&set_options(dir, set, items, cfg))
        .with_context(|| format!("rendering {}", dir.display()))?;
    Ok(Dataset::open(dir)?)
}

/// The options [`render`] renders set `set` into `dir` with.
fn set_options(
    dir: &Path,
    set: RenderSet,
    (n, seed, blink_fraction): (usize, u64, f64),
    cfg: &RunConfig,
) -> DatasetOptions {
    DatasetOptions {
        set,
        n,
        seed,
        width_px: cfg.width_px,
        height_px: cfg.height_px,
        spp: cfg.spp,
        out_dir: dir.to_path_buf(),
        rig: cfg.rig.clone().unwrap_or_default(),
        source: SceneSource::Procedural,
        progress: std::io::stderr().is_terminal(),
        layers: LayerSpec::default(),
        blink_fraction,
        protocol_grid: match set {
            RenderSet::Protocol => cfg.protocol_grid,
            _ => PROTOCOL_GRID,
        },
    }
}

/// The rendered sets of the job under `out`, in the order it renders them: (directory, set,
/// (items, seed, blink fraction)).
fn job_sets(out: &Path, cfg: &RunConfig) -> Vec<(PathBuf, RenderSet, (usize, u64, f64))> {
    let kind = match cfg.train_set {
        TrainSet::Envelope => RenderSet::Envelope,
        TrainSet::Ambiguity => RenderSet::Ambiguity,
    };
    let mut sets = vec![
        (
            out.join("data/train"),
            kind,
            (cfg.train_items, cfg.seed, cfg.train_blink_fraction),
        ),
        // V must measure what the protocol measures: a validation set of the training set's
        // kind.
        (
            out.join("data/val"),
            kind,
            (cfg.val_items, cfg.seed + 1, 0.0),
        ),
        (
            out.join("data/protocol"),
            RenderSet::Protocol,
            (cfg.protocol_subjects, cfg.seed + 2, 0.0),
        ),
        (
            out.join("data/sequence"),
            RenderSet::Sequence,
            (cfg.sequence_frames.max(1), cfg.seed + 3, 0.0),
        ),
    ];
    if cfg.learned_lens != LearnedLens::Trained {
        sets.push((
            out.join("data/triplets"),
            RenderSet::Variational,
            (cfg.embed_triplets, cfg.seed + 4, 0.0),
        ));
    }
    sets
}

/// Bytes the lenses' models under runs/ take at least: per lens two trainer checkpoints
/// (checkpoint.bin, selected.bin: the supernet's weights and BN statistics, and Adam's two
/// moments at 4 bytes per parameter each) and three tracker networks (weights and statistics:
/// the selected, min and max subnets'). 0.80 GB for the default configuration.
fn runs_bytes(cfg: &RunConfig) -> Result<u64> {
    let mut net = nanoeye_nets::Supernet::new(train_config(cfg, false, 0.0).supernet, 0)?;
    let weights = nanoeye_nets::checkpoint::to_bytes(&mut net)?.len() as u64;
    let moments = 2 * 4 * net.num_params() as u64;
    Ok(LENSES.len() as u64 * (2 * (weights + moments) + 3 * weights))
}

/// Refuses the job when its rendered sets' arrays and its models cannot fit on `out`'s disk
/// (and warns when they may not: [`util::check_disk`]), before anything is written.
fn check_job_disk(out: &Path, cfg: &RunConfig) -> Result<()> {
    let mut sets = (0u64, 0u64);
    for (dir, set, items) in job_sets(out, cfg) {
        let (lo, hi) = nanoeye_datagen::render::dataset::dataset_array_bytes(&set_options(
            &dir, set, items, cfg,
        ))?;
        sets = (sets.0.saturating_add(lo), sets.1.saturating_add(hi));
    }
    let runs = runs_bytes(cfg)?;
    util::check_disk(
        &format!(
            "nanoeye run's rendered sets (at least {:.2} GB) and models ({:.2} GB)",
            sets.0 as f64 / 1e9,
            runs as f64 / 1e9
        ),
        out,
        (sets.0.saturating_add(runs), sets.1.saturating_add(runs)),
        "lower train_items, val_items, protocol_subjects, protocol_grid, sequence_frames or \
         width_px × height_px",
    )
}

/// Runs the main job.
pub fn run(a: RunArgs) -> Result<()> {
    if a.rig.is_some() && a.set.iter().any(|s| s.starts_with("rig=")) {
        bail!("--set rig and --rig both give the rig; use one");
    }
    let mut cfg = apply_sets(load_config(a.config.as_deref())?, &a.set)?;
    if a.rig.is_some() {
        cfg.rig = Some(crate::rig::load(a.rig.as_deref())?);
    } else if let Some(r) = &cfg.rig {
        // The rig is the last --set rig=… if one is given, else the configuration file's.
        let from = if a.set.iter().any(|s| s.starts_with("rig=")) {
            "--set rig"
        } else {
            "--config: rig"
        };
        r.validate().context(from)?;
    }
    // check's messages name the key; with --set the value may not come from --config.
    check(&cfg).map_err(|e| {
        if a.set.is_empty() {
            e
        } else {
            e.context(format!("with --set {}", a.set.join(" --set ")))
        }
    })?;
    // Printed once checked: a configuration printed is one the job would run.
    if a.print_config {
        return util::print_json(&cfg);
    }
    let t0 = Instant::now();
    let out = a
        .out
        .clone()
        .unwrap_or_else(|| PathBuf::from(format!("nanoeye-run-{}", cfg.seed)));
    util::check_not_dataset(&out)?;
    let cpath = out.join("config.json");
    // A new run's disk is checked before anything is written: a configuration left behind by
    // a refused run would refuse the smaller one its message asks for.
    if !cpath.exists() {
        check_job_disk(&out, &cfg)?;
    }
    std::fs::create_dir_all(&out).with_context(|| format!("--out {}", out.display()))?;
    if let Some(text) = util::read_record(&cpath, util::MAX_RECORD_BYTES).context("--out")? {
        let old: RunConfig = serde_json::from_str(&text)
            .with_context(|| format!("--out: {} is not a run configuration", cpath.display()))?;
        // A key the file lacks was added after that run began; the default it would take now
        // may not be how its finished stages ran.
        let written: serde_json::Value = serde_json::from_str(&text)?;
        let now = serde_json::to_value(&cfg)?;
        // (Not a let-chain: Cargo.toml's rust-version, 1.85, predates them.)
        let missing = match (written.as_object(), now.as_object()) {
            (Some(w), Some(n)) => n.keys().find(|k| !w.contains_key(*k)),
            _ => None,
        };
        if let Some(k) = missing {
            bail!(
                "--out: {} was begun by an older nanoeye, without `{k}`; its stages may have \
                 run otherwise: use a new --out",
                out.display()
            );
        }
        if old != cfg {
            bail!(
                "--out: {} holds a run with another configuration ({}); use a new --out or the \
                 same --config and --set",
                out.display(),
                differing_keys(&serde_json::to_value(&old)?, &now)
            );
        }
        // A resumed run needs the disk for what it has not written; a finished one is only
        // reported again.
        if !out.join("result.json").exists() {
            check_job_disk(&out, &cfg)?;
        }
    } else {
        // Without its configuration a run's results and checkpoints cannot be told apart from
        // another configuration's: resuming over them would mix the two. (Rendered sets
        // vouch for themselves: a copied `data` is reused only where its manifest matches.)
        if let Some(f) = ["result.json", "runs"]
            .iter()
            .find(|f| out.join(f).exists())
        {
            bail!(
                "--out: {} holds a run's `{f}` but no config.json, so which configuration made \
                 it is unknown; use a new --out",
                out.display()
            );
        }
        util::write_atomic(&cpath, serde_json::to_string_pretty(&cfg)?.as_bytes())?;
    }
    // Temporary files of a killed run, anywhere in its tree (frames, checkpoints).
    util::remove_stale_temps_under(&out);
    // A finished run: report it again without redoing anything.
    let rpath = out.join("result.json");
    if let Some(text) = util::read_record(&rpath, util::MAX_RECORD_BYTES).context("--out")? {
        let corrupt = |why: String| {
            anyhow::anyhow!(
                "--out: {} is corrupt ({why}); delete it to re-evaluate the run",
                rpath.display()
            )
        };
        let result: serde_json::Value =
            serde_json::from_str(&text).map_err(|e| corrupt(e.to_string()))?;
        // As the run wrote it: an object without a null (it refuses to write one), or the
        // report of an edited file would print null with exit 0.
        if !result.is_object() {
            return Err(corrupt("not a JSON object".into()));
        }
        if let Some(k) = util::first_null(&result, &[]) {
            return Err(corrupt(format!("`{k}` is null")));
        }
        eprintln!(
            "{} is complete; reporting it (delete result.json to re-evaluate)",
            out.display()
        );
        return print_result(&result, a.json);
    }
    let spath = out.join("stages.json");
    // Stage timings only: one that cannot be parsed starts over, but what is not a regular
    // file is refused rather than read.
    let mut stages: Stages = util::read_record(&spath, util::MAX_RECORD_BYTES)
        .context("--out")?
        .and_then(|t| serde_json::from_str(&t).ok())
        .unwrap_or_default();
    let note = |s: &str| eprintln!("[{:>6.0} s] {s}", t0.elapsed().as_secs_f64());
    let stage = |name: &str, secs: f64, st: &mut Stages| -> Result<()> {
        st.0.entry(name.to_string()).or_insert(secs);
        util::write_atomic(&spath, serde_json::to_string_pretty(st)?.as_bytes())
    };

    // 1. Data.
    let t = Instant::now();
    note("rendering the training, validation and protocol sets");
    let sets = job_sets(&out, &cfg);
    let set = |(dir, set, items): &(PathBuf, RenderSet, _)| render(dir, *set, *items, &cfg);
    let (train, val, proto, seq) = (
        set(&sets[0])?,
        set(&sets[1])?,
        set(&sets[2])?,
        set(&sets[3])?,
    );
    // The variational triplets, rendered for the embedding objective only.
    let triplets = sets.get(4).map(set).transpose()?;
    stage("render", t.elapsed().as_secs_f64(), &mut stages)?;

    let chain_cfg = chain_config(&cfg, train.manifest.rig.camera.pixel_pitch_m);
    let chain = CameraChain::for_dataset(&train, chain_cfg.clone())?;

    // 2. Fisher initialization of the learned lens (A.2): the hyperbolic phase moved towards
    // PSFs that keep depth information under the sensor's binning at the initial p̂.
    let t = Instant::now();
    let fisher_path = out.join("runs/learned/fisher_phase.npy");
    let learned_init = if cfg.fisher_iterations == 0 {
        None
    } else if fisher_path.exists() {
        Some(
            nanoeye_fisher::nanoeye_optics::io::read_phase_npy(&fisher_path)
                .context("--out (resume): runs/learned/fisher_phase.npy")?,
        )
    } else {
        note(&format!(
            "Fisher initialization of the learned lens ({} iterations)",
            cfg.fisher_iterations
        ));
        let phase = crate::fisher::chain_init_phase(
            &chain,
            cfg.pitch_init_um,
            cfg.fisher_iterations,
            cfg.fisher_photons,
        )?;
        std::fs::create_dir_all(out.join("runs/learned"))?;
        util::write_atomic(&fisher_path, &crate::sim::npy_mat64(&phase)?)?;
        Some(phase)
    };
    stage("fisher", t.elapsed().as_secs_f64(), &mut stages)?;

    // 2b. The learned lens optimised for the optical embedding on the triplets, then fixed.
    let learned_init = match triplets
        .as_ref()
        .filter(|_| cfg.learned_lens == LearnedLens::Embedding)
    {
        Some(trip) => {
            let t = Instant::now();
            let start = learned_start(&chain, learned_init.as_ref())?;
            let phase = embed_lens(trip, &chain_cfg, &cfg, start, &out.join("runs/learned"))
                .context("the learned lens's embedding objective")?;
            if cfg.embed_steps > 0 {
                note(&format!(
                    "  embedding objective of the learned lens: {} steps in {:.0} s",
                    cfg.embed_steps,
                    t.elapsed().as_secs_f64()
                ));
            }
            stage("embed", t.elapsed().as_secs_f64(), &mut stages)?;
            Some(phase)
        }
        None => learned_init,
    };

    // 3. Sandwich training, the three lenses at once. One training keeps 2 cores ~165 % busy
    // (its serial parts: optimizer, batching, the chain's per-frame glue), so the three share
    // the rayon pool and fill each other's gaps. Each has its own chain (a chain keeps the
    // last PSF stack it computed, and the learned lens's would evict a fixed lens's); the
    // results do not depend on the threads (a training is bit-identical on 1 or 2 threads).
    let t = Instant::now();
    for_each_lens(|name, lens, failed| {
        LensTraining {
            name,
            lens,
            init: learned_init.as_ref().filter(|_| name == "learned"),
            triplets: triplets
                .as_ref()
                .filter(|_| name == "learned" && cfg.learned_lens == LearnedLens::Joint),
            train: &train,
            chain_cfg: &chain_cfg,
            cfg: &cfg,
            out: &out,
        }
        .run(&note, failed)
    })?;
    stage("train", t.elapsed().as_secs_f64(), &mut stages)?;
    if let (Some(trip), LearnedLens::Joint) = (&triplets, cfg.learned_lens) {
        // What the embedding term did to the lens: its objective over every triplet.
        let t = Instant::now();
        let start = learned_start(&chain, learned_init.as_ref())?;
        let dir = out.join("runs/learned");
        let trained = nanoeye_fisher::nanoeye_optics::io::read_phase_npy(&dir.join("phase.npy"))
            .context("--out (resume): runs/learned/phase.npy")?;
        joint_objective(trip, &chain_cfg, &cfg, start, trained, &dir)
            .context("the learned lens's embedding objective")?;
        stage("embed_eval", t.elapsed().as_secs_f64(), &mut stages)?;
    }

    // 4. Short REA on the co-designed run.
    let t = Instant::now();
    let rea_cfg = rea_config(&cfg);
    let learned_ck = out.join("runs/learned/checkpoint.bin");
    let mut rea = Rea::new(&chain, &train, &val, &learned_ck, rea_cfg)?;
    let rea_state = out.join("runs/learned/rea_state.json");
    if rea_state.exists() {
        rea.resume(&rea_state)?;
    }
    note(&format!(
        "regularized evolution: {} + {} candidates",
        cfg.rea_population, cfg.rea_cycles
    ));
    let rea_dir = out.join("runs/learned");
    // Two candidates at once, each thread on its own chain (the result is the sequential one).
    let chain_b = CameraChain::for_dataset(&train, chain_cfg.clone())?;
    rea.run_threads(&[&chain, &chain_b], &mut |s: &ReaState| {
        let io = |e: anyhow::Error| nanoeye_search::SearchError::Param {
            name: "out",
            reason: e.to_string(),
        };
        util::write_atomic(
            &rea_state,
            serde_json::to_string(s)
                .map_err(|e| io(e.into()))?
                .as_bytes(),
        )
        .map_err(io)?;
        let lines: String = s
            .history
            .iter()
            .map(|c| serde_json::to_string(c).unwrap_or_default() + "\n")
            .collect();
        util::write_atomic(&rea_dir.join("rea.jsonl"), lines.as_bytes()).map_err(io)
    })?;
    let best = rea.best().context("the search evaluated nothing")?.clone();
    stage("rea", t.elapsed().as_secs_f64(), &mut stages)?;

    // 5. The selected subnet fine-tuned behind each lens: weights inherited from the supernet,
    // then S16's inner loop with the budget hinge (φ and p̂ move for the learned lens only).
    // The protocol and the tracker use this model, so the REA's pick is a trained network and
    // not only a slice of the supernet.
    let t = Instant::now();
    let rc = rea_config(&cfg);
    // The three at once, as in training, each with its own chain.
    for_each_lens(|name, _, failed| {
        let chain = CameraChain::for_dataset(&train, chain_cfg.clone())?;
        let sel = out.join(format!("runs/{name}/selected.bin"));
        // A resume that finds the fine-tune done only rewrites its lens.
        let tr = if sel.exists() {
            Trainer::from_checkpoint(&chain, &train, &sel)?
        } else {
            note(&format!(
                "fine-tuning the selected subnet behind the {name} lens ({} steps)",
                cfg.final_steps
            ));
            let ck = out.join(format!("runs/{name}/checkpoint.bin"));
            let mut tr = Trainer::from_checkpoint(&chain, &train, &ck)?;
            for _ in 0..cfg.final_steps {
                if failed.load(Ordering::Relaxed) {
                    return Ok(());
                }
                tr.finetune_step_phase_at(
                    &best.arch,
                    &rc.budget(),
                    FINAL_LR_SCALE,
                    cfg.final_phase_lr_scale,
                )?;
            }
            tr.save(&sel)?;
            tr
        };
        util::write_atomic(
            &out.join(format!("runs/{name}/phase.npy")),
            &crate::sim::npy_mat64(&tr.phase)?,
        )
    })?;
    stage("finetune", t.elapsed().as_secs_f64(), &mut stages)?;

    // 6. The acquisition protocol through each lens's chain with the selected subnet.
    let t = Instant::now();
    let (grid, targets) = (cfg.protocol_grid, cfg.protocol_grid * cfg.protocol_grid);
    note(&format!(
        "evaluating the acquisition protocol ({targets} targets × 7 slippage states)"
    ));
    // The three lenses at once (one thread each, as in training); merged in `LENSES` order.
    let evals = for_each_lens(|name, _, _| {
        let mut ev = LensEval::default();
        let ck = out.join(format!("runs/{name}/selected.bin"));
        // Chains of its own: a chain keeps the last PSF stack it computed.
        let proto_chain = CameraChain::for_dataset(&proto, chain_cfg.clone())?;
        let chain = CameraChain::for_dataset(&train, chain_cfg.clone())?;
        let mut tr = Trainer::from_checkpoint(&proto_chain, &proto, &ck)?;
        // BN statistics from the training set's chain, then the protocol frames.
        let mut trn = Trainer::from_checkpoint(&chain, &train, &ck)?;
        // Every training frame once through the chain: BN statistics over the whole set for
        // the selected, min and max subnets (2 batches, 8 frames, until 2026-11-29), and the
        // data of the head refit (search::headfit), each subnet after its own statistics.
        let all = trn.all_frames()?;
        trn.net.recalibrate_bn(&best.arch, &all.inputs)?;
        let refit = |net: &mut nanoeye_nets::Supernet, arch: &Arch| -> Result<_> {
            if !cfg.slip_head_refit {
                return Ok(serde_json::Value::Null);
            }
            let fit = nanoeye_search::headfit::refit_slip_head(net, arch, &all)?;
            Ok(serde_json::to_value(fit)?)
        };
        let head_fit = refit(&mut trn.net, &best.arch)?;
        let bytes = nanoeye_nets::checkpoint::to_bytes(&mut trn.net)?;
        // The tracker's model: the selected subnet with its exact BN statistics.
        util::write_atomic(&out.join(format!("runs/{name}/tracker_net.bin")), &bytes)?;
        util::write_atomic(
            &out.join(format!("runs/{name}/tracker_arch.json")),
            serde_json::to_string(&best.arch)?.as_bytes(),
        )?;
        nanoeye_nets::checkpoint::from_bytes(&mut tr.net, &bytes)?;
        // The min and max subnets of the same weights with their own exact BN statistics, for
        // `track --subnet min|max` (the supernet's running statistics are a mixture).
        for (tag, arch) in [("min", Arch::min()), ("max", Arch::max())] {
            trn.net.recalibrate_bn(&arch, &all.inputs)?;
            refit(&mut trn.net, &arch)?;
            util::write_atomic(
                &out.join(format!("runs/{name}/tracker_net_{tag}.bin")),
                &nanoeye_nets::checkpoint::to_bytes(&mut trn.net)?,
            )?;
        }
        let map = tr.phase_map()?;
        let p_hat = tr.pitch_um * 1e-6;
        // One pass of the chain and the network per lens; for the learned lens the same pass
        // also feeds the solver without slippage and the solver alone (true masks and
        // slippage, with the configured solver and with the other one; each of the network's
        // two outputs alone), so the network's, each head's and the refraction correction's
        // shares of the error are visible.
        let other = match cfg.solver {
            SolverKind::Refractive => SolverKind::Sphere,
            SolverKind::Sphere => SolverKind::Refractive,
        };
        let c = cfg.pupil_centre;
        // The pupil centre the configuration does not use, for the chain and the solver alone:
        // what a pupil cut by the frame's edge costs either way (docs/gaze.md).
        let c_other = match c {
            PupilCentre::Centroid => PupilCentre::EllipseIfCut,
            PupilCentre::EllipseIfCut => PupilCentre::Centroid,
        };
        let mut solves = vec![
            (name.to_string(), SolverInput::Predicted, cfg.solver, c),
            (
                format!("{name}_{}", c_other.name()),
                SolverInput::Predicted,
                cfg.solver,
                c_other,
            ),
        ];
        if name == "learned" {
            solves.push((
                "geometric_no_slip".into(),
                SolverInput::NoSlip,
                cfg.solver,
                c,
            ));
            solves.push((
                "solver_true_mask_true_slip".into(),
                SolverInput::Truth,
                cfg.solver,
                c,
            ));
            solves.push((
                format!("{}_solver_true_mask_true_slip", other.name()),
                SolverInput::Truth,
                other,
                c,
            ));
            // What S11's neglect of the camera's rotation costs the solver, whatever the head
            // learns: the true mask with the eye-equivalent translation.
            solves.push((
                "solver_true_mask_eye_equivalent_slip".into(),
                SolverInput::TruthEyeEquivalent,
                cfg.solver,
                c,
            ));
            // The chain's error split between its two heads: each fed the truth in turn.
            solves.push((
                "network_mask_true_slip".into(),
                SolverInput::PredictedMaskTrueSlip,
                cfg.solver,
                c,
            ));
            solves.push((
                "true_mask_network_slip".into(),
                SolverInput::TrueMaskPredictedSlip,
                cfg.solver,
                c,
            ));
            solves.push((
                format!("solver_true_mask_true_slip_{}", c_other.name()),
                SolverInput::Truth,
                cfg.solver,
                c_other,
            ));
        }
        let setup = nanoeye_search::EvalSetup {
            chain: &proto_chain,
            data: &proto,
            map: &map,
            p_hat_m: p_hat,
            arch: &best.arch,
            batch: cfg.batch,
            seed: cfg.seed,
        };
        let evals = nanoeye_search::evaluate_frames_multi(
            &mut tr.net,
            &setup,
            &solves
                .iter()
                .map(|(_, i, k, c)| (*i, *k, *c))
                .collect::<Vec<_>>(),
        )?;
        // Frame by frame, what the chain estimated, so its errors can be traced to a head.
        let e = &evals[0];
        diverged(name, e)?;
        let mut lines = String::new();
        for (k, rec) in proto.records.iter().enumerate() {
            lines += &serde_json::json!({
                "frame": k,
                "slip_state": (k / targets) % 7,
                "true_gaze": rec.gaze,
                "tracked_gaze": e.gaze[k],
                "error_deg": e.errors_deg[k],
                "dice": e.dice[k],
                "true_slip_mm": e.true_slip_mm[k],
                "tracked_slip_mm": e.slip_mm[k],
                "fallback": e.fallback[k],
            })
            .to_string();
            lines.push('\n');
        }
        util::write_atomic(
            &out.join(format!("runs/{name}/protocol.jsonl")),
            lines.as_bytes(),
        )?;
        for ((key, ..), e) in solves.iter().zip(&evals) {
            let mut v = protocol_summary(&e.errors_deg, targets);
            v["fallbacks"] = fallbacks(e).into();
            if key == name {
                // The network's own share: segmentation and slippage against the truth.
                let n = e.dice.len().max(1) as f64;
                v["dice"] = (e.dice.iter().sum::<f64>() / n).into();
                v["slip_rmse_mm"] = (e.slip_sq_mm2.iter().sum::<f64>() / n).sqrt().into();
                v["slip_head_fit"] = head_fit.clone();
            }
            ev.entries.push((key.clone(), v));
        }
        // Figures for the report: the lens's PSFs over depth, and three protocol frames
        // (centre target, on an even grid the one next to the centre on the +azimuth,
        // +elevation side; slippage states 0, 3 and 6) as the network sees them.
        let (psf_png, depths) = crate::figures::psf_strip(&proto_chain, &map)?;
        util::write_atomic(&out.join(format!("runs/{name}/psfs.png")), &psf_png)?;
        ev.psf_depths_mm = depths;
        let centre = (grid / 2) * grid + grid / 2;
        let ids: Vec<usize> = [centre, 3 * targets + centre, 6 * targets + centre]
            .into_iter()
            .filter(|&i| i < proto.len())
            .collect();
        let ex = crate::figures::example_strip(&mut tr.net, &setup, &ids)?;
        util::write_atomic(&out.join(format!("runs/{name}/examples.png")), &ex)?;
        if name == "learned" {
            ev.pitch_um = Some(tr.pitch_um);
            // The demo sequence through the learned chain, frame by frame.
            let seq_setup = nanoeye_search::EvalSetup {
                chain: &CameraChain::for_dataset(&seq, chain_cfg.clone())?,
                data: &seq,
                ..setup
            };
            let e = nanoeye_search::evaluate_frames(
                &mut tr.net,
                &seq_setup,
                SolverInput::Predicted,
                cfg.solver,
                cfg.pupil_centre,
            )?;
            diverged(name, &e)?;
            let mut lines = String::new();
            for (k, rec) in seq.records.iter().enumerate() {
                let (ta, te) = nanoeye_gaze::eye::angles_from_gaze(rec.gaze);
                let est = e.gaze[k].map(|g| {
                    let (a, el) = nanoeye_gaze::eye::angles_from_gaze(g);
                    [a.to_degrees(), el.to_degrees()]
                });
                lines += &serde_json::json!({
                    "frame": k,
                    "true_deg": [ta.to_degrees(), te.to_degrees()],
                    "tracked_deg": est,
                    "slip_m": rec.state.slip_m,
                    "true_slip_mm": e.true_slip_mm[k],
                    "tracked_slip_mm": e.slip_mm[k],
                    "error_deg": e.errors_deg[k],
                    "fallback": e.fallback[k],
                })
                .to_string();
                lines.push('\n');
            }
            util::write_atomic(&out.join("demo.jsonl"), lines.as_bytes())?;
            let mut demo = summarize(&e.errors_deg);
            demo["fallbacks"] = fallbacks(&e).into();
            let n = e.slip_sq_mm2.len().max(1) as f64;
            demo["slip_rmse_mm"] = (e.slip_sq_mm2.iter().sum::<f64>() / n).sqrt().into();
            ev.demo = Some(demo);
        }
        Ok(ev)
    })?;
    let mut protocol = serde_json::Map::new();
    let mut pitch = 0.0;
    let mut demo = serde_json::Value::Null;
    let mut psf_depths_mm = Vec::new();
    for ev in evals {
        protocol.extend(ev.entries);
        pitch = ev.pitch_um.unwrap_or(pitch);
        demo = ev.demo.unwrap_or(demo);
        psf_depths_mm = ev.psf_depths_mm;
    }
    stage("protocol", t.elapsed().as_secs_f64(), &mut stages)?;
    let result = serde_json::json!({
        "stages": stages.0,
        "protocol": protocol,
        "demo_sequence": demo,
        "best_arch": best.arch,
        "macs": best.macs,
        "v_deg": best.v,
        "pitch_um": pitch,
        "psf_depths_mm": psf_depths_mm,
        "seconds": t0.elapsed().as_secs_f64(),
        "out": out.display().to_string(),
    });
    let mut result = result;
    if triplets.is_some() {
        // The embedding objective over every triplet, before and after (docs/run.md).
        let m = out.join("runs/learned/embed/metrics.json");
        let text = std::fs::read_to_string(&m).with_context(|| m.display().to_string())?;
        let mut e: serde_json::Value = serde_json::from_str(&text)?;
        e["learned_lens"] = serde_json::to_value(cfg.learned_lens)?;
        if cfg.learned_lens == LearnedLens::Joint {
            e["embed_weight"] = serde_json::json!(cfg.embed_weight);
        }
        result["learned_lens_embedding"] = e;
    }
    // A NaN would be written as null; nothing non-finite is reported as a result.
    if let Some(k) = util::first_null(&result, &[]) {
        bail!(
            "the result's `{k}` is not a finite number (a diverged training?): lower lr_net, \
             lr_pitch_um or lr_phase_rad"
        );
    }
    // result.json last: it marks the run complete (a rerun reports it and redoes nothing),
    // so the report must exist before it does.
    util::write_atomic(
        &out.join("report.html"),
        crate::report::html(&out, &result)?.as_bytes(),
    )?;
    util::write_atomic(
        &out.join("result.json"),
        serde_json::to_string_pretty(&result)?.as_bytes(),
    )?;
    print_result(&result, a.json)
}

/// Refuses an evaluation whose network predicted a non-finite slippage: its weights diverged
/// (a learning rate too high), and the tracked slippage would be written as null.
fn diverged(lens: &str, e: &nanoeye_search::FrameEval) -> Result<()> {
    if let Some(k) = e
        .slip_mm
        .iter()
        .position(|s| s.iter().any(|v| !v.is_finite()))
    {
        bail!(
            "the {lens} lens's network predicts a non-finite slippage (frame {k} of {}): its \
             training diverged; lower lr_net, lr_pitch_um or lr_phase_rad (or rea_epochs, \
             final_steps) and use a new --out",
            e.slip_mm.len()
        );
    }
    Ok(())
}

/// One lens's share of the protocol stage's result.
#[derive(Default)]
struct LensEval {
    /// `result.json`'s `protocol` entries of this lens: (key, summary).
    entries: Vec<(String, serde_json::Value)>,
    /// The final p̂ (µm), for the learned lens.
    pitch_um: Option<f64>,
    /// The demo sequence's summary, for the learned lens.
    demo: Option<serde_json::Value>,
    /// Depths (mm) of the PSF strip.
    psf_depths_mm: Vec<f64>,
}

/// Runs `job(name, lens spec, failed)` for the three lenses at once, one thread each (their
/// parallel parts share the rayon pool), and returns the results in `LENSES` order or the
/// first error once all have stopped; `failed` is set as soon as one job fails, so that the
/// long ones can stop early.
fn for_each_lens<T: Send>(
    job: impl Fn(&'static str, &'static str, &AtomicBool) -> Result<T> + Sync,
) -> Result<Vec<T>> {
    let failed = AtomicBool::new(false);
    let results: Vec<Result<T>> = std::thread::scope(|s| {
        let threads: Vec<_> = LENSES
            .iter()
            .map(|&(name, lens)| {
                let (job, failed) = (&job, &failed);
                // The main thread's stack size, not a spawned thread's 2 MiB default.
                std::thread::Builder::new()
                    .name(format!("lens-{name}"))
                    .stack_size(8 << 20)
                    .spawn_scoped(s, move || {
                        let r = job(name, lens, failed);
                        if r.is_err() {
                            failed.store(true, Ordering::Relaxed);
                        }
                        r
                    })
            })
            .collect();
        threads
            .into_iter()
            .map(|t| {
                t.context("starting a lens's thread")?
                    .join()
                    .unwrap_or_else(|_| Err(anyhow::anyhow!("a lens's thread panicked")))
            })
            .collect()
    });
    results.into_iter().collect()
}

/// The learned lens's starting phase map (rad): the Fisher initialization where there is one,
/// else the hyperbolic lens.
fn learned_start(chain: &CameraChain, fisher: Option<&Mat<f64>>) -> Result<Mat<f64>> {
    if let Some(p) = fisher {
        return Ok(p.clone());
    }
    let r = &chain.config().radiometry;
    Ok(LensSpec::Hyperbolic
        .phase_map(chain.aperture_grid(), r.wavelength_m, r.sensor_distance_m)?
        .phase_rad)
}

/// The learned lens's embedding stage (`learned_lens: "embedding"`): Adam on φ from `start`
/// under the optical-embedding objective on the triplets, resumed from `dir/embed/`
/// (checkpoint.bin, history.jsonl, metrics.json with the objective before and after over
/// every triplet); returns φ, also written to `dir/embed_phase.npy`.
fn embed_lens(
    trip: &Dataset,
    chain_cfg: &ChainConfig,
    cfg: &RunConfig,
    start: Mat<f64>,
    dir: &Path,
) -> Result<Mat<f64>> {
    let done = dir.join("embed_phase.npy");
    if done.exists() {
        return nanoeye_fisher::nanoeye_optics::io::read_phase_npy(&done)
            .context("--out (resume): runs/learned/embed_phase.npy");
    }
    let chain = CameraChain::for_dataset(trip, chain_cfg.clone())?;
    let mut e = Embedder::new(&chain, trip, embed_config(cfg), start)?;
    let edir = dir.join("embed");
    let ck = edir.join("checkpoint.bin");
    let init_path = edir.join("init.json");
    // Evaluated at the starting lens, before a checkpoint moves `e` on.
    let init = match std::fs::read_to_string(&init_path) {
        Ok(t) => serde_json::from_str(&t).context("--out (resume): embed/init.json")?,
        Err(_) => {
            let ev = e.evaluate(8)?;
            util::write_atomic(&init_path, serde_json::to_string_pretty(&ev)?.as_bytes())?;
            ev
        }
    };
    if ck.exists() {
        e.load(&ck).context("--out (resume)")?;
    }
    while e.step() < cfg.embed_steps {
        e.train_step()?;
        if e.step() % 10 == 0 {
            e.save(&ck)?;
        }
    }
    e.save(&ck)?;
    let fin = e.evaluate(8)?;
    if !(fin.loss.is_finite() && fin.crlb_slip_um.is_finite()) {
        bail!("the embedding objective is not finite: lower embed_lr_rad");
    }
    let lines: String = e
        .history()
        .iter()
        .map(|h| serde_json::to_string(h).unwrap_or_default() + "\n")
        .collect();
    util::write_atomic(&edir.join("history.jsonl"), lines.as_bytes())?;
    util::write_atomic(
        &edir.join("metrics.json"),
        serde_json::to_string_pretty(&serde_json::json!({"init": init, "final": fin}))?.as_bytes(),
    )?;
    util::write_atomic(&done, &crate::sim::npy_mat64(e.phase())?)?;
    Ok(e.phase().clone())
}

/// The embedding objective over every triplet at the learned lens's start `start` and after
/// its joint training `trained` (`learned_lens: "joint"`), at `pitch_init_um`, as
/// `dir/embed/metrics.json` (the embedding stage's format; kept on a resume).
fn joint_objective(
    trip: &Dataset,
    chain_cfg: &ChainConfig,
    cfg: &RunConfig,
    start: Mat<f64>,
    trained: Mat<f64>,
    dir: &Path,
) -> Result<()> {
    let path = dir.join("embed/metrics.json");
    if path.exists() {
        return Ok(());
    }
    let chain = CameraChain::for_dataset(trip, chain_cfg.clone())?;
    let init = Embedder::new(&chain, trip, embed_config(cfg), start)?.evaluate(8)?;
    let fin = Embedder::new(&chain, trip, embed_config(cfg), trained)?.evaluate(8)?;
    if !(fin.loss.is_finite() && fin.crlb_slip_um.is_finite()) {
        bail!("the embedding objective of the trained lens is not finite");
    }
    util::write_atomic(
        &path,
        serde_json::to_string_pretty(&serde_json::json!({"init": init, "final": fin}))?.as_bytes(),
    )
}

/// One lens's sandwich training (stage 3 of the main job), resumed from its checkpoint; writes
/// `runs/<name>/` (checkpoint, rig, phase map, history).
struct LensTraining<'a> {
    name: &'static str,
    lens: &'static str,
    /// The Fisher-initialized phase map (rad), for the learned lens.
    init: Option<&'a Mat<f64>>,
    /// The embedding term's triplets (the learned lens under `learned_lens: "joint"`).
    triplets: Option<&'a Dataset>,
    train: &'a Dataset,
    chain_cfg: &'a ChainConfig,
    cfg: &'a RunConfig,
    out: &'a Path,
}

impl LensTraining<'_> {
    /// Trains to `cfg.train_steps`; stops early (without error) once `failed` is set by
    /// another lens's training.
    fn run(&self, note: &(dyn Fn(&str) + Sync), failed: &AtomicBool) -> Result<()> {
        let (name, cfg, out) = (self.name, self.cfg, self.out);
        let chain = CameraChain::for_dataset(self.train, self.chain_cfg.clone())?;
        let ck = out.join(format!("runs/{name}/checkpoint.bin"));
        let r = &chain.config().radiometry;
        let map = self
            .lens
            .parse::<LensSpec>()
            .map_err(anyhow::Error::msg)?
            .phase_map(chain.aperture_grid(), r.wavelength_m, r.sensor_distance_m)?;
        let phase = self.init.cloned().unwrap_or(map.phase_rad);
        let mut tr = Trainer::new(
            &chain,
            self.train,
            train_config(
                cfg,
                name != "learned" || cfg.learned_lens == LearnedLens::Embedding,
                self.triplets.map_or(0.0, |_| cfg.embed_weight),
            ),
            phase,
        )?;
        if let Some(trip) = self.triplets {
            tr.set_embedding(trip)
                .context("the learned lens's embedding term")?;
        }
        if ck.exists() {
            tr.load(&ck).context("--out (resume)")?;
        }
        let ran = tr.step < cfg.train_steps;
        if ran {
            note(&format!(
                "training the supernet behind the {name} lens ({} steps)",
                cfg.train_steps
            ));
        }
        let t = Instant::now();
        while tr.step < cfg.train_steps {
            if failed.load(Ordering::Relaxed) {
                return Ok(());
            }
            let rec = tr.train_step()?;
            if (rec.step + 1) % (cfg.train_steps / 4).max(1) == 0 {
                note(&format!(
                    "  {name} step {}: L_max {:.3}, L_min {:.3}, p̂ {:.2} µm",
                    rec.step + 1,
                    rec.loss_max,
                    rec.loss_min,
                    rec.pitch_um
                ));
                tr.save(&ck)?;
            }
        }
        tr.save(&ck)?;
        util::write_atomic(
            &out.join(format!("runs/{name}/rig.json")),
            serde_json::to_string_pretty(&self.train.manifest.rig)?.as_bytes(),
        )?;
        util::write_atomic(
            &out.join(format!("runs/{name}/phase.npy")),
            &crate::sim::npy_mat64(&tr.phase)?,
        )?;
        let lines: String = tr
            .history
            .iter()
            .map(|h| serde_json::to_string(h).unwrap_or_default() + "\n")
            .collect();
        util::write_atomic(
            &out.join(format!("runs/{name}/history.jsonl")),
            lines.as_bytes(),
        )?;
        if ran {
            note(&format!(
                "  {name} trained in {:.0} s (beside the other lenses)",
                t.elapsed().as_secs_f64()
            ));
        }
        Ok(())
    }
}

fn print_result(result: &serde_json::Value, json: bool) -> Result<()> {
    if json {
        println!("{result}");
        return Ok(());
    }
    println!(
        "nanoeye run: {} s; report {}/report.html",
        result["seconds"].as_f64().unwrap_or(0.0).round(),
        result["out"].as_str().unwrap_or(".")
    );
    println!(
        "{:<28} {:>9} {:>9} {:>9} {:>6}",
        "protocol gaze error", "mean °", "median °", "p95 °", "fail"
    );
    for (name, s) in result["protocol"].as_object().cloned().unwrap_or_default() {
        let f = |k: &str| s[k].as_f64().map_or("-".into(), |v| format!("{v:.2}"));
        println!(
            "{:<28} {:>9} {:>9} {:>9} {:>6}",
            name,
            f("mean_deg"),
            f("median_deg"),
            f("p95_deg"),
            s["failures"]
        );
    }
    println!(
        "selected subnet: {} MACs at p̂ = {:.2} µm (V = {:.2}° on the validation set)",
        result["macs"],
        result["pitch_um"].as_f64().unwrap_or(0.0),
        result["v_deg"].as_f64().unwrap_or(0.0)
    );
    Ok(())
}

/// The top-level keys whose values differ between a run's configuration `was` and `now`, each
/// with both values (shortened), for the refusal of a resume.
fn differing_keys(was: &serde_json::Value, now: &serde_json::Value) -> String {
    let short = |v: Option<&serde_json::Value>| {
        let t = v.map_or("(none)".to_string(), |v| v.to_string());
        match t.char_indices().nth(40) {
            Some((i, _)) => format!("{}…", &t[..i]),
            None => t,
        }
    };
    let (Some(w), Some(n)) = (was.as_object(), now.as_object()) else {
        return String::new();
    };
    n.iter()
        .filter(|&(k, v)| w.get(k) != Some(v))
        .map(|(k, v)| {
            format!(
                "`{k}`: {} in the run, {} now",
                short(w.get(k)),
                short(Some(v))
            )
        })
        .collect::<Vec<_>>()
        .join("; ")
}

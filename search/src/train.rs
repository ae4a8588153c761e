//! Sandwich-rule co-design training (S22, B.4): each step runs N_max, N_min and n random
//! subnets on one batch through the camera chain, sums their task losses, and updates the
//! shared supernet weights (Adam, cosine schedule), the phase map φ and the effective pitch p̂
//! (Adam each, own learning rates) from one PSF VJP. Checkpoints are one atomic file holding
//! everything a resume needs; a resume with another configuration is refused.
//! Validation V (docs/train.md): mean angular gaze error of the full chain — predicted mask →
//! S9 centroid → S10–S14 with the predicted slippage — after BN recalibration.

use crate::basis::{PhaseBasis, Zernike};
use crate::bn::BnBatches;
use crate::chain::{CameraChain, ChainFrame};
use crate::embed::EmbedWeights;
use crate::error::{Result, param};
use crate::schedule::PhaseSchedule;
use crate::task::{TaskGrads, task_loss};
use faer::Mat;
use nanoeye_datagen::render::{Batcher, Dataset};
use nanoeye_gaze::{PupilCentre, Rig, SolverKind, angular_error, solver_for};
use nanoeye_nets::checkpoint::extend_f32_le;
use nanoeye_nets::loss::{hard_dice, slip_mse};
use nanoeye_nets::optim::{Adam, AdamState, cosine_lr};
use nanoeye_nets::{Arch, BnMode, Supernet, SupernetConfig, Tensor};
use nanoeye_optics::PhaseMap;
use nanoeye_sensor::NoiseMode;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Most network-input bytes [`Trainer::all_frames`] holds (a 100,000-frame training set would
/// need 18 GB at the default 270 × 169 input; 240 frames need 44 MB).
pub const ALL_FRAMES_BYTES: usize = 512 << 20;

/// Most steps a training takes (and most steps per φ step).
pub const MAX_STEPS: usize = 10_000_000;

/// Largest learning rate or loss weight a training takes: far beyond it the loss's gradient
/// overflows in the chain's backward.
pub const MAX_FACTOR: f64 = 1e3;

/// Training hyper-parameters (every one a CLI flag).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainConfig {
    /// Optimisation steps.
    pub steps: usize,
    /// Frames per batch.
    pub batch: usize,
    /// Random subnets per step besides N_max and N_min (n of S22).
    pub n_random: usize,
    /// Peak learning rate of the network weights (Adam, cosine decay to 0).
    pub lr_net: f64,
    /// Learning rate of φ (rad per step, Adam; per mode's unit-RMS coefficient with a
    /// Zernike `phase_basis`).
    pub lr_phase_rad: f64,
    /// What φ's steps are taken in: every aperture sample (`pixels`, the default and what
    /// checkpoints without the field used) or the Zernike modes up to a radial order.
    #[serde(default)]
    pub phase_basis: PhaseBasis,
    /// How φ's rate moves over the sandwich steps (absent in older checkpoints: constant); the
    /// inner loop's fine-tune (S16) runs at its own fraction of `lr_phase_rad` regardless.
    #[serde(default)]
    pub phase_schedule: PhaseSchedule,
    /// Sandwich steps per φ step (M ≥ 1; absent in older checkpoints: 1): φ stays fixed over
    /// each window of M steps, their ∂L/∂PSF are summed, and one PSF VJP of their mean takes
    /// one Adam step at the schedule's rate of the window's first step after its last.
    #[serde(default = "one")]
    pub phase_every: usize,
    /// Learning rate of p̂ (µm per step, Adam).
    pub lr_pitch_um: f64,
    /// Weight of the slippage MSE (per mm²).
    pub lambda_slip: f64,
    /// Relative weight of each slippage axis (x, y, z) in the MSE, multiplying `lambda_slip`
    /// (absent in older checkpoints: 1, 1, 1).
    #[serde(default = "unit_axes")]
    pub slip_axis_weights: [f64; 3],
    /// Initial effective pitch (µm).
    pub pitch_init_um: f64,
    /// Allowed effective pitch range (µm).
    pub pitch_range_um: [f64; 2],
    /// Keep φ fixed (baseline lenses).
    pub fixed_lens: bool,
    /// Seed of batches, subnets and sensor noise.
    pub seed: u64,
    /// Seed of the supernet's initial weights.
    pub weights_seed: u64,
    /// Supernet widths.
    pub supernet: SupernetConfig,
    /// Gaze solver of every evaluation (absent in older checkpoints: refraction-aware).
    #[serde(default)]
    pub solver: SolverKind,
    /// How every evaluation takes the pupil centre from a mask (absent in older checkpoints:
    /// S9's centroid).
    #[serde(default)]
    pub pupil_centre: PupilCentre,
    /// Weight μ of the optical-embedding objective (S15; `search::embed`) in φ's loss: each
    /// φ step descends L_train + μ·L_embed, L_embed on `embed_batch` variational triplets at
    /// the current p̂ (0: none, as in older checkpoints; needs [`Trainer::set_embedding`]).
    #[serde(default)]
    pub embed_weight: f64,
    /// Triplets per φ step of the embedding term.
    #[serde(default = "four")]
    pub embed_batch: usize,
    /// The embedding term's own weights (w_sens, w_orth, floor).
    #[serde(default)]
    pub embed_terms: EmbedWeights,
}

impl Default for TrainConfig {
    fn default() -> Self {
        TrainConfig {
            steps: 100,
            batch: 4,
            n_random: 2,
            lr_net: 2e-3,
            lr_phase_rad: 2e-2,
            phase_basis: PhaseBasis::Pixels,
            phase_schedule: PhaseSchedule::Constant,
            phase_every: 1,
            lr_pitch_um: 5e-2,
            lambda_slip: 0.1,
            slip_axis_weights: unit_axes(),
            pitch_init_um: 9.5,
            pitch_range_um: [3.0, 12.0],
            fixed_lens: false,
            seed: 0,
            weights_seed: 0,
            supernet: SupernetConfig::default(),
            solver: SolverKind::default(),
            pupil_centre: PupilCentre::default(),
            embed_weight: 0.0,
            embed_batch: four(),
            embed_terms: EmbedWeights::default(),
        }
    }
}

/// Refuses a task gradient w.r.t. the camera image or its mask target that is not finite: a
/// diverged network can keep a finite loss while that gradient overflows f32, so it is
/// refused here, naming the rates, before the sensor refuses it.
fn finite_task_grads(task: &TaskGrads) -> Result<()> {
    if [&task.input, &task.mask]
        .iter()
        .any(|t| t.data.iter().any(|v| !v.is_finite()))
    {
        return Err(param(
            "lr_net",
            "the loss's gradient w.r.t. the camera image or its mask target is not finite: \
             training diverged; lower the learning rates",
        ));
    }
    Ok(())
}

/// The first step of the window of `every` sandwich steps that holds step `t`, and whether
/// `t` ends it (windows start at multiples of `every`; the last of `steps` ends the last one).
fn window_of(t: usize, every: usize, steps: usize) -> (usize, bool) {
    let m = every.max(1);
    let first = t - t % m;
    (first, t + 1 >= (first + m).min(steps))
}

/// One step per φ step.
fn one() -> usize {
    1
}

/// Four triplets per φ step.
fn four() -> usize {
    4
}

/// Every slippage axis weighted alike.
fn unit_axes() -> [f64; 3] {
    [1.0; 3]
}

impl TrainConfig {
    /// λ_slip per axis (x, y, z), per mm².
    pub fn lambda_slip_axes(&self) -> [f64; 3] {
        self.slip_axis_weights.map(|w| self.lambda_slip * w)
    }

    /// Checks every field, naming the bad one.
    pub fn validate(&self) -> Result<()> {
        if self.steps == 0 || self.steps > MAX_STEPS {
            return Err(param(
                "steps",
                format!("must be 1..={:e}, got {}", MAX_STEPS as f64, self.steps),
            ));
        }
        if self.batch == 0 || self.batch > 4096 {
            return Err(param(
                "batch",
                format!("must be 1..=4096, got {}", self.batch),
            ));
        }
        if self.n_random > 64 {
            return Err(param("n_random", "at most 64 random subnets per step"));
        }
        for (name, v) in [
            ("lr_net", self.lr_net),
            ("lr_phase_rad", self.lr_phase_rad),
            ("lr_pitch_um", self.lr_pitch_um),
            ("lambda_slip", self.lambda_slip),
        ] {
            if !(v.is_finite() && (0.0..=MAX_FACTOR).contains(&v)) {
                return Err(param(
                    name,
                    format!("must be finite in [0, {MAX_FACTOR}], got {v}"),
                ));
            }
        }
        self.phase_basis.validate()?;
        self.phase_schedule.validate()?;
        if self.phase_every == 0 || self.phase_every > MAX_STEPS {
            return Err(param(
                "phase_every",
                format!(
                    "must be 1..={:e} steps per φ step, got {}",
                    MAX_STEPS as f64, self.phase_every
                ),
            ));
        }
        for (axis, &v) in ["x", "y", "z"].iter().zip(&self.slip_axis_weights) {
            if !(v.is_finite() && (0.0..=MAX_FACTOR).contains(&v)) {
                return Err(param(
                    "slip_axis_weights",
                    format!("the {axis} weight must be finite in [0, {MAX_FACTOR}], got {v}"),
                ));
            }
        }
        let [lo, hi] = self.pitch_range_um;
        if !(lo.is_finite() && hi.is_finite() && 0.0 < lo && lo <= hi) {
            return Err(param(
                "pitch_range_um",
                format!("need 0 < min ≤ max, got {lo}..{hi}"),
            ));
        }
        if !(lo..=hi).contains(&self.pitch_init_um) {
            return Err(param(
                "pitch_init_um",
                format!("{} lies outside {lo}..{hi} µm", self.pitch_init_um),
            ));
        }
        self.supernet.validate()?;
        let mu = self.embed_weight;
        if !(mu.is_finite() && (0.0..=MAX_FACTOR).contains(&mu)) {
            return Err(param(
                "embed_weight",
                format!("must be finite in [0, {MAX_FACTOR}], got {mu}"),
            ));
        }
        if mu > 0.0 && self.fixed_lens {
            return Err(param(
                "embed_weight",
                "a fixed lens takes no φ steps for the embedding term to act on",
            ));
        }
        if self.embed_batch == 0 || self.embed_batch > 4096 {
            return Err(param(
                "embed_batch",
                format!("must be 1..=4096 triplets, got {}", self.embed_batch),
            ));
        }
        self.embed_terms.validate()
    }
}

/// One step's losses.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StepRecord {
    /// Step index.
    pub step: usize,
    /// L_task of N_max.
    pub loss_max: f64,
    /// L_task of N_min.
    pub loss_min: f64,
    /// L_train of S22 (all subnets).
    pub loss_total: f64,
    /// p̂ after the step (µm).
    pub pitch_um: f64,
    /// RMS change of φ in the step (rad).
    pub phase_step_rad: f64,
    /// The embedding term's L_embed on the step's triplets, where φ stepped with one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub embed_loss: Option<f64>,
}

/// Validation metrics of one subnet.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Metrics {
    /// V: mean angular gaze error (degrees) over the validation frames; a frame whose mask
    /// is empty or whose ray misses the sphere counts 90° (a solver's flagged fallback
    /// estimate counts with its own error).
    pub v_deg: f64,
    /// Median angular error (degrees).
    pub median_deg: f64,
    /// Frames where the solver failed.
    pub failures: usize,
    /// Hard Dice of the thresholded mask.
    pub dice: f64,
    /// Slippage MSE (mm²).
    pub slip_mse: f64,
    /// Frames evaluated.
    pub frames: usize,
}

/// Adam for an f64 vector (φ, p̂): bias-corrected moments.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub(crate) struct VecAdam {
    pub(crate) t: i32,
    pub(crate) m: Vec<f64>,
    pub(crate) v: Vec<f64>,
}

impl VecAdam {
    pub(crate) fn new(n: usize) -> VecAdam {
        VecAdam {
            t: 0,
            m: vec![0.0; n],
            v: vec![0.0; n],
        }
    }

    /// Updates `x` in place; returns the RMS step.
    pub(crate) fn step(&mut self, x: &mut [f64], g: &[f64], lr: f64) -> f64 {
        let (b1, b2, eps) = (0.9f64, 0.999f64, 1e-12f64);
        self.t += 1;
        let c1 = 1.0 - b1.powi(self.t);
        let c2 = 1.0 - b2.powi(self.t);
        let mut ss = 0.0;
        for i in 0..x.len() {
            self.m[i] = b1 * self.m[i] + (1.0 - b1) * g[i];
            self.v[i] = b2 * self.v[i] + (1.0 - b2) * g[i] * g[i];
            let d = lr * (self.m[i] / c1) / ((self.v[i] / c2).sqrt() + eps);
            x[i] -= d;
            ss += d * d;
        }
        (ss / x.len().max(1) as f64).sqrt()
    }
}

/// The embedding term's variational triplet set and its triplets [anchor, slip+, gaze+].
struct EmbedTerm<'a> {
    ds: &'a Dataset,
    trips: Vec<[usize; 3]>,
}

/// One step's batch through the chain: what its backward needs.
struct StepData {
    frames: Vec<ChainFrame>,
    map: PhaseMap,
    psfs: std::sync::Arc<crate::chain::StepPsfs>,
    fwd: crate::chain::ChainForward,
}

/// ∂L/∂P per slab summed over the steps of φ's current window (`phase_every`) so far.
#[derive(Clone, Debug)]
struct PendingPhase {
    /// One PSF window per slab (the chain's `psf_grads` layout).
    grads: Vec<Mat<f64>>,
    /// Steps summed.
    steps: usize,
}

impl PendingPhase {
    /// As stored in a checkpoint: the sums' bits, slab after slab, column-major, so a resume
    /// continues the window with the same bits.
    fn to_stored(&self) -> StoredPending {
        let wp = self.grads.first().map_or(0, |g| g.nrows());
        StoredPending {
            steps: self.steps,
            psf_px: wp,
            bits: self
                .grads
                .iter()
                .flat_map(|g| (0..wp).flat_map(move |c| (0..wp).map(move |r| g[(r, c)].to_bits())))
                .collect(),
        }
    }
}

/// [`PendingPhase`] in a checkpoint's metadata.
#[derive(Clone, Debug, Serialize, Deserialize)]
struct StoredPending {
    steps: usize,
    psf_px: usize,
    bits: Vec<u64>,
}

/// Everything a resume needs besides the network and its optimiser.
#[derive(Clone, Debug, Serialize, Deserialize)]
struct Meta {
    config: TrainConfig,
    step: usize,
    pitch_um: f64,
    pitch_adam: VecAdam,
    phase_adam: VecAdam,
    history: Vec<StepRecord>,
    phase_n: usize,
    /// φ's window in progress (`phase_every` > 1), absent between windows.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    phase_pending: Option<StoredPending>,
    /// The caller's inputs ([`Trainer::set_inputs`]), absent when it gave none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    inputs: Option<serde_json::Value>,
}

/// The MAC budget of S16's inner loop.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Budget {
    /// C_budget (MACs; 0: none).
    pub macs: u64,
    /// Weight λ of the hinge λ·max(0, C/C_budget − 1).
    pub lambda: f64,
    /// Keep p̂ inside the budget by projection ([`Trainer::fit_pitch_to_budget`]).
    pub fit_pitch: bool,
}

/// The sandwich trainer over one dataset and one camera chain.
pub struct Trainer<'a> {
    chain: &'a CameraChain,
    ds: &'a Dataset,
    cfg: TrainConfig,
    batcher: Batcher,
    /// The supernet.
    pub net: Supernet,
    opt: Adam,
    /// Phase map φ (rad) on the chain's aperture grid.
    pub phase: Mat<f64>,
    /// Adam over φ's parameters: one per aperture sample, or one per mode of `zernike`.
    phase_adam: VecAdam,
    /// The modes φ steps in (`phase_basis` Zernike), or `None` for every sample.
    zernike: Option<Zernike>,
    /// Effective pitch p̂ (µm).
    pub pitch_um: f64,
    pitch_adam: VecAdam,
    /// ∂L/∂P of φ's window in progress (`phase_every` > 1).
    pending: Option<PendingPhase>,
    /// The variational triplets of the embedding term (`embed_weight` > 0).
    embed: Option<EmbedTerm<'a>>,
    /// Steps done.
    pub step: usize,
    /// Per-step losses.
    pub history: Vec<StepRecord>,
    /// What the result depends on beyond `cfg` ([`Self::set_inputs`]).
    inputs: Option<serde_json::Value>,
}

/// Magic line of a training checkpoint.
pub const TRAIN_MAGIC: &[u8] = b"NANOEYE-TRAIN-CKPT-1\n";

/// Writes `bytes` to `path` through a temporary file and a rename: one unit, never a mix.
pub(crate) fn write_file_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    let dir = path.parent().unwrap_or(Path::new("."));
    std::fs::create_dir_all(dir).map_err(|e| param("out", format!("{}: {e}", dir.display())))?;
    let io = |e: std::io::Error| param("out", format!("{}: {e}", path.display()));
    // Named `.nanoeye-tmp-<pid>-…`: the CLI removes those a killed process left behind.
    let mut b = tempfile::Builder::new();
    // A temporary file is created owner-only (0600); an output is an ordinary file, so ask
    // for 0666 and let the umask take its share, as `File::create` would.
    #[cfg(unix)]
    b.permissions(std::os::unix::fs::PermissionsExt::from_mode(0o666));
    let mut tmp = b
        .prefix(&format!(".nanoeye-tmp-{}-", std::process::id()))
        .tempfile_in(dir)
        .map_err(io)?;
    std::io::Write::write_all(&mut tmp, bytes).map_err(io)?;
    tmp.as_file().sync_all().map_err(io)?;
    tmp.persist(path).map_err(|e| io(e.error))?;
    Ok(())
}

pub(crate) fn fnv1a(bytes: &[u8]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for &b in bytes {
        h ^= b as u64;
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    h
}

impl<'a> Trainer<'a> {
    /// A fresh trainer starting from phase map `phase0` (rad, aperture grid).
    pub fn new(
        chain: &'a CameraChain,
        ds: &'a Dataset,
        cfg: TrainConfig,
        phase0: Mat<f64>,
    ) -> Result<Trainer<'a>> {
        cfg.validate()?;
        let n = chain.aperture_grid().n;
        if phase0.nrows() != n || phase0.ncols() != n {
            return Err(param(
                "lens",
                format!(
                    "phase map is {}×{}, aperture grid {n}×{n}",
                    phase0.nrows(),
                    phase0.ncols()
                ),
            ));
        }
        let min_pitch = chain.native().pitch_m() * 1e6;
        if cfg.pitch_range_um[0] < min_pitch * (1.0 - 1e-9) {
            return Err(param(
                "pitch_range_um",
                format!(
                    "the lower bound {} µm is finer than the dataset's {min_pitch} µm grid",
                    cfg.pitch_range_um[0]
                ),
            ));
        }
        let batcher = Batcher::new(&[ds.len()], cfg.batch.min(ds.len()), cfg.seed)?;
        let net = Supernet::new(cfg.supernet.clone(), cfg.weights_seed)?;
        // A fixed lens takes no φ steps: no modes to evaluate, no moments to keep.
        let zernike = match cfg.phase_basis {
            PhaseBasis::Zernike(order) if !cfg.fixed_lens => {
                Some(Zernike::new(order, *chain.aperture_grid())?)
            }
            _ => None,
        };
        let params = zernike.as_ref().map_or(n * n, Zernike::len);
        Ok(Trainer {
            chain,
            ds,
            batcher,
            net,
            opt: Adam::default(),
            phase_adam: VecAdam::new(params),
            zernike,
            phase: phase0,
            pitch_um: cfg.pitch_init_um,
            pitch_adam: VecAdam::new(1),
            pending: None,
            embed: None,
            step: 0,
            history: Vec::new(),
            inputs: None,
            cfg,
        })
    }

    /// Records what the result depends on beyond the configuration — a JSON object, e.g. the
    /// CLI's resume record and lens — in every checkpoint; [`Self::load`] then refuses a
    /// checkpoint saved with other values (one copied from another run's directory resumed
    /// there, mixing two runs). Keys one side lacks are not compared.
    pub fn set_inputs(&mut self, inputs: serde_json::Value) {
        self.inputs = Some(inputs);
    }

    /// Gives the embedding term (`embed_weight` > 0) its variational triplets: `triplets`
    /// must be rendered on this chain's grid and slabs and hold at least `embed_batch`.
    pub fn set_embedding(&mut self, triplets: &'a Dataset) -> Result<()> {
        let trips = crate::embed::triplets(triplets)?;
        if self.cfg.embed_batch > trips.len() {
            return Err(param(
                "embed_batch",
                format!(
                    "{} triplets per step, the triplet set has {}",
                    self.cfg.embed_batch,
                    trips.len()
                ),
            ));
        }
        // Refuses another grid or slab set now rather than at the first φ step.
        self.chain.load(triplets, &trips[0])?;
        self.embed = Some(EmbedTerm {
            ds: triplets,
            trips,
        });
        Ok(())
    }

    /// L_embed on step `t`'s triplets at φ = `map` and the current p̂, and its ∂/∂P per slab
    /// (the layout of [`CameraChain::psf_grads`]).
    fn embed_gradient(&self, t: usize, map: &PhaseMap) -> Result<(f64, Vec<Mat<f64>>)> {
        let e = self.embed.as_ref().ok_or_else(|| {
            param(
                "embed_weight",
                "the embedding term has no triplets: give a variational set (`search train \
                 --embed-triplets DIR`, rendered by `datagen render --set variational`)",
            )
        })?;
        let batch = crate::embed::triplet_batch(&e.trips, self.cfg.embed_batch, self.cfg.seed, t);
        let ids: Vec<usize> = batch.iter().flatten().copied().collect();
        let frames = self.chain.load(e.ds, &ids)?;
        // Its ∂/∂p̂ is left out on purpose: p̂ descends the sandwich loss alone (docs/run.md,
        // "The embedding as a term of the lens's loss"); L_embed also jumps wherever the grid
        // gains or loses a pixel (every ~0.05 µm at 14 µm), so its smooth slope guides p̂ badly.
        let (ev, grads, _) = crate::embed::embedding_psf_grads(
            self.chain,
            map,
            &frames,
            self.pitch_um * 1e-6,
            &self.cfg.embed_terms,
        )?;
        if !ev.loss.is_finite() {
            return Err(param(
                "embed_weight",
                format!("step {t}: the embedding objective is not finite; lower the rates"),
            ));
        }
        Ok((ev.loss, grads))
    }

    /// The configuration.
    pub fn config(&self) -> &TrainConfig {
        &self.cfg
    }

    /// The phase map as the optics needs it.
    pub fn phase_map(&self) -> Result<PhaseMap> {
        Ok(PhaseMap::phase_only(
            *self.chain.aperture_grid(),
            self.phase.clone(),
        )?)
    }

    /// The subnets of step `t`: N_max, N_min and n draws from ChaCha8(seed, stream t).
    pub fn subnets(&self, t: usize) -> Vec<Arch> {
        let mut rng = ChaCha8Rng::seed_from_u64(self.cfg.seed ^ 0x5a5a_5a5a);
        rng.set_stream(t as u64);
        let mut v = vec![Arch::max(), Arch::min()];
        v.extend((0..self.cfg.n_random).map(|_| Arch::sample(&mut rng)));
        v
    }

    fn frames(&self, t: usize) -> Result<Vec<ChainFrame>> {
        let ids: Vec<usize> = self
            .batcher
            .batch(t as u64)
            .into_iter()
            .map(|(_, i)| i)
            .collect();
        self.chain.load(self.ds, &ids)
    }

    /// φ's rate over the window of `phase_every` steps that holds sandwich step `t` (the
    /// schedule's at the window's first step; `t`'s own for one step per window) and whether
    /// `t` ends that window (the run's last step ends the last one).
    fn phase_window(&self, t: usize) -> (f64, bool) {
        let (first, ends) = window_of(t, self.cfg.phase_every, self.cfg.steps);
        (self.phase_lr(first), ends)
    }

    /// φ's learning rate at sandwich step `t` (rad): zero for a fixed lens and once the
    /// schedule has decayed, where the step needs no gradient to φ.
    fn phase_lr(&self, t: usize) -> f64 {
        self.phase_rate(self.cfg.phase_schedule.scale(t, self.cfg.steps))
    }

    /// φ's learning rate at `scale` times `lr_phase_rad` (rad); zero for a fixed lens.
    fn phase_rate(&self, scale: f64) -> f64 {
        if self.cfg.fixed_lens {
            0.0
        } else {
            self.cfg.lr_phase_rad * scale
        }
    }

    /// The batch of step `t` through the chain at the current φ and p̂, with the noise stream
    /// of step `t`, keeping what the backward to φ needs when `psf_grad`.
    fn chain_step_with(&self, t: usize, psf_grad: bool) -> Result<StepData> {
        let frames = self.frames(t)?;
        let map = self.phase_map()?;
        let (psfs, fwd) = self.through_chain(
            &frames,
            &map,
            self.cfg.seed ^ (t as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15),
            psf_grad,
        )?;
        Ok(StepData {
            frames,
            map,
            psfs,
            fwd,
        })
    }

    /// `frames` through the chain at φ = `map` and the current p̂, sensor noise from `seed`;
    /// with `psf_grad` keeping what the backward to φ needs (else S1's images may come from
    /// the chain's cache).
    fn through_chain(
        &self,
        frames: &[ChainFrame],
        map: &PhaseMap,
        seed: u64,
        psf_grad: bool,
    ) -> Result<(
        std::sync::Arc<crate::chain::StepPsfs>,
        crate::chain::ChainForward,
    )> {
        let psfs = self.chain.psfs(map, &self.chain.active(frames))?;
        let fwd = self.chain.forward_with(
            frames,
            &psfs,
            self.pitch_um * 1e-6,
            NoiseMode::Gaussian,
            seed,
            psf_grad,
        )?;
        Ok((psfs, fwd))
    }

    /// The chain's backward from ∂L/∂input `dx`, then one Adam step of φ at rate `lr_phase`
    /// (none, and no gradient to φ, where it is 0: `s` must then come from a step without
    /// `psf_grad`, and where it is not, with) and of p̂ (with `extra_dp_um` added to its
    /// gradient, per µm) at `lr_scale` times its rate, p̂ clamped to its range. With
    /// `window` = `Some(ends)` the step's ∂L/∂P joins φ's window in progress and φ steps, by
    /// the window's mean, only where `ends`; `extra_psf` (∂/∂P per slab of a term besides the
    /// task's at the same φ, weighted already) joins it where φ steps, before the one PSF VJP
    /// of the step. Returns the RMS change of φ (rad). The callers have refused a non-finite
    /// `task` ([`finite_task_grads`]) before stepping the network.
    #[allow(clippy::too_many_arguments)]
    fn update_optics(
        &mut self,
        s: StepData,
        task: &TaskGrads,
        extra_dp_um: f64,
        extra_psf: Option<&[Mat<f64>]>,
        lr_phase: f64,
        lr_scale: f64,
        window: Option<bool>,
    ) -> Result<f64> {
        // A step that does not move φ needs ∂L/∂p̂ only: the chain skips S1's PSF adjoint.
        let moves_phase = lr_phase > 0.0;
        let mut acc = if moves_phase {
            self.chain.accumulator()
        } else {
            self.chain.pitch_accumulator()
        };
        self.chain
            .backward(&s.frames, &s.psfs, &s.fwd, &task.input, &mut acc)?;
        self.chain
            .target_backward(&s.frames, &s.fwd, &task.mask, &mut acc)?;
        let dp_um = acc.p_hat() * 1e-6 + extra_dp_um;
        let mut phase_step = 0.0;
        let grads = if moves_phase {
            self.window_grads(&s, acc, window)?
        } else {
            None
        };
        if let Some(mut grads) = grads {
            if let Some(extra) = extra_psf {
                for (g, e) in grads.iter_mut().zip(extra) {
                    *g += e;
                }
            }
            let g = self.chain.phase_vjp(&s.map, &grads)?;
            let n = self.phase.nrows();
            match &self.zernike {
                None => {
                    let mut x: Vec<f64> = (0..n * n).map(|k| self.phase[(k / n, k % n)]).collect();
                    let gv: Vec<f64> = (0..n * n).map(|k| g[(k / n, k % n)]).collect();
                    phase_step = self.phase_adam.step(&mut x, &gv, lr_phase);
                    self.phase = Mat::from_fn(n, n, |i, j| x[i * n + j]);
                }
                Some(z) => {
                    // Adam moves the coefficients from 0 by −Δc; φ takes Σ_j Δc_j Z_j.
                    let mut dc = vec![0.0; z.len()];
                    self.phase_adam.step(&mut dc, &z.project(&g), lr_phase);
                    let ss = z.add_to(&dc, &mut self.phase);
                    phase_step = (ss / (n * n) as f64).sqrt();
                }
            }
        }
        let mut p = [self.pitch_um];
        self.pitch_adam
            .step(&mut p, &[dp_um], self.cfg.lr_pitch_um * lr_scale);
        let [lo, hi] = self.cfg.pitch_range_um;
        self.pitch_um = p[0].clamp(lo, hi);
        Ok(phase_step)
    }

    /// ∂L/∂P per slab that φ steps by now: the step's own (`window` None), or, in a window,
    /// the step's added to the window's sum and then their mean where the window ends (`None`
    /// before: φ does not step).
    fn window_grads(
        &mut self,
        s: &StepData,
        acc: crate::chain::PsfGradAccumulator,
        window: Option<bool>,
    ) -> Result<Option<Vec<Mat<f64>>>> {
        let (grads, _) = self.chain.psf_grads(&s.psfs, acc)?;
        let Some(ends) = window else {
            return Ok(Some(grads));
        };
        let p = self.pending.get_or_insert_with(|| PendingPhase {
            grads: grads
                .iter()
                .map(|g| Mat::zeros(g.nrows(), g.ncols()))
                .collect(),
            steps: 0,
        });
        for (a, g) in p.grads.iter_mut().zip(&grads) {
            *a += g;
        }
        p.steps += 1;
        if !ends {
            return Ok(None);
        }
        let p = self.pending.take().expect("filled above");
        let inv = 1.0 / p.steps as f64;
        Ok(Some(
            p.grads.into_iter().map(|g| g * faer::Scale(inv)).collect(),
        ))
    }

    /// The sandwich loss of step `t`'s subnets on its chain output, per subnet, and its
    /// gradients in the network input and the mask target; the network's gradients
    /// accumulated from zero.
    fn sandwich_loss(
        &mut self,
        t: usize,
        fwd: &crate::chain::ChainForward,
    ) -> Result<(Vec<f64>, TaskGrads)> {
        self.net.zero_grad();
        let mut dx = Tensor::zeros(fwd.input.n, 1, fwd.input.h, fwd.input.w);
        let mut dm = Tensor::zeros(fwd.mask.n, 1, fwd.mask.h, fwd.mask.w);
        let mut losses = Vec::new();
        for a in self.subnets(t) {
            let (l, g) = task_loss(
                &mut self.net,
                std::slice::from_ref(&a),
                &fwd.input,
                &fwd.mask,
                &fwd.slip_mm,
                self.cfg.lambda_slip_axes(),
                BnMode::Train,
            )?;
            dx.add_assign(&g.input);
            dm.add_assign(&g.mask);
            losses.push(l.total);
        }
        if losses.iter().any(|l| !l.is_finite()) {
            return Err(param(
                "lr_net",
                format!("step {t}: the loss is not finite ({losses:?}); lower the learning rates"),
            ));
        }
        Ok((
            losses,
            TaskGrads {
                input: dx,
                mask: dm,
            },
        ))
    }

    /// ∂L/∂φ (rad⁻¹, on the aperture grid) of step `t`'s sandwich loss (its batch, subnets
    /// and noise) at the current weights, φ and p̂, and that loss; nothing is updated but the
    /// network's gradient buffers (and BN's running statistics, as a training pass moves
    /// them). For measuring how consistent φ's gradient is from batch to batch.
    pub fn phase_gradient(&mut self, t: usize) -> Result<(f64, Mat<f64>)> {
        let s = self.chain_step_with(t, true)?;
        let (losses, task) = self.sandwich_loss(t, &s.fwd)?;
        finite_task_grads(&task)?;
        let mut acc = self.chain.accumulator();
        self.chain
            .backward(&s.frames, &s.psfs, &s.fwd, &task.input, &mut acc)?;
        let g = self.chain.finish(&s.map, &s.psfs, acc)?;
        if g.phase_rad
            .col_iter()
            .any(|c| c.iter().any(|v| !v.is_finite()))
        {
            return Err(param(
                "lr_phase_rad",
                format!("step {t}: ∂L/∂φ is not finite; lower the learning rates"),
            ));
        }
        Ok((losses.iter().sum(), g.phase_rad))
    }

    /// One sandwich step (S22).
    pub fn train_step(&mut self) -> Result<StepRecord> {
        let t = self.step;
        let (lr_phase, ends) = self.phase_window(t);
        let s = self.chain_step_with(t, lr_phase > 0.0)?;
        let (losses, task) = self.sandwich_loss(t, &s.fwd)?;
        // Before the network's step, so that a diverged step changes nothing.
        finite_task_grads(&task)?;
        self.opt.step(
            &mut self.net,
            cosine_lr(self.cfg.lr_net, 0.0, t, self.cfg.steps),
        )?;
        let window = (self.cfg.phase_every > 1).then_some(ends);
        // The embedding term only where φ steps: at the end of its window, at the φ the
        // window's task gradients were taken at.
        let embed = if lr_phase > 0.0 && ends && self.cfg.embed_weight > 0.0 {
            let (l, mut grads) = self.embed_gradient(t, &s.map)?;
            for g in &mut grads {
                *g *= faer::Scale(self.cfg.embed_weight);
            }
            Some((l, grads))
        } else {
            None
        };
        let extra = embed.as_ref().map(|(_, g)| g.as_slice());
        let phase_step = self.update_optics(s, &task, 0.0, extra, lr_phase, 1.0, window)?;
        let rec = StepRecord {
            step: t,
            loss_max: losses[0],
            loss_min: losses[1],
            loss_total: losses.iter().sum(),
            pitch_um: self.pitch_um,
            phase_step_rad: phase_step,
            embed_loss: embed.map(|(l, _)| l),
        };
        self.history.push(rec.clone());
        self.step += 1;
        Ok(rec)
    }

    /// Recomputes BN statistics of `arch` exactly over `batches` training batches at the
    /// current φ and p̂ (before any evaluation).
    pub fn recalibrate(&mut self, arch: &Arch, batches: usize) -> Result<()> {
        let recal = self.recalibration_inputs(batches)?;
        self.net.recalibrate_bn(arch, &recal)?;
        Ok(())
    }

    /// The network inputs of `batches` training batches at the current φ and p̂ that
    /// [`Self::recalibrate`] computes BN statistics over: compute them once to recalibrate
    /// several subnets (`net.recalibrate_bn(arch, &inputs)`).
    pub fn recalibration_inputs(&self, batches: usize) -> Result<Vec<Tensor>> {
        let map = self.phase_map()?;
        let mut recal = Vec::new();
        for b in 0..batches.max(1) {
            let frames = self.frames(b)?;
            let (_, fwd) = self.through_chain(&frames, &map, self.cfg.seed ^ 0xEEEE, false)?;
            // Refused after the first batch, before the rest is allocated: a count that cannot
            // be held is a parameter error, not an out-of-memory kill.
            if b == 0 {
                let t = &fwd.input;
                BnBatches::Count(batches.max(1)).check_fits(t.n, (t.c * t.h, t.w))?;
            }
            recal.push(fwd.input);
        }
        Ok(recal)
    }

    /// The network inputs BN statistics are taken over, as `bn` says ([`Self::all_frames`]
    /// or [`Self::recalibration_inputs`]), at the current φ and p̂.
    pub fn bn_inputs(&self, bn: BnBatches) -> Result<Vec<Tensor>> {
        match bn {
            BnBatches::All => Ok(self.all_frames()?.inputs),
            BnBatches::Count(n) => self.recalibration_inputs(n),
        }
    }

    /// The training frames in order through the chain at the current φ and p̂, one noise
    /// draw each, in batches of the training batch size, all of them or as many whole batches
    /// as [`ALL_FRAMES_BYTES`] of network inputs hold (at least one): BN statistics over the
    /// set (`net.recalibrate_bn(arch, &frames.inputs)`) and the data of
    /// [`crate::headfit::refit_slip_head`], computed once for any number of subnets.
    pub fn all_frames(&self) -> Result<crate::headfit::FitFrames> {
        self.frames_within(ALL_FRAMES_BYTES)
    }

    /// [`Self::all_frames`] with at most `max_bytes` of network inputs (at least one batch).
    pub fn frames_within(&self, max_bytes: usize) -> Result<crate::headfit::FitFrames> {
        let map = self.phase_map()?;
        let ids: Vec<usize> = (0..self.ds.len()).collect();
        let mut out = crate::headfit::FitFrames::default();
        let mut bytes = 0;
        for chunk in ids.chunks(self.cfg.batch.max(1)) {
            if bytes >= max_bytes {
                break;
            }
            let frames = self.chain.load(self.ds, chunk)?;
            let (_, fwd) = self.through_chain(&frames, &map, self.cfg.seed ^ 0x4EAD, false)?;
            bytes += fwd.input.data.len() * std::mem::size_of::<f32>();
            out.inputs.push(fwd.input);
            out.targets_mm.push(fwd.slip_mm);
        }
        Ok(out)
    }

    /// Validation of subnet `arch` on `val` (all frames, in batches of the training batch
    /// size) after recalibrating BN on `recal_batches` training batches at the current φ, p̂.
    pub fn evaluate(
        &mut self,
        val: &Dataset,
        arch: &Arch,
        recal_batches: usize,
    ) -> Result<Metrics> {
        self.recalibrate(arch, recal_batches)?;
        self.validate(val, arch)
    }

    /// Validation of subnet `arch` on `val` with the network as it stands (BN statistics
    /// already recalibrated).
    pub fn validate(&mut self, val: &Dataset, arch: &Arch) -> Result<Metrics> {
        let map = self.phase_map()?;
        let s = EvalSetup {
            chain: self.chain,
            data: val,
            map: &map,
            p_hat_m: self.pitch_um * 1e-6,
            arch,
            batch: self.cfg.batch,
            seed: self.cfg.seed,
        };
        evaluate_net(&mut self.net, &s, self.cfg.solver, self.cfg.pupil_centre)
    }

    /// Per-frame gaze errors of `arch` on `val` after BN recalibration, the solver fed as
    /// `input` says.
    pub fn evaluate_frames(
        &mut self,
        val: &Dataset,
        arch: &Arch,
        recal_batches: usize,
        input: SolverInput,
    ) -> Result<FrameEval> {
        self.recalibrate(arch, recal_batches)?;
        let map = self.phase_map()?;
        let s = EvalSetup {
            chain: self.chain,
            data: val,
            map: &map,
            p_hat_m: self.pitch_um * 1e-6,
            arch,
            batch: self.cfg.batch,
            seed: self.cfg.seed,
        };
        evaluate_frames(
            &mut self.net,
            &s,
            input,
            self.cfg.solver,
            self.cfg.pupil_centre,
        )
    }

    /// A trainer restored from a run's checkpoint, with the run's own configuration.
    pub fn from_checkpoint(
        chain: &'a CameraChain,
        ds: &'a Dataset,
        path: &Path,
    ) -> Result<Trainer<'a>> {
        let cfg = read_config(path)?;
        let n = chain.aperture_grid().n;
        let mut t = Trainer::new(chain, ds, cfg, Mat::zeros(n, n))?;
        t.load(path)?;
        Ok(t)
    }

    /// One inner-loop step (S16, S18): subnet `arch` alone, with the budget hinge
    /// λ·max(0, C/C_budget − 1) on p̂ through the continuous relaxation C ∝ p̂⁻² (the MAC count
    /// itself is piecewise constant in p̂); with `budget.fit_pitch`, p̂ is put inside the budget
    /// before the step and after it ([`Trainer::fit_pitch_to_budget`]: projected descent).
    /// Returns (task loss, MACs at the p̂ of the step).
    pub fn finetune_step(
        &mut self,
        arch: &Arch,
        budget: &Budget,
        lr_scale: f64,
    ) -> Result<(f64, u64)> {
        // The inner loop fine-tunes φ at `lr_scale` times its rate whatever the sandwich
        // schedule did (S16).
        self.finetune_step_phase_at(arch, budget, lr_scale, lr_scale)
    }

    /// [`Trainer::finetune_step`] with φ's rate at `phase_scale` times `lr_phase_rad` instead
    /// of `lr_scale` times (0: φ kept as it is, the network and p̂ fine-tuned alone).
    pub fn finetune_step_phase_at(
        &mut self,
        arch: &Arch,
        budget: &Budget,
        lr_scale: f64,
        phase_scale: f64,
    ) -> Result<(f64, u64)> {
        if budget.fit_pitch {
            self.fit_pitch_to_budget(arch, budget.macs)?;
        }
        let lr_phase = self.phase_rate(phase_scale);
        let s = self.chain_step_with(self.step, lr_phase > 0.0)?;
        self.net.zero_grad();
        let (l, task) = task_loss(
            &mut self.net,
            std::slice::from_ref(arch),
            &s.fwd.input,
            &s.fwd.mask,
            &s.fwd.slip_mm,
            self.cfg.lambda_slip_axes(),
            BnMode::Train,
        )?;
        if !l.total.is_finite() {
            return Err(param(
                "lr_net",
                "fine-tuning diverged; lower the learning rates",
            ));
        }
        finite_task_grads(&task)?;
        self.opt.step(&mut self.net, self.cfg.lr_net * lr_scale)?;
        let macs = self.macs_at(arch, self.pitch_um)?;
        // d/dp̂ [λ (C/B − 1)] with C ∝ p̂⁻²: −2λC/(B p̂), only while over the budget.
        let hinge = if budget.macs > 0 && macs > budget.macs {
            -2.0 * budget.lambda * macs as f64 / (budget.macs as f64 * self.pitch_um)
        } else {
            0.0
        };
        // Per step, whatever `phase_every`: the window of sandwich training is not its.
        self.update_optics(s, &task, hinge, None, lr_phase, lr_scale, None)?;
        if budget.fit_pitch {
            self.fit_pitch_to_budget(arch, budget.macs)?;
        }
        self.step += 1;
        Ok((l.total, macs))
    }

    /// C_total of `arch` (MACs, S23) on the sensor grid at pitch `pitch_um`.
    pub fn macs_at(&self, arch: &Arch, pitch_um: f64) -> Result<u64> {
        let (h, w) = self.chain.native().at(pitch_um * 1e-6)?.shape();
        Ok(nanoeye_nets::cost::subnet_cost(&self.cfg.supernet, arch, h, w)?.macs)
    }

    /// Raises p̂ to the smallest pitch of its range at which `arch` costs at most `budget_macs`,
    /// the nearest p̂ where S16's hinge vanishes, and returns whether `arch` fits at the p̂ it
    /// leaves. The hinge's gradient points there, but Adam moves p̂ by about its rate a step
    /// (0.05 µm at the defaults), so a few fine-tune steps could not take a 137 M MAC subnet
    /// from 14 µm to the ≈ 26 µm a 40 M budget needs. C_total does not grow with p̂ (the grid
    /// has ⌊n·p_base/p̂⌋ pixels a side), so the pitch is found by bisection to 1e-9 relative.
    /// Leaves p̂ alone when `arch` already fits, when the budget is 0 (none) and when it does
    /// not fit even at the range's top.
    pub fn fit_pitch_to_budget(&mut self, arch: &Arch, budget_macs: u64) -> Result<bool> {
        if budget_macs == 0 || self.macs_at(arch, self.pitch_um)? <= budget_macs {
            return Ok(true);
        }
        let top = self.cfg.pitch_range_um[1];
        if self.macs_at(arch, top)? > budget_macs {
            return Ok(false);
        }
        // Invariant: over the budget at `lo`, within it at `hi`.
        let (mut lo, mut hi) = (self.pitch_um, top);
        while hi - lo > 1e-9 * hi {
            let mid = 0.5 * (lo + hi);
            if self.macs_at(arch, mid)? <= budget_macs {
                hi = mid;
            } else {
                lo = mid;
            }
        }
        self.pitch_um = hi;
        Ok(true)
    }

    /// Batches per epoch of the training set.
    pub fn batches_per_epoch(&self) -> usize {
        self.batcher.batches_per_epoch()
    }

    /// Writes the checkpoint file atomically (temp file + rename): one unit, never a mix.
    pub fn save(&mut self, path: &Path) -> Result<()> {
        let meta = Meta {
            config: self.cfg.clone(),
            step: self.step,
            pitch_um: self.pitch_um,
            pitch_adam: self.pitch_adam.clone(),
            phase_adam: self.phase_adam.clone(),
            history: self.history.clone(),
            phase_n: self.phase.nrows(),
            phase_pending: self.pending.as_ref().map(PendingPhase::to_stored),
            inputs: self.inputs.clone(),
        };
        let json = serde_json::to_vec(&meta).map_err(|e| param("checkpoint", e.to_string()))?;
        let net = nanoeye_nets::checkpoint::to_bytes(&mut self.net)?;
        let st = self.opt.state();
        let n = self.phase.nrows();
        let adam: usize =
            st.m.iter()
                .zip(&st.v)
                .map(|(m, v)| 8 + 4 * (m.len() + v.len()))
                .sum();
        let size =
            TRAIN_MAGIC.len() + 8 + json.len() + 8 * n * n + 8 + net.len() + 4 + 8 + adam + 8;
        let mut b = Vec::with_capacity(size);
        b.extend_from_slice(TRAIN_MAGIC);
        b.extend_from_slice(&(json.len() as u64).to_le_bytes());
        b.extend_from_slice(&json);
        for i in 0..n {
            for j in 0..n {
                b.extend_from_slice(&self.phase[(i, j)].to_le_bytes());
            }
        }
        b.extend_from_slice(&(net.len() as u64).to_le_bytes());
        b.extend_from_slice(&net);
        b.extend_from_slice(&st.t.to_le_bytes());
        b.extend_from_slice(&(st.m.len() as u64).to_le_bytes());
        for (m, v) in st.m.iter().zip(&st.v) {
            b.extend_from_slice(&(m.len() as u64).to_le_bytes());
            extend_f32_le(&mut b, m);
            extend_f32_le(&mut b, v);
        }
        debug_assert_eq!(b.len() + 8, size);
        let h = fnv1a(&b);
        b.extend_from_slice(&h.to_le_bytes());
        write_file_atomic(path, &b)
    }

    /// Restores a checkpoint written by [`Self::save`]; refuses one made with another
    /// configuration (naming the first differing field) or whose checksum fails.
    pub fn load(&mut self, path: &Path) -> Result<()> {
        let b = read_checkpoint(path, "checkpoint")?;
        self.load_bytes(b, path)
    }

    /// [`Self::load`] from the checkpoint file's bytes `b` (read elsewhere, e.g. by another
    /// process); `path` only names the file in errors.
    pub fn load_bytes(&mut self, b: Vec<u8>, path: &Path) -> Result<()> {
        let (b, meta, at) = parse_checkpoint(b, path, "checkpoint")?;
        let bad = |why: &str| param("checkpoint", format!("{}: {why}", path.display()));
        let mut r = Reader {
            b: &b[..b.len() - 8],
            at,
        };
        if meta.config != self.cfg {
            return Err(param(
                "checkpoint",
                format!(
                    "{} was written with other parameters ({}); use a new --out or the same \
                     parameters",
                    path.display(),
                    crate::error::differences(&meta.config, &self.cfg)
                ),
            ));
        }
        check_inputs(meta.inputs.as_ref(), self.inputs.as_ref(), path)?;
        let n = meta.phase_n;
        if n != self.phase.nrows() {
            return Err(bad("phase grid differs from this run's aperture grid"));
        }

        if meta.phase_adam.m.len() != self.phase_adam.m.len()
            || meta.phase_adam.v.len() != self.phase_adam.m.len()
        {
            return Err(bad(
                "the phase optimiser's state does not match the phase basis",
            ));
        }
        let mut ph = Vec::with_capacity(n * n);
        for _ in 0..n * n {
            ph.push(r.f64()?);
        }
        let nl = r.u64()? as usize;
        nanoeye_nets::checkpoint::from_bytes(&mut self.net, r.take(nl)?)?;
        let t = r.i32()?;
        // Counts bounded by the bytes that must follow them: a checkpoint edited with its
        // checksum recomputed claimed 2⁴⁰ moments (an allocation abort) or 2⁶¹ (a panic).
        let cnt = r.count(8)?;
        let (mut m, mut v) = (Vec::new(), Vec::new());
        for _ in 0..cnt {
            let l = r.count(8)?;
            let mut a = Vec::with_capacity(l);
            for _ in 0..l {
                a.push(r.f32()?);
            }
            let mut c = Vec::with_capacity(l);
            for _ in 0..l {
                c.push(r.f32()?);
            }
            m.push(a);
            v.push(c);
        }
        self.opt.set_state(AdamState { t, m, v })?;
        self.phase = Mat::from_fn(n, n, |i, j| ph[i * n + j]);
        self.step = meta.step;
        self.pitch_um = meta.pitch_um;
        self.pitch_adam = meta.pitch_adam;
        self.phase_adam = meta.phase_adam;
        self.history = meta.history;
        self.pending = match meta.phase_pending {
            None => None,
            Some(sp) => {
                let wp = self.chain.psf_px();
                let count = self.chain.depths_m().len();
                if sp.psf_px != wp || sp.bits.len() != count * wp * wp || sp.steps == 0 {
                    return Err(bad(
                        "φ's window in progress does not match this chain's PSFs",
                    ));
                }
                let grads = sp
                    .bits
                    .chunks(wp * wp)
                    .map(|c| Mat::from_fn(wp, wp, |r, j| f64::from_bits(c[j * wp + r])))
                    .collect();
                Some(PendingPhase {
                    grads,
                    steps: sp.steps,
                })
            }
        };
        Ok(())
    }
}

/// The trained network, p̂ (µm) and configuration of a checkpoint, without a dataset or chain
/// (for the tracker): BN uses the running statistics stored with the weights.
pub fn load_model(path: &Path) -> Result<(Supernet, f64, TrainConfig)> {
    let (b, meta, at) = open_checkpoint(path, "model")?;
    let mut r = Reader {
        b: &b[..b.len() - 8],
        at,
    };
    let phase_bytes = meta
        .phase_n
        .checked_mul(meta.phase_n)
        .and_then(|v| v.checked_mul(8))
        .ok_or_else(|| param("model", format!("{}: phase grid too large", path.display())))?;
    r.take(phase_bytes)?;
    let nl = r.u64()? as usize;
    let mut net = Supernet::new(meta.config.supernet.clone(), meta.config.weights_seed)?;
    nanoeye_nets::checkpoint::from_bytes(&mut net, r.take(nl)?)?;
    Ok((net, meta.pitch_um, meta.config))
}

/// The configuration stored in a training checkpoint (checksum verified).
pub fn read_config(path: &Path) -> Result<TrainConfig> {
    Ok(open_checkpoint(path, "run")?.1.config)
}

/// The inputs record a training checkpoint keeps ([`Trainer::set_inputs`]; None in one of an
/// older build), checksum verified.
pub fn read_inputs(path: &Path) -> Result<Option<serde_json::Value>> {
    Ok(open_checkpoint(path, "run")?.1.inputs)
}

/// Reads a training checkpoint, checks its magic line and checksum and parses the metadata;
/// returns the bytes, the metadata and the offset just after it. Errors name `name`.
fn open_checkpoint(path: &Path, name: &'static str) -> Result<(Vec<u8>, Meta, usize)> {
    parse_checkpoint(read_checkpoint(path, name)?, path, name)
}

/// Refuses a checkpoint whose inputs ([`Trainer::set_inputs`]) differ from this run's in a
/// key both hold; either side without inputs (a checkpoint of an older build, a caller that
/// gives none) is not compared.
pub(crate) fn check_inputs(
    had: Option<&serde_json::Value>,
    now: Option<&serde_json::Value>,
    path: &Path,
) -> Result<()> {
    use serde_json::{Map, Value};
    let (Some(had), Some(now)) = (had, now) else {
        return Ok(());
    };
    let as_map = |v: &Value| match v {
        Value::Object(m) => m.clone(),
        other => Map::from_iter([(String::from("inputs"), other.clone())]),
    };
    let (a, b) = (as_map(had), as_map(now));
    let common = |x: &Map<String, Value>, y: &Map<String, Value>| -> Map<String, Value> {
        x.iter()
            .filter(|(k, _)| y.contains_key(*k))
            .map(|(k, v)| (k.clone(), v.clone()))
            .collect()
    };
    let (a, b) = (common(&a, &b), common(&b, &a));
    if a != b {
        return Err(param(
            "checkpoint",
            format!(
                "{} was written by a run with other inputs ({}): it belongs to another run; \
                 resume in that run's --out, or start a new one",
                path.display(),
                crate::error::differences(&a, &b)
            ),
        ));
    }
    Ok(())
}

fn read_checkpoint(path: &Path, name: &'static str) -> Result<Vec<u8>> {
    let err = |e: std::io::Error| param(name, format!("{}: {e}", path.display()));
    // A FIFO blocked the read and `/dev/zero` was read until memory ran out.
    if !std::fs::metadata(path).map_err(err)?.is_file() {
        return Err(param(
            name,
            format!("{}: not a regular file", path.display()),
        ));
    }
    std::fs::read(path).map_err(err)
}

/// [`open_checkpoint`] of bytes already read from `path`.
fn parse_checkpoint(b: Vec<u8>, path: &Path, name: &'static str) -> Result<(Vec<u8>, Meta, usize)> {
    let bad = |why: &str| param(name, format!("{}: {why}", path.display()));
    if b.len() < TRAIN_MAGIC.len() + 16 || &b[..TRAIN_MAGIC.len()] != TRAIN_MAGIC {
        return Err(bad("not a training checkpoint"));
    }
    let (body, tail) = b.split_at(b.len() - 8);
    if fnv1a(body) != u64::from_le_bytes(tail.try_into().expect("8 bytes")) {
        return Err(bad("checksum mismatch: the file is corrupted or truncated"));
    }
    let mut r = Reader {
        b: body,
        at: TRAIN_MAGIC.len(),
    };
    let jl = r.u64()? as usize;
    let meta: Meta = serde_json::from_slice(r.take(jl)?).map_err(|e| bad(&e.to_string()))?;
    let at = r.at;
    Ok((b, meta, at))
}

struct Reader<'b> {
    b: &'b [u8],
    at: usize,
}

impl<'b> Reader<'b> {
    fn take(&mut self, n: usize) -> Result<&'b [u8]> {
        let end = self
            .at
            .checked_add(n)
            .filter(|&e| e <= self.b.len())
            .ok_or_else(|| param("checkpoint", "truncated"))?;
        let s = &self.b[self.at..end];
        self.at = end;
        Ok(s)
    }
    fn u64(&mut self) -> Result<u64> {
        Ok(u64::from_le_bytes(self.take(8)?.try_into().expect("8")))
    }
    /// A count of items of at least `each` bytes, refused when the bytes left cannot hold
    /// them.
    fn count(&mut self, each: usize) -> Result<usize> {
        let n = self.u64()?;
        let left = (self.b.len() - self.at) as u64;
        if n.checked_mul(each as u64).is_none_or(|b| b > left) {
            return Err(param(
                "checkpoint",
                format!("a count of {n} items is more than the {left} bytes left hold"),
            ));
        }
        Ok(n as usize)
    }
    fn f64(&mut self) -> Result<f64> {
        Ok(f64::from_le_bytes(self.take(8)?.try_into().expect("8")))
    }
    fn i32(&mut self) -> Result<i32> {
        Ok(i32::from_le_bytes(self.take(4)?.try_into().expect("4")))
    }
    fn f32(&mut self) -> Result<f32> {
        Ok(f32::from_le_bytes(self.take(4)?.try_into().expect("4")))
    }
}

/// What the gaze solver is given in an evaluation.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SolverInput {
    /// The network's mask and slippage (the full chain).
    Predicted,
    /// The network's mask, zero slippage (the geometric solver that ignores slippage).
    NoSlip,
    /// The true visible-pupil mask on the p̂ grid and the true slippage (the head's target,
    /// [`FrameEval::true_slip_mm`]): the solver's own error on rendered frames, without the
    /// network.
    Truth,
    /// As `Truth`, with the eye-equivalent translation whatever the head's target
    /// (`Camera::eye_equivalent_slip`): what the camera's unmodelled rotation costs the solver.
    TruthEyeEquivalent,
    /// The network's mask with the true slippage: the segmentation's share of the error.
    PredictedMaskTrueSlip,
    /// The true mask with the network's slippage: the calibration head's share of the error.
    TrueMaskPredictedSlip,
}

/// Per-frame results of a validation pass.
#[derive(Clone, Debug, Default)]
pub struct FrameEval {
    /// Angular gaze error per frame (degrees); None where the solver failed (empty mask or
    /// the ray misses the sphere).
    pub errors_deg: Vec<Option<f64>>,
    /// Hard Dice per frame.
    pub dice: Vec<f64>,
    /// Slippage squared error per frame (mm²).
    pub slip_sq_mm2: Vec<f64>,
    /// Estimated gaze (unit optical axis) per frame; None where the solver failed.
    pub gaze: Vec<Option<[f64; 3]>>,
    /// The network's slippage estimate per frame (mm, rig frame).
    pub slip_mm: Vec<[f64; 3]>,
    /// The slippage it is trained to estimate per frame (mm, rig frame; the chain's
    /// [`crate::SlipTarget`]).
    pub true_slip_mm: Vec<[f64; 3]>,
    /// Per frame: the solver fell back to its nearest estimate
    /// ([`nanoeye_gaze::GazeSolution::fallback`]); false where it failed.
    pub fallback: Vec<bool>,
}

/// The gaze error V counts per frame (degrees): a failed frame counts 90°.
pub const FAILED_FRAME_DEG: f64 = 90.0;

impl FrameEval {
    /// Per frame, the error V averages (degrees; [`FAILED_FRAME_DEG`] where the solver failed).
    pub fn scored_errors_deg(&self) -> Vec<f64> {
        self.errors_deg
            .iter()
            .map(|x| x.unwrap_or(FAILED_FRAME_DEG))
            .collect()
    }
}

/// What an evaluation runs: every frame of `data` through `chain` at φ = `map`, p̂ =
/// `p_hat_m` (m), subnet `arch` (BN as it stands: recalibrate first), in batches of `batch`,
/// sensor noise drawn from `seed`.
#[derive(Clone, Copy)]
pub struct EvalSetup<'a> {
    /// The camera chain.
    pub chain: &'a CameraChain,
    /// The frames, with their recorded gaze and slippage.
    pub data: &'a Dataset,
    /// The lens.
    pub map: &'a PhaseMap,
    /// Effective pixel pitch p̂ (m).
    pub p_hat_m: f64,
    /// The subnet.
    pub arch: &'a Arch,
    /// Frames per batch.
    pub batch: usize,
    /// Noise seed.
    pub seed: u64,
}

/// Per-frame gaze errors of `s`: predicted mask → S9 → S10–S14 with the predicted slippage
/// (`input` selects what the solver gets, `kind` which solver, `centre` how it takes the pupil
/// centre from the mask), against the recorded gaze.
pub fn evaluate_frames(
    net: &mut Supernet,
    s: &EvalSetup,
    input: SolverInput,
    kind: SolverKind,
    centre: PupilCentre,
) -> Result<FrameEval> {
    let mut v = evaluate_frames_multi(net, s, &[(input, kind, centre)])?;
    Ok(v.remove(0))
}

/// [`evaluate_frames`] for several (solver input, solver, pupil centre) triples from one pass
/// of the chain and the network: one [`FrameEval`] per triple, in order.
pub fn evaluate_frames_multi(
    net: &mut Supernet,
    s: &EvalSetup,
    solves: &[(SolverInput, SolverKind, PupilCentre)],
) -> Result<Vec<FrameEval>> {
    if solves.is_empty() {
        return Err(param("solves", "need at least one solver input"));
    }
    let mut out = vec![FrameEval::default(); solves.len()];
    let ids: Vec<usize> = (0..s.data.len()).collect();
    for chunk in ids.chunks(s.batch.max(1)) {
        let b = ChainedBatch::new(s.chain, s.data, chunk, s.map, s.p_hat_m, s.seed)?;
        b.score(net, s.arch, solves, &mut out)?;
    }
    Ok(out)
}

/// An evaluation set through the chain once, at one lens (φ, p̂) and noise seed, as
/// [`evaluate_frames`] images it: network inputs, targets and records per batch, so that any
/// number of subnets are scored on it ([`evaluate_chained`]) without reloading the frames,
/// reimaging them or redrawing their noise.
pub struct ChainedSet {
    batches: Vec<ChainedBatch>,
}

/// One batch of a [`ChainedSet`]: what scoring a subnet on it needs.
struct ChainedBatch {
    /// Network input (N, 1, H, W) on the p̂ grid.
    input: Tensor,
    /// Visible-pupil coverage (N, 1, H, W).
    mask: Tensor,
    /// Slippage targets (N, 3, 1, 1), mm.
    slip_mm: Tensor,
    /// The rig with the camera at p̂.
    rig: Rig,
    /// Per frame, its record (state, gaze).
    records: Vec<nanoeye_datagen::render::FrameRecord>,
    /// Per frame, the slippage the network is trained to estimate (m, rig frame, f64).
    slip_target_m: Vec<[f64; 3]>,
}

impl ChainedSet {
    /// Every frame of `data` through `chain` at φ = `map`, p̂ = `p_hat_m` (m), in batches of
    /// `batch`, sensor noise drawn from `seed` (the images [`evaluate_frames`] scores).
    pub fn new(
        chain: &CameraChain,
        data: &Dataset,
        map: &PhaseMap,
        p_hat_m: f64,
        batch: usize,
        seed: u64,
    ) -> Result<ChainedSet> {
        let ids: Vec<usize> = (0..data.len()).collect();
        let batches = ids
            .chunks(batch.max(1))
            .map(|chunk| ChainedBatch::new(chain, data, chunk, map, p_hat_m, seed))
            .collect::<Result<_>>()?;
        Ok(ChainedSet { batches })
    }

    /// Bytes a set of `frames` frames of `h`×`w` p̂ pixels holds (network inputs and masks,
    /// f32): to decide before computing one whether it fits.
    pub fn bytes_for(frames: usize, h: usize, w: usize) -> usize {
        frames
            .saturating_mul(h)
            .saturating_mul(w)
            .saturating_mul(2 * std::mem::size_of::<f32>())
    }
}

impl ChainedBatch {
    /// Frames `ids` of `data` through the chain, as [`evaluate_frames`] images them.
    fn new(
        chain: &CameraChain,
        data: &Dataset,
        ids: &[usize],
        map: &PhaseMap,
        p_hat_m: f64,
        seed: u64,
    ) -> Result<ChainedBatch> {
        let frames = chain.load(data, ids)?;
        let psfs = chain.psfs(map, &chain.active(&frames))?;
        let fwd = chain.forward_with(
            &frames,
            &psfs,
            p_hat_m,
            NoiseMode::Gaussian,
            seed ^ 0xBEEF,
            false,
        )?;
        let rig = Rig {
            camera: fwd.grid.camera.clone(),
            ..data.manifest.rig.clone()
        };
        // In f64 from the state (the tensor holds it in f32 for the loss).
        let slip_target_m = frames
            .iter()
            .map(|f| chain.config().slip_target.of(&rig.camera, &f.record.state))
            .collect();
        Ok(ChainedBatch {
            input: fwd.input,
            mask: fwd.mask,
            slip_mm: fwd.slip_mm,
            rig,
            records: frames.into_iter().map(|f| f.record).collect(),
            slip_target_m,
        })
    }

    /// Subnet `arch` (BN as it stands) on this batch, each frame solved as every triple of
    /// `solves` says, appended to `out` (one [`FrameEval`] per triple).
    fn score(
        &self,
        net: &mut Supernet,
        arch: &Arch,
        solves: &[(SolverInput, SolverKind, PupilCentre)],
        out: &mut [FrameEval],
    ) -> Result<()> {
        let o = net.forward(arch, &self.input, BnMode::Eval)?;
        let rig = &self.rig;
        let solvers = solves
            .iter()
            .map(|&(_, k, _)| solver_for(rig, k))
            .collect::<std::result::Result<Vec<_>, _>>()?;
        let (h, w) = (self.input.h, self.input.w);
        for (b, record) in self.records.iter().enumerate() {
            let one = |t: &Tensor, c: usize| Tensor {
                n: 1,
                c: t.c,
                h: t.h,
                w: t.w,
                data: t.data[b * c * t.h * t.w..(b + 1) * c * t.h * t.w].to_vec(),
            };
            let target = one(&self.mask, 1);
            let hard = Tensor {
                data: target
                    .data
                    .iter()
                    .map(|&m| if m >= 0.5 { 1.0 } else { 0.0 })
                    .collect(),
                ..target
            };
            let dice = hard_dice(&one(&o.mask_logits, 1), &hard)?;
            let slip_sq = slip_mse(&one(&o.slip, 3), &one(&self.slip_mm, 3))?.0;
            // The network's soft mask as S9 defines it. Cutting it to its dominant blob
            // (gaze::centroid::dominant_blob) was measured to add failures (docs/gaze.md).
            let predicted = Mat::from_fn(h, w, |i, j| {
                let l = o.mask_logits.image(b)[i * w + j];
                1.0 / (1.0 + (-l).exp())
            });
            let truth = Mat::from_fn(h, w, |i, j| self.mask.image(b)[i * w + j]);
            let net_slip_mm = [0, 1, 2].map(|a| o.slip.data[b * 3 + a] as f64);
            let target_m = self.slip_target_m[b];
            let true_slip_mm = target_m.map(|v| v * 1e3);
            for ((&(input, _, centre), solver), e) in
                solves.iter().zip(&solvers).zip(out.iter_mut())
            {
                e.dice.push(dice);
                e.slip_sq_mm2.push(slip_sq);
                e.slip_mm.push(net_slip_mm);
                e.true_slip_mm.push(true_slip_mm);
                let probs = match input {
                    SolverInput::Truth
                    | SolverInput::TruthEyeEquivalent
                    | SolverInput::TrueMaskPredictedSlip => &truth,
                    _ => &predicted,
                };
                let slip = match input {
                    SolverInput::NoSlip => [0.0; 3],
                    SolverInput::Truth | SolverInput::PredictedMaskTrueSlip => target_m,
                    SolverInput::TruthEyeEquivalent => {
                        let st = &record.state;
                        rig.camera.eye_equivalent_slip(st.slip_m, st.cam_rot_rad)
                    }
                    SolverInput::Predicted | SolverInput::TrueMaskPredictedSlip => {
                        net_slip_mm.map(|v| v * 1e-3)
                    }
                };
                let sol = solver.solve_mask_with(probs.as_ref(), slip, centre).ok();
                e.errors_deg.push(
                    sol.as_ref()
                        .map(|s| angular_error(s.gaze, record.gaze).to_degrees()),
                );
                e.fallback.push(sol.is_some_and(|s| s.fallback));
                e.gaze.push(sol.map(|s| s.gaze));
            }
        }
        Ok(())
    }
}

/// [`evaluate_frames_multi`] on a set already through the chain: the same per-frame results,
/// bit for bit, as scoring `arch` (BN as it stands) on the set's data, lens and seed.
pub fn evaluate_chained(
    net: &mut Supernet,
    arch: &Arch,
    set: &ChainedSet,
    solves: &[(SolverInput, SolverKind, PupilCentre)],
) -> Result<Vec<FrameEval>> {
    if solves.is_empty() {
        return Err(param("solves", "need at least one solver input"));
    }
    let mut out = vec![FrameEval::default(); solves.len()];
    for b in &set.batches {
        b.score(net, arch, solves, &mut out)?;
    }
    Ok(out)
}

/// Validation of `s` solved by `kind` with the pupil centre `centre`: V, median, failures,
/// Dice, slip MSE.
pub fn evaluate_net(
    net: &mut Supernet,
    s: &EvalSetup,
    kind: SolverKind,
    centre: PupilCentre,
) -> Result<Metrics> {
    let e = evaluate_frames(net, s, SolverInput::Predicted, kind, centre)?;
    let nb = e.errors_deg.len();
    if nb == 0 {
        return Err(param("val", "no validation frames"));
    }
    let errs = e.scored_errors_deg();
    let mut sorted = errs.clone();
    sorted.sort_by(f64::total_cmp);
    Ok(Metrics {
        v_deg: errs.iter().sum::<f64>() / nb as f64,
        median_deg: sorted[nb / 2],
        failures: e.errors_deg.iter().filter(|x| x.is_none()).count(),
        dice: e.dice.iter().sum::<f64>() / nb as f64,
        slip_mse: e.slip_sq_mm2.iter().sum::<f64>() / nb as f64,
        frames: nb,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A task gradient with one infinite or NaN value, in the image's or the mask's part, is
    /// refused naming the network's rate; a finite one passes.
    #[test]
    fn a_non_finite_task_gradient_is_refused() {
        let finite = || Tensor::from_vec(1, 1, 2, 3, vec![0.5; 6]).unwrap();
        let ok = TaskGrads {
            input: finite(),
            mask: finite(),
        };
        assert!(finite_task_grads(&ok).is_ok());
        for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
            for in_mask in [false, true] {
                let mut g = TaskGrads {
                    input: finite(),
                    mask: finite(),
                };
                let t = if in_mask { &mut g.mask } else { &mut g.input };
                t.data[4] = bad;
                let e = finite_task_grads(&g).unwrap_err().to_string();
                assert!(e.contains("lr_net"), "{e}");
            }
        }
    }

    /// A checkpoint has the mode `File::create` gives under this umask, not a temporary
    /// file's 0600 (every output of a run was owner-only).
    #[cfg(unix)]
    #[test]
    fn an_atomic_write_has_the_mode_file_create_gives() {
        let dir = tempfile::tempdir().unwrap();
        use std::os::unix::fs::PermissionsExt;
        let mode = |p: &Path| std::fs::metadata(p).unwrap().permissions().mode() & 0o777;
        let plain = dir.path().join("plain");
        std::fs::write(&plain, b"x").unwrap();
        let out = dir.path().join("checkpoint.bin");
        write_file_atomic(&out, b"x").unwrap();
        assert_eq!(mode(&out), mode(&plain));
    }

    /// A checkpoint's inputs are compared key by key where both sides hold the key: another
    /// value is refused naming it; a key one side lacks (an older build's record) and a side
    /// without inputs are not compared.
    #[test]
    fn checkpoint_inputs_differ_only_in_keys_both_hold() {
        use serde_json::json;
        let p = Path::new("ck.bin");
        let a = json!({"dataset": "00ff", "val": null, "lens": {"lens": "init"}});
        assert!(check_inputs(Some(&a), Some(&a), p).is_ok());
        assert!(check_inputs(None, Some(&a), p).is_ok());
        assert!(check_inputs(Some(&a), None, p).is_ok());
        let older = json!({"dataset": "00ff"});
        assert!(check_inputs(Some(&older), Some(&a), p).is_ok());
        assert!(check_inputs(Some(&a), Some(&older), p).is_ok());
        let e = check_inputs(Some(&a), Some(&json!({"dataset": "00fe"})), p)
            .unwrap_err()
            .to_string();
        assert!(e.contains("`dataset`") && e.contains("other inputs"), "{e}");
        let e = check_inputs(Some(&a), Some(&json!({"lens": {"lens": "hyperbolic"}})), p)
            .unwrap_err()
            .to_string();
        assert!(e.contains("`lens`") && !e.contains("`dataset`"), "{e}");
    }

    /// A checkpoint's counts are bounded by the bytes after them (an edited checkpoint with its
    /// checksum recomputed claimed 2⁴⁰ Adam moments: an allocation abort; 2⁶¹: a panic).
    #[test]
    fn a_count_beyond_the_bytes_left_is_an_error_not_an_allocation() {
        let mut b = 2u64.to_le_bytes().to_vec();
        b.extend([0u8; 16]);
        assert_eq!(Reader { b: &b, at: 0 }.count(8).unwrap(), 2);
        assert!(Reader { b: &b, at: 0 }.count(9).is_err());
        for n in [1u64 << 40, 1 << 61, u64::MAX] {
            let mut b = n.to_le_bytes().to_vec();
            b.extend([0u8; 64]);
            let e = Reader { b: &b, at: 0 }.count(8).unwrap_err().to_string();
            assert!(e.contains(&n.to_string()), "{e}");
        }
    }

    #[test]
    fn windows_start_at_multiples_and_the_last_step_ends_the_last() {
        let ends = |every, steps| -> Vec<(usize, usize)> {
            (0..steps)
                .filter_map(|t| {
                    let (first, e) = window_of(t, every, steps);
                    e.then_some((first, t))
                })
                .collect()
        };
        assert_eq!(ends(1, 3), [(0, 0), (1, 1), (2, 2)]);
        assert_eq!(ends(2, 5), [(0, 1), (2, 3), (4, 4)]);
        assert_eq!(ends(3, 6), [(0, 2), (3, 5)]);
        // A window longer than the run: φ steps once, after the last step.
        assert_eq!(ends(10, 4), [(0, 3)]);
        for t in 0..7 {
            assert_eq!(window_of(t, 3, 7).0, t / 3 * 3);
        }
    }

    #[test]
    fn phase_every_zero_or_huge_is_refused_by_name() {
        for m in [0, 10_000_001, usize::MAX] {
            let c = TrainConfig {
                phase_every: m,
                ..TrainConfig::default()
            };
            let e = c.validate().unwrap_err().to_string();
            assert!(e.contains("phase_every"), "{m}: {e}");
        }
        let ok = TrainConfig {
            phase_every: 7,
            ..TrainConfig::default()
        };
        ok.validate().unwrap();
        // Older checkpoints' configurations, without the field, read as one step per step.
        let mut v = serde_json::to_value(&ok).unwrap();
        v.as_object_mut().unwrap().remove("phase_every");
        let back: TrainConfig = serde_json::from_value(v).unwrap();
        assert_eq!(back.phase_every, 1);
    }
}

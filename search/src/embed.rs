//! The optical-embedding objective (S15, C.2) through the camera chain: each variational
//! triplet (anchor, slip+, gaze+) imaged noise-free at p̂, its sensitivity fields to the
//! glasses' slippage and to the gaze, and ∂L/∂φ by the chain's backward — a lens objective
//! that asks for what the tracker needs (the slippage told apart from the gaze) on rendered
//! eyes, where the point-source Fisher initialization (A.2) asks for depth information only.
//!
//! Per triplet, with e the mean electrons per output pixel (clipped at full well, as the DN
//! image the network sees) and σ² the read noise: J_s = (e_slip − e₀)/(h_s √(e₀ + σ²)), J_g likewise with
//! h_g; F = [J_s·J_s, J_s·J_g; ·, J_g·J_g] is the Fisher matrix of (slip along the triplet's
//! slip step, in mm; gaze along its gaze step, in degrees) under Poisson + read noise.
//! L = w_sens·L_sens + w_orth·L_orth (`nanoeye_fisher::optical_embedding`), averaged over the
//! triplets.

use crate::chain::{CameraChain, ChainFrame, ChainGrad};
use crate::error::{Result, param, positive};
use crate::train::{VecAdam, fnv1a, write_file_atomic};
use faer::Mat;
use nanoeye_datagen::render::Dataset;
use nanoeye_nets::Tensor;
use nanoeye_optics::PhaseMap;
use nanoeye_sensor::NoiseMode;
use rand::SeedableRng;
use rand::seq::SliceRandom;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Weights of the two terms and the floor of F's diagonal (1/mm², 1/deg²).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct EmbedWeights {
    /// Weight of L_sens = −½[ln(F_ss + f) + ln(F_gg + f)].
    pub w_sens: f64,
    /// Weight of L_orth = cos²φ (φ the angle between J_s and J_g).
    pub w_orth: f64,
    /// The floor f: keeps the logarithms finite for an image that does not change.
    pub floor: f64,
}

impl Default for EmbedWeights {
    fn default() -> Self {
        EmbedWeights {
            w_sens: 1.0,
            w_orth: 1.0,
            floor: 1e-6,
        }
    }
}

impl EmbedWeights {
    /// Refuses a negative or non-finite weight, both weights zero, or a floor that is not
    /// positive and finite, naming the field.
    pub fn validate(&self) -> Result<()> {
        for (name, v) in [("w_sens", self.w_sens), ("w_orth", self.w_orth)] {
            if !(v.is_finite() && (0.0..=1e6).contains(&v)) {
                return Err(param(name, format!("must lie in [0, 1e6], got {v}")));
            }
        }
        if self.w_sens == 0.0 && self.w_orth == 0.0 {
            return Err(param(
                "w_sens",
                "w_sens and w_orth are both 0: nothing to optimise",
            ));
        }
        positive("floor", self.floor)?;
        Ok(())
    }
}

/// The dataset's variational triplets as frame indices [anchor, slip+, gaze+], in item order.
/// Refuses a dataset with no triplet or an incomplete one.
pub fn triplets(ds: &Dataset) -> Result<Vec<[usize; 3]>> {
    // An ambiguity set's frames are anchor, slip, gaze: its anchors alone are no triplets.
    if !ds.records.iter().any(|r| r.role == "slip_plus") {
        return Err(no_triplets());
    }
    let mut by_item: std::collections::BTreeMap<usize, [Option<usize>; 3]> = Default::default();
    for (i, r) in ds.records.iter().enumerate() {
        let slot = match r.role.as_str() {
            "anchor" => 0,
            "slip_plus" => 1,
            "gaze_plus" => 2,
            _ => continue,
        };
        let e = by_item.entry(r.item).or_default();
        if e[slot].replace(i).is_some() {
            return Err(param(
                "dataset",
                format!("item {} has two `{}` frames", r.item, r.role),
            ));
        }
    }
    by_item
        .into_iter()
        .map(|(item, t)| match t {
            [Some(a), Some(s), Some(g)] => Ok([a, s, g]),
            _ => Err(param(
                "dataset",
                format!("triplet {item} lacks a frame (anchor, slip_plus, gaze_plus)"),
            )),
        })
        .collect()
}

fn no_triplets() -> crate::error::SearchError {
    param(
        "dataset",
        "holds no variational triplets (roles anchor, slip_plus, gaze_plus): render one with \
         `nanoeye datagen render --set variational`",
    )
}

/// A triplet's steps: the slippage step (mm) and the gaze step (degrees).
fn steps_of(frames: &[ChainFrame]) -> Result<[f64; 2]> {
    let (a, s, g) = (&frames[0].record, &frames[1].record, &frames[2].record);
    let d: f64 = (0..3)
        .map(|i| (s.state.slip_m[i] - a.state.slip_m[i]).powi(2))
        .sum::<f64>()
        .sqrt();
    let dot: f64 = (0..3).map(|i| a.gaze[i] * g.gaze[i]).sum();
    let na: f64 = a.gaze.iter().map(|v| v * v).sum::<f64>().sqrt();
    let ng: f64 = g.gaze.iter().map(|v| v * v).sum::<f64>().sqrt();
    let ang = (dot / (na * ng)).clamp(-1.0, 1.0).acos().to_degrees();
    if !(d > 0.0 && ang > 0.0 && ang.is_finite()) {
        return Err(param(
            "dataset",
            format!(
                "triplet of frame {}: its slip+ or gaze+ frame does not move (steps {d:e} m, \
                 {ang:e}°)",
                a.frame
            ),
        ));
    }
    Ok([d * 1e3, ang])
}

/// The objective over a set of triplets.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EmbedEval {
    /// Triplets averaged.
    pub triplets: usize,
    /// w_sens·L_sens + w_orth·L_orth, mean over the triplets.
    pub loss: f64,
    /// L_sens, mean.
    pub l_sens: f64,
    /// L_orth = cos²φ, mean.
    pub l_orth: f64,
    /// The slippage's two-parameter Cramér–Rao bound 1/√(F_ss(1 − cos²φ)) (µm along the
    /// triplet's slip step), geometric mean over the triplets.
    pub crlb_slip_um: f64,
    /// The gaze's two-parameter Cramér–Rao bound 1/√(F_gg(1 − cos²φ)) (degrees), geometric
    /// mean.
    pub crlb_gaze_deg: f64,
}

/// The objective on `frames` (three per triplet: anchor, slip+, gaze+) at effective pitch
/// `p_hat_m`, and with `grad` its gradient (∂L/∂φ, ∂L/∂p̂) through the chain.
pub fn embedding_loss(
    chain: &CameraChain,
    map: &PhaseMap,
    frames: &[ChainFrame],
    p_hat_m: f64,
    w: &EmbedWeights,
    grad: bool,
) -> Result<(EmbedEval, Option<ChainGrad>)> {
    let (eval, back) = objective(chain, map, frames, p_hat_m, w, grad)?;
    let grad = match back {
        Some((psfs, acc)) => Some(chain.finish(map, &psfs, acc)?),
        None => None,
    };
    Ok((eval, grad))
}

/// The objective as [`embedding_loss`], and its ∂L/∂P per slab and ∂L/∂p̂ (per metre) in the
/// layout of [`CameraChain::psf_grads`]: linear at a fixed φ, so a caller may add them to
/// another loss's at the same φ and take one [`CameraChain::phase_vjp`] of the sum.
pub fn embedding_psf_grads(
    chain: &CameraChain,
    map: &PhaseMap,
    frames: &[ChainFrame],
    p_hat_m: f64,
    w: &EmbedWeights,
) -> Result<(EmbedEval, Vec<Mat<f64>>, f64)> {
    let (eval, back) = objective(chain, map, frames, p_hat_m, w, true)?;
    let (psfs, acc) = back.ok_or_else(|| param("embedding", "no gradient"))?;
    let (grads, p_hat) = chain.psf_grads(&psfs, acc)?;
    Ok((eval, grads, p_hat))
}

/// What the backward left to do: the step's PSF stack and the accumulator filled against it.
type Backward = (
    std::sync::Arc<crate::chain::StepPsfs>,
    crate::chain::PsfGradAccumulator,
);

/// The objective, and with `grad` the chain's backward into an accumulator.
fn objective(
    chain: &CameraChain,
    map: &PhaseMap,
    frames: &[ChainFrame],
    p_hat_m: f64,
    w: &EmbedWeights,
    grad: bool,
) -> Result<(EmbedEval, Option<Backward>)> {
    w.validate()?;
    if frames.is_empty() || !frames.len().is_multiple_of(3) {
        return Err(param(
            "frames",
            format!("need three per triplet, got {}", frames.len()),
        ));
    }
    let nt = frames.len() / 3;
    let steps: Vec<[f64; 2]> = frames.chunks(3).map(steps_of).collect::<Result<_>>()?;
    let psfs = chain.psfs(map, &chain.active(frames))?;
    let fwd = chain.forward_with(frames, &psfs, p_hat_m, NoiseMode::None, 0, grad)?;
    let c = &chain.config().sensor;
    // The input is (DN − black)/span with DN = black + gain·min(e, full well) clipped at the
    // ADC's top, so ∂L/∂x = ∂L/∂e·span/gain where e is below both (the sensor's VJP zeroes
    // the rest). The objective reads e itself rather than back from the f32 DN image, whose
    // rounding near the black level would swamp a dim pixel's change between two frames of
    // a triplet. It saturates where the DN does: at full well or at the ADC's top, whichever
    // comes first (the same point at the default gain, 1007 DN over 8000 e⁻).
    let to_e = (c.max_dn() - c.black_level_dn) / c.gain_dn_per_e;
    let var = c.read_noise_e * c.read_noise_e;
    let full = c.full_well_e.min(to_e) as f32;
    let [_, _, h, wd] = fwd.input.shape();
    let electrons = |b: usize| {
        let e = &fwd.electrons[b];
        Mat::from_fn(h, wd, |i, j| e[(i, j)].clamp(0.0, full))
    };
    let per: Vec<Result<_>> = (0..nt)
        .map(|t| {
            let (e0, es, eg) = (electrons(3 * t), electrons(3 * t + 1), electrons(3 * t + 2));
            nanoeye_fisher::optical_embedding(
                &e0, &es, &eg, steps[t], var, w.floor, w.w_sens, w.w_orth,
            )
            .map_err(|e| param("embedding", e.to_string()))
        })
        .collect();
    let mut d_input = grad.then(|| Tensor::zeros(frames.len(), 1, h, wd));
    let (mut loss, mut ls, mut lo, mut ln_s, mut ln_g) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for (t, r) in per.into_iter().enumerate() {
        let (terms, g) = r?;
        loss += w.w_sens * terms.l_sens + w.w_orth * terms.l_orth;
        ls += terms.l_sens;
        lo += terms.l_orth;
        let rest = (1.0 - terms.cos_phi * terms.cos_phi).max(1e-300);
        ln_s += -0.5 * (terms.f11 * rest).max(1e-300).ln();
        ln_g += -0.5 * (terms.f22 * rest).max(1e-300).ln();
        if let Some(d) = d_input.as_mut() {
            // The mean over triplets, back from electrons to the input's units.
            let k = to_e / nt as f64;
            for (s, m) in [g.d_i0, g.d_i1, g.d_i2].iter().enumerate() {
                let di = d.image_mut(3 * t + s);
                for i in 0..h {
                    for j in 0..wd {
                        di[i * wd + j] = (m[(i, j)] * k) as f32;
                    }
                }
            }
        }
    }
    let n = nt as f64;
    let eval = EmbedEval {
        triplets: nt,
        loss: loss / n,
        l_sens: ls / n,
        l_orth: lo / n,
        crlb_slip_um: (ln_s / n).exp() * 1e3,
        crlb_gaze_deg: (ln_g / n).exp(),
    };
    let back = match d_input {
        Some(d) => {
            let mut acc = chain.accumulator();
            chain.backward(frames, &psfs, &fwd, &d, &mut acc)?;
            Some((psfs, acc))
        }
        None => None,
    };
    Ok((eval, back))
}

/// The `batch` triplets of step `t`: a seeded permutation of `trips` per pass over them, so a
/// step's batch depends on (seed, t) only.
pub fn triplet_batch(trips: &[[usize; 3]], batch: usize, seed: u64, t: usize) -> Vec<[usize; 3]> {
    let n = trips.len();
    if n == 0 {
        return Vec::new();
    }
    let perm_of = |e: usize| {
        let mut p: Vec<usize> = (0..n).collect();
        let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0xe3b0_c442);
        rng.set_stream(e as u64);
        p.shuffle(&mut rng);
        p
    };
    let first = t * batch;
    let mut cache: Option<(usize, Vec<usize>)> = None;
    (first..first + batch)
        .map(|k| {
            let e = k / n;
            if cache.as_ref().is_none_or(|(ce, _)| *ce != e) {
                cache = Some((e, perm_of(e)));
            }
            trips[cache.as_ref().expect("set").1[k % n]]
        })
        .collect()
}

/// The settings of an embedding run (a resume must give the same).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EmbedConfig {
    /// Adam steps of φ.
    pub steps: usize,
    /// Triplets per step.
    pub batch: usize,
    /// Adam's learning rate of φ (rad).
    pub lr_rad: f64,
    /// Effective pitch p̂ (µm), fixed.
    pub pitch_um: f64,
    /// Seeds the triplets' order.
    pub seed: u64,
    /// The objective's weights.
    pub weights: EmbedWeights,
}

impl Default for EmbedConfig {
    fn default() -> Self {
        EmbedConfig {
            steps: 40,
            batch: 4,
            lr_rad: 0.02,
            pitch_um: 14.0,
            seed: 0,
            weights: EmbedWeights::default(),
        }
    }
}

impl EmbedConfig {
    /// Refuses out-of-range settings, naming the field.
    pub fn validate(&self) -> Result<()> {
        if self.steps > 1_000_000 {
            return Err(param(
                "steps",
                format!("must be at most 1e6, got {}", self.steps),
            ));
        }
        if self.batch == 0 || self.batch > 4096 {
            return Err(param(
                "batch",
                format!("must lie in 1..=4096, got {}", self.batch),
            ));
        }
        if !(self.lr_rad.is_finite() && self.lr_rad > 0.0 && self.lr_rad <= 10.0) {
            return Err(param(
                "lr_rad",
                format!("must lie in (0, 10], got {}", self.lr_rad),
            ));
        }
        positive("pitch_um", self.pitch_um)?;
        self.weights.validate()
    }
}

/// One step's record (history.jsonl).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EmbedRecord {
    /// Step index (0-based).
    pub step: usize,
    /// The batch's objective before the step.
    pub loss: f64,
    /// L_sens, the batch's mean.
    pub l_sens: f64,
    /// L_orth, the batch's mean.
    pub l_orth: f64,
    /// RMS change of φ in the step (rad).
    pub phase_step_rad: f64,
}

/// Magic line of an embedding checkpoint.
const EMBED_MAGIC: &[u8] = b"NANOEYE-EMBED-CKPT-1\n";

#[derive(Serialize, Deserialize)]
struct EmbedMeta {
    config: EmbedConfig,
    triplets: usize,
    phase_n: usize,
    step: usize,
    adam_t: i32,
    history: Vec<EmbedRecord>,
    /// The caller's inputs ([`Embedder::set_inputs`]), absent when it gave none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    inputs: Option<serde_json::Value>,
}

/// Adam on φ under the embedding objective, over a dataset's triplets (p̂ fixed).
pub struct Embedder<'a> {
    chain: &'a CameraChain,
    ds: &'a Dataset,
    cfg: EmbedConfig,
    trips: Vec<[usize; 3]>,
    phase: Mat<f64>,
    adam: VecAdam,
    step: usize,
    history: Vec<EmbedRecord>,
    /// What the result depends on beyond `cfg` ([`Self::set_inputs`]).
    inputs: Option<serde_json::Value>,
}

impl<'a> Embedder<'a> {
    /// Records what the result depends on beyond the configuration in every checkpoint, as
    /// [`crate::Trainer::set_inputs`] does: [`Self::load`] refuses a checkpoint saved with
    /// other values in a key both hold.
    pub fn set_inputs(&mut self, inputs: serde_json::Value) {
        self.inputs = Some(inputs);
    }

    /// Starts from `phase` (n×n on the chain's aperture grid).
    pub fn new(
        chain: &'a CameraChain,
        ds: &'a Dataset,
        cfg: EmbedConfig,
        phase: Mat<f64>,
    ) -> Result<Embedder<'a>> {
        cfg.validate()?;
        let n = chain.aperture_grid().n;
        if phase.shape() != (n, n) {
            return Err(param(
                "phase",
                format!("{:?}, the aperture grid is {n}×{n}", phase.shape()),
            ));
        }
        if phase.col_iter().any(|c| c.iter().any(|v| !v.is_finite())) {
            return Err(param("phase", "holds a value that is not finite"));
        }
        let trips = triplets(ds)?;
        if cfg.batch > trips.len() {
            return Err(param(
                "batch",
                format!(
                    "{} triplets per step, the dataset has {}",
                    cfg.batch,
                    trips.len()
                ),
            ));
        }
        Ok(Embedder {
            chain,
            ds,
            cfg,
            trips,
            adam: VecAdam::new(n * n),
            phase,
            step: 0,
            history: Vec::new(),
            inputs: None,
        })
    }

    /// Steps taken.
    pub fn step(&self) -> usize {
        self.step
    }

    /// φ now (rad).
    pub fn phase(&self) -> &Mat<f64> {
        &self.phase
    }

    /// The records of the steps taken.
    pub fn history(&self) -> &[EmbedRecord] {
        &self.history
    }

    /// The triplets of step `t` ([`triplet_batch`] at this run's batch and seed).
    pub fn batch_of(&self, t: usize) -> Vec<[usize; 3]> {
        triplet_batch(&self.trips, self.cfg.batch, self.cfg.seed, t)
    }

    fn map(&self) -> Result<PhaseMap> {
        Ok(PhaseMap::phase_only(
            *self.chain.aperture_grid(),
            self.phase.clone(),
        )?)
    }

    fn frames(&self, trips: &[[usize; 3]]) -> Result<Vec<ChainFrame>> {
        let ids: Vec<usize> = trips.iter().flatten().copied().collect();
        self.chain.load(self.ds, &ids)
    }

    /// One Adam step of φ on the next batch.
    pub fn train_step(&mut self) -> Result<EmbedRecord> {
        let frames = self.frames(&self.batch_of(self.step))?;
        let (ev, g) = embedding_loss(
            self.chain,
            &self.map()?,
            &frames,
            self.cfg.pitch_um * 1e-6,
            &self.cfg.weights,
            true,
        )?;
        let g = g.expect("asked for the gradient");
        let n = self.phase.nrows();
        let gv: Vec<f64> = (0..n * n).map(|k| g.phase_rad[(k / n, k % n)]).collect();
        let mut x: Vec<f64> = (0..n * n).map(|k| self.phase[(k / n, k % n)]).collect();
        let rms = self.adam.step(&mut x, &gv, self.cfg.lr_rad);
        self.phase = Mat::from_fn(n, n, |i, j| x[i * n + j]);
        let rec = EmbedRecord {
            step: self.step,
            loss: ev.loss,
            l_sens: ev.l_sens,
            l_orth: ev.l_orth,
            phase_step_rad: rms,
        };
        self.step += 1;
        self.history.push(rec.clone());
        Ok(rec)
    }

    /// The objective over every triplet at φ now, `chunk` triplets at a time (no gradient).
    pub fn evaluate(&self, chunk: usize) -> Result<EmbedEval> {
        let map = self.map()?;
        let (mut acc, mut n) = ((0.0, 0.0, 0.0, 0.0, 0.0), 0usize);
        for part in self.trips.chunks(chunk.max(1)) {
            let frames = self.frames(part)?;
            let (ev, _) = embedding_loss(
                self.chain,
                &map,
                &frames,
                self.cfg.pitch_um * 1e-6,
                &self.cfg.weights,
                false,
            )?;
            let k = ev.triplets as f64;
            acc.0 += ev.loss * k;
            acc.1 += ev.l_sens * k;
            acc.2 += ev.l_orth * k;
            acc.3 += ev.crlb_slip_um.ln() * k;
            acc.4 += ev.crlb_gaze_deg.ln() * k;
            n += ev.triplets;
        }
        let m = n as f64;
        Ok(EmbedEval {
            triplets: n,
            loss: acc.0 / m,
            l_sens: acc.1 / m,
            l_orth: acc.2 / m,
            crlb_slip_um: (acc.3 / m).exp(),
            crlb_gaze_deg: (acc.4 / m).exp(),
        })
    }

    /// Writes φ, Adam's moments, the step and the history as one file, atomically.
    pub fn save(&self, path: &Path) -> Result<()> {
        let meta = EmbedMeta {
            config: self.cfg.clone(),
            triplets: self.trips.len(),
            phase_n: self.phase.nrows(),
            step: self.step,
            adam_t: self.adam.t,
            history: self.history.clone(),
            inputs: self.inputs.clone(),
        };
        let json = serde_json::to_vec(&meta).map_err(|e| param("checkpoint", e.to_string()))?;
        let n = self.phase.nrows();
        let mut b = Vec::with_capacity(json.len() + 24 * n * n + 64);
        b.extend_from_slice(EMBED_MAGIC);
        b.extend_from_slice(&(json.len() as u64).to_le_bytes());
        b.extend_from_slice(&json);
        for i in 0..n {
            for j in 0..n {
                b.extend_from_slice(&self.phase[(i, j)].to_le_bytes());
            }
        }
        for x in self.adam.m.iter().chain(&self.adam.v) {
            b.extend_from_slice(&x.to_le_bytes());
        }
        let h = fnv1a(&b);
        b.extend_from_slice(&h.to_le_bytes());
        write_file_atomic(path, &b)
    }

    /// Restores a checkpoint of [`Self::save`]; refuses another configuration or dataset
    /// (naming the first differing setting) and a corrupt or truncated file.
    pub fn load(&mut self, path: &Path) -> Result<()> {
        let bad = |why: String| param("checkpoint", format!("{}: {why}", path.display()));
        let b = std::fs::read(path).map_err(|e| bad(e.to_string()))?;
        if b.len() < EMBED_MAGIC.len() + 16 || &b[..EMBED_MAGIC.len()] != EMBED_MAGIC {
            return Err(bad("not an embedding checkpoint".into()));
        }
        let (body, tail) = b.split_at(b.len() - 8);
        if fnv1a(body) != u64::from_le_bytes(tail.try_into().expect("8 bytes")) {
            return Err(bad(
                "checksum mismatch: the file is corrupted or truncated".into()
            ));
        }
        let mut at = EMBED_MAGIC.len();
        let jl = u64::from_le_bytes(body[at..at + 8].try_into().expect("8 bytes")) as usize;
        at += 8;
        let meta: EmbedMeta = body
            .get(at..at.saturating_add(jl))
            .ok_or_else(|| bad("truncated".into()))
            .and_then(|j| serde_json::from_slice(j).map_err(|e| bad(e.to_string())))?;
        at += jl;
        if meta.config != self.cfg {
            return Err(bad(format!(
                "written with other parameters ({}): use a new --out",
                crate::error::differences(&meta.config, &self.cfg)
            )));
        }
        crate::train::check_inputs(meta.inputs.as_ref(), self.inputs.as_ref(), path)?;
        let n = self.phase.nrows();
        if meta.triplets != self.trips.len() || meta.phase_n != n {
            return Err(bad(format!(
                "written for {} triplets and a {}² aperture grid, not {} and {n}²: use a new --out",
                meta.triplets,
                meta.phase_n,
                self.trips.len()
            )));
        }
        let vals: Vec<f64> = body[at..]
            .chunks_exact(8)
            .map(|c| f64::from_le_bytes(c.try_into().expect("8 bytes")))
            .collect();
        if vals.len() != 3 * n * n || body.len() - at != 24 * n * n {
            return Err(bad("truncated".into()));
        }
        self.phase = Mat::from_fn(n, n, |i, j| vals[i * n + j]);
        self.adam.m = vals[n * n..2 * n * n].to_vec();
        self.adam.v = vals[2 * n * n..].to_vec();
        self.adam.t = meta.adam_t;
        self.step = meta.step;
        self.history = meta.history;
        Ok(())
    }
}

//! `nanoeye search train`: sandwich-rule co-design of the lens, the pixel pitch and the
//! supernet (S22) on a rendered dataset, resumable, with loss curves and validation.

use crate::sim::{CAMERA_KEYS, ChainArgs};
use crate::util;
use anyhow::{Context, Result, bail};
use clap::Args;
use nanoeye_datagen::render::Dataset;
use nanoeye_nets::Arch;
use nanoeye_search::{CameraChain, LensSpec, StepRecord, TrainConfig, Trainer};
use std::io::IsTerminal;
use std::path::PathBuf;
use std::time::Instant;

/// `nanoeye search train` options.
#[derive(Debug, Args)]
pub struct TrainArgs {
    #[command(flatten)]
    chain: ChainArgs,
    /// Held-out dataset for validation (default: the training set).
    #[arg(long)]
    val: Option<PathBuf>,
    /// Initial lens: init (the Fisher initialization of A.2 on this chain, from the hyperbolic
    /// phase), hyperbolic, double-helix, flat (no lens) or file:PHASE.npy (e.g. `fisher init`'s
    /// DIR/phase.npy).
    #[arg(long, default_value = "hyperbolic")]
    lens: String,
    /// Fisher-initialization iterations of `--lens init`.
    #[arg(long, default_value_t = 40)]
    fisher_iterations: usize,
    /// Photons through the aperture in `--lens init`'s Fisher loss.
    #[arg(long, default_value_t = 1e5)]
    fisher_photons: f64,
    /// Keep the lens fixed (baselines).
    #[arg(long)]
    fixed_lens: bool,
    /// Optimisation steps.
    #[arg(long, default_value_t = 100)]
    steps: usize,
    /// Frames per batch.
    #[arg(long, default_value_t = 4)]
    batch: usize,
    /// Random subnets per step besides N_max and N_min.
    #[arg(long, default_value_t = 2)]
    random_subnets: usize,
    /// Peak learning rate of the network (Adam, cosine decay).
    #[arg(long, default_value_t = 2e-3)]
    lr_net: f64,
    /// Learning rate of the phase map (rad per step, Adam).
    #[arg(long, default_value_t = 2e-2)]
    lr_phase_rad: f64,
    /// What the phase map's steps are taken in: `pixels` (every aperture sample) or
    /// `zernike:N` (the Zernike modes of radial order 1..=N over the aperture).
    #[arg(long, default_value = "pixels")]
    phase_basis: nanoeye_search::PhaseBasis,
    /// How the phase map's rate moves over the steps: `constant`, `cosine` or `cosine:F`
    /// (cosine decay to zero over the first fraction F of the steps, the lens fixed after).
    #[arg(long, default_value = "constant")]
    phase_schedule: nanoeye_search::PhaseSchedule,
    /// Sandwich steps per phase-map step (M): φ is fixed over each window of M steps and
    /// steps once after it by the mean of their gradients (one PSF VJP per window).
    #[arg(long, default_value_t = 1)]
    phase_every: usize,
    /// Learning rate of the pitch (µm per step, Adam).
    #[arg(long, default_value_t = 5e-2)]
    lr_pitch_um: f64,
    /// Weight of the slippage MSE (per mm²).
    #[arg(long, default_value_t = 0.1)]
    lambda_slip: f64,
    /// Relative weight of the slippage axes in that MSE, X,Y,Z.
    #[arg(long, default_value = "1,1,1")]
    slip_axis_weights: String,
    /// Smallest and largest effective pitch (µm).
    #[arg(long, default_value = "3:12")]
    pitch_range_um: String,
    /// Seed of batches, subnets and noise.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Seed of the initial weights.
    #[arg(long, default_value_t = 0)]
    weights_seed: u64,
    /// Gaze solver of the validation: refractive (through the rig's cornea) or sphere (S12).
    #[arg(long, default_value = "refractive")]
    solver: String,
    /// Pupil centre of the validation: centroid (S9) or ellipse_if_cut (S9 unless the pupil
    /// reaches the frame's edge, then its boundary's fitted ellipse; docs/gaze.md).
    #[arg(long, default_value = "centroid")]
    pupil_centre: String,
    /// BN statistics of N_min and N_max before the final validation: `all`, every training
    /// frame once, or N training batches in training order (2 until 2026-12-02). Training does
    /// not depend on it, so a resume may change it.
    #[arg(long, default_value = "all", allow_negative_numbers = true)]
    bn_batches: nanoeye_search::BnBatches,
    /// Weight μ of the optical-embedding objective (S15, `search embed`'s) in the phase map's
    /// loss: every phase step descends the sandwich loss + μ·L_embed on `--embed-triplets`
    /// (0: none).
    #[arg(long, default_value_t = 0.0)]
    embed_weight: f64,
    /// Variational triplet set of the embedding term (`datagen render --set variational`, on
    /// the training set's rig and slabs).
    #[arg(long)]
    embed_triplets: Option<PathBuf>,
    /// Triplets per phase step of the embedding term.
    #[arg(long, default_value_t = 4)]
    embed_batch: usize,
    /// Weight of the embedding term's sensitivity part L_sens.
    #[arg(long, default_value_t = 1.0)]
    embed_w_sens: f64,
    /// Weight of the embedding term's orthogonality part cos²φ.
    #[arg(long, default_value_t = 1.0)]
    embed_w_orth: f64,
    /// Steps between checkpoints.
    #[arg(long, default_value_t = 10)]
    checkpoint_every: usize,
    /// Run directory (checkpoint.bin, phase.npy, history.jsonl, loss.svg, metrics.json).
    #[arg(long)]
    out: PathBuf,
    /// Print JSON.
    #[arg(long)]
    json: bool,
}

/// The error prefixed with the CLI flag of the configuration field it names (`flags`: field →
/// flag), or with `fallback` when it names none.
fn with_flag(
    e: nanoeye_search::SearchError,
    flags: &[(&str, &'static str)],
    fallback: &'static str,
) -> anyhow::Error {
    let flag = match &e {
        nanoeye_search::SearchError::Param { name, .. } => flags
            .iter()
            .find(|(k, _)| k == name)
            .map_or(fallback, |(_, f)| f),
        _ => fallback,
    };
    anyhow::anyhow!("{flag}: {e}")
}

/// Three comma-separated numbers X,Y,Z for `flag`.
fn parse_axes(flag: &str, text: &str) -> Result<[f64; 3]> {
    <[f64; 3]>::try_from(util::parse_list(flag, text)?)
        .map_err(|v| anyhow::anyhow!("{flag}: expected 3 values X,Y,Z, got {}", v.len()))
}

/// A 640×360 line plot of `n` points over x = 0 … n − 1 and y = 0 … `ymax`.
pub(crate) struct Plot {
    pub(crate) n: f64,
    pub(crate) ymax: f64,
}

impl Plot {
    const W: f64 = 640.0;
    const H: f64 = 360.0;
    const M: f64 = 40.0;

    /// SVG coordinates of point `i` at value `v` (clamped to the axes).
    fn xy(&self, i: usize, v: f64) -> (f64, f64) {
        let (w, h, m) = (Self::W, Self::H, Self::M);
        (
            m + (w - 2.0 * m) * i as f64 / (self.n - 1.0).max(1.0),
            h - m - (h - 2.0 * m) * (v / self.ymax).clamp(0.0, 1.0),
        )
    }

    /// "x,y x,y …" of `values`.
    pub(crate) fn polyline(&self, values: impl Iterator<Item = f64>) -> String {
        values
            .enumerate()
            .map(|(i, v)| {
                let (x, y) = self.xy(i, v);
                format!("{x:.1},{y:.1}")
            })
            .collect::<Vec<_>>()
            .join(" ")
    }

    /// The self-contained SVG: axes, labels, `body`, and `legend` as (text, colour) lines.
    pub(crate) fn svg(
        &self,
        xlabel: &str,
        ylabel: &str,
        body: &str,
        legend: &[(&str, &str)],
    ) -> String {
        let (w, ht, m) = (Self::W, Self::H, Self::M);
        let (b, r, cx, tb, cy) = (ht - m, w - m, w / 2.0, ht - 8.0, ht / 2.0);
        let last = (self.n as usize).saturating_sub(1);
        let legend: String = legend
            .iter()
            .enumerate()
            .map(|(k, (t, c))| {
                format!(
                    r##"<text x="{}" y="{}" fill="{c}">{t}</text>"##,
                    w - m - 150.0,
                    m + 16.0 * k as f64
                )
            })
            .collect();
        format!(
            r##"<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{ht}" font-family="sans-serif" font-size="12">
<rect width="100%" height="100%" fill="white"/>
<line x1="{m}" y1="{b}" x2="{r}" y2="{b}" stroke="black"/><line x1="{m}" y1="{m}" x2="{m}" y2="{b}" stroke="black"/>
<text x="{cx}" y="{tb}" text-anchor="middle">{xlabel} (0 … {last})</text>
<text x="12" y="{cy}" transform="rotate(-90 12 {cy})" text-anchor="middle">{ylabel} (0 … {ymax:.3})</text>
{body}
{legend}
</svg>
"##,
            ymax = self.ymax
        )
    }
}

/// Loss curves of N_max and N_min as a self-contained SVG, and the embedding term's L_embed
/// (on its own scale, from its lowest to its highest value) where the run has one.
pub fn svg_curves(h: &[StepRecord]) -> String {
    let p = Plot {
        n: h.len().max(2) as f64,
        ymax: h
            .iter()
            .flat_map(|r| [r.loss_max, r.loss_min])
            .fold(1e-9f64, f64::max),
    };
    let mut body = format!(
        r##"<polyline fill="none" stroke="#c0392b" stroke-width="1.5" points="{}"/>
<polyline fill="none" stroke="#2471a3" stroke-width="1.5" points="{}"/>"##,
        p.polyline(h.iter().map(|r| r.loss_max)),
        p.polyline(h.iter().map(|r| r.loss_min)),
    );
    let mut legend = vec![
        ("N_max".to_string(), "#c0392b"),
        ("N_min".to_string(), "#2471a3"),
    ];
    let embed: Vec<(usize, f64)> = h
        .iter()
        .enumerate()
        .filter_map(|(i, r)| r.embed_loss.filter(|l| l.is_finite()).map(|l| (i, l)))
        .collect();
    if !embed.is_empty() {
        let lo = embed.iter().map(|e| e.1).fold(f64::INFINITY, f64::min);
        let hi = embed.iter().map(|e| e.1).fold(f64::NEG_INFINITY, f64::max);
        let span = (hi - lo).max(1e-12);
        let pts: Vec<String> = embed
            .iter()
            .map(|&(i, l)| {
                let (x, y) = p.xy(i, (l - lo) / span * p.ymax);
                format!("{x:.1},{y:.1}")
            })
            .collect();
        body.push_str(&format!(
            "\n<polyline fill=\"none\" stroke=\"#27ae60\" stroke-width=\"1\" points=\"{}\"/>",
            pts.join(" ")
        ));
        legend.push((format!("L_embed ({lo:.3} … {hi:.3})"), "#27ae60"));
    }
    let legend: Vec<(&str, &str)> = legend.iter().map(|(t, c)| (t.as_str(), *c)).collect();
    p.svg("step", "task loss", &body, &legend)
}

/// Fitness curve of a search as a self-contained SVG: per cycle the child's V (degrees) and its
/// penalized error −fitness = V + γ·𝕀(C > budget) (S19), and the best penalized error so far.
pub fn svg_fitness(h: &[nanoeye_search::CycleRecord]) -> String {
    let p = Plot {
        n: h.len().max(2) as f64,
        ymax: h
            .iter()
            .flat_map(|c| [c.child.v, -c.child.fitness])
            .filter(|v| v.is_finite())
            .fold(1e-9f64, f64::max),
    };
    let mut body = String::new();
    for (i, c) in h.iter().enumerate() {
        let pen = -c.child.fitness;
        if pen > c.child.v {
            let (x, y) = p.xy(i, pen);
            body += &format!(
                r##"<circle cx="{x:.1}" cy="{y:.1}" r="2.5" fill="none" stroke="#c0392b"/>"##
            );
        }
        let (x, y) = p.xy(i, c.child.v);
        body += &format!(r##"<circle cx="{x:.1}" cy="{y:.1}" r="2.5" fill="#2471a3"/>"##);
    }
    let best = h.iter().scan(f64::INFINITY, |b, c| {
        *b = b.min(-c.child.fitness);
        Some(*b)
    });
    body += &format!(
        r##"
<polyline fill="none" stroke="black" stroke-width="1.5" points="{}"/>"##,
        p.polyline(best)
    );
    p.svg(
        "cycle",
        "degrees",
        &body,
        &[
            ("child V", "#2471a3"),
            ("V + γ (over budget)", "#c0392b"),
            ("best so far", "black"),
        ],
    )
}

fn write_outputs(t: &mut Trainer, out: &std::path::Path) -> Result<()> {
    t.save(&out.join("checkpoint.bin"))
        .context("--out: writing checkpoint.bin")?;
    util::write_atomic(&out.join("phase.npy"), &crate::sim::npy_mat64(&t.phase)?)?;
    let lines: String = t
        .history
        .iter()
        .map(|r| serde_json::to_string(r).unwrap_or_default() + "\n")
        .collect();
    util::write_atomic(&out.join("history.jsonl"), lines.as_bytes())?;
    util::write_atomic(&out.join("loss.svg"), svg_curves(&t.history).as_bytes())?;
    Ok(())
}

/// Runs `nanoeye search train`. Under `mpirun -np N` every rank runs the same training and
/// each step's PSF stack and PSF VJP are split over depth across the ranks and all-gathered
/// (`dist::RankSplit`): the same bits on every rank as on one process; rank 0 alone reads the
/// checkpoint (and sends it), writes the outputs and prints.
pub fn train(a: TrainArgs) -> Result<()> {
    let t0 = Instant::now();
    let w = crate::dist::world();
    let (ds, mut chain) = a.chain.build(nanoeye_optics::PsfUsage::Training)?;
    let split = std::sync::Arc::new(crate::dist::RankSplit::new(w));
    if w.is_distributed() {
        chain.set_split(split.clone());
    }
    let range = util::parse_list("--pitch-range-um", &a.pitch_range_um.replace(':', ","))?;
    let [lo, hi] = range[..] else {
        bail!(
            "--pitch-range-um: expected MIN:MAX, got '{}'",
            a.pitch_range_um
        );
    };
    let (nh, nw) = chain.native().shape();
    util::check_batch_memory("--batch", a.batch, 1, nw, nh)?;
    // p̂ may reach the range's top: the sensor must hold at least a pixel of it (else the
    // training failed at that step, naming the rig's pixel pitch).
    // (A top finer than the native grid is refused with the range's other checks.)
    if hi.is_finite() && hi * 1e-6 >= chain.native().pitch_m() {
        chain.native().at(hi * 1e-6).with_context(|| {
            format!("--pitch-range-um: ends at {hi} µm, beyond what --dataset's frames hold")
        })?;
    }
    let cfg = TrainConfig {
        steps: a.steps,
        batch: a.batch,
        n_random: a.random_subnets,
        lr_net: a.lr_net,
        lr_phase_rad: a.lr_phase_rad,
        phase_basis: a.phase_basis,
        phase_schedule: a.phase_schedule,
        phase_every: a.phase_every,
        lr_pitch_um: a.lr_pitch_um,
        lambda_slip: a.lambda_slip,
        slip_axis_weights: parse_axes("--slip-axis-weights", &a.slip_axis_weights)?,
        pitch_init_um: a.chain.pitch_um(),
        pitch_range_um: [lo, hi],
        fixed_lens: a.fixed_lens,
        seed: a.seed,
        weights_seed: a.weights_seed,
        solver: nanoeye_gaze::SolverKind::parse(&a.solver).context("--solver")?,
        pupil_centre: nanoeye_gaze::PupilCentre::parse(&a.pupil_centre)
            .context("--pupil-centre")?,
        embed_weight: a.embed_weight,
        embed_batch: a.embed_batch,
        embed_terms: nanoeye_search::EmbedWeights {
            w_sens: a.embed_w_sens,
            w_orth: a.embed_w_orth,
            ..Default::default()
        },
        ..TrainConfig::default()
    };
    cfg.validate().map_err(|e| {
        with_flag(
            e,
            &[
                ("steps", "--steps"),
                ("batch", "--batch"),
                ("n_random", "--random-subnets"),
                ("lr_net", "--lr-net"),
                ("lr_phase_rad", "--lr-phase-rad"),
                ("phase_basis", "--phase-basis"),
                ("phase_schedule", "--phase-schedule"),
                ("phase_every", "--phase-every"),
                ("lr_pitch_um", "--lr-pitch-um"),
                ("lambda_slip", "--lambda-slip"),
                ("slip_axis_weights", "--slip-axis-weights"),
                ("pitch_range_um", "--pitch-range-um"),
                ("pitch_init_um", "--pitch-um"),
                ("embed_weight", "--embed-weight"),
                ("embed_batch", "--embed-batch"),
                ("w_sens", "--embed-w-sens"),
                ("w_orth", "--embed-w-orth"),
            ],
            "--out",
        )
    })?;
    let triplets = match (&a.embed_triplets, a.embed_weight > 0.0) {
        (Some(p), true) => {
            Some(Dataset::open(p).with_context(|| format!("--embed-triplets {}", p.display()))?)
        }
        (None, true) => bail!(
            "--embed-triplets: --embed-weight {} needs a variational triplet set (render one \
             with `nanoeye datagen render --set variational` on the training set's rig)",
            a.embed_weight
        ),
        (Some(_), false) => {
            bail!("--embed-weight: --embed-triplets given but the weight is 0; set μ > 0")
        }
        (None, false) => None,
    };
    if a.checkpoint_every == 0 {
        bail!("--checkpoint-every: must be at least 1");
    }
    // Before training: the network inputs are largest at the finest p̂ the run may reach.
    a.bn_batches
        .check_fits_from(a.batch, chain.native(), lo * 1e-6)
        .map_err(|e| anyhow::anyhow!("--bn-batches: {e}"))?;
    let val = match &a.val {
        Some(p) => Some(Dataset::open(p).with_context(|| format!("--val {}", p.display()))?),
        None => None,
    };
    let init = a.lens == "init";
    // Whatever the lens: a NaN given for a flag this lens does not use is still no value
    // (it exited 0; a helper's audit).
    crate::fisher::check_init_budget(
        a.fisher_iterations,
        a.fisher_photons,
        ["--fisher-iterations", "--fisher-photons"],
    )?;
    let spec = if init {
        LensSpec::Hyperbolic
    } else {
        a.lens
            .parse::<LensSpec>()
            .map_err(|e| anyhow::anyhow!("--lens: {e} (or init)"))?
    };
    util::check_not_dataset(&a.out)?;
    let ck = a.out.join("checkpoint.bin");
    // The lens a run started from is part of its parameters: a resume from another is refused.
    let lens_json = serde_json::to_string(&if init {
        serde_json::json!({"lens": "init", "fisher_iterations": a.fisher_iterations,
            "fisher_photons": a.fisher_photons})
    } else {
        serde_json::json!({"lens": a.lens})
    })?;
    // So is the embedding term's triplet set (absent without one: older runs' lens.json).
    let lens_json = match &a.embed_triplets {
        Some(p) => {
            let mut v: serde_json::Value = serde_json::from_str(&lens_json)?;
            let p = std::fs::canonicalize(p).unwrap_or_else(|_| p.clone());
            v["embed_triplets"] = serde_json::json!(p.display().to_string());
            serde_json::to_string(&v)?
        }
        None => lens_json,
    };
    let lens_path = a.out.join("lens.json");
    // The data and the chain's other settings, which no checkpoint holds: a resume with
    // others would mix two runs (docs/formats.md, "Resume records").
    let inputs_path = a.out.join("inputs.json");
    let mut inputs = a.chain.inputs(Some(a.val.as_deref()))?;
    // The triplet set by content too (lens.json names its path): re-rendered in place, it is
    // another set (an audit resumed over one).
    if let Some(p) = &a.embed_triplets {
        inputs["embed_triplets"] = serde_json::json!(util::dataset_digest("--embed-triplets", p)?);
    }
    // Rank 0 reads the checkpoint and sends it (empty: none), so --out need not be shared.
    let resume = if w.is_root() {
        util::check_output_target(&ck)?;
        // Temporary files of a killed run (a checkpoint cut off before its rename).
        util::remove_stale_temps_under(&a.out);
        if ck.exists() {
            let keys = [
                ("dataset", "--dataset"),
                ("val", "--val"),
                ("embed_triplets", "--embed-triplets"),
            ];
            util::check_inputs(
                &inputs_path,
                &inputs,
                &[&keys[..], &CAMERA_KEYS[..]].concat(),
                "--out",
            )?;
        }
        if ck.exists() && lens_path.exists() {
            let had = util::read_small_text(&lens_path, util::MAX_RECORD_BYTES)
                .context("--out (resume): lens.json")?;
            if had.trim() != lens_json {
                // Name the flag that differs: the embedding's triplet set, where all else
                // agrees, or the lens.
                let without = |t: &str| {
                    serde_json::from_str::<serde_json::Value>(t)
                        .ok()
                        .map(|mut v| {
                            if let Some(o) = v.as_object_mut() {
                                o.remove("embed_triplets");
                            }
                            v
                        })
                };
                let flag = if without(had.trim()) == without(&lens_json) {
                    "--embed-triplets"
                } else {
                    "--lens"
                };
                bail!(
                    "{flag}: {} was started from {}, not {lens_json}; use another --out",
                    a.out.display(),
                    had.trim()
                );
            }
        }
        if ck.exists() {
            let b =
                std::fs::read(&ck).with_context(|| format!("--out (resume): {}", ck.display()))?;
            // Empty bytes tell the other ranks "no checkpoint"; no save writes an empty file,
            // and one was overwritten by a fresh start.
            if b.is_empty() {
                bail!(
                    "--out (resume): '{}' is empty, not a training checkpoint; remove it to \
                     start afresh, or give another --out",
                    ck.display()
                );
            }
            b
        } else {
            Vec::new()
        }
    } else {
        Vec::new()
    };
    let resume = w.broadcast(resume);
    let r = &chain.config().radiometry;
    let mut phase0 = spec
        .phase_map(chain.aperture_grid(), r.wavelength_m, r.sensor_distance_m)
        .context("--lens")?
        .phase_rad;
    // A checkpoint holds φ itself; before the first one, `--lens init` starts from the Fisher
    // phase, computed by rank 0 (sent to the others) and written beside the checkpoint. It is
    // computed again rather than read back after a kill before the first checkpoint: nothing
    // there vouches for the flags it was computed with (an audit: a rerun with other
    // --fisher-iterations started from the old phase).
    let fisher_path = a.out.join("fisher_phase.npy");
    let mut fisher_new = None;
    if init && resume.is_empty() {
        let mut bytes = Vec::new();
        if w.is_root() {
            let phase = {
                eprintln!(
                    "Fisher initialization of the lens ({} iterations)",
                    a.fisher_iterations
                );
                let p = crate::fisher::chain_init_phase(
                    &chain,
                    a.chain.pitch_um(),
                    a.fisher_iterations,
                    a.fisher_photons,
                )?;
                fisher_new = Some(p.clone());
                p
            };
            bytes = (0..phase.ncols())
                .flat_map(|j| (0..phase.nrows()).map(move |i| (i, j)))
                .flat_map(|(i, j)| phase[(i, j)].to_le_bytes())
                .collect();
        }
        let bytes = w.broadcast(bytes);
        let n = phase0.nrows();
        if bytes.len() != n * n * 8 {
            bail!("--lens init: the Fisher phase is not {n}×{n}");
        }
        phase0 = faer::Mat::from_fn(n, n, |i, j| {
            let k = 8 * (j * n + i);
            f64::from_le_bytes(bytes[k..k + 8].try_into().unwrap_or([0; 8]))
        });
    }
    let mut t = Trainer::new(&chain, &ds, cfg, phase0).context("--lens / --pitch-um")?;
    if let Some(trip) = &triplets {
        t.set_embedding(trip)
            .map_err(|e| with_flag(e, &[("embed_batch", "--embed-batch")], "--embed-triplets"))?;
    }
    // The records beside the checkpoint go in it too: one copied from another run's --out
    // (whose records differ) is refused, not resumed here.
    let mut kept = inputs.clone();
    kept["lens"] = serde_json::from_str(&lens_json)?;
    t.set_inputs(kept);
    if !resume.is_empty() {
        t.load_bytes(resume, &ck).context("--out (resume)")?;
        if w.is_root() {
            eprintln!("resuming {} at step {}", a.out.display(), t.step);
        }
    }
    if w.is_root() {
        std::fs::create_dir_all(&a.out).with_context(|| format!("--out {}", a.out.display()))?;
        util::write_atomic(&lens_path, format!("{lens_json}\n").as_bytes())?;
        util::write_atomic(&inputs_path, format!("{inputs}\n").as_bytes())?;
        if let Some(p) = &fisher_new {
            util::write_atomic(&fisher_path, &crate::sim::npy_mat64(p)?)?;
        }
        // The native rig: with p̂ it gives the camera the tracker must use.
        util::write_atomic(
            &a.out.join("rig.json"),
            serde_json::to_string_pretty(&ds.manifest.rig)?.as_bytes(),
        )?;
    }
    let tty = w.is_root() && std::io::stderr().is_terminal();
    let bar = if tty {
        indicatif::ProgressBar::new(a.steps as u64)
    } else {
        indicatif::ProgressBar::hidden()
    };
    bar.set_position(t.step as u64);
    let tick = (a.steps / 10).max(1);
    let t_train = Instant::now();
    let step0 = t.step;
    while t.step < a.steps {
        let rec = t.train_step()?;
        bar.inc(1);
        bar.set_message(format!(
            "L_max {:.3} L_min {:.3}",
            rec.loss_max, rec.loss_min
        ));
        if w.is_root() && !tty && (rec.step + 1) % tick == 0 {
            let embed = rec
                .embed_loss
                .map_or(String::new(), |l| format!(", L_embed {l:.4}"));
            eprintln!(
                "step {}/{}: L_max {:.4}, L_min {:.4}{embed}, p̂ {:.3} µm, {:.0} s",
                rec.step + 1,
                a.steps,
                rec.loss_max,
                rec.loss_min,
                rec.pitch_um,
                t0.elapsed().as_secs_f64()
            );
        }
        if w.is_root() && (t.step % a.checkpoint_every == 0 || t.step == a.steps) {
            write_outputs(&mut t, &a.out)?;
        }
    }
    bar.finish_and_clear();
    let train_s = t_train.elapsed().as_secs_f64();
    let (step_gathers, step_gather_s) = split.gather_time();
    if w.is_root() {
        write_outputs(&mut t, &a.out)?;
    }
    // Every rank evaluates: the chain's PSF stacks are shared out among them.
    let v = val.as_ref().unwrap_or(&ds);
    // One chain pass of the BN set for both subnets' statistics.
    let bn = t.bn_inputs(a.bn_batches)?;
    let mut validate = |arch: &Arch| -> Result<nanoeye_search::Metrics> {
        t.net.recalibrate_bn(arch, &bn)?;
        Ok(t.validate(v, arch)?)
    };
    let m = validate(&Arch::min())?;
    let mmax = validate(&Arch::max())?;
    let out = serde_json::json!({
        "steps": t.step,
        "v_deg": m.v_deg,
        "median_deg": m.median_deg,
        "failures": m.failures,
        "dice": m.dice,
        "slip_mse": m.slip_mse,
        "max_subnet": {"v_deg": mmax.v_deg, "dice": mmax.dice, "slip_mse": mmax.slip_mse},
        "pitch_um": t.pitch_um,
        "bn_batches": a.bn_batches,
        "seconds": t0.elapsed().as_secs_f64(),
        // Wall time of the steps this invocation ran (checkpoints included), per step; 0 when
        // it ran none (a finished run's rerun printed 7.8e-7 s, a helper's audit).
        "seconds_per_step": util::per_step(train_s, t.step - step0),
    });
    // Every number (max_subnet's and median_deg too): a NaN would print as null.
    if let Some(k) = util::first_null(&out, &[]) {
        bail!("{k} is not finite: training diverged; lower the learning rates");
    }
    if !w.is_root() {
        return Ok(());
    }
    let mut out = out;
    if w.is_distributed() {
        // Rank 0's time in the PSF all-gathers of the steps (its wait for rank 1's share
        // included), then of the whole run.
        let (gathers, gather_s) = split.gather_time();
        out["mpi"] = serde_json::json!({
            "ranks": w.size(),
            "step_all_gathers": step_gathers,
            "step_all_gather_seconds": step_gather_s,
            "all_gathers": gathers,
            "all_gather_seconds": gather_s,
        });
    }
    util::write_atomic(
        &a.out.join("metrics.json"),
        serde_json::to_string_pretty(&out)?.as_bytes(),
    )?;
    if a.json {
        println!("{out}");
    } else {
        println!(
            "{} steps: V = {:.2}° (min subnet, {} failures), Dice {:.3}, slip MSE {:.3} mm², p̂ {:.3} µm; {}",
            t.step,
            m.v_deg,
            m.failures,
            m.dice,
            m.slip_mse,
            t.pitch_um,
            a.out.display()
        );
    }
    Ok(())
}

/// `nanoeye search rea` options.
#[derive(Debug, Args)]
pub struct ReaArgs {
    #[command(flatten)]
    chain: ChainArgs,
    /// Trained run directory (`search train --out`): its checkpoint gives the supernet, φ, p̂.
    #[arg(long)]
    run: PathBuf,
    /// Validation dataset (default: the training set).
    #[arg(long)]
    val: Option<PathBuf>,
    /// Evolution cycles N_iter.
    #[arg(long, default_value_t = 150)]
    cycles: usize,
    /// Population size P.
    #[arg(long, default_value_t = 100)]
    population: usize,
    /// Tournament size k.
    #[arg(long, default_value_t = 10)]
    tournament: usize,
    /// Inner-loop fine-tuning epochs.
    #[arg(long, default_value_t = 3.0)]
    epochs: f64,
    /// Budget penalty γ.
    #[arg(long, default_value_t = 10.0)]
    gamma: f64,
    /// Mutation rate per layer.
    #[arg(long, default_value_t = 0.1)]
    mutation_rate: f64,
    /// MAC budget (0: none).
    #[arg(long, default_value_t = 0)]
    budget_macs: u64,
    /// Seed.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Score each candidate as `nanoeye run` deploys it: BN statistics over every training
    /// frame and the calibration head's output layer solved on them (docs/run.md).
    #[arg(long)]
    head_refit: bool,
    /// What each candidate's BN statistics are computed over before its V, without
    /// `--head-refit`: `all`, every training frame once, or N training batches in training
    /// order (2 until 2026-12-02; a search begun then resumes with `--bn-batches 2`).
    #[arg(
        long,
        default_value = "all",
        conflicts_with = "head_refit",
        allow_negative_numbers = true
    )]
    bn_batches: nanoeye_search::BnBatches,
    /// Start each candidate's fine-tune at the smallest p̂ of the run's pitch range at which it
    /// fits --budget-macs, instead of the inherited p̂ (docs/run.md).
    #[arg(long)]
    fit_pitch: bool,
    /// Candidates evaluated at once, one thread and chain each (the result does not depend on
    /// it; under MPI each worker rank evaluates one instead).
    #[arg(long, default_value_t = 2)]
    parallel: usize,
    /// Print JSON.
    #[arg(long)]
    json: bool,
}

/// Runs `nanoeye search rea`.
pub fn rea(a: ReaArgs) -> Result<()> {
    use nanoeye_search::{Rea, ReaConfig, ReaState};
    let t0 = Instant::now();
    if !(1..=64).contains(&a.parallel) {
        bail!(
            "--parallel must be 1 to 64 candidates at once, got {}",
            a.parallel
        );
    }
    if a.fit_pitch && a.budget_macs == 0 {
        bail!(
            "--fit-pitch fits p̂ to --budget-macs, which is 0 (none): give a budget or drop the flag"
        );
    }
    crate::sim::check_trained_with(&a.run, &a.chain.camera, "--run")?;
    let (ds, chain) = a.chain.build(nanoeye_optics::PsfUsage::Training)?;
    // One process's --parallel chains, each with its PSF model, weighed before any output:
    // the first is built (and so in the memory left), the others are not yet.
    if !crate::dist::world().is_distributed() && a.parallel > 1 {
        crate::sim::check_psf_memory(
            chain.config(),
            &ds,
            nanoeye_optics::PsfUsage::Training,
            a.parallel - 1,
        )
        .context("--parallel")?;
    }
    if let Some(p) = a.chain.pitch_um {
        // The flag is shared with the commands that take p̂ from it; here it changes nothing,
        // so a resume does not compare it either.
        eprintln!(
            "note: --pitch-um {p} is not used by search rea: each candidate starts from the \
             p̂ in --run's checkpoint and fine-tunes it"
        );
    }
    if a.head_refit && ds.len() < 3 {
        bail!(
            "--head-refit needs at least 3 training frames in --dataset for its leave-one-out \
             error; the set has {}",
            ds.len()
        );
    }
    let val = match &a.val {
        Some(p) => Some(Dataset::open(p).with_context(|| format!("--val {}", p.display()))?),
        None => None,
    };
    let cfg = ReaConfig {
        cycles: a.cycles,
        population: a.population,
        tournament: a.tournament,
        epochs: a.epochs,
        gamma: a.gamma,
        mutation_rate: a.mutation_rate,
        budget_macs: a.budget_macs,
        seed: a.seed,
        head_refit: a.head_refit,
        fit_pitch: a.fit_pitch,
        recal_batches: a.bn_batches,
        ..ReaConfig::default()
    };
    cfg.validate().map_err(|e| {
        with_flag(
            e,
            &[
                ("population", "--population"),
                ("tournament", "--tournament"),
                ("cycles", "--cycles"),
                ("epochs", "--epochs"),
                ("gamma", "--gamma"),
                ("mutation_rate", "--mutation-rate"),
            ],
            "--run",
        )
    })?;
    let ck = a.run.join("checkpoint.bin");
    let v = val.as_ref().unwrap_or(&ds);
    let mut r =
        Rea::new(&chain, &ds, v, &ck, cfg).with_context(|| format!("--run {}", a.run.display()))?;
    // Before any fine-tune: the network inputs are largest at the finest p̂ a candidate may
    // reach.
    let tcfg = nanoeye_search::train::read_config(&ck)?;
    a.bn_batches
        .check_fits_from(tcfg.batch, chain.native(), tcfg.pitch_range_um[0] * 1e-6)
        .map_err(|e| anyhow::anyhow!("--bn-batches: {e}"))?;
    let w = crate::dist::world();
    if w.is_distributed() && !w.is_root() {
        // Ranks 1.. evaluate the candidates rank 0 sends them until it says stop.
        return rea_worker(&r.evaluator(), w);
    }
    let state_path = a.run.join("rea_state.json");
    util::check_output_target(&state_path)?;
    util::remove_stale_temps_under(&a.run);
    // What the candidates are trained and scored on besides the search's settings: the
    // trained run, the data and the chain. A resume with others would mix two searches.
    let inputs_path = a.run.join("rea_inputs.json");
    let mut inputs = a.chain.inputs(Some(a.val.as_deref()))?;
    let mut d = util::Digest::default();
    d.file(&ck)
        .with_context(|| format!("--run {}", a.run.display()))?;
    inputs["run_checkpoint"] = serde_json::json!(d.hex());
    if state_path.exists() {
        let keys = [
            (
                "run_checkpoint",
                "--run (its checkpoint.bin changed since the search began)",
            ),
            ("dataset", "--dataset"),
            ("val", "--val"),
        ];
        let keys = [&keys[..], &CAMERA_KEYS[..]].concat();
        util::check_inputs(&inputs_path, &inputs, &keys, "--run")?;
        // The state's own copy of the record: with rea_inputs.json deleted, a resume on
        // another --val scored its candidates on other data than the earlier ones (an audit).
        let text = util::read_record(&state_path, 1 << 30)
            .context("--run (resume)")?
            .unwrap_or_default();
        let had = serde_json::from_str::<serde_json::Value>(&text)
            .ok()
            .map(|s| s["inputs"].clone())
            .unwrap_or_default();
        if let Some((flag, key, old, new)) = util::value_difference(&had, &inputs, &keys) {
            bail!(
                "{flag}: differs from the search being resumed ({} records {key} = {old}, \
                 this command gives {new}); use the original value or search a copy of the run",
                state_path.display()
            );
        }
    }
    util::write_atomic(&inputs_path, format!("{inputs}\n").as_bytes())?;
    if state_path.exists() {
        r.resume(&state_path).context("--run (resume)")?;
        eprintln!(
            "resuming the search: {} evaluated, {} cycles done",
            r.state.evaluated.len(),
            r.state.history.len()
        );
    }
    let total = a.population + a.cycles;
    let tty = std::io::stderr().is_terminal();
    let bar = if tty {
        indicatif::ProgressBar::new(total as u64)
    } else {
        indicatif::ProgressBar::hidden()
    };
    let run_dir = a.run.clone();
    let mut save = |s: &ReaState| -> nanoeye_search::Result<()> {
        let io = |e: anyhow::Error| nanoeye_search::SearchError::Param {
            name: "run",
            reason: e.to_string(),
        };
        // With the inputs it was computed from: a resume compares them even where
        // rea_inputs.json is gone.
        let mut state = serde_json::to_value(s).map_err(|e| io(e.into()))?;
        state["inputs"] = inputs.clone();
        let text = serde_json::to_string(&state).map_err(|e| io(e.into()))?;
        util::write_atomic(&state_path, text.as_bytes()).map_err(io)?;
        let lines: String = s
            .history
            .iter()
            .map(|c| serde_json::to_string(c).unwrap_or_default() + "\n")
            .collect();
        util::write_atomic(&run_dir.join("rea.jsonl"), lines.as_bytes()).map_err(io)?;
        util::write_atomic(
            &run_dir.join("fitness.svg"),
            svg_fitness(&s.history).as_bytes(),
        )
        .map_err(io)?;
        bar.set_position((s.evaluated.len()) as u64);
        if !tty && s.evaluated.len().is_multiple_of((total / 10).max(1)) {
            eprintln!(
                "evaluated {}/{total}, {:.0} s",
                s.evaluated.len(),
                t0.elapsed().as_secs_f64()
            );
        }
        Ok(())
    };
    if w.is_distributed() {
        let mut pool = RankPool::new(w);
        let done = r.run_pool(&mut pool, &mut save);
        pool.stop();
        done?;
    } else {
        // A chain per thread: each keeps the last PSF stack it computed.
        let extra = (1..a.parallel)
            .map(|_| CameraChain::for_dataset(&ds, chain.config().clone()))
            .collect::<nanoeye_search::Result<Vec<_>>>()?;
        let chains: Vec<&CameraChain> = std::iter::once(&chain).chain(&extra).collect();
        r.run_threads(&chains, &mut save)?;
    }
    // Once more, whatever was done: a finished search resumed with rea.jsonl deleted or cut
    // reported the file and left it so (an audit); the same state writes the same bytes.
    save(&r.state)?;
    bar.finish_and_clear();
    let best = r.best().context("the search evaluated nothing")?;
    let out = serde_json::json!({
        "best": {"arch": best.arch, "macs": best.macs, "v_deg": best.v, "pitch_um": best.pitch_um,
                 "fitness": best.fitness, "id": best.id},
        "evaluated": r.state.evaluated.len(),
        "cycles": r.state.history.len(),
        // How each candidate's BN statistics were taken (null batches: every frame, with the
        // head refit).
        "head_refit": a.head_refit,
        "bn_batches": (!a.head_refit).then_some(a.bn_batches),
        "seconds": t0.elapsed().as_secs_f64(),
    });
    if a.json {
        println!("{out}");
    } else {
        println!(
            "best of {}: id {} with V = {:.2}°, {} MACs at p̂ {:.3} µm; history in {}",
            r.state.evaluated.len(),
            best.id,
            best.v,
            best.macs,
            best.pitch_um,
            a.run.join("rea.jsonl").display()
        );
    }
    Ok(())
}

/// The search's candidates evaluated by MPI ranks 1..N (rank 0 runs the evolution): one
/// candidate per rank at a time, results taken in the order they finish.
struct RankPool {
    w: crate::dist::World,
    idle: Vec<usize>,
    /// Candidate id each busy rank is evaluating.
    busy: std::collections::BTreeMap<usize, usize>,
}

impl RankPool {
    fn new(w: crate::dist::World) -> RankPool {
        RankPool {
            w,
            idle: (1..w.size()).rev().collect(),
            busy: Default::default(),
        }
    }
    /// Tells every worker rank to leave its loop.
    fn stop(&mut self) {
        for r in 1..self.w.size() {
            self.w.send(r, crate::dist::TAG_STOP, &[]);
        }
    }
}

fn pool_err(reason: String) -> nanoeye_search::SearchError {
    nanoeye_search::SearchError::Param {
        name: "pool",
        reason,
    }
}

impl nanoeye_search::EvalPool for RankPool {
    fn slots(&self) -> usize {
        self.w.size() - 1
    }
    fn submit(&mut self, id: usize, arch: &Arch) -> nanoeye_search::Result<()> {
        let r = self
            .idle
            .pop()
            .ok_or_else(|| pool_err("every worker rank is busy".into()))?;
        let task = serde_json::to_vec(&serde_json::json!({"id": id, "arch": arch}))
            .map_err(|e| pool_err(e.to_string()))?;
        self.w.send(r, crate::dist::TAG_TASK, &task);
        self.busy.insert(r, id);
        Ok(())
    }
    fn next(&mut self) -> nanoeye_search::Result<nanoeye_search::Individual> {
        let (r, _, bytes) = self.w.receive_any();
        let id = self.busy.remove(&r).ok_or_else(|| {
            pool_err(format!("rank {r} answered without a candidate to evaluate"))
        })?;
        self.idle.push(r);
        let reply: std::result::Result<nanoeye_search::Individual, String> =
            serde_json::from_slice(&bytes).map_err(|e| pool_err(format!("rank {r}: {e}")))?;
        reply.map_err(|e| pool_err(format!("rank {r} evaluating candidate {id}: {e}")))
    }
}

/// A worker rank's loop: evaluate each candidate rank 0 sends, reply with the individual (or
/// the error), until told to stop.
fn rea_worker(eval: &nanoeye_search::Evaluator, w: crate::dist::World) -> Result<()> {
    #[derive(serde::Deserialize)]
    struct Task {
        id: usize,
        arch: Arch,
    }
    loop {
        let (from, tag, bytes) = w.receive_any();
        if tag == crate::dist::TAG_STOP {
            return Ok(());
        }
        if from != 0 || tag != crate::dist::TAG_TASK {
            bail!("unexpected message (tag {tag}) from rank {from}");
        }
        let task: Task = serde_json::from_slice(&bytes).context("a task from rank 0")?;
        let reply: std::result::Result<nanoeye_search::Individual, String> = eval
            .evaluate(task.id, &task.arch)
            .map_err(|e| e.to_string());
        w.send(0, crate::dist::TAG_RESULT, &serde_json::to_vec(&reply)?);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nanoeye_search::CycleRecord;
    use nanoeye_search::rea::ChildRecord;

    fn cycle(c: usize, v: f64, over: bool) -> CycleRecord {
        CycleRecord {
            cycle: c,
            population: vec![],
            tournament: vec![],
            parent: 0,
            child: ChildRecord {
                id: c,
                arch: Arch::min(),
                macs: 0,
                fitness: -v - if over { 10.0 } else { 0.0 },
                v,
                pitch_um: 14.0,
            },
            removed: 0,
        }
    }

    #[test]
    fn the_loss_plot_shows_the_embedding_term_on_its_own_scale_only_where_there_is_one() {
        let rec = |i: usize, e: Option<f64>| StepRecord {
            step: i,
            loss_max: 2.0 - 0.1 * i as f64,
            loss_min: 3.0 - 0.1 * i as f64,
            loss_total: 5.0,
            pitch_um: 14.0,
            phase_step_rad: 0.01,
            embed_loss: e,
        };
        let plain: Vec<_> = (0..4).map(|i| rec(i, None)).collect();
        assert!(!svg_curves(&plain).contains("L_embed"));
        assert_eq!(svg_curves(&plain).matches("<polyline").count(), 2);
        let joint: Vec<_> = (0..4)
            .map(|i| rec(i, Some(-16.0 - 0.05 * i as f64)))
            .collect();
        let svg = svg_curves(&joint);
        assert!(svg.contains("L_embed (-16.150 … -16.000)"), "{svg}");
        assert_eq!(svg.matches("<polyline").count(), 3);
        // Its highest value at the top of the axes (y = M = 40), its lowest at the bottom.
        assert!(svg.contains("40.0,40.0 "), "{svg}");
        assert!(svg.contains(",320.0\"/>"), "{svg}");
    }

    #[test]
    fn the_fitness_plot_marks_penalized_children_and_keeps_the_best_so_far() {
        let h = [
            cycle(0, 20.0, false),
            cycle(1, 5.0, true),
            cycle(2, 12.0, false),
        ];
        let s = svg_fitness(&h);
        // Three children's V, one penalty mark (the over-budget child's V + γ).
        assert_eq!(s.matches("fill=\"#2471a3\"/>").count(), 3);
        assert_eq!(s.matches("stroke=\"#c0392b\"/>").count(), 1);
        // Best penalized error so far: 20, 15, 12 on a 0 … 20 axis (y = 40 + 280·(1 − v/20)).
        assert!(
            s.contains("points=\"40.0,40.0 320.0,110.0 600.0,152.0\""),
            "{s}"
        );
    }
}

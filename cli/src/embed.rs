//! `nanoeye search embed`: the lens optimised for the optical embedding (S15, C.2) on a
//! dataset of variational triplets — the slippage and the gaze made visible and told apart
//! in the sensor image — resumable, with its history and the bounds before and after.

use crate::sim::{CAMERA_KEYS, ChainArgs};
use crate::util;
use anyhow::{Context, Result, bail};
use clap::Args;
use nanoeye_search::{EmbedConfig, EmbedWeights, Embedder, LensSpec};
use std::io::IsTerminal;
use std::path::PathBuf;
use std::time::Instant;

/// `nanoeye search embed` options.
#[derive(Debug, Args)]
pub struct EmbedArgs {
    #[command(flatten)]
    chain: ChainArgs,
    /// Initial lens: hyperbolic, double-helix, flat or file:PHASE.npy (e.g. a run's
    /// fisher_phase.npy).
    #[arg(long, default_value = "hyperbolic")]
    lens: String,
    /// Adam steps of the phase map.
    #[arg(long, default_value_t = 40)]
    steps: usize,
    /// Triplets per step.
    #[arg(long, default_value_t = 4)]
    batch: usize,
    /// Learning rate of the phase map (rad per step, Adam).
    #[arg(long, default_value_t = 2e-2)]
    lr_phase_rad: f64,
    /// Weight of the sensitivity term L_sens.
    #[arg(long, default_value_t = 1.0)]
    w_sens: f64,
    /// Weight of the orthogonality term L_orth = cos²φ.
    #[arg(long, default_value_t = 1.0)]
    w_orth: f64,
    /// Seed of the triplets' order.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Steps between checkpoints.
    #[arg(long, default_value_t = 10)]
    checkpoint_every: usize,
    /// Triplets imaged at once when the objective is evaluated over the whole dataset.
    #[arg(long, default_value_t = 8)]
    eval_chunk: usize,
    /// Run directory (checkpoint.bin, phase.npy, history.jsonl, embed.svg, metrics.json).
    #[arg(long)]
    out: PathBuf,
    /// Print JSON.
    #[arg(long)]
    json: bool,
}

/// The files a run writes into `--out`.
const OUTPUTS: [&str; 8] = [
    "checkpoint.bin",
    "phase.npy",
    "history.jsonl",
    "embed.svg",
    "lens.json",
    "inputs.json",
    "init.json",
    "metrics.json",
];

/// Runs (or resumes) the embedding optimisation.
pub fn embed(a: EmbedArgs) -> Result<()> {
    let t0 = Instant::now();
    let (ds, chain) = a.chain.build(nanoeye_optics::PsfUsage::Training)?;
    let cfg = EmbedConfig {
        steps: a.steps,
        batch: a.batch,
        lr_rad: a.lr_phase_rad,
        pitch_um: a.chain.pitch_um(),
        seed: a.seed,
        weights: EmbedWeights {
            w_sens: a.w_sens,
            w_orth: a.w_orth,
            ..EmbedWeights::default()
        },
    };
    let flag = |e: nanoeye_search::SearchError| {
        let f = match &e {
            nanoeye_search::SearchError::Param { name, .. } => match *name {
                "steps" => "--steps",
                "batch" => "--batch",
                "lr_rad" => "--lr-phase-rad",
                "pitch_um" => "--pitch-um",
                "w_sens" => "--w-sens",
                "w_orth" => "--w-orth",
                "dataset" => "--dataset",
                "phase" => "--lens",
                _ => "--out",
            },
            _ => "--dataset",
        };
        anyhow::anyhow!("{f}: {e}")
    };
    cfg.validate().map_err(flag)?;
    if a.checkpoint_every == 0 {
        bail!("--checkpoint-every: must be at least 1");
    }
    if a.eval_chunk == 0 || a.eval_chunk > 4096 {
        bail!("--eval-chunk: must lie in 1..=4096, got {}", a.eval_chunk);
    }
    let spec = a
        .lens
        .parse::<LensSpec>()
        .map_err(|e| anyhow::anyhow!("--lens: {e}"))?;
    let r = &chain.config().radiometry;
    let phase0 = spec
        .phase_map(chain.aperture_grid(), r.wavelength_m, r.sensor_distance_m)
        .context("--lens")?
        .phase_rad;
    // p̂ against the native grid and the sensor before anything is written: a p̂ finer than
    // the grid was refused by the embedder, after --out held lens.json and inputs.json,
    // naming a `pitch` parameter or a rig field instead of the flag (a helper's audit).
    chain
        .native()
        .at(a.chain.pitch_um() * 1e-6)
        .context("--pitch-um")?;
    let mut e = Embedder::new(&chain, &ds, cfg, phase0).map_err(flag)?;
    if a.out.exists() && !a.out.is_dir() {
        bail!("--out {}: exists and is not a directory", a.out.display());
    }
    util::check_not_dataset(&a.out)?;
    // Every output's target before the steps, not only the checkpoint's (a directory at
    // OUT/phase.npy was found after the training), and none of them the starting lens (`--lens
    // file:OUT/phase.npy` was replaced by the run's own phase map).
    for name in OUTPUTS {
        util::check_output_target(&a.out.join(name)).with_context(|| format!("--out {name}"))?;
        if let LensSpec::File(f) = &spec
            && util::same_file(&a.out.join(name), f)
        {
            bail!(
                "--out: its {name} is --lens {}; give another --out (or copy the lens \
                 out of it first)",
                f.display()
            );
        }
    }
    let ck = a.out.join("checkpoint.bin");
    util::remove_stale_temps_under(&a.out);
    let lens_path = a.out.join("lens.json");
    let lens_json = serde_json::json!({ "lens": a.lens }).to_string();
    // The data and the chain's other settings, which the checkpoint does not hold.
    let inputs_path = a.out.join("inputs.json");
    let inputs = a.chain.inputs(None)?;
    if ck.exists() {
        util::check_inputs(
            &inputs_path,
            &inputs,
            &[&[("dataset", "--dataset")][..], &CAMERA_KEYS[..]].concat(),
            "--out",
        )?;
        // The starting lens is part of the run's parameters: a resume from another is refused.
        let had = util::read_small_text(&lens_path, util::MAX_RECORD_BYTES)
            .context("--out (resume): lens.json")?;
        if had.trim() != lens_json {
            bail!(
                "--lens: {} was started from {}, not {lens_json}; use another --out",
                a.out.display(),
                had.trim()
            );
        }
    } else {
        std::fs::create_dir_all(&a.out).with_context(|| format!("--out {}", a.out.display()))?;
        util::write_atomic(&lens_path, lens_json.as_bytes())?;
    }
    util::write_atomic(&inputs_path, format!("{inputs}\n").as_bytes())?;
    // The bounds of the starting lens over every triplet (kept from the first invocation;
    // `e` is still at the starting lens until the checkpoint is loaded below). Read back only
    // beside a checkpoint, whose lens and inputs were compared above: before the first one
    // nothing vouches for it (an audit: a rerun with another --lens reported the old bounds).
    let init_path = a.out.join("init.json");
    let kept = if ck.exists() {
        util::read_record(&init_path, util::MAX_RECORD_BYTES).context("--out (resume)")?
    } else {
        None
    };
    let init = match kept {
        Some(t) => serde_json::from_str(&t).context("--out (resume): init.json")?,
        None => {
            let ev = e.evaluate(a.eval_chunk)?;
            util::write_atomic(&init_path, serde_json::to_string_pretty(&ev)?.as_bytes())?;
            ev
        }
    };
    // The records beside the checkpoint go in it too: one copied from another run's --out
    // (whose records differ) is refused, not resumed here.
    let mut kept = inputs.clone();
    kept["lens"] = serde_json::from_str(&lens_json)?;
    e.set_inputs(kept);
    if ck.exists() {
        e.load(&ck)
            .map_err(|e| anyhow::anyhow!("--out (resume): {e}"))?;
        eprintln!("resuming {} at step {}", a.out.display(), e.step());
    }
    let tty = std::io::stderr().is_terminal();
    let bar = if tty {
        indicatif::ProgressBar::new(a.steps as u64)
    } else {
        indicatif::ProgressBar::hidden()
    };
    bar.set_position(e.step() as u64);
    let t_steps = Instant::now();
    let step0 = e.step();
    while e.step() < a.steps {
        let rec = e.train_step()?;
        if !rec.loss.is_finite() {
            bail!(
                "the objective is not finite at step {}: lower --lr-phase-rad",
                rec.step
            );
        }
        bar.inc(1);
        bar.set_message(format!("L {:.4}, cos² {:.3}", rec.loss, rec.l_orth));
        if !tty && (rec.step + 1) % 10 == 0 {
            eprintln!(
                "step {}/{}: L {:.4} (L_sens {:.4}, cos² {:.3}), {:.0} s",
                rec.step + 1,
                a.steps,
                rec.loss,
                rec.l_sens,
                rec.l_orth,
                t0.elapsed().as_secs_f64()
            );
        }
        if e.step() % a.checkpoint_every == 0 || e.step() == a.steps {
            write_outputs(&e, &a.out)?;
        }
    }
    bar.finish_and_clear();
    let step_s = t_steps.elapsed().as_secs_f64();
    write_outputs(&e, &a.out)?;
    let fin = e.evaluate(a.eval_chunk)?;
    let out = serde_json::json!({
        "steps": e.step(),
        "triplets": fin.triplets,
        "pitch_um": a.chain.pitch_um(),
        "init": init,
        "final": fin,
        "seconds": t0.elapsed().as_secs_f64(),
        "seconds_per_step": crate::util::per_step(step_s, e.step() - step0),
    });
    for k in ["loss", "crlb_slip_um", "crlb_gaze_deg"] {
        if !out["final"][k].as_f64().is_some_and(f64::is_finite) {
            bail!("{k} is not finite: the run diverged; lower --lr-phase-rad");
        }
    }
    util::write_atomic(
        &a.out.join("metrics.json"),
        serde_json::to_string_pretty(&out)?.as_bytes(),
    )?;
    if a.json {
        println!("{out}");
    } else {
        println!(
            "{} steps over {} triplets: L {:.4} → {:.4}; slippage bound {:.2} → {:.2} µm, gaze \
             bound {:.4} → {:.4}°; {}",
            e.step(),
            fin.triplets,
            out["init"]["loss"].as_f64().unwrap_or(f64::NAN),
            fin.loss,
            out["init"]["crlb_slip_um"].as_f64().unwrap_or(f64::NAN),
            fin.crlb_slip_um,
            out["init"]["crlb_gaze_deg"].as_f64().unwrap_or(f64::NAN),
            fin.crlb_gaze_deg,
            a.out.join("phase.npy").display()
        );
    }
    Ok(())
}

/// The checkpoint, phase.npy, history.jsonl and embed.svg of the steps so far.
fn write_outputs(e: &Embedder, out: &std::path::Path) -> Result<()> {
    e.save(&out.join("checkpoint.bin"))?;
    util::write_atomic(&out.join("phase.npy"), &crate::sim::npy_mat64(e.phase())?)?;
    let mut h = String::new();
    for r in e.history() {
        h.push_str(&serde_json::to_string(r)?);
        h.push('\n');
    }
    util::write_atomic(&out.join("history.jsonl"), h.as_bytes())?;
    util::write_atomic(&out.join("embed.svg"), svg_history(e.history()).as_bytes())?;
    Ok(())
}

/// The objective's two terms per step (L_sens shifted to start at its minimum), as an SVG.
fn svg_history(h: &[nanoeye_search::EmbedRecord]) -> String {
    let lo = h.iter().map(|r| r.l_sens).fold(f64::INFINITY, f64::min);
    let p = crate::train::Plot {
        n: h.len().max(2) as f64,
        ymax: h
            .iter()
            .flat_map(|r| [r.l_sens - lo, r.l_orth])
            .fold(1e-9f64, f64::max),
    };
    let body = format!(
        r##"<polyline fill="none" stroke="#2471a3" stroke-width="1.5" points="{}"/>
<polyline fill="none" stroke="#c0392b" stroke-width="1.5" points="{}"/>"##,
        p.polyline(h.iter().map(|r| r.l_sens - lo)),
        p.polyline(h.iter().map(|r| r.l_orth)),
    );
    p.svg(
        "step",
        "batch objective",
        &body,
        &[("L_sens − its minimum", "#2471a3"), ("cos²φ", "#c0392b")],
    )
}

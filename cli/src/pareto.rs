//! `nanoeye search pareto`: subnets of trained runs scored on the ambiguity set, one
//! (MACs, V) point each, the Pareto front per lens (B.6, Fig. 8), resumable.

use crate::util;
use anyhow::{Context, Result, bail};
use clap::Args;
use nanoeye_datagen::render::Dataset;
use nanoeye_nets::Arch;
use nanoeye_search::BnBatches;
use nanoeye_search::pareto::{
    Interval, LensFrames, Point, average_runs, bootstrap, dominates, front, seed_differences,
    seed_interval,
};
use nanoeye_search::train::ALL_FRAMES_BYTES;
use nanoeye_search::{ChainedSet, Trainer, evaluate_chained};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// `nanoeye search pareto` options.
#[derive(Debug, Args)]
pub struct ParetoArgs {
    /// Trained run directories, comma separated, one lens each; `+` joins runs of one lens
    /// trained with other seeds (`A0+A1,B0+B1`), whose per-frame errors are averaged subnet
    /// by subnet (list each lens's seeds in the same order: they are paired by position).
    #[arg(long)]
    runs: String,
    /// Evaluation dataset (the ambiguity set, C.3).
    #[arg(long)]
    dataset: PathBuf,
    /// Dataset for BN recalibration (default: the evaluation dataset).
    #[arg(long)]
    train: Option<PathBuf>,
    /// The chain settings the runs were trained with.
    #[command(flatten)]
    camera: crate::sim::CameraArgs,
    /// Subnets per lens: the run's REA selections by fitness (the first run's, shared by all
    /// lenses), topped up with uniform draws (resolution scale U[0.3, 1]).
    #[arg(long, default_value_t = 100)]
    subnets: usize,
    /// Seed of the uniform draws.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Score each subnet as `nanoeye run` deploys it: BN statistics over every frame of the
    /// BN set (`--train`, default the evaluation set) and the calibration head's output layer
    /// solved on them (docs/run.md); without it, BN from `--bn-batches` and the trained head.
    #[arg(long)]
    head_refit: bool,
    /// What each subnet's BN statistics are computed over, without `--head-refit`: `all`,
    /// every frame of the BN set (in its order, in batches of the run's training batch size),
    /// or N batches of it in the run's training order (2 was the fixed count before the flag).
    #[arg(
        long,
        default_value = "all",
        conflicts_with = "head_refit",
        allow_negative_numbers = true
    )]
    bn_batches: BnBatches,
    /// Plot file (SVG).
    #[arg(long, default_value = "pareto.svg")]
    plot: PathBuf,
    /// State file: the points scored so far and what they were scored from, written after
    /// every subnet; a rerun with the same inputs continues from it, one with other inputs is
    /// refused (default: the plot's path with the extension `state.json`).
    #[arg(long)]
    state: Option<PathBuf>,
    /// States of earlier `search pareto` runs (repeatable) whose complete runs are taken as
    /// scored instead of scoring them again: a run with the same checkpoint (size and digest),
    /// scored on the same evaluation and BN sets, chain, subnets and BN setting; a state
    /// scored from other inputs is refused, naming them.
    #[arg(long)]
    reuse: Vec<PathBuf>,
    /// Resamples of the paired bootstrap over the evaluation set (each lens's median V and the
    /// fronts' dominance recomputed on its items drawn with replacement, an item's frames
    /// together, seed 0); 0: none.
    #[arg(long, default_value_t = 1000)]
    bootstrap: usize,
    /// Print JSON.
    #[arg(long)]
    json: bool,
}

/// Where a run's subnets take their BN statistics from, computed once per run.
enum Bn {
    /// Every frame of the BN set, with the head refit (`--head-refit`).
    Refit(nanoeye_search::headfit::FitFrames),
    /// The network inputs of `--bn-batches` training batches.
    Batches(Vec<nanoeye_nets::Tensor>),
}

/// The scatter with each lens's front; each legend line names the lens and, with a bootstrap,
/// its median V and 90 % interval.
fn pareto_svg(lenses: &[(String, Vec<Point>)], medians: Option<&[Interval]>) -> String {
    let (w, ht, m) = (720.0, 420.0, 50.0);
    let all: Vec<_> = lenses.iter().flat_map(|(_, p)| p.iter()).collect();
    let xmax = all.iter().map(|p| p.macs as f64).fold(1.0, f64::max) * 1.05;
    let ymax = all.iter().map(|p| p.v_deg).fold(1e-9, f64::max) * 1.05;
    let xy = |p: &Point| {
        (
            m + (w - 2.0 * m) * p.macs as f64 / xmax,
            ht - m - (ht - 2.0 * m) * p.v_deg / ymax,
        )
    };
    let colors = ["#c0392b", "#2471a3", "#229954", "#7d3c98", "#b9770e"];
    let mut s = format!(
        r##"<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{ht}" font-family="sans-serif" font-size="12">
<rect width="100%" height="100%" fill="white"/>
<line x1="{m}" y1="{b}" x2="{r}" y2="{b}" stroke="black"/><line x1="{m}" y1="{m}" x2="{m}" y2="{b}" stroke="black"/>
<text x="{cx}" y="{tb}" text-anchor="middle">MACs (0 … {xmax:.3e})</text>
<text x="14" y="{cy}" transform="rotate(-90 14 {cy})" text-anchor="middle">gaze error V, degrees (0 … {ymax:.1})</text>
"##,
        b = ht - m,
        r = w - m,
        cx = w / 2.0,
        tb = ht - 10.0,
        cy = ht / 2.0
    );
    for (k, (name, pts)) in lenses.iter().enumerate() {
        let c = colors[k % colors.len()];
        let label = match medians.and_then(|m| m.get(k)) {
            Some(m) => format!(
                "{name}: median V {:.1}° [{:.1}, {:.1}]",
                m.value, m.lo, m.hi
            ),
            None => name.clone(),
        };
        for p in pts {
            let (x, y) = xy(p);
            s += &format!(
                "<circle cx=\"{x:.1}\" cy=\"{y:.1}\" r=\"2.5\" fill=\"{c}\" fill-opacity=\"0.5\"/>\n"
            );
        }
        let f: Vec<String> = front(pts)
            .iter()
            .map(|p| {
                let (x, y) = xy(p);
                format!("{x:.1},{y:.1}")
            })
            .collect();
        s += &format!(
            "<polyline fill=\"none\" stroke=\"{c}\" stroke-width=\"2\" points=\"{}\"/>\n<text x=\"{}\" y=\"{}\" fill=\"{c}\">{}</text>\n",
            f.join(" "),
            w - m - 330.0,
            m + 16.0 * k as f64,
            crate::report::esc(&label)
        );
    }
    s + "</svg>\n"
}

/// Runs `nanoeye search pareto`.
pub fn pareto(a: ParetoArgs) -> Result<()> {
    use rand::SeedableRng;
    let t0 = Instant::now();
    let groups: Vec<Vec<PathBuf>> = a
        .runs
        .split(',')
        .map(|g| g.split('+').map(|s| PathBuf::from(s.trim())).collect())
        .collect();
    if groups.iter().flatten().any(|r| r.as_os_str().is_empty()) {
        bail!(
            "--runs: give run directories separated by commas, one lens each (`+` joins runs of \
             one lens trained with other seeds), got {:?}",
            a.runs
        );
    }
    // Every run is scored on its own (the state holds them in this order); a lens's runs are
    // averaged afterwards.
    let runs: Vec<PathBuf> = groups.iter().flatten().cloned().collect();
    // One run twice compares a lens with itself, or averages one seed as two.
    for (i, r) in runs.iter().enumerate() {
        if let Some(s) = runs[..i].iter().find(|s| util::same_file(s, r)) {
            bail!(
                "--runs: '{}' and '{}' are the same run; give each run once",
                s.display(),
                r.display()
            );
        }
    }
    if a.subnets == 0 || a.subnets > 100_000 {
        bail!("--subnets: must be 1..=100000, got {}", a.subnets);
    }
    if a.bootstrap > 1_000_000 {
        bail!(
            "--bootstrap: at most 1000000 resamples, got {} (0 turns it off)",
            a.bootstrap
        );
    }
    // Both outputs checked before minutes of scoring, not after; the plot's own target
    // first (`--plot .` was refused as "--state: . is also --plot", the default state path
    // of a plot with no file name).
    util::check_output_target(&a.plot).context("--plot")?;
    let state_path = a
        .state
        .clone()
        .unwrap_or_else(|| a.plot.with_extension("state.json"));
    if state_path == a.plot {
        bail!(
            "--state: {} is also --plot; give the state its own path",
            state_path.display()
        );
    }
    util::check_output_target(&state_path).context("--state")?;
    // Not into an input's tree either (the plot replaced a run's own loss.svg, exit 0).
    let inputs = runs
        .iter()
        .map(|r| ("--runs", r))
        .chain([("--dataset", &a.dataset)])
        .chain(a.train.iter().map(|t| ("--train", t)));
    for (flag, dir) in inputs {
        for (out, path) in [("--plot", &a.plot), ("--state", &state_path)] {
            if util::is_inside(path, dir) {
                bail!(
                    "{out}: '{}' lies inside {flag} '{}'; write it elsewhere",
                    path.display(),
                    dir.display()
                );
            }
        }
    }
    // The plot replaces its path whole: an existing file there must be an earlier plot, not
    // an input (the plot replaced a run's checkpoint.bin and a dataset's dataset.json, exit 0).
    if let Ok(mut f) = std::fs::File::open(&a.plot) {
        use std::io::Read;
        let mut head = [0u8; 5];
        let n = f.read(&mut head).unwrap_or(0);
        if n > 0 && !(head[..n].starts_with(b"<svg") || head[..n].starts_with(b"<?xml")) {
            bail!(
                "--plot: '{}' exists and is not an SVG plot; give another path",
                a.plot.display()
            );
        }
    }
    let ds =
        Dataset::open(&a.dataset).with_context(|| format!("--dataset {}", a.dataset.display()))?;
    let train = match &a.train {
        Some(p) => Dataset::open(p).with_context(|| format!("--train {}", p.display()))?,
        None => ds.clone(),
    };
    if a.head_refit && train.len() < 3 {
        bail!(
            "--head-refit needs at least 3 frames in the BN set (--train, default --dataset) \
             for its leave-one-out error; the set has {}",
            train.len()
        );
    }
    for run in &runs {
        crate::sim::check_trained_with(run, &a.camera, "--runs")?;
    }
    let chain = a.camera.chain(&ds, nanoeye_optics::PsfUsage::Training)?;
    let tchain = a.camera.chain(&train, nanoeye_optics::PsfUsage::Training)?;
    // Subnets: REA selections of the first run by fitness, then uniform draws.
    // A run without a search has no state; a state that does not parse is refused, not
    // silently replaced by uniform draws.
    let rea_path = runs[0].join("rea_state.json");
    // A regular file of bounded size (a FIFO blocked, /dev/zero was read without end).
    let mut archs: Vec<Arch> = match util::read_record(&rea_path, util::MAX_RECORD_BYTES)
        .with_context(|| format!("--runs: {}", rea_path.display()))?
    {
        Some(t) => {
            let st: nanoeye_search::ReaState = serde_json::from_str(&t)
                .with_context(|| format!("--runs: {} is not a search state", rea_path.display()))?;
            let mut e = st.evaluated;
            e.sort_by(|x, y| y.fitness.total_cmp(&x.fitness));
            e.into_iter().map(|i| i.arch).collect()
        }
        None => Vec::new(),
    };
    archs.truncate(a.subnets);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(a.seed);
    while archs.len() < a.subnets {
        archs.push(Arch::sample(&mut rng));
    }
    let key = Key::new(&a, &runs, &archs)?;
    let mut state = match std::fs::read(&state_path) {
        Ok(bytes) => State::resume(&bytes, key, &state_path, ds.len())?,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => State {
            key,
            lenses: Vec::new(),
            frame_errors: Vec::new(),
        },
        Err(e) => return Err(e).with_context(|| format!("--state {}", state_path.display())),
    };
    let reused = reusable(&a.reuse, &state.key)?;
    for (r, run) in runs.iter().enumerate() {
        if state.lenses.get(r).is_some_and(|p| p.len() == archs.len()) {
            continue;
        }
        let (_, bytes, digest) = &state.key.runs[r];
        if let Some((points, errors, from)) = reused.get(&(*bytes, digest.clone())) {
            state.lenses.truncate(r);
            state.frame_errors.truncate(r);
            state.lenses.push(points.clone());
            state.frame_errors.push(errors.clone());
            util::write_atomic(&state_path, &serde_json::to_vec(&state)?)
                .with_context(|| format!("--state {}", state_path.display()))?;
            eprintln!(
                "{}: {} subnets taken from --reuse {}",
                run.display(),
                points.len(),
                from.display()
            );
            continue;
        }
        if state.lenses.len() == r {
            state.lenses.push(Vec::with_capacity(archs.len()));
            state.frame_errors.push(Vec::with_capacity(archs.len()));
        }
        let ck = run.join("checkpoint.bin");
        let tcfg = nanoeye_search::train::read_config(&ck)
            .with_context(|| format!("--runs {}", run.display()))?;
        let mut tr = Trainer::from_checkpoint(&tchain, &train, &ck).with_context(|| {
            format!(
                "--runs {}: read with this chain (--aperture-step-um, --exposure-ms and \
                 --base-pitch-um must be those the run was trained with)",
                run.display()
            )
        })?;
        let map = tr.phase_map()?;
        let p_hat = tr.pitch_um * 1e-6;
        let (h, w) = chain.native().at(p_hat)?.shape();
        // The BN set through this lens once, for every subnet's statistics (and head fit):
        // the same images in every subnet's recalibration, so computed once per run.
        let bn = if a.head_refit {
            Bn::Refit(tr.all_frames()?)
        } else if let BnBatches::Count(n) = a.bn_batches {
            a.bn_batches
                .check_fits_from(tcfg.batch, tchain.native(), p_hat)
                .map_err(|e| anyhow::anyhow!("--bn-batches, through {}: {e}", run.display()))?;
            Bn::Batches(tr.recalibration_inputs(n)?)
        } else {
            let all = tr.all_frames()?.inputs;
            let n: usize = all.iter().map(|t| t.n).sum();
            if n < train.len() {
                eprintln!(
                    "{}: BN over the first {n} of the BN set's {} frames (the {} MiB of network \
                     inputs kept)",
                    run.display(),
                    train.len(),
                    ALL_FRAMES_BYTES >> 20
                );
            }
            Bn::Batches(all)
        };
        // The evaluation set through this lens once when it fits the same budget (the same
        // images and noise for every subnet, bit for bit); else through the chain per subnet.
        let kept = (ChainedSet::bytes_for(ds.len(), h, w) <= ALL_FRAMES_BYTES)
            .then(|| ChainedSet::new(&chain, &ds, &map, p_hat, tcfg.batch, tcfg.seed))
            .transpose()?;
        let solves = [(
            nanoeye_search::SolverInput::Predicted,
            tcfg.solver,
            tcfg.pupil_centre,
        )];
        // Each subnet's score depends on the run and the subnet only (BN statistics and the
        // head are recomputed from scratch), so a resumed run gives the same points.
        for k in state.lenses[r].len()..archs.len() {
            let arch = &archs[k];
            match &bn {
                Bn::Refit(all) => {
                    nanoeye_search::headfit::recalibrate_and_refit(&mut tr.net, arch, all)?;
                }
                Bn::Batches(inputs) => tr.net.recalibrate_bn(arch, inputs)?,
            }
            let mut e = match &kept {
                Some(set) => evaluate_chained(&mut tr.net, arch, set, &solves)?,
                None => {
                    let setup = nanoeye_search::EvalSetup {
                        chain: &chain,
                        data: &ds,
                        map: &map,
                        p_hat_m: p_hat,
                        arch,
                        batch: tcfg.batch,
                        seed: tcfg.seed,
                    };
                    nanoeye_search::evaluate_frames_multi(&mut tr.net, &setup, &solves)?
                }
            };
            let e = e.remove(0);
            let errs = e.scored_errors_deg();
            if errs.is_empty() {
                bail!("--dataset {}: no frames to score", a.dataset.display());
            }
            // V as `evaluate_net` sums it, so the points are those scored before the
            // per-frame errors were kept.
            let v_deg = errs.iter().sum::<f64>() / errs.len() as f64;
            let macs = nanoeye_nets::cost::subnet_cost(&tcfg.supernet, arch, h, w)?.macs;
            state.lenses[r].push(Point { macs, v_deg });
            state.frame_errors[r].push(errs);
            util::write_atomic(&state_path, &serde_json::to_vec(&state)?)
                .with_context(|| format!("--state {}", state_path.display()))?;
            if (k + 1) % (archs.len() / 5).max(1) == 0 {
                eprintln!("{}: {}/{} subnets", run.display(), k + 1, archs.len());
            }
        }
    }
    let per_run: Vec<LensFrames> = state
        .lenses
        .iter()
        .zip(&state.frame_errors)
        .map(|(p, e)| LensFrames {
            macs: p.iter().map(|q| q.macs).collect(),
            errors_deg: e.clone(),
        })
        .collect();
    // Per lens its runs' frames, and their average (a lens of one run: its own).
    let mut by_lens: Vec<&[LensFrames]> = Vec::with_capacity(groups.len());
    let mut at = 0;
    for g in &groups {
        by_lens.push(&per_run[at..at + g.len()]);
        at += g.len();
    }
    let frames: Vec<LensFrames> = by_lens
        .iter()
        .map(|r| average_runs(r).map_err(|e| anyhow::anyhow!("--runs: {e}")))
        .collect::<Result<_>>()?;
    let names: Vec<String> = groups
        .iter()
        .map(|g| {
            g.iter()
                .map(|r| r.display().to_string())
                .collect::<Vec<_>>()
                .join("+")
        })
        .collect();
    let boot = if a.bootstrap > 0 {
        // An item's frames (an ambiguity pair's anchor, slip and gaze) are drawn together.
        let items: Vec<usize> = ds.records.iter().map(|r| r.item).collect();
        Some(
            bootstrap(&frames, &items, a.bootstrap, 0)
                .map_err(|e| anyhow::anyhow!("--bootstrap: {e}"))?,
        )
    } else {
        None
    };
    // With several seeds per lens, the lenses' paired differences seed by seed: how far the
    // training's randomness moves what the average says.
    let mut seed_diff = serde_json::Map::new();
    let mut seed_int = serde_json::Map::new();
    if groups.iter().all(|g| g.len() > 1) {
        for (i, na) in names.iter().enumerate() {
            for (j, nb) in names.iter().enumerate() {
                if let Some(d) = (i != j)
                    .then(|| seed_differences(by_lens[i], by_lens[j]))
                    .flatten()
                {
                    if let Some(t) = seed_interval(&d) {
                        seed_int.insert(
                            format!("{na} - {nb}"),
                            serde_json::json!({
                                "value": t.value, "lo": t.lo, "hi": t.hi, "seeds": d.len(),
                            }),
                        );
                    }
                    seed_diff.insert(format!("{na} - {nb}"), d.into());
                }
            }
        }
    }
    let lenses: Vec<(String, Vec<Point>)> = names
        .iter()
        .cloned()
        .zip(frames.iter().map(LensFrames::points))
        .collect();
    let medians = boot.as_ref().map(|b| b.median_v.as_slice());
    // A lens of several runs is named in the legend by its first, so the line fits the plot.
    let legend: Vec<(String, Vec<Point>)> = lenses
        .iter()
        .zip(&groups)
        .map(|((n, p), g)| match g.len() {
            1 => (n.clone(), p.clone()),
            k => (
                format!("{} +{} seeds (mean)", g[0].display(), k - 1),
                p.clone(),
            ),
        })
        .collect();
    util::write_atomic(&a.plot, pareto_svg(&legend, medians).as_bytes())
        .with_context(|| format!("--plot {}", a.plot.display()))?;
    let mut dom = serde_json::Map::new();
    for (na, pa) in &lenses {
        for (nb, pb) in &lenses {
            if na != nb {
                dom.insert(
                    format!("{na} > {nb}"),
                    dominates(&front(pa), &front(pb)).into(),
                );
            }
        }
    }
    let mut out = serde_json::json!({
        "lenses": lenses.iter().zip(&groups).map(|((n, p), g)| serde_json::json!({
            "run": n,
            "runs": g.iter().map(|r| r.display().to_string()).collect::<Vec<_>>(),
            "points": p,
            "front": front(p),
        })).collect::<Vec<_>>(),
        "dominates": dom,
        "subnets": archs.len(),
        // How each subnet's BN statistics were taken (null batches: every frame, with the
        // head refit).
        "head_refit": a.head_refit,
        "bn_batches": (!a.head_refit).then_some(a.bn_batches),
        "plot": a.plot.display().to_string(),
        "seconds": t0.elapsed().as_secs_f64(),
    });
    if let Some(b) = &boot {
        out["bootstrap"] = bootstrap_json(b, &lenses);
    }
    if !seed_diff.is_empty() {
        out["seed_differences"] = seed_diff.clone().into();
        out["seed_intervals"] = seed_int.clone().into();
    }
    if a.json {
        println!("{out}");
    } else {
        for (n, p) in &lenses {
            let f = front(p);
            println!("{n}: {} points, front of {}", p.len(), f.len());
        }
        for (k, v) in &dom {
            println!("{k}: {v}");
        }
        if let Some(b) = &boot {
            println!(
                "paired bootstrap over the {} items ({} frames; {} resamples; 90 % intervals):",
                b.clusters, b.frames, b.draws
            );
            for ((n, _), m) in lenses.iter().zip(&b.median_v) {
                println!("  {n}: median V {:.2}° [{:.2}, {:.2}]", m.value, m.lo, m.hi);
            }
            for (i, (na, _)) in lenses.iter().enumerate() {
                for (j, (nb, _)) in lenses.iter().enumerate() {
                    if i == j {
                        continue;
                    }
                    let d = b.mean_diff[i][j]
                        .map(|d| {
                            format!(
                                "; mean of V({na}) − V({nb}) {:+.2}° [{:+.2}, {:+.2}]",
                                d.value, d.lo, d.hi
                            )
                        })
                        .unwrap_or_default();
                    println!(
                        "  {na} > {nb}: front dominates in {:.1} % of resamples{d}",
                        100.0 * b.dominates[i][j]
                    );
                }
            }
        }
        for (k, d) in &seed_diff {
            let d: Vec<String> = d
                .as_array()
                .into_iter()
                .flatten()
                .filter_map(|v| v.as_f64())
                .map(|v| format!("{v:+.2}°"))
                .collect();
            let t = seed_int
                .get(k)
                .map(|t| {
                    format!(
                        "; mean {:+.2}°, Student's t 90 % [{:+.2}, {:+.2}]",
                        t["value"].as_f64().unwrap_or(f64::NAN),
                        t["lo"].as_f64().unwrap_or(f64::NAN),
                        t["hi"].as_f64().unwrap_or(f64::NAN)
                    )
                })
                .unwrap_or_default();
            println!(
                "mean of V({}) seed by seed: {}{t}",
                k.replace(" - ", ") − V("),
                d.join(", ")
            );
        }
        println!("plot: {}", a.plot.display());
    }
    Ok(())
}

/// The bootstrap's results as JSON (docs/run.md, "`nanoeye search pareto`"), keyed by run.
fn bootstrap_json(
    b: &nanoeye_search::pareto::Bootstrap,
    lenses: &[(String, Vec<Point>)],
) -> serde_json::Value {
    let mut dom = serde_json::Map::new();
    let mut diff = serde_json::Map::new();
    for (i, (na, _)) in lenses.iter().enumerate() {
        for (j, (nb, _)) in lenses.iter().enumerate() {
            if i != j {
                dom.insert(format!("{na} > {nb}"), b.dominates[i][j].into());
                if let Some(d) = b.mean_diff[i][j] {
                    diff.insert(format!("{na} - {nb}"), serde_json::json!(d));
                }
            }
        }
    }
    serde_json::json!({
        "draws": b.draws,
        "frames": b.frames,
        "items": b.clusters,
        "seed": 0,
        "median_v": lenses.iter().zip(&b.median_v).map(|((n, _), m)| serde_json::json!({
            "run": n, "value": m.value, "lo": m.lo, "hi": m.hi,
        })).collect::<Vec<_>>(),
        "dominates_fraction": dom,
        "mean_v_difference": diff,
    })
}

/// What a state's points were scored from; a rerun with another key is refused.
#[derive(Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct Key {
    /// The runs as given, each with its checkpoint's size and digest.
    runs: Vec<(String, u64, String)>,
    /// The evaluation set as given, with its record files' digest.
    dataset: (String, String),
    /// The BN set as given (absent: the evaluation set), with its records' digest.
    train: Option<(String, String)>,
    /// The chain settings: metasurface step (µm), exposure (ms), base pitch (µm).
    camera: (f64, f64, Option<f64>),
    /// The subnets, in the order scored.
    archs: Vec<Arch>,
    /// Whether each subnet was scored with the head refit.
    head_refit: bool,
    /// The BN batches without the head refit, null for every frame (absent in states
    /// written before the flag: 2, the count then fixed, so they resume with `--bn-batches 2`).
    #[serde(default = "two_batches")]
    bn_batches: Option<u64>,
}

/// `--bn-batches` before it was a flag.
fn two_batches() -> Option<u64> {
    Some(2)
}

impl Key {
    /// The key as JSON without the paths as given: the runs' checkpoints by size and digest,
    /// the sets by digest. What the points depend on, so that the same files named otherwise
    /// (`./ds`, an absolute path, a moved directory) resume and reuse.
    fn content(&self) -> Result<serde_json::Value> {
        let mut v = serde_json::to_value(self)?;
        v["runs"] = serde_json::json!(self.runs.iter().map(|(_, n, d)| (n, d)).collect::<Vec<_>>());
        v["dataset"] = serde_json::json!(self.dataset.1);
        v["train"] = serde_json::json!(self.train.as_ref().map(|t| &t.1));
        Ok(v)
    }

    /// The flags whose inputs differ between `self` and `other` (with `runs`, the runs too),
    /// by content ([`Self::content`]).
    fn differences(&self, other: &Key, runs: bool) -> Result<Vec<&'static str>> {
        let (old, new) = (self.content()?, other.content()?);
        Ok([
            ("runs", "--runs (or a run's checkpoint)"),
            ("dataset", "--dataset"),
            ("train", "--train"),
            ("camera", "the chain flags"),
            (
                "archs",
                "the subnets (--subnets, --seed or the first run's search)",
            ),
            ("head_refit", "--head-refit"),
            ("bn_batches", "--bn-batches"),
        ]
        .into_iter()
        .filter(|&(f, _)| (runs || f != "runs") && old[f] != new[f])
        .map(|(_, flag)| flag)
        .collect())
    }

    fn new(a: &ParetoArgs, runs: &[PathBuf], archs: &[Arch]) -> Result<Key> {
        let data = |flag: &str, dir: &Path| -> Result<(String, String)> {
            Ok((dir.display().to_string(), util::dataset_digest(flag, dir)?))
        };
        Ok(Key {
            runs: runs
                .iter()
                .map(|r| {
                    let ck = r.join("checkpoint.bin");
                    let mut d = util::Digest::default();
                    let n = d
                        .file(&ck)
                        .with_context(|| format!("--runs {}", r.display()))?;
                    Ok((r.display().to_string(), n, d.hex()))
                })
                .collect::<Result<_>>()?,
            dataset: data("--dataset", &a.dataset)?,
            train: a.train.as_deref().map(|t| data("--train", t)).transpose()?,
            camera: (
                a.camera.aperture_step_um,
                a.camera.exposure_ms,
                a.camera.base_pitch_um,
            ),
            archs: archs.to_vec(),
            head_refit: a.head_refit,
            bn_batches: match a.bn_batches {
                BnBatches::All => None,
                BnBatches::Count(n) => Some(n as u64),
            },
        })
    }
}

/// A run's points and per-frame errors, and the state they come from.
type Scored = (Vec<Point>, Vec<Vec<f64>>, PathBuf);

/// The complete runs of the `--reuse` states, by checkpoint (size, digest); a state scored
/// from other inputs than `key` (runs aside) is refused, naming them.
fn reusable(
    paths: &[PathBuf],
    key: &Key,
) -> Result<std::collections::HashMap<(u64, String), Scored>> {
    let mut out = std::collections::HashMap::new();
    for p in paths {
        let bytes = std::fs::read(p).with_context(|| format!("--reuse {}", p.display()))?;
        let st: State = serde_json::from_slice(&bytes)
            .with_context(|| format!("--reuse {}: not a `search pareto` state", p.display()))?;
        let differ = st.key.differences(key, false)?;
        if !differ.is_empty() {
            bail!(
                "--reuse {} was scored from other inputs ({} differ); reuse a state of the same \
                 inputs, or leave it out",
                p.display(),
                differ.join(", ")
            );
        }
        let n = key.archs.len();
        for ((run, points), errors) in st.key.runs.iter().zip(&st.lenses).zip(&st.frame_errors) {
            if points.len() == n && errors.len() == n {
                out.entry((run.1, run.2.clone()))
                    .or_insert_with(|| (points.clone(), errors.clone(), p.clone()));
            }
        }
    }
    Ok(out)
}

/// A `search pareto` run's state file (docs/formats.md): the key and the points per run so
/// far, in the order of `--runs` (the last one may be partial).
#[derive(Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct State {
    key: Key,
    lenses: Vec<Vec<Point>>,
    /// Per run, per subnet scored, the error on every evaluation frame (degrees; a failed
    /// frame 90°), for the bootstrap (absent in states written before it: refused on resume).
    #[serde(default)]
    frame_errors: Vec<Vec<Vec<f64>>>,
}

impl State {
    /// The state in `bytes` if it was scored from the inputs of `key`, with `key` (the paths
    /// as given now) in place of its own; refused, naming what differs, if not.
    fn resume(bytes: &[u8], key: Key, path: &Path, frames: usize) -> Result<State> {
        let mut st: State = serde_json::from_slice(bytes).with_context(|| {
            format!(
                "--state {}: not a `search pareto` state (delete it, or give another --state)",
                path.display()
            )
        })?;
        let differ = st.key.differences(&key, true)?;
        if !differ.is_empty() {
            bail!(
                "--state {} holds points scored from other inputs ({} differ); rerun with the \
                 same inputs, give another --state, or delete it",
                path.display(),
                differ.join(", ")
            );
        }
        let n = key.archs.len();
        if st.lenses.len() > key.runs.len()
            || st.lenses.iter().rev().skip(1).any(|p| p.len() != n)
            || st.lenses.last().is_some_and(|p| p.len() > n)
        {
            bail!(
                "--state {}: its points do not fit its {} runs of {n} subnets (delete it, or \
                 give another --state)",
                path.display(),
                key.runs.len()
            );
        }
        if st.frame_errors.len() != st.lenses.len()
            || st
                .frame_errors
                .iter()
                .zip(&st.lenses)
                .any(|(e, p)| e.len() != p.len())
        {
            bail!(
                "--state {}: written without the per-frame errors the bootstrap needs (an older \
                 nanoeye); delete it to score again",
                path.display()
            );
        }
        // What scoring writes: a subnet's MACs, its V and one error per evaluation frame, each
        // an angle (an edited error of 1e308 was blamed on --bootstrap, or with --bootstrap 0
        // printed as V = 1.7e307, exit 0).
        let angle = |v: f64| (0.0..=180.0).contains(&v);
        for (r, (points, errors)) in st.lenses.iter().zip(&st.frame_errors).enumerate() {
            for (k, (p, e)) in points.iter().zip(errors).enumerate() {
                if p.macs == 0
                    || !angle(p.v_deg)
                    || e.len() != frames
                    || !e.iter().all(|&v| angle(v))
                {
                    bail!(
                        "--state {}: run {r}, subnet {k} is no score a search writes ({} MACs, \
                         V {}°, {} frame errors for {frames} frames, each in [0°, 180°]); delete \
                         it, or give another --state",
                        path.display(),
                        p.macs,
                        p.v_deg,
                        e.len()
                    );
                }
            }
        }
        st.key = key;
        Ok(st)
    }
}

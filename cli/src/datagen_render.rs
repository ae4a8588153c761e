//! `nanoeye datagen render`: renders a state set into a dataset directory (docs/renderer.md).

use anyhow::{Context, Result, bail};
use nanoeye_datagen::render::{
    DatasetOptions, DatasetSummary, LayerSpec, Mesh, MeshUnits, RenderError, RenderSet,
    SceneSource, finish_dataset, open_dataset, plan_dataset, render_frames, write_dataset,
};
use nanoeye_datagen::states::PROTOCOL_GRID;
use nanoeye_gaze::Rig;
use std::path::PathBuf;

/// Which state set to render.
#[derive(Debug, Clone, Copy, clap::ValueEnum)]
pub enum SetArg {
    /// Ambiguity pairs: anchor, slip, gaze frames per pair.
    Ambiguity,
    /// Variational triplets: anchor, slip+, gaze+ frames per triplet.
    Variational,
    /// Acquisition protocol: 7 stage positions × --protocol-grid² targets (D.4: 49) per subject.
    Protocol,
    /// Video-like sequence of --n frames: a smooth gaze path while the glasses drift 3 mm.
    Sequence,
    /// --n frames spanning the protocol's gaze range and stage slippage (training data).
    Envelope,
}

/// Length unit of a mesh file.
#[derive(Debug, Clone, Copy, clap::ValueEnum)]
pub enum UnitsArg {
    /// Millimetres.
    Mm,
    /// Metres.
    M,
}

/// Arguments of `datagen render`.
#[derive(Debug, clap::Args)]
pub struct RenderArgs {
    /// State set to render.
    #[arg(long, value_enum)]
    pub set: SetArg,
    /// Items: pairs (ambiguity), triplets (variational) or subjects (protocol).
    #[arg(long)]
    pub n: usize,
    /// Seed of states, subjects and pixel samples.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Image width (px); the rig's sensor is resampled to it.
    #[arg(long, default_value_t = 320)]
    pub width: usize,
    /// Image height (px); must keep the rig's aspect ratio.
    #[arg(long, default_value_t = 200)]
    pub height: usize,
    /// Samples per pixel.
    #[arg(long, default_value_t = 4)]
    pub spp: usize,
    /// Output directory (frames already written are skipped).
    #[arg(long)]
    pub out: PathBuf,
    /// Rig JSON (default: the built-in rig).
    #[arg(long)]
    pub rig: Option<PathBuf>,
    /// Mesh file (.obj, .gltf, .glb) replacing the procedural eye region.
    #[arg(long)]
    pub mesh: Option<PathBuf>,
    /// Unit of the mesh coordinates, with --mesh only [default: mm].
    #[arg(long, value_enum)]
    pub mesh_units: Option<UnitsArg>,
    /// Share (0–1) of envelope frames caught in a blink or partial closure (lid closure
    /// uniform in 0.2–1); 0 keeps every lid open.
    #[arg(long, default_value_t = 0.0)]
    pub blink_fraction: f64,
    /// Targets per side of the protocol set's grid, 2–7 (D.4: 7 × 7), with --set protocol only.
    #[arg(long, default_value_t = PROTOCOL_GRID)]
    pub protocol_grid: usize,
}

/// Runs `datagen render`.
pub fn run(args: RenderArgs) -> Result<()> {
    if args.n == 0 {
        bail!("--n must be at least 1");
    }
    if args.spp == 0 {
        bail!("--spp must be at least 1");
    }
    // A flag the procedural scene does not take would be ignored: refuse it.
    if args.mesh_units.is_some() && args.mesh.is_none() {
        bail!("--mesh-units: gives the unit of a --mesh file; no --mesh is given");
    }
    let rig = match &args.rig {
        Some(p) => {
            // A small regular file: a FIFO would block, /dev/zero be read without end.
            let text = crate::util::read_small_text(p, crate::util::MAX_ARCH_BYTES)
                .with_context(|| format!("--rig {}", p.display()))?;
            Rig::from_json(&text).with_context(|| format!("--rig {}", p.display()))?
        }
        None => Rig::default(),
    };
    let source = match &args.mesh {
        Some(p) => {
            let units = match args.mesh_units.unwrap_or(UnitsArg::Mm) {
                UnitsArg::Mm => MeshUnits::Millimetres,
                UnitsArg::M => MeshUnits::Metres,
            };
            SceneSource::Mesh(
                Mesh::load(p, units).with_context(|| format!("--mesh {}", p.display()))?,
            )
        }
        None => SceneSource::Procedural,
    };
    let set = match args.set {
        SetArg::Ambiguity => RenderSet::Ambiguity,
        SetArg::Variational => RenderSet::Variational,
        SetArg::Protocol => RenderSet::Protocol,
        SetArg::Sequence => RenderSet::Sequence,
        SetArg::Envelope => RenderSet::Envelope,
    };
    let opts = DatasetOptions {
        set,
        n: args.n,
        seed: args.seed,
        width_px: args.width,
        height_px: args.height,
        spp: args.spp,
        out_dir: args.out.clone(),
        rig,
        source,
        progress: true,
        layers: LayerSpec::default(),
        blink_fraction: args.blink_fraction,
        protocol_grid: args.protocol_grid,
    };
    // A disk that cannot hold the frames' arrays is refused before anything is written (an
    // estimate that fails leaves the error to the writer, which names the flag).
    if let Ok(bytes) = nanoeye_datagen::render::dataset::dataset_array_bytes(&opts) {
        crate::util::check_disk(
            "datagen render",
            &args.out,
            bytes,
            "lower --n or --width × --height",
        )?;
    }
    // Temporary files of a killed run (frames/ is written by the renderer only).
    crate::util::remove_stale_temps_under(&args.out);
    let w = crate::dist::world();
    let result = if w.is_distributed() {
        render_distributed(&opts, w)
    } else {
        write_dataset(&opts).map(Some)
    };
    let summary = result.map_err(|e| {
        let msg = e.to_string();
        // Name the flag behind a size or sample error.
        let flag = if msg.contains("requested, at most") {
            "--n"
        } else if msg.contains("invalid width") {
            "--width"
        } else if msg.contains("invalid height") {
            "--height"
        } else if msg.contains("invalid spp") {
            "--spp"
        } else if msg.contains("invalid blink_fraction") {
            "--blink-fraction"
        } else if msg.contains("invalid protocol_grid") {
            "--protocol-grid"
        } else if msg.contains("camera.pixel_pitch_m") {
            // The rig's sensor spread over so few pixels that each is beyond any pitch.
            "--width/--height"
        } else {
            "--out"
        };
        anyhow::anyhow!("{flag}: {msg}")
    })?;
    // Rank 0 prints; the other ranks are done.
    let Some(summary) = summary else {
        return Ok(());
    };
    println!(
        "{}",
        serde_json::json!({
            "out": args.out.display().to_string(),
            "frames_written": summary.written,
            "frames_skipped": summary.skipped,
            "frames_jsonl": args.out.join("frames.jsonl").display().to_string(),
            "contact_sheet": args.out.join("contact_sheet.png").display().to_string(),
        })
    );
    Ok(())
}

/// The dataset over MPI ranks: rank 0 opens the directory, every rank renders frames
/// i ≡ rank (mod ranks) into it (a filesystem all ranks share), and rank 0 writes
/// frames.jsonl and the contact sheet once all are done. The summary over all ranks on rank
/// 0, None elsewhere.
fn render_distributed(
    opts: &DatasetOptions,
    w: crate::dist::World,
) -> Result<Option<DatasetSummary>, RenderError> {
    // Rank 0 refuses another dataset's directory before anyone renders; a refusal ends the
    // run there (the others wait in the broadcast).
    let plan = if w.is_root() {
        let p = open_dataset(opts)?;
        w.broadcast(Vec::new());
        p
    } else {
        w.broadcast(Vec::new());
        plan_dataset(opts)?
    };
    let mine = crate::dist::round_robin(plan.planned.len(), w);
    let s = render_frames(opts, &plan, &mine, w.is_root() && opts.progress)?;
    let mut counts = (s.written as u64).to_le_bytes().to_vec();
    counts.extend((s.skipped as u64).to_le_bytes());
    let Some(all) = w.gather(counts) else {
        return Ok(None);
    };
    let mut total = DatasetSummary {
        written: 0,
        skipped: 0,
    };
    for c in all {
        let v: Vec<u64> = c
            .chunks_exact(8)
            .map(|b| u64::from_le_bytes(b.try_into().unwrap_or([0; 8])))
            .collect();
        total.written += v.first().copied().unwrap_or(0) as usize;
        total.skipped += v.get(1).copied().unwrap_or(0) as usize;
    }
    finish_dataset(opts, &plan)?;
    Ok(Some(total))
}

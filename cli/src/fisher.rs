//! `nanoeye fisher …`: the initialization loop of Sec. A.2 and the PSF analysis of Sec. E.

use crate::util::{parse_list, parse_range, print_json, write_atomic};
use anyhow::{Context, Result, bail};
use clap::{Args, Subcommand};
use faer::Mat;
use nanoeye_fisher::nanoeye_optics::{
    ApertureGrid, AsmPsf, DoubleHelix, Hyperbolic, PhaseMap, PhaseProfile, PsfConfig, PsfModel,
    PsfUsage, io::read_phase_npy,
};
use nanoeye_fisher::{FisherNoise, InitConfig, InitState, compare_lenses, init_step, write_npy};
use nanoeye_sensor::SensorConfig;
use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Fisher-information design commands.
#[derive(Subcommand)]
pub enum Cmd {
    /// Initialization loop (A.2): Adam on a free-form phase map minimizing L_init (S3–S6),
    /// starting from the hyperbolic lens; resumes from DIR/checkpoint when present.
    Init(InitArgs),
    /// Depth Fisher information (S25) of lenses at several pixel pitches (Sec. E, Fig. S10).
    Compare(CompareArgs),
}

/// Optics shared by both commands.
#[derive(Args, Clone)]
pub struct OpticsArgs {
    /// Aperture sampling step of the phase map (µm); the aperture is 1 mm wide.
    #[arg(long, default_value_t = 1.5)]
    aperture_step_um: f64,
    /// PSF window at the native 3 µm pitch (pixels; a multiple of 3 keeps 3×3 binning exact).
    #[arg(long, default_value_t = 63)]
    window_px: usize,
    /// Photons from the point source incident on the aperture per exposure.
    #[arg(long, default_value_t = 1e5)]
    photons: f64,
}

/// Arguments of `fisher init`.
#[derive(Args)]
pub struct InitArgs {
    /// Output directory (phase.npy, psf_montage.png, history.json, checkpoint/).
    #[arg(long)]
    out: PathBuf,
    /// Total number of Adam iterations (a resumed run continues up to this count).
    #[arg(long, default_value_t = 200)]
    iterations: usize,
    /// Effective sensor pitch p̂ the losses see (µm).
    #[arg(long, default_value_t = 9.0)]
    pitch_um: f64,
    /// Depth planes (mm), a:b:step.
    #[arg(long, default_value = "17:26:1.5")]
    depths_mm: String,
    /// Adam step on the phase (rad).
    #[arg(long, default_value_t = 0.05)]
    lr_rad: f64,
    /// Checkpoint every this many iterations.
    #[arg(long, default_value_t = 10)]
    checkpoint_every: usize,
    #[command(flatten)]
    optics: OpticsArgs,
    /// Print a JSON summary.
    #[arg(long)]
    json: bool,
}

/// Arguments of `fisher compare`.
#[derive(Args)]
pub struct CompareArgs {
    /// Lenses: hyperbolic, double-helix, file:PATH.npy (a phase map, rad, on the aperture grid).
    #[arg(long, default_value = "hyperbolic,double-helix")]
    lenses: String,
    /// Depth planes (mm), a:b:step.
    #[arg(long, default_value = "17:26:1.5")]
    depths_mm: String,
    /// Pixel pitches (µm); the smallest is the native pitch, the others box-integrate it.
    #[arg(long, default_value = "3,9")]
    pitch_um: String,
    /// Montage PNG of all lenses at all pitches.
    #[arg(long, default_value = "fisher_compare.png")]
    montage: PathBuf,
    #[command(flatten)]
    optics: OpticsArgs,
    /// Print one line of JSON: {"results":[{"lens","pitch_um","fisher_z"}…],"retained":{…}}.
    #[arg(long)]
    json: bool,
}

/// Runs a fisher command.
pub fn run(cmd: Cmd) -> Result<()> {
    match cmd {
        Cmd::Init(a) => init(a),
        Cmd::Compare(a) => compare(a),
    }
}

/// Least spacing of neighbouring depth planes (m): 1 µm, where the PSFs of the default lens
/// still differ by far more than f32 round-off.
const MIN_DEPTH_STEP_M: f64 = 1e-6;

fn depths(flag: &str, text: &str) -> Result<Vec<f64>> {
    let d = parse_range(flag, text)?;
    if d.len() < 2 {
        bail!("{flag}: need at least 2 depth planes for ∂PSF/∂z");
    }
    let m: Vec<f64> = d.into_iter().map(|z| z * 1e-3).collect();
    // Checked in metres: 4.9e-324 mm is positive but 0 m; 1e-308 mm gave planes of zeros.
    let min = crate::optics::MIN_DISTANCE_M;
    if m.iter().any(|&z| z.is_nan() || z < min) {
        bail!("{flag}: depths must be at least {} mm", min * 1e3);
    }
    // As `optics psf` bounds them: depths of 1e300 mm gave every fisher_z 0 with exit 0.
    let max = crate::optics::MAX_DISTANCE_M;
    if m.iter().any(|&z| z > max) {
        bail!("{flag}: depths must be at most {} mm", max * 1e3);
    }
    // ∂PSF/∂z is a difference of neighbouring f32 planes: planes 1e-11 mm apart differ by
    // round-off alone, and fisher_z read 0 or 8e8 with exit 0 (a helper's audit).
    // (With slack: 17:26:0.001 steps by 0.000999… mm in f64.)
    if let Some(w) = m
        .windows(2)
        .find(|w| (w[1] - w[0]).abs() < MIN_DEPTH_STEP_M * (1.0 - 1e-6))
    {
        bail!(
            "{flag}: neighbouring depths must be at least {} mm apart (∂PSF/∂z is their \
             difference), got {} and {} mm",
            MIN_DEPTH_STEP_M * 1e3,
            w[0] * 1e3,
            w[1] * 1e3
        );
    }
    Ok(m)
}

/// Most PSF values a command holds per lens and pitch: depth planes × window² (each plane
/// has its PSF and ∂PSF/∂z in f64, so 1 GiB at this bound); beyond it a run would fail an
/// allocation, panic and hang rather than refuse (9001 planes of 1024² did).
const MAX_PLANE_VALUES: u128 = 1 << 26;

// Most lenses or pitches `fisher compare` takes (each multiplies the work and the montage).
use crate::util::MAX_LIST;

/// Refuses a depth stack whose PSFs and derivatives would not fit [`MAX_PLANE_VALUES`].
fn check_stack(planes: usize, window_px: usize) -> Result<()> {
    let values = planes as u128 * window_px as u128 * window_px as u128;
    if values > MAX_PLANE_VALUES {
        bail!(
            "--depths-mm/--window-px: {planes} planes of {window_px}×{window_px} pixels is \
             {values} values, more than {MAX_PLANE_VALUES} (1 GiB of PSFs and derivatives); \
             give fewer planes or a smaller window"
        );
    }
    Ok(())
}

/// Largest photon budget: Fisher information scales with it, and far beyond any exposure
/// (10^20 photons) the sums overflow to inf (1e308 gave a null fisher_z).
const MAX_PHOTONS: f64 = 1e20;

/// Smallest photon budget: far below it QE · photons underflows (5e-324 failed naming
/// --pitch-um), and a millionth of a photon carries no information worth a Fisher study.
const MIN_PHOTONS: f64 = 1e-6;

/// The aperture grid and PSF configuration of the optics flags.
fn optics_of(o: &OpticsArgs, native_pitch_m: f64) -> Result<(ApertureGrid, PsfConfig)> {
    check_optics(o)?;
    let grid = ApertureGrid::new(1e-3, o.aperture_step_um * 1e-6).context("--aperture-step-um")?;
    let cfg = PsfConfig {
        pitch_m: native_pitch_m,
        window_px: o.window_px,
        ..PsfConfig::default()
    };
    Ok((grid, cfg))
}

/// Refuses optics whose work would not fit in memory, before anything is built: `maps` phase
/// maps held at once, stacks of `depths` depths used as `usage` says (a size the model itself
/// refuses is left to [`model`]).
fn check_model_memory(
    o: &OpticsArgs,
    native_pitch_m: f64,
    depths: usize,
    maps: usize,
    usage: PsfUsage,
) -> Result<()> {
    let (grid, cfg) = optics_of(o, native_pitch_m)?;
    let threads = rayon::current_num_threads();
    let map_bytes = 16 * (grid.n as u64).pow(2);
    // A configuration the model refuses is left to `model`, whose caller names the flag.
    let Ok(one) = AsmPsf::memory_bytes(&cfg, &grid, depths, threads, usage) else {
        return Ok(());
    };
    let need = one.saturating_add((maps.saturating_sub(1) as u64).saturating_mul(map_bytes));
    crate::util::check_memory(
        "--aperture-step-um/--window-px",
        need,
        "give a coarser --aperture-step-um or a smaller --window-px",
    )
}

fn model(o: &OpticsArgs, native_pitch_m: f64) -> Result<(ApertureGrid, AsmPsf)> {
    let (grid, cfg) = optics_of(o, native_pitch_m)?;
    let m = AsmPsf::new(cfg, grid).context("--window-px / --aperture-step-um")?;
    Ok((grid, m))
}

/// The optics flags' own ranges, each error naming its flag.
fn check_optics(o: &OpticsArgs) -> Result<()> {
    // At most an eighth of the aperture: 1000 µm left one sample and failed naming no flag.
    crate::sim::check_aperture_step("--aperture-step-um", o.aperture_step_um)?;
    if o.window_px < 3 || o.window_px > 1024 {
        bail!("--window-px: must lie in 3..=1024, got {}", o.window_px);
    }
    if !(o.photons.is_finite() && o.photons >= MIN_PHOTONS && o.photons <= MAX_PHOTONS) {
        bail!(
            "--photons: must lie in [{MIN_PHOTONS:e}, {MAX_PHOTONS:e}], got {:e}",
            o.photons
        );
    }
    Ok(())
}

/// Fisher noise of the default sensor: electrons = QE · photons · PSF, σ² = read noise².
pub(crate) fn sensor_noise(photons: f64) -> FisherNoise {
    let s = SensorConfig::default();
    FisherNoise {
        photons: s.quantum_efficiency * photons,
        noise_var: s.read_noise_e * s.read_noise_e,
        ..FisherNoise::default()
    }
}

/// Fisher initialization of a co-design lens on `chain` (A.2): `iterations` steps of `fisher
/// init`'s L_init from the hyperbolic phase, on the chain's PSF model and depth slabs, at the
/// initial effective pitch `pitch_init_um` (µm) with `photons` through the aperture. Returns φ
/// (rad) on the chain's aperture grid. Used by `nanoeye run` and `search train --lens init`.
pub(crate) fn chain_init_phase(
    chain: &nanoeye_search::CameraChain,
    pitch_init_um: f64,
    iterations: usize,
    photons: f64,
) -> Result<Mat<f64>> {
    let grid = *chain.aperture_grid();
    let r = &chain.config().radiometry;
    let hyper = nanoeye_search::LensSpec::Hyperbolic
        .phase_map(&grid, r.wavelength_m, r.sensor_distance_m)?
        .phase_rad;
    let icfg = InitConfig {
        depths_m: chain.depths_m().to_vec(),
        sensor_pitch_m: pitch_init_um * 1e-6,
        noise: sensor_noise(photons),
        ..InitConfig::default()
    };
    let mut st = InitState::new(hyper);
    while st.iteration < iterations {
        init_step(chain.psf_model(), &grid, &icfg, &mut st).context("Fisher initialization")?;
    }
    Ok(st.phase)
}

/// Checks the Fisher initialization's iteration count and photon budget, naming `flags`
/// (iterations, photons) in the error.
pub(crate) fn check_init_budget(iterations: usize, photons: f64, flags: [&str; 2]) -> Result<()> {
    if iterations > 100_000 {
        bail!("{}: must be at most 100000, got {iterations}", flags[0]);
    }
    // 1e20 photons: beyond it the Fisher sums overflow (as `fisher init --photons`).
    if !(photons.is_finite() && photons > 0.0 && photons <= 1e20) {
        bail!("{}: must lie in (0, 1e20], got {photons:e}", flags[1]);
    }
    Ok(())
}

/// Gray montage: one row per entry, one tile per plane, each tile scaled to its own maximum
/// and upscaled by `up` (nearest) so that all rows show the same sensor area.
fn montage(rows: &[(Vec<Mat<f32>>, usize)]) -> Result<Vec<u8>> {
    let gap = 2usize;
    let tile = rows
        .iter()
        .map(|(p, up)| p.first().map_or(0, |m| m.nrows() * up))
        .max()
        .unwrap_or(0);
    let ncol = rows.iter().map(|(p, _)| p.len()).max().unwrap_or(0);
    if tile == 0 || ncol == 0 {
        bail!("nothing to draw");
    }
    let (w, h) = (ncol * (tile + gap) + gap, rows.len() * (tile + gap) + gap);
    let mut img = image::GrayImage::from_pixel(w as u32, h as u32, image::Luma([40u8]));
    for (ri, (planes, up)) in rows.iter().enumerate() {
        for (ci, p) in planes.iter().enumerate() {
            let mx = p
                .col_iter()
                .flat_map(|c| c.iter().copied().collect::<Vec<_>>())
                .fold(0f32, f32::max);
            for i in 0..p.nrows() * up {
                for j in 0..p.ncols() * up {
                    let v = if mx > 0.0 {
                        p[(i / up, j / up)] / mx
                    } else {
                        0.0
                    };
                    let x = gap + ci * (tile + gap) + j;
                    let y = gap + ri * (tile + gap) + i;
                    if x < w && y < h {
                        img.put_pixel(
                            x as u32,
                            y as u32,
                            image::Luma([(v.clamp(0.0, 1.0) * 255.0) as u8]),
                        );
                    }
                }
            }
        }
    }
    let mut buf = Vec::new();
    image::DynamicImage::ImageLuma8(img)
        .write_to(&mut std::io::Cursor::new(&mut buf), image::ImageFormat::Png)?;
    Ok(buf)
}

fn init(a: InitArgs) -> Result<()> {
    if a.iterations == 0 {
        bail!("--iterations: must be at least 1");
    }
    // The job's bound on its `fisher_iterations`, and the photons' (checked again with the
    // optics below, where the message is the same).
    check_init_budget(
        a.iterations,
        a.optics.photons,
        ["--iterations", "--photons"],
    )?;
    if a.checkpoint_every == 0 {
        bail!("--checkpoint-every: must be at least 1");
    }
    if a.out.exists() && !a.out.is_dir() {
        bail!(
            "--out: '{}' exists and is not a directory; give a directory (new or of an earlier run)",
            a.out.display()
        );
    }
    if !(a.pitch_um.is_finite() && a.pitch_um >= 3.0) {
        bail!(
            "--pitch-um: must be >= 3 (the native pitch), got {}",
            a.pitch_um
        );
    }
    // The training's bound on a learning rate (search::train::MAX_FACTOR): Adam moves φ by at
    // most about this per iteration, so φ stays finite (1e308 overflowed it).
    let max_lr = nanoeye_search::train::MAX_FACTOR;
    if !(a.lr_rad.is_finite() && a.lr_rad > 0.0 && a.lr_rad <= max_lr) {
        bail!("--lr-rad: must lie in (0, {max_lr}], got {}", a.lr_rad);
    }
    let depths_m = depths("--depths-mm", &a.depths_mm)?;
    check_optics(&a.optics)?;
    check_stack(depths_m.len(), a.optics.window_px)?;
    // The PSF window (on the 3 µm native grid) must hold at least one effective pixel.
    let widest = a.optics.window_px as f64 * 3.0;
    if a.pitch_um > widest {
        bail!(
            "--pitch-um: at most {widest} µm (the {}-pixel PSF window at 3 µm), got {}",
            a.optics.window_px,
            a.pitch_um
        );
    }
    check_model_memory(&a.optics, 3e-6, depths_m.len(), 1, PsfUsage::Training)?;
    let (grid, model) = model(&a.optics, 3e-6)?;
    let ckpt = a.out.join("checkpoint");
    let requested = InitConfig {
        depths_m: depths_m.clone(),
        sensor_pitch_m: a.pitch_um * 1e-6,
        lr_phase: a.lr_rad,
        noise: sensor_noise(a.optics.photons),
        ..InitConfig::default()
    };
    // Temporary files of a killed run (its checkpoint/ is written by the fisher crate only).
    crate::util::remove_stale_temps_under(&a.out);
    // The PSF window and the aperture sampling shape every iteration's PSFs but are not in
    // the checkpoint's config (its grid size alone let another step of the same size resume).
    let inputs_path = a.out.join("inputs.json");
    let inputs = serde_json::json!({
        "window_px": a.optics.window_px,
        "aperture_step_um": a.optics.aperture_step_um,
    });
    let keys = [
        ("window_px", "--window-px"),
        ("aperture_step_um", "--aperture-step-um"),
    ];
    let (mut state, cfg) = if InitState::checkpoint_exists(&ckpt) {
        let (s, c) = InitState::load(&ckpt)
            .with_context(|| format!("--out: cannot resume from '{}'", ckpt.display()))?;
        crate::util::check_inputs(&inputs_path, &inputs, &keys, "--out")?;
        // The checkpoint keeps them too: without inputs.json (deleted, or the checkpoint
        // copied from another run) a resume with another window went on (a helper's audit).
        if let Some((flag, key, old, new)) = s
            .inputs
            .as_ref()
            .and_then(|had| crate::util::value_difference(had, &inputs, &keys))
        {
            bail!(
                "{flag}: differs from the checkpoint in '{}' ({key} = {old} there, {new} now); \
                 use the original value or another --out",
                ckpt.display()
            );
        }
        // A resumed run must continue the same problem: refuse changed parameters by name.
        let changed = [
            ("--depths-mm", c.depths_m != requested.depths_m),
            ("--pitch-um", c.sensor_pitch_m != requested.sensor_pitch_m),
            ("--lr-rad", c.lr_phase != requested.lr_phase),
            ("--photons", c.noise != requested.noise),
        ];
        if let Some((flag, _)) = changed.iter().find(|(_, d)| *d) {
            bail!(
                "{flag}: differs from the checkpoint in '{}' (it was written with other \
                 parameters); use the original value or another --out",
                ckpt.display()
            );
        }
        if s.phase.nrows() != grid.n {
            bail!(
                "--aperture-step-um: checkpoint grid is {} samples, this run's is {}",
                s.phase.nrows(),
                grid.n
            );
        }
        // Fewer iterations than the checkpoint holds would rewrite the outputs of a longer
        // run under a shorter request, exit 0 (a helper's audit): the count is the total.
        if a.iterations < s.iteration {
            bail!(
                "--iterations: {} is fewer than the {} the checkpoint in '{}' has done (the \
                 count is the run's total); give at least {} or another --out",
                a.iterations,
                s.iteration,
                ckpt.display(),
                s.iteration
            );
        }
        eprintln!(
            "resuming from '{}' at iteration {}",
            ckpt.display(),
            s.iteration
        );
        (s, c)
    } else {
        let phase = Hyperbolic::default().phase_map(&grid)?.phase_rad;
        (InitState::new(phase), requested)
    };
    state.inputs = Some(inputs.clone());
    crate::util::check_not_dataset(&a.out)?;
    // Every output's place checked before the first is written: a directory at
    // OUT/history.json was found only after the checkpoint, phase and montage were written.
    for name in [
        "inputs.json",
        "phase.npy",
        "psf_montage.png",
        "history.json",
    ] {
        crate::util::check_output_target(&a.out.join(name)).context("--out")?;
    }
    if ckpt.exists() && !ckpt.is_dir() {
        bail!(
            "--out: '{}' exists and is not a directory (the checkpoint's); remove it or give \
             another --out",
            ckpt.display()
        );
    }
    crate::util::check_output_target(&ckpt.join(nanoeye_fisher::CHECKPOINT_FILE))
        .context("--out")?;
    std::fs::create_dir_all(&a.out).with_context(|| format!("--out {}", a.out.display()))?;
    write_atomic(&inputs_path, format!("{inputs}\n").as_bytes())?;
    let t0 = Instant::now();
    let start = state.iteration;
    while state.iteration < a.iterations {
        let rec = init_step(&model, &grid, &cfg, &mut state).context("initialization step")?;
        let done = state.iteration - start;
        let per = t0.elapsed().as_secs_f64() / done as f64;
        eprint!(
            "\rinit {:>5}/{}  L_init {:+.4}  (prec {:+.3}, dist {:.3e}, comp {:.3})  {:.2} s/it, ETA {:.0} s   ",
            state.iteration,
            a.iterations,
            rec.l_init,
            rec.terms[0],
            rec.terms[1],
            rec.terms[2],
            per,
            per * (a.iterations - state.iteration) as f64
        );
        let _ = std::io::stderr().flush();
        if state.iteration % a.checkpoint_every == 0 {
            state
                .save(&ckpt, &cfg)
                .context("--out: writing the checkpoint")?;
        }
    }
    eprintln!();
    state
        .save(&ckpt, &cfg)
        .context("--out: writing the checkpoint")?;
    let phase_path = a.out.join("phase.npy");
    write_npy(&phase_path, &state.phase).context("--out: writing phase.npy")?;
    // Final PSFs at the native pitch and at p̂.
    let map = PhaseMap::phase_only(grid, state.phase.clone())?;
    let st = model.forward(&map, &cfg.depths_m, None)?;
    let (_, op) =
        nanoeye_fisher::bin_planes(&st.planes, st.pitch_m, cfg.sensor_pitch_m, &cfg.depths_m)?;
    let mut rows = vec![(st.planes.clone(), 1usize)];
    if let Some(op) = op {
        let b = st
            .planes
            .iter()
            .map(|p| op.forward(p))
            .collect::<Result<Vec<_>, _>>()?;
        rows.push((
            b,
            (cfg.sensor_pitch_m / st.pitch_m).round().max(1.0) as usize,
        ));
    }
    let montage_path = a.out.join("psf_montage.png");
    write_atomic(&montage_path, &montage(&rows)?)?;
    write_atomic(
        &a.out.join("history.json"),
        &serde_json::to_vec_pretty(&state.history)?,
    )?;
    let last = state.history.last().cloned();
    // The run's first iteration, also after a resume (the history holds every iteration).
    let first = state.history.first().cloned();
    let summary = serde_json::json!({
        "iterations": state.iteration,
        "seconds": t0.elapsed().as_secs_f64(),
        "l_init_first": first.as_ref().map(|r| r.l_init),
        "l_init_last": last.as_ref().map(|r| r.l_init),
        "terms_first": first.as_ref().map(|r| r.terms),
        "terms_last": last.as_ref().map(|r| r.terms),
        "phase": phase_path,
        "montage": montage_path,
    });
    if a.json {
        print_json(&summary)
    } else {
        println!("{}", serde_json::to_string_pretty(&summary)?);
        Ok(())
    }
}

fn lens_map(spec: &str, grid: &ApertureGrid) -> Result<PhaseMap> {
    match spec {
        "hyperbolic" => Ok(Hyperbolic::default().phase_map(grid)?),
        "double-helix" => Ok(DoubleHelix::default().phase_map(grid)?),
        s if s.starts_with("file:") => {
            let path = Path::new(&s[5..]);
            let phi = read_phase_npy(path)
                .with_context(|| format!("--lenses: cannot read '{}'", path.display()))?;
            if phi.nrows() != grid.n {
                bail!(
                    "--lenses: '{}' is {}x{} but the aperture grid is {}x{} (check --aperture-step-um)",
                    path.display(),
                    phi.nrows(),
                    phi.ncols(),
                    grid.n,
                    grid.n
                );
            }
            Ok(PhaseMap::phase_only(*grid, phi)?)
        }
        other => bail!("--lenses: unknown lens '{other}' (hyperbolic, double-helix, file:PATH)"),
    }
}

fn compare(a: CompareArgs) -> Result<()> {
    if !a
        .montage
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("png"))
    {
        bail!(
            "--montage: '{}' must end in .png (the montage is written as PNG)",
            a.montage.display()
        );
    }
    crate::util::check_output_target(&a.montage).context("--montage")?;
    let depths_m = depths("--depths-mm", &a.depths_mm)?;
    let pitches_um = parse_list("--pitch-um", &a.pitch_um)?;
    if pitches_um.is_empty() {
        bail!("--pitch-um: need positive pitches");
    }
    // Far below a sensor pixel the window holds no PSF (1e-308 µm gave fisher_z 0, exit 0).
    let min = crate::sim::MIN_BASE_PITCH_UM;
    if let Some(p) = pitches_um.iter().find(|&&p| p.is_nan() || p < min) {
        bail!("--pitch-um: pitches must be at least {min} µm (a sensor pixel), got {p:e}");
    }
    if pitches_um.len() > MAX_LIST {
        bail!(
            "--pitch-um: at most {MAX_LIST} pitches, got {}",
            pitches_um.len()
        );
    }
    // A value given twice would be computed and reported twice.
    if let Some(p) = crate::util::first_repeat(&pitches_um) {
        bail!("--pitch-um: {p} is given twice");
    }
    let native = pitches_um.iter().copied().fold(f64::INFINITY, f64::min);
    // The optics flags first, so that the context below only ever wraps the pitch's errors.
    check_optics(&a.optics)?;
    check_stack(depths_m.len(), a.optics.window_px)?;
    let specs: Vec<&str> = a
        .lenses
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .collect();
    if specs.is_empty() {
        bail!("--lenses: no lens given");
    }
    // The montage replaces its path whole: a lens file there (an NPY named .png) was lost.
    for spec in &specs {
        if let Some(f) = spec.strip_prefix("file:")
            && crate::util::same_file(&a.montage, Path::new(f))
        {
            bail!(
                "--montage: '{}' is the lens {spec}; give another path",
                a.montage.display()
            );
        }
    }
    if specs.len() > MAX_LIST {
        bail!("--lenses: at most {MAX_LIST} lenses, got {}", specs.len());
    }
    if let Some(l) = crate::util::first_repeat(&specs) {
        bail!("--lenses: {l} is given twice");
    }
    let usage = if specs.len() > 1 {
        PsfUsage::Repeated
    } else {
        PsfUsage::Once
    };
    check_model_memory(&a.optics, native * 1e-6, depths_m.len(), specs.len(), usage)?;
    let (grid, model) = model(&a.optics, native * 1e-6)
        .context("--pitch-um: the smallest pitch is the PSF model's native pitch")?;
    let lenses = specs
        .iter()
        .map(|s| Ok((s.to_string(), lens_map(s, &grid)?)))
        .collect::<Result<Vec<_>>>()?;
    let pitches_m: Vec<f64> = pitches_um.iter().map(|p| p * 1e-6).collect();
    let noise = sensor_noise(a.optics.photons);
    // Binning fails for a pitch whose effective pixel exceeds the window.
    let (rows, planes) = compare_lenses(&model, &lenses, &depths_m, &pitches_m, &noise)
        .context("--pitch-um/--window-px")?;
    if let Some(r) = rows.iter().find(|r| !r.fisher_z.is_finite()) {
        bail!(
            "--photons: the Fisher information of {} at {} µm is not finite ({}); lower the \
             photon budget",
            r.lens,
            r.pitch_um,
            r.fisher_z
        );
    }
    let coarse = pitches_um.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let mut retained = BTreeMap::new();
    for s in &specs {
        let f = |p: f64| {
            rows.iter()
                .find(|r| r.lens == *s && (r.pitch_um - p).abs() < 1e-9)
                .map(|r| r.fisher_z)
        };
        if let (Some(fc), Some(ff)) = (f(coarse), f(native)) {
            retained.insert(s.to_string(), if ff > 0.0 { fc / ff } else { 0.0 });
        }
    }
    let tiles: Vec<(Vec<Mat<f32>>, usize)> = planes
        .into_iter()
        .map(|p| (p.planes, (p.pitch_um / native).round().max(1.0) as usize))
        .collect();
    write_atomic(&a.montage, &montage(&tiles)?).context("--montage")?;
    if a.json {
        let results: Vec<_> = rows
            .iter()
            .map(|r| serde_json::json!({"lens": r.lens, "pitch_um": r.pitch_um, "fisher_z": r.fisher_z}))
            .collect();
        print_json(&serde_json::json!({"results": results, "retained": retained}))
    } else {
        println!(
            "depth Fisher information Σ_z I(z) (S25, m⁻²), {} photons, default sensor noise:",
            a.optics.photons
        );
        for r in &rows {
            println!(
                "  {:<28} {:>5.1} µm  {:.4e}",
                r.lens, r.pitch_um, r.fisher_z
            );
        }
        for (k, v) in &retained {
            println!("  retained {k}: {v:.4}");
        }
        println!("montage: {}", a.montage.display());
        Ok(())
    }
}

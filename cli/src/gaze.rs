//! `nanoeye gaze …`: batch gaze solving and the pupil-sphere bias study.

use crate::{rig, util};
use anyhow::{Context, Result, bail};
use clap::Subcommand;
use faer::Mat;
use nanoeye_gaze::bias::{GazeGrid, MAX_GRID_STEPS, pupil_sphere_bias};
use nanoeye_gaze::{GazeSolver, PupilCentre, RefractiveSolver, SolverKind, SphereSolver};
use serde::Deserialize;
use serde_json::json;
use std::io::{BufRead, Write};
use std::path::{Path, PathBuf};

/// Gaze commands.
#[derive(Subcommand)]
pub enum Cmd {
    /// Solve gaze for a batch of queries (JSONL, one per line; docs/formats.md).
    Solve {
        /// Input JSONL: {"pupil_px":[u,v],"slip_m":[x,y,z]} or {"mask_png":"path","slip_m":[…]}.
        #[arg(long)]
        input: PathBuf,
        /// Rig JSON file; default: the built-in seed rig.
        #[arg(long)]
        rig: Option<PathBuf>,
        /// Also output the visual axis (rig's kappa applied).
        #[arg(long)]
        kappa: bool,
        /// Solver: sphere (S12–S14 on the rig's `eye_radius_m`) or refractive (the pupil seen
        /// through the rig's cornea, on its pupil sphere; docs/gaze.md).
        #[arg(long, default_value = "sphere")]
        solver: String,
        /// Pupil centre of a mask query: centroid (S9) or ellipse_if_cut (S9 unless the pupil
        /// reaches the mask's edge, then the centre of its boundary's fitted ellipse).
        #[arg(long, default_value = "centroid")]
        pupil_centre: String,
        /// Write results here (atomically) instead of stdout.
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// Angular bias over Table S2's gaze range when the solver sphere differs from the pupil's.
    Bias {
        /// Rig JSON file; default: the built-in seed rig.
        #[arg(long)]
        rig: Option<PathBuf>,
        /// Solver radii to evaluate (mm, comma-separated); the rig's pupil radius is always added.
        #[arg(long, default_value = "9,10,11,12,13")]
        solver_radii_mm: String,
        /// Grid samples per axis.
        #[arg(long, default_value_t = 41)]
        steps: usize,
        /// Print JSON instead of a table.
        #[arg(long)]
        json: bool,
    },
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct Query {
    pupil_px: Option<[f64; 2]>,
    mask_png: Option<String>,
    #[serde(default)]
    slip_m: [f64; 3],
}

/// Reads a PNG mask (8- or 16-bit grey, or any format reduced to luma) into [0, 1]: a regular
/// file whose header's size is `grid` = (rows, columns), the camera image's, or a downscale of
/// it by one factor in x and y (docs/formats.md), checked before the image is decoded (a FIFO
/// blocked the batch; a 48 KB PNG of 20000² pixels took 3 GB before its size was compared).
pub fn read_mask_png(path: &Path, grid: (usize, usize)) -> Result<Mat<f32>> {
    let what = || format!("cannot read mask '{}'", path.display());
    if !std::fs::metadata(path).with_context(what)?.is_file() {
        bail!("mask '{}' is not a regular file", path.display());
    }
    let open = || {
        image::ImageReader::open(path)
            .and_then(|r| r.with_guessed_format())
            .with_context(what)
    };
    let (w, h) = open()?.into_dimensions().with_context(what)?;
    // The solver's own rule (a downscale was refused here, against the format's documentation);
    // no larger than the camera image, so the decode stays bounded by it.
    nanoeye_gaze::centroid::mask_scale(w as usize, h as usize, grid.1, grid.0)?;
    // Decoded (up to 8 bytes a pixel for 16-bit colour), as 16-bit luma and as f32.
    crate::util::check_memory(
        &format!("mask '{}'", path.display()),
        14 * w as u64 * h as u64,
        "give a smaller (downscaled) mask or a camera of fewer pixels (--rig)",
    )?;
    let img = open()?.decode().with_context(what)?.into_luma16();
    let (w, h) = img.dimensions();
    Ok(Mat::from_fn(h as usize, w as usize, |i, j| {
        img.get_pixel(j as u32, i as u32)[0] as f32 / 65535.0
    }))
}

/// Whether a line's error is a valid query's lack of a gaze (no pupil in the mask, a ray that
/// misses the eye, a camera slipped into it, a gaze that with κ points straight back) rather
/// than a line that is no valid query.
fn no_solution(e: &anyhow::Error) -> bool {
    use nanoeye_gaze::GazeError as G;
    matches!(
        e.downcast_ref::<G>(),
        Some(
            G::EmptyMask { .. }
                | G::RayMissesSphere { .. }
                | G::RayMissesCornea { .. }
                | G::CameraInsideSphere { .. }
                | G::BehindCamera { .. }
                | G::OppositeGaze { .. }
        )
    )
}

/// Largest |slip_m| component a query may give (m): glasses a metre off the nose. 1e200 made
/// the refraction-aware solver's norms overflow into a zero gaze and a null visual axis.
const MAX_SLIP_M: f64 = 1.0;
/// Largest |pupil_px| component a query may give (px), far outside any image.
const MAX_PUPIL_PX: f64 = 1e7;

/// Answers one query line; `masks` collects the mask files read (none may be `--out`), and
/// `grid` is the camera image's (rows, columns).
fn solve_line(
    solver: &dyn GazeSolver,
    centre: PupilCentre,
    line: &str,
    base: &Path,
    grid: (usize, usize),
    masks: &mut Vec<PathBuf>,
) -> Result<serde_json::Value> {
    let v: serde_json::Value = serde_json::from_str(line).context("not a query object")?;
    if let Some(m) = crate::util::array_for_object(&serde_json::json!({}), &v) {
        bail!("{m}");
    }
    let q: Query = serde_json::from_str(line).context("not a query object")?;
    if let Some(x) = q
        .slip_m
        .iter()
        .find(|x| !(-MAX_SLIP_M..=MAX_SLIP_M).contains(*x))
    {
        bail!("\"slip_m\": {x} m is outside ±{MAX_SLIP_M} m");
    }
    if let Some(x) = q
        .pupil_px
        .iter()
        .flatten()
        .find(|x| !(-MAX_PUPIL_PX..=MAX_PUPIL_PX).contains(*x))
    {
        bail!("\"pupil_px\": {x} px is outside ±{MAX_PUPIL_PX:e} px");
    }
    let sol = match (q.pupil_px, q.mask_png) {
        (Some(px), None) => solver.solve_pixel(px, q.slip_m)?,
        (None, Some(png)) => {
            let path = base.join(png);
            masks.push(path.clone());
            let mask = read_mask_png(&path, grid)?;
            solver.solve_mask_with(mask.as_ref(), q.slip_m, centre)?
        }
        _ => bail!("exactly one of \"pupil_px\" and \"mask_png\" is required"),
    };
    // A gaze is a unit vector: anything else is no answer, not one to print (a zero gaze and
    // a null visual axis were printed with exit 0).
    let unit = |v: [f64; 3]| (v.iter().map(|x| x * x).sum::<f64>() - 1.0).abs() < 1e-6;
    if !unit(sol.gaze) || sol.visual_axis.is_some_and(|v| !unit(v)) {
        bail!("the solver found no gaze for this query (its result is not a unit vector)");
    }
    let mut out = json!({
        "gaze": sol.gaze,
        "pupil_3d_m": sol.pupil_3d_m,
        "pupil_px": sol.pupil_px,
        "fallback": sol.fallback,
    });
    if let Some(v) = sol.visual_axis {
        out["visual_axis"] = json!(v);
    }
    Ok(out)
}

pub fn run(cmd: Cmd) -> Result<()> {
    match cmd {
        Cmd::Solve {
            input,
            rig,
            kappa,
            solver,
            pupil_centre,
            out,
        } => {
            let centre = PupilCentre::parse(&pupil_centre).context("--pupil-centre")?;
            let rig_path = rig;
            let rig = rig::load(rig_path.as_deref())?;
            let solver: Box<dyn GazeSolver> =
                match SolverKind::parse(&solver).context("--solver")? {
                    SolverKind::Sphere => {
                        let s = SphereSolver::new(&rig)?;
                        Box::new(if kappa { s.with_kappa(&rig) } else { s })
                    }
                    SolverKind::Refractive => {
                        let s = RefractiveSolver::new(&rig)?;
                        Box::new(if kappa { s.with_kappa(&rig) } else { s })
                    }
                };
            // The answers replace --out whole: given the query file, the rig or a mask, they
            // would replace it.
            let inputs = [
                ("--input", Some(input.as_path())),
                ("--rig", rig_path.as_deref()),
            ];
            if let Some(o) = &out {
                for (flag, p) in inputs {
                    if p.is_some_and(|p| crate::util::same_file(o, p)) {
                        bail!("--out: '{}' is {flag}; give another path", o.display());
                    }
                }
            }
            // A FIFO blocked; /dev/zero was read as one endless line (an allocation abort).
            let meta = std::fs::metadata(&input)
                .with_context(|| format!("--input: cannot open '{}'", input.display()))?;
            if !meta.is_file() {
                bail!("--input: '{}' is not a regular file", input.display());
            }
            let file = std::fs::File::open(&input)
                .with_context(|| format!("--input: cannot open '{}'", input.display()))?;
            let grid = (rig.camera.height_px, rig.camera.width_px);
            let mut masks = Vec::new();
            // Mask paths are relative to the query file's directory.
            let base = input.parent().unwrap_or(Path::new(".")).to_path_buf();
            let mut lines = Vec::new();
            let mut reader = std::io::BufReader::new(file);
            let mut raw = Vec::new();
            let mut n = 0usize;
            // Lines that are not valid queries, and the first one's error.
            let (mut n_invalid, mut invalid) = (0usize, None::<String>);
            loop {
                raw.clear();
                let read = reader
                    .read_until(b'\n', &mut raw)
                    .with_context(|| format!("--input: read error at line {}", n + 1))?;
                if read == 0 {
                    break;
                }
                n += 1;
                // A bad line answers with an error object and never stops the batch.
                let v = match util::jsonl_line(&raw, n) {
                    Ok(line) if line.trim().is_empty() => continue,
                    Ok(line) => solve_line(solver.as_ref(), centre, line, &base, grid, &mut masks),
                    Err(e) => Err(e),
                }
                .unwrap_or_else(|e| {
                    let msg = format!("line {n}: {e:#}");
                    if !no_solution(&e) {
                        invalid.get_or_insert_with(|| msg.clone());
                        n_invalid += 1;
                    }
                    json!({ "error": msg })
                });
                lines.push(serde_json::to_string(&v)?);
            }
            // An empty or blank file printed one blank line with exit 0.
            if lines.is_empty() {
                bail!(
                    "--input {}: no query lines (the file is empty or blank)",
                    input.display()
                );
            }
            // A file none of whose lines is a query is refused, not answered line by line
            // with exit 0; a line whose ray misses the eye is a query without a gaze.
            if let Some(first) = invalid.filter(|_| n_invalid == lines.len()) {
                bail!(
                    "--input {}: none of its {} query lines is a valid query ({first})",
                    input.display(),
                    lines.len()
                );
            }
            if let (Some(o), Some(m)) = (
                &out,
                masks
                    .iter()
                    .find(|m| out.as_deref().is_some_and(|o| crate::util::same_file(o, m))),
            ) {
                bail!(
                    "--out: '{}' is the mask '{}' of a query; give another path",
                    o.display(),
                    m.display()
                );
            }
            let mut text = lines.join("\n");
            text.push('\n');
            match out {
                Some(p) => util::write_atomic(&p, text.as_bytes()),
                None => {
                    std::io::stdout().write_all(text.as_bytes())?;
                    Ok(())
                }
            }
        }
        Cmd::Bias {
            rig,
            solver_radii_mm,
            steps,
            json,
        } => {
            let rig = rig::load(rig.as_deref())?;
            if steps < 2 {
                bail!("--steps: need at least 2 samples per axis, got {steps}");
            }
            if steps > MAX_GRID_STEPS {
                bail!("--steps: at most {MAX_GRID_STEPS} samples per axis, got {steps}");
            }
            let mut radii = util::parse_list("--solver-radii-mm", &solver_radii_mm)?;
            // Each radius is a sweep of steps² solves: 1000 radii at 4096 steps ran for hours.
            if radii.len() > util::MAX_LIST {
                bail!(
                    "--solver-radii-mm: at most {} radii, got {}",
                    util::MAX_LIST,
                    radii.len()
                );
            }
            // A radius twice is the same sweep twice: its rows were printed twice.
            if let Some(r) = radii
                .iter()
                .enumerate()
                .find_map(|(i, r)| radii[..i].contains(r).then_some(r))
            {
                bail!("--solver-radii-mm: {r} mm is given twice; give each radius once");
            }
            // The rig's true pupil radius is always a row: the zero-bias reference.
            let true_mm = rig.pupil_sphere_radius_m * 1e3;
            if !radii.iter().any(|r| (r - true_mm).abs() < 1e-9) {
                radii.push(true_mm);
                radii.sort_by(f64::total_cmp);
            }
            let grid = GazeGrid::table_s2(steps);
            let reports = radii
                .iter()
                .map(|r| pupil_sphere_bias(&rig, r * 1e-3, &grid))
                .collect::<Result<Vec<_>, _>>()
                .context("--solver-radii-mm")?;
            // A rig whose camera sees the pupil at none of the gazes has no bias to report (a
            // 1×1-pixel camera printed a table of dashes, exit 0), as datagen states refuses it.
            if reports.iter().all(|r| r.in_view == 0) {
                bail!(
                    "--rig: the camera sees the pupil at none of the {} gazes of the sweep \
                     (az −35…45°, el −15…15°); check its pose and image size",
                    steps * steps
                );
            }
            if json {
                return util::print_json(&json!({"reports": reports}));
            }
            println!(
                "true pupil sphere {:.3} mm; gaze grid az −35…45°, el −15…15°, {steps}×{steps}",
                rig.pupil_sphere_radius_m * 1e3
            );
            println!(
                "solver R (mm)  mean (°)  median (°)  p95 (°)  max (°)  in view  hidden  missed"
            );
            for r in &reports {
                let e = r.error_deg;
                let f = |x: Option<f64>| x.map_or("-".to_string(), |v| format!("{v:.3}"));
                println!(
                    "{:>12.3}  {:>8}  {:>10}  {:>7}  {:>7}  {:>7}  {:>6}  {:>6}",
                    r.solver_radius_m * 1e3,
                    f(e.map(|s| s.mean)),
                    f(e.map(|s| s.median)),
                    f(e.map(|s| s.p95)),
                    f(e.map(|s| s.max)),
                    r.in_view,
                    r.hidden,
                    r.missed
                );
            }
            println!(
                "hidden: pupil beyond the sphere's limb as the camera sees it, left out of the statistics"
            );
            Ok(())
        }
    }
}

//! `nanoeye optics …`: PSF stacks of metasurface lenses over depth.

use crate::util::{parse_range, print_json, write_atomic, write_atomic_with};
use anyhow::{Context, Result, bail};
use clap::{Args, Subcommand};
use faer::Mat;
use nanoeye_optics::stats::plane_stats;
use nanoeye_optics::{
    ApertureGrid, AsmPsf, DoubleHelix, FreeForm, Hyperbolic, PhaseMap, PhaseProfile, PsfConfig,
    PsfModel, PsfUsage,
};
use std::path::PathBuf;

/// Optics commands.
#[derive(Subcommand)]
pub enum Cmd {
    /// PSF stack of a lens over depth: DIR/psf.npy [depth, y, x] float32 and DIR/montage.png.
    Psf(PsfArgs),
}

/// Arguments of `nanoeye optics psf`.
#[derive(Args)]
pub struct PsfArgs {
    /// Lens: hyperbolic | double-helix | file:PATH.npy (square phase map in rad on the aperture grid).
    #[arg(long, default_value = "hyperbolic")]
    lens: String,
    /// Source depths in mm, a:b:step or a single value.
    #[arg(long, default_value = "17:26:1.5")]
    depths_mm: String,
    /// Sensor pixel pitch in µm.
    #[arg(long, default_value_t = 3.0)]
    pitch_um: f64,
    /// PSF window width in pixels.
    #[arg(long, default_value_t = 64)]
    window_px: usize,
    /// Aperture diameter in mm.
    #[arg(long, default_value_t = 1.0)]
    aperture_mm: f64,
    /// Aperture sampling pitch in µm (must match a file: phase map's pitch).
    #[arg(long, default_value_t = 1.5)]
    sample_um: f64,
    /// Metasurface-to-sensor distance in mm.
    #[arg(long, default_value_t = 2.0)]
    sensor_mm: f64,
    /// Wavelength in nm.
    #[arg(long, default_value_t = 940.0)]
    wavelength_nm: f64,
    /// Object distance in focus in mm, for the hyperbolic lens only [default: 25].
    #[arg(long)]
    focus_mm: Option<f64>,
    /// Number of annular zones, for the double-helix lens only [default: 4].
    #[arg(long)]
    dh_zones: Option<usize>,
    /// Spectral period L in mm (padding); default aperture + window.
    #[arg(long)]
    period_mm: Option<f64>,
    /// Output directory.
    #[arg(long)]
    out: PathBuf,
    /// Print a JSON summary on stdout.
    #[arg(long)]
    json: bool,
}

/// Runs an optics command.
pub fn run(cmd: Cmd) -> Result<()> {
    match cmd {
        Cmd::Psf(a) => psf(a),
    }
}

/// Largest metasurface-to-sensor distance (m).
const MAX_SENSOR_DISTANCE_M: f64 = 1.0;
/// Largest object distance (m).
pub const MAX_DISTANCE_M: f64 = 1e3;
/// Nearest object distance (m), for `fisher` too: a hundred wavelengths; a point source at
/// 1e-311 m gave a PSF of zeros with exit 0.
pub const MIN_DISTANCE_M: f64 = 1e-4;
/// Smallest metasurface-to-sensor distance (m): ten wavelengths.
const MIN_SENSOR_DISTANCE_M: f64 = 1e-5;
/// Smallest sensor pixel pitch (m), `--base-pitch-um`'s floor: 1e-30 µm gave a PSF of zeros.
const MIN_PITCH_M: f64 = crate::sim::MIN_BASE_PITCH_UM * 1e-6;
/// Largest sensor pixel pitch (m), a rig's bound (1e308 µm printed "inf sub-pixel points").
const MAX_PITCH_M: f64 = nanoeye_gaze::rig::PIXEL_PITCH_RANGE_M.1;
/// Largest aperture (m): a 10 cm metasurface (1e308 mm failed naming --pitch-um).
const MAX_APERTURE_M: f64 = 0.1;
/// Fewest aperture samples across the diameter.
const MIN_APERTURE_SAMPLES: usize = 4;
/// Largest folded grid (samples per period) the PSF model accepts.
const MAX_FOLD: f64 = 16384.0;
/// Largest sub-pixel points per window side the PSF model accepts.
const MAX_SUBPIXEL_POINTS: f64 = 8192.0;

/// Most float32 values of a PSF stack (depth planes × window²): 1 GiB, and the montage holds
/// one byte per value.
const MAX_STACK_VALUES: u128 = 1 << 28;

/// `v · scale` (SI units) when `v` is finite and the product is finite and > 0: a value like
/// 4.9e-324 mm passes a check in mm but is 0 in m.
fn positive(flag: &str, v: f64, scale: f64) -> Result<f64> {
    let si = v * scale;
    // A subnormal SI value has lost its precision and prints as no valid length.
    if v.is_finite() && si.is_normal() && si > 0.0 {
        Ok(si)
    } else {
        bail!(
            "{flag}: must be finite and > 0 (at least {:e} in SI units), got {v}",
            f64::MIN_POSITIVE
        )
    }
}

fn psf(a: PsfArgs) -> Result<()> {
    let lam = positive("--wavelength-nm", a.wavelength_nm, 1e-9)?;
    let s = positive("--sensor-mm", a.sensor_mm, 1e-3)?;
    let d = positive("--aperture-mm", a.aperture_mm, 1e-3)?;
    let dx = positive("--sample-um", a.sample_um, 1e-6)?;
    let pitch = positive("--pitch-um", a.pitch_um, 1e-6)?;
    // A flag that shapes another lens than the one chosen would be ignored: refuse it.
    if a.focus_mm.is_some() && a.lens != "hyperbolic" {
        bail!("--focus-mm: shapes --lens hyperbolic only, not {}", a.lens);
    }
    if a.dh_zones.is_some() && a.lens != "double-helix" {
        bail!(
            "--dh-zones: shapes --lens double-helix only, not {}",
            a.lens
        );
    }
    let zf = positive("--focus-mm", a.focus_mm.unwrap_or(25.0), 1e-3)?;
    if a.window_px == 0 || a.window_px > 1024 {
        bail!("--window-px: must be 1..=1024, got {}", a.window_px);
    }
    let depths: Vec<f64> = parse_range("--depths-mm", &a.depths_mm)?
        .iter()
        .map(|z| z * 1e-3)
        .collect();
    if depths.iter().any(|&z| z <= 0.0) {
        bail!("--depths-mm: depths must be > 0");
    }
    let values = depths.len() as u128 * (a.window_px as u128).pow(2);
    if values > MAX_STACK_VALUES {
        bail!(
            "--depths-mm/--window-px: {} planes of {}×{} pixels is {values} values, more than \
             {MAX_STACK_VALUES} (1 GiB of float32)",
            depths.len(),
            a.window_px,
            a.window_px
        );
    }
    let period = a
        .period_mm
        .map(|p| positive("--period-mm", p, 1e-3))
        .transpose()?;
    if !(MIN_PITCH_M..=MAX_PITCH_M).contains(&pitch) {
        bail!(
            "--pitch-um: must lie in [{}, {}] µm (a sensor pixel), got {:e}",
            crate::sim::MIN_BASE_PITCH_UM,
            MAX_PITCH_M * 1e6,
            a.pitch_um
        );
    }
    if d > MAX_APERTURE_M {
        bail!(
            "--aperture-mm: at most {} mm, got {:e}",
            MAX_APERTURE_M * 1e3,
            a.aperture_mm
        );
    }
    if s < MIN_SENSOR_DISTANCE_M {
        bail!(
            "--sensor-mm: at least {} mm, got {:e}",
            MIN_SENSOR_DISTANCE_M * 1e3,
            a.sensor_mm
        );
    }
    if zf < MIN_DISTANCE_M || depths.iter().any(|&z| z < MIN_DISTANCE_M) {
        bail!(
            "--focus-mm/--depths-mm: object distances must be at least {} mm",
            MIN_DISTANCE_M * 1e3
        );
    }
    if s > MAX_SENSOR_DISTANCE_M {
        bail!(
            "--sensor-mm: at most {} mm, got {:e}",
            MAX_SENSOR_DISTANCE_M * 1e3,
            a.sensor_mm
        );
    }
    if zf > MAX_DISTANCE_M || depths.iter().any(|&z| z > MAX_DISTANCE_M) {
        bail!(
            "--focus-mm/--depths-mm: object distances must be at most {} mm",
            MAX_DISTANCE_M * 1e3
        );
    }
    if !(1e-7..=1e-4).contains(&lam) {
        bail!(
            "--wavelength-nm: must lie in [100, 100000] nm, got {}",
            a.wavelength_nm
        );
    }
    let samples = d / dx;
    if samples.is_nan() || samples < MIN_APERTURE_SAMPLES as f64 {
        bail!(
            "--aperture-mm/--sample-um: the aperture must span at least {MIN_APERTURE_SAMPLES} \
             samples, got {samples:e}"
        );
    }
    if let Some(p) = period {
        if p < d {
            bail!(
                "--period-mm: the period {} mm is smaller than the aperture {} mm (the folded \
                 field would overlap itself)",
                p * 1e3,
                d * 1e3
            );
        }
        // Checked here in f64: the model's own size check works on a saturated integer.
        if (p / dx).is_nan() || p / dx > MAX_FOLD {
            bail!(
                "--period-mm: {:e} samples per period at --sample-um {} is more than {MAX_FOLD}",
                p / dx,
                a.sample_um
            );
        }
    }
    // Sub-pixel points per side the model will use (its default sub-pixel ≤ 0.8 λ s / 2D).
    let sub = pitch / (0.8 * lam * s / (2.0 * d));
    let points = sub * a.window_px as f64;
    if points.is_nan() || points > MAX_SUBPIXEL_POINTS {
        bail!(
            "--pitch-um/--window-px: {:e} sub-pixel points per side is more than \
             {MAX_SUBPIXEL_POINTS} (the sub-pixel is 0.4 λ s / D: --wavelength-nm, --sensor-mm \
             and --aperture-mm set it)",
            sub.ceil() * a.window_px as f64
        );
    }
    let grid = ApertureGrid::new(d, dx).context("--aperture-mm/--sample-um")?;
    let cfg = PsfConfig {
        wavelength_m: lam,
        sensor_distance_m: s,
        pitch_m: pitch,
        window_px: a.window_px,
        period_m: period,
        ..PsfConfig::default()
    };
    // Weighed before the phase map is built: the finest legal sampling needs tens of GiB.
    let need = AsmPsf::memory_bytes(
        &cfg,
        &grid,
        depths.len(),
        rayon::current_num_threads(),
        PsfUsage::Once,
    )
    .context("--sample-um/--pitch-um/--window-px/--period-mm")?;
    crate::util::check_memory(
        "--sample-um/--aperture-mm/--window-px/--period-mm",
        need,
        "give a coarser --sample-um, or a smaller --aperture-mm, --window-px or --period-mm",
    )?;
    let lens = Hyperbolic {
        wavelength_m: lam,
        object_distance_m: zf,
        image_distance_m: s,
    };
    let map: PhaseMap = match a.lens.as_str() {
        "hyperbolic" => lens.phase_map(&grid)?,
        "double-helix" => {
            let dh = DoubleHelix {
                lens: Hyperbolic {
                    wavelength_m: lam,
                    image_distance_m: s,
                    ..DoubleHelix::default().lens
                },
                zones: a.dh_zones.unwrap_or(DoubleHelix::default().zones),
            };
            dh.phase_map(&grid).context("--dh-zones")?
        }
        other => match other.strip_prefix("file:") {
            Some(path) => {
                let phase = nanoeye_optics::io::read_phase_npy(std::path::Path::new(path))
                    .with_context(|| format!("--lens: cannot read '{path}'"))?;
                let ff = FreeForm {
                    map: PhaseMap::phase_only(
                        ApertureGrid {
                            n: phase.nrows(),
                            ..grid
                        },
                        phase,
                    )?,
                };
                // An NPY map carries no pitch: it is read at --sample-um, so the library's
                // message (both pitches, the same number) would say nothing; the sizes do.
                ff.phase_map(&grid).map_err(|_| {
                    anyhow::anyhow!(
                        "--lens: '{path}' is a {0}×{0} map; --aperture-mm {1} at --sample-um \
                         {2} needs {3}×{3} samples (an NPY phase map has no pitch of its own: \
                         give the --aperture-mm/--sample-um it was made with, or resample it)",
                        ff.map.grid.n,
                        a.aperture_mm,
                        a.sample_um,
                        grid.n
                    )
                })?
            }
            None => {
                bail!("--lens: expected hyperbolic, double-helix or file:PATH.npy, got '{other}'")
            }
        },
    };
    let model = AsmPsf::new(cfg, grid).context("--sample-um/--pitch-um/--window-px/--period-mm")?;
    let w = crate::dist::world();
    let (stack, timing) = if w.is_distributed() {
        psf_distributed(&model, &map, &depths, w)?
    } else {
        (model.forward(&map, &depths, None)?, serde_json::Value::Null)
    };
    // Every rank holds the whole stack (the AllGather); rank 0 writes it.
    if !w.is_root() {
        return Ok(());
    }
    if let Some(k) = stack
        .planes
        .iter()
        .position(|p| p.col_iter().any(|c| c.iter().any(|v| !v.is_finite())))
    {
        bail!(
            "the PSF at depth {} mm is not finite: --aperture-mm/--sample-um/--sensor-mm/\
             --pitch-um lie outside the model's numerically valid range",
            stack.depths_m[k] * 1e3
        );
    }
    let montage_png = montage(&stack.planes)?;
    for name in ["psf.npy", "montage.png"] {
        crate::util::check_output_target(&a.out.join(name)).context("--out")?;
    }
    // An output replacing the lens it was computed from (a file: lens at OUT/psf.npy).
    if let Some(f) = a.lens.strip_prefix("file:") {
        for name in ["psf.npy", "montage.png"] {
            if crate::util::same_file(&a.out.join(name), std::path::Path::new(f)) {
                bail!("--out: its {name} is --lens {}; give another --out", a.lens);
            }
        }
    }
    std::fs::create_dir_all(&a.out)
        .with_context(|| format!("--out: cannot create '{}'", a.out.display()))?;
    write_atomic_with(&a.out.join("psf.npy"), |w| {
        nanoeye_optics::io::write_stack_npy(&stack, w).map_err(Into::into)
    })?;
    write_atomic(&a.out.join("montage.png"), &montage_png)?;
    if a.json {
        let planes: Vec<serde_json::Value> = stack
            .planes
            .iter()
            .zip(&stack.depths_m)
            .map(|(p, &z)| {
                let st = plane_stats(p);
                serde_json::json!({
                    "depth_m": z, "energy": st.energy, "peak": st.peak,
                    "centroid_px": st.centroid_px, "rms_radius_px": st.rms_radius_px,
                })
            })
            .collect();
        let mut v = serde_json::json!({
            "pitch_m": stack.pitch_m, "depths_m": stack.depths_m, "planes": planes,
        });
        if !timing.is_null() {
            v["mpi"] = timing;
        }
        print_json(&v)?;
    }
    Ok(())
}

/// The stack over MPI ranks: rank r computes depths k ≡ r (mod ranks), and the planes are
/// all-gathered into the stack one process computes (each plane depends on its depth only).
/// With the stack, the timing: each rank's seconds on its planes, and the AllGather's.
fn psf_distributed(
    model: &AsmPsf,
    map: &PhaseMap,
    depths: &[f64],
    w: crate::dist::World,
) -> Result<(nanoeye_optics::PsfStack, serde_json::Value)> {
    use crate::dist::{bytes_f64, f64_bytes, frame, round_robin, unframe};
    let mine = round_robin(depths.len(), w);
    let active: Vec<bool> = (0..depths.len()).map(|k| mine.contains(&k)).collect();
    let t0 = std::time::Instant::now();
    let own = model.planes_f64(map, depths, Some(&active))?;
    let own_s = t0.elapsed().as_secs_f64();
    let n = model.config().window_px;
    let parts: Vec<Vec<u8>> = mine
        .iter()
        .filter_map(|&k| {
            let p = own[k].as_ref()?;
            // Column-major, as faer stores it.
            let flat: Vec<f64> = (0..n)
                .flat_map(|j| (0..n).map(move |i| p[(i, j)]))
                .collect();
            let mut bytes = (k as u64).to_le_bytes().to_vec();
            bytes.extend(f64_bytes(&flat));
            Some(bytes)
        })
        .collect();
    let mut planes: Vec<Option<Mat<f64>>> = vec![None; depths.len()];
    // Wait for the slowest rank first, so the time below is the transfer's alone.
    w.barrier();
    let t1 = std::time::Instant::now();
    let gathered = w.all_gather(frame(&parts));
    let gather_s = t1.elapsed().as_secs_f64();
    let rank_s: Vec<f64> = w
        .all_gather(own_s.to_le_bytes().to_vec())
        .iter()
        .flat_map(|b| bytes_f64(b))
        .collect();
    for rank_bytes in gathered {
        for part in unframe(&rank_bytes) {
            let (head, body) = part.split_at(8.min(part.len()));
            let k = u64::from_le_bytes(head.try_into().unwrap_or([0xff; 8])) as usize;
            let v = bytes_f64(body);
            if k < depths.len() && v.len() == n * n {
                planes[k] = Some(Mat::from_fn(n, n, |i, j| v[j * n + i]));
            }
        }
    }
    if let Some(k) = planes.iter().position(Option::is_none) {
        bail!(
            "the PSF at depth {} mm did not arrive from its rank",
            depths[k] * 1e3
        );
    }
    let timing = serde_json::json!({
        "ranks": w.size(), "plane_seconds": rank_s, "allgather_seconds": gather_s,
    });
    Ok((
        nanoeye_optics::PsfStack::from_planes(depths, model.config().pitch_m, n, &planes),
        timing,
    ))
}

/// One tile per depth, left to right, each scaled to its own peak (as in Fig. S10), as PNG.
fn montage(planes: &[Mat<f32>]) -> Result<Vec<u8>> {
    let w = planes.first().map_or(0, |p| p.ncols());
    let h = planes.first().map_or(0, |p| p.nrows());
    let gap = 2;
    let width = (planes.len() * (w + gap)).saturating_sub(gap).max(1);
    let mut img = image::GrayImage::new(width as u32, h.max(1) as u32);
    for (k, p) in planes.iter().enumerate() {
        let peak = plane_stats(p).peak.max(f64::MIN_POSITIVE) as f32;
        for i in 0..h {
            for j in 0..w {
                let v = (p[(i, j)] / peak).clamp(0.0, 1.0).sqrt();
                img.put_pixel(
                    (k * (w + gap) + j) as u32,
                    i as u32,
                    image::Luma([(v * 255.0).round() as u8]),
                );
            }
        }
    }
    let mut bytes = Vec::new();
    img.write_to(
        &mut std::io::Cursor::new(&mut bytes),
        image::ImageFormat::Png,
    )?;
    Ok(bytes)
}

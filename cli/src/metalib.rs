//! `nanoeye metalib …`: RCWA unit cell, design sweep, candidate selection, blueprint.

use anyhow::{Context, Result, anyhow, bail};
use clap::{Args, Subcommand};
use nanoeye_metalib::blueprint::{self, BlueprintOptions};
use nanoeye_metalib::dispersion;
use nanoeye_metalib::library::{PillarLibrary, TabulatedLibrary};
use nanoeye_metalib::material::{
    A_SI_K_940, A_SI_N_940, DEFAULT_WAVELENGTH_M, FUSED_SILICA_N_940, MAX_INDEX, MIN_INDEX,
    Materials,
};
use nanoeye_metalib::rcwa::{
    CellSpec, DEFAULT_HARMONICS, DEFAULT_RULE, LayerModes, Rule, WAVELENGTH_RANGE_M,
};
use nanoeye_metalib::select::{self, Criteria};
use nanoeye_metalib::sweep::{self, Range, SweepConfig};
use std::path::PathBuf;

/// Nanopillar library: RCWA cell, sweep, selection, blueprint.
#[derive(Subcommand)]
pub enum MetalibCmd {
    /// Solve one unit cell (zero-order t, τ, R, phase).
    Cell(CellArgs),
    /// Run (or resume) the (height, pitch, diameter) sweep.
    Sweep(SweepArgs),
    /// Apply the D.1 selection criteria to a sweep and draw Fig. S4/S5.
    Select(SelectArgs),
    /// Phase map (NPY) → diameter map, GDSII, preview PNG, RMS phase error.
    Blueprint(BlueprintArgs),
    /// Issue 19 study: is (700 nm, 530 nm) viable for which pillar n + ik, under which criteria.
    MaterialStudy(StudyArgs),
}

/// Material and solver flags shared by the commands.
#[derive(Args, Clone)]
pub struct SolverArgs {
    /// Fourier orders −N..N per direction.
    #[arg(long, default_value_t = DEFAULT_HARMONICS)]
    harmonics: usize,
    /// Factorisation rule: laurent | nv.
    #[arg(long, default_value = DEFAULT_RULE.name())]
    rule: String,
    /// Tabulated pillar material (n, k interpolated at the wavelength): pierce-spicer-1972,
    /// franta-2013-asih, karaman-2025-asi, green-2008-csi, sputtered-2020-asi,
    /// sputtered-2020-asih;
    /// --n-pillar/--k-pillar, when given, override its n/k.
    #[arg(long)]
    material: Option<String>,
    /// Pillar refractive index (real part); default a-Si (Pierce & Spicer 1972).
    #[arg(long)]
    n_pillar: Option<f64>,
    /// Pillar extinction coefficient.
    #[arg(long)]
    k_pillar: Option<f64>,
    /// Substrate index; default fused silica 1.4512.
    #[arg(long)]
    n_substrate: Option<f64>,
    /// Index around the pillars inside the layer (default air).
    #[arg(long)]
    n_background: Option<f64>,
    /// Wavelength in nm.
    #[arg(long, default_value_t = DEFAULT_WAVELENGTH_M * 1e9)]
    wavelength_nm: f64,
}

impl SolverArgs {
    /// The named material's table, if `--material` was given (unknown names list the known).
    fn material_table(&self) -> Result<Option<&'static dispersion::DispersionTable>> {
        self.material
            .as_deref()
            .map(|name| {
                dispersion::by_name(name).map_err(|e| anyhow!("--{}", flagify(&e.to_string())))
            })
            .transpose()
    }
    fn materials(&self) -> Result<Materials> {
        // The default pillar index is a-Si's at 940 nm: at another wavelength it was used as
        // it is (n 3.7, k 0.008 at 100 nm and at 5000 nm, exit 0; a helper's audit).
        self.wavelength_m()?;
        let at_default = (self.wavelength_nm - DEFAULT_WAVELENGTH_M * 1e9).abs() <= 1e-9;
        if !at_default
            && self.material.is_none()
            && (self.n_pillar.is_none() || self.k_pillar.is_none())
        {
            bail!(
                "--wavelength-nm: the default pillar index (a-Si: n {A_SI_N_940}, k {A_SI_K_940}) \
                 is the one at {} nm; at {} nm name a --material tabulated there, or give \
                 --n-pillar and --k-pillar (the substrate is fused silica's {FUSED_SILICA_N_940} \
                 at 940 nm unless --n-substrate)",
                DEFAULT_WAVELENGTH_M * 1e9,
                self.wavelength_nm
            );
        }
        let mut m = Materials::default();
        if let Some(t) = self.material_table()? {
            let (n, k) = t.nk_at(self.wavelength_m()?).map_err(|_| {
                let (lo, hi) = t.range_m();
                anyhow!(
                    "--material: `{}` is tabulated over {:.1}–{:.1} nm; --wavelength-nm {} lies outside",
                    t.name,
                    lo * 1e9,
                    hi * 1e9,
                    self.wavelength_nm
                )
            })?;
            m.n_pillar = n;
            m.k_pillar = k;
        }
        if let Some(v) = self.n_pillar {
            m.n_pillar = v;
        }
        if let Some(v) = self.k_pillar {
            m.k_pillar = v;
        }
        if let Some(v) = self.n_substrate {
            m.n_substrate = v;
        }
        if let Some(v) = self.n_background {
            m.n_background = v;
        }
        m.validate()
            .map_err(|e| anyhow!("--{}", flagify(&e.to_string())))?;
        Ok(m)
    }
    /// Refuses a solver flag given against the sweep at `dir` whose settings `cfg` are: a
    /// command that reads a sweep's cells solves nothing, so `--harmonics 5` or `--material X`
    /// beside `--sweep` were ignored and the output was the sweep's (a helper's audit). A
    /// value-typed flag counts as given where it is not its default.
    fn against_sweep(&self, dir: &std::path::Path, cfg: &SweepConfig) -> Result<()> {
        let m = &cfg.materials;
        let differs = |given: Option<f64>, had: f64| given.is_some_and(|v| v != had);
        let wl_nm = cfg.wavelength_m * 1e9;
        let clashes = [
            (
                "--harmonics",
                self.harmonics != DEFAULT_HARMONICS && self.harmonics != cfg.harmonics,
                cfg.harmonics.to_string(),
            ),
            (
                "--rule",
                self.rule != DEFAULT_RULE.name() && self.rule()? != cfg.rule,
                cfg.rule.name().to_string(),
            ),
            (
                "--wavelength-nm",
                (self.wavelength_nm - DEFAULT_WAVELENGTH_M * 1e9).abs() > 1e-9
                    && (self.wavelength_nm - wl_nm).abs() > 1e-6,
                format!("{wl_nm}"),
            ),
            (
                "--material",
                self.material.is_some() && self.material != cfg.material,
                cfg.material.clone().unwrap_or_else(|| "none".into()),
            ),
            (
                "--n-pillar",
                differs(self.n_pillar, m.n_pillar),
                m.n_pillar.to_string(),
            ),
            (
                "--k-pillar",
                differs(self.k_pillar, m.k_pillar),
                m.k_pillar.to_string(),
            ),
            (
                "--n-substrate",
                differs(self.n_substrate, m.n_substrate),
                m.n_substrate.to_string(),
            ),
            (
                "--n-background",
                differs(self.n_background, m.n_background),
                m.n_background.to_string(),
            ),
        ];
        if let Some((flag, _, had)) = clashes.into_iter().find(|c| c.1) {
            bail!(
                "{flag}: the sweep in {} was solved with {had}; a blueprint from a sweep reads \
                 its cells and solves nothing — drop {flag}, or run a sweep with it",
                dir.display()
            );
        }
        Ok(())
    }
    fn rule(&self) -> Result<Rule> {
        self.rule.parse().map_err(|e| anyhow!("--rule: {e}"))
    }
    fn wavelength_m(&self) -> Result<f64> {
        let (lo, hi) = WAVELENGTH_RANGE_M;
        let m = self.wavelength_nm * 1e-9;
        if !(self.wavelength_nm.is_finite() && (lo..=hi).contains(&m)) {
            bail!(
                "--wavelength-nm: must lie in [{}, {}] nm (the solver's valid range), got {}",
                lo * 1e9,
                hi * 1e9,
                self.wavelength_nm
            );
        }
        Ok(m)
    }
}

/// Names the flag of a cell error: "invalid parameter `pitch`: …" becomes "--pitch-nm: …"; a
/// numerical breakdown names the flags that set the problem.
fn cell_flags(msg: &str) -> String {
    const FLAGS: [(&str, &str); 4] = [
        ("wavelength", "--wavelength-nm"),
        ("pitch", "--pitch-nm"),
        ("diameter", "--diameter-nm"),
        ("height", "--height-nm"),
    ];
    for (name, flag) in FLAGS {
        if let Some(rest) = msg.strip_prefix(&format!("invalid parameter `{name}`: ")) {
            // "diameter … exceeds the pitch …": both flags set the limit.
            let mut flags = vec![flag];
            flags.extend(
                FLAGS
                    .iter()
                    .filter(|(n, f)| *f != flag && rest.contains(n))
                    .map(|(_, f)| *f),
            );
            return format!("{}: {rest}", flags.join("/"));
        }
    }
    if let Some(rest) = msg.strip_prefix("numerical failure: ") {
        return format!(
            "--wavelength-nm/--pitch-nm/--diameter-nm/--harmonics or the materials (--n-pillar, \
             --k-pillar, --n-background, --n-substrate): {rest}"
        );
    }
    format!("--{}", flagify(msg))
}

/// Names the flag of a sweep grid error: "invalid parameter `fractions`: …" becomes
/// "--fractions: …"; the representative cell's `pitch` and `diameter` are the pitch and
/// fraction axes.
fn sweep_flags(msg: &str) -> String {
    for (name, flag) in [
        ("heights", "--heights-nm"),
        ("pitches", "--pitches-nm"),
        ("pitch", "--pitches-nm"),
        ("fractions", "--fractions"),
        ("diameter", "--fractions"),
        ("wavelength", "--wavelength-nm"),
    ] {
        if let Some(rest) = msg.strip_prefix(&format!("invalid parameter `{name}`: ")) {
            // "pitch … exceeds 20 wavelengths": the wavelength sets the limit too.
            return if rest.contains("wavelength") && flag != "--wavelength-nm" {
                format!("{flag}/--wavelength-nm: {rest}")
            } else {
                format!("{flag}: {rest}")
            };
        }
    }
    format!("--{}", flagify(msg))
}

/// A blueprint error with the flag that sets its parameter in front.
fn blueprint_flag(e: nanoeye_metalib::MetalibError) -> anyhow::Error {
    let flag = match &e {
        nanoeye_metalib::MetalibError::InvalidParameter { name, .. } => match *name {
            "diameter_step" => "--diameter-step-nm",
            "circle_vertices" => "--circle-vertices",
            "library" => "--pitch-nm (or the library: --library-csv / --sweep)",
            _ => "--phase",
        },
        _ => "--phase",
    };
    anyhow!("{flag}: {e}")
}

/// Turns "invalid parameter `n_pillar`: …" into "n-pillar: …" for flag-named messages.
fn flagify(msg: &str) -> String {
    msg.replace("invalid parameter `", "")
        .replacen("`:", ":", 1)
        .replace('_', "-")
}

#[derive(Args)]
pub struct CellArgs {
    /// Pillar height in nm.
    #[arg(long)]
    height_nm: f64,
    /// Lattice pitch in nm.
    #[arg(long)]
    pitch_nm: f64,
    /// Pillar diameter in nm.
    #[arg(long)]
    diameter_nm: f64,
    #[command(flatten)]
    solver: SolverArgs,
    /// Print JSON.
    #[arg(long)]
    json: bool,
}

#[derive(Args)]
pub struct SweepArgs {
    /// Output directory (resumes a matching interrupted sweep).
    #[arg(long, required_unless_present = "plan_ranks")]
    out: Option<PathBuf>,
    /// Heights a:b:step in nm.
    #[arg(long, default_value = "100:1500:10")]
    heights_nm: String,
    /// Pitches a:b:step in nm.
    #[arg(long, default_value = "100:1000:10")]
    pitches_nm: String,
    /// Diameter fractions of the pitch a:b:step.
    #[arg(long, default_value = "0.10:0.90:0.005")]
    fractions: String,
    #[command(flatten)]
    solver: SolverArgs,
    /// Print the manifest as JSON.
    #[arg(long)]
    json: bool,
    /// Print the pitches each of N processes would solve (`mpirun -np N`) and the share
    /// imbalance (largest share's cost over the mean), then exit without solving.
    #[arg(long)]
    plan_ranks: Option<usize>,
}

#[derive(Args)]
pub struct SelectArgs {
    /// Sweep directory.
    #[arg(long)]
    sweep: PathBuf,
    /// Where to write the figures (default: <sweep>/figures).
    #[arg(long)]
    figures: Option<PathBuf>,
    /// Height (nm) of the pair marked in the figures, one of the sweep's heights [default:
    /// 700, or the sweep's nearest height].
    #[arg(long)]
    mark_height_nm: Option<f64>,
    /// Pitch (nm) of the marked pair and of the Fig. S5 curves, one of the sweep's pitches
    /// [default: 530, or the sweep's nearest pitch].
    #[arg(long)]
    mark_pitch_nm: Option<f64>,
    /// Print JSON.
    #[arg(long)]
    json: bool,
}

#[derive(Args)]
pub struct BlueprintArgs {
    /// Phase map (NPY, 2-D, radians, one value per lattice site; NaN = no pillar).
    #[arg(long)]
    phase: PathBuf,
    /// Pillar height in nm.
    #[arg(long)]
    height_nm: f64,
    /// Lattice pitch in nm.
    #[arg(long)]
    pitch_nm: f64,
    /// Output directory.
    #[arg(long)]
    out: PathBuf,
    /// Sweep directory holding (height, pitch); if absent, the library is computed directly.
    #[arg(long, conflicts_with = "library_csv")]
    sweep: Option<PathBuf>,
    /// User library CSV `diameter_nm,phase_rad,transmittance` instead of a sweep.
    #[arg(long)]
    library_csv: Option<PathBuf>,
    /// Fabrication diameter grid in nm (0 = continuous).
    #[arg(long, default_value_t = 1.0)]
    diameter_step_nm: f64,
    /// Vertices per GDSII circle.
    #[arg(long, default_value_t = blueprint::DEFAULT_CIRCLE_VERTICES)]
    circle_vertices: usize,
    /// Use the whole map instead of the inscribed circular aperture.
    #[arg(long)]
    square_aperture: bool,
    #[command(flatten)]
    solver: SolverArgs,
    /// Print JSON.
    #[arg(long)]
    json: bool,
}

#[derive(Args)]
pub struct StudyArgs {
    /// Lattice pitch in nm.
    #[arg(long, default_value_t = 530.0)]
    pitch_nm: f64,
    /// Height in nm whose viability is reported (must lie on --heights-nm).
    #[arg(long, default_value_t = 700.0)]
    height_nm: f64,
    /// Heights a:b:step in nm also evaluated (free: the same eigen-solves).
    #[arg(long, default_value = "500:900:10")]
    heights_nm: String,
    /// Diameter fractions of the pitch a:b:step.
    #[arg(long, default_value = "0.10:0.90:0.005")]
    fractions: String,
    /// Grid of pillar n, a:b:step.
    #[arg(long, default_value = "3.0:4.0:0.1")]
    n_values: String,
    /// Grid of pillar k, comma-separated.
    #[arg(long, default_value = "0,0.002,0.005,0.01")]
    k_values: String,
    /// Named materials, comma-separated, `all` or `none`.
    #[arg(long, default_value = "all")]
    materials: String,
    /// Fourier orders −N..N per direction (docs/metalib.md: N = 6 is 9× cheaper but flips
    /// verdicts near the thresholds).
    #[arg(long, default_value_t = DEFAULT_HARMONICS)]
    harmonics: usize,
    /// Factorisation rule: laurent | nv.
    #[arg(long, default_value = DEFAULT_RULE.name())]
    rule: String,
    /// Wavelength in nm.
    #[arg(long, default_value_t = DEFAULT_WAVELENGTH_M * 1e9)]
    wavelength_nm: f64,
    /// Print JSON.
    #[arg(long)]
    json: bool,
}

/// Runs one `metalib` subcommand.
pub fn run(cmd: MetalibCmd) -> Result<()> {
    match cmd {
        MetalibCmd::Cell(a) => cell(a),
        MetalibCmd::Sweep(a) => sweep_cmd(a),
        MetalibCmd::Select(a) => select_cmd(a),
        MetalibCmd::Blueprint(a) => blueprint_cmd(a),
        MetalibCmd::MaterialStudy(a) => study_cmd(a),
    }
}

/// `--height-nm` in metres, finite and at most [`sweep::MAX_HEIGHT_M`].
fn height_m(height_nm: f64) -> Result<f64> {
    let h = nm("--height-nm", height_nm)?;
    if h > sweep::MAX_HEIGHT_M {
        bail!(
            "--height-nm: must be at most {:e} nm, got {height_nm:?}",
            sweep::MAX_HEIGHT_M * 1e9
        );
    }
    Ok(h)
}

fn nm(flag: &str, v: f64) -> Result<f64> {
    if !v.is_finite() {
        bail!("{flag} must be finite, got {v}");
    }
    Ok(v * 1e-9)
}

/// Refuses `solves` RCWA solves at once at `harmonics` orders that would need more memory than
/// the process may use, naming --harmonics: the allowed 40 orders took 4.5 GB a solve, and an
/// allocation failure inside the eigen-solver panicked. Peak per solve: 128 B per (2N+1)⁴ plus
/// 32 MiB, above the peaks of `metalib cell` (release, /usr/bin/time: N = 10, 20, 25, 30 →
/// 36, 300, 683 MB, 1.43 GB, ≈ 30 MB + 100 B·(2N+1)⁴); a sweep on two threads at N = 20
/// peaked at 570 MB.
fn check_rcwa_memory(harmonics: usize, solves: usize) -> Result<()> {
    // Saturating: a count of 1.7e19 (the property test's) overflowed; such a count is refused
    // here, naming the flag, before the solver's own bound of 40.
    let orders = (harmonics as u64)
        .saturating_mul(2)
        .saturating_add(1)
        .saturating_pow(4);
    let one = orders.saturating_mul(128).saturating_add(32 << 20);
    crate::util::check_memory(
        "--harmonics",
        one.saturating_mul(solves as u64),
        "give fewer --harmonics",
    )
}

fn cell(a: CellArgs) -> Result<()> {
    let spec = CellSpec {
        wavelength_m: a.solver.wavelength_m()?,
        pitch_m: nm("--pitch-nm", a.pitch_nm)?,
        diameter_m: nm("--diameter-nm", a.diameter_nm)?,
        materials: a.solver.materials()?,
        harmonics: a.solver.harmonics,
        rule: a.solver.rule()?,
    };
    let h = height_m(a.height_nm)?;
    if h < 0.0 {
        bail!("--height-nm: must be >= 0, got {:?}", a.height_nm);
    }
    check_rcwa_memory(spec.harmonics, 1)?;
    let r = LayerModes::new(&spec)
        .map_err(|e| anyhow!("{}", cell_flags(&e.to_string())))?
        .at_height(h)
        .map_err(|e| anyhow!("{}", cell_flags(&e.to_string())))?;
    if a.json {
        let v = serde_json::json!({
            "t_re": r.t.re, "t_im": r.t.im, "transmittance": r.transmittance,
            "reflectance": r.reflectance, "transmitted_total": r.transmitted_total,
            "phase_rad": r.phase_rad, "harmonics": spec.harmonics, "rule": spec.rule.name(),
            "n_pillar": spec.materials.n_pillar, "k_pillar": spec.materials.k_pillar,
        });
        // `material` only when one was named (never a null).
        let mut v = v;
        if let Some(m) = &a.solver.material {
            v["material"] = serde_json::json!(m);
        }
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        println!(
            "t = {:.6}{:+.6}i  τ = {:.6}  R = {:.6}  T_total = {:.6}  phase = {:.6} rad  (N = {}, rule {})",
            r.t.re,
            r.t.im,
            r.transmittance,
            r.reflectance,
            r.transmitted_total,
            r.phase_rad,
            spec.harmonics,
            spec.rule.name()
        );
    }
    Ok(())
}

fn range(flag: &str, text: &str, scale: f64) -> Result<Range> {
    let p: Vec<&str> = text.split(':').collect();
    if p.len() != 3 {
        bail!("{flag}: expected a:b:step, got `{text}`");
    }
    let f = |s: &str| {
        s.trim()
            .parse::<f64>()
            .map_err(|_| anyhow!("{flag}: `{s}` is not a number"))
    };
    let r = Range {
        start: f(p[0])? * scale,
        stop: f(p[1])? * scale,
        step: f(p[2])? * scale,
    };
    r.values("range").map_err(|e| anyhow!("{flag}: {e}"))?;
    Ok(r)
}

fn sweep_cmd(a: SweepArgs) -> Result<()> {
    let config = SweepConfig {
        heights_m: range("--heights-nm", &a.heights_nm, 1e-9)?,
        pitches_m: range("--pitches-nm", &a.pitches_nm, 1e-9)?,
        fractions: range("--fractions", &a.fractions, 1.0)?,
        wavelength_m: a.solver.wavelength_m()?,
        materials: a.solver.materials()?,
        harmonics: a.solver.harmonics,
        rule: a.solver.rule()?,
        material: a.solver.material.clone(),
    };
    // The whole grid is checked before planning or solving, naming the flags (the sweep's own
    // check reported a bad axis as an --out error, and --plan-ranks by its parameter name).
    sweep::sweep_grid(&config).map_err(|e| anyhow!("{}", sweep_flags(&e.to_string())))?;
    check_rcwa_memory(config.harmonics, rayon::current_num_threads())?;
    let out = match (a.plan_ranks, &a.out) {
        (Some(n), _) => return plan_cmd(&config, n),
        (None, Some(out)) => out.clone(),
        (None, None) => bail!("--out: required"),
    };
    // Temporary files of a killed run (partial/ is written by the metalib crate only).
    crate::util::remove_stale_temps_under(&out);
    let t0 = std::time::Instant::now();
    let w = crate::dist::world();
    let m = if w.is_distributed() {
        sweep_distributed(&config, &out, w)
    } else {
        sweep::run_sweep_with_progress(&config, &out)
            .map(|m| Some((m, serde_json::Value::Null)))
            .map_err(Into::into)
    }
    .with_context(|| format!("--out {}", out.display()))?;
    // Rank 0 prints; the other ranks are done.
    let Some((m, timing)) = m else {
        return Ok(());
    };
    let secs = t0.elapsed().as_secs_f64();
    let cells = m.shape.iter().product::<usize>();
    if a.json {
        let mut v = serde_json::to_value(&m)?;
        v["seconds"] = serde_json::json!(secs);
        if !timing.is_null() {
            v["mpi"] = timing;
        }
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        println!(
            "{cells} cells ({:?}) in {secs:.1} s, {} failed → {}",
            m.shape,
            m.failed_cells,
            out.display()
        );
    }
    Ok(())
}

/// `--plan-ranks N`: the shares N processes would get, and their balance, without solving.
fn plan_cmd(config: &SweepConfig, n: usize) -> Result<()> {
    if n == 0 || n > 1_000_000 {
        bail!("--plan-ranks: must be 1..=1000000, got {n}");
    }
    let grid = sweep::sweep_grid(config)?;
    let shares = sweep::plan_shares(&grid, n);
    let pitches: Vec<Vec<f64>> = shares
        .iter()
        .map(|s| {
            s.iter()
                .map(|&i| (grid.pitches_m[i] * 1e9).round())
                .collect()
        })
        .collect();
    let v = serde_json::json!({
        "ranks": n,
        "imbalance": sweep::share_imbalance(&grid, &shares),
        "pitches_nm": pitches,
    });
    println!("{}", serde_json::to_string(&v)?);
    Ok(())
}

/// The sweep over MPI ranks: rank 0 opens the directory, each rank solves (or restores) its
/// load-balanced share of pitches, checkpointing every block, and rank 0 gathers the blocks
/// and writes the same files a single process writes. On rank 0 the manifest and the timing
/// (seconds each rank spent on its share, and in the gather and the writing), None elsewhere.
fn sweep_distributed(
    config: &SweepConfig,
    dir: &std::path::Path,
    w: crate::dist::World,
) -> Result<Option<(sweep::Manifest, serde_json::Value)>> {
    use crate::dist::{bytes_f64, f64_bytes, frame, unframe};
    let grid = sweep::sweep_grid(config)?;
    // A finished sweep is returned as it stands; rank 0 tells every rank so, and they stop.
    let done = w
        .is_root()
        .then(|| sweep::completed_sweep(config, dir))
        .flatten();
    if w.broadcast(vec![u8::from(done.is_some())]) == [1] {
        return Ok(done.map(|m| (m, serde_json::Value::Null)));
    }
    // Rank 0 refuses another sweep's directory before anyone computes; a refusal ends the
    // run there (the others wait in the broadcast).
    if w.is_root() {
        sweep::open_sweep(config, dir)?;
    }
    w.broadcast(Vec::new());
    let shares = sweep::plan_shares(&grid, w.size());
    let mine = &shares[w.rank()];
    let cells = (mine.len() * grid.heights_m.len() * grid.fractions.len()) as u64;
    // Rank 0 reports its own share's progress; the others stay quiet.
    let total = if w.is_root() { cells } else { 0 };
    let t_share = std::time::Instant::now();
    let blocks = sweep::with_progress(total, |report| {
        sweep::solve_share(config, dir, mine, report)
    })?;
    let share_s = t_share.elapsed().as_secs_f64();
    let shares_s = w.gather(share_s.to_le_bytes().to_vec());
    // Every rank is done here, so the time below is the transfer's and the writing's alone.
    w.barrier();
    let t_gather = std::time::Instant::now();
    let parts: Vec<Vec<u8>> = blocks
        .iter()
        .map(|(is, b)| {
            let flat: Vec<f64> = b.iter().flatten().copied().collect();
            let mut bytes = (*is as u64).to_le_bytes().to_vec();
            bytes.extend(f64_bytes(&flat));
            bytes
        })
        .collect();
    let gathered = w.gather(frame(&parts));
    let manifest = match gathered {
        Some(all) => {
            let mut blocks = Vec::new();
            for rank_bytes in all {
                for part in unframe(&rank_bytes) {
                    let (head, body) = part.split_at(8.min(part.len()));
                    let is = u64::from_le_bytes(head.try_into().unwrap_or([0xff; 8])) as usize;
                    let block: Vec<[f64; 4]> = bytes_f64(body)
                        .chunks_exact(4)
                        .map(|c| [c[0], c[1], c[2], c[3]])
                        .collect();
                    blocks.push((is, block));
                }
            }
            let gather_s = t_gather.elapsed().as_secs_f64();
            let m = sweep::finish_sweep(config, dir, blocks)?;
            let rank_s: Vec<f64> = shares_s
                .unwrap_or_default()
                .iter()
                .flat_map(|b| crate::dist::bytes_f64(b))
                .collect();
            let timing = serde_json::json!({
                "ranks": w.size(),
                "share_seconds": rank_s,
                "gather_seconds": gather_s,
                "write_seconds": t_gather.elapsed().as_secs_f64() - gather_s,
            });
            Some((m, timing))
        }
        None => None,
    };
    w.barrier();
    if !w.is_root() {
        // Without a shared filesystem this rank's checkpoints are its own; they are in the
        // arrays now (on a shared one, rank 0 already removed them).
        for &is in mine {
            for ext in ["bin", "fnv"] {
                let _ = std::fs::remove_file(dir.join(format!("partial/pitch_{is:04}.{ext}")));
            }
        }
        let _ = std::fs::remove_dir(dir.join("partial"));
    }
    Ok(manifest)
}

/// The sweep value (nm) a mark flag names: `given` when it is one of `grid_m` (to 1e-6
/// relative), else refused naming `flag`; without it, the grid value nearest `default_nm`.
fn on_sweep_grid(flag: &str, given: Option<f64>, default_nm: f64, grid_m: &[f64]) -> Result<f64> {
    let nm: Vec<f64> = grid_m.iter().map(|v| v * 1e9).collect();
    let target = given.unwrap_or(default_nm);
    let Some(nearest) = nm
        .iter()
        .copied()
        .min_by(|a, b| (a - target).abs().total_cmp(&(b - target).abs()))
    else {
        bail!("--sweep: the sweep has no {flag} values");
    };
    if given.is_some() && (nearest - target).abs() > 1e-6 * target {
        // To the picometre: the grid's values in nm carry the metre's rounding.
        let pm = |x: f64| (x * 1e3).round() / 1e3;
        bail!(
            "{flag}: {target} nm is not one of the sweep's values ({} … {} nm, {} of them)",
            pm(nm[0]),
            pm(nm[nm.len() - 1]),
            nm.len()
        );
    }
    Ok(nearest)
}

fn select_cmd(a: SelectArgs) -> Result<()> {
    for (flag, v) in [
        ("--mark-height-nm", a.mark_height_nm),
        ("--mark-pitch-nm", a.mark_pitch_nm),
    ] {
        if let Some(v) = v.filter(|v| !(v.is_finite() && *v > 0.0)) {
            bail!("{flag}: must be finite and > 0, got {v}");
        }
    }
    let data =
        sweep::load_sweep(&a.sweep).with_context(|| format!("--sweep {}", a.sweep.display()))?;
    // A mark given must be a pair of the sweep (the figures mark a cell: another value was
    // drawn at the nearest cell, however far); the default snaps to the nearest.
    let mark_height_nm =
        on_sweep_grid("--mark-height-nm", a.mark_height_nm, 700.0, &data.heights_m)?;
    let mark_pitch_nm = on_sweep_grid("--mark-pitch-nm", a.mark_pitch_nm, 530.0, &data.pitches_m)?;
    let sel = select::select_sweep(&data, &Criteria::default());
    let figdir = a.figures.clone().unwrap_or_else(|| a.sweep.join("figures"));
    // A sweep of zero height alone (legal: the bare substrate) has no pillar to mark; the
    // figures went unwritten with an error about an internal `mark` (a helper's audit).
    let mark = (mark_height_nm > 0.0).then_some((mark_height_nm * 1e-9, mark_pitch_nm * 1e-9));
    let mut files = select::render_figures(&figdir, &data, &sel, mark, mark_pitch_nm * 1e-9)?;
    // To a thousandth of a nm: whole nm merged the pairs of a sweep in steps of 0.2 nm into
    // one key (and the viable list named pairs the map did not).
    let nm = |m: f64| (m * 1e12).round() / 1e3;
    let key = |h_nm: f64, s_nm: f64| format!("{h_nm}x{s_nm}");
    let viable: Vec<[f64; 2]> = sel
        .iter()
        .filter(|p| p.viable)
        .map(|p| [nm(p.height_m), nm(p.pitch_m)])
        .collect();
    let mut pairs = serde_json::Map::new();
    for p in &sel {
        // A quantity a pair does not have (a usable run's, for a pair without one) is left
        // out, not written as null.
        let mut o = serde_json::Map::new();
        o.insert("viable".into(), p.viable.into());
        for (k, v) in [
            ("diameter_min_nm", p.diameter_min_m * 1e9),
            ("diameter_max_nm", p.diameter_max_m * 1e9),
            ("phase_coverage_rad", p.phase_coverage_rad),
            ("min_transmittance_2pi", p.min_transmittance_2pi),
            ("max_aspect_ratio", p.max_aspect_ratio),
        ] {
            if v.is_finite() {
                o.insert(k.into(), v.into());
            }
        }
        pairs.insert(key(nm(p.height_m), nm(p.pitch_m)), o.into());
    }
    let mut viable_map = Vec::with_capacity(sel.len() * 8);
    for p in &sel {
        viable_map.push(if p.viable { 1.0 } else { 0.0 });
    }
    let shape = [data.heights_m.len() as u64, data.pitches_m.len() as u64];
    files.push((
        figdir.join("viable.npy"),
        sweep::npy_bytes(&shape, &viable_map)?,
    ));
    // The figures and the map as one set: a full disk left five of ten files before.
    let files = sweep::write_set(&figdir, &files)
        .with_context(|| format!("--figures {}", figdir.display()))?;
    if a.json {
        let v = serde_json::json!({"viable": viable, "pairs": pairs, "figures": files});
        println!("{}", serde_json::to_string(&v)?);
    } else {
        println!(
            "{} of {} (height, pitch) pairs viable; figures in {}",
            viable.len(),
            sel.len(),
            figdir.display()
        );
        let k = key(nm(mark_height_nm * 1e-9), nm(mark_pitch_nm * 1e-9));
        if let Some(p) = pairs.get(&k) {
            println!("{k}: {p}");
        }
    }
    Ok(())
}

/// The files `metalib blueprint` writes in its --out.
const BLUEPRINT_OUTPUTS: [&str; 3] = ["diameters.npy", "layout.gds", "preview.png"];

fn blueprint_cmd(a: BlueprintArgs) -> Result<()> {
    let h = height_m(a.height_nm)?;
    let s = nm("--pitch-nm", a.pitch_nm)?;
    if !(h > 0.0 && s > 0.0) {
        bail!("--height-nm/--pitch-nm: must be > 0");
    }
    let opt = BlueprintOptions {
        diameter_step_m: nm("--diameter-step-nm", a.diameter_step_nm)?,
        circle_vertices: a.circle_vertices,
        layer: 1,
        circular_aperture: !a.square_aperture,
    };
    opt.validate().map_err(blueprint_flag)?;
    a.solver.wavelength_m()?;
    // --out a file, or a directory where an output goes, refused before the library's
    // solves (a helper's audit: a directory at OUT/diameters.npy was found after 161 cells
    // were solved into OUT/library_sweep; a file as --out failed naming library_sweep).
    if a.out.exists() && !a.out.is_dir() {
        bail!("--out {}: exists and is not a directory", a.out.display());
    }
    // No output over an input, before any work (a helper's audit: --phase OUT/diameters.npy
    // was replaced by the blueprint's diameters, exit 0).
    for name in BLUEPRINT_OUTPUTS {
        let o = a.out.join(name);
        sweep::check_output_target(&o).context("--out")?;
        for (flag, p) in [
            ("--phase", Some(&a.phase)),
            ("--library-csv", a.library_csv.as_ref()),
        ] {
            if p.is_some_and(|p| crate::util::same_file(&o, p)) {
                bail!("--out: its {name} would replace {flag}; give another --out");
            }
        }
    }
    let (shape, phase) =
        sweep::read_npy(&a.phase).with_context(|| format!("--phase {}", a.phase.display()))?;
    if shape.len() != 2 {
        bail!("--phase: expected a 2-D array, got shape {shape:?}");
    }
    let (rows, cols) = (shape[0] as usize, shape[1] as usize);
    let materials = a.solver.materials()?;
    let tau_per_t2 = materials.n_substrate / materials.n_superstrate;
    let lib: TabulatedLibrary = if let Some(csv) = &a.library_csv {
        // A regular file of at most 64 MiB (a library has hundreds of rows): a FIFO would
        // block, /dev/zero be read without end.
        let text = crate::util::read_small_text(csv, 64 << 20)
            .with_context(|| format!("--library-csv {}", csv.display()))?;
        TabulatedLibrary::from_csv(&text, h, s, a.solver.wavelength_m()?, tau_per_t2)
            .map_err(|e| anyhow!("--library-csv: {e}"))?
    } else if let Some(dir) = &a.sweep {
        let data = sweep::load_sweep(dir).with_context(|| format!("--sweep {}", dir.display()))?;
        a.solver.against_sweep(dir, &data.manifest.config)?;
        TabulatedLibrary::from_sweep(&data, h, s, &Criteria::default())
            .map_err(|e| anyhow!("--sweep: {e}"))?
            .0
    } else {
        // Compute the (h, s) slice directly: one eigen-solve per diameter.
        check_rcwa_memory(a.solver.harmonics, rayon::current_num_threads())?;
        let cfg = SweepConfig {
            heights_m: Range {
                start: h,
                stop: h,
                step: 1e-9,
            },
            pitches_m: Range {
                start: s,
                stop: s,
                step: 1e-9,
            },
            fractions: Range {
                start: 0.10,
                stop: 0.90,
                step: 0.005,
            },
            wavelength_m: a.solver.wavelength_m()?,
            materials,
            harmonics: a.solver.harmonics,
            rule: a.solver.rule()?,
            material: a.solver.material.clone(),
        };
        let dir = a.out.join("library_sweep");
        // A slice of other settings there is refused naming --out, the flag that chose it
        // (its sweep's fields are this command's --height-nm, --pitch-nm and solver flags).
        sweep::run_sweep_with_progress(&cfg, &dir).map_err(|e| match e {
            nanoeye_metalib::MetalibError::InvalidParameter {
                name: "out",
                reason,
            } if !reason.contains("format version") => {
                anyhow!("--out: {reason} (another --height-nm, --pitch-nm or solver setting)")
            }
            nanoeye_metalib::MetalibError::InvalidParameter {
                name: "out",
                reason,
            } => anyhow!("--out: {reason}"),
            e => e.into(),
        })?;
        let data = sweep::load_sweep(&dir)?;
        TabulatedLibrary::from_sweep(
            &data,
            data.heights_m[0],
            data.pitches_m[0],
            &Criteria::default(),
        )
        .map_err(|e| anyhow!("--height-nm/--pitch-nm: {e}"))?
        .0
    };
    if (lib.pitch_m() - s).abs() > 1e-6 * s {
        bail!(
            "--pitch-nm: {} nm differs from the library's pitch {} nm",
            a.pitch_nm,
            lib.pitch_m() * 1e9
        );
    }
    let bp = blueprint::invert_phase_map(&lib, &phase, rows, cols, &opt).map_err(blueprint_flag)?;
    // The layout is built in memory (about 0.5 KB a pillar at 64 vertices: a 2500² map's 2.7
    // GB aborted an allocation under ulimit -v 4 GB); weighed with the preview's canvas.
    crate::util::check_memory(
        "--phase/--circle-vertices",
        blueprint::gdsii_len(&bp, &opt).saturating_add(3 * (rows as u64) * (cols as u64)),
        "give a smaller phase map or fewer --circle-vertices",
    )?;
    // Every output is produced in memory and every target checked before the first write,
    // so a failure never leaves new files next to old ones.
    let (dmin, dmax) = lib.diameter_range_m();
    let outputs = [
        (
            "diameters.npy",
            sweep::npy_bytes(&[rows as u64, cols as u64], &bp.diameters_m)?,
        ),
        (
            "layout.gds",
            blueprint::gdsii(&bp, s, &opt).map_err(|e| anyhow!("--pitch-nm: {e}"))?,
        ),
        ("preview.png", blueprint::preview_png(&bp, dmin, dmax)?),
    ];
    debug_assert!(outputs.iter().map(|o| o.0).eq(BLUEPRINT_OUTPUTS));
    for (name, _) in &outputs {
        sweep::check_output_target(&a.out.join(name)).context("--out")?;
    }
    std::fs::create_dir_all(&a.out).with_context(|| format!("--out {}", a.out.display()))?;
    for (name, bytes) in &outputs {
        sweep::write_atomic(&a.out.join(name), bytes)?;
    }
    let v = serde_json::json!({
        "pillars": bp.pillars, "rows": rows, "cols": cols,
        "diameter_min_nm": dmin * 1e9, "diameter_max_nm": dmax * 1e9,
        "library_coverage_rad": lib.coverage_rad(),
        "rms_phase_error_rad": bp.rms_phase_error_rad, "max_phase_error_rad": bp.max_phase_error_rad,
        "circle_vertices": opt.circle_vertices, "gds_db_unit_m": blueprint::GDS_DB_UNIT_M,
    });
    if a.json {
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        println!(
            "{} pillars, diameters {:.1}–{:.1} nm, RMS phase error {:.4} rad → {}",
            bp.pillars,
            dmin * 1e9,
            dmax * 1e9,
            bp.rms_phase_error_rad,
            a.out.display()
        );
    }
    Ok(())
}

/// Most (height, diameter) cells one index's curves of `material-study` hold: 10⁶, 32 MB.
const MAX_STUDY_CELLS: f64 = 1e6;

fn study_cmd(a: StudyArgs) -> Result<()> {
    let (lo, hi) = WAVELENGTH_RANGE_M;
    let wavelength_m = nm("--wavelength-nm", a.wavelength_nm)?;
    if !(lo..=hi).contains(&wavelength_m) {
        bail!(
            "--wavelength-nm: must lie in [{}, {}] nm, got {}",
            lo * 1e9,
            hi * 1e9,
            a.wavelength_nm
        );
    }
    let pitch_m = nm("--pitch-nm", a.pitch_nm)?;
    if pitch_m <= 0.0 {
        bail!("--pitch-nm: must be > 0, got {}", a.pitch_nm);
    }
    let heights = range("--heights-nm", &a.heights_nm, 1e-9)?;
    let height_values = heights
        .values("heights")
        .map_err(|e| anyhow!("--heights-nm: {e}"))?;
    if let Some(h) = height_values
        .iter()
        .find(|h| !(0.0..=sweep::MAX_HEIGHT_M).contains(*h))
    {
        bail!(
            "--heights-nm: height {} nm outside [0, {:e}] nm",
            h * 1e9,
            sweep::MAX_HEIGHT_M * 1e9
        );
    }
    let target = nm("--height-nm", a.height_nm)?;
    let on_grid = height_values
        .iter()
        .copied()
        .find(|h| (h - target).abs() <= 1e-6 * target.abs().max(1e-9));
    let Some(target_height_m) = on_grid else {
        bail!(
            "--height-nm: {} nm is not on --heights-nm {}",
            a.height_nm,
            a.heights_nm
        );
    };
    let n_range = range("--n-values", &a.n_values, 1.0)?;
    let n_values = n_range
        .values("n")
        .map_err(|e| anyhow!("--n-values: {e}"))?;
    if n_values.len() > 1000 {
        bail!("--n-values: {} values is more than 1000", n_values.len());
    }
    // The cell's own bounds on a pillar index, checked here before any solve.
    if let Some(n) = n_values
        .iter()
        .find(|n| !(MIN_INDEX..=MAX_INDEX).contains(*n))
    {
        bail!("--n-values: {n} is outside [{MIN_INDEX}, {MAX_INDEX}]");
    }
    let mut k_values = Vec::new();
    for t in a
        .k_values
        .split(',')
        .map(str::trim)
        .filter(|t| !t.is_empty())
    {
        let k: f64 = t
            .parse()
            .map_err(|_| anyhow!("--k-values: `{t}` is not a number"))?;
        if !(k.is_finite() && (0.0..=MAX_INDEX).contains(&k)) {
            bail!("--k-values: {k} must lie in [0, {MAX_INDEX}]");
        }
        k_values.push(k);
    }
    if k_values.is_empty() {
        bail!("--k-values: give at least one k (0 for a lossless pillar)");
    }
    if k_values.len() > 1000 {
        bail!("--k-values: {} values is more than 1000", k_values.len());
    }
    let materials: Vec<String> = match a.materials.trim() {
        "all" => dispersion::names(),
        "none" | "" => Vec::new(),
        list => list.split(',').map(|s| s.trim().to_string()).collect(),
    };
    for m in &materials {
        dispersion::by_name(m).map_err(|e| anyhow!("--materials: {}", flagify(&e.to_string())))?;
    }
    let fractions = range("--fractions", &a.fractions, 1.0)?;
    let nd = fractions.values("fractions").map_or(0, |v| v.len()) as f64;
    let indices = (materials.len() + n_values.len() * k_values.len()) as f64;
    let solves = indices * nd;
    if solves > 1e6 {
        bail!(
            "--n-values/--k-values/--materials/--fractions: {solves:e} eigen-solves is more than 1e6 \
             (the default study is 7728)"
        );
    }
    // Each solve is then propagated to every height and held as one index's curves (32 bytes
    // a cell): 10⁵ heights × 1601 diameters asked for 1.3 GB at once (an allocation abort)
    // under the solve count's bound.
    let cells = nd * height_values.len() as f64;
    if cells > MAX_STUDY_CELLS {
        bail!(
            "--heights-nm/--fractions: {cells:e} (height, diameter) cells is more than \
             {MAX_STUDY_CELLS:e} (the default study has 6601)"
        );
    }
    if cells * indices > MAX_STUDY_CELLS * 100.0 {
        bail!(
            "--heights-nm/--fractions/--n-values/--k-values/--materials: {:e} cells over every \
             index is more than {:e} (the default study has 3.2e5)",
            cells * indices,
            MAX_STUDY_CELLS * 100.0
        );
    }
    check_rcwa_memory(a.harmonics, rayon::current_num_threads())?;
    let cfg = nanoeye_metalib::study::StudyConfig {
        wavelength_m,
        pitch_m,
        target_height_m,
        heights_m: heights,
        fractions,
        harmonics: a.harmonics,
        rule: a.rule.parse().map_err(|e| anyhow!("--rule: {e}"))?,
        n_values,
        k_values,
        materials,
        ..Default::default()
    };
    let t0 = std::time::Instant::now();
    let saved = faer::get_global_parallelism();
    faer::set_global_parallelism(faer::Par::Seq);
    let out = nanoeye_metalib::study::run_study(&cfg, &|done, total| {
        eprintln!(
            "material-study: {done}/{total} pillar indices, {:.0} s",
            t0.elapsed().as_secs_f64()
        );
    });
    faer::set_global_parallelism(saved);
    let points = out.map_err(|e| {
        let msg = e.to_string();
        match msg.strip_prefix("numerical failure: ") {
            // This command's flags, not `metalib cell`'s.
            Some(rest) => anyhow!(
                "--pitch-nm/--heights-nm/--fractions/--harmonics or the pillar indices \
                 (--n-values, --k-values, --materials): {rest}"
            ),
            None => anyhow!("{}", cell_flags(&msg)),
        }
    })?;
    let secs = t0.elapsed().as_secs_f64();
    let variants: Vec<serde_json::Value> = nanoeye_metalib::study::criteria_variants()
        .iter()
        .map(|v| serde_json::json!({"name": v.name, "description": v.description}))
        .collect();
    if a.json {
        let v = serde_json::json!({
            "pitch_nm": a.pitch_nm, "height_nm": target_height_m * 1e9,
            "wavelength_nm": a.wavelength_nm, "harmonics": cfg.harmonics,
            "rule": cfg.rule.name(),
            "paper_range_nm": [cfg.paper_range_m.0 * 1e9, cfg.paper_range_m.1 * 1e9],
            "range_tolerance_nm": cfg.range_tolerance_m * 1e9,
            "variants": variants, "points": points, "seconds": secs,
        });
        println!("{}", serde_json::to_string(&v)?);
    } else {
        let names: Vec<&str> = nanoeye_metalib::study::criteria_variants()
            .iter()
            .map(|v| v.name)
            .collect();
        println!(
            "(h, s) = ({:.0}, {:.0}) nm, N = {}, {:.1} s; per criteria variant: V = viable \
             (* = range within {:.0} nm of {:.0}-{:.0} nm), - = not; coverage in rad",
            target_height_m * 1e9,
            a.pitch_nm,
            cfg.harmonics,
            secs,
            cfg.range_tolerance_m * 1e9,
            cfg.paper_range_m.0 * 1e9,
            cfg.paper_range_m.1 * 1e9
        );
        println!(
            "{:<20} {:>6} {:>7}  {}",
            "source",
            "n",
            "k",
            names.join(" ")
        );
        for p in &points {
            let cells: Vec<String> = p
                .variants
                .iter()
                .map(|v| {
                    let mark = if v.near_paper_range {
                        "V*"
                    } else if v.viable {
                        "V"
                    } else {
                        "-"
                    };
                    format!("{mark}{:.2}", v.coverage_rad)
                })
                .collect();
            println!(
                "{:<20} {:>6.3} {:>7.4}  {}",
                p.source,
                p.n,
                p.k,
                cells.join(" ")
            );
        }
    }
    Ok(())
}

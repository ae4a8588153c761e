//! The (height, pitch, diameter) design sweep of Sec. D.1: parallel, checkpointed, NPY output.
//!
//! Layout of an output directory: `manifest.json`, `phase.npy`, `transmittance.npy`, `t_re.npy`,
//! `t_im.npy` (f64, C order, shape [n_heights, n_pitches, n_fractions]), and while running
//! `partial/pitch_XXXX.bin` checkpoints (one per completed pitch), removed when the sweep
//! completes. Each checkpoint is one file that vouches for itself (the configuration's hash
//! and a hash of its own bytes inside it), so a restarted sweep, on any number of processes,
//! reuses every completed pitch of the same configuration whose file is intact.

use crate::error::MetalibError;
use crate::material::Materials;
use crate::rcwa::{CellSpec, LayerModes, Rule};
use rayon::prelude::*;
use std::io::Write;
use std::path::{Path, PathBuf};

/// Format version written into the manifest.
pub const SWEEP_FORMAT_VERSION: u32 = 1;

/// An inclusive arithmetic range start:stop:step (SI units or fractions).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Range {
    /// First value.
    pub start: f64,
    /// Last value (inclusive, up to rounding).
    pub stop: f64,
    /// Step (> 0).
    pub step: f64,
}

impl Range {
    /// Values of the range; errors for non-finite, non-positive step or stop < start.
    pub fn values(&self, name: &'static str) -> Result<Vec<f64>, MetalibError> {
        if !(self.start.is_finite() && self.stop.is_finite() && self.step.is_finite()) {
            return Err(MetalibError::param(name, "range bounds must be finite"));
        }
        if self.step <= 0.0 || self.stop < self.start {
            return Err(MetalibError::param(name, "need step > 0 and stop >= start"));
        }
        // Count in f64: a tiny step makes the quotient overflow usize (or reach +inf), and a
        // saturating cast plus one would wrap to an empty range.
        let steps = ((self.stop - self.start) / self.step + 1e-9).floor();
        if steps.is_nan() || steps >= 100_000.0 {
            return Err(MetalibError::param(
                name,
                format!(
                    "{:e} samples (step {:e}) is more than 100000",
                    steps + 1.0,
                    self.step
                ),
            ));
        }
        let n = steps as usize + 1;
        Ok((0..n).map(|i| self.start + i as f64 * self.step).collect())
    }
}

/// Full description of a sweep (what the manifest records).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SweepConfig {
    /// Heights (m).
    pub heights_m: Range,
    /// Pitches (m).
    pub pitches_m: Range,
    /// Diameter as a fraction of the pitch.
    pub fractions: Range,
    /// Wavelength (m).
    pub wavelength_m: f64,
    /// Materials.
    pub materials: Materials,
    /// Truncation order.
    pub harmonics: usize,
    /// Factorisation rule.
    pub rule: Rule,
    /// Name of the tabulated pillar material (`dispersion::by_name`) that `materials` was
    /// taken from, if any: part of the parameters a resumed sweep must match. Absent from
    /// manifests of sweeps run with explicit or default indices (and from older manifests).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub material: Option<String>,
}

impl Default for SweepConfig {
    fn default() -> Self {
        Self {
            heights_m: Range {
                start: 100e-9,
                stop: 1500e-9,
                step: 10e-9,
            },
            pitches_m: Range {
                start: 100e-9,
                stop: 1000e-9,
                step: 10e-9,
            },
            fractions: Range {
                start: 0.10,
                stop: 0.90,
                step: 0.005,
            },
            wavelength_m: crate::material::DEFAULT_WAVELENGTH_M,
            materials: Materials::default(),
            harmonics: crate::rcwa::DEFAULT_HARMONICS,
            rule: crate::rcwa::DEFAULT_RULE,
            material: None,
        }
    }
}

/// Manifest written next to the arrays.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Manifest {
    /// Format version.
    pub version: u32,
    /// Crate version that wrote it.
    pub crate_version: String,
    /// Sweep parameters.
    pub config: SweepConfig,
    /// Array shape [heights, pitches, fractions].
    pub shape: [usize; 3],
    /// Index order of the arrays.
    pub index_order: String,
    /// Phase convention.
    pub phase_convention: String,
    /// Cells whose solve failed (stored as NaN).
    pub failed_cells: usize,
    /// Whether every pitch is complete.
    pub complete: bool,
    /// FNV-1a 64-bit hash (hex) of each completed `partial/pitch_XXXX.bin`, by pitch index: a
    /// record of the blocks on disk (each block vouches for itself; a resume reads the files).
    #[serde(default)]
    pub block_fnv1a64: std::collections::BTreeMap<usize, String>,
}

/// FNV-1a, 64-bit: the checksum of sweep checkpoint blocks (detects flipped bytes and
/// truncation; not a cryptographic hash).
pub fn fnv1a64(bytes: &[u8]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for &b in bytes {
        h ^= u64::from(b);
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    h
}

/// Sweep results in memory, each array flattened [h, s, f] (C order).
#[derive(Debug, Clone)]
pub struct SweepData {
    /// Manifest.
    pub manifest: Manifest,
    /// Heights (m).
    pub heights_m: Vec<f64>,
    /// Pitches (m).
    pub pitches_m: Vec<f64>,
    /// Diameter fractions of the pitch.
    pub fractions: Vec<f64>,
    /// arg t (rad).
    pub phase: Vec<f64>,
    /// τ.
    pub transmittance: Vec<f64>,
    /// Re t.
    pub t_re: Vec<f64>,
    /// Im t.
    pub t_im: Vec<f64>,
}

impl SweepData {
    /// Flat index of (height, pitch, fraction).
    pub fn idx(&self, ih: usize, is: usize, id: usize) -> usize {
        (ih * self.pitches_m.len() + is) * self.fractions.len() + id
    }
}

fn io_err(path: &Path, source: std::io::Error) -> MetalibError {
    MetalibError::Io {
        path: path.display().to_string(),
        cause: source,
    }
}

/// Fails when `path` exists and is not a regular file: renaming over a symlink, pipe,
/// device or directory would silently replace that node with a plain file.
pub fn check_output_target(path: &Path) -> Result<(), MetalibError> {
    match std::fs::symlink_metadata(path) {
        Ok(m) if !m.file_type().is_file() => Err(MetalibError::Io {
            path: path.display().to_string(),
            cause: std::io::Error::other(
                "exists and is not a regular file (symlink, pipe, device or directory); \
                 refusing to replace it",
            ),
        }),
        _ => Ok(()),
    }
}

/// Writes `bytes` to `path` atomically (temporary file in the same directory, then rename).
/// Refuses to replace anything but a regular file (a symlink, pipe, device or directory would
/// silently become a plain file).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), MetalibError> {
    check_output_target(path)?;
    let tmp = stage(path, bytes)?;
    tmp.persist(path).map_err(|e| io_err(path, e.error))?;
    Ok(())
}

/// `bytes` written in full to a temporary file beside `path`, to be persisted there.
fn stage(path: &Path, bytes: &[u8]) -> Result<tempfile::NamedTempFile, MetalibError> {
    let dir = path
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    // Named `.nanoeye-tmp-<pid>-…`: the CLI removes those a killed process left behind.
    let mut b = tempfile::Builder::new();
    // A temporary file is created owner-only (0600); an output is an ordinary file, so ask
    // for 0666 and let the umask take its share, as `File::create` would.
    #[cfg(unix)]
    b.permissions(std::os::unix::fs::PermissionsExt::from_mode(0o666));
    let mut tmp = b
        .prefix(&format!(".nanoeye-tmp-{}-", std::process::id()))
        .tempfile_in(dir)
        .map_err(|e| io_err(path, e))?;
    tmp.write_all(bytes).map_err(|e| io_err(path, e))?;
    Ok(tmp)
}

/// Writes a set of files into `dir` (created with its parents where missing) as one unit:
/// every target is checked and every file written in full beside it before the first is
/// renamed into place, so a full disk or a bad target leaves none of them (and no directory
/// this call created) rather than half a set. Returns the paths written, in order.
pub fn write_set(dir: &Path, files: &[(PathBuf, Vec<u8>)]) -> Result<Vec<String>, MetalibError> {
    for (p, _) in files {
        check_output_target(p)?;
    }
    let created = !dir.exists();
    std::fs::create_dir_all(dir).map_err(|e| io_err(dir, e))?;
    let staged: Result<Vec<_>, _> = files.iter().map(|(p, b)| stage(p, b)).collect();
    let staged = match staged {
        Ok(s) => s,
        Err(e) => {
            // The temporary files are gone with `staged`; an empty new directory goes too.
            if created {
                let _ = std::fs::remove_dir(dir);
            }
            return Err(e);
        }
    };
    let mut written = Vec::with_capacity(files.len());
    for (tmp, (p, _)) in staged.into_iter().zip(files) {
        tmp.persist(p).map_err(|e| io_err(p, e.error))?;
        written.push(p.display().to_string());
    }
    Ok(written)
}

/// Serialises a C-order f64 array as NPY bytes.
pub fn npy_bytes(shape: &[u64], data: &[f64]) -> Result<Vec<u8>, MetalibError> {
    let mut buf = Vec::with_capacity(data.len() * 8 + 128);
    {
        use npyz::WriterBuilder;
        let mut w = npyz::WriteOptions::new()
            .default_dtype()
            .shape(shape)
            .writer(std::io::Cursor::new(&mut buf))
            .begin_nd()
            .map_err(|e| MetalibError::Numerical(format!("npy header: {e}")))?;
        w.extend(data.iter().copied())
            .map_err(|e| MetalibError::Numerical(format!("npy write: {e}")))?;
        w.finish()
            .map_err(|e| MetalibError::Numerical(format!("npy finish: {e}")))?;
    }
    Ok(buf)
}

/// Most values [`read_npy`] reads: 2 GiB of f64, far beyond any phase map or sweep.
pub const MAX_NPY_VALUES: u128 = 1 << 28;

/// Reads an NPY file of f64 or f32 into (shape, data as f64): a regular file of at most
/// [`MAX_NPY_VALUES`] values whose data fills its shape.
pub fn read_npy(path: &Path) -> Result<(Vec<u64>, Vec<f64>), MetalibError> {
    let fmt = |r: String| MetalibError::Format {
        path: path.display().to_string(),
        reason: r,
    };
    // A FIFO or a device (`/dev/zero`) would be read until memory ran out.
    let meta = std::fs::metadata(path).map_err(|e| io_err(path, e))?;
    let max_bytes = MAX_NPY_VALUES * 8 + (1 << 16);
    if !meta.is_file() || u128::from(meta.len()) > max_bytes {
        return Err(fmt(format!(
            "not a regular file of at most {max_bytes} bytes"
        )));
    }
    let bytes = std::fs::read(path).map_err(|e| io_err(path, e))?;
    // Before the NPY parser, which allocates the header length it reads and multiplies the
    // dimensions unchecked.
    if let Some(d) = nanoeye_npy::check(&bytes, bytes.len() as u64).map_err(fmt)? {
        let n = d.iter().try_fold(1u128, |a, &v| a.checked_mul(v));
        if n.is_none_or(|n| n > MAX_NPY_VALUES) {
            return Err(fmt(format!(
                "shape {d:?} claims more than {MAX_NPY_VALUES} values"
            )));
        }
    }
    let npy = npyz::NpyFile::new(&bytes[..]).map_err(|e| fmt(e.to_string()))?;
    let shape = npy.shape().to_vec();
    if npy.order() != npyz::Order::C {
        return Err(fmt("Fortran-order arrays are not supported".into()));
    }
    let descr = npy.dtype().descr();
    let data: Vec<f64> = if descr.contains("f8") {
        npy.into_vec::<f64>().map_err(|e| fmt(e.to_string()))?
    } else if descr.contains("f4") {
        npy.into_vec::<f32>()
            .map_err(|e| fmt(e.to_string()))?
            .into_iter()
            .map(f64::from)
            .collect()
    } else {
        return Err(fmt(format!("unsupported dtype {descr} (need f4 or f8)")));
    };
    let n: u128 = shape.iter().map(|&d| u128::from(d)).product();
    if n != data.len() as u128 {
        return Err(fmt(format!(
            "shape {shape:?} holds {n} values, the file {}",
            data.len()
        )));
    }
    Ok((shape, data))
}

fn checkpoint_path(dir: &Path, is: usize) -> PathBuf {
    dir.join("partial").join(format!("pitch_{is:04}.bin"))
}

/// First eight bytes of a pitch block checkpoint.
const BLOCK_MAGIC: [u8; 8] = *b"NEOSWB02";
/// Bytes of a checkpoint around its cells: the magic and the configuration's hash before,
/// the file's own hash after.
const BLOCK_FRAME: usize = 24;

/// A pitch block's checkpoint, one file that vouches for itself: [`BLOCK_MAGIC`], the
/// configuration's hash ([`config_hash`], u64 LE), for each fraction for each height
/// (phase, τ, Re t, Im t) as f64 LE, then the FNV-1a 64 of all the bytes before (u64 LE).
fn encode_block(block: &[[f64; 4]], config_hash: u64) -> Vec<u8> {
    let mut b = Vec::with_capacity(BLOCK_FRAME + 32 * block.len());
    b.extend_from_slice(&BLOCK_MAGIC);
    b.extend_from_slice(&config_hash.to_le_bytes());
    b.extend(
        block
            .iter()
            .flat_map(|c| c.iter().flat_map(|v| v.to_le_bytes())),
    );
    let h = fnv1a64(&b);
    b.extend_from_slice(&h.to_le_bytes());
    b
}

/// The `expect` cells of a checkpoint written by [`encode_block`] for the configuration of
/// hash `config_hash`; None for a file truncated, altered, of another configuration or in
/// the older format (cells alone, vouched for by a side file), which is then solved again.
fn decode_block(bytes: &[u8], expect: usize, config_hash: u64) -> Option<Vec<[f64; 4]>> {
    if bytes.len() != BLOCK_FRAME + expect * 32 {
        return None;
    }
    let le = |b: &[u8]| {
        let mut a = [0u8; 8];
        a.copy_from_slice(b);
        u64::from_le_bytes(a)
    };
    let (body, tail) = bytes.split_at(bytes.len() - 8);
    if body[..8] != BLOCK_MAGIC || le(&body[8..16]) != config_hash || le(tail) != fnv1a64(body) {
        return None;
    }
    Some(
        body[16..]
            .chunks_exact(32)
            .map(|c| {
                let mut v = [0.0; 4];
                for (k, x) in v.iter_mut().enumerate() {
                    let mut b = [0u8; 8];
                    b.copy_from_slice(&c[8 * k..8 * k + 8]);
                    *x = f64::from_le_bytes(b);
                }
                v
            })
            .collect(),
    )
}

/// Solves every height of one (pitch, diameter) cell: one eigen-decomposition, many heights.
/// Failed solves are stored as NaN and counted in the manifest; so are responses beyond what
/// [`load_sweep`] accepts (τ above [`MAX_PLAUSIBLE_TRANSMITTANCE`]: a strongly absorbing pillar
/// at 3 harmonics gave τ = 3.26, saved with exit 0 and "0 failed", and the sweep could not be
/// loaded).
fn solve_column(spec: &CellSpec, heights: &[f64]) -> Vec<[f64; 4]> {
    let nan = [f64::NAN; 4];
    match LayerModes::new(spec) {
        Ok(modes) => heights
            .iter()
            .map(|&h| match modes.transmission_at(h) {
                Ok(t) => {
                    let tau = modes.transmittance_of(t);
                    let plausible = tau <= MAX_PLAUSIBLE_TRANSMITTANCE
                        && t.re.abs() <= MAX_PLAUSIBLE_T
                        && t.im.abs() <= MAX_PLAUSIBLE_T;
                    if plausible {
                        [t.arg(), tau, t.re, t.im]
                    } else {
                        nan
                    }
                }
                Err(_) => nan,
            })
            .collect(),
        Err(_) => vec![nan; heights.len()],
    }
}

/// One pitch's results: (pitch index, `[fraction][height]` of (phase rad, τ, Re t, Im t)).
pub type PitchBlock = (usize, Vec<[f64; 4]>);

/// The sampled axes of a validated sweep configuration.
#[derive(Debug, Clone)]
pub struct SweepGrid {
    /// Heights (m).
    pub heights_m: Vec<f64>,
    /// Pitches (m).
    pub pitches_m: Vec<f64>,
    /// Diameter fractions of the pitch.
    pub fractions: Vec<f64>,
}

/// Validates `config` (ranges, materials, harmonics) and returns its axes.
pub fn sweep_grid(config: &SweepConfig) -> Result<SweepGrid, MetalibError> {
    let heights = config.heights_m.values("heights")?;
    let pitches = config.pitches_m.values("pitches")?;
    let fractions = config.fractions.values("fractions")?;
    if let Some(f) = fractions.iter().find(|f| !(**f >= 0.0 && **f <= 1.0)) {
        return Err(MetalibError::param(
            "fractions",
            format!("fraction {f} outside [0, 1]"),
        ));
    }
    check_heights(&heights)?;
    if let Some(s) = pitches.iter().find(|s| **s <= 0.0) {
        return Err(MetalibError::param(
            "pitches",
            format!("non-positive pitch {s}"),
        ));
    }
    // Validate the materials/harmonics with representative cells: the range's ends bound the
    // pitch and the diameter (a loaded manifest's pitches of 1e300 m once reached the plots).
    for (&pitch_m, &fraction) in [
        (&pitches[0], &fractions[0]),
        (&pitches[pitches.len() - 1], &fractions[fractions.len() - 1]),
    ] {
        CellSpec {
            wavelength_m: config.wavelength_m,
            pitch_m,
            diameter_m: fraction * pitch_m,
            materials: config.materials,
            harmonics: config.harmonics,
            rule: config.rule,
        }
        .validate()?;
    }
    Ok(SweepGrid {
        heights_m: heights,
        pitches_m: pitches,
        fractions,
    })
}

/// Tallest pillar any command takes (m): 100 µm, two orders beyond any metasurface; a height
/// of 1e300 nm passed every check and gave t = 0 or a non-finite response (and a loaded
/// manifest's heights of 1e300 m hung the plotting of their axis).
pub const MAX_HEIGHT_M: f64 = 1e-4;

/// Refuses a height below 0 or above [`MAX_HEIGHT_M`], naming `heights`.
pub fn check_heights(heights_m: &[f64]) -> Result<(), MetalibError> {
    match heights_m
        .iter()
        .find(|h| !(0.0..=MAX_HEIGHT_M).contains(*h))
    {
        Some(h) => Err(MetalibError::param(
            "heights",
            format!("height {h} m outside [0, {MAX_HEIGHT_M}] m"),
        )),
        None => Ok(()),
    }
}

/// Relative cost of solving one pitch's block (one eigen-solve per fraction, then every
/// height), for splitting a sweep across processes. Per (pitch, fraction) the eigen-solve
/// costs about the same at every pitch (~31 ms at N = 10) while the 141-height solve grows
/// from 0.7 ms at 100 nm to 19.6 ms at 1000 nm (docs/bench/metalib.md): about 0.5 ms +
/// 19.6 ms × (s / 1 µm)², scaled by the number of heights.
pub fn pitch_cost(pitch_m: f64, heights: usize, fractions: usize) -> f64 {
    let s_um = pitch_m * 1e6;
    fractions as f64 * (31.0 + heights as f64 / 141.0 * (0.5 + 19.6 * s_um * s_um))
}

/// Splits the pitches of `grid` into `ranks` shares of about equal [`pitch_cost`]: longest
/// processing time first (costliest pitch to the least-loaded share, ties to the lower
/// share). Deterministic; every pitch index appears in exactly one share, each share sorted.
pub fn plan_shares(grid: &SweepGrid, ranks: usize) -> Vec<Vec<usize>> {
    let ranks = ranks.max(1);
    let (nh, nf) = (grid.heights_m.len(), grid.fractions.len());
    let cost: Vec<f64> = grid
        .pitches_m
        .iter()
        .map(|&s| pitch_cost(s, nh, nf))
        .collect();
    let mut order: Vec<usize> = (0..cost.len()).collect();
    // Costliest first; equal costs keep pitch order.
    order.sort_by(|&a, &b| cost[b].total_cmp(&cost[a]).then(a.cmp(&b)));
    let mut load = vec![0.0f64; ranks];
    let mut shares = vec![Vec::new(); ranks];
    for is in order {
        let r = (0..ranks)
            .min_by(|&a, &b| load[a].total_cmp(&load[b]).then(a.cmp(&b)))
            .unwrap_or(0);
        load[r] += cost[is];
        shares[r].push(is);
    }
    for s in &mut shares {
        s.sort_unstable();
    }
    shares
}

/// Largest share's [`pitch_cost`] over the mean share's: the run time of a split sweep
/// relative to a perfect split (1 = perfect).
pub fn share_imbalance(grid: &SweepGrid, shares: &[Vec<usize>]) -> f64 {
    let (nh, nf) = (grid.heights_m.len(), grid.fractions.len());
    let loads: Vec<f64> = shares
        .iter()
        .map(|s| {
            s.iter()
                .map(|&is| pitch_cost(grid.pitches_m[is], nh, nf))
                .sum()
        })
        .collect();
    let total: f64 = loads.iter().sum();
    let max = loads.iter().copied().fold(0.0, f64::max);
    if total > 0.0 {
        max * loads.len() as f64 / total
    } else {
        1.0
    }
}

/// FNV-1a 64-bit of the configuration's JSON: ties a checkpoint block to the sweep that
/// wrote it.
fn config_hash(config: &SweepConfig) -> u64 {
    fnv1a64(&serde_json::to_vec(config).unwrap_or_default())
}

/// Pitch `is`'s checkpoint block read back, with the FNV-1a 64 (hex) of the file the
/// manifest records, if the file is a whole block of this configuration ([`decode_block`]).
fn restore_block(
    dir: &Path,
    is: usize,
    cells: usize,
    config_hash: u64,
) -> Option<(Vec<[f64; 4]>, String)> {
    let bytes = std::fs::read(checkpoint_path(dir, is)).ok()?;
    let block = decode_block(&bytes, cells, config_hash)?;
    Some((block, format!("{:016x}", fnv1a64(&bytes))))
}

/// Solves one pitch's block: per fraction (rayon-parallel) the column of every height.
fn solve_block(
    config: &SweepConfig,
    grid: &SweepGrid,
    is: usize,
    progress: &(dyn Fn(u64, bool) + Sync),
) -> Vec<[f64; 4]> {
    let s = grid.pitches_m[is];
    let nh = grid.heights_m.len();
    let cols: Vec<Vec<[f64; 4]>> = grid
        .fractions
        .par_iter()
        .map(|&f| {
            let spec = CellSpec {
                wavelength_m: config.wavelength_m,
                pitch_m: s,
                diameter_m: (f * s).min(s),
                materials: config.materials,
                harmonics: config.harmonics,
                rule: config.rule,
            };
            let out = solve_column(&spec, &grid.heights_m);
            progress(nh as u64, false);
            out
        })
        .collect();
    let mut block = Vec::with_capacity(nh * grid.fractions.len());
    for col in cols {
        block.extend(col);
    }
    block
}

fn fresh_manifest(config: &SweepConfig, grid: &SweepGrid) -> Manifest {
    Manifest {
        version: SWEEP_FORMAT_VERSION,
        crate_version: env!("CARGO_PKG_VERSION").to_string(),
        config: config.clone(),
        shape: [
            grid.heights_m.len(),
            grid.pitches_m.len(),
            grid.fractions.len(),
        ],
        index_order: "[height, pitch, diameter_fraction], C order".into(),
        phase_convention: "time dependence exp(-i omega t); t = Ex(z = h+, zero order) / Ex_inc(z = 0-); \
                           phase = arg t in (-pi, pi]; z = 0 is the pillar top, z = h the substrate surface"
            .into(),
        failed_cells: 0,
        complete: false,
        block_fnv1a64: Default::default(),
    }
}

fn write_manifest(dir: &Path, manifest: &Manifest) -> Result<(), MetalibError> {
    let json =
        serde_json::to_vec_pretty(manifest).map_err(|e| MetalibError::Numerical(e.to_string()))?;
    write_atomic(&dir.join("manifest.json"), &json)
}

/// Opens `dir` for `config`: refuses a directory holding another sweep, keeps the record of
/// the blocks an interrupted run left intact, and writes the (incomplete) manifest. The first step
/// of [`run_sweep`]; a distributed run calls it on one process only.
pub fn open_sweep(config: &SweepConfig, dir: &Path) -> Result<Manifest, MetalibError> {
    let grid = sweep_grid(config)?;
    let mut manifest = fresh_manifest(config, &grid);
    let mpath = dir.join("manifest.json");
    if mpath.exists() {
        let old = read_manifest(&mpath)?;
        if old.config != manifest.config || old.version != manifest.version {
            // Name what differs: the format, or the configuration's fields.
            let what = if old.version != manifest.version {
                format!(
                    "format version {} there, {} here",
                    old.version, manifest.version
                )
            } else {
                let fields = |c: &SweepConfig| match serde_json::to_value(c) {
                    Ok(serde_json::Value::Object(m)) => m,
                    _ => serde_json::Map::new(),
                };
                let (was, now) = (fields(&old.config), fields(&manifest.config));
                now.iter()
                    .filter(|&(k, v)| was.get(k) != Some(v))
                    .map(|(k, _)| format!("`{k}`"))
                    .collect::<Vec<_>>()
                    .join(", ")
            };
            return Err(MetalibError::param(
                "out",
                format!(
                    "{} holds a sweep with different parameters ({what}); use another directory \
                     or the same parameters",
                    dir.display()
                ),
            ));
        }
        manifest.block_fnv1a64 = old.block_fnv1a64;
    }
    // Made once the directory is this sweep's: a refused one was left an empty partial/.
    std::fs::create_dir_all(dir.join("partial")).map_err(|e| io_err(dir, e))?;
    // Keep only the records whose block is still there and intact.
    let cells = grid.heights_m.len() * grid.fractions.len();
    let chash = config_hash(config);
    manifest
        .block_fnv1a64
        .retain(|is, _| restore_block(dir, *is, cells, chash).is_some());
    write_manifest(dir, &manifest)?;
    Ok(manifest)
}

/// Solves (or restores) the pitch blocks `share` of a sweep opened by [`open_sweep`] and
/// returns them as (pitch index, block `[fraction][height]` of (phase, τ, Re t, Im t)).
/// Each block solved is checkpointed at once to `partial/pitch_XXXX.bin`, one atomic file
/// holding the configuration's hash and its own ([`encode_block`]), so an interrupted share
/// resumes on any number of processes.
pub fn solve_share(
    config: &SweepConfig,
    dir: &Path,
    share: &[usize],
    progress: &(dyn Fn(u64, bool) + Sync),
) -> Result<Vec<PitchBlock>, MetalibError> {
    let grid = sweep_grid(config)?;
    let ns = grid.pitches_m.len();
    if let Some(is) = share.iter().find(|&&is| is >= ns) {
        return Err(MetalibError::param(
            "share",
            format!("pitch index {is} out of 0..{ns}"),
        ));
    }
    std::fs::create_dir_all(dir.join("partial")).map_err(|e| io_err(dir, e))?;
    let cells = grid.heights_m.len() * grid.fractions.len();
    let chash = config_hash(config);
    let mut out = Vec::with_capacity(share.len());
    for &is in share {
        if let Some((b, _)) = restore_block(dir, is, cells, chash) {
            progress(cells as u64, true);
            out.push((is, b));
        }
    }
    for &is in share {
        if out.iter().any(|(j, _)| *j == is) {
            continue;
        }
        let block = solve_block(config, &grid, is, progress);
        write_atomic(&checkpoint_path(dir, is), &encode_block(&block, chash))?;
        out.push((is, block));
    }
    out.sort_by_key(|(is, _)| *is);
    Ok(out)
}

/// Writes the arrays and the complete manifest of a sweep from all of its pitch blocks
/// (any order) and removes the checkpoints: the last step of [`run_sweep`].
pub fn finish_sweep(
    config: &SweepConfig,
    dir: &Path,
    blocks: Vec<PitchBlock>,
) -> Result<Manifest, MetalibError> {
    let grid = sweep_grid(config)?;
    let (nh, ns, nf) = (
        grid.heights_m.len(),
        grid.pitches_m.len(),
        grid.fractions.len(),
    );
    let mut by_pitch: Vec<Option<Vec<[f64; 4]>>> = vec![None; ns];
    for (is, b) in blocks {
        if is < ns && b.len() == nh * nf {
            by_pitch[is] = Some(b);
        }
    }
    // Assemble [h, s, f] arrays from the per-pitch blocks (stored [f][h]).
    let total = nh * ns * nf;
    let mut arrays = vec![vec![0.0; total]; 4];
    for (is, b) in by_pitch.iter().enumerate() {
        let b = b
            .as_ref()
            .ok_or_else(|| MetalibError::Numerical(format!("missing pitch block {is}")))?;
        for id in 0..nf {
            for ih in 0..nh {
                let c = b[id * nh + ih];
                let k = (ih * ns + is) * nf + id;
                for (a, v) in arrays.iter_mut().zip(c) {
                    a[k] = v;
                }
            }
        }
    }
    let mut manifest = fresh_manifest(config, &grid);
    manifest.failed_cells = arrays[0].iter().filter(|v| v.is_nan()).count();
    let shape = [nh as u64, ns as u64, nf as u64];
    for (name, a) in ["phase", "transmittance", "t_re", "t_im"]
        .iter()
        .zip(&arrays)
    {
        write_atomic(&dir.join(format!("{name}.npy")), &npy_bytes(&shape, a)?)?;
    }
    manifest.complete = true;
    write_manifest(dir, &manifest)?;
    let _ = std::fs::remove_dir_all(dir.join("partial"));
    Ok(manifest)
}

/// The manifest of a complete sweep of `config` in `dir` whose arrays read back (shapes and
/// values checked by [`load_sweep`]), or None: a rerun of a finished sweep returns it instead
/// of solving every cell again, since the checkpoints it would resume from are gone.
pub fn completed_sweep(config: &SweepConfig, dir: &Path) -> Option<Manifest> {
    let grid = sweep_grid(config).ok()?;
    let old = read_manifest(&dir.join("manifest.json")).ok()?;
    let fresh = fresh_manifest(config, &grid);
    let same = old.complete && old.config == fresh.config && old.version == fresh.version;
    (same && load_sweep(dir).is_ok()).then_some(old)
}

/// Runs (or resumes) a sweep into `dir`, reporting completed cells to `progress` as
/// (cells, restored): `restored` is true for cells read back from a checkpoint or from the
/// arrays of a sweep already complete.
pub fn run_sweep(
    config: &SweepConfig,
    dir: &Path,
    progress: &(dyn Fn(u64, bool) + Sync),
) -> Result<Manifest, MetalibError> {
    let grid = sweep_grid(config)?;
    if let Some(done) = completed_sweep(config, dir) {
        progress(done.shape.iter().product::<usize>() as u64, true);
        return Ok(done);
    }
    let mut manifest = open_sweep(config, dir)?;
    let mut blocks = Vec::with_capacity(grid.pitches_m.len());
    for is in 0..grid.pitches_m.len() {
        // One pitch at a time, each recorded in the manifest as soon as it is on disk.
        let mut b = solve_share(config, dir, &[is], progress)?;
        if let Ok(bytes) = std::fs::read(checkpoint_path(dir, is)) {
            manifest
                .block_fnv1a64
                .insert(is, format!("{:016x}", fnv1a64(&bytes)));
        }
        write_manifest(dir, &manifest)?;
        blocks.append(&mut b);
    }
    finish_sweep(config, dir, blocks)
}

/// Calls `work` with a progress reporter for `total` cells: an indicatif bar on stderr when
/// stderr is a terminal, a plain line per 10 % of the cells otherwise (logs of long runs
/// under nohup, CI or mpirun). The faer global parallelism is set to sequential for the
/// duration, since the sweep already runs one cell per rayon task, and restored afterwards.
pub fn with_progress<R>(total: u64, work: impl FnOnce(&(dyn Fn(u64, bool) + Sync)) -> R) -> R {
    let bar = indicatif::ProgressBar::with_draw_target(
        Some(total),
        indicatif::ProgressDrawTarget::stderr(),
    );
    if let Ok(style) = indicatif::ProgressStyle::with_template(
        "{elapsed_precise} [{bar:40}] {pos}/{len} cells, eta {eta}",
    ) {
        bar.set_style(style);
    }
    let plain = !std::io::IsTerminal::is_terminal(&std::io::stderr());
    let done = std::sync::atomic::AtomicU64::new(0);
    // Cells restored from checkpoints count as done but not towards the rate.
    let restored = std::sync::atomic::AtomicU64::new(0);
    let next_tenth = std::sync::atomic::AtomicU64::new(1);
    let start = std::time::Instant::now();
    let report = |n: u64, from_checkpoint: bool| {
        bar.inc(n);
        if !plain || total == 0 {
            return;
        }
        use std::sync::atomic::Ordering::Relaxed;
        if from_checkpoint {
            restored.fetch_add(n, Relaxed);
        }
        let d = done.fetch_add(n, Relaxed) + n;
        let tenth = next_tenth.load(Relaxed);
        // One thread wins the swap and prints each tenth once.
        if d * 10 >= tenth * total
            && next_tenth
                .compare_exchange(tenth, d * 10 / total + 1, Relaxed, Relaxed)
                .is_ok()
        {
            let t = start.elapsed().as_secs_f64();
            let computed = d.saturating_sub(restored.load(Relaxed));
            let left = if computed > 0 {
                format!(
                    ", about {:.0} s left",
                    t * (total - d) as f64 / computed as f64
                )
            } else {
                " (restored: nothing solved)".to_string()
            };
            eprintln!(
                "sweep: {:.0} % ({d}/{total} cells), {t:.0} s elapsed{left}",
                100.0 * d as f64 / total as f64,
            );
        }
    };
    let saved = faer::get_global_parallelism();
    faer::set_global_parallelism(faer::Par::Seq);
    let out = work(&report);
    faer::set_global_parallelism(saved);
    bar.finish_and_clear();
    out
}

/// [`run_sweep`] with [`with_progress`]'s reporting.
pub fn run_sweep_with_progress(config: &SweepConfig, dir: &Path) -> Result<Manifest, MetalibError> {
    let g = sweep_grid(config)?;
    let total = (g.heights_m.len() * g.pitches_m.len() * g.fractions.len()) as u64;
    with_progress(total, |report| run_sweep(config, dir, report))
}

/// Largest τ a loaded sweep may hold: energy conservation gives τ ≤ 1; the margin covers
/// Fourier truncation error at low harmonic counts.
pub const MAX_PLAUSIBLE_TRANSMITTANCE: f64 = 1.5;
/// Largest |Re t|, |Im t| a loaded sweep may hold (|t|² n_sub/n_sup = τ).
const MAX_PLAUSIBLE_T: f64 = 2.0;
/// Phases are arg t in (−π, π] (a little slack for rounding).
const PHASE_BOUND: f64 = std::f64::consts::PI + 1e-9;

/// Largest manifest read (bytes): a manifest is a configuration and a few counts, under 1 KB.
const MAX_MANIFEST_BYTES: u64 = 1 << 20;

/// Reads a sweep's manifest: a regular file of at most [`MAX_MANIFEST_BYTES`] (a FIFO blocked
/// the read, `/dev/zero` was read until memory ran out).
fn read_manifest(path: &Path) -> Result<Manifest, MetalibError> {
    let format = |reason: String| MetalibError::Format {
        path: path.display().to_string(),
        reason,
    };
    let meta = std::fs::metadata(path).map_err(|e| io_err(path, e))?;
    if !meta.is_file() || meta.len() > MAX_MANIFEST_BYTES {
        return Err(format(format!(
            "not a regular file of at most {MAX_MANIFEST_BYTES} bytes"
        )));
    }
    let bytes = std::fs::read(path).map_err(|e| io_err(path, e))?;
    serde_json::from_slice(&bytes).map_err(|e| format(e.to_string()))
}

/// Loads a completed sweep directory.
pub fn load_sweep(dir: &Path) -> Result<SweepData, MetalibError> {
    let mpath = dir.join("manifest.json");
    let manifest = read_manifest(&mpath)?;
    let format = |reason: String| MetalibError::Format {
        path: mpath.display().to_string(),
        reason,
    };
    if manifest.version != SWEEP_FORMAT_VERSION {
        return Err(format(format!(
            "format version {}, this build reads {SWEEP_FORMAT_VERSION}",
            manifest.version
        )));
    }
    if !manifest.complete {
        return Err(format(
            "sweep incomplete; rerun `sweep` to resume it".into(),
        ));
    }
    // The grid a sweep may have been run on, checked as a new sweep's is: heights of 1e300 m
    // hung the plots, fractions above 1 and pitches of 0 were reported as pillars.
    let SweepGrid {
        heights_m,
        pitches_m,
        fractions,
    } = sweep_grid(&manifest.config).map_err(|e| format(e.to_string()))?;
    let expect = [
        heights_m.len() as u64,
        pitches_m.len() as u64,
        fractions.len() as u64,
    ];
    let mut arrays = Vec::new();
    for name in ["phase", "transmittance", "t_re", "t_im"] {
        let p = dir.join(format!("{name}.npy"));
        let (shape, data) = read_npy(&p)?;
        if shape != expect {
            return Err(MetalibError::Format {
                path: p.display().to_string(),
                reason: format!("shape {shape:?} != manifest {expect:?}"),
            });
        }
        // Failed cells are NaN; anything else must be a physically possible value, or the
        // selection would call impossible pillars (τ = 1e308) usable.
        let (lo, hi) = match name {
            "transmittance" => (0.0, MAX_PLAUSIBLE_TRANSMITTANCE),
            "phase" => (-PHASE_BOUND, PHASE_BOUND),
            _ => (-MAX_PLAUSIBLE_T, MAX_PLAUSIBLE_T),
        };
        if let Some((k, v)) = data
            .iter()
            .enumerate()
            .find(|(_, v)| !v.is_nan() && !(lo..=hi).contains(*v))
        {
            return Err(MetalibError::Format {
                path: p.display().to_string(),
                reason: format!("value {v:e} at flat index {k} lies outside [{lo}, {hi}]"),
            });
        }
        arrays.push(data);
    }
    let t_im = arrays.pop().unwrap_or_default();
    let t_re = arrays.pop().unwrap_or_default();
    let transmittance = arrays.pop().unwrap_or_default();
    let phase = arrays.pop().unwrap_or_default();
    Ok(SweepData {
        manifest,
        heights_m,
        pitches_m,
        fractions,
        phase,
        transmittance,
        t_re,
        t_im,
    })
}

#[cfg(test)]
mod bad_input_tests {
    use super::*;

    fn tiny(dir: &Path) -> SweepConfig {
        let _ = dir;
        SweepConfig {
            heights_m: Range {
                start: 700e-9,
                stop: 700e-9,
                step: 10e-9,
            },
            pitches_m: Range {
                start: 500e-9,
                stop: 510e-9,
                step: 10e-9,
            },
            fractions: Range {
                start: 0.3,
                stop: 0.4,
                step: 0.1,
            },
            harmonics: 1,
            ..SweepConfig::default()
        }
    }

    #[test]
    fn tiny_steps_are_refused_not_wrapped_to_zero_samples() {
        for (start, stop, step) in [(0.1, 0.9, 1e-300), (0.0, 1e9, 1e-300), (0.0, 1.0, 1e-5)] {
            let r = Range { start, stop, step };
            assert!(r.values("fractions").is_err(), "{r:?}");
        }
        let cfg = SweepConfig {
            fractions: Range {
                start: 0.1,
                stop: 0.9,
                step: 1e-300,
            },
            ..tiny(Path::new("."))
        };
        let dir = tempfile::tempdir().unwrap();
        assert!(run_sweep(&cfg, dir.path(), &|_, _| {}).is_err());
    }

    /// A helper's audit: a pillar of k = 100 at 3 harmonics gave τ up to 3.26, which the sweep
    /// saved as a result ("0 failed") and load_sweep then refused; such cells are failures.
    #[test]
    fn responses_a_load_would_refuse_are_failed_cells() {
        let dir = tempfile::tempdir().unwrap();
        let cfg = SweepConfig {
            heights_m: Range {
                start: 700e-9,
                stop: 700e-9,
                step: 1e-9,
            },
            pitches_m: Range {
                start: 530e-9,
                stop: 530e-9,
                step: 1e-9,
            },
            fractions: Range {
                start: 0.1,
                stop: 0.9,
                step: 0.005,
            },
            harmonics: 3,
            materials: Materials {
                k_pillar: 100.0,
                ..Materials::default()
            },
            ..SweepConfig::default()
        };
        let m = run_sweep(&cfg, dir.path(), &|_, _| {}).unwrap();
        assert!(m.failed_cells > 0, "no cell failed");
        let data = load_sweep(dir.path()).unwrap();
        assert_eq!(
            data.transmittance.iter().filter(|v| v.is_nan()).count(),
            m.failed_cells
        );
        assert!(
            data.transmittance
                .iter()
                .all(|&t| t.is_nan() || t <= MAX_PLAUSIBLE_TRANSMITTANCE)
        );
    }

    #[test]
    fn a_corrupted_checkpoint_block_is_recomputed_not_reused() {
        let dir = tempfile::tempdir().unwrap();
        let cfg = tiny(dir.path());
        let done = run_sweep(&cfg, dir.path(), &|_, _| {}).unwrap();
        let real = load_sweep(dir.path()).unwrap();
        // Fake an interrupted run whose pitch-0 block holds marker values.
        let fake = vec![[0.5, 0.25, 0.5, 0.0]; 2];
        let bytes = encode_block(&fake, config_hash(&cfg));
        let mut m = done.clone();
        m.complete = false;
        let write_state = |block: &[u8]| {
            std::fs::create_dir_all(dir.path().join("partial")).unwrap();
            write_atomic(&checkpoint_path(dir.path(), 0), block).unwrap();
            let json = serde_json::to_vec_pretty(&m).unwrap();
            write_atomic(&dir.path().join("manifest.json"), &json).unwrap();
        };
        write_state(&bytes);
        run_sweep(&cfg, dir.path(), &|_, _| {}).unwrap();
        let resumed = load_sweep(dir.path()).unwrap();
        assert_eq!(resumed.transmittance[0], 0.25, "intact block is reused");
        // One bit flipped in a cell, the header or the hash; the block cut short; another
        // configuration's block; the cells alone (the older format): each is solved again.
        let other = encode_block(&fake, config_hash(&cfg) ^ 1);
        let n = bytes.len();
        let mut bad: Vec<Vec<u8>> = [20, 3, 9, n - 2]
            .iter()
            .map(|&i| {
                let mut b = bytes.clone();
                b[i] ^= 0x40;
                b
            })
            .collect();
        bad.extend([bytes[..n - 1].to_vec(), other, bytes[16..n - 8].to_vec()]);
        for b in bad {
            write_state(&b);
            run_sweep(&cfg, dir.path(), &|_, _| {}).unwrap();
            let redone = load_sweep(dir.path()).unwrap();
            assert_eq!(
                redone.transmittance, real.transmittance,
                "corrupt block is recomputed"
            );
        }
    }

    #[test]
    fn shares_cover_every_pitch_once_and_balance_the_full_sweep() {
        let grid = sweep_grid(&SweepConfig::default()).unwrap();
        for ranks in [1, 2, 3, 8, 64, 200] {
            let shares = plan_shares(&grid, ranks);
            assert_eq!(shares.len(), ranks);
            let mut all: Vec<usize> = shares.iter().flatten().copied().collect();
            all.sort_unstable();
            assert_eq!(all, (0..grid.pitches_m.len()).collect::<Vec<_>>());
            // LPT is within 4/3 of the best split, and never below the costliest pitch.
            let imb = share_imbalance(&grid, &shares);
            let (nh, nf) = (grid.heights_m.len(), grid.fractions.len());
            let costs: Vec<f64> = grid
                .pitches_m
                .iter()
                .map(|&s| pitch_cost(s, nh, nf))
                .collect();
            let total: f64 = costs.iter().sum();
            let biggest = costs.iter().copied().fold(0.0, f64::max);
            let bound = (total / ranks as f64).max(biggest) * 4.0 / 3.0;
            assert!(imb * total / ranks as f64 <= bound + 1e-9, "{ranks}: {imb}");
        }
        // Two ranks split the 91 pitches to within 1 % of even.
        assert!(share_imbalance(&grid, &plan_shares(&grid, 2)) < 1.01);
        // The costliest (largest) pitch comes first, to share 0.
        assert!(plan_shares(&grid, 2)[0].contains(&(grid.pitches_m.len() - 1)));
    }

    #[test]
    fn shares_solved_apart_resume_and_assemble_to_the_single_run() {
        let dir = tempfile::tempdir().unwrap();
        let cfg = tiny(dir.path());
        let one = tempfile::tempdir().unwrap();
        run_sweep(&cfg, one.path(), &|_, _| {}).unwrap();
        let m = open_sweep(&cfg, dir.path()).unwrap();
        let solved = |share: &[usize]| {
            let restored = std::sync::atomic::AtomicU64::new(0);
            let b = solve_share(&cfg, dir.path(), share, &|n, r| {
                if r {
                    restored.fetch_add(n, std::sync::atomic::Ordering::Relaxed);
                }
            })
            .unwrap();
            (b, restored.into_inner())
        };
        let (b1, r1) = solved(&[1]);
        assert_eq!(r1, 0);
        // A later run (any share holding pitch 1) restores pitch 1 from its checkpoint alone.
        let (mut b0, r0) = solved(&[0, 1]);
        assert_eq!(r0, 2, "pitch 1's two cells come back from disk");
        assert_eq!(b0[1], b1[0]);
        // Another configuration's sweep does not take it.
        let other = SweepConfig {
            harmonics: 2,
            ..cfg.clone()
        };
        assert!(restore_block(dir.path(), 1, 2, config_hash(&other)).is_none());
        assert!(restore_block(dir.path(), 1, 2, config_hash(&cfg)).is_some());
        b0.reverse();
        let done = finish_sweep(&cfg, dir.path(), b0).unwrap();
        assert!(done.complete && m.shape == done.shape);
        assert!(!dir.path().join("partial").exists());
        for f in [
            "manifest.json",
            "phase.npy",
            "transmittance.npy",
            "t_re.npy",
            "t_im.npy",
        ] {
            assert_eq!(
                std::fs::read(dir.path().join(f)).unwrap(),
                std::fs::read(one.path().join(f)).unwrap(),
                "{f}"
            );
        }
    }

    #[test]
    fn impossible_values_in_a_sweep_are_refused_on_load() {
        let dir = tempfile::tempdir().unwrap();
        let cfg = tiny(dir.path());
        run_sweep(&cfg, dir.path(), &|_, _| {}).unwrap();
        let (shape, mut tau) = read_npy(&dir.path().join("transmittance.npy")).unwrap();
        tau[0] = 1e308;
        write_atomic(
            &dir.path().join("transmittance.npy"),
            &npy_bytes(&shape, &tau).unwrap(),
        )
        .unwrap();
        let e = load_sweep(dir.path()).unwrap_err().to_string();
        assert!(e.contains("1e308"), "{e}");
    }

    #[cfg(unix)]
    #[test]
    fn write_atomic_refuses_a_symlink_target() {
        let dir = tempfile::tempdir().unwrap();
        let real = dir.path().join("real");
        std::fs::write(&real, b"keep").unwrap();
        let link = dir.path().join("link");
        std::os::unix::fs::symlink(&real, &link).unwrap();
        assert!(write_atomic(&link, b"x").is_err());
        assert_eq!(std::fs::read(&real).unwrap(), b"keep");
    }

    /// The sweep's files have the mode `File::create` gives under this umask (they were
    /// 0644 whatever the umask, after a temporary file's 0600).
    #[cfg(unix)]
    #[test]
    fn an_atomic_write_has_the_mode_file_create_gives() {
        let dir = tempfile::tempdir().unwrap();
        use std::os::unix::fs::PermissionsExt;
        let mode = |p: &Path| std::fs::metadata(p).unwrap().permissions().mode() & 0o777;
        let plain = dir.path().join("plain");
        std::fs::write(&plain, b"x").unwrap();
        let out = dir.path().join("out.json");
        write_atomic(&out, b"x").unwrap();
        assert_eq!(mode(&out), mode(&plain));
        let set_dir = dir.path().join("set");
        let set = write_set(&set_dir, &[(set_dir.join("a.json"), b"x".to_vec())]).unwrap();
        assert_eq!(mode(Path::new(&set[0])), mode(&plain));
    }
}

#[cfg(test)]
mod range_proptests {
    use super::*;
    use proptest::prelude::*;

    fn extreme() -> impl Strategy<Value = f64> {
        prop_oneof![
            -10.0f64..10.0,
            any::<f64>(),
            Just(f64::NAN),
            Just(f64::INFINITY),
            Just(1e-300),
            Just(f64::MIN_POSITIVE),
            Just(1e308),
        ]
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(256))]
        /// Any (start, stop, step) is refused or gives 1..=100000 finite, non-decreasing samples.
        #[test]
        fn ranges_are_refused_or_sane(start in extreme(), stop in extreme(), step in extreme()) {
            let r = Range { start, stop, step };
            if let Ok(v) = r.values("range") {
                prop_assert!(!v.is_empty() && v.len() <= 100_000);
                prop_assert!(v.iter().all(|x| x.is_finite()));
                prop_assert!(v.windows(2).all(|w| w[1] >= w[0]));
            }
        }
    }
}

//! The initialization loop of Sec. A.2: Adam on a free-form phase map minimizing L_init
//! (S3–S6) of the PSF stack seen through the sensor's box integration at the effective pitch
//! p̂, with the optics VJP carrying ∂L/∂PSF to ∂L/∂φ. The state (phase, Adam moments,
//! log-variances, history) is checkpointed to a directory and can be resumed from it.

use crate::composite::InitLoss;
use crate::error::{FisherError, check_positive};
use crate::precision::{FisherNoise, Precision};
use crate::stack::PsfStack;
use faer::Mat;
use nanoeye_optics::{ApertureGrid, PhaseMap, PsfModel};
use nanoeye_sensor::BoxIntegrator;
use std::path::Path;

/// Settings of the initialization loop (SI units).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct InitConfig {
    /// Depth planes (m).
    pub depths_m: Vec<f64>,
    /// Effective sensor pitch p̂ (m) the losses see (box integration of the optics' pixels).
    pub sensor_pitch_m: f64,
    /// Adam step on the phase (rad).
    pub lr_phase: f64,
    /// Adam step on the log-variances s_k.
    pub lr_log_var: f64,
    /// Photon budget and noise of the precision term.
    pub noise: FisherNoise,
}

impl Default for InitConfig {
    /// 17–26 mm in 1.5 mm steps, p̂ = 9 µm, Adam steps 0.05 rad and 0.05, 10⁵ photons.
    fn default() -> Self {
        InitConfig {
            depths_m: (0..7).map(|k| 17e-3 + 1.5e-3 * k as f64).collect(),
            sensor_pitch_m: 9e-6,
            lr_phase: 0.05,
            lr_log_var: 0.05,
            noise: FisherNoise {
                photons: 1e5,
                noise_var: 16.0,
                ..FisherNoise::default()
            },
        }
    }
}

/// One iteration's record.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct InitRecord {
    /// Iteration index (0-based) at which the losses were evaluated.
    pub iteration: usize,
    /// L_init (S6).
    pub l_init: f64,
    /// L_prec (in units of [`crate::PREC_UNIT_M2`]), L_dist, L_comp.
    pub terms: [f64; 3],
    /// s_k = log σ_k² used.
    pub log_vars: [f64; 3],
}

/// Optimizer state: everything needed to resume.
#[derive(Clone, Debug)]
pub struct InitState {
    /// Iterations done.
    pub iteration: usize,
    /// Phase map (rad) on the aperture grid.
    pub phase: Mat<f64>,
    /// Adam first moment of the phase.
    pub m: Mat<f64>,
    /// Adam second moment of the phase.
    pub v: Mat<f64>,
    /// Log-variances s_k.
    pub log_vars: [f64; 3],
    /// Adam moments of s_k.
    pub s_m: [f64; 3],
    /// Adam second moments of s_k.
    pub s_v: [f64; 3],
    /// Per-iteration records.
    pub history: Vec<InitRecord>,
}

#[derive(serde::Serialize, serde::Deserialize)]
struct Meta {
    iteration: usize,
    n: usize,
    log_vars: [f64; 3],
    s_m: [f64; 3],
    s_v: [f64; 3],
    config: InitConfig,
    history: Vec<InitRecord>,
}

const BETA1: f64 = 0.9;
const BETA2: f64 = 0.999;
const ADAM_EPS: f64 = 1e-8;

impl InitState {
    /// Fresh state starting from `phase` (rad).
    pub fn new(phase: Mat<f64>) -> InitState {
        let (r, c) = (phase.nrows(), phase.ncols());
        InitState {
            iteration: 0,
            phase,
            m: Mat::zeros(r, c),
            v: Mat::zeros(r, c),
            log_vars: [0.0; 3],
            s_m: [0.0; 3],
            s_v: [0.0; 3],
            history: Vec::new(),
        }
    }

    /// Writes the checkpoint (state.json, phase.npy, adam_m.npy, adam_v.npy) into `dir`,
    /// each file atomically; phase.npy is float64 [y, x] in radians.
    pub fn save(&self, dir: &Path, cfg: &InitConfig) -> Result<(), FisherError> {
        std::fs::create_dir_all(dir).map_err(|e| io("checkpoint dir", dir, e))?;
        write_npy(&dir.join("phase.npy"), &self.phase)?;
        write_npy(&dir.join("adam_m.npy"), &self.m)?;
        write_npy(&dir.join("adam_v.npy"), &self.v)?;
        let meta = Meta {
            iteration: self.iteration,
            n: self.phase.nrows(),
            log_vars: self.log_vars,
            s_m: self.s_m,
            s_v: self.s_v,
            config: cfg.clone(),
            history: self.history.clone(),
        };
        let text = serde_json::to_vec_pretty(&meta).map_err(|e| FisherError::Shape {
            name: "checkpoint",
            why: e.to_string(),
        })?;
        write_file(&dir.join("state.json"), &text)
    }

    /// Loads a checkpoint written by [`InitState::save`]; returns the state and its config.
    pub fn load(dir: &Path) -> Result<(InitState, InitConfig), FisherError> {
        let p = dir.join("state.json");
        let bytes = std::fs::read(&p).map_err(|e| io("checkpoint", &p, e))?;
        let meta: Meta = serde_json::from_slice(&bytes).map_err(|e| FisherError::Shape {
            name: "checkpoint",
            why: format!("{}: {e}", p.display()),
        })?;
        let phase = read_npy(&dir.join("phase.npy"), meta.n)?;
        let m = read_npy(&dir.join("adam_m.npy"), meta.n)?;
        let v = read_npy(&dir.join("adam_v.npy"), meta.n)?;
        Ok((
            InitState {
                iteration: meta.iteration,
                phase,
                m,
                v,
                log_vars: meta.log_vars,
                s_m: meta.s_m,
                s_v: meta.s_v,
                history: meta.history,
            },
            meta.config,
        ))
    }
}

fn io(name: &'static str, path: &Path, e: impl std::fmt::Display) -> FisherError {
    FisherError::Shape {
        name,
        why: format!("{}: {e}", path.display()),
    }
}

fn write_file(path: &Path, bytes: &[u8]) -> Result<(), FisherError> {
    use std::io::Write;
    let dir = path.parent().unwrap_or(Path::new("."));
    let mut tmp = tempfile::NamedTempFile::new_in(dir).map_err(|e| io("output", path, e))?;
    tmp.write_all(bytes).map_err(|e| io("output", path, e))?;
    tmp.persist(path).map_err(|e| io("output", path, e.error))?;
    Ok(())
}

/// Writes a float64 C-order NPY array [rows, cols] atomically.
pub fn write_npy(path: &Path, m: &Mat<f64>) -> Result<(), FisherError> {
    use npyz::WriterBuilder;
    let mut buf = Vec::new();
    {
        let mut w = npyz::WriteOptions::new()
            .default_dtype()
            .shape(&[m.nrows() as u64, m.ncols() as u64])
            .writer(&mut buf)
            .begin_nd()
            .map_err(|e| io("npy", path, e))?;
        for i in 0..m.nrows() {
            for j in 0..m.ncols() {
                w.push(&m[(i, j)]).map_err(|e| io("npy", path, e))?;
            }
        }
        w.finish().map_err(|e| io("npy", path, e))?;
    }
    write_file(path, &buf)
}

fn read_npy(path: &Path, n: usize) -> Result<Mat<f64>, FisherError> {
    let bytes = std::fs::read(path).map_err(|e| io("checkpoint", path, e))?;
    let npy = npyz::NpyFile::new(&bytes[..]).map_err(|e| io("checkpoint", path, e))?;
    if npy.shape() != [n as u64, n as u64] || npy.order() != npyz::Order::C {
        return Err(io(
            "checkpoint",
            path,
            format!("expected a C-order {n}x{n} array"),
        ));
    }
    let data: Vec<f64> = npy
        .into_vec::<f64>()
        .map_err(|e| io("checkpoint", path, e))?;
    Ok(Mat::from_fn(n, n, |i, j| data[i * n + j]))
}

/// Bins each f32 plane to pitch `p_hat` (sums over the effective pixel; identity when p̂
/// equals the optics' pitch) and returns the binned stack and the integrator plan.
pub fn bin_planes(
    planes: &[Mat<f32>],
    pitch: f64,
    p_hat: f64,
    depths: &[f64],
) -> Result<(PsfStack, Option<BoxIntegrator>), FisherError> {
    if (p_hat / pitch - 1.0).abs() < 1e-12 {
        return Ok((PsfStack::from_f32(planes, depths, pitch)?, None));
    }
    let (r, c) = planes
        .first()
        .map(|m| (m.nrows(), m.ncols()))
        .unwrap_or((0, 0));
    let op = BoxIntegrator::new(r, c, pitch, p_hat, pitch).map_err(|e| {
        FisherError::InvalidParameter {
            name: "sensor_pitch_m",
            value: p_hat,
            why: leak(e.to_string()),
        }
    })?;
    let binned = planes
        .iter()
        .map(|p| op.forward(p))
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| FisherError::Shape {
            name: "planes",
            why: e.to_string(),
        })?;
    Ok((PsfStack::from_f32(&binned, depths, p_hat)?, Some(op)))
}

fn leak(s: String) -> &'static str {
    // Error reasons are &'static; integrator errors are rare and tiny, so leaking is fine.
    Box::leak(s.into_boxed_str())
}

/// One Adam iteration on `state`; returns the record of the losses evaluated before the step.
pub fn init_step(
    model: &dyn PsfModel,
    grid: &ApertureGrid,
    cfg: &InitConfig,
    state: &mut InitState,
) -> Result<InitRecord, FisherError> {
    check_positive("lr_phase", cfg.lr_phase)?;
    check_positive("lr_log_var", cfg.lr_log_var)?;
    let optics = |e: nanoeye_optics::OpticsError| FisherError::Shape {
        name: "optics",
        why: e.to_string(),
    };
    let map = PhaseMap::phase_only(*grid, state.phase.clone()).map_err(optics)?;
    let st = model.forward(&map, &cfg.depths_m, None).map_err(optics)?;
    let (stack, op) = bin_planes(&st.planes, st.pitch_m, cfg.sensor_pitch_m, &cfg.depths_m)?;
    let loss = InitLoss {
        precision: Precision { noise: cfg.noise },
        ..InitLoss::default()
    };
    let eval = loss.evaluate(&stack, &state.log_vars)?;
    if !eval.value.is_finite() {
        return Err(FisherError::InvalidParameter {
            name: "l_init",
            value: eval.value,
            why: "loss is not finite",
        });
    }
    // ∂L/∂(optics planes) through the sensor's box integration.
    let mut grads = Vec::with_capacity(st.planes.len());
    for (k, g) in eval.grad.planes.iter().enumerate() {
        match &op {
            None => grads.push(g.clone()),
            Some(op) => {
                let g32 = Mat::from_fn(g.nrows(), g.ncols(), |i, j| g[(i, j)] as f32);
                let r = op
                    .vjp(&st.planes[k], &g32)
                    .map_err(|e| FisherError::Shape {
                        name: "planes",
                        why: e.to_string(),
                    })?;
                grads.push(Mat::from_fn(
                    r.d_image.nrows(),
                    r.d_image.ncols(),
                    |i, j| f64::from(r.d_image[(i, j)]),
                ));
            }
        }
    }
    let gphi = model
        .vjp(&map, &cfg.depths_m, &grads, None)
        .map_err(optics)?
        .phase_rad;
    let t = (state.iteration + 1) as i32;
    let (c1, c2) = (1.0 - BETA1.powi(t), 1.0 - BETA2.powi(t));
    for j in 0..gphi.ncols() {
        for i in 0..gphi.nrows() {
            let g = gphi[(i, j)];
            if !g.is_finite() {
                return Err(FisherError::InvalidParameter {
                    name: "phase_gradient",
                    value: g,
                    why: "not finite",
                });
            }
            let m = BETA1 * state.m[(i, j)] + (1.0 - BETA1) * g;
            let v = BETA2 * state.v[(i, j)] + (1.0 - BETA2) * g * g;
            state.m[(i, j)] = m;
            state.v[(i, j)] = v;
            state.phase[(i, j)] -= cfg.lr_phase * (m / c1) / ((v / c2).sqrt() + ADAM_EPS);
        }
    }
    for k in 0..3 {
        let g = eval.d_log_vars[k];
        state.s_m[k] = BETA1 * state.s_m[k] + (1.0 - BETA1) * g;
        state.s_v[k] = BETA2 * state.s_v[k] + (1.0 - BETA2) * g * g;
        state.log_vars[k] -=
            cfg.lr_log_var * (state.s_m[k] / c1) / ((state.s_v[k] / c2).sqrt() + ADAM_EPS);
        state.log_vars[k] =
            state.log_vars[k].clamp(-crate::KENDALL_S_LIMIT, crate::KENDALL_S_LIMIT);
    }
    let rec = InitRecord {
        iteration: state.iteration,
        l_init: eval.value,
        terms: eval.terms,
        log_vars: state.log_vars,
    };
    state.iteration += 1;
    state.history.push(rec.clone());
    Ok(rec)
}

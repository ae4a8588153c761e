//! The simulated camera, end to end: stored depth layers → radiometry → per-layer PSFs (optics)
//! → occlusion-aware S1 on the native grid → sensor at p̂ (S2) → normalised network input, and
//! the reverse: ∂L/∂input → ∂L/∂p̂ and ∂L/∂PSF, accumulated over a batch (and over the subnets
//! of a sandwich step) before one PSF VJP to ∂L/∂φ.
//!
//! Conventions fixed here, in one place:
//! - Layers: stored near to far with premultiplied radiance; S1 runs back to front.
//! - Depth: slab k of ray distance [near, far) gets the on-axis PSF of the axial depth
//!   z_k = (near + far)/2 (docs/chain.md gives the error this carries off axis).
//! - PSF normalisation: the PSF model returns fractions of the aperture power per native pixel,
//!   summing to η_k < 1 where light leaves the window. The radiance term uses P_k (light
//!   outside the window is lost), the occlusion term uses P̂_k = P_k/η_k, so an opaque layer
//!   (α ≡ 1 over more than the PSF's support) hides everything behind it exactly.
//!   Implemented as S1 with kernel P̂_k and radiance L_k, η_k multiplying its convolution
//!   (so a frame's layer spectra do not depend on the lens, crate::spectra).
//! - Units: the S1 image is photons per base-pixel area (sensor convention); the network input
//!   is x = (DN − black level)/(max DN − black level), ≈ [0, 1].

use crate::error::{Result, SearchError, param, positive};
use crate::geometry::{NativeGrid, PitchGrid};
use crate::radiometry::Radiometry;
use crate::spectra::SpectraStore;
use crate::split::{DepthSplit, OneProcess, map_gather};
use faer::Mat;
use nanoeye_datagen::render::{Dataset, FrameRecord, LayerSpec, Light, StoredFrame, Subject};
use nanoeye_datagen::states::State;
use nanoeye_gaze::Camera;
use nanoeye_nets::Tensor;
use nanoeye_optics::psf::{add_cells, depths_with_gradient};
use nanoeye_optics::{
    ApertureGrid, AsmPsf, KernelGradAccumulator, KernelSpectra, LayerSpectra, LayeredImager,
    PhaseMap, PsfConfig, PsfStack, PsfUsage, S1Tape, SpectralLayer,
};
use nanoeye_sensor::{CmosSensor, NoiseMode, Sensor, SensorConfig, SensorTape};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::sync::{Arc, Mutex};

/// Parameters of the camera chain beyond the dataset's geometry.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ChainConfig {
    /// Radiometry (aperture, exposure, illuminator).
    pub radiometry: Radiometry,
    /// Sensor (base pitch, QE, noise, ADC); `noise` and `quantize` apply to the forward pass.
    pub sensor: SensorConfig,
    /// Metasurface sampling step Δ (m) of the phase map.
    pub aperture_step_m: f64,
    /// PSF window side (m); rounded to an odd number of native pixels so the kernel has a
    /// centre pixel.
    pub psf_window_m: f64,
    /// What the calibration head is trained to estimate (S8's Δt*).
    #[serde(default)]
    pub slip_target: SlipTarget,
}

/// The slippage target Δt* of S8, from a frame's state.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SlipTarget {
    /// The camera's translation (m), as S11 is written.
    #[default]
    Translation,
    /// The translation with the camera's rotation folded in about the eye centre, so that
    /// S11's translation-only model costs the rotation's angle
    /// (`Camera::eye_equivalent_slip`, docs/gaze.md).
    EyeEquivalent,
}

impl SlipTarget {
    /// Δt* (m) for `state` seen by `camera` (only its nominal position matters).
    pub fn of(self, camera: &Camera, state: &State) -> [f64; 3] {
        match self {
            SlipTarget::Translation => state.slip_m,
            SlipTarget::EyeEquivalent => {
                camera.eye_equivalent_slip(state.slip_m, state.cam_rot_rad)
            }
        }
    }
}

impl Default for ChainConfig {
    /// Default radiometry and sensor; Δ = 1.5 µm (PSF converged to ~2e-4 of the peak,
    /// docs/bench/optics.md); a 192 µm window (5× the 17 mm defocus blur of the hyperbolic
    /// lens).
    fn default() -> Self {
        ChainConfig {
            radiometry: Radiometry::default(),
            sensor: SensorConfig::default(),
            aperture_step_m: 1.5e-6,
            psf_window_m: 192e-6,
            slip_target: SlipTarget::Translation,
        }
    }
}

/// The camera chain for one native grid and one set of depth slabs.
pub struct CameraChain {
    cfg: ChainConfig,
    native: NativeGrid,
    spec: LayerSpec,
    depths_m: Vec<f64>,
    psf: AsmPsf,
    imager: LayeredImager,
    /// Photons per base-pixel area per unit rendered radiance, per native pixel, stored as its
    /// transpose (W×H): row-major like the stored layers it weights, for S1's streamed pack.
    scale_t: Mat<f32>,
    /// Who computes which depth of a PSF stack or PSF VJP ([`OneProcess`] unless set).
    split: Arc<dyn DepthSplit>,
    /// The last stack [`CameraChain::psfs`] computed and what it was computed for.
    memo: Mutex<Option<PsfMemo>>,
    /// S1 images of frames imaged without a tape under one PSF stack (see [`S1Cache`]).
    s1_cache: Mutex<S1Cache>,
    /// Whether tape-less forwards read and fill `s1_cache` ([`CameraChain::set_s1_cache`]).
    s1_cache_on: bool,
    /// Frames' layer spectra, shared with the process's chains of the same grid and weight.
    spectra: Arc<SpectraStore>,
}

/// Most bytes of S1 images kept by [`S1Cache`] (128 frames at 1280×800, 2,048 at 320×200).
const S1_CACHE_BYTES: usize = 512 << 20;

/// S1 images (after the clamp at zero) of frames imaged under the stack with id `psfs`. An
/// image depends on the frame and the PSF stack only — not on p̂, the noise or the network —
/// so while a stack stays (a fixed lens's training, BN recalibration, head refit and
/// evaluation) a frame seen again skips S1. Filled until [`S1_CACHE_BYTES`], emptied when
/// another stack comes. Only forwards that keep no S1 tape read or fill it.
#[derive(Default)]
struct S1Cache {
    psfs: u64,
    images: std::collections::HashMap<(u64, u64), Arc<Mat<f32>>>,
    bytes: usize,
}

impl S1Cache {
    /// The image of frame `key` under stack `psfs`, if kept; empties the cache when `psfs`
    /// is not the stack it holds images of.
    fn get(&mut self, psfs: u64, key: (u64, u64)) -> Option<Arc<Mat<f32>>> {
        if self.psfs != psfs {
            *self = S1Cache {
                psfs,
                ..S1Cache::default()
            };
        }
        self.images.get(&key).cloned()
    }

    fn put(&mut self, psfs: u64, key: (u64, u64), img: &Arc<Mat<f32>>) {
        let size = img.nrows() * img.ncols() * std::mem::size_of::<f32>();
        if self.psfs == psfs
            && self.bytes + size <= S1_CACHE_BYTES
            && self.images.insert(key, img.clone()).is_none()
        {
            self.bytes += size;
        }
    }
}

/// Ids of computed PSF stacks: a kept stack handed out again keeps its id.
static NEXT_PSFS_ID: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(1);

/// A PSF stack with the exact phase map (bit patterns) and slabs it belongs to. A fixed lens
/// (the baselines' training, BN recalibration, every evaluation) asks for the same stack once
/// per batch; p̂ does not enter it (the PSFs live on the native grid), so it is computed once.
struct PsfMemo {
    grid: ApertureGrid,
    phase_bits: Vec<u64>,
    amplitude_bits: Vec<u64>,
    active: Vec<bool>,
    psfs: Arc<StepPsfs>,
}

impl PsfMemo {
    fn bits(m: &Mat<f64>) -> Vec<u64> {
        m.col_iter()
            .flat_map(|c| c.iter())
            .map(|v| v.to_bits())
            .collect()
    }

    fn same(bits: &[u64], m: &Mat<f64>) -> bool {
        bits.len() == m.nrows() * m.ncols()
            && m.col_iter()
                .flat_map(|c| c.iter())
                .zip(bits)
                .all(|(v, &b)| v.to_bits() == b)
    }

    fn matches(&self, map: &PhaseMap, active: &[bool]) -> bool {
        self.grid == map.grid
            && self.active == active
            && Self::same(&self.phase_bits, &map.phase_rad)
            && Self::same(&self.amplitude_bits, &map.amplitude)
    }
}

/// The PSFs of one step, normalised as the chain uses them, with their spectra on S1's grid.
pub struct StepPsfs {
    /// The model's stack (fractions of aperture power; zero planes where inactive).
    pub stack: PsfStack,
    /// P̂_k = P_k / η_k (f32, zero where inactive).
    pub unit: Vec<Mat<f32>>,
    /// η_k = Σ P_k (0 where inactive).
    pub eta: Vec<f64>,
    /// FFTs of P̂_k for S1 (computed once, shared by every frame of the step).
    spectra: KernelSpectra,
    /// Unique per computed stack (the S1 image cache's key).
    id: u64,
}

/// A loaded frame and its targets on the p̂ grid.
#[derive(Clone, Debug)]
pub struct ChainFrame {
    /// Global frame id: seeds its noise stream.
    pub id: u64,
    /// The dataset the frame was loaded from (a hash of its directory), with `id` its key in
    /// the S1 image cache; `None` (a frame built in memory) is never cached.
    pub source: Option<u64>,
    /// Stored layers and masks (native grid).
    pub data: StoredFrame,
    /// Its record (state, gaze, landmarks).
    pub record: FrameRecord,
}

impl ChainFrame {
    /// The frame as if built in memory (`source: None`): the chain keeps nothing for it, so
    /// S1 computes its layer spectra in every call (for comparing the two paths).
    pub fn unkeyed(&self) -> ChainFrame {
        ChainFrame {
            source: None,
            ..self.clone()
        }
    }
}

/// Forward results of a batch.
pub struct ChainForward {
    /// Network input (N, 1, H, W) on the p̂ grid.
    pub input: Tensor,
    /// Mean photo-electrons per output pixel before noise (N images, p̂ grid).
    pub electrons: Vec<Mat<f32>>,
    /// Digital numbers per output pixel (N images).
    pub dn: Vec<Mat<f32>>,
    /// Visible-pupil coverage on the p̂ grid (N, 1, H, W), the segmentation target.
    pub mask: Tensor,
    /// Slippage targets Δt* in mm (N, 3, 1, 1), as [`ChainConfig::slip_target`] defines them.
    pub slip_mm: Tensor,
    /// True pupil centre in p̂ pixels (None where it projects behind the camera).
    pub pupil_center_px: Vec<Option<[f64; 2]>>,
    /// The p̂ grid.
    pub grid: PitchGrid,
    tapes: Vec<SensorTape>,
    /// S1's tapes, `None` for a forward that keeps none (see [`CameraChain::forward_with`]);
    /// a frame whose layer spectra the store does not keep has them on its tape.
    s1: Vec<Option<S1Tape>>,
}

/// Gradients of a scalar loss w.r.t. the optical and sensor parameters.
#[derive(Clone, Debug)]
pub struct ChainGrad {
    /// ∂L/∂φ (per radian), aperture grid n×n.
    pub phase_rad: Mat<f64>,
    /// ∂L/∂p̂ (per metre).
    pub p_hat: f64,
}

/// ∂L/∂PSF accumulated over frames (and subnets) before the one PSF VJP of a step: ∂L/∂P̂_k
/// in the frequency domain, ⟨∂L/∂I⁽ᵏ⁾, conv_k⟩ for ∂L/∂η_k, and ∂L/∂p̂.
pub struct PsfGradAccumulator {
    /// ∂L/∂P̂ per kernel; `None` for an accumulator of ∂L/∂p̂ alone (a fixed lens).
    kernels: Option<KernelGradAccumulator>,
    /// ∂L/∂p̂ (per metre).
    p_hat: f64,
}

/// Frames whose S1 adjoints run at once, at least: their per-frame accumulators are merged
/// in frame order, so the sum depends neither on the thread count nor on the chunk, and
/// memory stays bounded.
const BACKWARD_CHUNK: usize = 4;

/// Bytes of per-frame accumulators a backward keeps alive at once: more frames than
/// [`BACKWARD_CHUNK`] run together where they fit, since each chunk ends with a wait for its
/// slowest frame (on tiles, 3.2 MB a paper-size frame: a batch of 16 in one chunk; the
/// whole grid's 74 MB a frame: chunks of four).
const BACKWARD_BYTES: usize = 64 << 20;

impl PsfGradAccumulator {
    /// ∂L/∂p̂ accumulated so far (per metre).
    pub fn p_hat(&self) -> f64 {
        self.p_hat
    }
}

/// The PSF model's configuration and aperture grid for native pixels of `p` (m): a square
/// window of an odd number of pixels spanning about `cfg.psf_window_m`.
fn psf_setup(p: f64, cfg: &ChainConfig) -> Result<(PsfConfig, ApertureGrid)> {
    let half = (0.5 * cfg.psf_window_m / p).round().max(1.0) as usize;
    let r = &cfg.radiometry;
    let grid = ApertureGrid::new(r.aperture_m, cfg.aperture_step_m)?;
    let psf_cfg = PsfConfig {
        wavelength_m: r.wavelength_m,
        sensor_distance_m: r.sensor_distance_m,
        pitch_m: p,
        window_px: 2 * half + 1,
        ..PsfConfig::default()
    };
    Ok((psf_cfg, grid))
}

impl CameraChain {
    /// A chain for `native` (the dataset's camera) with depth slabs `spec`, for radiance
    /// rendered with an illuminator of `render_w_per_sr` at `render_distance_m` from the cornea.
    pub fn new(
        native: NativeGrid,
        spec: LayerSpec,
        render_w_per_sr: f64,
        render_distance_m: f64,
        cfg: ChainConfig,
    ) -> Result<CameraChain> {
        cfg.radiometry.validate()?;
        CmosSensor::new(cfg.sensor.clone())?;
        positive("aperture_step_m", cfg.aperture_step_m)?;
        positive("psf_window_m", cfg.psf_window_m)?;
        if spec.count == 0 || !(spec.near_m > 0.0 && spec.near_m < spec.far_m) {
            return Err(param(
                "layers",
                format!("{spec:?}: need count ≥ 1, 0 < near < far"),
            ));
        }
        let p = native.pitch_m();
        let base = cfg.sensor.base_pitch;
        if p < base * (1.0 - 1e-9) {
            return Err(param(
                "base_pitch",
                format!(
                    "the dataset's {:.3} µm pixels are finer than the sensor's {:.3} µm base pitch",
                    p * 1e6,
                    base * 1e6
                ),
            ));
        }
        let (psf_cfg, grid) = psf_setup(p, &cfg)?;
        let wp = psf_cfg.window_px;
        let psf = AsmPsf::new(psf_cfg, grid)?;
        let (h, w) = native.shape();
        let imager = LayeredImager::new(h, w, wp)?;
        let dz = (spec.far_m - spec.near_m) / spec.count as f64;
        let depths_m = (0..spec.count)
            .map(|k| spec.near_m + dz * (k as f64 + 0.5))
            .collect();
        // Radiometry per base-pixel area: the sensor's input unit.
        let mut cam = native.camera.clone();
        cam.pixel_pitch_m = base;
        let scale = cfg
            .radiometry
            .scale_map(&cam, render_w_per_sr, render_distance_m)?;
        // What a frame's layer spectra depend on besides the frame: S1's grid and the weight.
        let fp = {
            use std::hash::{Hash, Hasher};
            let mut hs = std::collections::hash_map::DefaultHasher::new();
            (h, w, wp).hash(&mut hs);
            for c in scale.col_iter() {
                c.iter().for_each(|v| v.to_bits().hash(&mut hs));
            }
            hs.finish()
        };
        Ok(CameraChain {
            cfg,
            native,
            spec,
            depths_m,
            psf,
            imager,
            scale_t: scale.transpose().to_owned(),
            split: Arc::new(OneProcess),
            memo: Mutex::new(None),
            s1_cache: Mutex::new(S1Cache::default()),
            s1_cache_on: true,
            spectra: SpectraStore::shared(fp),
        })
    }

    /// Shares the depth planes of every PSF stack and PSF VJP of this chain among the
    /// processes of `split` (crate::split): every process must then make the same calls on the
    /// chain in the same order; the results are the bits a single process gets.
    pub fn set_split(&mut self, split: Arc<dyn DepthSplit>) {
        self.split = split;
    }

    /// Whether forwards without S1's tape keep the S1 images they compute for the next
    /// forward of the same frames under the same stack (default on; up to 512 MiB). Off for
    /// a caller that images each frame once, e.g. a simulation, which would only fill it.
    pub fn set_s1_cache(&mut self, on: bool) {
        self.s1_cache_on = on;
        if !on && let Ok(mut c) = self.s1_cache.lock() {
            *c = S1Cache::default();
        }
    }

    /// The processes sharing this chain's PSF work.
    pub fn split(&self) -> &dyn DepthSplit {
        &*self.split
    }

    /// A chain for a dataset's native grid, slabs and illuminator.
    pub fn for_dataset(ds: &Dataset, cfg: ChainConfig) -> Result<CameraChain> {
        let cam = &ds.manifest.rig.camera;
        let light = Light::near_camera(&cam.nominal_pose());
        let apex = [0.0, 0.0, Subject::default().cornea_apex_m];
        let d = nanoeye_gaze::geom::norm(nanoeye_gaze::geom::sub(light.position_m, apex));
        CameraChain::new(
            NativeGrid::new(cam.clone())?,
            ds.layer_spec(),
            ds.manifest.light_intensity_w_per_sr,
            d,
            cfg,
        )
    }

    /// Bytes the PSF model of a chain on `native_pitch_m` pixels with `layers` depth slabs
    /// needs when used as `usage` says, over `threads` threads ([`AsmPsf::memory_bytes`], and
    /// for a training the chain's own copies of the phase gradient): weighed before
    /// [`CameraChain::new`] builds anything.
    pub fn psf_memory_bytes(
        native_pitch_m: f64,
        layers: usize,
        cfg: &ChainConfig,
        threads: usize,
        usage: PsfUsage,
    ) -> Result<u64> {
        positive("aperture_step_m", cfg.aperture_step_m)?;
        positive("psf_window_m", cfg.psf_window_m)?;
        let (psf_cfg, grid) = psf_setup(native_pitch_m, cfg)?;
        let model = AsmPsf::memory_bytes(&psf_cfg, &grid, layers, threads, usage)?;
        // The chain's own per-sample arrays, in f64 or u64: always the caller's phase map
        // (phase and amplitude) and the memo's bit copies of both (left out until a helper's
        // audit: `sim --aperture-step-um 0.2` was estimated at 2.21 GiB and peaked at 2.78,
        // an allocation abort under a limit between them); in a training also `phase_vjp`'s
        // copy and gather of each depth's term, and the sum, φ and its Adam moments.
        let per_sample = 4 + match usage {
            PsfUsage::Training => 2 * layers as u64 + 4,
            _ => 0,
        };
        let own = (grid.n as u64).pow(2).saturating_mul(8 * per_sample);
        Ok(model.saturating_add(own))
    }

    /// The configuration.
    pub fn config(&self) -> &ChainConfig {
        &self.cfg
    }

    /// The native grid.
    pub fn native(&self) -> &NativeGrid {
        &self.native
    }

    /// Axial depth z_k (m) whose PSF slab k uses.
    pub fn depths_m(&self) -> &[f64] {
        &self.depths_m
    }

    /// The aperture grid the phase map must be sampled on.
    pub fn aperture_grid(&self) -> &ApertureGrid {
        self.psf.grid()
    }

    /// PSF window side in native pixels (odd).
    pub fn psf_px(&self) -> usize {
        self.psf.config().window_px
    }

    /// Side in native pixels of the tiles S1's spectral path runs on (`None`: the whole
    /// padded grid; docs/optics.md, "Tiles").
    pub fn s1_tile(&self) -> Option<usize> {
        self.imager.tile()
    }

    /// The PSF model.
    pub fn psf_model(&self) -> &AsmPsf {
        &self.psf
    }

    /// Loads frames `ids` of `ds` (checks they fit this chain's grid and slabs).
    pub fn load(&self, ds: &Dataset, ids: &[usize]) -> Result<Vec<ChainFrame>> {
        if ds.shape() != self.native.shape() || ds.layer_spec() != self.spec {
            return Err(param(
                "dataset",
                format!(
                    "{}: grid {:?} / slabs {:?} differ from the chain's {:?} / {:?}",
                    ds.dir.display(),
                    ds.shape(),
                    ds.layer_spec(),
                    self.native.shape(),
                    self.spec
                ),
            ));
        }
        // The directory, its frame count and when its records were written: a directory
        // rendered again in the same process (same path, new frames) is another source for
        // the S1 and layer-spectra caches.
        let source = {
            use std::hash::{Hash, Hasher};
            let dir = std::fs::canonicalize(&ds.dir).unwrap_or_else(|_| ds.dir.clone());
            let written = std::fs::metadata(dir.join("frames.jsonl"))
                .and_then(|m| m.modified())
                .ok();
            let mut h = std::collections::hash_map::DefaultHasher::new();
            (dir, ds.len(), written).hash(&mut h);
            h.finish()
        };
        // Every stored layer is covered (the renderer writes non-empty slabs only).
        self.spectra.admit(source, || {
            let layers: usize = ds.records.iter().map(|r| r.layers.len()).sum();
            layers.saturating_mul(LayerSpectra::layer_bytes(&self.imager))
        });
        ids.par_iter()
            .map(|&i| {
                Ok(ChainFrame {
                    id: i as u64,
                    source: Some(source),
                    data: ds.load(i)?,
                    record: ds.records[i].clone(),
                })
            })
            .collect()
    }

    /// Which slabs hold content in any of `frames`.
    pub fn active(&self, frames: &[ChainFrame]) -> Vec<bool> {
        let mut a = vec![false; self.spec.count];
        for f in frames {
            for l in &f.data.layers {
                if l.info.index < a.len() {
                    a[l.info.index] = true;
                }
            }
        }
        a
    }

    /// PSFs of the slabs `active` for phase map `map`, normalised (one stack per step).
    /// The active planes are computed through the chain's [`DepthSplit`] (each process its
    /// share, then all-gathered in f64), so every process gets the same stack.
    /// The stack of the last call is kept: the same map (bit for bit) and slabs return it
    /// without any work, and every process of a split makes the same decision.
    pub fn psfs(&self, map: &PhaseMap, active: &[bool]) -> Result<Arc<StepPsfs>> {
        let memo = self.memo.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(m) = memo.as_ref().filter(|m| m.matches(map, active)) {
            return Ok(Arc::clone(&m.psfs));
        }
        drop(memo);
        let psfs = Arc::new(self.compute_psfs(map, active)?);
        *self.memo.lock().unwrap_or_else(|e| e.into_inner()) = Some(PsfMemo {
            grid: map.grid,
            phase_bits: PsfMemo::bits(&map.phase_rad),
            amplitude_bits: PsfMemo::bits(&map.amplitude),
            active: active.to_vec(),
            psfs: Arc::clone(&psfs),
        });
        Ok(psfs)
    }

    fn compute_psfs(&self, map: &PhaseMap, active: &[bool]) -> Result<StepPsfs> {
        let count = self.depths_m.len();
        if active.len() != count {
            return Err(param(
                "active",
                format!("{} flags for {count} slabs", active.len()),
            ));
        }
        let wp = self.psf_px();
        let items: Vec<usize> = (0..count).filter(|&k| active[k]).collect();
        let got = map_gather(&*self.split, &items, wp * wp, |mine| {
            let mut mask = vec![false; count];
            for &k in mine {
                mask[k] = true;
            }
            let planes = self.psf.planes_f64(map, &self.depths_m, Some(&mask))?;
            Ok(mine
                .iter()
                .map(|&k| planes[k].as_ref().map_or_else(Vec::new, col_major))
                .collect())
        })?;
        let mut planes: Vec<Option<Mat<f64>>> = vec![None; count];
        for (&k, v) in items.iter().zip(&got) {
            planes[k] = Some(Mat::from_fn(wp, wp, |i, j| v[j * wp + i]));
        }
        let stack = PsfStack::from_planes(&self.depths_m, self.psf.config().pitch_m, wp, &planes);
        let mut eta = vec![0.0; stack.planes.len()];
        let mut unit = Vec::with_capacity(stack.planes.len());
        for (k, p) in stack.planes.iter().enumerate() {
            let s: f64 = p
                .col_iter()
                .map(|c| c.iter().map(|&v| v as f64).sum::<f64>())
                .sum();
            if active[k] && s <= 1e-9 {
                return Err(param(
                    "phase",
                    format!(
                        "the lens sends {s:e} of the aperture power into the PSF window at depth {:.2} mm",
                        self.depths_m[k] * 1e3
                    ),
                ));
            }
            eta[k] = if active[k] { s } else { 0.0 };
            let inv = if active[k] { 1.0 / s } else { 0.0 };
            unit.push(Mat::from_fn(p.nrows(), p.ncols(), |i, j| {
                (p[(i, j)] as f64 * inv) as f32
            }));
        }
        let kernels: Vec<Option<&Mat<f32>>> = unit
            .iter()
            .zip(active)
            .map(|(u, &a)| a.then_some(u))
            .collect();
        let spectra = self.imager.kernel_spectra(&kernels)?;
        Ok(StepPsfs {
            stack,
            unit,
            eta,
            spectra,
            id: NEXT_PSFS_ID.fetch_add(1, std::sync::atomic::Ordering::Relaxed),
        })
    }

    /// Sensor-plane image of one frame (photons per base-pixel area, native grid): S1, and
    /// the tape its PSF VJP needs. A frame whose layer spectra are not kept has them
    /// computed by S1 and recorded on its tape; they move to the store when its dataset's
    /// spectra all fit the budget and while it has room (a lens in training images the frame
    /// under a new stack every step), else stay on the tape for this step's backward alone.
    pub fn optical_image(&self, f: &ChainFrame, psfs: &StepPsfs) -> Result<(Mat<f32>, S1Tape)> {
        let layers = self.spectral_layers(f, psfs);
        let kept = self.kept_spectra(f);
        // Without kept spectra the tiled path packs every layer; its pass over the planes to
        // find the tiles is done once per frame.
        let cover = match kept {
            None => self.frame_cover(f, &layers)?,
            Some(_) => None,
        };
        let (img, mut tape) = self
            .imager
            .forward_spectral_covered(&layers, &psfs.spectra, kept.as_deref(), cover.as_deref())
            .map_err(|e| Self::frame_error(f, e))?;
        if let (None, Some(key)) = (&kept, f.source.map(|s| (s, f.id))) {
            let bytes = tape.spectra_bytes();
            if bytes > 0 {
                self.spectra.keep(key, bytes, || tape.take_spectra());
            }
        }
        Ok((Self::clamped(img), tape))
    }

    /// [`Self::optical_image`] without the tape; reads kept layer spectra but keeps none: a
    /// fixed lens and evaluation see a frame again under the same stack, which the S1 image
    /// cache serves.
    fn optical_image_alone(&self, f: &ChainFrame, psfs: &StepPsfs) -> Result<Mat<f32>> {
        let layers = self.spectral_layers(f, psfs);
        let kept = self.kept_spectra(f);
        let img = self
            .imager
            .image_spectral(&layers, &psfs.spectra, kept.as_deref())
            .map_err(|e| Self::frame_error(f, e))?;
        Ok(Self::clamped(img))
    }

    /// Frame `f`'s layer cover for S1's tiled path (`layers` its spectral layers), kept in
    /// the store from its first computation on; `None` for an untiled imager or a frame of no
    /// dataset.
    fn frame_cover(
        &self,
        f: &ChainFrame,
        layers: &[SpectralLayer],
    ) -> Result<Option<Arc<nanoeye_optics::LayerCover>>> {
        // An untiled imager makes none: no lookup on its hot path.
        let (Some(key), Some(_)) = (f.source.map(|s| (s, f.id)), self.imager.tile()) else {
            return Ok(None);
        };
        if let Some(c) = self.spectra.cover(key) {
            return Ok(Some(c));
        }
        let cover = self
            .imager
            .layer_cover(layers)
            .map_err(|e| Self::frame_error(f, e))?;
        Ok(cover.map(|c| {
            let c = Arc::new(c);
            self.spectra.keep_cover(key, c.clone());
            c
        }))
    }

    /// The kept layer spectra of a frame from a dataset.
    fn kept_spectra(&self, f: &ChainFrame) -> Option<Arc<LayerSpectra>> {
        f.source.and_then(|s| self.spectra.get((s, f.id)))
    }

    /// Frames whose layer spectra this chain's store keeps (see crate::spectra).
    pub fn cached_layer_spectra(&self) -> usize {
        self.spectra.len()
    }

    /// An S1 error named by its frame: in a dataset of hundreds, "layer 7 is not finite"
    /// alone does not say which file to look at. S1 numbers the layers it was given, back
    /// to front; its kernel is the frame's depth slab (`index` in the record's "layers").
    fn frame_error(f: &ChainFrame, e: nanoeye_optics::OpticsError) -> SearchError {
        param(
            "frames",
            format!("frame {}: optics (kernel = depth slab): {e}", f.id),
        )
    }

    /// FFT round-off leaves values of order 1e-16 of the peak below zero where there is no
    /// light; intensity is non-negative, so they are cut (the VJP treats the cut as identity:
    /// it moves nothing larger than round-off).
    fn clamped(mut img: Mat<f32>) -> Mat<f32> {
        for j in 0..img.ncols() {
            for v in img.col_mut(j).iter_mut() {
                *v = v.max(0.0);
            }
        }
        img
    }

    /// S1 images kept for frames seen again under the same PSF stack (at most
    /// 512 MiB of them).
    pub fn cached_s1_images(&self) -> usize {
        self.s1_cache.lock().map(|c| c.images.len()).unwrap_or(0)
    }

    /// S1's image of `f` without a tape: the cached one when `f` came from a dataset and was
    /// imaged under `psfs` before, else computed (and kept while the cache has room); with the
    /// cache off, computed.
    fn cached_optical_image(&self, f: &ChainFrame, psfs: &StepPsfs) -> Result<Arc<Mat<f32>>> {
        let key = f.source.filter(|_| self.s1_cache_on).map(|s| (s, f.id));
        if let Some(key) = key {
            let hit = self
                .s1_cache
                .lock()
                .ok()
                .and_then(|mut c| c.get(psfs.id, key));
            if let Some(img) = hit {
                return Ok(img);
            }
        }
        let img = Arc::new(self.optical_image_alone(f, psfs)?);
        if let (Some(key), Ok(mut c)) = (key, self.s1_cache.lock()) {
            c.put(psfs.id, key, &img);
        }
        Ok(img)
    }

    /// The frame's layers back to front for S1, each radiance scaled on the fly to photons
    /// by its slab's PSF energy η and the per-pixel radiometric factor.
    fn spectral_layers<'a>(&'a self, f: &'a ChainFrame, psfs: &StepPsfs) -> Vec<SpectralLayer<'a>> {
        f.data
            .layers
            .iter()
            .rev()
            .map(|l| {
                let k = l.info.index;
                SpectralLayer {
                    radiance: l.radiance(),
                    alpha: l.alpha(),
                    kernel: k,
                    gain: psfs.eta[k] as f32,
                    weight: Some(self.scale_t.transpose()),
                }
            })
            .collect()
    }

    /// Runs the batch forward at effective pitch `p_hat_m` with noise mode `noise` drawn from
    /// `seed` (frame `id` selects the stream, so a frame's noise does not depend on its batch),
    /// keeping what a backward with ∂L/∂PSF needs.
    pub fn forward(
        &self,
        frames: &[ChainFrame],
        psfs: &StepPsfs,
        p_hat_m: f64,
        noise: NoiseMode,
        seed: u64,
    ) -> Result<ChainForward> {
        self.forward_with(frames, psfs, p_hat_m, noise, seed, true)
    }

    /// [`Self::forward`], keeping S1's tape only with `psf_grad`. Without it (a fixed lens's
    /// training, evaluation) the forward allows a backward into a
    /// [`Self::pitch_accumulator`] only, and a frame's S1 image comes from the chain's cache
    /// when the same frame was imaged under the same PSF stack before (the same bits).
    pub fn forward_with(
        &self,
        frames: &[ChainFrame],
        psfs: &StepPsfs,
        p_hat_m: f64,
        noise: NoiseMode,
        seed: u64,
        psf_grad: bool,
    ) -> Result<ChainForward> {
        if frames.is_empty() {
            return Err(param("frames", "empty batch"));
        }
        let grid = self.native.at(p_hat_m)?;
        let mut scfg = self.cfg.sensor.clone();
        scfg.noise = noise;
        if noise != NoiseMode::Poisson {
            // Rounding to DN has no useful derivative; the differentiable modes skip it.
            scfg.quantize = false;
        }
        let sensor = CmosSensor::new(scfg)?;
        let base = self.native.pitch_m();
        let per: Vec<Result<_>> = frames
            .par_iter()
            .map(|f| {
                let (img, s1) = if psf_grad {
                    let (img, s1) = self.optical_image(f, psfs)?;
                    (Arc::new(img), Some(s1))
                } else {
                    (self.cached_optical_image(f, psfs)?, None)
                };
                let (dn, tape) = sensor.forward(&img, base, p_hat_m, seed, f.id)?;
                let el = tape.mean_electrons().clone();
                let mask = grid.downsample_mask(&f.data.mask_visible_pupil)?;
                let state: State = f.record.state;
                let pose = grid.camera.slipped_pose(state.slip_m, state.cam_rot_rad);
                let pc = grid
                    .project(&pose, f.record.landmarks.pupil_center.world_m)
                    .ok();
                Ok((dn, tape, el, mask, pc, s1))
            })
            .collect();
        let (h, w) = grid.shape();
        let n = frames.len();
        let c = &self.cfg.sensor;
        let span = (c.max_dn() - c.black_level_dn) as f32;
        let black = c.black_level_dn as f32;
        let mut input = Tensor::zeros(n, 1, h, w);
        let mut mask = Tensor::zeros(n, 1, h, w);
        let mut slip = Tensor::zeros(n, 3, 1, 1);
        let (mut dns, mut els, mut tapes, mut pcs) = (vec![], vec![], vec![], vec![]);
        let mut s1s = Vec::with_capacity(n);
        for (b, r) in per.into_iter().enumerate() {
            let (dn, tape, el, m, pc, s1) = r?;
            s1s.push(s1);
            let xi = input.image_mut(b);
            let mi = &mut mask.data[b * h * w..(b + 1) * h * w];
            for i in 0..h {
                for j in 0..w {
                    xi[i * w + j] = (dn[(i, j)] - black) / span;
                    mi[i * w + j] = m[(i, j)];
                }
            }
            let target = self
                .cfg
                .slip_target
                .of(&grid.camera, &frames[b].record.state);
            for (a, v) in target.iter().enumerate() {
                slip.data[b * 3 + a] = (*v * 1e3) as f32;
            }
            dns.push(dn);
            els.push(el);
            tapes.push(tape);
            pcs.push(pc);
        }
        Ok(ChainForward {
            input,
            electrons: els,
            dn: dns,
            mask,
            slip_mm: slip,
            pupil_center_px: pcs,
            grid,
            tapes,
            s1: s1s,
        })
    }

    /// A zeroed accumulator for this chain's slabs.
    pub fn accumulator(&self) -> PsfGradAccumulator {
        PsfGradAccumulator {
            kernels: Some(self.imager.kernel_grad_accumulator(self.spec.count)),
            p_hat: 0.0,
        }
    }

    /// An accumulator of ∂L/∂p̂ alone, for a lens that does not train: [`Self::backward`]
    /// then runs the sensor's VJP only and skips S1's PSF adjoint (two FFTs per layer and
    /// frame) whose result nothing would read; [`Self::finish`] refuses it.
    pub fn pitch_accumulator(&self) -> PsfGradAccumulator {
        PsfGradAccumulator {
            kernels: None,
            p_hat: 0.0,
        }
    }

    /// Backward of [`Self::forward`] for ∂L/∂input `d_input` (N, 1, H, W): adds ∂L/∂p̂ and
    /// ∂L/∂PSF of the batch into `acc` (call once per subnet's gradient, or once with their sum;
    /// ∂L/∂p̂ only into a [`Self::pitch_accumulator`]).
    pub fn backward(
        &self,
        frames: &[ChainFrame],
        psfs: &StepPsfs,
        fwd: &ChainForward,
        d_input: &Tensor,
        acc: &mut PsfGradAccumulator,
    ) -> Result<()> {
        let (h, w) = fwd.grid.shape();
        if d_input.shape() != [frames.len(), 1, h, w] {
            return Err(param(
                "d_input",
                format!(
                    "shape {:?}, expected [{}, 1, {h}, {w}]",
                    d_input.shape(),
                    frames.len()
                ),
            ));
        }
        let c = &self.cfg.sensor;
        let inv_span = 1.0 / (c.max_dn() - c.black_level_dn) as f32;
        let mut scfg = c.clone();
        scfg.noise = NoiseMode::None;
        let sensor = CmosSensor::new(scfg)?;
        let psf_grad = acc.kernels.is_some();
        let frame_bytes = self.imager.kernel_grad_bytes(self.spec.count).max(1);
        let chunk = (BACKWARD_BYTES / frame_bytes).max(BACKWARD_CHUNK);
        for c0 in (0..frames.len()).step_by(chunk) {
            let c1 = (c0 + chunk).min(frames.len());
            let per: Vec<Result<_>> = (c0..c1)
                .into_par_iter()
                .map(|b| {
                    let f = &frames[b];
                    let gi = d_input.image(b);
                    let g_dn = Mat::from_fn(h, w, |i, j| gi[i * w + j] * inv_span);
                    // A fixed lens's step needs ∂L/∂p̂ alone: no image gradient is formed.
                    if !psf_grad {
                        return Ok((sensor.pitch_vjp(&fwd.tapes[b], &g_dn)?, None));
                    }
                    let sg = sensor.vjp(&fwd.tapes[b], &g_dn)?;
                    let Some(s1) = &fwd.s1[b] else {
                        return Err(param(
                            "acc",
                            "the forward kept no S1 tape (forward_with without psf_grad): \
                             backward into a pitch_accumulator(), or run forward()",
                        ));
                    };
                    let layers = self.spectral_layers(f, psfs);
                    // Kept ones, or (None) those on the tape when the forward recorded them.
                    let spectra = self.kept_spectra(f);
                    let mut local = self.imager.kernel_grad_accumulator(self.spec.count);
                    self.imager
                        .vjp_kernels(&layers, s1, &sg.d_image, &mut local, spectra.as_deref())
                        .map_err(|e| Self::frame_error(f, e))?;
                    Ok((sg.d_p_hat, Some(local)))
                })
                .collect();
            // Merged in frame order: the sum does not depend on the thread count.
            for r in per {
                let (dp, local) = r?;
                acc.p_hat += dp;
                if let (Some(k), Some(local)) = (acc.kernels.as_mut(), local) {
                    self.imager.merge_kernel_grads(k, local);
                }
            }
        }
        Ok(())
    }

    /// Adds to `acc` ∂L/∂p̂ through the segmentation target for ∂L/∂mask `d_mask`
    /// (N, 1, H, W; [`crate::task::TaskGrads::mask`]): the target is the pupil mask averaged
    /// onto the p̂ grid, so it moves with p̂ as the network input does, and a finite difference
    /// of the loss in p̂ sees both. Cheap: two box passes over each frame's native mask.
    pub fn target_backward(
        &self,
        frames: &[ChainFrame],
        fwd: &ChainForward,
        d_mask: &Tensor,
        acc: &mut PsfGradAccumulator,
    ) -> Result<()> {
        let (h, w) = fwd.grid.shape();
        if d_mask.shape() != [frames.len(), 1, h, w] || fwd.mask.shape() != d_mask.shape() {
            return Err(param(
                "d_mask",
                format!(
                    "shape {:?}, expected [{}, 1, {h}, {w}] (the forward's mask)",
                    d_mask.shape(),
                    frames.len()
                ),
            ));
        }
        let as_mat = |t: &Tensor, b: usize| {
            let d = &t.data[b * h * w..(b + 1) * h * w];
            Mat::from_fn(h, w, |i, j| d[i * w + j])
        };
        let per: Vec<Result<f64>> = frames
            .par_iter()
            .enumerate()
            .map(|(b, f)| {
                fwd.grid.mask_pitch_vjp(
                    &f.data.mask_visible_pupil,
                    &as_mat(d_mask, b),
                    &as_mat(&fwd.mask, b),
                )
            })
            .collect();
        // Added in frame order: the sum does not depend on the thread count.
        for r in per {
            acc.p_hat += r?;
        }
        Ok(())
    }

    /// The one PSF VJP of a step: ∂L/∂φ from the accumulated ∂L/∂P̂, ∂L/∂η
    /// (∂P̂/∂P = (I − P̂·1ᵀ)/η, ∂η/∂P = 1): [`Self::psf_grads`] then [`Self::phase_vjp`].
    pub fn finish(
        &self,
        map: &PhaseMap,
        psfs: &StepPsfs,
        acc: PsfGradAccumulator,
    ) -> Result<ChainGrad> {
        let (grads, p_hat) = self.psf_grads(psfs, acc)?;
        let phase_rad = self.phase_vjp(map, &grads)?;
        Ok(ChainGrad { phase_rad, p_hat })
    }

    /// ∂L/∂P per slab (the PSF window, `psf_px()`², before normalisation; zero for slabs the
    /// step did not use) and ∂L/∂p̂ (per metre) from an accumulator filled against `psfs`.
    /// Linear in the accumulator at a fixed φ, so steps at one φ may sum these and take one
    /// [`Self::phase_vjp`] of the sum.
    pub fn psf_grads(
        &self,
        psfs: &StepPsfs,
        acc: PsfGradAccumulator,
    ) -> Result<(Vec<Mat<f64>>, f64)> {
        let wp = self.psf_px();
        let p_hat = acc.p_hat;
        let Some(kernels) = acc.kernels else {
            return Err(param(
                "acc",
                "an accumulator from pitch_accumulator() holds no PSF gradient; \
                 use accumulator() to train the lens",
            ));
        };
        let scale = kernels.radiance_scale.clone();
        let unit = self.imager.kernel_grads(kernels);
        let grads: Vec<Mat<f64>> = (0..self.spec.count)
            .map(|k| {
                let e = psfs.eta[k];
                if e <= 0.0 {
                    return Mat::zeros(wp, wp);
                }
                let g = &unit[k];
                let u = &psfs.unit[k];
                let mut dot = 0.0;
                for c in 0..wp {
                    for r in 0..wp {
                        dot += g[(r, c)] * u[(r, c)] as f64;
                    }
                }
                // Radiance enters as η_k·L': ∂L/∂η_k = ⟨∂L/∂I⁽ᵏ⁾, conv_k⟩ / η_k.
                let g_eta = scale[k] / e;
                Mat::from_fn(wp, wp, |r, c| (g[(r, c)] - dot) / e + g_eta)
            })
            .collect();
        Ok((grads, p_hat))
    }

    /// ∂L/∂φ (per radian, aperture grid) at φ = `map` from ∂L/∂P per slab (`psf_grads`'s
    /// layout): the PSF model's VJP, the expensive half of [`Self::finish`].
    pub fn phase_vjp(&self, map: &PhaseMap, grads: &[Mat<f64>]) -> Result<Mat<f64>> {
        let wp = self.psf_px();
        if grads.len() != self.spec.count || grads.iter().any(|g| g.shape() != (wp, wp)) {
            return Err(param(
                "grads",
                format!("need {} slabs of {wp}×{wp}", self.spec.count),
            ));
        }
        // AsmPsf::vjp through the chain's split: each process the terms of its depths, then
        // every term added in increasing depth from zero, as `vjp` adds them (the same bits).
        let items = depths_with_gradient(grads);
        let n = self.aperture_grid().n;
        let terms = map_gather(&*self.split, &items, n * n, |mine| {
            Ok(self
                .psf
                .vjp_terms(map, &self.depths_m, grads, mine)?
                .iter()
                .map(|t| col_major(&t.phase_rad))
                .collect())
        })?;
        let mut phase_rad = Mat::zeros(n, n);
        for t in &terms {
            add_cells(&mut phase_rad, &Mat::from_fn(n, n, |i, j| t[j * n + i]));
        }
        Ok(phase_rad)
    }
}

/// A matrix's values, column after column.
fn col_major(m: &Mat<f64>) -> Vec<f64> {
    (0..m.ncols())
        .flat_map(|j| m.col(j).iter().copied().collect::<Vec<_>>())
        .collect()
}

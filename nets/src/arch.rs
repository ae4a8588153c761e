//! The Once-for-All MobileNetV3 search space: fixed layout, the `Arch` choice of kernel,
//! expansion and depth per stage/layer plus the input-resolution scale, and its sampling.

use crate::act::Act;
use crate::error::{NetsError, Result};
use rand::Rng;
use serde::{Deserialize, Serialize};

/// Number of elastic stages.
pub const N_STAGES: usize = 5;
/// Most blocks per stage.
pub const MAX_DEPTH: usize = 4;
/// Elastic layers (blocks) in all stages.
pub const N_LAYERS: usize = N_STAGES * MAX_DEPTH;
/// Depthwise kernel choices.
pub const KERNELS: [usize; 3] = [3, 5, 7];
/// Expansion-ratio choices.
pub const EXPANDS: [usize; 3] = [3, 4, 6];
/// Depth choices per stage.
pub const DEPTHS: [usize; 3] = [2, 3, 4];
/// Smallest input-resolution scale.
pub const RES_MIN: f64 = 0.3;
/// Largest input-resolution scale.
pub const RES_MAX: f64 = 1.0;

/// Layout of one stage of the OFA MobileNetV3 backbone.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct StageSpec {
    /// Output channels.
    pub channels: usize,
    /// Stride of the first block.
    pub stride: usize,
    /// Activation of the expanded features.
    pub act: Act,
    /// Whether blocks carry squeeze-excitation.
    pub se: bool,
}

/// The five stages of the OFA MobileNetV3 layout (oracles.md).
pub const STAGES: [StageSpec; N_STAGES] = [
    StageSpec {
        channels: 24,
        stride: 2,
        act: Act::Relu,
        se: false,
    },
    StageSpec {
        channels: 40,
        stride: 2,
        act: Act::Relu,
        se: true,
    },
    StageSpec {
        channels: 80,
        stride: 2,
        act: Act::HSwish,
        se: false,
    },
    StageSpec {
        channels: 112,
        stride: 1,
        act: Act::HSwish,
        se: true,
    },
    StageSpec {
        channels: 160,
        stride: 2,
        act: Act::HSwish,
        se: true,
    },
];
/// Stem output channels (3×3, stride 2, h-swish) and the first block's width.
pub const STEM_CHANNELS: usize = 16;

/// Rounds `v` to a multiple of `d`, never below `d` nor below 90 % of `v` (MobileNet rule).
pub fn make_divisible(v: f64, d: usize) -> usize {
    let df = d as f64;
    let mut r = ((v + df / 2.0) / df).floor() as usize * d;
    r = r.max(d);
    if (r as f64) < 0.9 * v {
        r += d;
    }
    r
}

/// Middle (expanded) width of a block with `cin` inputs and expansion `e`.
pub fn mid_channels(cin: usize, e: usize) -> usize {
    make_divisible((cin * e) as f64, 8)
}

/// Squeeze width of an SE module over `c` channels (reduction 4).
pub fn se_channels(c: usize) -> usize {
    make_divisible((c / 4) as f64, 8)
}

/// Widths of the non-elastic parts: input channels and the heads.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct SupernetConfig {
    /// Image channels (1 for NIR eye images, 3 for RGB).
    pub in_channels: usize,
    /// Calibration head: 1×1 expansion width after the last stage (960 in OFA).
    pub head_expand: usize,
    /// Calibration head: hidden linear width (1280 in OFA).
    pub head_hidden: usize,
    /// Segmentation decoder width.
    pub decoder_width: usize,
}

impl Default for SupernetConfig {
    fn default() -> Self {
        Self {
            in_channels: 1,
            head_expand: 960,
            head_hidden: 1280,
            decoder_width: 16,
        }
    }
}

/// Largest width of the supernet's configurable layers: the head's hidden weights alone are
/// `head_expand × head_hidden` f32 (256 MiB at this bound), so a mistyped width is refused
/// rather than aborting the process on a failed allocation.
pub const MAX_WIDTH: usize = 8192;

impl SupernetConfig {
    /// Fails on a zero width or one above [`MAX_WIDTH`].
    pub fn validate(&self) -> Result<()> {
        if self.in_channels == 0
            || self.head_expand == 0
            || self.head_hidden == 0
            || self.decoder_width == 0
        {
            return Err(NetsError::Arch(format!("zero width in {self:?}")));
        }
        let widest = [
            self.in_channels,
            self.head_expand,
            self.head_hidden,
            self.decoder_width,
        ]
        .into_iter()
        .max()
        .unwrap_or(0);
        if widest > MAX_WIDTH {
            return Err(NetsError::Arch(format!(
                "a width of {widest} in {self:?}, above the {MAX_WIDTH} allowed"
            )));
        }
        Ok(())
    }
}

/// One subnet: kernel and expansion per layer (20, stage-major), depth per stage, and the
/// input-resolution scale in [0.3, 1].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Arch {
    /// Depthwise kernel size per layer, ∈ {3, 5, 7}.
    pub kernel: Vec<usize>,
    /// Expansion ratio per layer, ∈ {3, 4, 6}.
    pub expand: Vec<usize>,
    /// Active blocks per stage, ∈ {2, 3, 4}.
    pub depth: Vec<usize>,
    /// Input-resolution scale, ∈ [0.3, 1].
    pub resolution_scale: f64,
}

impl Arch {
    /// The largest subnet: k = 7, e = 6, d = 4, full resolution.
    pub fn max() -> Self {
        Self {
            kernel: vec![7; N_LAYERS],
            expand: vec![6; N_LAYERS],
            depth: vec![4; N_STAGES],
            resolution_scale: RES_MAX,
        }
    }

    /// The smallest subnet: k = 3, e = 3, d = 2, scale 0.3.
    pub fn min() -> Self {
        Self {
            kernel: vec![3; N_LAYERS],
            expand: vec![3; N_LAYERS],
            depth: vec![2; N_STAGES],
            resolution_scale: RES_MIN,
        }
    }

    /// Uniform draw over every choice (scale uniform in [0.3, 1]).
    pub fn sample<R: Rng + ?Sized>(rng: &mut R) -> Self {
        let pick = |rng: &mut R, c: &[usize]| c[rng.random_range(0..c.len())];
        Self {
            kernel: (0..N_LAYERS).map(|_| pick(rng, &KERNELS)).collect(),
            expand: (0..N_LAYERS).map(|_| pick(rng, &EXPANDS)).collect(),
            depth: (0..N_STAGES).map(|_| pick(rng, &DEPTHS)).collect(),
            resolution_scale: rng.random_range(RES_MIN..=RES_MAX),
        }
    }

    /// Kernel, width and depth mutation (and resolution resampling), each decided
    /// independently per layer / stage with probability `rate`.
    pub fn mutate<R: Rng + ?Sized>(&self, rng: &mut R, rate: f64) -> Result<Self> {
        if !(0.0..=1.0).contains(&rate) {
            return Err(NetsError::Param(format!(
                "mutation rate {rate} outside [0, 1]"
            )));
        }
        let mut a = self.clone();
        for i in 0..N_LAYERS {
            if rng.random_bool(rate) {
                a.kernel[i] = KERNELS[rng.random_range(0..3)];
            }
            if rng.random_bool(rate) {
                a.expand[i] = EXPANDS[rng.random_range(0..3)];
            }
        }
        for s in 0..N_STAGES {
            if rng.random_bool(rate) {
                a.depth[s] = DEPTHS[rng.random_range(0..3)];
            }
        }
        if rng.random_bool(rate) {
            a.resolution_scale = rng.random_range(RES_MIN..=RES_MAX);
        }
        Ok(a)
    }

    /// Fails unless every choice lies in the search space.
    pub fn validate(&self) -> Result<()> {
        if self.kernel.len() != N_LAYERS
            || self.expand.len() != N_LAYERS
            || self.depth.len() != N_STAGES
        {
            return Err(NetsError::Arch(format!(
                "need {N_LAYERS} kernels, {N_LAYERS} expansions, {N_STAGES} depths; got {}, {}, {}",
                self.kernel.len(),
                self.expand.len(),
                self.depth.len()
            )));
        }
        if let Some(k) = self.kernel.iter().find(|k| !KERNELS.contains(k)) {
            return Err(NetsError::Arch(format!("kernel {k} not in {KERNELS:?}")));
        }
        if let Some(e) = self.expand.iter().find(|e| !EXPANDS.contains(e)) {
            return Err(NetsError::Arch(format!("expansion {e} not in {EXPANDS:?}")));
        }
        if let Some(d) = self.depth.iter().find(|d| !DEPTHS.contains(d)) {
            return Err(NetsError::Arch(format!("depth {d} not in {DEPTHS:?}")));
        }
        if !(RES_MIN..=RES_MAX).contains(&self.resolution_scale) {
            return Err(NetsError::Arch(format!(
                "resolution scale {} outside [{RES_MIN}, {RES_MAX}]",
                self.resolution_scale
            )));
        }
        Ok(())
    }

    /// Network input size for an image of `n` pixels along one axis: max(1, round(n·scale)).
    pub fn scaled(&self, n: usize) -> usize {
        ((n as f64 * self.resolution_scale).round() as usize).max(1)
    }
}

//! The cost model (S23): multiply–accumulates and parameters of any network under the
//! counting rule of weight-sharing NAS (conv and linear MACs, SE 1×1 convs included; batch
//! norm, activations, pooling, resampling and the SE scaling multiply excluded). Parameters
//! count weights, biases and batch-norm γ, β (not running statistics).

use crate::arch::{Arch, STAGES, STEM_CHANNELS, SupernetConfig, mid_channels, se_channels};
use crate::conv::out_size;
use crate::error::{NetsError, Result};
use crate::supernet::head_inputs;
use serde::Serialize;

/// Largest input side (px) the cost model accepts: beyond it MAC counts approach the range of
/// u64 and no eye camera comes close.
pub const MAX_RESOLUTION: usize = 1 << 16;
/// Largest number of input channels the cost model accepts.
pub const MAX_IN_CHANNELS: usize = 1 << 12;

/// Checks an input size for the cost model: `h`, `w` in 1..=[`MAX_RESOLUTION`].
pub fn check_resolution(h: usize, w: usize) -> Result<()> {
    for v in [h, w] {
        if v == 0 || v > MAX_RESOLUTION {
            return Err(NetsError::Param(format!(
                "resolution {v} px outside 1..={MAX_RESOLUTION}"
            )));
        }
    }
    Ok(())
}

/// MACs split by layer kind.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct PerKind {
    /// 1×1 convolutions (expansion, projection, head and decoder 1×1s).
    pub pointwise: u64,
    /// Depthwise convolutions.
    pub depthwise: u64,
    /// Squeeze-excitation 1×1 convolutions.
    pub se: u64,
    /// Everything else: dense stem convolution, linear layers.
    pub other: u64,
}

/// Total MACs and parameters of one inference pass of one image.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct Cost {
    /// Multiply–accumulates.
    pub macs: u64,
    /// Learnable parameters.
    pub params: u64,
    /// MACs by layer kind.
    pub per_kind: PerKind,
}

/// The kind a layer's MACs are booked under.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kind {
    /// 1×1 convolution.
    Pointwise,
    /// Depthwise convolution.
    Depthwise,
    /// SE convolution.
    Se,
    /// Other.
    Other,
}

/// Walks a network layer by layer, tracking the feature-map shape and summing the cost.
#[derive(Clone, Debug)]
pub struct Counter {
    /// Current channels.
    pub c: usize,
    /// Current height.
    pub h: usize,
    /// Current width.
    pub w: usize,
    /// Cost so far.
    pub cost: Cost,
}

impl Counter {
    /// Starts at an input of `c` channels, `h`×`w` pixels.
    pub fn new(c: usize, h: usize, w: usize) -> Self {
        Self {
            c,
            h,
            w,
            cost: Cost::default(),
        }
    }

    fn book(&mut self, macs: u64, params: u64, kind: Kind) {
        self.cost.macs += macs;
        self.cost.params += params;
        let k = &mut self.cost.per_kind;
        match kind {
            Kind::Pointwise => k.pointwise += macs,
            Kind::Depthwise => k.depthwise += macs,
            Kind::Se => k.se += macs,
            Kind::Other => k.other += macs,
        }
    }

    /// A k×k convolution (same padding) with `groups` groups, optional bias and batch norm.
    #[allow(clippy::too_many_arguments)]
    pub fn conv(
        &mut self,
        cout: usize,
        k: usize,
        stride: usize,
        groups: usize,
        bias: bool,
        bn: bool,
        kind: Kind,
    ) {
        let (ho, wo) = (out_size(self.h, k, stride), out_size(self.w, k, stride));
        let per_out = (k * k * (self.c / groups)) as u64;
        let macs = (ho * wo * cout) as u64 * per_out;
        let params = per_out * cout as u64
            + if bias { cout as u64 } else { 0 }
            + if bn { 2 * cout as u64 } else { 0 };
        self.book(macs, params, kind);
        (self.c, self.h, self.w) = (cout, ho, wo);
    }

    /// A 1×1 convolution with batch norm and no bias.
    pub fn pointwise(&mut self, cout: usize) {
        self.conv(cout, 1, 1, 1, false, true, Kind::Pointwise);
    }

    /// A depthwise k×k convolution with batch norm.
    pub fn depthwise(&mut self, k: usize, stride: usize) {
        let c = self.c;
        self.conv(c, k, stride, c, false, true, Kind::Depthwise);
    }

    /// Squeeze-excitation with a squeeze width `m` (biased 1×1 convs; the shape is unchanged).
    pub fn se(&mut self, m: usize) {
        let c = self.c as u64;
        let m = m as u64;
        self.book(2 * c * m, 2 * c * m + c + m, Kind::Se);
    }

    /// Global average pooling.
    pub fn pool(&mut self) {
        (self.h, self.w) = (1, 1);
    }

    /// `extra` more pooled features beside the current ones (a concatenation: no MACs).
    pub fn concat(&mut self, extra: usize) {
        self.c += extra;
    }

    /// A fully connected layer on the current (pooled) features.
    pub fn linear(&mut self, cout: usize, bias: bool) {
        let cin = (self.c * self.h * self.w) as u64;
        self.book(
            cin * cout as u64,
            cin * cout as u64 + if bias { cout as u64 } else { 0 },
            Kind::Other,
        );
        (self.c, self.h, self.w) = (cout, 1, 1);
    }
}

/// One MobileNetV3 bottleneck: (kernel, expanded width, output width, SE, stride).
type Bneck = (usize, usize, usize, bool, usize);

/// MobileNetV3-Large bottlenecks (Howard et al. 2019, Table 1).
const LARGE: [Bneck; 15] = [
    (3, 16, 16, false, 1),
    (3, 64, 24, false, 2),
    (3, 72, 24, false, 1),
    (5, 72, 40, true, 2),
    (5, 120, 40, true, 1),
    (5, 120, 40, true, 1),
    (3, 240, 80, false, 2),
    (3, 200, 80, false, 1),
    (3, 184, 80, false, 1),
    (3, 184, 80, false, 1),
    (3, 480, 112, true, 1),
    (3, 672, 112, true, 1),
    (5, 672, 160, true, 2),
    (5, 960, 160, true, 1),
    (5, 960, 160, true, 1),
];

/// MobileNetV3-Small bottlenecks (Howard et al. 2019, Table 2).
const SMALL: [Bneck; 11] = [
    (3, 16, 16, true, 2),
    (3, 72, 24, false, 2),
    (3, 88, 24, false, 1),
    (5, 96, 40, true, 2),
    (5, 240, 40, true, 1),
    (5, 240, 40, true, 1),
    (5, 120, 48, true, 1),
    (5, 144, 48, true, 1),
    (5, 288, 96, true, 2),
    (5, 576, 96, true, 1),
    (5, 576, 96, true, 1),
];

fn mobilenet_v3(
    table: &[Bneck],
    last: usize,
    hidden: usize,
    resolution: usize,
    classes: usize,
) -> Cost {
    let mut c = Counter::new(3, resolution, resolution);
    c.conv(16, 3, 2, 1, false, true, Kind::Other);
    for &(k, exp, out, se, s) in table {
        if exp != c.c {
            c.pointwise(exp);
        }
        c.depthwise(k, s);
        if se {
            c.se(se_channels(exp));
        }
        c.pointwise(out);
    }
    c.pointwise(last);
    c.pool();
    c.linear(hidden, true);
    c.linear(classes, true);
    c.cost
}

/// MobileNetV3-Large with its 1000-class classifier at `resolution`² RGB input.
pub fn mobilenet_v3_large(resolution: usize) -> Cost {
    mobilenet_v3(&LARGE, 960, 1280, resolution, 1000)
}

/// MobileNetV3-Small with its 1000-class classifier at `resolution`² RGB input.
pub fn mobilenet_v3_small(resolution: usize) -> Cost {
    mobilenet_v3(&SMALL, 576, 1024, resolution, 1000)
}

/// Backbone, perception decoder and calibration head of a supernet subnet for an input image
/// of `h`×`w` pixels (the subnet sees it rescaled by `arch.resolution_scale`).
pub fn subnet_cost(cfg: &SupernetConfig, arch: &Arch, h: usize, w: usize) -> Result<Cost> {
    cfg.validate()?;
    arch.validate()?;
    check_resolution(h, w)?;
    if cfg.in_channels > MAX_IN_CHANNELS {
        return Err(NetsError::Param(format!(
            "in_channels {} exceeds the maximum {MAX_IN_CHANNELS}",
            cfg.in_channels
        )));
    }
    let mut c = Counter::new(cfg.in_channels, arch.scaled(h), arch.scaled(w));
    c.conv(STEM_CHANNELS, 3, 2, 1, false, true, Kind::Other);
    c.depthwise(3, 1);
    c.pointwise(STEM_CHANNELS);
    let f2 = (c.c, c.h, c.w);
    let mut f8 = f2;
    for (s, st) in STAGES.iter().enumerate() {
        for b in 0..arch.depth[s] {
            let l = s * 4 + b;
            let mid = mid_channels(c.c, arch.expand[l]);
            c.pointwise(mid);
            c.depthwise(arch.kernel[l], if b == 0 { st.stride } else { 1 });
            if st.se {
                c.se(se_channels(mid));
            }
            c.pointwise(st.channels);
        }
        if s == 1 {
            f8 = (c.c, c.h, c.w);
        }
    }
    let f32_ = (c.c, c.h, c.w);
    // Calibration head.
    let mut head = c.clone();
    head.pointwise(cfg.head_expand);
    head.pool();
    // The x and y moments of the last stage and the stride-8 stage join the pooled expansion
    // (supernet.rs).
    head.concat(head_inputs(cfg.head_expand) - cfg.head_expand);
    head.linear(cfg.head_hidden, true);
    head.linear(3, true);
    // Perception decoder: biased 1×1 projections of three taps and the 1-channel logit conv.
    let mut total = head.cost;
    let dw = cfg.decoder_width;
    for (ci, hi, wi) in [f32_, f8, f2] {
        let mut d = Counter::new(ci, hi, wi);
        d.conv(dw, 1, 1, 1, true, false, Kind::Pointwise);
        add(&mut total, &d.cost);
    }
    let mut d = Counter::new(dw, f2.1, f2.2);
    d.conv(1, 1, 1, 1, true, false, Kind::Pointwise);
    add(&mut total, &d.cost);
    Ok(total)
}

fn add(a: &mut Cost, b: &Cost) {
    a.macs += b.macs;
    a.params += b.params;
    a.per_kind.pointwise += b.per_kind.pointwise;
    a.per_kind.depthwise += b.per_kind.depthwise;
    a.per_kind.se += b.per_kind.se;
    a.per_kind.other += b.per_kind.other;
}

#[cfg(test)]
mod bad_input_tests {
    use super::*;

    #[test]
    fn huge_inputs_are_refused_instead_of_wrapping() {
        let cfg = SupernetConfig::default();
        assert!(subnet_cost(&cfg, &Arch::max(), usize::MAX, usize::MAX).is_err());
        let wide = SupernetConfig {
            in_channels: usize::MAX,
            ..SupernetConfig::default()
        };
        assert!(subnet_cost(&wide, &Arch::max(), 224, 224).is_err());
        // At the limits the counts still fit u64 (no wrap-around: MACs grow with the input).
        let big = subnet_cost(&cfg, &Arch::max(), MAX_RESOLUTION, MAX_RESOLUTION).unwrap();
        let small = subnet_cost(&cfg, &Arch::max(), 224, 224).unwrap();
        assert!(big.macs > small.macs * 1000);
        let wide = SupernetConfig {
            in_channels: MAX_IN_CHANNELS,
            ..SupernetConfig::default()
        };
        subnet_cost(&wide, &Arch::max(), MAX_RESOLUTION, MAX_RESOLUTION).unwrap();
        assert!(mobilenet_v3_large(MAX_RESOLUTION).macs > mobilenet_v3_large(224).macs);
        assert!(check_resolution(MAX_RESOLUTION + 1, 1).is_err());
    }

    #[test]
    fn arch_json_with_an_unknown_key_is_refused() {
        let mut v = serde_json::to_value(Arch::min()).unwrap();
        v["kernal"] = serde_json::json!([3]);
        assert!(serde_json::from_value::<Arch>(v).is_err());
    }
}

#[cfg(test)]
mod bad_input_proptests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]
        /// Any resolution and channel count either is refused or gives a cost that grows
        /// with the input (debug builds would panic on an overflow).
        #[test]
        fn extreme_sizes_are_refused_or_counted_without_overflow(
            res in prop_oneof![0usize..=4096, any::<usize>(), Just(usize::MAX), Just(MAX_RESOLUTION)],
            ch in prop_oneof![0usize..=8, any::<usize>(), Just(MAX_IN_CHANNELS)],
        ) {
            let cfg = SupernetConfig { in_channels: ch, ..SupernetConfig::default() };
            match subnet_cost(&cfg, &Arch::max(), res, res) {
                Ok(c) => {
                    prop_assert!((1..=MAX_RESOLUTION).contains(&res));
                    prop_assert!((1..=MAX_IN_CHANNELS).contains(&ch));
                    prop_assert!(c.macs > 0 && c.macs >= c.per_kind.pointwise);
                }
                Err(_) => prop_assert!(
                    !(1..=MAX_RESOLUTION).contains(&res) || !(1..=MAX_IN_CHANNELS).contains(&ch)
                ),
            }
        }
    }
}

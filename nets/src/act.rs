//! Point-wise activations (ReLU, h-swish, h-sigmoid) and their derivatives.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Elements per rayon task of the element-wise passes (below this, one thread is faster).
/// 4 Ki since every pass runs inside the pool (a task no longer wakes a sleeping thread):
/// 32 Ki left the deep stages' small tensors on one core (docs/bench/nets.md).
pub(crate) const PAR_MIN: usize = 1 << 12;

/// An element-wise activation; h-swish(x) = x·ReLU6(x+3)/6, h-sigmoid(x) = ReLU6(x+3)/6.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Act {
    /// y = x.
    Identity,
    /// y = max(x, 0).
    Relu,
    /// y = x·ReLU6(x+3)/6 (Howard et al. 2019).
    HSwish,
    /// y = ReLU6(x+3)/6.
    HSigmoid,
}

impl Act {
    /// The activation at `x`.
    #[inline]
    pub fn apply(self, x: f32) -> f32 {
        match self {
            Act::Identity => x,
            Act::Relu => x.max(0.0),
            Act::HSwish => x * ((x + 3.0).clamp(0.0, 6.0) / 6.0),
            Act::HSigmoid => (x + 3.0).clamp(0.0, 6.0) / 6.0,
        }
    }

    /// dy/dx at the pre-activation `x` (one-sided value 0 at the kinks' lower side).
    #[inline]
    pub fn deriv(self, x: f32) -> f32 {
        match self {
            Act::Identity => 1.0,
            Act::Relu => {
                if x > 0.0 {
                    1.0
                } else {
                    0.0
                }
            }
            Act::HSwish => {
                // Two selects after the quotient (the values of the if-else chain it replaced):
                // loops over it vectorize, where the chain of branches kept them scalar.
                let mid = (2.0 * x + 3.0) / 6.0;
                let upper = if x >= 3.0 { 1.0 } else { mid };
                if x <= -3.0 { 0.0 } else { upper }
            }
            Act::HSigmoid => {
                if x > -3.0 && x < 3.0 {
                    1.0 / 6.0
                } else {
                    0.0
                }
            }
        }
    }

    /// Applies the activation to every element of `x` into a new vector.
    pub fn forward(self, x: &[f32]) -> Vec<f32> {
        x.par_iter()
            .with_min_len(PAR_MIN)
            .map(|&v| self.apply(v))
            .collect()
    }

    /// VJP: dL/dx = dL/dy ⊙ f'(x), with `x` the pre-activation.
    pub fn vjp(self, x: &[f32], dy: &[f32]) -> Vec<f32> {
        x.par_iter()
            .zip(dy)
            .with_min_len(PAR_MIN)
            .map(|(&v, &g)| g * self.deriv(v))
            .collect()
    }
}

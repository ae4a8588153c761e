//! Networks: layers with explicit backward passes, the elastic MobileNetV3 supernet, perception
//! (pupil mask) and calibration (slippage) heads, and the MAC/parameter cost model (S23).
//! Main type: `Supernet`.

// Index loops over several arrays mirror the adjoint equations more clearly than zips.
#![allow(clippy::needless_range_loop)]

pub mod act;
pub mod arch;
pub mod block;
pub mod checkpoint;
pub mod conv;
pub mod cost;
mod dense;
mod depthwise;
pub mod error;
pub mod infer;
pub mod loss;
pub mod norm;
pub mod optim;
pub mod pool;
pub mod resize;
pub mod se;
pub mod supernet;
pub mod tensor;
pub mod toy;

pub use error::{NetsError, Result};
pub use infer::{Inference, InferenceOutput};
pub use tensor::{Param, Tensor};

pub use arch::{Arch, SupernetConfig};
pub use norm::BnMode;
pub use supernet::{Supernet, SupernetOutput};

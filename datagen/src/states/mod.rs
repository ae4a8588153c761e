//! Eye/slippage state sampling: TRUNCNORM, the state vector, and the ambiguity, variational and
//! protocol sets.

pub mod sets;
pub mod state;
pub mod truncnorm;

pub use sets::{
    AmbiguityPair, Capture, MAX_PROTOCOL_SUBJECTS, MAX_SET_ITEMS, PROTOCOL_GRID, Protocol,
    StatesError, TableS2, Triplet, ambiguity, envelope, protocol, variational,
};
pub use state::{Mounting, State};
pub use truncnorm::{TruncNormError, TruncNormal};

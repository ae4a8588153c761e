//! Fisher-information design losses: CRLB (S3), distinctness (S4), compactness (S5),
//! auto-balancing (S6), optical embedding (S15), per-depth Fisher information (S25) and the
//! initialization loop of Sec. A.2. Main trait: `DesignLoss`.
//!
//! Every loss returns its value and its gradient w.r.t. every PSF plane, so the optics VJP
//! can carry it to the phase map. Positions and depths in metres, intensities in photons
//! (or electrons when a quantum efficiency is folded into the photon budget).

mod balance;
mod compact;
mod compare;
mod composite;
mod distinct;
mod embedding;
mod error;
mod init;
mod precision;
mod stack;

pub use balance::{KENDALL_S_LIMIT, Kendall, kendall};
pub use compact::Compactness;
pub use compare::{ComparePlanes, CompareRow, compare_lenses};
pub use composite::{InitEval, InitLoss, PREC_UNIT_M2};
pub use distinct::Distinctness;
pub use embedding::{EmbeddingGrad, EmbeddingTerms, optical_embedding};
pub use error::FisherError;
pub use init::{
    CHECKPOINT_FILE, InitConfig, InitRecord, InitState, bin_planes, init_step, write_npy,
};
pub use precision::{
    DepthFisher, FisherNoise, Precision, depth_fisher, fisher_matrix, log_trace_inverse,
};
pub use stack::{PsfStack, StackGrad};

/// The optics crate, re-exported for callers of the initialization loop.
pub use nanoeye_optics;

/// A design loss on a PSF stack: value and gradient w.r.t. each plane.
pub trait DesignLoss {
    /// Loss value and ∂L/∂PSF for every plane (same shapes as the stack's planes).
    fn value_and_grad(&self, stack: &PsfStack) -> Result<(f64, StackGrad), FisherError>;

    /// Loss value only.
    fn value(&self, stack: &PsfStack) -> Result<f64, FisherError> {
        Ok(self.value_and_grad(stack)?.0)
    }
}

//! The crate's error type.

use thiserror::Error;

/// Errors of the nets crate; every variant names what was wrong with the input.
#[derive(Debug, Error)]
pub enum NetsError {
    /// A tensor shape does not fit the operation.
    #[error("shape mismatch: {0}")]
    Shape(String),
    /// An architecture or configuration value is outside its legal range.
    #[error("invalid architecture: {0}")]
    Arch(String),
    /// A checkpoint file could not be used.
    #[error("checkpoint refused: {0}")]
    Checkpoint(String),
    /// An invalid numeric parameter (learning rate, step count, …).
    #[error("invalid parameter: {0}")]
    Param(String),
    /// Underlying I/O failure.
    #[error("i/o error: {0}")]
    Io(#[from] std::io::Error),
}

/// Result alias of the crate.
pub type Result<T> = std::result::Result<T, NetsError>;

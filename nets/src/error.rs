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
    Io(std::io::Error),
}

// By hand rather than `#[from]`, which would also make the I/O error the `source()` and print
// its message twice under `{:#}`.
impl From<std::io::Error> for NetsError {
    fn from(e: std::io::Error) -> Self {
        Self::Io(e)
    }
}

/// Result alias of the crate.
pub type Result<T> = std::result::Result<T, NetsError>;

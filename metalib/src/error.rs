//! Error type of the metalib crate.

/// Errors raised by the pillar solver, sweep, selection, library and blueprint code.
#[derive(Debug, thiserror::Error)]
pub enum MetalibError {
    /// A parameter is out of its legal range or not finite.
    #[error("invalid parameter `{name}`: {reason}")]
    InvalidParameter {
        /// Parameter name.
        name: &'static str,
        /// Why it was rejected.
        reason: String,
    },
    /// A query lies outside the range a library covers.
    #[error("out of range: {0}")]
    OutOfRange(String),
    /// Tabulated data is not usable (non-monotonic, too short, non-finite).
    #[error("invalid library data: {0}")]
    InvalidData(String),
    /// A linear-algebra step failed (singular system, eigen solver did not converge).
    #[error("numerical failure: {0}")]
    Numerical(String),
    /// File input/output failed.
    #[error("i/o error on {path}: {cause}")]
    Io {
        /// File concerned.
        path: String,
        /// Underlying error.
        cause: std::io::Error,
    },
    /// A file had an unexpected format.
    #[error("format error in {path}: {reason}")]
    Format {
        /// File concerned.
        path: String,
        /// What was wrong.
        reason: String,
    },
}

impl MetalibError {
    /// Shorthand for [`MetalibError::InvalidParameter`].
    pub fn param(name: &'static str, reason: impl Into<String>) -> Self {
        Self::InvalidParameter {
            name,
            reason: reason.into(),
        }
    }
}

//! Error type of the optics crate.

/// Errors raised by phase profiles, PSF models, layered image formation and NPY I/O.
#[derive(Debug, thiserror::Error)]
pub enum OpticsError {
    /// A parameter is out of its legal range or not finite.
    #[error("invalid parameter `{name}`: {reason}")]
    InvalidParameter {
        /// Parameter name.
        name: &'static str,
        /// Why it was rejected.
        reason: String,
    },
    /// Arrays whose shapes must agree do not.
    #[error("shape mismatch: {0}")]
    Shape(String),
    /// The pillar library rejected a query.
    #[error("pillar library: {0}")]
    Library(nanoeye_metalib::MetalibError),
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

impl OpticsError {
    /// Shorthand for [`OpticsError::InvalidParameter`].
    pub fn param(name: &'static str, reason: impl Into<String>) -> Self {
        Self::InvalidParameter {
            name,
            reason: reason.into(),
        }
    }
}

// By hand rather than `#[from]`, which would also make the library's error the `source()` and
// print its message twice under `{:#}`.
impl From<nanoeye_metalib::MetalibError> for OpticsError {
    fn from(e: nanoeye_metalib::MetalibError) -> Self {
        Self::Library(e)
    }
}

/// Result alias of the optics crate.
pub type Result<T> = std::result::Result<T, OpticsError>;

/// Checks that `v` is finite and strictly positive.
pub(crate) fn positive(name: &'static str, v: f64) -> Result<f64> {
    if v.is_finite() && v > 0.0 {
        Ok(v)
    } else {
        Err(OpticsError::param(
            name,
            format!("must be finite and > 0, got {v}"),
        ))
    }
}

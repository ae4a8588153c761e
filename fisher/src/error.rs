//! Error type of the fisher crate.

/// Errors of the design losses; every variant names the offending input.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum FisherError {
    /// A scalar parameter is outside its legal range.
    #[error("invalid parameter {name}: {value} ({why})")]
    InvalidParameter {
        /// Parameter name.
        name: &'static str,
        /// Offending value.
        value: f64,
        /// Reason.
        why: &'static str,
    },
    /// A PSF plane holds a negative or non-finite value.
    #[error("PSF plane {plane} has a negative or non-finite value at ({row}, {col})")]
    InvalidPlane {
        /// Plane index.
        plane: usize,
        /// Row.
        row: usize,
        /// Column.
        col: usize,
    },
    /// A file could not be read or written, or is not what it should be (a checkpoint that
    /// is cut short, corrupted or no checkpoint at all).
    #[error("{name}: {why}")]
    File {
        /// Which file.
        name: &'static str,
        /// Where and why.
        why: String,
    },
    /// Shapes or lengths disagree.
    #[error("shape mismatch for {name}: {why}")]
    Shape {
        /// Which input.
        name: &'static str,
        /// What disagrees.
        why: String,
    },
}

pub(crate) fn check_nonneg(name: &'static str, value: f64) -> Result<(), FisherError> {
    if value.is_finite() && value >= 0.0 {
        Ok(())
    } else {
        Err(FisherError::InvalidParameter {
            name,
            value,
            why: "must be finite and >= 0",
        })
    }
}

pub(crate) fn check_positive(name: &'static str, value: f64) -> Result<(), FisherError> {
    if value.is_finite() && value > 0.0 {
        Ok(())
    } else {
        Err(FisherError::InvalidParameter {
            name,
            value,
            why: "must be finite and > 0",
        })
    }
}

//! Error type of the sensor crate.

/// Errors of the sensor stage; every variant names the offending parameter.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum SensorError {
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
    /// An image holds a negative or non-finite value.
    #[error("image {name} has a negative or non-finite value at ({row}, {col})")]
    InvalidImage {
        /// Which image.
        name: &'static str,
        /// Row of the first bad value.
        row: usize,
        /// Column of the first bad value.
        col: usize,
    },
    /// Two arrays that must agree in shape do not.
    #[error("shape mismatch for {name}: expected {expected:?}, got {got:?}")]
    Shape {
        /// Which array.
        name: &'static str,
        /// Expected (rows, cols).
        expected: (usize, usize),
        /// Actual (rows, cols).
        got: (usize, usize),
    },
}

pub(crate) fn check_positive(name: &'static str, value: f64) -> Result<(), SensorError> {
    if value.is_finite() && value > 0.0 {
        Ok(())
    } else {
        Err(SensorError::InvalidParameter {
            name,
            value,
            why: "must be finite and > 0",
        })
    }
}

pub(crate) fn check_image(
    name: &'static str,
    img: &faer::Mat<f32>,
    allow_negative: bool,
) -> Result<(), SensorError> {
    for c in 0..img.ncols() {
        for r in 0..img.nrows() {
            let v = img[(r, c)];
            if !v.is_finite() || (!allow_negative && v < 0.0) {
                return Err(SensorError::InvalidImage {
                    name,
                    row: r,
                    col: c,
                });
            }
        }
    }
    Ok(())
}

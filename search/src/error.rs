//! Errors of the camera chain and the search: one enum wrapping each stage's error, plus the
//! chain's own parameter checks (which name the parameter).

/// Errors of the `search` crate.
#[derive(Debug, thiserror::Error)]
pub enum SearchError {
    /// A chain or search parameter is out of range; `name` is the parameter.
    #[error("invalid `{name}`: {reason}")]
    Param {
        /// Parameter name.
        name: &'static str,
        /// What is wrong.
        reason: String,
    },
    /// Optics stage.
    #[error("optics: {0}")]
    Optics(#[from] nanoeye_optics::OpticsError),
    /// Sensor stage.
    #[error("sensor: {0}")]
    Sensor(#[from] nanoeye_sensor::SensorError),
    /// Network stage.
    #[error("network: {0}")]
    Nets(#[from] nanoeye_nets::NetsError),
    /// Geometry (rig, solver).
    #[error("geometry: {0}")]
    Gaze(#[from] nanoeye_gaze::GazeError),
    /// Dataset reading.
    #[error("dataset: {0}")]
    Data(#[from] nanoeye_datagen::render::RenderError),
}

/// Result alias of the crate.
pub type Result<T> = std::result::Result<T, SearchError>;

/// A `Param` error.
pub(crate) fn param(name: &'static str, reason: impl Into<String>) -> SearchError {
    SearchError::Param {
        name,
        reason: reason.into(),
    }
}

/// `v` if finite and > 0, else a `Param` error naming it.
pub(crate) fn positive(name: &'static str, v: f64) -> Result<f64> {
    if v.is_finite() && v > 0.0 {
        Ok(v)
    } else {
        Err(param(name, format!("must be positive and finite, got {v}")))
    }
}

//! Errors of the camera chain and the search: one enum wrapping each stage's error, plus the
//! chain's own parameter checks (which name the parameter).

/// Errors of the `search` crate. A stage's error is wrapped with its message in ours and no
/// `source()`: with both, `{:#}` printed the stage's message twice.
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
    Optics(nanoeye_optics::OpticsError),
    /// Sensor stage.
    #[error("sensor: {0}")]
    Sensor(nanoeye_sensor::SensorError),
    /// Network stage.
    #[error("network: {0}")]
    Nets(nanoeye_nets::NetsError),
    /// Geometry (rig, solver).
    #[error("geometry: {0}")]
    Gaze(nanoeye_gaze::GazeError),
    /// Dataset reading.
    #[error("dataset: {0}")]
    Data(nanoeye_datagen::render::RenderError),
}

/// The fields in which two configurations differ, for a refused resume, worded as the
/// dataset renderer words its own ([`nanoeye_datagen::render::dataset::field_differences`]).
pub fn differences(was: &impl serde::Serialize, now: &impl serde::Serialize) -> String {
    nanoeye_datagen::render::dataset::field_differences(was, now, None)
}

macro_rules! wrap {
    ($($t:ty => $v:ident),*) => {$(
        impl From<$t> for SearchError {
            fn from(e: $t) -> Self {
                Self::$v(e)
            }
        }
    )*};
}
wrap!(
    nanoeye_optics::OpticsError => Optics,
    nanoeye_sensor::SensorError => Sensor,
    nanoeye_nets::NetsError => Nets,
    nanoeye_gaze::GazeError => Gaze,
    nanoeye_datagen::render::RenderError => Data
);

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

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

/// The fields in which two configurations (serialised to JSON objects) differ, for a refused
/// resume: `` `name`: A there, B now `` for a number, string or flag, `` `name` `` alone for a
/// nested value, separated by "; " ("unreadable" when either is not an object).
pub fn differences(was: &impl serde::Serialize, now: &impl serde::Serialize) -> String {
    use serde_json::Value;
    let (Ok(Value::Object(a)), Ok(Value::Object(b))) =
        (serde_json::to_value(was), serde_json::to_value(now))
    else {
        return String::from("unreadable");
    };
    let nested = |v: Option<&Value>| v.is_some_and(|v| v.is_object() || v.is_array());
    let show = |v: Option<&Value>| v.map_or_else(|| String::from("none"), Value::to_string);
    a.keys()
        .chain(b.keys().filter(|k| !a.contains_key(*k)))
        .filter(|k| a.get(*k) != b.get(*k))
        .map(|k| {
            let (x, y) = (a.get(k), b.get(k));
            if nested(x) || nested(y) {
                format!("`{k}`")
            } else {
                format!("`{k}`: {} there, {} now", show(x), show(y))
            }
        })
        .collect::<Vec<_>>()
        .join("; ")
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

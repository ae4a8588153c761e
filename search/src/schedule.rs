//! How φ's learning rate moves over sandwich training: constant (S22 as written), or a cosine
//! decay that reaches zero after a fraction of the steps and keeps φ fixed from there.
//!
//! Why a decay: at the default job's size ∂L/∂φ agrees from batch to batch early in training
//! (one sign on the defocus and spherical modes after one step) and hardly at all after 200
//! (docs/run.md, "A Zernike basis for φ's steps"), so a constant rate turns the late steps into a
//! random walk of the lens under a network that must follow it. Once the rate is zero the step
//! needs no gradient to φ: the chain skips S1's PSF adjoint and may serve S1's images from its
//! cache, as for a fixed lens.

use nanoeye_nets::optim::cosine_lr;
use serde::{Deserialize, Serialize};

/// φ's learning-rate schedule over the sandwich steps. Written `"constant"`, `"cosine"` or
/// `"cosine:F"` (F in (0, 1], the fraction of the steps the decay lasts; `cosine` is F = 1).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "String", into = "String")]
pub enum PhaseSchedule {
    /// φ's rate is `lr_phase_rad` at every step (what checkpoints without the field used).
    #[default]
    Constant,
    /// Cosine decay from `lr_phase_rad` at step 0 to zero at step ⌈F·steps⌉, zero after.
    Cosine(f64),
}

impl PhaseSchedule {
    /// The factor on `lr_phase_rad` at step `t` of `steps` (1 at t = 0; in [0, 1]).
    pub fn scale(self, t: usize, steps: usize) -> f64 {
        match self {
            PhaseSchedule::Constant => 1.0,
            PhaseSchedule::Cosine(f) => {
                // At least one step, so that any F > 0 moves φ.
                let end = ((f * steps as f64).ceil() as usize).max(1);
                if t >= end {
                    0.0
                } else {
                    cosine_lr(1.0, 0.0, t, end)
                }
            }
        }
    }

    /// Refuses a fraction outside (0, 1] (a value built in code, not parsed).
    pub fn validate(self) -> crate::Result<()> {
        match self {
            PhaseSchedule::Cosine(f) if !(f > 0.0 && f <= 1.0) => Err(crate::error::param(
                "phase_schedule",
                format!("the cosine's fraction of the steps must lie in (0, 1], got {f}"),
            )),
            _ => Ok(()),
        }
    }
}

impl std::str::FromStr for PhaseSchedule {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        let bad = || {
            format!(
                "`{s}` is none of `constant`, `cosine` and `cosine:F` with F, the fraction of the \
                 steps the decay lasts, in (0, 1]"
            )
        };
        match s {
            "constant" => Ok(PhaseSchedule::Constant),
            "cosine" => Ok(PhaseSchedule::Cosine(1.0)),
            _ => {
                let f: f64 = s
                    .strip_prefix("cosine:")
                    .ok_or_else(bad)?
                    .parse()
                    .map_err(|_| bad())?;
                let sched = PhaseSchedule::Cosine(f);
                sched.validate().map_err(|_| bad())?;
                Ok(sched)
            }
        }
    }
}

impl std::fmt::Display for PhaseSchedule {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            PhaseSchedule::Constant => write!(f, "constant"),
            PhaseSchedule::Cosine(x) if *x == 1.0 => write!(f, "cosine"),
            // f64's Display is the shortest text that parses back to the same bits.
            PhaseSchedule::Cosine(x) => write!(f, "cosine:{x}"),
        }
    }
}

impl TryFrom<String> for PhaseSchedule {
    type Error = String;
    fn try_from(s: String) -> std::result::Result<Self, String> {
        s.parse()
    }
}

impl From<PhaseSchedule> for String {
    fn from(s: PhaseSchedule) -> String {
        s.to_string()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn constant_is_one_at_every_step() {
        for t in [0, 1, 50, 199, 1000] {
            assert_eq!(PhaseSchedule::Constant.scale(t, 200), 1.0);
        }
    }

    #[test]
    fn the_cosine_falls_from_one_to_zero_at_its_fraction_and_stays_there() {
        let s = PhaseSchedule::Cosine(0.25);
        assert_eq!(s.scale(0, 200), 1.0);
        // Half-way through its 50 steps: cos(π/2) = 0, so exactly one half.
        assert!((s.scale(25, 200) - 0.5).abs() < 1e-15);
        let mut last = 1.0;
        for t in 1..50 {
            let v = s.scale(t, 200);
            assert!(v > 0.0 && v < last, "step {t}: {v} after {last}");
            last = v;
        }
        for t in 50..400 {
            assert_eq!(s.scale(t, 200), 0.0);
        }
        // The whole run, and a fraction too small for one step of a short run.
        let full = PhaseSchedule::Cosine(1.0);
        assert!((full.scale(100, 200) - 0.5).abs() < 1e-15);
        assert_eq!(full.scale(200, 200), 0.0);
        let tiny = PhaseSchedule::Cosine(1e-9);
        assert_eq!((tiny.scale(0, 10), tiny.scale(1, 10)), (1.0, 0.0));
    }

    #[test]
    fn text_round_trips_and_bad_text_is_refused() {
        for (s, want) in [
            ("constant", PhaseSchedule::Constant),
            ("cosine", PhaseSchedule::Cosine(1.0)),
            ("cosine:1", PhaseSchedule::Cosine(1.0)),
            ("cosine:0.25", PhaseSchedule::Cosine(0.25)),
            ("cosine:0.1", PhaseSchedule::Cosine(0.1)),
            ("cosine:1e-3", PhaseSchedule::Cosine(1e-3)),
        ] {
            let got: PhaseSchedule = s.parse().unwrap();
            assert_eq!(got, want, "{s}");
            assert_eq!(got.to_string().parse::<PhaseSchedule>().unwrap(), got);
            let json = serde_json::to_string(&got).unwrap();
            assert_eq!(serde_json::from_str::<PhaseSchedule>(&json).unwrap(), got);
        }
        for s in [
            "",
            "cosine:",
            "cosine:0",
            "cosine:-0.5",
            "cosine:1.5",
            "cosine:nan",
            "cosine:inf",
            "Cosine",
            "linear",
            "cosine:0.5x",
            "constant:1",
        ] {
            let e = s.parse::<PhaseSchedule>().unwrap_err();
            assert!(e.contains("cosine:F"), "{s}: {e}");
        }
        assert!(PhaseSchedule::Cosine(f64::NAN).validate().is_err());
        assert!(PhaseSchedule::Cosine(2.0).validate().is_err());
        assert!(serde_json::from_str::<PhaseSchedule>("0.5").is_err());
    }
}

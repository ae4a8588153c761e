//! Which frames a subnet's batch-norm statistics are recalibrated over before it is scored
//! (B.6): every frame of the training set, or a few batches of it in training order.

use crate::error::{Result, param};
use crate::geometry::NativeGrid;
use serde::{Deserialize, Deserializer, Serialize, Serializer};

/// The BN recalibration set: `All` frames of the training set once (as many as
/// [`crate::train::ALL_FRAMES_BYTES`] of network inputs hold), or `Count(n)` training batches.
/// Written as `"all"` or the count; parsed from the same text.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BnBatches {
    /// Every training frame once, in the set's order.
    All,
    /// This many training batches (≥ 1), in training order.
    Count(usize),
}

impl BnBatches {
    /// Refuses a count whose network inputs, `batch` frames of `h`×`w` f32 pixels a batch,
    /// exceed [`crate::train::ALL_FRAMES_BYTES`] (`All` stops at that size by itself).
    pub fn check_fits(self, batch: usize, (h, w): (usize, usize)) -> Result<()> {
        let BnBatches::Count(n) = self else {
            return Ok(());
        };
        let limit = crate::train::ALL_FRAMES_BYTES;
        let frames = n as u128 * batch.max(1) as u128;
        let need =
            frames.saturating_mul((h as u128 * w as u128) * std::mem::size_of::<f32>() as u128);
        if need > limit as u128 {
            return Err(param(
                "bn_batches",
                format!(
                    "{n} batches ({frames} frames of {h}×{w} pixels) need {} MiB of network \
                     inputs, above the {} MiB kept; give fewer batches or \"all\"",
                    need >> 20,
                    limit >> 20
                ),
            ));
        }
        Ok(())
    }
}

impl BnBatches {
    /// [`Self::check_fits`] for the network inputs at the finest p̂ a run may reach:
    /// `finest_m` (m), or the native grid's pitch where that is finer.
    pub fn check_fits_from(self, batch: usize, native: &NativeGrid, finest_m: f64) -> Result<()> {
        let shape = native.at(finest_m.max(native.pitch_m()))?.shape();
        self.check_fits(batch, shape)
    }
}

impl std::str::FromStr for BnBatches {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "all" => Ok(BnBatches::All),
            _ => match s.parse::<usize>() {
                Ok(n) if n >= 1 => Ok(BnBatches::Count(n)),
                _ => Err(format!("`{s}` is neither `all` nor a count of batches ≥ 1")),
            },
        }
    }
}

impl std::fmt::Display for BnBatches {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            BnBatches::All => write!(f, "all"),
            BnBatches::Count(n) => write!(f, "{n}"),
        }
    }
}

impl Serialize for BnBatches {
    fn serialize<S: Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        match self {
            BnBatches::All => s.serialize_str("all"),
            BnBatches::Count(n) => s.serialize_u64(*n as u64),
        }
    }
}

impl<'de> Deserialize<'de> for BnBatches {
    fn deserialize<D: Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        d.deserialize_any(BnVisitor)
    }
}

/// Reads a count as a JSON number (how states written before `all` existed hold it) or as
/// text, and names what it got otherwise.
struct BnVisitor;

impl BnVisitor {
    fn bad<E: serde::de::Error>(got: impl std::fmt::Display) -> E {
        E::custom(format!(
            "{got} is neither \"all\" nor a count of batches ≥ 1"
        ))
    }
}

impl serde::de::Visitor<'_> for BnVisitor {
    type Value = BnBatches;
    fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        write!(f, "\"all\" or a count of batches ≥ 1")
    }
    fn visit_u64<E: serde::de::Error>(self, n: u64) -> std::result::Result<BnBatches, E> {
        match usize::try_from(n) {
            Ok(n) if n >= 1 => Ok(BnBatches::Count(n)),
            _ => Err(Self::bad(n)),
        }
    }
    fn visit_i64<E: serde::de::Error>(self, n: i64) -> std::result::Result<BnBatches, E> {
        match u64::try_from(n) {
            Ok(n) => self.visit_u64(n),
            Err(_) => Err(Self::bad(n)),
        }
    }
    fn visit_f64<E: serde::de::Error>(self, x: f64) -> std::result::Result<BnBatches, E> {
        Err(Self::bad(x))
    }
    fn visit_str<E: serde::de::Error>(self, s: &str) -> std::result::Result<BnBatches, E> {
        s.parse().map_err(|_| Self::bad(format!("\"{s}\"")))
    }
    fn visit_unit<E: serde::de::Error>(self) -> std::result::Result<BnBatches, E> {
        Err(Self::bad("null"))
    }
    fn visit_none<E: serde::de::Error>(self) -> std::result::Result<BnBatches, E> {
        Err(Self::bad("null"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_count_is_refused_only_when_its_inputs_exceed_what_is_kept() {
        let limit = crate::train::ALL_FRAMES_BYTES;
        // One 1024×1024 f32 frame is 4 MiB: 128 of them are exactly the limit.
        let hw = (1024, 1024);
        assert_eq!(limit, 128 * 1024 * 1024 * 4);
        assert!(BnBatches::Count(32).check_fits(4, hw).is_ok());
        let e = BnBatches::Count(33)
            .check_fits(4, hw)
            .unwrap_err()
            .to_string();
        assert!(e.contains("bn_batches") && e.contains("528 MiB"), "{e}");
        assert!(BnBatches::All.check_fits(usize::MAX, hw).is_ok());
        assert!(
            BnBatches::Count(usize::MAX)
                .check_fits(usize::MAX, hw)
                .is_err()
        );
    }

    #[test]
    fn text_and_json_round_trip_and_old_counts_still_read() {
        for b in [BnBatches::All, BnBatches::Count(1), BnBatches::Count(60)] {
            assert_eq!(b.to_string().parse::<BnBatches>(), Ok(b));
            let j = serde_json::to_string(&b).unwrap();
            assert_eq!(serde_json::from_str::<BnBatches>(&j).unwrap(), b);
        }
        assert_eq!(serde_json::to_string(&BnBatches::All).unwrap(), "\"all\"");
        assert_eq!(
            serde_json::from_str::<BnBatches>("2").unwrap(),
            BnBatches::Count(2)
        );
        assert_eq!(
            serde_json::from_str::<BnBatches>("\"7\"").unwrap(),
            BnBatches::Count(7)
        );
        for bad in [
            "0", "-1", "1.5", "\"ALL\"", "\"two\"", "null", "\"\"", "1e3",
        ] {
            let e = serde_json::from_str::<BnBatches>(bad)
                .unwrap_err()
                .to_string();
            assert!(e.contains("neither \"all\""), "{bad}: {e}");
        }
        // Neither a number nor text: serde's own message, naming what was expected.
        let e = serde_json::from_str::<BnBatches>("[2]")
            .unwrap_err()
            .to_string();
        assert!(e.contains("\"all\" or a count of batches"), "{e}");
        for bad in ["0", "-1", "two", "1.5", "ALL", ""] {
            let e = bad.parse::<BnBatches>().unwrap_err();
            assert!(e.contains("neither `all`"), "{e}");
        }
    }
}

//! `nanoeye datagen …`: state sets, Listing's law, rendering.

use crate::{rig, util};
use anyhow::{Result, bail};
use clap::{Subcommand, ValueEnum};
use nanoeye_datagen::states::{self, Protocol};
use nanoeye_gaze::eye;
use serde_json::json;
use std::path::PathBuf;

/// Which state set to generate.
#[derive(Clone, Copy, Debug, ValueEnum)]
pub enum Set {
    /// Ambiguity pairs (C.3, Table S2).
    Ambiguity,
    /// Variational triplets (C.2, Table S3).
    Variational,
    /// The acquisition protocol (D.4); `--n` counts subjects.
    Protocol,
}

/// Data generation commands.
#[derive(Subcommand)]
pub enum Cmd {
    /// Sample a state set to JSONL (docs/formats.md).
    States {
        /// Which set.
        #[arg(long, value_enum)]
        set: Set,
        /// Number of items (pairs, triplets, or subjects for `protocol`).
        #[arg(long)]
        n: usize,
        /// Random seed; the same seed gives a byte-identical file on any thread count.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Output JSONL file (written atomically).
        #[arg(long)]
        out: PathBuf,
        /// Rig JSON file; default: the built-in seed rig.
        #[arg(long)]
        rig: Option<PathBuf>,
        /// Print a one-line JSON summary.
        #[arg(long)]
        json: bool,
    },
    /// Render a state set into a dataset directory (docs/renderer.md).
    Render(crate::datagen_render::RenderArgs),
    /// The torsion Listing's law implies for a gaze (Fick angles).
    Listing {
        /// Azimuth (deg), positive towards +x.
        #[arg(long, allow_hyphen_values = true)]
        azimuth_deg: f64,
        /// Elevation (deg), positive up.
        #[arg(long, allow_hyphen_values = true)]
        elevation_deg: f64,
        /// Print JSON.
        #[arg(long)]
        json: bool,
    },
}

/// Serializes the items of a set as JSONL text.
pub fn set_jsonl(rig: &nanoeye_gaze::Rig, set: Set, n: usize, seed: u64) -> Result<String> {
    let lines: Vec<String> = match set {
        Set::Ambiguity => states::ambiguity(rig, n, seed)?
            .iter()
            .map(serde_json::to_string)
            .collect::<Result<_, _>>()?,
        Set::Variational => states::variational(rig, n, seed)?
            .iter()
            .map(serde_json::to_string)
            .collect::<Result<_, _>>()?,
        Set::Protocol => states::protocol(rig, &Protocol::default(), n, seed)?
            .iter()
            .map(serde_json::to_string)
            .collect::<Result<_, _>>()?,
    };
    let mut text = lines.join("\n");
    if !text.is_empty() {
        text.push('\n');
    }
    Ok(text)
}

pub fn run(cmd: Cmd) -> Result<()> {
    match cmd {
        Cmd::Render(args) => crate::datagen_render::run(args),
        Cmd::States {
            set,
            n,
            seed,
            out,
            rig,
            json,
        } => {
            if n == 0 {
                bail!("--n: must be at least 1");
            }
            let max = match set {
                Set::Protocol => states::MAX_PROTOCOL_SUBJECTS,
                Set::Ambiguity | Set::Variational => states::MAX_SET_ITEMS,
            };
            if n > max {
                bail!("--n: at most {max} for --set {set:?} (the set is held in memory), got {n}");
            }
            let rig = rig::load(rig.as_deref())?;
            let text = set_jsonl(&rig, set, n, seed)?;
            util::write_atomic(&out, text.as_bytes())?;
            let lines = text.lines().count();
            if json {
                util::print_json(&json!({"out": out, "lines": lines, "seed": seed}))
            } else {
                println!("wrote {lines} lines to {}", out.display());
                Ok(())
            }
        }
        Cmd::Listing {
            azimuth_deg,
            elevation_deg,
            json,
        } => {
            if !(azimuth_deg.abs() < 90.0 && elevation_deg.abs() < 90.0) {
                bail!("--azimuth-deg/--elevation-deg: Fick angles must lie in (−90°, 90°)");
            }
            let psi = eye::listing_torsion(azimuth_deg.to_radians(), elevation_deg.to_radians())?;
            if json {
                util::print_json(&json!({"torsion_deg": psi.to_degrees()}))
            } else {
                println!("torsion {:.4}°", psi.to_degrees());
                Ok(())
            }
        }
    }
}

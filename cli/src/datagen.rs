//! `nanoeye datagen …`: state sets, Listing's law, rendering.

use crate::{rig, util};
use anyhow::{Context, Result, bail};
use clap::{Subcommand, ValueEnum};
use nanoeye_datagen::states::{self, Protocol};
use nanoeye_gaze::eye;
use serde_json::json;
use std::path::{Path, PathBuf};

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
        /// Targets per side of the protocol set's grid, 2–7 (D.4: 7 × 7), with --set protocol
        /// only (as `datagen render --protocol-grid`).
        #[arg(long, default_value_t = states::PROTOCOL_GRID)]
        protocol_grid: usize,
        /// Print a one-line JSON summary.
        #[arg(long)]
        json: bool,
    },
    /// Render a state set into a dataset directory (docs/renderer.md).
    Render(crate::datagen_render::RenderArgs),
    /// Export the procedural eye region of one subject in one state as glTF 2.0 (GLB): face,
    /// eye, camera and illuminator with named materials (docs/formats.md).
    Export {
        /// Subject seed (the same seed as a dataset frame's "subject").
        #[arg(long, default_value_t = 0)]
        subject: u64,
        /// The state as JSON text or a JSON file ({"azimuth_rad", "elevation_rad",
        /// "torsion_rad", "slip_m", "cam_rot_rad", "lid_closure"}); default: primary gaze, no slip.
        #[arg(long)]
        state: Option<String>,
        /// Output .glb file (written atomically).
        #[arg(long)]
        out: PathBuf,
        /// Rig JSON file; default: the built-in seed rig.
        #[arg(long)]
        rig: Option<PathBuf>,
        /// Print a one-line JSON summary.
        #[arg(long)]
        json: bool,
    },
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

/// Writes `items` to `out` as JSON lines, atomically, one item serialized at a time (the text
/// of 2 million items is 2 GB); returns the number of lines.
fn write_jsonl<T: serde::Serialize>(items: &[T], out: &std::path::Path) -> Result<usize> {
    use std::io::Write;
    util::write_atomic_with(out, |w| {
        for item in items {
            serde_json::to_writer(&mut *w, item)?;
            w.write_all(b"\n")?;
        }
        Ok(())
    })
    .context("--out")?;
    Ok(items.len())
}

pub fn run(cmd: Cmd) -> Result<()> {
    match cmd {
        Cmd::Render(args) => crate::datagen_render::run(args),
        Cmd::Export {
            subject,
            state,
            out,
            rig,
            json,
        } => export(subject, state.as_deref(), &out, rig.as_deref(), json),
        Cmd::States {
            set,
            n,
            seed,
            out,
            rig,
            protocol_grid,
            json,
        } => {
            if n == 0 {
                bail!("--n: must be at least 1");
            }
            // As the flag takes it (`ambiguity`), not the variant's Debug name.
            let name = format!("{set:?}").to_lowercase();
            // The same rule as `datagen render`'s: only the protocol set has a grid, and the
            // default cannot be told apart from a 7 given on another set.
            if !matches!(set, Set::Protocol) && protocol_grid != states::PROTOCOL_GRID {
                bail!(
                    "--protocol-grid: with --set protocol only (--set {name} has no target \
                     grid), got {protocol_grid}"
                );
            }
            let max = match set {
                Set::Protocol => states::MAX_PROTOCOL_SUBJECTS,
                Set::Ambiguity | Set::Variational => states::MAX_SET_ITEMS,
            };
            if n > max {
                bail!("--n: at most {max} for --set {name} (the set is held in memory), got {n}");
            }
            // Before the sampling: a directory or a device at --out was found after it.
            util::check_output_target(&out).context("--out")?;
            let rig_path = rig;
            if rig_path
                .as_deref()
                .is_some_and(|p| util::same_file(p, &out))
            {
                bail!("--out: '{}' is --rig; give another path", out.display());
            }
            let rig = rig::load(rig_path.as_deref())?;
            // The built-in rig always admits the sets; a rig file whose camera never sees the
            // pupil does not, and the error must say which input is at fault.
            let why = || match &rig_path {
                Some(p) => format!("--rig '{}': no {name} state fits this rig", p.display()),
                None => format!("--set {name}: sampling failed"),
            };
            let lines = match set {
                Set::Ambiguity => {
                    write_jsonl(&states::ambiguity(&rig, n, seed).with_context(why)?, &out)?
                }
                Set::Variational => {
                    write_jsonl(&states::variational(&rig, n, seed).with_context(why)?, &out)?
                }
                Set::Protocol => {
                    let p = Protocol {
                        grid: protocol_grid,
                        ..Protocol::default()
                    };
                    let captures = match states::protocol(&rig, &p, n, seed) {
                        Err(e @ states::StatesError::Grid { .. }) => {
                            bail!("--protocol-grid: {e}")
                        }
                        r => r.with_context(why)?,
                    };
                    write_jsonl(&captures, &out)?
                }
            };
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
            for (flag, v) in [
                ("--azimuth-deg", azimuth_deg),
                ("--elevation-deg", elevation_deg),
            ] {
                if v.is_nan() || v.abs() >= 90.0 {
                    bail!("{flag}: a Fick angle must lie in (−90°, 90°), got {v}");
                }
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

/// `nanoeye datagen export`.
fn export(
    subject: u64,
    state: Option<&str>,
    out: &std::path::Path,
    rig: Option<&std::path::Path>,
    json: bool,
) -> Result<()> {
    use nanoeye_datagen::render::{Light, Subject, export_glb};
    use nanoeye_datagen::states::State;
    if out
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
        != Some("glb".into())
    {
        bail!("--out: must name a .glb file, got '{}'", out.display());
    }
    // The model replaces --out whole: given an input, it would replace it.
    let inputs = [
        ("--rig", rig),
        (
            "--state",
            state
                .filter(|t| !t.trim_start().starts_with('{'))
                .map(Path::new),
        ),
    ];
    for (flag, p) in inputs {
        if p.is_some_and(|p| util::same_file(p, out)) {
            bail!("--out: '{}' is {flag}; give another path", out.display());
        }
    }
    util::check_output_target(out).context("--out")?;
    let rig = rig::load(rig)?;
    // Primary gaze, no slippage: the default, and the layout a given state must have.
    let primary = State {
        azimuth_rad: 0.0,
        elevation_rad: 0.0,
        torsion_rad: 0.0,
        slip_m: [0.0; 3],
        cam_rot_rad: [0.0; 3],
        lid_closure: 0.0,
    };
    let state: State = match state {
        None => primary,
        Some(text) => {
            // Inline JSON: an object, or an array that no file is named after (refused below
            // as the wrong layout, not as a missing file).
            let t = text.trim_start();
            let body = if t.starts_with('{') || (t.starts_with('[') && !Path::new(text).exists()) {
                text.to_string()
            } else {
                util::read_small_text(Path::new(text), util::MAX_ARCH_BYTES).context("--state")?
            };
            let given: serde_json::Value =
                serde_json::from_str(&body).map_err(|e| anyhow::anyhow!("--state: {e}"))?;
            if let Some(m) = util::array_for_object(&serde_json::to_value(primary)?, &given) {
                bail!("--state: {m}");
            }
            // serde's error for a null names a line and a column, not the key.
            if let Some((k, _)) = given
                .as_object()
                .and_then(|m| m.iter().find(|(_, v)| v.is_null()))
            {
                bail!("--state: key '{k}' is null; give a number");
            }
            // From the text, not the parsed value: a key given twice is refused there (the
            // value kept only the last).
            let state: State =
                serde_json::from_str(&body).map_err(|e| {
                    match util::failing_path(&primary, &given) {
                        Some((key, why)) => anyhow::anyhow!("--state: key '{key}': {why}"),
                        None => anyhow::anyhow!("--state: {e}"),
                    }
                })?;
            // An unknown key (a misspelt `lid_closure`) would be ignored silently. Checked
            // here rather than by the type: stored records keep their states readable.
            let known = serde_json::to_value(State {
                lid_closure: 1.0,
                ..state
            })?;
            if let (Some(given), Some(known)) = (given.as_object(), known.as_object())
                && let Some(k) = given.keys().find(|k| !known.contains_key(*k))
            {
                let keys: Vec<&str> = known.keys().map(String::as_str).collect();
                bail!(
                    "--state: unknown key '{k}'; a state has {}",
                    keys.join(", ")
                );
            }
            state
        }
    };
    let finite = [state.azimuth_rad, state.elevation_rad, state.torsion_rad]
        .iter()
        .chain(&state.slip_m)
        .chain(&state.cam_rot_rad)
        .all(|x| x.is_finite());
    if !finite {
        bail!("--state: every angle and offset must be finite");
    }
    let subj = Subject::from_seed(subject);
    let light = Light::near_camera(&state.camera_pose(&rig));
    let bytes =
        export_glb(&rig, &state, &subj, &light).map_err(|e| anyhow::anyhow!("--state: {e}"))?;
    util::write_atomic(out, &bytes).context("--out")?;
    if json {
        util::print_json(&json!({"out": out, "bytes": bytes.len(), "subject": subject}))
    } else {
        println!("wrote {} ({} bytes)", out.display(), bytes.len());
        Ok(())
    }
}

//! `nanoeye rig …`: show and check the eye–camera rig.

use crate::util;
use anyhow::{Context, Result};
use clap::Subcommand;
use nanoeye_gaze::Rig;
use std::path::{Path, PathBuf};

/// Rig commands.
#[derive(Subcommand)]
pub enum Cmd {
    /// Print the rig (the built-in default, or --rig FILE after validation).
    Show {
        /// Rig JSON file (docs/formats.md); default: the built-in seed rig.
        #[arg(long)]
        rig: Option<PathBuf>,
        /// Print JSON instead of a table.
        #[arg(long)]
        json: bool,
    },
}

/// Loads `--rig FILE` or the built-in default.
pub fn load(path: Option<&Path>) -> Result<Rig> {
    match path {
        None => Ok(Rig::default()),
        Some(p) => {
            // A FIFO or device would block or be read without end: a rig is a small file.
            let text =
                crate::util::read_small_text(p, crate::util::MAX_ARCH_BYTES).context("--rig")?;
            let parsed = serde_json::from_str::<serde_json::Value>(&text).ok();
            if let Some(v) = &parsed {
                let t = serde_json::to_value(Rig::default())?;
                if let Some(m) = crate::util::array_for_object(&t, v) {
                    anyhow::bail!("--rig: '{}': {m}", p.display());
                }
            }
            Rig::from_json(&text).map_err(|e| {
                // A value the type does not take (from_json's "(json)" error, not a check's),
                // named by its path rather than a column.
                let unparsed = matches!(
                    e,
                    nanoeye_gaze::GazeError::InvalidRig {
                        field: "(json)",
                        ..
                    }
                );
                let at = parsed
                    .as_ref()
                    .filter(|_| unparsed)
                    .and_then(|v| crate::util::failing_path(&Rig::default(), v));
                match at {
                    Some((path, why)) => {
                        anyhow::anyhow!("--rig: '{}': rig field `{path}`: {why}", p.display())
                    }
                    None => anyhow::Error::new(e)
                        .context(format!("--rig: '{}' is not a valid rig", p.display())),
                }
            })
        }
    }
}

pub fn run(cmd: Cmd) -> Result<()> {
    match cmd {
        Cmd::Show { rig, json } => {
            let rig = load(rig.as_deref())?;
            if json {
                return util::print_json(&rig);
            }
            let c = &rig.camera;
            println!("eye sphere (solver)   {:.3} mm", rig.eye_radius_m * 1e3);
            println!(
                "pupil sphere (true)   {:.3} mm",
                rig.pupil_sphere_radius_m * 1e3
            );
            println!(
                "kappa                 ({:.2}°, {:.2}°)",
                rig.kappa_rad[0].to_degrees(),
                rig.kappa_rad[1].to_degrees()
            );
            println!(
                "camera                {}×{} px, pitch {:.2} µm, image distance {:.3} mm",
                c.width_px,
                c.height_px,
                c.pixel_pitch_m * 1e6,
                c.focal_length_m * 1e3
            );
            println!("  fx, fy              {:.3}, {:.3} px", c.fx_px, c.fy_px);
            println!("  cx, cy              {:.3}, {:.3} px", c.cx_px, c.cy_px);
            let p = c.position_m;
            println!(
                "  centre T_nom        ({:.3}, {:.3}, {:.3}) mm",
                p[0] * 1e3,
                p[1] * 1e3,
                p[2] * 1e3
            );
            let b = rig.slip.bridge_direction;
            println!(
                "slip direction        ({:.3}, {:.3}, {:.3}); pitch {:.3}°/mm",
                b[0],
                b[1],
                b[2],
                (rig.slip.pitch_rate_rad_per_m * 1e-3).to_degrees()
            );
            Ok(())
        }
    }
}

//! The PSF analysis of Sec. E (Fig. S10): Fisher information about depth (S25) summed over a
//! depth range, at the native pitch and after box integration to coarser pixels, per lens.

use crate::error::FisherError;
use crate::init::bin_planes;
use crate::precision::{FisherNoise, depth_fisher};
use faer::Mat;
use nanoeye_optics::{PhaseMap, PsfModel};

/// One (lens, pitch) result.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct CompareRow {
    /// Lens label as given.
    pub lens: String,
    /// Effective pixel pitch, µm (the CLI's unit, kept in the name).
    pub pitch_um: f64,
    /// Σ_k I(z_k) (S25), m⁻².
    pub fisher_z: f64,
    /// I(z_k) per depth, m⁻².
    pub fisher_z_per_depth: Vec<f64>,
}

/// Binned PSF planes of one lens at one pitch (for montages).
pub struct ComparePlanes {
    /// Lens label.
    pub lens: String,
    /// Pitch, µm.
    pub pitch_um: f64,
    /// Planes (fraction of incident power per effective pixel).
    pub planes: Vec<Mat<f32>>,
}

/// Evaluates every lens at every pitch: PSFs from `model` at its native pitch, box-integrated
/// to each pitch (m, ≥ native) by the sensor's integrator, S25 with `noise`.
pub fn compare_lenses(
    model: &dyn PsfModel,
    lenses: &[(String, PhaseMap)],
    depths_m: &[f64],
    pitches_m: &[f64],
    noise: &FisherNoise,
) -> Result<(Vec<CompareRow>, Vec<ComparePlanes>), FisherError> {
    let mut rows = Vec::new();
    let mut planes = Vec::new();
    for (name, map) in lenses {
        let st = model
            .forward(map, depths_m, None)
            .map_err(|e| FisherError::Shape {
                name: "optics",
                why: e.to_string(),
            })?;
        for &p in pitches_m {
            let (stack, op) = bin_planes(&st.planes, st.pitch_m, p, depths_m)?;
            let per = depth_fisher(&stack, noise)?;
            rows.push(CompareRow {
                lens: name.clone(),
                pitch_um: p * 1e6,
                fisher_z: per.iter().sum(),
                fisher_z_per_depth: per,
            });
            let binned = match op {
                None => st.planes.clone(),
                Some(op) => st
                    .planes
                    .iter()
                    .map(|m| op.forward(m))
                    .collect::<Result<Vec<_>, _>>()
                    .map_err(|e| FisherError::Shape {
                        name: "planes",
                        why: e.to_string(),
                    })?,
            };
            planes.push(ComparePlanes {
                lens: name.clone(),
                pitch_um: p * 1e6,
                planes: binned,
            });
        }
    }
    Ok((rows, planes))
}

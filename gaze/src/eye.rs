//! Eye orientation: Fick angles, Listing's law, torsion and the kappa (visual-axis) offset.
//!
//! Frame (DESIGN.md): origin at the eye's rotation centre, +z primary gaze, +y up,
//! +x = y × z. Azimuth φ rotates the gaze towards +x, elevation θ towards +y:
//! g(φ, θ) = (cos θ sin φ, sin θ, cos θ cos φ), i.e. the Fick gimbal R_y(φ) R_x(−θ).

use crate::error::GazeError;
use crate::geom::{self, Mat3, Vec3};

/// Unit gaze (optical-axis) direction for Fick azimuth `az` and elevation `el` (rad).
pub fn gaze_from_angles(az: f64, el: f64) -> Vec3 {
    let (sa, ca) = az.sin_cos();
    let (se, ce) = el.sin_cos();
    [ce * sa, se, ce * ca]
}

/// Fick azimuth and elevation (rad) of a unit gaze direction; inverse of [`gaze_from_angles`].
pub fn angles_from_gaze(g: Vec3) -> (f64, f64) {
    let az = g[0].atan2(g[2]);
    let el = g[1].atan2((g[0] * g[0] + g[2] * g[2]).sqrt());
    (az, el)
}

/// The Listing's-law rotation taking the primary direction +z onto unit gaze `g`: the rotation
/// about an axis in Listing's plane (z = 0). Errors only for g = −z, where the axis is undefined.
pub fn listing_rotation(g: Vec3) -> Result<Mat3, GazeError> {
    if !geom::is_finite(g) {
        return Err(GazeError::NonFinite {
            what: "gaze direction",
        });
    }
    let g = geom::normalize(g);
    let axis = [-g[1], g[0], 0.0]; // e_z × g, |axis| = sin(angle)
    let s = geom::norm(axis);
    let c = g[2];
    if s < 1e-300 {
        return if c > 0.0 {
            Ok(geom::IDENTITY)
        } else {
            Err(GazeError::OppositeGaze { gaze: g })
        };
    }
    let angle = s.atan2(c);
    Ok(geom::rot_from_vector(geom::scale(axis, angle / s)))
}

/// Full eye rotation for state angles: Listing's rotation to g(φ, θ) followed by an extra
/// torsion `torsion` (rad) about the line of sight (Listing's-plane thickness, C.1).
pub fn eye_rotation(az: f64, el: f64, torsion: f64) -> Result<Mat3, GazeError> {
    let l = listing_rotation(gaze_from_angles(az, el))?;
    Ok(geom::mul_mm(&l, &geom::rot_z(torsion)))
}

/// Fick torsion ψ (rad) of the Listing's-law eye position with Fick angles (az, el): the
/// angle of R_z(ψ) = R_x(el) R_y(−az) L. Closed form: |tan(ψ/2)| = |tan(az/2) tan(el/2)|.
pub fn listing_torsion(az: f64, el: f64) -> Result<f64, GazeError> {
    let l = listing_rotation(gaze_from_angles(az, el))?;
    let q = geom::mul_mm(&geom::mul_mm(&geom::rot_x(el), &geom::rot_y(-az)), &l);
    Ok(q[1][0].atan2(q[0][0]))
}

/// The visual axis for optical axis `g` and kappa angles (horizontal, vertical; rad), assuming
/// the eye obeys Listing's law (no extra torsion).
pub fn visual_axis(g: Vec3, kappa: [f64; 2]) -> Result<Vec3, GazeError> {
    let l = listing_rotation(g)?;
    Ok(geom::mul_mv(&l, gaze_from_angles(kappa[0], kappa[1])))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn angles_round_trip() {
        for &(a, e) in &[(0.0, 0.0), (0.3, -0.2), (-0.6, 0.25), (0.78, 0.26)] {
            let (a2, e2) = angles_from_gaze(gaze_from_angles(a, e));
            assert!((a - a2).abs() < 1e-15 && (e - e2).abs() < 1e-15);
        }
    }

    #[test]
    fn listing_axis_lies_in_listing_plane() {
        let g = gaze_from_angles(0.4, 0.3);
        let l = listing_rotation(g).unwrap();
        let mapped = geom::mul_mv(&l, [0.0, 0.0, 1.0]);
        assert!(geom::norm(geom::sub(mapped, g)) < 1e-15);
        // A rotation about an axis in the xy plane has R - Rᵀ with zero (x,y) skew part.
        assert!((l[0][1] - l[1][0]).abs() < 1e-15);
    }
}

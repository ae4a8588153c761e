//! Small fixed-size 3-vector and 3×3 rotation helpers (f64, no allocation).

/// A 3-vector in metres (positions) or unitless (directions).
pub type Vec3 = [f64; 3];
/// A 3×3 matrix stored as rows.
pub type Mat3 = [[f64; 3]; 3];

/// a + b.
#[inline]
pub fn add(a: Vec3, b: Vec3) -> Vec3 {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

/// a − b.
#[inline]
pub fn sub(a: Vec3, b: Vec3) -> Vec3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

/// k·a.
#[inline]
pub fn scale(a: Vec3, k: f64) -> Vec3 {
    [a[0] * k, a[1] * k, a[2] * k]
}

/// a · b.
#[inline]
pub fn dot(a: Vec3, b: Vec3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// a × b.
#[inline]
pub fn cross(a: Vec3, b: Vec3) -> Vec3 {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// Euclidean norm.
#[inline]
pub fn norm(a: Vec3) -> f64 {
    dot(a, a).sqrt()
}

/// a / |a| (caller guarantees a ≠ 0).
#[inline]
pub fn normalize(a: Vec3) -> Vec3 {
    scale(a, 1.0 / norm(a))
}

/// True when every component is finite.
#[inline]
pub fn is_finite(a: Vec3) -> bool {
    a.iter().all(|x| x.is_finite())
}

/// M v.
#[inline]
pub fn mul_mv(m: &Mat3, v: Vec3) -> Vec3 {
    [dot(m[0], v), dot(m[1], v), dot(m[2], v)]
}

/// Mᵀ v.
#[inline]
pub fn mul_mtv(m: &Mat3, v: Vec3) -> Vec3 {
    [
        m[0][0] * v[0] + m[1][0] * v[1] + m[2][0] * v[2],
        m[0][1] * v[0] + m[1][1] * v[1] + m[2][1] * v[2],
        m[0][2] * v[0] + m[1][2] * v[1] + m[2][2] * v[2],
    ]
}

/// A B.
pub fn mul_mm(a: &Mat3, b: &Mat3) -> Mat3 {
    let mut c = [[0.0; 3]; 3];
    for (i, row) in c.iter_mut().enumerate() {
        for (j, cij) in row.iter_mut().enumerate() {
            *cij = (0..3).map(|k| a[i][k] * b[k][j]).sum();
        }
    }
    c
}

/// Aᵀ.
pub fn transpose(a: &Mat3) -> Mat3 {
    let mut t = [[0.0; 3]; 3];
    for (i, row) in a.iter().enumerate() {
        for (j, &v) in row.iter().enumerate() {
            t[j][i] = v;
        }
    }
    t
}

/// The identity matrix.
pub const IDENTITY: Mat3 = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];

/// Rotation by `angle` (rad) about the world x axis (right-handed).
pub fn rot_x(angle: f64) -> Mat3 {
    let (s, c) = angle.sin_cos();
    [[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]]
}

/// Rotation by `angle` (rad) about the world y axis (right-handed).
pub fn rot_y(angle: f64) -> Mat3 {
    let (s, c) = angle.sin_cos();
    [[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]
}

/// Rotation by `angle` (rad) about the world z axis (right-handed).
pub fn rot_z(angle: f64) -> Mat3 {
    let (s, c) = angle.sin_cos();
    [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
}

/// Rotation for a rotation vector (axis × angle in rad), by Rodrigues' formula; exact at 0.
pub fn rot_from_vector(w: Vec3) -> Mat3 {
    let theta = norm(w);
    // sin θ/θ and (1 − cos θ)/θ² by their series near 0 so tiny rotations stay exact.
    let (a, b) = if theta < 1e-4 {
        let t2 = theta * theta;
        (1.0 - t2 / 6.0, 0.5 - t2 / 24.0)
    } else {
        (theta.sin() / theta, (1.0 - theta.cos()) / (theta * theta))
    };
    let [x, y, z] = w;
    let k = [[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]];
    let mut r = IDENTITY;
    for i in 0..3 {
        for j in 0..3 {
            let kk: f64 = (0..3).map(|m| k[i][m] * k[m][j]).sum();
            r[i][j] += a * k[i][j] + b * kk;
        }
    }
    r
}

/// Largest deviation of RᵀR from the identity and det R (for validating rotations).
pub fn orthonormality(r: &Mat3) -> (f64, f64) {
    let rtr = mul_mm(&transpose(r), r);
    let mut dev: f64 = 0.0;
    for (i, row) in rtr.iter().enumerate() {
        for (j, &v) in row.iter().enumerate() {
            let target = if i == j { 1.0 } else { 0.0 };
            dev = dev.max((v - target).abs());
        }
    }
    let det = dot(r[0], cross(r[1], r[2]));
    (dev, det)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rodrigues_matches_axis_rotations() {
        for &a in &[1e-9, 1e-5, 0.3, 2.0, -1.2] {
            for (axis, r) in [
                ([1.0, 0.0, 0.0], rot_x(a)),
                ([0.0, 1.0, 0.0], rot_y(a)),
                ([0.0, 0.0, 1.0], rot_z(a)),
            ] {
                let q = rot_from_vector(scale(axis, a));
                for i in 0..3 {
                    for j in 0..3 {
                        assert!((q[i][j] - r[i][j]).abs() < 1e-15, "{a} {i}{j}");
                    }
                }
            }
        }
    }

    #[test]
    fn transpose_mul_inverts_rotation() {
        let r = rot_from_vector([0.3, -0.2, 0.7]);
        let v = [1.0, 2.0, -3.0];
        let back = mul_mtv(&r, mul_mv(&r, v));
        assert!(norm(sub(back, v)) < 1e-14);
        let (dev, det) = orthonormality(&r);
        assert!(dev < 1e-15 && (det - 1.0).abs() < 1e-15);
    }
}

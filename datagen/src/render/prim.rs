//! Ray primitives: clipped spheres, annular discs and triangles, with bounds and analytic hits.

use super::Ray;
use nanoeye_gaze::{Vec3, geom};

/// Axis-aligned bounding box (m). `repr(C)`: `min` then `max`, six contiguous f64, which the
/// BVH build's binning loads as two overlapping four-lane vectors.
#[derive(Debug, Clone, Copy, PartialEq)]
#[repr(C)]
pub struct Aabb {
    /// Minimum corner.
    pub min: Vec3,
    /// Maximum corner.
    pub max: Vec3,
}

impl Aabb {
    /// The empty box (union identity).
    pub const EMPTY: Aabb = Aabb {
        min: [f64::INFINITY; 3],
        max: [f64::NEG_INFINITY; 3],
    };

    /// Smallest box holding both.
    pub fn union(&self, o: &Aabb) -> Aabb {
        Aabb {
            min: [
                self.min[0].min(o.min[0]),
                self.min[1].min(o.min[1]),
                self.min[2].min(o.min[2]),
            ],
            max: [
                self.max[0].max(o.max[0]),
                self.max[1].max(o.max[1]),
                self.max[2].max(o.max[2]),
            ],
        }
    }

    /// Grows the box to hold point `p`.
    pub fn grow(&self, p: Vec3) -> Aabb {
        self.union(&Aabb { min: p, max: p })
    }

    /// Surface area (m²); 0 for an empty box.
    pub fn area(&self) -> f64 {
        let d = geom::sub(self.max, self.min);
        if d.iter().any(|x| x.is_nan() || *x < 0.0) {
            return 0.0;
        }
        2.0 * (d[0] * d[1] + d[1] * d[2] + d[2] * d[0])
    }

    /// Box centre.
    pub fn center(&self) -> Vec3 {
        geom::scale(geom::add(self.min, self.max), 0.5)
    }

    /// Slab test: entry distance if the ray meets the box within (0, t_max).
    #[inline]
    pub fn hit(&self, ray: &Ray, t_max: f64) -> Option<f64> {
        let mut t0 = 0.0f64;
        let mut t1 = t_max;
        for a in 0..3 {
            let ta = (self.min[a] - ray.origin[a]) * ray.inv_dir[a];
            let tb = (self.max[a] - ray.origin[a]) * ray.inv_dir[a];
            let (lo, hi) = if ta < tb { (ta, tb) } else { (tb, ta) };
            // NaN (0·∞ on a slab face) leaves the interval unchanged.
            if lo > t0 {
                t0 = lo;
            }
            if hi < t1 {
                t1 = hi;
            }
            if t0 > t1 {
                return None;
            }
        }
        Some(t0)
    }
}

/// Which part of a sphere exists.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Clip {
    /// The whole sphere.
    None,
    /// Only points p with `sign · (n·p − d) ≥ 0` (a cap cut by a plane).
    Plane {
        /// Unit plane normal.
        normal: Vec3,
        /// Plane offset (m): the plane is n·p = d.
        offset_m: f64,
        /// +1 keeps the side the normal points to, −1 the other.
        sign: f64,
    },
}

/// Geometric shape of a primitive (m).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Shape {
    /// Sphere, possibly clipped.
    Sphere {
        /// Centre.
        center: Vec3,
        /// Radius.
        radius_m: f64,
        /// Which part exists.
        clip: Clip,
    },
    /// Annulus r_in ≤ |p − c| ≤ r_out in the plane through `center` with unit `normal`.
    Disc {
        /// Centre.
        center: Vec3,
        /// Unit normal.
        normal: Vec3,
        /// Inner radius (0 for a full disc).
        r_in_m: f64,
        /// Outer radius.
        r_out_m: f64,
    },
    /// Triangle.
    Triangle {
        /// Vertices.
        v: [Vec3; 3],
    },
}

/// Smallest ray distance (m) counted as a hit: well below every scene feature (µm-scale
/// geometry is never modelled) and far above f64 round-off at 10 cm scale.
pub const T_EPS: f64 = 1e-9;

impl Shape {
    /// Bounding box.
    pub fn bounds(&self) -> Aabb {
        match *self {
            Shape::Sphere {
                center, radius_m, ..
            } => Aabb {
                min: geom::sub(center, [radius_m; 3]),
                max: geom::add(center, [radius_m; 3]),
            },
            Shape::Disc {
                center,
                normal,
                r_out_m,
                ..
            } => {
                // Extent of a disc along axis a: r · sqrt(1 − n_a²).
                let e = [0, 1, 2].map(|a| r_out_m * (1.0 - normal[a] * normal[a]).max(0.0).sqrt());
                Aabb {
                    min: geom::sub(center, e),
                    max: geom::add(center, e),
                }
            }
            Shape::Triangle { v } => Aabb::EMPTY.grow(v[0]).grow(v[1]).grow(v[2]),
        }
    }

    /// Nearest hit distance in (T_EPS, t_max), or None.
    #[inline]
    pub fn intersect(&self, ray: &Ray, t_max: f64) -> Option<f64> {
        match *self {
            Shape::Sphere {
                center,
                radius_m,
                clip,
            } => {
                let oc = geom::sub(ray.origin, center);
                let b = geom::dot(oc, ray.dir);
                let c = geom::dot(oc, oc) - radius_m * radius_m;
                let disc = b * b - c;
                if disc < 0.0 {
                    return None;
                }
                let sq = disc.sqrt();
                // Stable roots: q = −b ∓ sq has no cancellation.
                let q = if b > 0.0 { -b - sq } else { -b + sq };
                let (mut t0, mut t1) = (q, if q != 0.0 { c / q } else { 0.0 });
                if t0 > t1 {
                    std::mem::swap(&mut t0, &mut t1);
                }
                for t in [t0, t1] {
                    if t > T_EPS && t < t_max {
                        let p = ray.at(t);
                        let keep = match clip {
                            Clip::None => true,
                            Clip::Plane {
                                normal,
                                offset_m,
                                sign,
                            } => sign * (geom::dot(normal, p) - offset_m) >= 0.0,
                        };
                        if keep {
                            return Some(t);
                        }
                    }
                }
                None
            }
            Shape::Disc {
                center,
                normal,
                r_in_m,
                r_out_m,
            } => {
                let den = geom::dot(normal, ray.dir);
                if den == 0.0 {
                    return None;
                }
                let t = geom::dot(normal, geom::sub(center, ray.origin)) / den;
                if !(t > T_EPS && t < t_max) {
                    return None;
                }
                let d = geom::sub(ray.at(t), center);
                let r2 = geom::dot(d, d);
                (r2 <= r_out_m * r_out_m && r2 >= r_in_m * r_in_m).then_some(t)
            }
            Shape::Triangle { v } => triangle_hit(
                v[0],
                geom::sub(v[1], v[0]),
                geom::sub(v[2], v[0]),
                ray,
                t_max,
            ),
        }
    }

    /// Unit geometric normal at surface point `p` (outward for spheres, the stored normal for
    /// discs, right-handed winding for triangles).
    pub fn normal(&self, p: Vec3) -> Vec3 {
        match *self {
            Shape::Sphere { center, .. } => geom::normalize(geom::sub(p, center)),
            Shape::Disc { normal, .. } => normal,
            Shape::Triangle { v } => {
                geom::normalize(geom::cross(geom::sub(v[1], v[0]), geom::sub(v[2], v[0])))
            }
        }
    }

    /// Centroid used for BVH binning.
    pub fn centroid(&self) -> Vec3 {
        match *self {
            Shape::Sphere { center, .. } | Shape::Disc { center, .. } => center,
            Shape::Triangle { v } => geom::scale(geom::add(geom::add(v[0], v[1]), v[2]), 1.0 / 3.0),
        }
    }
}

/// Möller–Trumbore: hit distance in (T_EPS, t_max) on the triangle (v0, v0 + e1, v0 + e2).
/// Takes the edges so a scene can store them once (the same f64 values
/// [`Shape::intersect`] computes, hence the same hits).
#[inline(always)]
pub fn triangle_hit(v0: Vec3, e1: Vec3, e2: Vec3, ray: &Ray, t_max: f64) -> Option<f64> {
    let p = geom::cross(ray.dir, e2);
    let det = geom::dot(e1, p);
    if det.abs() < 1e-30 {
        return None;
    }
    let inv = 1.0 / det;
    let s = geom::sub(ray.origin, v0);
    let u = geom::dot(s, p) * inv;
    if !(0.0..=1.0).contains(&u) {
        return None;
    }
    let q = geom::cross(s, e1);
    let w = geom::dot(ray.dir, q) * inv;
    if w < 0.0 || u + w > 1.0 {
        return None;
    }
    let t = geom::dot(e2, q) * inv;
    (t > T_EPS && t < t_max).then_some(t)
}

/// Two unit vectors that complete unit `n` to a right-handed orthonormal basis (e1, e2, n).
#[inline]
pub fn perpendicular_basis(n: Vec3) -> (Vec3, Vec3) {
    let a = if n[0].abs() > 0.9 {
        [0.0, 1.0, 0.0]
    } else {
        [1.0, 0.0, 0.0]
    };
    let e1 = geom::normalize(geom::cross(n, a));
    (e1, geom::cross(n, e1))
}

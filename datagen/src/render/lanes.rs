//! Four triangles of a BVH leaf tested against one ray at once.
//!
//! A leaf holds up to four primitives; the scalar Möller–Trumbore test leaves each one at the
//! first failed bound, a branch the CPU cannot predict. Here the slots' vertices and edges are
//! stored component by component ([`TriLanes`]), so four consecutive slots load as four AVX
//! lanes and every test runs to the end without a branch. The lanes compute the same
//! operations in the same order as [`prim::triangle_hit`](super::prim::triangle_hit) (no fused
//! multiply-add: Rust never contracts), so the distances and verdicts are the same bits
//! (tested).

use super::Ray;
use super::prim::T_EPS;
#[cfg(not(all(target_arch = "x86_64", target_feature = "avx")))]
use super::prim::triangle_hit;
use nanoeye_gaze::Vec3;

/// Lanes per test.
pub const LANES: usize = 4;

/// Triangle vertex v0 and edges e1, e2 of every slot, component by component: row k of nine
/// (v0 x, y, z, e1 x, y, z, e2 x, y, z; metres) holds slot s at `k · stride + s`. Each row has
/// [`LANES`] − 1 zero slots of padding, so four lanes from any slot load in bounds.
#[derive(Debug, Clone, Default)]
pub struct TriLanes {
    rows: Vec<f64>,
    stride: usize,
}

impl TriLanes {
    /// Lays out (v0, e1, e2) of each slot; non-triangle slots pass zeros (never a hit:
    /// the determinant is 0).
    pub fn new(tris: impl ExactSizeIterator<Item = (Vec3, Vec3, Vec3)>) -> TriLanes {
        let stride = tris.len() + LANES - 1;
        let mut rows = vec![0.0; 9 * stride];
        for (s, (v0, e1, e2)) in tris.enumerate() {
            for a in 0..3 {
                rows[a * stride + s] = v0[a];
                rows[(3 + a) * stride + s] = e1[a];
                rows[(6 + a) * stride + s] = e2[a];
            }
        }
        TriLanes { rows, stride }
    }

    /// Number of slots.
    pub fn len(&self) -> usize {
        self.stride.saturating_sub(LANES - 1)
    }

    /// True when there are no slots.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Slots `base .. base + 4` against `ray`: bit l of the mask is set where slot base + l is
    /// hit at a distance above [`T_EPS`], at distance `t[l]` (the caller compares it with its
    /// t_max). Lanes past the last slot are zeros and never set. Panics if `base` ≥ len.
    #[inline(always)]
    pub fn hit4(&self, base: usize, ray: &Ray) -> (u32, [f64; LANES]) {
        assert!(base < self.len(), "slot {base} of {}", self.len());
        #[cfg(all(target_arch = "x86_64", target_feature = "avx"))]
        {
            // SAFETY: base + 3 < stride, so each row's four loads are in bounds.
            unsafe { self.hit4_avx(base, ray) }
        }
        #[cfg(not(all(target_arch = "x86_64", target_feature = "avx")))]
        {
            self.hit4_scalar(base, ray)
        }
    }

    /// [`TriLanes::hit4`] one lane at a time through
    /// [`prim::triangle_hit`](super::prim::triangle_hit).
    #[cfg(any(test, not(all(target_arch = "x86_64", target_feature = "avx"))))]
    fn hit4_scalar(&self, base: usize, ray: &Ray) -> (u32, [f64; LANES]) {
        #[cfg(test)]
        use super::prim::triangle_hit;
        let mut mask = 0;
        let mut t = [0.0; LANES];
        for (l, tl) in t.iter_mut().enumerate() {
            let r = |k: usize| -> Vec3 {
                std::array::from_fn(|a| self.rows[(k + a) * self.stride + base + l])
            };
            if let Some(th) = triangle_hit(r(0), r(3), r(6), ray, f64::INFINITY) {
                mask |= 1 << l;
                *tl = th;
            }
        }
        (mask, t)
    }

    /// The four lanes on AVX, operation for operation as
    /// [`prim::triangle_hit`](super::prim::triangle_hit); the early exits become ordered
    /// comparisons folded into one mask.
    #[cfg(all(target_arch = "x86_64", target_feature = "avx"))]
    #[inline(always)]
    unsafe fn hit4_avx(&self, base: usize, ray: &Ray) -> (u32, [f64; LANES]) {
        use std::arch::x86_64::*;
        let row = |k: usize| {
            // SAFETY: the caller keeps base + 3 inside the row (padding included).
            unsafe { _mm256_loadu_pd(self.rows.as_ptr().add(k * self.stride + base)) }
        };
        let (v0, e1, e2) = (
            [row(0), row(1), row(2)],
            [row(3), row(4), row(5)],
            [row(6), row(7), row(8)],
        );
        let d = ray.dir.map(|c| unsafe { _mm256_set1_pd(c) });
        let o = ray.origin.map(|c| unsafe { _mm256_set1_pd(c) });
        let (mul, sub, add) = (_mm256_mul_pd, _mm256_sub_pd, _mm256_add_pd);
        // geom::cross and geom::dot, term by term.
        // SAFETY (this and the closures below): the build enables AVX (cfg above).
        let cross = |a: [__m256d; 3], b: [__m256d; 3]| unsafe {
            [
                sub(mul(a[1], b[2]), mul(a[2], b[1])),
                sub(mul(a[2], b[0]), mul(a[0], b[2])),
                sub(mul(a[0], b[1]), mul(a[1], b[0])),
            ]
        };
        let dot = |a: [__m256d; 3], b: [__m256d; 3]| unsafe {
            add(add(mul(a[0], b[0]), mul(a[1], b[1])), mul(a[2], b[2]))
        };
        let (mask, t) = unsafe {
            let p = cross(d, e2);
            let det = dot(e1, p);
            let abs_det = _mm256_andnot_pd(_mm256_set1_pd(-0.0), det);
            let inv = _mm256_div_pd(_mm256_set1_pd(1.0), det);
            let s = [sub(o[0], v0[0]), sub(o[1], v0[1]), sub(o[2], v0[2])];
            let u = mul(dot(s, p), inv);
            let q = cross(s, e1);
            let w = mul(dot(d, q), inv);
            let t = mul(dot(e2, q), inv);
            let (zero, one) = (_mm256_setzero_pd(), _mm256_set1_pd(1.0));
            // Accepted where triangle_hit returns: |det| ≥ 1e-30 (not <), 0 ≤ u ≤ 1, not w < 0,
            // not u + w > 1, t > T_EPS — each an ordered comparison, so a NaN goes the same way.
            let reject = _mm256_or_pd(
                _mm256_or_pd(
                    _mm256_cmp_pd::<_CMP_LT_OQ>(abs_det, _mm256_set1_pd(1e-30)),
                    _mm256_cmp_pd::<_CMP_LT_OQ>(w, zero),
                ),
                _mm256_cmp_pd::<_CMP_GT_OQ>(add(u, w), one),
            );
            let accept = _mm256_and_pd(
                _mm256_and_pd(
                    _mm256_cmp_pd::<_CMP_GE_OQ>(u, zero),
                    _mm256_cmp_pd::<_CMP_LE_OQ>(u, one),
                ),
                _mm256_cmp_pd::<_CMP_GT_OQ>(t, _mm256_set1_pd(T_EPS)),
            );
            (
                _mm256_movemask_pd(_mm256_andnot_pd(reject, accept)) as u32,
                t,
            )
        };
        let mut out = [0.0; LANES];
        // SAFETY: `out` holds four f64.
        unsafe { _mm256_storeu_pd(out.as_mut_ptr(), t) };
        (mask, out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nanoeye_gaze::geom;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// hit4 (AVX where the build has it) equals triangle_hit lane by lane, bit for bit, over
    /// random triangles and rays, degenerate and edge-grazing ones included.
    #[test]
    fn four_lanes_equal_the_scalar_test() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let mut tris = Vec::new();
        for i in 0..4001 {
            let v0: Vec3 = std::array::from_fn(|_| rng.random_range(-1.0..1.0));
            let mut e1: Vec3 = std::array::from_fn(|_| rng.random_range(-0.5..0.5));
            let e2: Vec3 = match i % 5 {
                // Degenerate: e2 parallel to e1 (det 0) or tiny.
                0 => geom::scale(e1, 2.0),
                1 => geom::scale(e1, 1e-20),
                _ => std::array::from_fn(|_| rng.random_range(-0.5..0.5)),
            };
            if i % 7 == 0 {
                e1 = [0.0; 3];
            }
            tris.push((v0, e1, e2));
        }
        let lanes = TriLanes::new(tris.iter().copied());
        assert_eq!(lanes.len(), tris.len());
        let mut hits = 0;
        for case in 0..20_000 {
            let base = rng.random_range(0..tris.len());
            // Aim at a point of slot `base`'s plane, sometimes on an edge (u + w = 1) or a
            // vertex, so the boundary comparisons are exercised.
            let (v0, e1, e2) = tris[base];
            let (a, b): (f64, f64) = match case % 4 {
                0 => (0.0, 0.0),
                1 => {
                    let a = rng.random_range(0.0..1.0);
                    (a, 1.0 - a)
                }
                _ => (rng.random_range(-0.2..1.2), rng.random_range(-0.2..1.2)),
            };
            let target = geom::add(v0, geom::add(geom::scale(e1, a), geom::scale(e2, b)));
            let o: Vec3 = std::array::from_fn(|_| rng.random_range(-2.0..2.0));
            let mut d = geom::sub(target, o);
            if d == [0.0; 3] {
                d = [0.0, 0.0, 1.0];
            }
            let ray = Ray::new(o, d);
            let (m0, t0) = lanes.hit4_scalar(base, &ray);
            let (m1, t1) = lanes.hit4(base, &ray);
            assert_eq!(m0, m1, "case {case}: masks");
            for l in 0..LANES {
                if m0 & (1 << l) != 0 {
                    assert_eq!(t0[l].to_bits(), t1[l].to_bits(), "case {case}, lane {l}");
                }
            }
            // Lanes past the last slot are never hit.
            if base + LANES > tris.len() {
                assert_eq!(m1 >> (tris.len() - base), 0, "case {case}: padding");
            }
            hits += (m0 & 1) as usize;
        }
        // About a fifth of the cases hit lane 0 (4,001 with this seed): the lanes are exercised.
        assert!(hits > 2_000, "{hits}");
    }

    #[test]
    fn empty_lanes_have_no_slots() {
        let l = TriLanes::new(std::iter::empty());
        assert!(l.is_empty());
        assert!(TriLanes::default().is_empty());
    }
}

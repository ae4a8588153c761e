//! Bounding-volume hierarchy: binned surface-area-heuristic build (12 bins per axis; the two
//! halves of the top splits built in parallel), then a packed traversal layout: one 64-byte
//! node per inner node holding both children's boxes (f32, rounded outward), stack traversal
//! nearest child first that skips any node entered beyond the current nearest hit.

use super::Ray;
use super::prim::Aabb;
use nanoeye_gaze::Vec3;

const BINS: usize = 12;
const LEAF_MAX: usize = 4;
// Relative cost of a ray–box test against a ray–primitive test in the SAH.
const TRAVERSAL_COST: f64 = 0.5;
const STACK: usize = 32;
// Below this many primitives a subtree is built on the calling thread: spawning costs more.
const PAR_MIN: usize = 4096;
// Parallel split levels: 2 levels give 4 subtrees, enough to balance 2 cores across the
// uneven SAH splits near the root.
const PAR_LEVELS: u32 = 2;

/// One BVH node of the build tree: an inner node's children are `first` and `first + 1`; a
/// leaf holds primitive slots `first .. first + count` of [`Bvh::order`].
#[derive(Debug, Clone, Copy)]
pub struct Node {
    /// Bounds of everything below.
    pub bounds: Aabb,
    /// First child (inner) or first primitive slot (leaf).
    pub first: u32,
    /// Number of primitives (0 for an inner node).
    pub count: u32,
}

/// An inner node in traversal layout: both children's boxes in one cache line, so a visit
/// costs one line instead of two 56-byte f64 nodes.
#[derive(Debug, Clone, Copy, Default)]
#[repr(C, align(64))]
pub struct Packed {
    /// Minimum corners of child 0 and 1 (rounded down to f32).
    pub min: [[f32; 3]; 2],
    /// Maximum corners of child 0 and 1 (rounded up to f32).
    pub max: [[f32; 3]; 2],
    /// Per child: its packed index (inner) or its first primitive slot (leaf).
    pub first: [u32; 2],
    /// Per child: number of primitives (0 for an inner child).
    pub count: [u32; 2],
}

/// A BVH over primitive bounds.
#[derive(Debug, Clone, Default)]
pub struct Bvh {
    /// Build-tree nodes, root first.
    pub nodes: Vec<Node>,
    /// Primitive indices in leaf order: the traversal callbacks receive a slot `s` of this
    /// array, the primitive is `order[s]`.
    pub order: Vec<u32>,
    /// Inner nodes in traversal layout, root first (empty when the root is a leaf).
    pub packed: Vec<Packed>,
}

/// One pending traversal entry: a child reference and the distance at which the ray enters it.
#[derive(Clone, Copy)]
struct Entry {
    first: u32,
    count: u32,
    t: f64,
}

impl Bvh {
    /// Builds the hierarchy over `bounds` (one box per primitive).
    pub fn build(bounds: &[Aabb]) -> Bvh {
        if bounds.is_empty() {
            return Bvh::default();
        }
        let centroids: Vec<Vec3> = bounds.iter().map(|b| b.center()).collect();
        let mut order: Vec<u32> = (0..bounds.len() as u32).collect();
        let nodes = build_subtree(bounds, &centroids, &mut order, 0, PAR_LEVELS);
        let packed = pack(&nodes);
        Bvh {
            nodes,
            order,
            packed,
        }
    }

    /// Nearest hit: `hit(slot, t_max)` returns the hit distance below `t_max` of primitive
    /// `order[slot]`. Returns (slot, distance).
    #[inline]
    pub fn closest(
        &self,
        ray: &Ray,
        t_max: f64,
        mut hit: impl FnMut(u32, f64) -> Option<f64>,
    ) -> Option<(u32, f64)> {
        let mut best: Option<(u32, f64)> = None;
        let mut t_best = t_max;
        self.walk(
            ray,
            &mut t_best,
            #[inline(always)]
            |s, t| {
                let h = hit(s, t);
                if let Some(th) = h {
                    best = Some((s, th));
                }
                h
            },
        );
        best
    }

    /// True if any primitive is hit below `t_max` (shadow rays); `hit` as in [`Bvh::closest`].
    #[inline]
    pub fn any(&self, ray: &Ray, t_max: f64, mut hit: impl FnMut(u32, f64) -> Option<f64>) -> bool {
        let mut t = t_max;
        let mut found = false;
        self.walk(
            ray,
            &mut t,
            #[inline(always)]
            |s, tm| {
                if hit(s, tm).is_some() {
                    found = true;
                    // Every pending node is entered at t ≥ 0 > −1: the traversal ends here.
                    return Some(-1.0);
                }
                None
            },
        );
        found
    }

    #[inline(always)]
    fn walk(&self, ray: &Ray, t_max: &mut f64, mut hit: impl FnMut(u32, f64) -> Option<f64>) {
        let Some(root) = self.nodes.first() else {
            return;
        };
        if root.bounds.hit(ray, *t_max).is_none() {
            return;
        }
        let mut leaf = |first: u32, count: u32, t_max: &mut f64| {
            for s in first..first + count {
                if let Some(t) = hit(s, *t_max) {
                    *t_max = t;
                    // An any-hit query is answered (see Bvh::any).
                    if t < 0.0 {
                        break;
                    }
                }
            }
        };
        if root.count > 0 {
            leaf(root.first, root.count, t_max);
            return;
        }
        let mut stack = [Entry {
            first: 0,
            count: 0,
            t: 0.0,
        }; STACK];
        // Only a tree deeper than STACK spills here; Vec::new does not allocate until then.
        let mut spill: Vec<Entry> = Vec::new();
        let mut sp = 0;
        let mut cur = Entry {
            first: 0,
            count: 0,
            t: 0.0,
        };
        loop {
            if cur.count > 0 {
                leaf(cur.first, cur.count, t_max);
            } else {
                let n = &self.packed[cur.first as usize];
                let ta = slab(&n.min[0], &n.max[0], ray, *t_max);
                let tb = slab(&n.min[1], &n.max[1], ray, *t_max);
                let a = |t| Entry {
                    first: n.first[0],
                    count: n.count[0],
                    t,
                };
                let b = |t| Entry {
                    first: n.first[1],
                    count: n.count[1],
                    t,
                };
                // Descend into the near child, keep the far one for later.
                let far = match (ta, tb) {
                    (Some(x), Some(y)) => {
                        if x <= y {
                            cur = a(x);
                            Some(b(y))
                        } else {
                            cur = b(y);
                            Some(a(x))
                        }
                    }
                    (Some(x), None) => {
                        cur = a(x);
                        None
                    }
                    (None, Some(y)) => {
                        cur = b(y);
                        None
                    }
                    (None, None) => None,
                };
                if ta.is_some() || tb.is_some() {
                    if let Some(f) = far {
                        if sp < STACK && spill.is_empty() {
                            stack[sp] = f;
                            sp += 1;
                        } else {
                            spill.push(f);
                        }
                    }
                    continue;
                }
            }
            // Pop the next pending node, skipping those entered beyond the nearest hit so
            // far: nothing inside them can be nearer.
            loop {
                let e = if let Some(e) = spill.pop() {
                    e
                } else if sp > 0 {
                    sp -= 1;
                    stack[sp]
                } else {
                    return;
                };
                if e.t <= *t_max {
                    cur = e;
                    break;
                }
            }
        }
    }

    /// Depth of the tree (1 for a single leaf).
    pub fn depth(&self) -> usize {
        fn d(b: &Bvh, n: usize) -> usize {
            let node = &b.nodes[n];
            if node.count > 0 {
                1
            } else {
                1 + d(b, node.first as usize).max(d(b, node.first as usize + 1))
            }
        }
        if self.nodes.is_empty() { 0 } else { d(self, 0) }
    }
}

/// Slab test against an f32 box: entry distance if the ray meets it within (0, t_max). The
/// arithmetic is f64 so the outward-rounded box is only ever larger than the exact one.
#[inline(always)]
fn slab(min: &[f32; 3], max: &[f32; 3], ray: &Ray, t_max: f64) -> Option<f64> {
    let mut t0 = 0.0f64;
    let mut t1 = t_max;
    for a in 0..3 {
        let ta = (min[a] as f64 - ray.origin[a]) * ray.inv_dir[a];
        let tb = (max[a] as f64 - ray.origin[a]) * ray.inv_dir[a];
        let (lo, hi) = if ta < tb { (ta, tb) } else { (tb, ta) };
        // NaN (0·∞ on a slab face) leaves the interval unchanged.
        if lo > t0 {
            t0 = lo;
        }
        if hi < t1 {
            t1 = hi;
        }
    }
    (t0 <= t1).then_some(t0)
}

/// Largest f32 ≤ x (x finite or infinite, not NaN).
fn f32_down(x: f64) -> f32 {
    let f = x as f32;
    if (f as f64) <= x {
        return f;
    }
    let b = f.to_bits();
    if f == 0.0 {
        -f32::from_bits(1)
    } else if f > 0.0 {
        f32::from_bits(b - 1)
    } else {
        f32::from_bits(b + 1)
    }
}

/// Smallest f32 ≥ x.
fn f32_up(x: f64) -> f32 {
    -f32_down(-x)
}

/// The traversal layout of a build tree (inner nodes only, in build order).
fn pack(nodes: &[Node]) -> Vec<Packed> {
    // Build index of each inner node → its packed index.
    let mut map = vec![u32::MAX; nodes.len()];
    let mut k = 0u32;
    for (i, n) in nodes.iter().enumerate() {
        if n.count == 0 {
            map[i] = k;
            k += 1;
        }
    }
    nodes
        .iter()
        .filter(|n| n.count == 0)
        .map(|n| {
            let mut p = Packed::default();
            for c in 0..2 {
                let ch = &nodes[n.first as usize + c];
                p.min[c] = ch.bounds.min.map(f32_down);
                p.max[c] = ch.bounds.max.map(f32_up);
                if ch.count > 0 {
                    p.first[c] = ch.first;
                    p.count[c] = ch.count;
                } else {
                    p.first[c] = map[n.first as usize + c];
                    p.count[c] = 0;
                }
            }
            p
        })
        .collect()
}

// The build's own min/max: bounds are finite (Scene::new checks), so the NaN handling of
// f64::min/max is not needed, and ±0 ties only ever feed areas and slab tests, where the sign
// of a zero makes no difference.
#[inline(always)]
fn lo(a: f64, b: f64) -> f64 {
    if a < b { a } else { b }
}

#[inline(always)]
fn hi(a: f64, b: f64) -> f64 {
    if a > b { a } else { b }
}

#[inline(always)]
fn join(a: &Aabb, b: &Aabb) -> Aabb {
    Aabb {
        min: [
            lo(a.min[0], b.min[0]),
            lo(a.min[1], b.min[1]),
            lo(a.min[2], b.min[2]),
        ],
        max: [
            hi(a.max[0], b.max[0]),
            hi(a.max[1], b.max[1]),
            hi(a.max[2], b.max[2]),
        ],
    }
}

#[inline(always)]
fn join_point(a: &Aabb, p: Vec3) -> Aabb {
    join(a, &Aabb { min: p, max: p })
}

/// Bounds and centroid bounds of the primitives in `idx`.
fn extent(idx: &[u32], bounds: &[Aabb], cen: &[Vec3]) -> (Aabb, Aabb) {
    let mut bb = Aabb::EMPTY;
    let mut cb = Aabb::EMPTY;
    for &i in idx {
        bb = join(&bb, &bounds[i as usize]);
        cb = join_point(&cb, cen[i as usize]);
    }
    (bb, cb)
}

/// Splits `idx` in place by the binned SAH: Some(mid) with `idx[..mid]` the left child, or
/// None for a leaf.
fn split(idx: &mut [u32], bounds: &[Aabb], cen: &[Vec3], cb: &Aabb, bb: &Aabb) -> Option<usize> {
    let n = idx.len();
    if n <= 1 {
        return None;
    }
    let (axis, split) = best_split(idx, bounds, cen, cb, bb)?;
    let lo = cb.min[axis];
    let ext = cb.max[axis] - lo;
    let bin = |c: Vec3| (((c[axis] - lo) / ext * BINS as f64) as usize).min(BINS - 1);
    let mut mid = 0;
    for k in 0..n {
        if bin(cen[idx[k] as usize]) < split {
            idx.swap(k, mid);
            mid += 1;
        }
    }
    (mid != 0 && mid != n).then_some(mid)
}

/// Builds the subtree over `idx` (slots `base ..` of the order array) in local layout: root
/// at 0, leaves' `first` already global slots. The top `par` levels split across threads.
fn build_subtree(
    bounds: &[Aabb],
    cen: &[Vec3],
    idx: &mut [u32],
    base: usize,
    par: u32,
) -> Vec<Node> {
    if par == 0 || idx.len() < PAR_MIN {
        return build_serial(bounds, cen, idx, base);
    }
    let (bb, cb) = extent(idx, bounds, cen);
    let Some(mid) = split(idx, bounds, cen, &cb, &bb) else {
        return vec![Node {
            bounds: bb,
            first: base as u32,
            count: idx.len() as u32,
        }];
    };
    let (l, r) = idx.split_at_mut(mid);
    let (ln, rn) = rayon::join(
        || build_subtree(bounds, cen, l, base, par - 1),
        || build_subtree(bounds, cen, r, base + mid, par - 1),
    );
    // Layout: root, the two child roots, then the rest of the left and of the right subtree.
    let (nl, nr) = (ln.len(), rn.len());
    let map_l = |i: u32| if i == 0 { 1 } else { i + 2 };
    let map_r = |i: u32| if i == 0 { 2 } else { i + 1 + nl as u32 };
    let mut out = Vec::with_capacity(1 + nl + nr);
    out.push(Node {
        bounds: bb,
        first: 1,
        count: 0,
    });
    let fix = |n: &Node, map: &dyn Fn(u32) -> u32| Node {
        first: if n.count == 0 { map(n.first) } else { n.first },
        ..*n
    };
    out.push(fix(&ln[0], &map_l));
    out.push(fix(&rn[0], &map_r));
    out.extend(ln[1..].iter().map(|n| fix(n, &map_l)));
    out.extend(rn[1..].iter().map(|n| fix(n, &map_r)));
    out
}

/// Single-threaded build of a subtree (layout as in [`build_subtree`]).
fn build_serial(bounds: &[Aabb], cen: &[Vec3], idx: &mut [u32], base: usize) -> Vec<Node> {
    let mut nodes = Vec::with_capacity(2 * idx.len());
    nodes.push(Node {
        bounds: Aabb::EMPTY,
        first: 0,
        count: 0,
    });
    // Explicit work stack: (node index, start, end) – deep recursion cannot overflow.
    let mut work = vec![(0usize, 0usize, idx.len())];
    while let Some((ni, start, end)) = work.pop() {
        let slice = &mut idx[start..end];
        let (bb, cb) = extent(slice, bounds, cen);
        nodes[ni] = Node {
            bounds: bb,
            first: (base + start) as u32,
            count: (end - start) as u32,
        };
        let Some(mid) = split(slice, bounds, cen, &cb, &bb) else {
            continue;
        };
        let left = nodes.len();
        let blank = Node {
            bounds: Aabb::EMPTY,
            first: 0,
            count: 0,
        };
        nodes.push(blank);
        nodes.push(blank);
        nodes[ni].first = left as u32;
        nodes[ni].count = 0;
        work.push((left, start, start + mid));
        work.push((left + 1, start + mid, end));
    }
    nodes
}

/// Best (axis, bin split) by the binned SAH, or None when a leaf is cheaper.
fn best_split(
    idx: &[u32],
    bounds: &[Aabb],
    cen: &[Vec3],
    cb: &Aabb,
    bb: &Aabb,
) -> Option<(usize, usize)> {
    let n = idx.len();
    let leaf_cost = n as f64;
    let parent_area = bb.area().max(1e-300);
    let mut best: Option<(f64, usize, usize)> = None;
    #[allow(clippy::needless_range_loop)] // axis indexes three parallel arrays
    for axis in 0..3 {
        let lo = cb.min[axis];
        let ext = cb.max[axis] - lo;
        if ext.is_nan() || ext <= 0.0 {
            continue;
        }
        let mut bin_box = [Aabb::EMPTY; BINS];
        let mut bin_n = [0usize; BINS];
        for &i in idx {
            let b = (((cen[i as usize][axis] - lo) / ext * BINS as f64) as usize).min(BINS - 1);
            bin_box[b] = join(&bin_box[b], &bounds[i as usize]);
            bin_n[b] += 1;
        }
        // Right-to-left sweep of cumulative area × count.
        let mut right_cost = [0.0; BINS];
        let mut acc = Aabb::EMPTY;
        let mut cnt = 0;
        for b in (1..BINS).rev() {
            acc = join(&acc, &bin_box[b]);
            cnt += bin_n[b];
            right_cost[b] = acc.area() * cnt as f64;
        }
        let mut acc = Aabb::EMPTY;
        let mut cnt = 0;
        for split in 1..BINS {
            acc = join(&acc, &bin_box[split - 1]);
            cnt += bin_n[split - 1];
            if cnt == 0 || cnt == n {
                continue;
            }
            let cost = TRAVERSAL_COST + (acc.area() * cnt as f64 + right_cost[split]) / parent_area;
            if best.is_none_or(|(c, _, _)| cost < c) {
                best = Some((cost, axis, split));
            }
        }
    }
    let (cost, axis, split) = best?;
    (cost < leaf_cost || n > LEAF_MAX).then_some((axis, split))
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// The packed boxes must never be smaller than the exact ones: f32_down/f32_up bracket x
    /// and are the tightest f32 that do.
    #[test]
    fn f32_rounding_brackets_tightly() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let mut xs = vec![0.0, -0.0, 1e-3, -1e-3, 1e-45, -1e-45, 1e-300, 1e300, -1e300];
        for _ in 0..20_000 {
            let m: f64 = rng.random_range(-1.0..1.0);
            xs.push(m * 10f64.powi(rng.random_range(-40..40)));
        }
        for x in xs {
            let (d, u) = (f32_down(x), f32_up(x));
            assert!((d as f64) <= x && (u as f64) >= x, "{x}: {d} {u}");
            // Tight: the next f32 outward from the bound would be on the wrong side of x.
            if d.is_finite() && (d as f64) < x {
                assert!(next_up(d) as f64 > x, "{x}: {d} not the largest below");
            }
            if u.is_finite() && (u as f64) > x {
                assert!(
                    ((-next_up(-u)) as f64) < x,
                    "{x}: {u} not the smallest above"
                );
            }
        }
    }

    fn next_up(f: f32) -> f32 {
        if f == 0.0 {
            f32::from_bits(1)
        } else if f > 0.0 {
            f32::from_bits(f.to_bits() + 1)
        } else {
            f32::from_bits(f.to_bits() - 1)
        }
    }
}

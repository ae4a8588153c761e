//! Bounding-volume hierarchy: binned surface-area-heuristic build (12 bins per axis), flat
//! node array, stack traversal nearest child first.

use super::Ray;
use super::prim::Aabb;
use nanoeye_gaze::Vec3;

const BINS: usize = 12;
const LEAF_MAX: usize = 4;
// Relative cost of a ray–box test against a ray–primitive test in the SAH.
const TRAVERSAL_COST: f64 = 0.5;
const STACK: usize = 64;

/// One BVH node: an inner node's children are `first` and `first + 1`; a leaf holds primitive
/// slots `first .. first + count` of [`Bvh::order`].
#[derive(Debug, Clone, Copy)]
pub struct Node {
    /// Bounds of everything below.
    pub bounds: Aabb,
    /// First child (inner) or first primitive slot (leaf).
    pub first: u32,
    /// Number of primitives (0 for an inner node).
    pub count: u32,
}

/// A BVH over primitive bounds.
#[derive(Debug, Clone, Default)]
pub struct Bvh {
    /// Nodes, root first.
    pub nodes: Vec<Node>,
    /// Primitive indices in leaf order.
    pub order: Vec<u32>,
}

impl Bvh {
    /// Builds the hierarchy over `bounds` (one box per primitive).
    pub fn build(bounds: &[Aabb]) -> Bvh {
        let centroids: Vec<Vec3> = bounds.iter().map(|b| b.center()).collect();
        let mut order: Vec<u32> = (0..bounds.len() as u32).collect();
        let mut nodes = Vec::with_capacity(2 * bounds.len().max(1));
        if bounds.is_empty() {
            return Bvh { nodes, order };
        }
        nodes.push(Node {
            bounds: Aabb::EMPTY,
            first: 0,
            count: bounds.len() as u32,
        });
        // Explicit work stack: (node index, start, end) – deep recursion cannot overflow.
        let mut work = vec![(0usize, 0usize, bounds.len())];
        while let Some((ni, start, end)) = work.pop() {
            let mut bb = Aabb::EMPTY;
            let mut cb = Aabb::EMPTY;
            for &i in &order[start..end] {
                bb = bb.union(&bounds[i as usize]);
                cb = cb.grow(centroids[i as usize]);
            }
            nodes[ni].bounds = bb;
            nodes[ni].first = start as u32;
            nodes[ni].count = (end - start) as u32;
            let n = end - start;
            if n <= 1 {
                continue;
            }
            let Some((axis, split)) = best_split(&order[start..end], bounds, &centroids, &cb, &bb)
            else {
                continue;
            };
            let lo = cb.min[axis];
            let ext = cb.max[axis] - lo;
            let bin = |c: Vec3| (((c[axis] - lo) / ext * BINS as f64) as usize).min(BINS - 1);
            let slice = &mut order[start..end];
            let mut mid = 0;
            for k in 0..slice.len() {
                if bin(centroids[slice[k] as usize]) < split {
                    slice.swap(k, mid);
                    mid += 1;
                }
            }
            if mid == 0 || mid == n {
                continue;
            }
            let left = nodes.len();
            nodes.push(Node {
                bounds: Aabb::EMPTY,
                first: 0,
                count: 0,
            });
            nodes.push(Node {
                bounds: Aabb::EMPTY,
                first: 0,
                count: 0,
            });
            nodes[ni].first = left as u32;
            nodes[ni].count = 0;
            work.push((left, start, start + mid));
            work.push((left + 1, start + mid, end));
        }
        Bvh { nodes, order }
    }

    /// Nearest hit: `hit(prim, t_max)` returns the primitive's hit distance below `t_max`.
    /// Returns (primitive, distance).
    #[inline]
    pub fn closest(
        &self,
        ray: &Ray,
        t_max: f64,
        mut hit: impl FnMut(u32, f64) -> Option<f64>,
    ) -> Option<(u32, f64)> {
        let mut best: Option<(u32, f64)> = None;
        let mut t_best = t_max;
        self.walk(ray, &mut t_best, |p, t| {
            let h = hit(p, t);
            if let Some(th) = h {
                best = Some((p, th));
            }
            h
        });
        best
    }

    /// True if any primitive is hit below `t_max` (shadow rays).
    #[inline]
    pub fn any(&self, ray: &Ray, t_max: f64, mut hit: impl FnMut(u32, f64) -> Option<f64>) -> bool {
        let mut t = t_max;
        let mut found = false;
        self.walk(ray, &mut t, |p, tm| {
            if hit(p, tm).is_some() {
                found = true;
                // Collapsing t_max ends the traversal.
                return Some(0.0);
            }
            None
        });
        found
    }

    #[inline]
    fn walk(&self, ray: &Ray, t_max: &mut f64, mut hit: impl FnMut(u32, f64) -> Option<f64>) {
        if self.nodes.is_empty() || self.nodes[0].bounds.hit(ray, *t_max).is_none() {
            return;
        }
        let mut stack = [0u32; STACK];
        let mut sp = 1;
        while sp > 0 {
            sp -= 1;
            let node = &self.nodes[stack[sp] as usize];
            if node.count > 0 {
                let s = node.first as usize;
                for &p in &self.order[s..s + node.count as usize] {
                    if let Some(t) = hit(p, *t_max) {
                        *t_max = t;
                    }
                }
                continue;
            }
            let (a, b) = (node.first, node.first + 1);
            let ta = self.nodes[a as usize].bounds.hit(ray, *t_max);
            let tb = self.nodes[b as usize].bounds.hit(ray, *t_max);
            // Push the far child first so the near one is popped next.
            let mut push = |n: u32| {
                if sp < STACK {
                    stack[sp] = n;
                    sp += 1;
                }
            };
            match (ta, tb) {
                (Some(x), Some(y)) => {
                    if x <= y {
                        push(b);
                        push(a);
                    } else {
                        push(a);
                        push(b);
                    }
                }
                (Some(_), None) => push(a),
                (None, Some(_)) => push(b),
                (None, None) => {}
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
            bin_box[b] = bin_box[b].union(&bounds[i as usize]);
            bin_n[b] += 1;
        }
        // Right-to-left sweep of cumulative area × count.
        let mut right_cost = [0.0; BINS];
        let mut acc = Aabb::EMPTY;
        let mut cnt = 0;
        for b in (1..BINS).rev() {
            acc = acc.union(&bin_box[b]);
            cnt += bin_n[b];
            right_cost[b] = acc.area() * cnt as f64;
        }
        let mut acc = Aabb::EMPTY;
        let mut cnt = 0;
        for split in 1..BINS {
            acc = acc.union(&bin_box[split - 1]);
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

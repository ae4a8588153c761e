//! Bounding-volume hierarchy: binned surface-area-heuristic build (12 bins per axis; the two
//! halves of the top splits built in parallel), collapsed into a 4-wide traversal layout: one
//! 128-byte node holds up to four children's boxes (f32, rounded outward, one array per axis
//! and side so the four slab tests run as vector lanes), stack traversal nearest child first
//! that skips any node entered beyond the current nearest hit.

use super::Ray;
use super::prim::Aabb;
use nanoeye_gaze::Vec3;

const BINS: usize = 12;
const LEAF_MAX: usize = 4;
/// Most primitives in any leaf (a [`Wide`] child's count is a u16): only coincident
/// centroids leave the SAH without a split, and then a leaf beyond this is halved.
pub const LEAF_HARD_MAX: usize = u16::MAX as usize;
const _: () = assert!(std::mem::size_of::<Wide>() == 128);
// Relative cost of a ray–box test against a ray–primitive test in the SAH. 0.5 while a leaf's
// primitives were tested one by one; with a leaf's four triangles in one vector test
// (render::lanes) a node costs more than a primitive: 1.0, 1.5 and 2.0 rendered the bench
// scene 3-4 % faster than 0.5 on one thread (no difference among them beyond noise) and
// built the tree faster (fewer nodes). Images are byte-identical (render_check, seeds 1, 7).
const TRAVERSAL_COST: f64 = 1.5;
// Pending entries kept on the call stack: a 4-wide node pushes up to three.
const STACK: usize = 64;
// Below this many primitives a subtree is built on the calling thread: spawning costs more.
const PAR_MIN: usize = 4096;
// Parallel split levels: 2 levels give 4 subtrees, enough to balance 2 cores across the
// uneven SAH splits near the root.
const PAR_LEVELS: u32 = 2;
/// Children per traversal node.
pub const WIDTH: usize = 4;

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

/// An inner node in traversal layout: up to four children's boxes, axis by axis, so that one
/// visit tests all of them with the same instructions on four lanes; 128 bytes, two cache
/// lines (with u32 counts it took three).
#[derive(Debug, Clone, Copy, Default)]
#[repr(C, align(64))]
pub struct Wide {
    /// Minimum corners per axis and child (rounded down to f32).
    pub min: [[f32; WIDTH]; 3],
    /// Maximum corners per axis and child (rounded up to f32).
    pub max: [[f32; WIDTH]; 3],
    /// Per child: its wide index (inner) or its first primitive slot (leaf).
    pub first: [u32; WIDTH],
    /// Per child: number of primitives (0 for an inner child; at most [`LEAF_HARD_MAX`]).
    pub count: [u16; WIDTH],
    /// Number of children in use (2 ..= 4; the first `len` lanes).
    pub len: u32,
}

/// A BVH over primitive bounds.
#[derive(Debug, Clone, Default)]
pub struct Bvh {
    /// Build-tree nodes, root first.
    pub nodes: Vec<Node>,
    /// Primitive indices in leaf order: the traversal callbacks receive a slot `s` of this
    /// array, the primitive is `order[s]`.
    pub order: Vec<u32>,
    /// Inner nodes in 4-wide traversal layout, root first (empty when the root is a leaf).
    pub wide: Vec<Wide>,
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
        let mut items: Vec<Item> = bounds
            .iter()
            .enumerate()
            .map(|(i, b)| Item {
                bounds: *b,
                cen: b.center(),
                id: i as u32,
            })
            .collect();
        let nodes = build_subtree(&mut items, 0, PAR_LEVELS);
        let order = items.iter().map(|it| it.id).collect();
        let wide = widen(&nodes);
        Bvh { nodes, order, wide }
    }

    /// Nearest hit: `leaf(first, count, t_max)` returns the nearest hit below `t_max` among
    /// slots `first .. first + count` (primitives `order[slot]`) as (slot, distance), the
    /// lowest slot on a tie. Returns (slot, distance).
    #[inline]
    pub fn closest(
        &self,
        ray: &Ray,
        t_max: f64,
        mut leaf: impl FnMut(u32, u32, f64) -> Option<(u32, f64)>,
    ) -> Option<(u32, f64)> {
        let mut best: Option<(u32, f64)> = None;
        let mut t_best = t_max;
        self.walk::<true>(
            ray,
            &mut t_best,
            #[inline(always)]
            |first, count, t: &mut f64| {
                if let Some((s, th)) = leaf(first, count, *t) {
                    best = Some((s, th));
                    *t = th;
                }
            },
        );
        best
    }

    /// True if any primitive is hit below `t_max` (shadow rays): `leaf(first, count, t_max)`
    /// says whether one of slots `first .. first + count` is.
    #[inline]
    pub fn any(&self, ray: &Ray, t_max: f64, mut leaf: impl FnMut(u32, u32, f64) -> bool) -> bool {
        let mut t = t_max;
        let mut found = false;
        self.walk::<false>(
            ray,
            &mut t,
            #[inline(always)]
            |first, count, tm: &mut f64| {
                if leaf(first, count, *tm) {
                    found = true;
                    // Every pending node is entered at t ≥ 0 > −1: the traversal ends here.
                    *tm = -1.0;
                }
            },
        );
        found
    }

    #[inline(always)]
    fn walk<const NEAREST: bool>(
        &self,
        ray: &Ray,
        t_max: &mut f64,
        leaf: impl FnMut(u32, u32, &mut f64),
    ) {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx") {
            // SAFETY: the CPU has AVX (checked just above).
            unsafe { self.walk_avx::<NEAREST>(ray, t_max, leaf) };
            return;
        }
        self.walk_with::<NEAREST>(ray, t_max, leaf, slab4);
    }

    /// [`Bvh::walk`] compiled for AVX, the four slab tests of a node on 256-bit lanes.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx")]
    fn walk_avx<const NEAREST: bool>(
        &self,
        ray: &Ray,
        t_max: &mut f64,
        leaf: impl FnMut(u32, u32, &mut f64),
    ) {
        // SAFETY: this function only runs where AVX is present.
        self.walk_with::<NEAREST>(ray, t_max, leaf, |n, r, t| unsafe { slab4_avx(n, r, t) });
    }

    #[inline(always)]
    fn walk_with<const NEAREST: bool>(
        &self,
        ray: &Ray,
        t_max: &mut f64,
        mut leaf: impl FnMut(u32, u32, &mut f64),
        slab: impl Fn(&Wide, &Ray, f64) -> (u32, [f64; WIDTH]),
    ) {
        let Some(root) = self.nodes.first() else {
            return;
        };
        if root.bounds.hit(ray, *t_max).is_none() {
            return;
        }
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
                let n = &self.wide[cur.first as usize];
                let (met, t) = slab(n, ray, *t_max);
                // The children met, nearest first (stable: ties keep the child order), as
                // child indices: sorting 16-byte entries built field by field and reloading
                // them whole stalled on store forwarding (a tenth of the traversal's samples).
                let mut near = [0usize; WIDTH];
                let mut m = 0;
                for (i, &ti) in t.iter().enumerate() {
                    if met & (1 << i) == 0 {
                        continue;
                    }
                    let mut j = m;
                    while NEAREST && j > 0 && t[near[j - 1]] > ti {
                        near[j] = near[j - 1];
                        j -= 1;
                    }
                    near[j] = i;
                    m += 1;
                }
                let child = |i: usize| Entry {
                    first: n.first[i],
                    count: n.count[i] as u32,
                    t: t[i],
                };
                if m > 0 {
                    // Descend into the nearest child, keep the others for later, the farthest
                    // deepest in the stack.
                    for &i in near[1..m].iter().rev() {
                        if sp < STACK && spill.is_empty() {
                            stack[sp] = child(i);
                            sp += 1;
                        } else {
                            spill.push(child(i));
                        }
                    }
                    cur = child(near[0]);
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

/// Slab test of the first `n.len` children of a wide node: bit i of the mask is set if the ray
/// meets child i's f32 box within (0, t_max), at entry distance t[i]. The arithmetic is f64,
/// so the outward-rounded box is only ever larger than the exact one.
#[inline(always)]
fn slab4(n: &Wide, ray: &Ray, t_max: f64) -> (u32, [f64; WIDTH]) {
    let mut t0 = [0.0f64; WIDTH];
    let mut t1 = [t_max; WIDTH];
    for a in 0..3 {
        let (o, inv) = (ray.origin[a], ray.inv_dir[a]);
        for i in 0..WIDTH {
            let ta = (n.min[a][i] as f64 - o) * inv;
            let tb = (n.max[a][i] as f64 - o) * inv;
            // A NaN (0·∞: a ray parallel to a slab, starting in its face plane) goes through
            // these ordered comparisons the same way in slab4_avx.
            let (lo, hi) = if ta < tb { (ta, tb) } else { (tb, ta) };
            if lo > t0[i] {
                t0[i] = lo;
            }
            if hi < t1[i] {
                t1[i] = hi;
            }
        }
    }
    let mut met = 0;
    for i in 0..n.len as usize {
        if t0[i] <= t1[i] {
            met |= 1 << i;
        }
    }
    (met, t0)
}

/// [`slab4`] on AVX lanes: the same operations in the same order with the same ordered
/// comparisons, hence the same mask and distances bit for bit (tested).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx")]
#[inline]
unsafe fn slab4_avx(n: &Wide, ray: &Ray, t_max: f64) -> (u32, [f64; WIDTH]) {
    use std::arch::x86_64::*;
    let mut t0 = _mm256_setzero_pd();
    let mut t1 = _mm256_set1_pd(t_max);
    for a in 0..3 {
        let o = _mm256_set1_pd(ray.origin[a]);
        let inv = _mm256_set1_pd(ray.inv_dir[a]);
        // SAFETY: each row is 4 f32 in bounds; unaligned loads need no alignment.
        let (mn, mx) = unsafe {
            (
                _mm256_cvtps_pd(_mm_loadu_ps(n.min[a].as_ptr())),
                _mm256_cvtps_pd(_mm_loadu_ps(n.max[a].as_ptr())),
            )
        };
        let ta = _mm256_mul_pd(_mm256_sub_pd(mn, o), inv);
        let tb = _mm256_mul_pd(_mm256_sub_pd(mx, o), inv);
        // vminpd(a, b) is exactly `a < b ? a : b` and vmaxpd(a, b) `a > b ? a : b`, NaN and
        // signed zeros included, so these are slab4's selections bit for bit, one instruction
        // each instead of a compare and a blend on the node's latency chain:
        // lo = ta < tb ? ta : tb; hi = tb > ta ? tb : ta (= ta < tb ? tb : ta);
        // t0 = lo > t0 ? lo : t0; t1 = hi < t1 ? hi : t1.
        let lo = _mm256_min_pd(ta, tb);
        let hi = _mm256_max_pd(tb, ta);
        t0 = _mm256_max_pd(lo, t0);
        t1 = _mm256_min_pd(hi, t1);
    }
    let met = _mm256_movemask_pd(_mm256_cmp_pd::<_CMP_LE_OQ>(t0, t1)) as u32 & ((1 << n.len) - 1);
    let mut t = [0.0; WIDTH];
    // SAFETY: t holds exactly four f64.
    unsafe { _mm256_storeu_pd(t.as_mut_ptr(), t0) };
    (met, t)
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

/// The 4-wide traversal layout of a build tree: each wide node takes its build node's two
/// children and, while it has fewer than four, replaces the inner child of largest surface
/// area by that child's two children.
fn widen(nodes: &[Node]) -> Vec<Wide> {
    if nodes.first().is_none_or(|r| r.count > 0) {
        return Vec::new();
    }
    let mut out = vec![Wide::default()];
    // (build node, its wide index)
    let mut work = vec![(0usize, 0usize)];
    while let Some((ni, wi)) = work.pop() {
        let f = nodes[ni].first as usize;
        let mut ch = [f, f + 1, 0, 0];
        let mut len = 2;
        while len < WIDTH {
            let widest = (0..len)
                .filter(|&k| nodes[ch[k]].count == 0)
                .max_by(|&a, &b| {
                    nodes[ch[a]]
                        .bounds
                        .area()
                        .total_cmp(&nodes[ch[b]].bounds.area())
                });
            let Some(k) = widest else { break };
            let g = nodes[ch[k]].first as usize;
            ch[k] = g;
            ch[len] = g + 1;
            len += 1;
        }
        let mut w = Wide {
            len: len as u32,
            ..Wide::default()
        };
        for (k, &c) in ch[..len].iter().enumerate() {
            let node = &nodes[c];
            for a in 0..3 {
                w.min[a][k] = f32_down(node.bounds.min[a]);
                w.max[a][k] = f32_up(node.bounds.max[a]);
            }
            if node.count > 0 {
                w.first[k] = node.first;
                // The build keeps leaves at most LEAF_HARD_MAX = u16::MAX.
                w.count[k] = node.count as u16;
            } else {
                w.first[k] = out.len() as u32;
                out.push(Wide::default());
                work.push((c, w.first[k] as usize));
            }
        }
        out[wi] = w;
    }
    out
}

// The build's own min/max: bounds are finite (Scene::new checks), so the NaN handling of
// f64::min/max is not needed, and ±0 ties only ever feed areas and slab tests, where the sign
// of a zero makes no difference. `bin_of` relies on their comparison with a NaN (the value of
// a zero-extent axis): false, so `hi(NaN, b)` and `lo(NaN, b)` are `b`.
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

/// The SAH bins' boxes while primitives are added. Written as `join` into an `[Aabb; BINS]`,
/// the update was compiled to masked stores (store a corner only where it moved), which are
/// slow on AMD cores and stall the next load of the same bin: two thirds of the scene build.
/// Here each bin is two four-lane vectors, minima [x, y, z, ·] and maxima [·, x, y, z], updated
/// with vminpd/vmaxpd and stored whole: the same selections as `lo`/`hi`, bit for bit.
struct BinBoxes {
    min: [[f64; 4]; BINS],
    max: [[f64; 4]; BINS],
}

impl BinBoxes {
    fn new() -> BinBoxes {
        BinBoxes {
            min: [[f64::INFINITY; 4]; BINS],
            max: [[f64::NEG_INFINITY; 4]; BINS],
        }
    }

    /// Bin `b` ∪= `x`.
    #[inline(always)]
    fn grow(&mut self, b: usize, x: &Aabb) {
        #[cfg(all(target_arch = "x86_64", target_feature = "avx"))]
        {
            use std::arch::x86_64::*;
            let p = (x as *const Aabb).cast::<f64>();
            // SAFETY: Aabb is repr(C), six f64: lanes 0..4 and 2..6 are inside it; the build
            // enables AVX (cfg above); the bin rows hold four f64 each.
            unsafe {
                let (lo, hi) = (_mm256_loadu_pd(p), _mm256_loadu_pd(p.add(2)));
                let (m, n) = (self.min[b].as_mut_ptr(), self.max[b].as_mut_ptr());
                // vminpd(a, b) = a < b ? a : b = lo(a, b); vmaxpd likewise hi.
                _mm256_storeu_pd(m, _mm256_min_pd(_mm256_loadu_pd(m), lo));
                _mm256_storeu_pd(n, _mm256_max_pd(_mm256_loadu_pd(n), hi));
            }
        }
        #[cfg(not(all(target_arch = "x86_64", target_feature = "avx")))]
        self.grow_scalar(b, x);
    }

    /// [`BinBoxes::grow`] without vectors.
    #[cfg(any(test, not(all(target_arch = "x86_64", target_feature = "avx"))))]
    fn grow_scalar(&mut self, b: usize, x: &Aabb) {
        for a in 0..3 {
            self.min[b][a] = lo(self.min[b][a], x.min[a]);
            self.max[b][a + 1] = hi(self.max[b][a + 1], x.max[a]);
        }
    }

    fn boxes(&self) -> [Aabb; BINS] {
        std::array::from_fn(|b| Aabb {
            min: [self.min[b][0], self.min[b][1], self.min[b][2]],
            max: [self.max[b][1], self.max[b][2], self.max[b][3]],
        })
    }
}

/// A primitive during the build: its box, centroid and index. The build partitions these
/// themselves, not indices into the boxes, so every pass over a node reads memory in order
/// (through indices, each pass gathered from 2 MB of boxes at random).
#[derive(Debug, Clone, Copy)]
struct Item {
    bounds: Aabb,
    cen: Vec3,
    id: u32,
}

/// Bounds and centroid bounds of `items`.
fn extent(items: &[Item]) -> (Aabb, Aabb) {
    let mut bb = Aabb::EMPTY;
    let mut cb = Aabb::EMPTY;
    for it in items {
        bb = join(&bb, &it.bounds);
        cb = join_point(&cb, it.cen);
    }
    (bb, cb)
}

/// Splits `items` in place by the binned SAH: Some(mid) with `items[..mid]` the left child,
/// or None for a leaf.
fn split(items: &mut [Item], cb: &Aabb, bb: &Aabb) -> Option<usize> {
    let n = items.len();
    if n <= 1 {
        return None;
    }
    let Some((axis, split)) = best_split(items, cb, bb) else {
        // No SAH split (every centroid the same, or a leaf is cheaper): a leaf, unless it
        // would hold more than a wide node's u16 count, then halves in the current order.
        return (n > LEAF_HARD_MAX).then_some(n / 2);
    };
    let (lo, scale) = bin_scale(cb, axis);
    let mut mid = 0;
    for k in 0..n {
        if bin_of(items[k].cen[axis], lo, scale) < split {
            // Until the first item that goes right every item is already in place. Past it
            // mid < k: two distinct items swap through registers (`slice::swap` must allow
            // equal indices and went through a stack copy of the 80 bytes, stalling on it).
            if k != mid {
                let (l, r) = items.split_at_mut(k);
                std::mem::swap(&mut l[mid], &mut r[0]);
            }
            mid += 1;
        }
    }
    (mid != 0 && mid != n).then_some(mid)
}

/// Builds the subtree over `items` (slots `base ..` of the order array) in local layout: root
/// at 0, leaves' `first` already global slots. The top `par` levels split across threads.
fn build_subtree(items: &mut [Item], base: usize, par: u32) -> Vec<Node> {
    if par == 0 || items.len() < PAR_MIN {
        return build_serial(items, base);
    }
    let (bb, cb) = extent(items);
    let Some(mid) = split(items, &cb, &bb) else {
        return vec![Node {
            bounds: bb,
            first: base as u32,
            count: items.len() as u32,
        }];
    };
    let (l, r) = items.split_at_mut(mid);
    let (ln, rn) = rayon::join(
        || build_subtree(l, base, par - 1),
        || build_subtree(r, base + mid, par - 1),
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
fn build_serial(items: &mut [Item], base: usize) -> Vec<Node> {
    let mut nodes = Vec::with_capacity(2 * items.len());
    nodes.push(Node {
        bounds: Aabb::EMPTY,
        first: 0,
        count: 0,
    });
    // Explicit work stack: (node index, start, end) – deep recursion cannot overflow.
    let mut work = vec![(0usize, 0usize, items.len())];
    while let Some((ni, start, end)) = work.pop() {
        let slice = &mut items[start..end];
        let (bb, cb) = extent(slice);
        nodes[ni] = Node {
            bounds: bb,
            first: (base + start) as u32,
            count: (end - start) as u32,
        };
        let Some(mid) = split(slice, &cb, &bb) else {
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

/// Origin and scale (bins per metre) of the SAH bins along `axis` of the centroid bounds.
#[inline]
fn bin_scale(cb: &Aabb, axis: usize) -> (f64, f64) {
    let lo = cb.min[axis];
    (lo, BINS as f64 / (cb.max[axis] - lo))
}

/// SAH bin of a centroid coordinate: one multiplication, not a division per primitive; the
/// split and the partition both bin through here, so they always agree.
#[inline]
fn bin_of(c: f64, lo: f64, scale: f64) -> usize {
    // Clamped to [0, BINS − 1] first (NaN and negatives to 0 by `hi`'s comparison, as `as
    // usize` takes them), so the conversion needs none of a saturating cast's fix-ups (15 % of
    // the build's `perf` samples before): the same bin as `(x as usize).min(BINS − 1)` for
    // every x.
    let x = self::lo(hi((c - lo) * scale, 0.0), (BINS - 1) as f64);
    // SAFETY: x is finite and in [0, BINS − 1] (`hi` maps NaN to 0.0).
    unsafe { x.to_int_unchecked::<u32>() as usize }
}

/// Best (axis, bin split) by the binned SAH, or None when a leaf is cheaper.
fn best_split(items: &[Item], cb: &Aabb, bb: &Aabb) -> Option<(usize, usize)> {
    let n = items.len();
    let leaf_cost = n as f64;
    let parent_area = bb.area().max(1e-300);
    let mut best: Option<(f64, usize, usize)> = None;
    // The three axes binned in one pass: each primitive's box and centroid are read once.
    let scales = [0, 1, 2].map(|a| bin_scale(cb, a));
    let mut bins = [BinBoxes::new(), BinBoxes::new(), BinBoxes::new()];
    let mut counts = [[0usize; BINS]; 3];
    for it in items {
        let (c, x) = (it.cen, &it.bounds);
        for a in 0..3 {
            // An axis of zero or NaN extent bins anywhere (a NaN bin is 0) and is skipped below.
            let b = bin_of(c[a], scales[a].0, scales[a].1);
            bins[a].grow(b, x);
            counts[a][b] += 1;
        }
    }
    #[allow(clippy::needless_range_loop)] // axis indexes three parallel arrays
    for axis in 0..3 {
        let ext = cb.max[axis] - cb.min[axis];
        if ext.is_nan() || ext <= 0.0 {
            continue;
        }
        let bin_box = bins[axis].boxes();
        let bin_n = &counts[axis];
        // Only occupied bins move the sweeps: an empty bin's box is `Aabb::EMPTY`, which `join`
        // leaves unchanged either side, and adds no count, so every split in a run of empty
        // bins costs the same, bit for bit, as the run's first, which the strict `<` below
        // keeps. Sweeping the occupied bins alone picks the same split; most nodes are small
        // and fill a few of the twelve bins, and the sweeps were the build's fixed cost per node.
        let mut occ = [0usize; BINS];
        let mut m = 0;
        for (b, &c) in bin_n.iter().enumerate() {
            if c > 0 {
                occ[m] = b;
                m += 1;
            }
        }
        let occ = &occ[..m];
        // Right-to-left: right_cost[j] = area × count of the occupied bins j.. (positions in
        // `occ`).
        let mut right_cost = [0.0; BINS];
        let mut acc = Aabb::EMPTY;
        let mut cnt = 0;
        for j in (1..m).rev() {
            acc = join(&acc, &bin_box[occ[j]]);
            cnt += bin_n[occ[j]];
            right_cost[j] = acc.area() * cnt as f64;
        }
        // Left to right: the split just after occupied bin i (bin index occ[i] + 1); after the
        // last one nothing would be left on the right.
        let mut acc = Aabb::EMPTY;
        let mut cnt = 0;
        for i in 0..m.saturating_sub(1) {
            acc = join(&acc, &bin_box[occ[i]]);
            cnt += bin_n[occ[i]];
            let cost = TRAVERSAL_COST + (acc.area() * cnt as f64 + right_cost[i + 1]) / parent_area;
            if best.is_none_or(|(c, _, _)| cost < c) {
                best = Some((cost, axis, occ[i] + 1));
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

    /// The stored (f32) boxes must never be smaller than the exact ones: f32_down/f32_up
    /// bracket x and are the tightest f32 that do.
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

    /// Random boxes (some flat, some far, f32-rounded) against rays from random origins, axis-
    /// parallel ones and ones starting on a face plane included: the AVX lanes and the scalar
    /// slab test give the same mask and the same entry distances, bit for bit.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn avx_slab_test_equals_the_scalar_one_bit_for_bit() {
        if !std::arch::is_x86_feature_detected!("avx") {
            return;
        }
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let mut differing = 0;
        for case in 0..20_000 {
            let mut n = Wide {
                len: rng.random_range(2..=WIDTH as u32),
                ..Wide::default()
            };
            for a in 0..3 {
                for i in 0..WIDTH {
                    let c: f64 = rng.random_range(-1.0..1.0);
                    let h: f64 = if rng.random_bool(0.1) {
                        0.0
                    } else {
                        rng.random_range(0.0..0.5)
                    };
                    n.min[a][i] = f32_down(c - h);
                    n.max[a][i] = f32_up(c + h);
                }
            }
            let mut o: [f64; 3] = std::array::from_fn(|_| rng.random_range(-2.0..2.0));
            let mut d: [f64; 3] = std::array::from_fn(|_| rng.random_range(-1.0..1.0));
            if case % 3 == 0 {
                // Parallel to an axis plane, starting on a face of child 0.
                let a = rng.random_range(0..3);
                d[a] = 0.0;
                o[a] = n.min[a][0] as f64;
            }
            if d == [0.0; 3] {
                d = [1.0, 0.0, 0.0];
            }
            let ray = Ray::new(o, d);
            let t_max = if rng.random_bool(0.5) {
                f64::INFINITY
            } else {
                rng.random_range(0.0..3.0)
            };
            let (m0, t0) = slab4(&n, &ray, t_max);
            // SAFETY: AVX checked above.
            let (m1, t1) = unsafe { slab4_avx(&n, &ray, t_max) };
            assert_eq!(m0, m1, "case {case}: masks");
            for i in 0..WIDTH {
                if m0 & (1 << i) != 0 {
                    assert_eq!(t0[i].to_bits(), t1[i].to_bits(), "case {case}, child {i}");
                }
            }
            differing += usize::from(m0 != 0 && m0 != (1 << n.len) - 1);
        }
        // Partly met nodes, not only all-or-nothing.
        assert!(differing > 200, "{differing}");
    }

    /// Coincident boxes leave the SAH without a split: more of them than a wide node's u16
    /// count still build, into leaves of at most LEAF_HARD_MAX, and are all found.
    #[test]
    fn coincident_boxes_beyond_a_u16_leaf_are_halved() {
        let n = LEAF_HARD_MAX + 10;
        let b = Aabb {
            min: [-1.0; 3],
            max: [1.0; 3],
        };
        let bvh = Bvh::build(&vec![b; n]);
        let leaves: Vec<u32> = bvh
            .nodes
            .iter()
            .filter(|x| x.count > 0)
            .map(|x| x.count)
            .collect();
        assert!(leaves.len() >= 2 && leaves.iter().all(|&c| c as usize <= LEAF_HARD_MAX));
        assert_eq!(leaves.iter().map(|&c| c as usize).sum::<usize>(), n);
        let ray = Ray::new([-3.0, 0.1, 0.2], [1.0, 0.0, 0.0]);
        let mut seen = 0usize;
        let got = bvh.closest(&ray, f64::INFINITY, |first, count, tm| {
            seen += count as usize;
            (first..first + count)
                .filter_map(|s| b.hit(&ray, tm).map(|t| (s, t)))
                .min_by(|x, y| x.1.total_cmp(&y.1))
        });
        assert_eq!(got.map(|g| g.1), b.hit(&ray, f64::INFINITY));
        assert!(seen >= 1);
        assert!(bvh.any(&ray, f64::INFINITY, |_, count, _| count > 0));
    }

    /// The bins grown with vectors hold the boxes that `join` gives, bit for bit, signed
    /// zeros included.
    #[test]
    fn bin_boxes_equal_join() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let mut simd = BinBoxes::new();
        let mut scalar = BinBoxes::new();
        let mut want = [Aabb::EMPTY; BINS];
        for k in 0..5000 {
            let pick = |r: &mut ChaCha8Rng| match r.random_range(0..4) {
                0 => 0.0,
                1 => -0.0,
                _ => r.random_range(-1.0..1.0),
            };
            let c: [f64; 3] = std::array::from_fn(|_| pick(&mut rng));
            let h: [f64; 3] = std::array::from_fn(|_| pick(&mut rng).abs());
            let x = Aabb {
                min: std::array::from_fn(|a| c[a] - h[a]),
                max: std::array::from_fn(|a| c[a] + h[a]),
            };
            let b = k % BINS;
            simd.grow(b, &x);
            scalar.grow_scalar(b, &x);
            want[b] = join(&want[b], &x);
        }
        let bits = |bx: &[Aabb; BINS]| -> Vec<u64> {
            bx.iter()
                .flat_map(|x| x.min.iter().chain(&x.max).map(|v| v.to_bits()))
                .collect()
        };
        assert_eq!(bits(&simd.boxes()), bits(&want));
        assert_eq!(bits(&scalar.boxes()), bits(&want));
    }

    /// `bin_of` gives the bin of the saturating cast it replaced for NaN, signed zeros,
    /// negatives, bin edges, infinities and huge values.
    #[test]
    fn bin_of_equals_the_saturating_cast() {
        let cast = |c: f64, lo: f64, scale: f64| (((c - lo) * scale) as usize).min(BINS - 1);
        let mut xs = vec![
            0.0,
            -0.0,
            -1e-300,
            -5.0,
            f64::NAN,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::MAX,
            1e30,
            f64::MIN_POSITIVE,
        ];
        for b in 0..=BINS {
            let e = b as f64;
            xs.extend([e, e - 1e-12, e + 1e-12, next_below(e)]);
        }
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        xs.extend((0..20_000).map(|_| rng.random_range(-2.0..(BINS as f64 + 2.0))));
        for scale in [1.0, 0.5, 3.0, f64::INFINITY, f64::NAN] {
            for &x in &xs {
                assert_eq!(
                    bin_of(x, 0.0, scale),
                    cast(x, 0.0, scale),
                    "x {x}, scale {scale}"
                );
            }
        }
    }

    /// The next f64 below `x` ≥ 0.
    fn next_below(x: f64) -> f64 {
        if x > 0.0 {
            f64::from_bits(x.to_bits() - 1)
        } else {
            -f64::from_bits(1)
        }
    }

    /// The binned SAH as first written: both sweeps over all twelve bins. Also says whether
    /// the chosen split is followed by an empty bin (a run the sparse sweeps skip).
    fn best_split_dense(items: &[Item], cb: &Aabb, bb: &Aabb) -> (Option<(usize, usize)>, bool) {
        let n = items.len();
        let parent_area = bb.area().max(1e-300);
        let mut best: Option<(f64, usize, usize)> = None;
        let mut counts = [[0usize; BINS]; 3];
        #[allow(clippy::needless_range_loop)] // axis indexes the items' coordinates too
        for axis in 0..3 {
            let ext = cb.max[axis] - cb.min[axis];
            if ext.is_nan() || ext <= 0.0 {
                continue;
            }
            let (lo, scale) = bin_scale(cb, axis);
            let mut bin_box = [Aabb::EMPTY; BINS];
            let mut bin_n = [0usize; BINS];
            for it in items {
                let b = (((it.cen[axis] - lo) * scale) as usize).min(BINS - 1);
                bin_box[b] = join(&bin_box[b], &it.bounds);
                bin_n[b] += 1;
            }
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
                let cost =
                    TRAVERSAL_COST + (acc.area() * cnt as f64 + right_cost[split]) / parent_area;
                if best.is_none_or(|(c, _, _)| cost < c) {
                    best = Some((cost, axis, split));
                }
            }
            counts[axis] = bin_n;
        }
        let Some((cost, axis, split)) = best else {
            return (None, false);
        };
        let pick = (cost < n as f64 || n > LEAF_MAX).then_some((axis, split));
        (pick, pick.is_some() && counts[axis][split] == 0)
    }

    /// The sweeps over occupied bins only choose the dense sweeps' split: on sets of 2–400
    /// boxes, clustered (most bins empty) or spread, with coincident centroids, flat boxes and
    /// signed zeros.
    #[test]
    fn sparse_sweeps_choose_the_dense_sweeps_split() {
        let mut rng = ChaCha8Rng::seed_from_u64(12);
        let item = |c: [f64; 3], h: [f64; 3], id: u32| {
            let bounds = Aabb {
                min: std::array::from_fn(|a| c[a] - h[a]),
                max: std::array::from_fn(|a| c[a] + h[a]),
            };
            Item {
                bounds,
                cen: bounds.center(),
                id,
            }
        };
        let (mut splits, mut gaps) = (0, 0);
        for case in 0..4000 {
            let n = if case % 4 == 0 {
                rng.random_range(41..=400)
            } else {
                rng.random_range(2..=40)
            };
            let clusters: Vec<[f64; 3]> = (0..rng.random_range(1..=3))
                .map(|_| std::array::from_fn(|_| rng.random_range(-1.0..1.0)))
                .collect();
            let items: Vec<Item> = (0..n)
                .map(|i| {
                    let k = clusters[rng.random_range(0..clusters.len())];
                    let spread = [1e-6, 1e-3, 0.3][case % 3];
                    let c: [f64; 3] = std::array::from_fn(|a| match rng.random_range(0..8) {
                        0 => 0.0,
                        1 => -0.0,
                        2 => k[a],
                        _ => k[a] + rng.random_range(-spread..spread),
                    });
                    let h: [f64; 3] = std::array::from_fn(|_| match rng.random_range(0..4) {
                        0 => 0.0,
                        _ => rng.random_range(0.0..0.05),
                    });
                    item(c, h, i as u32)
                })
                .collect();
            let (bb, cb) = extent(&items);
            let (want, gap) = best_split_dense(&items, &cb, &bb);
            assert_eq!(best_split(&items, &cb, &bb), want, "case {case}");
            splits += usize::from(want.is_some());
            gaps += usize::from(gap);
        }
        assert!(splits > 1000, "{splits} of 4000 sets split");
        assert!(gaps > 1000, "{gaps} splits before an empty bin");
    }

    /// The portable walk (the path of CPUs without AVX) finds the same nearest hit and any-hit
    /// as brute force over random boxes.
    #[test]
    fn portable_walk_equals_brute_force() {
        let mut rng = ChaCha8Rng::seed_from_u64(8);
        let bounds: Vec<Aabb> = (0..3000)
            .map(|_| {
                let c: [f64; 3] = std::array::from_fn(|_| rng.random_range(-1.0..1.0));
                let h: [f64; 3] = std::array::from_fn(|_| rng.random_range(0.0..0.03));
                Aabb {
                    min: std::array::from_fn(|a| c[a] - h[a]),
                    max: std::array::from_fn(|a| c[a] + h[a]),
                }
            })
            .collect();
        let bvh = Bvh::build(&bounds);
        let mut hits = 0;
        for _ in 0..2000 {
            let o: [f64; 3] = std::array::from_fn(|_| rng.random_range(-1.5..1.5));
            let d: [f64; 3] = std::array::from_fn(|_| rng.random_range(-1.0..1.0));
            let ray = Ray::new(o, d);
            let want = bounds
                .iter()
                .filter_map(|b| b.hit(&ray, f64::INFINITY))
                .min_by(f64::total_cmp);
            let mut t = f64::INFINITY;
            let mut got = None;
            bvh.walk_with::<true>(
                &ray,
                &mut t,
                |first, count, tm| {
                    for s in first..first + count {
                        if let Some(h) = bounds[bvh.order[s as usize] as usize].hit(&ray, *tm) {
                            got = Some(h);
                            *tm = h;
                        }
                    }
                },
                slab4,
            );
            assert_eq!(got, want);
            let cut = rng.random_range(0.0..2.0);
            let mut t = cut;
            let mut any = false;
            bvh.walk_with::<false>(
                &ray,
                &mut t,
                |first, count, tm| {
                    if (first..first + count).any(|s| {
                        bounds[bvh.order[s as usize] as usize]
                            .hit(&ray, *tm)
                            .is_some()
                    }) {
                        any = true;
                        *tm = -1.0;
                    }
                },
                slab4,
            );
            assert_eq!(any, want.is_some_and(|w| w < cut));
            hits += usize::from(want.is_some());
        }
        assert!(hits > 200, "{hits}");
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

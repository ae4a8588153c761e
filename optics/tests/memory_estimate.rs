//! `AsmPsf::memory_bytes` against the bytes the model really allocates: a counting global
//! allocator (this test binary's own) records the peak of live heap bytes while a map is
//! built, the model made and a stack (and its VJP) computed. One test in the file, so no other
//! test's allocations mix into the count.

use faer::Mat;
use nanoeye_optics::{
    ApertureGrid, AsmPsf, Hyperbolic, PhaseProfile, PsfConfig, PsfModel, PsfUsage,
};
use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};

struct Counting;

static LIVE: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);

// SAFETY: every call is forwarded to the system allocator unchanged; only counts are kept.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, l: Layout) -> *mut u8 {
        let p = unsafe { System.alloc(l) };
        if !p.is_null() {
            let now = LIVE.fetch_add(l.size(), Ordering::Relaxed) + l.size();
            PEAK.fetch_max(now, Ordering::Relaxed);
        }
        p
    }
    unsafe fn dealloc(&self, p: *mut u8, l: Layout) {
        unsafe { System.dealloc(p, l) };
        LIVE.fetch_sub(l.size(), Ordering::Relaxed);
    }
    unsafe fn realloc(&self, p: *mut u8, l: Layout, new: usize) -> *mut u8 {
        let q = unsafe { System.realloc(p, l, new) };
        if !q.is_null() {
            if new >= l.size() {
                let now = LIVE.fetch_add(new - l.size(), Ordering::Relaxed) + new - l.size();
                PEAK.fetch_max(now, Ordering::Relaxed);
            } else {
                LIVE.fetch_sub(l.size() - new, Ordering::Relaxed);
            }
        }
        q
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

/// Peak live bytes above those live before, while `f` runs.
fn peak_of(f: impl FnOnce()) -> usize {
    let base = LIVE.load(Ordering::Relaxed);
    PEAK.store(base, Ordering::Relaxed);
    f();
    PEAK.load(Ordering::Relaxed) - base
}

#[test]
fn the_estimate_is_within_a_quarter_of_the_allocated_peak() {
    // 0.5 µm across 1 mm: 2000² aperture samples, which dominate as at the sizes the check
    // refuses; two depths on at most two threads.
    let cfg = PsfConfig::default();
    let grid = ApertureGrid::new(1e-3, 0.5e-6).unwrap();
    let depths = [20e-3, 22e-3];
    let threads = rayon::current_num_threads();
    for usage in [PsfUsage::Once, PsfUsage::Training] {
        let est = AsmPsf::memory_bytes(&cfg, &grid, depths.len(), threads, usage).unwrap() as f64;
        let used = peak_of(|| {
            let map = Hyperbolic::default().phase_map(&grid).unwrap();
            let model = AsmPsf::new(cfg, grid).unwrap();
            let st = model.forward(&map, &depths, None).unwrap();
            if usage == PsfUsage::Training {
                let g: Vec<Mat<f64>> = st
                    .planes
                    .iter()
                    .map(|p| Mat::from_fn(p.nrows(), p.ncols(), |i, j| f64::from(p[(i, j)])))
                    .collect();
                // A second map's stack while the first's samples sit in the memo, then the
                // VJP: what a training step does.
                let mut map2 = map.clone();
                map2.phase_rad[(0, 0)] += 1.0;
                let st2 = model.forward(&map2, &depths, None).unwrap();
                assert_eq!(st2.planes.len(), depths.len());
                let grad = model.vjp(&map2, &depths, &g, None).unwrap();
                assert_eq!(grad.phase_rad.nrows(), grid.n);
            }
        }) as f64;
        let ratio = est / used;
        eprintln!("{usage:?}: estimated {est:.4e} B, allocated at most {used:.4e} B ({ratio:.3})");
        assert!(
            (0.75..=1.25).contains(&ratio),
            "{usage:?}: estimated {est:.3e} B, allocated at most {used:.3e} B (ratio {ratio:.3})"
        );
    }
}

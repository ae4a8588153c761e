//! Layer spectra kept across training steps. A frame's S1 spectra F{α·w·L + iα} depend on
//! its stored layers, the chain's radiometric weight w and S1's grid, not on the lens (η_k
//! multiplies the convolution, after them): a frame a lens in training sees again — in the
//! next step, in another chain of the same process over the same data — skips each layer's
//! packing and forward transforms, in the forward pass and in the PSF adjoint. Only such
//! forwards (with S1's tape) fill the store, with the spectra S1 computed and recorded on
//! the way; every forward reads it.
//!
//! Chains with the same grid and weight share one [`SpectraStore`] while any of them lives;
//! all stores of a process together hold at most [`LAYER_SPECTRA_BYTES`]. A store keeps the
//! frames it got first and evicts nothing: over an epoch that cycles through more frames
//! than fit, least-recently-used eviction would evict each frame before its next use.
//! A frame beyond the budget keeps the spectra S1 recorded on its tape, for the backward of
//! its own step.
//!
//! A store also keeps each frame's layer cover (the tiles S1's tiled path finds its layers
//! reach, and their radiance scales: `LayeredImager::layer_cover`), a few hundred bytes a
//! frame, for every dataset and up to [`LAYER_COVER_BYTES`]: a frame whose spectra are not
//! kept then skips S1's pass over its planes.
//!
//! A dataset whose frames' spectra would not all fit the budget keeps none: keeping the first
//! frames seen would spend the whole budget on a fraction budget/need of the visits — the
//! default job's 240 training frames at 320×200 hold 1,903 covered layers, more than 1 GiB
//! at 0.58 MB each, and the first 1 GiB of them took its peak RSS from 4.2 to 5.8 GB for no
//! time it could measure — while every frame's backward already reads the spectra its
//! forward recorded.

use nanoeye_optics::{LayerCover, LayerSpectra};
use std::collections::HashMap;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, Weak};

/// Most bytes of layer spectra kept in one process, all stores together: about 230 frames at
/// the default job's 320×200 (0.58 MB per covered layer); at the paper's 1280×800, whose S1
/// runs on tiles, the admission counts every tile of a covered layer (16.1 MB), 8 frames of
/// 8 layers. 2 GiB filled by every forward took the default job's
/// peak RSS from 4.2 to 7.4 GB for no gain in its time.
pub const LAYER_SPECTRA_BYTES: usize = 1 << 30;

/// Most bytes of layer covers one store keeps (a paper-size frame's under 1.6 KB: 8 layers of
/// at most 40 tiles; so over 40,000 frames): the tiles each layer reaches and its radiance
/// scale, whose pass over the planes was 8–9 % of the chain's forward at batch 16 on
/// paper-size frames (docs/bench/chain.md).
pub const LAYER_COVER_BYTES: usize = 64 << 20;

/// Bytes reserved by every live store.
static IN_USE: AtomicUsize = AtomicUsize::new(0);

/// The live stores by fingerprint (grid and weight), so that chains over the same data share.
static STORES: Mutex<Vec<(u64, Weak<SpectraStore>)>> = Mutex::new(Vec::new());

/// Layer spectra of frames keyed by (dataset, frame id), for chains of one fingerprint.
#[derive(Default)]
pub(crate) struct SpectraStore {
    frames: Mutex<HashMap<(u64, u64), Arc<LayerSpectra>>>,
    /// Whether a dataset's frames' spectra all fit the budget, by source hash (decided once).
    admitted: Mutex<HashMap<u64, bool>>,
    /// Bytes this store holds or has reserved (released when it is dropped).
    bytes: AtomicUsize,
    /// Frames' layer covers and their bytes (see [`LAYER_COVER_BYTES`]).
    covers: Mutex<Covers>,
}

/// Layer covers of frames keyed by (dataset, frame id), and the bytes they hold.
#[derive(Default)]
struct Covers {
    frames: HashMap<(u64, u64), Arc<LayerCover>>,
    bytes: usize,
}

impl SpectraStore {
    /// The live store of chains with fingerprint `fp`, or a new one.
    pub(crate) fn shared(fp: u64) -> Arc<SpectraStore> {
        let mut stores = STORES.lock().unwrap_or_else(|e| e.into_inner());
        stores.retain(|(_, s)| s.strong_count() > 0);
        if let Some(s) = stores
            .iter()
            .filter(|(f, _)| *f == fp)
            .find_map(|(_, s)| s.upgrade())
        {
            return s;
        }
        let s = Arc::new(SpectraStore::default());
        stores.push((fp, Arc::downgrade(&s)));
        s
    }

    /// The kept spectra of frame `key`.
    pub(crate) fn get(&self, key: (u64, u64)) -> Option<Arc<LayerSpectra>> {
        self.frames.lock().ok().and_then(|m| m.get(&key).cloned())
    }

    /// Admits the dataset `source` when the spectra of all its frames, `need()` bytes, fit
    /// the process's budget; its frames are then kept as they come (see the module's doc).
    /// Decided the first time a source is seen: `need` is not evaluated again.
    pub(crate) fn admit(&self, source: u64, need: impl FnOnce() -> usize) {
        let mut a = self.admitted.lock().unwrap_or_else(|e| e.into_inner());
        a.entry(source)
            .or_insert_with(|| need() <= LAYER_SPECTRA_BYTES);
    }

    /// Keeps the spectra `take` gives (`bytes` of them: `S1Tape::spectra_bytes`) for frame
    /// `key` (dataset, frame) when its dataset was admitted and while the process's budget
    /// has room. False, `take` not called, otherwise or when the frame is kept already (by
    /// another thread meanwhile: the same bits).
    pub(crate) fn keep(
        &self,
        key: (u64, u64),
        bytes: usize,
        take: impl FnOnce() -> Option<LayerSpectra>,
    ) -> bool {
        let admitted = self
            .admitted
            .lock()
            .is_ok_and(|a| a.get(&key.0) == Some(&true));
        let mut frames = self.frames.lock().unwrap_or_else(|e| e.into_inner());
        if !admitted || frames.contains_key(&key) || !self.reserve(bytes) {
            return false;
        }
        let Some(s) = take() else {
            self.release(bytes);
            return false;
        };
        debug_assert_eq!(s.bytes(), bytes, "the budget counts what is kept");
        frames.insert(key, Arc::new(s));
        true
    }

    /// Reserves `bytes` of the process's budget; false (nothing reserved) when they do not
    /// fit.
    fn reserve(&self, bytes: usize) -> bool {
        let ok = IN_USE
            .fetch_update(Ordering::AcqRel, Ordering::Acquire, |u| {
                u.checked_add(bytes).filter(|&t| t <= LAYER_SPECTRA_BYTES)
            })
            .is_ok();
        if ok {
            self.bytes.fetch_add(bytes, Ordering::AcqRel);
        }
        ok
    }

    /// Gives back `bytes` of a reservation.
    fn release(&self, bytes: usize) {
        self.bytes.fetch_sub(bytes, Ordering::AcqRel);
        IN_USE.fetch_sub(bytes, Ordering::AcqRel);
    }

    /// The kept layer cover of frame `key`.
    pub(crate) fn cover(&self, key: (u64, u64)) -> Option<Arc<LayerCover>> {
        self.covers
            .lock()
            .ok()
            .and_then(|c| c.frames.get(&key).cloned())
    }

    /// Keeps frame `key`'s layer cover while [`LAYER_COVER_BYTES`] has room (every admitted
    /// dataset or not: a cover is small).
    pub(crate) fn keep_cover(&self, key: (u64, u64), cover: Arc<LayerCover>) {
        let mut c = self.covers.lock().unwrap_or_else(|e| e.into_inner());
        let bytes = cover.bytes();
        if c.bytes + bytes <= LAYER_COVER_BYTES && !c.frames.contains_key(&key) {
            c.frames.insert(key, cover);
            c.bytes += bytes;
        }
    }

    /// Frames kept.
    pub(crate) fn len(&self) -> usize {
        self.frames.lock().map(|m| m.len()).unwrap_or(0)
    }
}

impl Drop for SpectraStore {
    fn drop(&mut self) {
        IN_USE.fetch_sub(*self.bytes.get_mut(), Ordering::AcqRel);
    }
}

/// Bytes held by every live store of the process.
pub fn layer_spectra_bytes() -> usize {
    IN_USE.load(Ordering::Acquire)
}

#[cfg(test)]
mod tests {
    use super::*;
    use faer::Mat;
    use nanoeye_optics::{LayeredImager, SpectralLayer};

    /// One covered layer's spectra on a small grid, and their bytes.
    fn spectra() -> (LayerSpectra, usize) {
        let im = LayeredImager::new(6, 5, 3).unwrap();
        let (l, a) = (
            Mat::from_fn(6, 5, |i, j| (i + j) as f32),
            Mat::full(6, 5, 1.0f32),
        );
        let s = im
            .layer_spectra(&[SpectralLayer::new(l.as_ref(), a.as_ref(), 0)])
            .unwrap();
        let b = s.bytes();
        (s, b)
    }

    /// A frame's layer cover is kept for any dataset, admitted or not; the first kept for a
    /// frame stays; the store stops keeping at its byte limit and counts what it holds.
    #[test]
    fn layer_covers_are_kept_first_come_within_their_limit() {
        let im = LayeredImager::with_tiles(40, 44, 5, Some(12)).unwrap();
        let (l, a) = (
            Mat::from_fn(40, 44, |i, j| (i + j) as f32),
            Mat::full(40, 44, 1.0f32),
        );
        let half = Mat::from_fn(40, 44, |i, _| if i < 20 { 1.0f32 } else { 0.0 });
        let cover = |a: &Mat<f32>| {
            let layer = [SpectralLayer::new(l.as_ref(), a.as_ref(), 0)];
            Arc::new(im.layer_cover(&layer).unwrap().expect("tiled"))
        };
        let (whole, top) = (cover(&a), cover(&half));
        assert_ne!(whole, top);
        let store = SpectraStore::default();
        assert!(store.cover((1, 0)).is_none());
        store.keep_cover((1, 0), whole.clone());
        store.keep_cover((1, 0), top.clone());
        assert_eq!(store.cover((1, 0)).as_deref(), Some(&*whole));
        store.keep_cover((2, 5), top.clone());
        assert_eq!(store.cover((2, 5)).as_deref(), Some(&*top));
        let held = store.covers.lock().unwrap().bytes;
        assert_eq!(held, whole.bytes() + top.bytes());
        // At the limit: counted as full, nothing more is kept.
        store.covers.lock().unwrap().bytes = LAYER_COVER_BYTES - top.bytes() + 1;
        store.keep_cover((3, 1), top.clone());
        assert!(store.cover((3, 1)).is_none());
    }

    #[test]
    fn a_dataset_whose_spectra_do_not_all_fit_keeps_none_one_that_fits_keeps_them() {
        let store = SpectraStore::default();
        let (s, bytes) = spectra();
        assert!(bytes > 0);
        // Not admitted: nothing reserved, `take` never called.
        store.admit(1, || LAYER_SPECTRA_BYTES + 1);
        assert!(!store.keep((1, 0), bytes, || panic!("taken")));
        assert!(!store.keep((3, 0), bytes, || panic!("never admitted")));
        assert_eq!(store.len(), 0);
        assert_eq!(store.bytes.load(Ordering::Acquire), 0);
        store.admit(2, || LAYER_SPECTRA_BYTES);
        // Decided once per dataset: later loads do not sum its records again.
        store.admit(2, || panic!("decided already"));
        assert!(store.keep((2, 0), bytes, || Some(s)));
        assert!(store.get((2, 0)).is_some() && store.get((1, 0)).is_none());
        assert_eq!(store.bytes.load(Ordering::Acquire), bytes);
        // Kept once: a second copy is not taken and reserves nothing.
        assert!(!store.keep((2, 0), bytes, || panic!("kept already")));
        assert_eq!(store.bytes.load(Ordering::Acquire), bytes);
    }
}

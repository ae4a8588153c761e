//! rustfft's planner for `f32` and `f64`, instantiated in this crate only.
//!
//! rustfft is generic over the float type, so its planner and every algorithm the planner can
//! choose (AVX, SSE and scalar butterflies, mixed radix, Rader, Bluestein) are compiled in
//! whichever crate first names `FftPlanner<f32>` or `FftPlanner<f64>`, at that crate's
//! optimisation level. In the optics crate that was 0.78 M of its 1.0 M lines of LLVM IR, compiled
//! twice per test build (the library and its unit tests) at the dev profile's `opt-level` 1.
//! Here the two precisions' plans are built by non-generic functions, so they are compiled once,
//! at `opt-level` 3 (the workspace's `[profile.dev.package.nanoeye-fft]`), and the crates that
//! plan transforms call them and the plans' trait objects; what they still compile of it is
//! `Planner`'s thin methods and the planner's drop glue.

use std::sync::Arc;

pub use rustfft::num_complex;
pub use rustfft::{Fft, FftDirection, FftNum};

/// A cache of FFT plans in one precision: rustfft's planner, which picks AVX, SSE or scalar code
/// at run time and reuses a plan for a length it has planned. Transforms are unnormalized.
pub struct Planner<T: Float>(rustfft::FftPlanner<T>);

/// The precisions this crate plans: `f32` and `f64`.
pub trait Float: FftNum + sealed::Sealed {
    /// A new planner (rustfft's `FftPlanner::new`), built in this crate.
    #[doc(hidden)]
    fn new_planner() -> rustfft::FftPlanner<Self>;
    /// A plan of `len` points in `direction` from `planner`, built in this crate.
    #[doc(hidden)]
    fn plan(
        planner: &mut rustfft::FftPlanner<Self>,
        len: usize,
        direction: FftDirection,
    ) -> Arc<dyn Fft<Self>>;
}

mod sealed {
    pub trait Sealed {}
    impl Sealed for f32 {}
    impl Sealed for f64 {}
}

macro_rules! float {
    ($t:ty) => {
        impl Float for $t {
            // Never inlined: the point is that the generic code behind them is compiled here.
            #[inline(never)]
            fn new_planner() -> rustfft::FftPlanner<$t> {
                rustfft::FftPlanner::new()
            }

            #[inline(never)]
            fn plan(
                planner: &mut rustfft::FftPlanner<$t>,
                len: usize,
                direction: FftDirection,
            ) -> Arc<dyn Fft<$t>> {
                planner.plan_fft(len, direction)
            }
        }
    };
}
float!(f32);
float!(f64);

impl<T: Float> Planner<T> {
    /// An empty cache.
    pub fn new() -> Self {
        Self(T::new_planner())
    }

    /// The forward transform of `len` points, X_k = Σ_n x_n e^(−2πi kn/len).
    pub fn plan_fft_forward(&mut self, len: usize) -> Arc<dyn Fft<T>> {
        T::plan(&mut self.0, len, FftDirection::Forward)
    }

    /// The inverse transform of `len` points, x_n = Σ_k X_k e^(+2πi kn/len) (not divided by len).
    pub fn plan_fft_inverse(&mut self, len: usize) -> Arc<dyn Fft<T>> {
        T::plan(&mut self.0, len, FftDirection::Inverse)
    }
}

impl<T: Float> Default for Planner<T> {
    fn default() -> Self {
        Self::new()
    }
}

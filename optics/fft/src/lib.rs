//! rustfft's planner for `f32` and `f64`, instantiated in this crate only.
//!
//! rustfft is generic over the float type, so its planner and every algorithm the planner can
//! choose (AVX, SSE and scalar butterflies, mixed radix, Rader, Bluestein) are compiled in
//! whichever crate first names `FftPlanner<f32>` or `FftPlanner<f64>`, at that crate's
//! optimisation level. In the optics crate that was 0.78 M of its 1.0 M lines of LLVM IR, compiled
//! twice per test build (the library and its unit tests) at the dev profile's `opt-level` 1.
//! Here the two precisions' plans are built by non-generic functions, so they are compiled once,
//! at `opt-level` 3 (the workspace's `[profile.dev.package.nanoeye-fft]`), and the crates that
//! plan transforms only call them and the plans' trait objects.

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

#[cfg(test)]
mod tests {
    use super::*;
    use num_complex::Complex;

    /// A complex exponential of frequency k0 transforms to len at bin k0 and 0 elsewhere, and the
    /// inverse of the transform is len times the input: lengths that take rustfft's radix,
    /// mixed-radix, Rader (97) and Bluestein (2 × 211 + 1 = 423 = 9 × 47) paths.
    fn delta_and_round_trip<T: Float + Into<f64>>(tol: f64) {
        let mut planner = Planner::<T>::new();
        for len in [1usize, 7, 97, 160, 360, 423, 1024] {
            let k0 = 5 % len;
            let (fwd, inv) = (planner.plan_fft_forward(len), planner.plan_fft_inverse(len));
            assert_eq!((fwd.len(), inv.len()), (len, len));
            assert_eq!(fwd.fft_direction(), FftDirection::Forward);
            assert_eq!(inv.fft_direction(), FftDirection::Inverse);
            let x: Vec<Complex<T>> = (0..len)
                .map(|n| {
                    let a = std::f64::consts::TAU * (k0 * n) as f64 / len as f64;
                    Complex::new(T::from_f64(a.cos()).unwrap(), T::from_f64(a.sin()).unwrap())
                })
                .collect();
            let mut y = x.clone();
            fwd.process(&mut y);
            for (k, v) in y.iter().enumerate() {
                let want = if k == k0 { len as f64 } else { 0.0 };
                let (re, im): (f64, f64) = (v.re.into(), v.im.into());
                assert!(
                    (re - want).abs() < tol * len as f64 && im.abs() < tol * len as f64,
                    "len {len} bin {k}: {re} + {im}i, want {want}"
                );
            }
            inv.process(&mut y);
            for (a, b) in x.iter().zip(&y) {
                let (ar, ai): (f64, f64) = (a.re.into(), a.im.into());
                let (br, bi): (f64, f64) = (b.re.into(), b.im.into());
                assert!((br - len as f64 * ar).abs() < tol * len as f64);
                assert!((bi - len as f64 * ai).abs() < tol * len as f64);
            }
        }
    }

    #[test]
    fn f64_plans_give_the_dft_and_its_inverse() {
        delta_and_round_trip::<f64>(1e-12);
    }

    #[test]
    fn f32_plans_give_the_dft_and_its_inverse() {
        delta_and_round_trip::<f32>(2e-5);
    }

    #[test]
    fn a_length_planned_twice_is_the_same_plan() {
        let mut planner = Planner::<f32>::new();
        let (a, b) = (planner.plan_fft_forward(360), planner.plan_fft_forward(360));
        assert!(Arc::ptr_eq(&a, &b));
    }
}

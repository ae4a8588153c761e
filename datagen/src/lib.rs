//! Synthetic data: eye/slippage state sampling (C.2–C.4, D.4) and the eye-region renderer.

pub mod render;
pub mod states;

pub use states::{State, TruncNormal};

//! Nanopillar library: materials, RCWA unit-cell solver, the (height, pitch, diameter) design
//! sweep of Sec. D.1, candidate selection, phase→diameter inversion and the GDSII fabrication
//! blueprint. Main trait: `PillarLibrary`.

pub mod error;
pub mod library;

pub use error::MetalibError;
pub use library::{PillarLibrary, TabulatedLibrary};
pub mod cody_lorentz;
pub mod dispersion;
pub mod material;
pub mod rcwa;

pub use material::Materials;
pub use rcwa::{CellResult, CellSpec, LayerModes, Rule};
pub mod blueprint;
pub mod plot;
pub mod select;
pub mod study;
pub mod sweep;

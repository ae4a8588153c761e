//! Metasurface optics: phase profiles (hyperbolic, double-helix, free-form, pillar-quantized),
//! band-limited angular-spectrum propagation, depth-dependent PSF stacks with their VJP, and
//! occlusion-aware layered image formation (S1). Main traits: `PhaseProfile`, `PsfModel`.

mod czt;
pub mod error;
pub mod grid;
pub mod io;
pub mod layered;
pub mod profile;
pub mod psf;
pub mod stats;

pub use error::{OpticsError, Result};
pub use grid::ApertureGrid;
pub use layered::{
    GradValue, KernelGradAccumulator, KernelSpectra, Layer, LayerCover, LayerGrads, LayerSpectra,
    LayeredImager, S1Tape, SpectralLayer,
};
pub use profile::{DoubleHelix, FreeForm, Hyperbolic, PhaseMap, PhaseProfile, PillarQuantized};
pub use psf::{AsmPsf, PhaseMapGrad, PsfConfig, PsfModel, PsfStack, PsfUsage};

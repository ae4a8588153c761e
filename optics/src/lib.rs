//! Metasurface optics: phase profiles (hyperbolic, double-helix, free-form, pillar-quantized),
//! band-limited angular-spectrum propagation, depth-dependent PSF stacks with their VJP, and
//! occlusion-aware layered image formation (S1). Main traits: `PhaseProfile`, `PsfModel`.

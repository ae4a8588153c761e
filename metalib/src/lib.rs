//! Nanopillar library: materials, RCWA unit-cell solver, the (height, pitch, diameter) design
//! sweep of Sec. D.1, candidate selection, phase→diameter inversion and the GDSII fabrication
//! blueprint. Main trait: `PillarLibrary`.

//! Sensor model (S2, S24): box integration with a learnable effective pitch p̂, downsampling,
//! κ = (p̂/p_base)², shot and read noise, full-well clipping and ADC. Main trait: `Sensor`.

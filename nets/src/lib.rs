//! Networks: layers with explicit backward passes, the elastic MobileNetV3 supernet, perception
//! (pupil mask) and calibration (slippage) heads, and the MAC/parameter cost model (S23).
//! Main trait: `Supernet`.

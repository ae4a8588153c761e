//! Fisher-information design losses: CRLB (S3), distinctness (S4), compactness (S5),
//! auto-balancing (S6), optical embedding (S15), per-depth Fisher information (S25) and the
//! initialization loop of Sec. A.2. Main trait: `DesignLoss`.

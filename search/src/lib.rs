//! Co-design search: sandwich-rule supernet training (S22), the inner loop (S16, S18) and the
//! regularized evolutionary algorithm (S17, S19–S21) under a MAC budget; Pareto benchmark (B.6).

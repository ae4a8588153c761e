//! Row-major GEMM helpers for the small dense products of a batch (the elastic-kernel
//! transforms of all channels): one sequential faer GEMM each instead of per-channel scalar loops.

use faer::linalg::matmul::matmul;
use faer::{Accum, MatMut, MatRef, Par};

/// A row-major `rows × cols` view of `s` (`s.len() == rows·cols`).
pub(crate) fn rm(s: &[f32], rows: usize, cols: usize) -> MatRef<'_, f32> {
    MatRef::from_row_major_slice(s, rows, cols)
}

/// dst (`rows × cols`, row-major) = a·b (`Accum::Replace`) or dst + a·b (`Accum::Add`).
pub(crate) fn gemm(
    dst: &mut [f32],
    rows: usize,
    cols: usize,
    accum: Accum,
    a: MatRef<'_, f32>,
    b: MatRef<'_, f32>,
) {
    let dm = MatMut::from_row_major_slice_mut(dst, rows, cols);
    matmul(dm, accum, a, b, 1.0f32, Par::Seq);
}

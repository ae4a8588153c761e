//! The PSF stack the losses read: planes over depth on one pixel grid, in f64.

use crate::error::{FisherError, check_positive};
use faer::Mat;

/// PSF planes (intensity per pixel, ≥ 0) at strictly increasing depths (m), pixel pitch (m).
#[derive(Clone, Debug)]
pub struct PsfStack {
    rows: usize,
    cols: usize,
    pitch: f64,
    depths: Vec<f64>,
    /// Column-major plane buffers, index c·rows + r.
    planes: Vec<Vec<f64>>,
}

/// Gradient of a loss w.r.t. each plane of a [`PsfStack`] (same shapes).
#[derive(Clone, Debug)]
pub struct StackGrad {
    /// ∂L/∂PSF per plane.
    pub planes: Vec<Mat<f64>>,
}

impl StackGrad {
    /// The gradient planes in f32 (for the optics VJP).
    pub fn to_f32(&self) -> Vec<Mat<f32>> {
        self.planes
            .iter()
            .map(|m| Mat::from_fn(m.nrows(), m.ncols(), |i, j| m[(i, j)] as f32))
            .collect()
    }
}

impl PsfStack {
    /// Builds a stack from f32 planes; validates shapes, depths and values.
    pub fn from_f32(
        planes: &[Mat<f32>],
        depths: &[f64],
        pitch: f64,
    ) -> Result<PsfStack, FisherError> {
        let (shape, bufs) = column_buffers(planes, f64::from)?;
        PsfStack::from_buffers(shape.0, shape.1, bufs, depths, pitch)
    }

    /// Builds a stack from f64 planes.
    pub fn from_f64(
        planes: &[Mat<f64>],
        depths: &[f64],
        pitch: f64,
    ) -> Result<PsfStack, FisherError> {
        let (shape, bufs) = column_buffers(planes, |x| x)?;
        PsfStack::from_buffers(shape.0, shape.1, bufs, depths, pitch)
    }

    /// Builds a stack from column-major buffers (index c·rows + r).
    pub fn from_buffers(
        rows: usize,
        cols: usize,
        planes: Vec<Vec<f64>>,
        depths: &[f64],
        pitch: f64,
    ) -> Result<PsfStack, FisherError> {
        check_positive("pitch", pitch)?;
        if planes.is_empty() || rows == 0 || cols == 0 {
            return Err(FisherError::Shape {
                name: "planes",
                why: "the stack is empty".into(),
            });
        }
        if planes.len() != depths.len() {
            return Err(FisherError::Shape {
                name: "depths",
                why: format!("{} planes but {} depths", planes.len(), depths.len()),
            });
        }
        for w in depths.windows(2) {
            if w[1] <= w[0] || !w[0].is_finite() || !w[1].is_finite() {
                return Err(FisherError::InvalidParameter {
                    name: "depths",
                    value: w[1],
                    why: "depths must be finite and strictly increasing",
                });
            }
        }
        for (k, p) in planes.iter().enumerate() {
            if p.len() != rows * cols {
                return Err(FisherError::Shape {
                    name: "planes",
                    why: format!("plane {k} has {} values, expected {}", p.len(), rows * cols),
                });
            }
            if let Some(i) = p.iter().position(|v| !v.is_finite() || *v < 0.0) {
                return Err(FisherError::InvalidPlane {
                    plane: k,
                    row: i % rows,
                    col: i / rows,
                });
            }
        }
        Ok(PsfStack {
            rows,
            cols,
            pitch,
            depths: depths.to_vec(),
            planes,
        })
    }

    /// Rows per plane.
    pub fn rows(&self) -> usize {
        self.rows
    }
    /// Columns per plane.
    pub fn cols(&self) -> usize {
        self.cols
    }
    /// Pixel pitch, metres.
    pub fn pitch(&self) -> f64 {
        self.pitch
    }
    /// Depths, metres.
    pub fn depths(&self) -> &[f64] {
        &self.depths
    }
    /// Number of planes.
    pub fn len(&self) -> usize {
        self.planes.len()
    }
    /// True when the stack has no plane (never, by construction).
    pub fn is_empty(&self) -> bool {
        self.planes.is_empty()
    }
    /// Column-major buffer of plane `k`.
    pub fn plane(&self, k: usize) -> &[f64] {
        &self.planes[k]
    }
    /// Mutable column-major buffer of plane `k` (values must stay ≥ 0 and finite).
    pub fn plane_mut(&mut self, k: usize) -> &mut [f64] {
        &mut self.planes[k]
    }

    /// Central (interior) or one-sided (end) depth difference: (lower, upper, 1/Δz).
    pub(crate) fn dz_stencil(&self, k: usize) -> Option<(usize, usize, f64)> {
        let n = self.planes.len();
        if n < 2 {
            return None;
        }
        let lo = k.saturating_sub(1);
        let hi = (k + 1).min(n - 1);
        Some((lo, hi, 1.0 / (self.depths[hi] - self.depths[lo])))
    }

    pub(crate) fn grad_from_buffers(&self, g: Vec<Vec<f64>>) -> StackGrad {
        StackGrad {
            planes: g
                .into_iter()
                .map(|b| Mat::from_fn(self.rows, self.cols, |i, j| b[j * self.rows + i]))
                .collect(),
        }
    }
}

/// Rows and columns of a plane.
type Shape = (usize, usize);

/// The planes' common shape and each plane's values column after column, converted by `f`;
/// a plane whose shape differs from the first's is refused, naming it.
fn column_buffers<T: Copy>(
    planes: &[Mat<T>],
    f: impl Fn(T) -> f64,
) -> Result<(Shape, Vec<Vec<f64>>), FisherError> {
    let shape = planes
        .first()
        .map(|m| (m.nrows(), m.ncols()))
        .unwrap_or((0, 0));
    let mut bufs = Vec::with_capacity(planes.len());
    for (k, m) in planes.iter().enumerate() {
        if (m.nrows(), m.ncols()) != shape {
            return Err(FisherError::Shape {
                name: "planes",
                why: format!(
                    "plane {k} is {}x{}, plane 0 is {}x{}",
                    m.nrows(),
                    m.ncols(),
                    shape.0,
                    shape.1
                ),
            });
        }
        let mut v = Vec::with_capacity(shape.0 * shape.1);
        for c in 0..m.ncols() {
            v.extend(m.col(c).iter().map(|&x| f(x)));
        }
        bufs.push(v);
    }
    Ok((shape, bufs))
}

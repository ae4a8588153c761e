//! The crate's own dense 4D tensor (N, C, H, W), f32, row-major with W fastest.

use crate::error::{NetsError, Result};
use rayon::prelude::*;

/// A dense f32 tensor of shape (N, C, H, W); dimensionless values (pixels, activations).
#[derive(Clone, Debug, PartialEq)]
pub struct Tensor {
    /// Batch size.
    pub n: usize,
    /// Channels.
    pub c: usize,
    /// Height in pixels.
    pub h: usize,
    /// Width in pixels.
    pub w: usize,
    /// Values, index ((n·C + c)·H + y)·W + x.
    pub data: Vec<f32>,
}

/// `len` zeros; large buffers are written by every thread of the pool, since a reused heap
/// block is zeroed by `calloc` on one thread at memory speed.
pub(crate) fn zeroed(len: usize) -> Vec<f32> {
    const PAR_ZERO: usize = 1 << 16;
    if len < PAR_ZERO {
        return vec![0.0; len];
    }
    let mut v = Vec::with_capacity(len);
    v.par_extend(rayon::iter::repeat_n(0.0f32, len));
    v
}

/// n·c·h·w values, or None where the product overflows `usize` (a wrapped product would give
/// a tensor whose shape claims more values than it holds).
fn shape_len([n, c, h, w]: [usize; 4]) -> Option<usize> {
    [c, h, w].iter().try_fold(n, |a, &b| a.checked_mul(b))
}

impl Tensor {
    /// An all-zero tensor of the given shape; panics when n·c·h·w overflows `usize` (a wrapped
    /// product would give a tensor whose shape claims more values than it holds).
    pub fn zeros(n: usize, c: usize, h: usize, w: usize) -> Self {
        let len = shape_len([n, c, h, w])
            .unwrap_or_else(|| panic!("tensor shape ({n},{c},{h},{w}) overflows usize"));
        Self {
            n,
            c,
            h,
            w,
            data: zeroed(len),
        }
    }

    /// Whether `data` holds exactly n·c·h·w values (the fields are public, so a tensor can be
    /// built or changed that does not).
    pub(crate) fn holds_its_shape(&self) -> bool {
        shape_len(self.shape()) == Some(self.data.len())
    }

    /// Wraps `data`; fails when its length is not n·c·h·w.
    pub fn from_vec(n: usize, c: usize, h: usize, w: usize, data: Vec<f32>) -> Result<Self> {
        // Checked: a wrapped product let a shape of 2⁶³ + 1 rows hold eight values (a review).
        if shape_len([n, c, h, w]) != Some(data.len()) {
            return Err(NetsError::Shape(format!(
                "data of length {} cannot hold ({n},{c},{h},{w})",
                data.len()
            )));
        }
        Ok(Self { n, c, h, w, data })
    }

    /// A tensor of this one's shape holding `data` (the shape is copied, not the values).
    pub fn like(&self, data: Vec<f32>) -> Self {
        debug_assert_eq!(data.len(), self.len());
        Self {
            n: self.n,
            c: self.c,
            h: self.h,
            w: self.w,
            data,
        }
    }

    /// Shape as [N, C, H, W].
    pub fn shape(&self) -> [usize; 4] {
        [self.n, self.c, self.h, self.w]
    }

    /// Number of elements.
    pub fn len(&self) -> usize {
        self.data.len()
    }

    /// True when the tensor holds no element.
    pub fn is_empty(&self) -> bool {
        self.data.is_empty()
    }

    /// Pixels per channel plane (H·W).
    pub fn plane(&self) -> usize {
        self.h * self.w
    }

    /// The values of image `i` (C·H·W contiguous).
    pub fn image(&self, i: usize) -> &[f32] {
        let s = self.c * self.plane();
        &self.data[i * s..(i + 1) * s]
    }

    /// Mutable values of image `i`.
    pub fn image_mut(&mut self, i: usize) -> &mut [f32] {
        let s = self.c * self.plane();
        &mut self.data[i * s..(i + 1) * s]
    }

    /// Fails unless `other` has the same shape (used to validate upstream gradients).
    pub fn check_same(&self, other: &Tensor, what: &str) -> Result<()> {
        if self.shape() != other.shape() {
            return Err(NetsError::Shape(format!(
                "{what}: expected {:?}, got {:?}",
                self.shape(),
                other.shape()
            )));
        }
        Ok(())
    }

    /// Element-wise in-place addition of a same-shaped tensor.
    pub fn add_assign(&mut self, other: &Tensor) {
        for (a, b) in self.data.iter_mut().zip(&other.data) {
            *a += b;
        }
    }
}

/// A learnable parameter: values and their accumulated gradient (same length).
#[derive(Clone, Debug, PartialEq)]
pub struct Param {
    /// Current values.
    pub value: Vec<f32>,
    /// Gradient accumulated by backward passes since the last `zero_grad`.
    pub grad: Vec<f32>,
}

impl Param {
    /// A parameter holding `value` with a zero gradient.
    pub fn new(value: Vec<f32>) -> Self {
        let grad = vec![0.0; value.len()];
        Self { value, grad }
    }

    /// Number of scalars.
    pub fn len(&self) -> usize {
        self.value.len()
    }

    /// True when the parameter holds no scalar.
    pub fn is_empty(&self) -> bool {
        self.value.is_empty()
    }

    /// Sets the gradient to zero.
    pub fn zero_grad(&mut self) {
        self.grad.iter_mut().for_each(|g| *g = 0.0);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A shape whose element count overflows is refused, not wrapped onto a short buffer
    /// ((2⁶³ + 1) × 8 wrapped to 8 and took eight values as 2⁶³ + 1 rows).
    #[test]
    fn a_shape_past_usize_is_refused() {
        assert!(Tensor::from_vec(1, 1, (1usize << 63) + 1, 8, vec![0.0; 8]).is_err());
        assert!(Tensor::from_vec(1 << 32, 1 << 32, 1, 1, vec![]).is_err());
        assert!(Tensor::from_vec(2, 1, 2, 2, vec![0.0; 8]).is_ok());
    }

    /// `zeros` of such a shape panics naming it: 2³² × 2³² wrapped to an empty tensor that
    /// claimed 2⁶⁴ values.
    #[test]
    #[should_panic(expected = "overflows usize")]
    fn zeros_of_a_shape_past_usize_panics() {
        let _ = Tensor::zeros(1 << 32, 1 << 32, 1, 1);
    }
}

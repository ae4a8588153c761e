//! Occlusion-aware layered image formation (S1, after Ikoma et al. 2021):
//! I⁽ᵏ⁾ = (α_k L_k) ∗ P_k + (1 − α_k ∗ P_k) · I⁽ᵏ⁻¹⁾, layers ordered back to front, I⁽⁻¹⁾ = 0,
//! with its VJP w.r.t. radiance, alpha and PSF.
//!
//! Convolution is linear ("same" size, zeros outside the image), by FFT on a grid padded to
//! at least H + W_p − 1. Both real convolutions of a layer share one complex FFT: αL + iα is
//! transformed once and multiplied by the real kernel's spectrum, so the real part carries
//! αL ∗ P and the imaginary part α ∗ P – the same saving a real-to-complex transform gives,
//! without an extra dependency.

use crate::error::{OpticsError, Result};
use crate::psf::fast_fft_size;
use faer::{Mat, c64};
use rustfft::{Fft, FftPlanner};
use std::sync::Arc;

/// One depth layer: radiance L (H×W), alpha α ∈ [0, 1] (H×W) and the PSF of its depth
/// (W_p×W_p, kernel centre at index (W_p/2, W_p/2)).
#[derive(Clone, Copy, Debug)]
pub struct Layer<'a> {
    /// Radiance L_k (any non-negative unit; the image carries the same unit).
    pub radiance: &'a Mat<f32>,
    /// Coverage α_k (dimensionless).
    pub alpha: &'a Mat<f32>,
    /// PSF P_k of the layer's depth (dimensionless energy fractions).
    pub psf: &'a Mat<f32>,
}

/// Gradients of a scalar loss w.r.t. every layer's inputs (zero for skipped layers).
#[derive(Clone, Debug)]
pub struct LayerGrads {
    /// ∂loss/∂L_k.
    pub radiance: Vec<Mat<f64>>,
    /// ∂loss/∂α_k.
    pub alpha: Vec<Mat<f64>>,
    /// ∂loss/∂P_k.
    pub psf: Vec<Mat<f64>>,
}

/// Planned FFTs for images of H×W with PSFs of W_p×W_p; reusable across calls.
pub struct LayeredImager {
    h: usize,
    w: usize,
    wp: usize,
    ny: usize,
    nx: usize,
    fy: Arc<dyn Fft<f64>>,
    fx: Arc<dyn Fft<f64>>,
    iy: Arc<dyn Fft<f64>>,
    ix: Arc<dyn Fft<f64>>,
}

/// Per layer kept for the VJP: the image below it I⁽ᵏ⁻¹⁾ and its occlusion α∗P.
type Saved = Option<(Mat<f64>, Mat<f64>)>;

struct Buffers {
    a: Vec<c64>,
    p: Vec<c64>,
    col: Vec<c64>,
    scratch: Vec<c64>,
}

impl LayeredImager {
    /// Imager for H×W images and W_p×W_p PSFs.
    pub fn new(height: usize, width: usize, psf_px: usize) -> Result<Self> {
        for (name, v) in [("height", height), ("width", width), ("psf_px", psf_px)] {
            if v == 0 || v > 16384 {
                return Err(OpticsError::param(
                    name,
                    format!("must be 1..=16384, got {v}"),
                ));
            }
        }
        let ny = fast_fft_size(height + psf_px - 1);
        let nx = fast_fft_size(width + psf_px - 1);
        let mut pl = FftPlanner::<f64>::new();
        Ok(Self {
            h: height,
            w: width,
            wp: psf_px,
            ny,
            nx,
            fy: pl.plan_fft_forward(ny),
            fx: pl.plan_fft_forward(nx),
            iy: pl.plan_fft_inverse(ny),
            ix: pl.plan_fft_inverse(nx),
        })
    }

    fn buffers(&self) -> Buffers {
        let s = [&self.fy, &self.fx, &self.iy, &self.ix]
            .iter()
            .map(|f| f.get_inplace_scratch_len())
            .max()
            .unwrap_or(0);
        let z = c64::new(0.0, 0.0);
        Buffers {
            a: vec![z; self.ny * self.nx],
            p: vec![z; self.ny * self.nx],
            col: vec![z; self.ny],
            scratch: vec![z; s],
        }
    }

    fn fft2(&self, data: &mut [c64], col: &mut [c64], scratch: &mut [c64], inverse: bool) {
        let (rf, cf) = if inverse {
            (&self.ix, &self.iy)
        } else {
            (&self.fx, &self.fy)
        };
        rf.process_with_scratch(data, scratch);
        for c in 0..self.nx {
            for (r, v) in col.iter_mut().enumerate() {
                *v = data[r * self.nx + c];
            }
            cf.process_with_scratch(col, scratch);
            for (r, v) in col.iter().enumerate() {
                data[r * self.nx + c] = *v;
            }
        }
    }

    fn check(&self, layers: &[Layer]) -> Result<()> {
        for (k, l) in layers.iter().enumerate() {
            let shapes = [
                (
                    l.radiance.nrows(),
                    l.radiance.ncols(),
                    self.h,
                    self.w,
                    "radiance",
                ),
                (l.alpha.nrows(), l.alpha.ncols(), self.h, self.w, "alpha"),
                (l.psf.nrows(), l.psf.ncols(), self.wp, self.wp, "psf"),
            ];
            for (r, c, er, ec, name) in shapes {
                if r != er || c != ec {
                    return Err(OpticsError::Shape(format!(
                        "layer {k}: {name} is {r}×{c}, expected {er}×{ec}"
                    )));
                }
            }
            for m in [l.radiance, l.alpha, l.psf] {
                if m.col_iter().any(|c| c.iter().any(|v| !v.is_finite())) {
                    return Err(OpticsError::param(
                        "layers",
                        format!("layer {k} holds non-finite values"),
                    ));
                }
            }
        }
        Ok(())
    }

    fn empty(l: &Layer) -> bool {
        l.alpha.col_iter().all(|c| c.iter().all(|&v| v == 0.0))
    }

    /// P̂ of a layer into `b.p`.
    fn psf_spectrum(&self, l: &Layer, b: &mut Buffers) {
        b.p.fill(c64::new(0.0, 0.0));
        for r in 0..self.wp {
            for c in 0..self.wp {
                b.p[r * self.nx + c] = c64::new(l.psf[(r, c)] as f64, 0.0);
            }
        }
        self.fft2(&mut b.p, &mut b.col, &mut b.scratch, false);
    }

    /// (αL ∗ P, α ∗ P) of one layer, cropped to H×W, as one complex image in `b.a` (spatial).
    fn convolve(&self, l: &Layer, b: &mut Buffers) {
        self.psf_spectrum(l, b);
        b.a.fill(c64::new(0.0, 0.0));
        for r in 0..self.h {
            for c in 0..self.w {
                let al = l.alpha[(r, c)] as f64;
                b.a[r * self.nx + c] = c64::new(al * l.radiance[(r, c)] as f64, al);
            }
        }
        self.fft2(&mut b.a, &mut b.col, &mut b.scratch, false);
        let norm = 1.0 / (self.ny * self.nx) as f64;
        b.a.iter_mut().zip(&b.p).for_each(|(a, p)| *a *= p * norm);
        self.fft2(&mut b.a, &mut b.col, &mut b.scratch, true);
    }

    fn forward_f64(&self, layers: &[Layer], keep: bool) -> (Mat<f64>, Vec<Saved>) {
        let (cy, cx) = (self.wp / 2, self.wp / 2);
        let mut img = Mat::<f64>::zeros(self.h, self.w);
        let mut saved = Vec::with_capacity(layers.len());
        let mut b = self.buffers();
        for l in layers {
            if Self::empty(l) {
                saved.push(None);
                continue;
            }
            self.convolve(l, &mut b);
            let o = Mat::from_fn(self.h, self.w, |r, c| b.a[(r + cy) * self.nx + c + cx].im);
            if keep {
                saved.push(Some((img.clone(), o.clone())));
            }
            for c in 0..self.w {
                for r in 0..self.h {
                    let conv = b.a[(r + cy) * self.nx + c + cx].re;
                    img[(r, c)] = conv + (1.0 - o[(r, c)]) * img[(r, c)];
                }
            }
        }
        (img, saved)
    }

    /// Sensor-plane intensity I (H×W) of the layers (back to front); layers with α ≡ 0 skipped.
    pub fn forward(&self, layers: &[Layer]) -> Result<Mat<f32>> {
        self.check(layers)?;
        let (img, _) = self.forward_f64(layers, false);
        Ok(Mat::from_fn(self.h, self.w, |r, c| img[(r, c)] as f32))
    }

    /// [`Self::forward`] in f64 (the accumulation precision), for losses and gradient checks.
    pub fn forward_f64_image(&self, layers: &[Layer]) -> Result<Mat<f64>> {
        self.check(layers)?;
        Ok(self.forward_f64(layers, false).0)
    }

    /// Gradients w.r.t. each layer's radiance, alpha and PSF of a loss with ∂loss/∂I = `grad`.
    pub fn vjp(&self, layers: &[Layer], grad: &Mat<f64>) -> Result<LayerGrads> {
        self.check(layers)?;
        if grad.nrows() != self.h || grad.ncols() != self.w {
            return Err(OpticsError::Shape(format!(
                "grad is {}×{}, image is {}×{}",
                grad.nrows(),
                grad.ncols(),
                self.h,
                self.w
            )));
        }
        let (_, saved) = self.forward_f64(layers, true);
        let n = layers.len();
        let mut out = LayerGrads {
            radiance: vec![Mat::zeros(self.h, self.w); n],
            alpha: vec![Mat::zeros(self.h, self.w); n],
            psf: vec![Mat::zeros(self.wp, self.wp); n],
        };
        let (cy, cx) = (self.wp / 2, self.wp / 2);
        let mut gi = grad.clone();
        let mut b = self.buffers();
        let mut g = vec![c64::new(0.0, 0.0); self.ny * self.nx];
        let norm = 1.0 / (self.ny * self.nx) as f64;
        for k in (0..n).rev() {
            let Some((prev, o)) = &saved[k] else { continue };
            let l = &layers[k];
            // g_c = gI (to αL∗P), g_o = −gI·I⁽ᵏ⁻¹⁾ (to α∗P), packed as g_c + i g_o at the
            // output's offset (cy, cx) in the padded grid.
            g.fill(c64::new(0.0, 0.0));
            for r in 0..self.h {
                for c in 0..self.w {
                    g[(r + cy) * self.nx + c + cx] =
                        c64::new(gi[(r, c)], -gi[(r, c)] * prev[(r, c)]);
                }
            }
            for c in 0..self.w {
                for r in 0..self.h {
                    gi[(r, c)] *= 1.0 - o[(r, c)];
                }
            }
            self.fft2(&mut g, &mut b.col, &mut b.scratch, false);
            // Â of the packed input αL + iα.
            b.a.fill(c64::new(0.0, 0.0));
            for r in 0..self.h {
                for c in 0..self.w {
                    let al = l.alpha[(r, c)] as f64;
                    b.a[r * self.nx + c] = c64::new(al * l.radiance[(r, c)] as f64, al);
                }
            }
            self.fft2(&mut b.a, &mut b.col, &mut b.scratch, false);
            // ∂/∂P(u,v) = Re Σ G(t+u) conj(A(t)) → IFFT(Ĝ·conj(Â)).
            b.a.iter_mut()
                .zip(&g)
                .for_each(|(a, gg)| *a = gg * a.conj() * norm);
            self.fft2(&mut b.a, &mut b.col, &mut b.scratch, true);
            for r in 0..self.wp {
                for c in 0..self.wp {
                    out.psf[k][(r, c)] = b.a[r * self.nx + c].re;
                }
            }
            // ∂/∂(αL, α) = Σ G(t+y0) P(t) → IFFT(Ĝ·conj(P̂)), real and imaginary parts.
            self.psf_spectrum(l, &mut b);
            g.iter_mut()
                .zip(&b.p)
                .for_each(|(gg, p)| *gg *= p.conj() * norm);
            self.fft2(&mut g, &mut b.col, &mut b.scratch, true);
            for r in 0..self.h {
                for c in 0..self.w {
                    let v = g[r * self.nx + c];
                    let (al, lr) = (l.alpha[(r, c)] as f64, l.radiance[(r, c)] as f64);
                    out.radiance[k][(r, c)] = v.re * al;
                    out.alpha[k][(r, c)] = v.re * lr + v.im;
                }
            }
        }
        Ok(out)
    }
}

/// Kernel spectra P̂ on a [`LayeredImager`]'s padded grid, computed once and shared by every
/// frame of a batch (a batch's layers at one depth all use the same PSF).
pub struct KernelSpectra {
    spec: Vec<Option<Vec<c64>>>,
}

/// One layer for the spectral path: radiance, alpha and the index of its kernel.
#[derive(Clone, Copy, Debug)]
pub struct SpectralLayer<'a> {
    /// Radiance L_k.
    pub radiance: &'a Mat<f32>,
    /// Coverage α_k.
    pub alpha: &'a Mat<f32>,
    /// Index into the [`KernelSpectra`].
    pub kernel: usize,
}

/// What a spectral forward pass keeps for the PSF VJP: per layer the image below it and its
/// occlusion α∗P, in f32 (the adjoint needs them to round-off precision only).
pub struct S1Tape {
    saved: Vec<Option<(Mat<f32>, Mat<f32>)>>,
    image: Mat<f32>,
}

/// ∂loss/∂P accumulated in the frequency domain over frames: one inverse FFT per kernel at
/// the end instead of one per layer and frame.
pub struct KernelGradAccumulator {
    spec: Vec<Option<Vec<c64>>>,
    /// Σ over layers using kernel j of ⟨∂loss/∂I⁽ᵏ⁾, (α_k L_k) ∗ P_j⟩: the gradient w.r.t. a
    /// scalar factor on the layer's radiance.
    pub radiance_scale: Vec<f64>,
}

impl LayeredImager {
    /// FFTs of the kernels (`None`: unused, skipped).
    pub fn kernel_spectra(&self, kernels: &[Option<&Mat<f32>>]) -> Result<KernelSpectra> {
        let mut b = self.buffers();
        let mut spec = Vec::with_capacity(kernels.len());
        for (j, k) in kernels.iter().enumerate() {
            match k {
                None => spec.push(None),
                Some(m) => {
                    if m.nrows() != self.wp || m.ncols() != self.wp {
                        return Err(OpticsError::Shape(format!(
                            "kernel {j} is {}×{}, expected {}×{}",
                            m.nrows(),
                            m.ncols(),
                            self.wp,
                            self.wp
                        )));
                    }
                    let l = Layer {
                        radiance: m,
                        alpha: m,
                        psf: m,
                    };
                    self.psf_spectrum(&l, &mut b);
                    spec.push(Some(b.p.clone()));
                }
            }
        }
        Ok(KernelSpectra { spec })
    }

    /// A zeroed accumulator for `n` kernels.
    pub fn kernel_grad_accumulator(&self, n: usize) -> KernelGradAccumulator {
        KernelGradAccumulator {
            spec: vec![None; n],
            radiance_scale: vec![0.0; n],
        }
    }

    fn check_spectral(&self, layers: &[SpectralLayer], ks: &KernelSpectra) -> Result<()> {
        for (k, l) in layers.iter().enumerate() {
            for (name, m) in [("radiance", l.radiance), ("alpha", l.alpha)] {
                if m.nrows() != self.h || m.ncols() != self.w {
                    return Err(OpticsError::Shape(format!(
                        "layer {k}: {name} is {}×{}, expected {}×{}",
                        m.nrows(),
                        m.ncols(),
                        self.h,
                        self.w
                    )));
                }
                if m.col_iter().any(|c| c.iter().any(|v| !v.is_finite())) {
                    return Err(OpticsError::param(
                        "layers",
                        format!("layer {k} holds non-finite values"),
                    ));
                }
            }
            if ks.spec.get(l.kernel).is_none_or(Option::is_none) {
                return Err(OpticsError::param(
                    "kernel",
                    format!("layer {k} uses kernel {} which was not computed", l.kernel),
                ));
            }
        }
        Ok(())
    }

    /// Packs αL + iα of a layer into `b.a` and transforms it.
    fn layer_spectrum(&self, l: &SpectralLayer, b: &mut Buffers) {
        b.a.fill(c64::new(0.0, 0.0));
        for r in 0..self.h {
            for c in 0..self.w {
                let al = l.alpha[(r, c)] as f64;
                b.a[r * self.nx + c] = c64::new(al * l.radiance[(r, c)] as f64, al);
            }
        }
        self.fft2(&mut b.a, &mut b.col, &mut b.scratch, false);
    }

    /// S1 with precomputed kernel spectra (two FFTs per non-empty layer); keeps the tape the
    /// PSF VJP needs.
    pub fn forward_spectral(
        &self,
        layers: &[SpectralLayer],
        ks: &KernelSpectra,
    ) -> Result<(Mat<f32>, S1Tape)> {
        self.check_spectral(layers, ks)?;
        let (cy, cx) = (self.wp / 2, self.wp / 2);
        let mut img = Mat::<f64>::zeros(self.h, self.w);
        let mut saved = Vec::with_capacity(layers.len());
        let mut b = self.buffers();
        let norm = 1.0 / (self.ny * self.nx) as f64;
        for l in layers {
            if l.alpha.col_iter().all(|c| c.iter().all(|&v| v == 0.0)) {
                saved.push(None);
                continue;
            }
            self.layer_spectrum(l, &mut b);
            let p = ks.spec[l.kernel].as_ref().expect("checked");
            b.a.iter_mut().zip(p).for_each(|(a, p)| *a *= p * norm);
            self.fft2(&mut b.a, &mut b.col, &mut b.scratch, true);
            let prev = Mat::from_fn(self.h, self.w, |r, c| img[(r, c)] as f32);
            let o = Mat::from_fn(self.h, self.w, |r, c| {
                b.a[(r + cy) * self.nx + c + cx].im as f32
            });
            for c in 0..self.w {
                for r in 0..self.h {
                    let v = b.a[(r + cy) * self.nx + c + cx];
                    img[(r, c)] = v.re + (1.0 - v.im) * img[(r, c)];
                }
            }
            saved.push(Some((prev, o)));
        }
        let image = Mat::from_fn(self.h, self.w, |r, c| img[(r, c)] as f32);
        Ok((image.clone(), S1Tape { saved, image }))
    }

    /// Adds ∂loss/∂P (in the frequency domain) and ∂loss/∂(radiance scale) of one frame into
    /// `acc`, for ∂loss/∂I = `grad`. Two FFTs per non-empty layer; no input gradients.
    pub fn vjp_kernels(
        &self,
        layers: &[SpectralLayer],
        tape: &S1Tape,
        grad: &Mat<f64>,
        acc: &mut KernelGradAccumulator,
    ) -> Result<()> {
        if grad.nrows() != self.h || grad.ncols() != self.w || tape.saved.len() != layers.len() {
            return Err(OpticsError::Shape(format!(
                "grad is {}×{} for {} layers; forward was {}×{} with {} layers",
                grad.nrows(),
                grad.ncols(),
                layers.len(),
                self.h,
                self.w,
                tape.saved.len()
            )));
        }
        let (cy, cx) = (self.wp / 2, self.wp / 2);
        let mut gi = grad.clone();
        let mut b = self.buffers();
        let mut g = vec![c64::new(0.0, 0.0); self.ny * self.nx];
        let norm = 1.0 / (self.ny * self.nx) as f64;
        let n = layers.len();
        // I⁽ᵏ⁾ of each layer: the next non-empty layer's `prev`, or the final image.
        let mut above: &Mat<f32> = &tape.image;
        for k in (0..n).rev() {
            let Some((prev, o)) = &tape.saved[k] else {
                continue;
            };
            let l = &layers[k];
            // ⟨gI, conv⟩ with conv = I⁽ᵏ⁾ − (1 − o)·I⁽ᵏ⁻¹⁾.
            let mut dot = 0.0;
            g.fill(c64::new(0.0, 0.0));
            for r in 0..self.h {
                for c in 0..self.w {
                    let (p, oo) = (prev[(r, c)] as f64, o[(r, c)] as f64);
                    let conv = above[(r, c)] as f64 - (1.0 - oo) * p;
                    dot += gi[(r, c)] * conv;
                    g[(r + cy) * self.nx + c + cx] = c64::new(gi[(r, c)], -gi[(r, c)] * p);
                }
            }
            for c in 0..self.w {
                for r in 0..self.h {
                    gi[(r, c)] *= 1.0 - o[(r, c)] as f64;
                }
            }
            self.fft2(&mut g, &mut b.col, &mut b.scratch, false);
            self.layer_spectrum(l, &mut b);
            let slot = acc.spec[l.kernel].get_or_insert_with(|| vec![c64::new(0.0, 0.0); g.len()]);
            slot.iter_mut()
                .zip(g.iter().zip(&b.a))
                .for_each(|(s, (gg, a))| *s += gg * a.conj() * norm);
            acc.radiance_scale[l.kernel] += dot;
            above = prev;
        }
        Ok(())
    }

    /// Sums `other` into `acc` (per-thread accumulators of a batch).
    pub fn merge_kernel_grads(acc: &mut KernelGradAccumulator, other: KernelGradAccumulator) {
        for (a, o) in acc.spec.iter_mut().zip(other.spec) {
            match (a.as_mut(), o) {
                (Some(x), Some(y)) => x.iter_mut().zip(&y).for_each(|(p, q)| *p += q),
                (None, Some(y)) => *a = Some(y),
                _ => {}
            }
        }
        for (a, o) in acc.radiance_scale.iter_mut().zip(other.radiance_scale) {
            *a += o;
        }
    }

    /// ∂loss/∂P_j (W_p×W_p) from an accumulator: one inverse FFT per kernel that got gradient.
    pub fn kernel_grads(&self, acc: KernelGradAccumulator) -> Vec<Mat<f64>> {
        let mut b = self.buffers();
        acc.spec
            .into_iter()
            .map(|s| match s {
                None => Mat::zeros(self.wp, self.wp),
                Some(mut v) => {
                    self.fft2(&mut v, &mut b.col, &mut b.scratch, true);
                    Mat::from_fn(self.wp, self.wp, |r, c| v[r * self.nx + c].re)
                }
            })
            .collect()
    }
}

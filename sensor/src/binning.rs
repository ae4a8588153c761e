//! Box envelope W_p̂ of continuous width p̂ with fractional edge weights, downsampling to the
//! effective pixel grid and the energy factor κ (S2, S24), as one separable linear operator.
//!
//! Effective pixel i (per axis) spans [a_i, a_i + w] in sample units, w = p̂/Δ, centred on
//! the image: a_i = n/2 + (i − m/2)·w with m = ⌊n/w⌋ pixels. Sample k covers [k, k+1]; its
//! weight is the overlap length, so edge samples get fractional weights and the result is
//! piecewise linear (hence differentiable almost everywhere) in p̂. The mean over the box
//! times κ = (p̂/p_base)² equals (Δ/p_base)² × (overlap-weighted sum): photons per effective
//! pixel when the input is photons per base-pixel area.

use crate::error::{SensorError, check_positive};
use faer::Mat;

/// One axis of the operator: per output pixel, the first sample and the overlap weights and
/// their derivatives w.r.t. w (samples per effective pixel).
#[derive(Clone, Debug)]
struct Band {
    start: Vec<usize>,
    weight: Vec<Vec<f64>>,
    dweight: Vec<Vec<f64>>,
}

impl Band {
    fn new(n: usize, w: f64) -> Band {
        let m = (n as f64 / w + 1e-9).floor() as usize;
        let mut start = Vec::with_capacity(m);
        let mut weight = Vec::with_capacity(m);
        let mut dweight = Vec::with_capacity(m);
        let c = n as f64 / 2.0;
        for i in 0..m {
            let da = i as f64 - m as f64 / 2.0;
            let db = da + 1.0;
            let a = c + da * w;
            let b = c + db * w;
            let mut k0 = a.floor().max(0.0) as usize;
            let mut k1 = (b.ceil() as usize).min(n);
            // An edge exactly on a sample boundary (every edge at an integer multiple of the
            // sample pitch, every sixth at 9.5 µm from 3 µm) is a kink: moving it right takes
            // in one sample, moving it left the other. Its derivative is the mean of the two,
            // so the sample beyond it joins the band with weight 0 and half the derivative
            // (before, both halves were dropped: ∂/∂p̂ was 0 at 9 µm and off at 9.5 µm).
            if a == a.floor() && k0 > 0 {
                k0 -= 1;
            }
            if b == b.ceil() && k1 < n {
                k1 += 1;
            }
            let mut ws = Vec::with_capacity(k1.saturating_sub(k0));
            let mut dws = Vec::with_capacity(k1.saturating_sub(k0));
            for k in k0..k1 {
                let (kl, kr) = (k as f64, k as f64 + 1.0);
                let ov = (kr.min(b) - kl.max(a)).max(0.0);
                // How much of an edge's motion this sample's overlap follows.
                let share = |e: f64| {
                    if e > kl && e < kr {
                        1.0
                    } else if e == kl || e == kr {
                        0.5
                    } else {
                        0.0
                    }
                };
                ws.push(ov);
                dws.push(share(b) * db - share(a) * da);
            }
            start.push(k0);
            weight.push(ws);
            dweight.push(dws);
        }
        Band {
            start,
            weight,
            dweight,
        }
    }

    fn len(&self) -> usize {
        self.start.len()
    }
}

/// Plan of the box integration from a fine grid to the effective pixel grid (S2, S24).
#[derive(Clone, Debug)]
pub struct BoxIntegrator {
    rows: Band,
    cols: Band,
    in_shape: (usize, usize),
    scale: f64,
    sample_pitch: f64,
}

/// Gradients of a scalar loss through [`BoxIntegrator::vjp`].
#[derive(Clone, Debug)]
pub struct IntegratorGrad {
    /// Gradient w.r.t. the fine input image (per photon per base-pixel area).
    pub d_image: Mat<f32>,
    /// Gradient w.r.t. the effective pitch p̂ (per metre).
    pub d_p_hat: f64,
}

impl BoxIntegrator {
    /// Plans integration of a `rows`×`cols` image sampled every `sample_pitch` m into pixels of
    /// width `p_hat` m, with base pitch `base_pitch` m (κ = (p̂/p_base)²).
    pub fn new(
        rows: usize,
        cols: usize,
        sample_pitch: f64,
        p_hat: f64,
        base_pitch: f64,
    ) -> Result<BoxIntegrator, SensorError> {
        check_positive("sample_pitch", sample_pitch)?;
        check_positive("p_hat", p_hat)?;
        check_positive("base_pitch", base_pitch)?;
        let w = p_hat / sample_pitch;
        if w < 1.0 - 1e-12 {
            return Err(SensorError::InvalidParameter {
                name: "p_hat",
                value: p_hat,
                why: "effective pitch must be at least the sample pitch",
            });
        }
        if (rows as f64) < w || (cols as f64) < w {
            return Err(SensorError::InvalidParameter {
                name: "p_hat",
                value: p_hat,
                why: "effective pixel is larger than the image",
            });
        }
        let r = sample_pitch / base_pitch;
        Ok(BoxIntegrator {
            rows: Band::new(rows, w),
            cols: Band::new(cols, w),
            in_shape: (rows, cols),
            scale: r * r,
            sample_pitch,
        })
    }

    /// Shape (rows, cols) of the effective pixel grid.
    pub fn out_shape(&self) -> (usize, usize) {
        (self.rows.len(), self.cols.len())
    }

    /// Shape (rows, cols) of the fine input grid.
    pub fn in_shape(&self) -> (usize, usize) {
        self.in_shape
    }

    fn check_in(&self, name: &'static str, img: &Mat<f32>) -> Result<(), SensorError> {
        if (img.nrows(), img.ncols()) != self.in_shape {
            return Err(SensorError::Shape {
                name,
                expected: self.in_shape,
                got: (img.nrows(), img.ncols()),
            });
        }
        Ok(())
    }

    fn check_grad(&self, grad: &Mat<f32>) -> Result<(), SensorError> {
        let (mr, mc) = self.out_shape();
        if (grad.nrows(), grad.ncols()) != (mr, mc) {
            return Err(SensorError::Shape {
                name: "grad",
                expected: (mr, mc),
                got: (grad.nrows(), grad.ncols()),
            });
        }
        Ok(())
    }

    /// Column pass: T[r, j] = Σ_k band[j][k] X[r, k] (f64 accumulation).
    fn col_pass(&self, img: &Mat<f32>, deriv: bool) -> Vec<f64> {
        let (nr, _) = self.in_shape;
        let mc = self.cols.len();
        let mut t = vec![0.0f64; nr * mc];
        for j in 0..mc {
            let k0 = self.cols.start[j];
            let ws = if deriv {
                &self.cols.dweight[j]
            } else {
                &self.cols.weight[j]
            };
            let col = &mut t[j * nr..(j + 1) * nr];
            for (dk, &wk) in ws.iter().enumerate() {
                if wk == 0.0 {
                    continue;
                }
                let src = img.col(k0 + dk);
                for (r, o) in col.iter_mut().enumerate() {
                    *o += wk * src[r] as f64;
                }
            }
        }
        t
    }

    /// Row pass of a column-major nr×mc buffer: Y[i, j] = Σ_k band[i][k] T[k, j].
    fn row_pass(&self, t: &[f64], deriv: bool, out: &mut [f64]) {
        let (nr, _) = self.in_shape;
        let (mr, mc) = self.out_shape();
        for j in 0..mc {
            let col = &t[j * nr..(j + 1) * nr];
            for i in 0..mr {
                let k0 = self.rows.start[i];
                let ws = if deriv {
                    &self.rows.dweight[i]
                } else {
                    &self.rows.weight[i]
                };
                let s: f64 = ws.iter().zip(&col[k0..]).map(|(a, b)| a * b).sum();
                out[j * mr + i] += s;
            }
        }
    }

    /// Photons per effective pixel: D↓(I * W_p̂)·κ.
    pub fn forward(&self, img: &Mat<f32>) -> Result<Mat<f32>, SensorError> {
        self.check_in("image", img)?;
        let (mr, mc) = self.out_shape();
        let t = self.col_pass(img, false);
        let mut y = vec![0.0; mr * mc];
        self.row_pass(&t, false, &mut y);
        Ok(Mat::from_fn(mr, mc, |i, j| {
            (self.scale * y[j * mr + i]) as f32
        }))
    }

    /// VJP: gradient `grad` w.r.t. the output → gradients w.r.t. the input image and p̂.
    pub fn vjp(&self, img: &Mat<f32>, grad: &Mat<f32>) -> Result<IntegratorGrad, SensorError> {
        self.check_in("image", img)?;
        let (mr, mc) = self.out_shape();
        self.check_grad(grad)?;
        let (nr, nc) = self.in_shape;
        // d_image = s A_yᵀ G A_x.
        let mut d = Mat::<f32>::zeros(nr, nc);
        let mut tmp = vec![0.0f64; nr];
        for j in 0..mc {
            tmp.iter_mut().for_each(|v| *v = 0.0);
            for i in 0..mr {
                let g = grad[(i, j)] as f64;
                if g == 0.0 {
                    continue;
                }
                let k0 = self.rows.start[i];
                for (dk, &w) in self.rows.weight[i].iter().enumerate() {
                    tmp[k0 + dk] += w * g;
                }
            }
            let k0 = self.cols.start[j];
            for (dk, &w) in self.cols.weight[j].iter().enumerate() {
                let mut col = d.col_mut(k0 + dk);
                for (r, &v) in tmp.iter().enumerate() {
                    col[r] += (self.scale * w * v) as f32;
                }
            }
        }
        Ok(IntegratorGrad {
            d_image: d,
            d_p_hat: self.p_hat_dot(img, grad),
        })
    }

    /// ∂L/∂p̂ alone (per metre) for gradient `grad` w.r.t. the output: [`Self::vjp`]'s
    /// `d_p_hat` without the input gradient, for an input that is data (a target).
    pub fn pitch_vjp(&self, img: &Mat<f32>, grad: &Mat<f32>) -> Result<f64, SensorError> {
        self.check_in("image", img)?;
        self.check_grad(grad)?;
        Ok(self.p_hat_dot(img, grad))
    }

    /// ⟨G, ∂Y/∂p̂⟩ with ∂Y/∂p̂ = s (A_y' X A_xᵀ + A_y X A_x'ᵀ) / Δ (shapes checked by the caller).
    fn p_hat_dot(&self, img: &Mat<f32>, grad: &Mat<f32>) -> f64 {
        let (mr, mc) = self.out_shape();
        let t = self.col_pass(img, false);
        let u = self.col_pass(img, true);
        let mut dy = vec![0.0; mr * mc];
        self.row_pass(&t, true, &mut dy);
        self.row_pass(&u, false, &mut dy);
        let mut dw = 0.0;
        for j in 0..mc {
            for i in 0..mr {
                dw += grad[(i, j)] as f64 * dy[j * mr + i];
            }
        }
        self.scale * dw / self.sample_pitch
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ramp(n: usize, m: usize) -> Mat<f32> {
        Mat::from_fn(n, m, |r, c| (1.0 + ((r * 7 + c * 3) % 11) as f32) * 0.5)
    }

    #[test]
    fn integer_binning_sums_blocks_and_conserves_photons() {
        // 3×3 binning of a 9×9 image with p_base = Δ: each output is the block sum.
        let img = ramp(9, 9);
        let op = BoxIntegrator::new(9, 9, 1e-6, 3e-6, 1e-6).unwrap();
        let y = op.forward(&img).unwrap();
        assert_eq!(op.out_shape(), (3, 3));
        for i in 0..3 {
            for j in 0..3 {
                let mut s = 0.0;
                for r in 0..3 {
                    for c in 0..3 {
                        s += img[(3 * i + r, 3 * j + c)];
                    }
                }
                assert!((y[(i, j)] - s).abs() < 1e-4);
            }
        }
    }

    #[test]
    fn kappa_is_area_ratio_for_flat_field() {
        // Flat field of q photons per base-pixel area: effective pixel collects q (p̂/p_base)².
        let q = 100.0f32;
        let img = Mat::from_fn(40, 40, |_, _| q);
        let op = BoxIntegrator::new(40, 40, 0.5e-6, 3.7e-6, 3e-6).unwrap();
        let y = op.forward(&img).unwrap();
        let k = (3.7f64 / 3.0).powi(2) as f32;
        for v in y
            .col_iter()
            .flat_map(|c| c.iter().copied().collect::<Vec<_>>())
        {
            assert!((v - q * k).abs() < 1e-3 * q * k, "{v}");
        }
    }

    #[test]
    fn vjp_matches_finite_differences() {
        let img = ramp(23, 19);
        let dx = 1e-6;
        let p = 3.3e-6;
        let op = BoxIntegrator::new(23, 19, dx, p, 2e-6).unwrap();
        let (mr, mc) = op.out_shape();
        let g = Mat::from_fn(mr, mc, |i, j| ((i * 5 + j * 2) % 7) as f32 - 3.0);
        let loss = |o: &BoxIntegrator, x: &Mat<f32>| -> f64 {
            let y = o.forward(x).unwrap();
            (0..mr)
                .flat_map(|i| (0..mc).map(move |j| (i, j)))
                .map(|(i, j)| g[(i, j)] as f64 * y[(i, j)] as f64)
                .sum()
        };
        let gr = op.vjp(&img, &g).unwrap();
        // p̂ (central difference, step small enough to stay on one linear piece).
        let h = 1e-10;
        let lp = loss(&BoxIntegrator::new(23, 19, dx, p + h, 2e-6).unwrap(), &img);
        let lm = loss(&BoxIntegrator::new(23, 19, dx, p - h, 2e-6).unwrap(), &img);
        let fd = (lp - lm) / (2.0 * h);
        assert!(
            (fd - gr.d_p_hat).abs() < 1e-3 * fd.abs().max(1.0),
            "{fd} vs {}",
            gr.d_p_hat
        );
        assert_eq!(op.pitch_vjp(&img, &g).unwrap(), gr.d_p_hat);
        // Image (linear: exact up to f32 rounding).
        for &(r, c) in &[(0, 0), (5, 7), (11, 9), (22, 18)] {
            let mut xp = img.clone();
            xp[(r, c)] += 0.5;
            let fd = (loss(&op, &xp) - loss(&op, &img)) / 0.5;
            assert!((fd - gr.d_image[(r, c)] as f64).abs() < 1e-3, "{fd}");
        }
    }

    /// Where box edges sit exactly on sample boundaries the loss has a kink in p̂, and ∂L/∂p̂ is the mean of its one-sided
    /// derivatives, not 0 or a part of them.
    #[test]
    fn edges_on_sample_boundaries_give_the_mean_of_the_one_sided_derivatives() {
        // Sizes where edges do land on boundaries: a_i = n/2 + (i − m/2)·w is an integer for
        // rows at w = 3 on 23, for both axes at w = 2.5 on 21 × 26, for columns at w = 5 on 19.
        for (w, n, nc) in [(3.0, 23, 19), (2.5, 21, 26), (5.0, 23, 19)] {
            let img = ramp(n, nc);
            let op = BoxIntegrator::new(n, nc, 1.0, w, 1.0).unwrap();
            let (mr, mc) = op.out_shape();
            let g = Mat::from_fn(mr, mc, |i, j| ((i * 5 + j * 2) % 7) as f32 - 2.5);
            let loss = |p: f64| -> f64 {
                let o = BoxIntegrator::new(n, nc, 1.0, p, 1.0).unwrap();
                assert_eq!(o.out_shape(), (mr, mc));
                let y = o.forward(&img).unwrap();
                (0..mr)
                    .flat_map(|i| (0..mc).map(move |j| (i, j)))
                    .map(|(i, j)| g[(i, j)] as f64 * y[(i, j)] as f64)
                    .sum()
            };
            // Each side is linear up to the next kink (edges move by at most 5h); a wider step
            // keeps the outputs' f32 rounding out of the differences.
            let h = 1e-3;
            let (l0, right, left) = (loss(w), loss(w + h), loss(w - h));
            let (dr, dl) = ((right - l0) / h, (l0 - left) / h);
            assert!(
                (dr - dl).abs() > 1e-2 * dr.abs().max(dl.abs()),
                "w {w}: no kink"
            );
            let want = 0.5 * (dr + dl);
            let got = op.vjp(&img, &g).unwrap().d_p_hat;
            assert!(
                (got - want).abs() < 1e-3 * want.abs().max(1.0),
                "w {w}: {got} against the mean {want} of {dl} and {dr}"
            );
            // The forward is unchanged by the zero-weight samples the band took in.
            let y = op.forward(&img).unwrap();
            let total: f64 = (0..mr)
                .flat_map(|i| (0..mc).map(move |j| (i, j)))
                .map(|(i, j)| y[(i, j)] as f64)
                .sum();
            let covered = |n: usize, m: usize| {
                let c = n as f64 / 2.0;
                (c - m as f64 / 2.0 * w, c + m as f64 / 2.0 * w)
            };
            let ((r0, r1), (c0, c1)) = (covered(n, mr), covered(nc, mc));
            let mut want_total = 0.0;
            for r in 0..n {
                for c in 0..nc {
                    let fr = ((r as f64 + 1.0).min(r1) - (r as f64).max(r0)).max(0.0);
                    let fc = ((c as f64 + 1.0).min(c1) - (c as f64).max(c0)).max(0.0);
                    want_total += fr * fc * img[(r, c)] as f64;
                }
            }
            assert!((total - want_total).abs() < 1e-4 * want_total, "w {w}");
        }
    }

    #[test]
    fn rejects_bad_pitch() {
        assert!(BoxIntegrator::new(10, 10, 1e-6, 0.5e-6, 1e-6).is_err());
        assert!(BoxIntegrator::new(10, 10, 1e-6, f64::NAN, 1e-6).is_err());
        assert!(BoxIntegrator::new(10, 10, 1e-6, 20e-6, 1e-6).is_err());
    }
}

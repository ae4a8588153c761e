//! The calibration head's output layer solved in closed form: ridge regression of the
//! slippage targets on the head's hidden activations over the training frames, the ridge
//! weight per axis chosen by exact leave-one-out error.
//!
//! The output layer is linear in those activations, so for fixed lower layers S8's squared
//! error over the training set has a closed-form minimiser; the few hundred SGD steps of
//! sandwich training leave the layer far from it (the heads read the x translation with a
//! slope of 0.17 on their own training frames, docs/run.md). With more hidden units (1280)
//! than frames (a few hundred) the plain minimiser interpolates, so the fit is ridge, through
//! one eigendecomposition of the n × n kernel (or of the d × d Gram matrix when there are more
//! frames than units) for every weight tried, the weight picked per axis from a log grid by
//! the closed-form leave-one-out residuals r_i / (1 − H_ii).

use crate::error::{Result, param};
use faer::{Mat, Side};
use nanoeye_nets::arch::Arch;
use nanoeye_nets::{BnMode, Supernet, Tensor};

/// Ridge weights tried: 10^(k/4) times the kernel's mean eigenvalue, k in this range.
const GRID: std::ops::RangeInclusive<i32> = -24..=8;

/// What a refit did, per slippage axis x, y, z.
#[derive(Clone, Debug, serde::Serialize)]
pub struct HeadFit {
    /// Frames fitted.
    pub frames: usize,
    /// Chosen ridge weight per axis, relative to the kernel's mean eigenvalue.
    pub lambda_rel: [f64; 3],
    /// RMS error of the head before the refit on the fitted frames (mm).
    pub rmse_before_mm: [f64; 3],
    /// RMS error of the refitted layer on the fitted frames (mm).
    pub rmse_fit_mm: [f64; 3],
    /// Leave-one-out RMS error of the refitted layer (mm): an estimate of its error on new
    /// frames of the same distribution.
    pub loo_rmse_mm: [f64; 3],
}

/// A refit's data, batch by batch: network inputs (N, 1, H, W) and slippage targets
/// (N, 3, 1, 1) in the head's units (mm).
#[derive(Clone, Debug, Default)]
pub struct FitFrames {
    /// Network inputs per batch.
    pub inputs: Vec<Tensor>,
    /// Slippage targets per batch (mm).
    pub targets_mm: Vec<Tensor>,
}

/// Subnet `arch` as deployed: its BN statistics over every frame of `data`, then its head's
/// output layer refitted on them ([`refit_slip_head`]). The fit replaces the layer whole and
/// depends only on the hidden activations, so subnets scored one after another on one network
/// do not carry one another's fit.
pub fn recalibrate_and_refit(net: &mut Supernet, arch: &Arch, data: &FitFrames) -> Result<HeadFit> {
    net.recalibrate_bn(arch, &data.inputs)?;
    refit_slip_head(net, arch, data)
}

/// Replaces `net.head_out` by the ridge fit of the targets of `data` on the head's hidden
/// activations of subnet `arch` (BN in eval mode as it stands: recalibrate first).
pub fn refit_slip_head(net: &mut Supernet, arch: &Arch, data: &FitFrames) -> Result<HeadFit> {
    let (z, y, before) = features(net, arch, data)?;
    let (n, d) = (z.nrows(), z.ncols());
    if d * 3 != net.head_out.w.value.len() {
        return Err(param(
            "net",
            format!(
                "the head's output layer has {} weights for {d} hidden units",
                net.head_out.w.value.len()
            ),
        ));
    }
    let ridge = Ridge::new(&z, &y)?;
    let mut best = [(f64::INFINITY, 0.0); 3];
    for k in GRID {
        let rel = 10f64.powf(k as f64 / 4.0);
        let sse = ridge.loo_sse(ridge.mean_eigenvalue * rel);
        for a in 0..3 {
            if sse[a] < best[a].0 {
                best[a] = (sse[a], rel);
            }
        }
    }
    let lambda_rel = best.map(|(_, r)| r);
    let (w, b) = ridge.solve(lambda_rel.map(|r| ridge.mean_eigenvalue * r));
    for a in 0..3 {
        for k in 0..d {
            net.head_out.w.value[a * d + k] = w[(a, k)] as f32;
        }
        net.head_out.b.value[a] = b[a] as f32;
    }
    let mut fit = [0.0; 3];
    for i in 0..n {
        for (a, f) in fit.iter_mut().enumerate() {
            let p = b[a] + (0..d).map(|k| w[(a, k)] * z[(i, k)]).sum::<f64>();
            *f += (p - y[(i, a)]).powi(2);
        }
    }
    let rms = |v: [f64; 3]| v.map(|e| (e / n as f64).sqrt());
    Ok(HeadFit {
        frames: n,
        lambda_rel,
        rmse_before_mm: rms(before),
        rmse_fit_mm: rms(fit),
        loo_rmse_mm: rms(best.map(|(e, _)| e)),
    })
}

/// The head's hidden activations of `arch` on `data` (n × d), the targets (n × 3, mm) and the
/// head's squared error per axis as it stands.
fn features(
    net: &mut Supernet,
    arch: &Arch,
    data: &FitFrames,
) -> Result<(Mat<f64>, Mat<f64>, [f64; 3])> {
    let n: usize = data.inputs.iter().map(|x| x.n).sum();
    if n < 3 {
        return Err(param(
            "frames",
            format!("a slippage head refit needs at least 3 frames, got {n}"),
        ));
    }
    if data.targets_mm.len() != data.inputs.len() {
        return Err(param(
            "targets",
            format!(
                "{} target batches for {} input batches",
                data.targets_mm.len(),
                data.inputs.len()
            ),
        ));
    }
    let mut rows: Vec<f32> = Vec::new();
    let mut y = Mat::<f64>::zeros(n, 3);
    let mut before = [0.0; 3];
    let mut i = 0;
    for (x, t) in data.inputs.iter().zip(&data.targets_mm) {
        if t.shape() != [x.n, 3, 1, 1] {
            return Err(param(
                "targets",
                format!("shape {:?} for {} inputs", t.shape(), x.n),
            ));
        }
        let o = net.forward(arch, x, BnMode::Eval)?;
        let za = net
            .head_hidden_features()
            .ok_or_else(|| param("net", "no head features after a forward pass"))?;
        rows.extend_from_slice(&za.data);
        for b in 0..x.n {
            for a in 0..3 {
                let ta = t.data[b * 3 + a] as f64;
                y[(i, a)] = ta;
                before[a] += (o.slip.data[b * 3 + a] as f64 - ta).powi(2);
            }
            i += 1;
        }
    }
    let d = rows.len() / n;
    Ok((Mat::from_fn(n, d, |i, k| rows[i * d + k] as f64), y, before))
}

/// Ridge regression of y (n × 3) on z (n × d) with an unpenalised intercept through the
/// centred data's kernel Zc Zcᵀ = U S Uᵀ (from the smaller of Zc Zcᵀ and Zcᵀ Zc), decomposed
/// once for every ridge weight.
struct Ridge {
    zm: Vec<f64>,
    ym: [f64; 3],
    zc: Mat<f64>,
    yc: Mat<f64>,
    u: Mat<f64>,
    s: Vec<f64>,
    /// Uᵀ Yc: the centred targets in the kernel's eigenbasis.
    uy: Mat<f64>,
    mean_eigenvalue: f64,
}

impl Ridge {
    fn new(z: &Mat<f64>, y: &Mat<f64>) -> Result<Ridge> {
        Ridge::decomposing(z, y, z.nrows() > z.ncols())
    }

    /// [`Ridge::new`] through Zcᵀ Zc (`gram`) or Zc Zcᵀ.
    fn decomposing(z: &Mat<f64>, y: &Mat<f64>, gram: bool) -> Result<Ridge> {
        let (n, d) = (z.nrows(), z.ncols());
        let zm: Vec<f64> = (0..d)
            .map(|k| (0..n).map(|i| z[(i, k)]).sum::<f64>() / n as f64)
            .collect();
        let ym: [f64; 3] =
            std::array::from_fn(|a| (0..n).map(|i| y[(i, a)]).sum::<f64>() / n as f64);
        let zc = Mat::from_fn(n, d, |i, k| z[(i, k)] - zm[k]);
        let yc = Mat::from_fn(n, 3, |i, a| y[(i, a)] - ym[a]);
        // The nonzero eigenvalues of Zc Zcᵀ are those of Zcᵀ Zc: decompose the smaller one.
        let (u, s) = if !gram {
            let evd = (&zc * zc.transpose())
                .self_adjoint_eigen(Side::Lower)
                .map_err(|e| param("head features", format!("eigendecomposition failed: {e:?}")))?;
            let sv = evd.S().column_vector();
            // Round-off can leave tiny negative eigenvalues of a PSD kernel.
            let s: Vec<f64> = (0..n).map(|j| sv[j].max(0.0)).collect();
            (evd.U().to_owned(), s)
        } else {
            let evd = (zc.transpose() * &zc)
                .self_adjoint_eigen(Side::Lower)
                .map_err(|e| param("head features", format!("eigendecomposition failed: {e:?}")))?;
            let sv = evd.S().column_vector();
            let s: Vec<f64> = (0..d).map(|j| sv[j].max(0.0)).collect();
            let top = s.iter().cloned().fold(0.0, f64::max);
            // U = Zc V S^(-1/2) on the kept directions; a null direction gets a zero column
            // and eigenvalue, so it neither fits nor counts in the hat matrix.
            let zv = &zc * evd.U();
            let keep: Vec<f64> = s
                .iter()
                .map(|&sj| {
                    if sj > 1e-12 * top {
                        1.0 / sj.sqrt()
                    } else {
                        0.0
                    }
                })
                .collect();
            let u = Mat::from_fn(n, d, |i, j| zv[(i, j)] * keep[j]);
            let s = s
                .iter()
                .zip(&keep)
                .map(|(&sj, &k)| if k > 0.0 { sj } else { 0.0 })
                .collect();
            (u, s)
        };
        // trace(Zc Zcᵀ) / n whichever side was decomposed, so `lambda_rel` means one thing.
        let mean_eigenvalue = s.iter().sum::<f64>() / n as f64;
        if !(mean_eigenvalue.is_finite() && mean_eigenvalue > 0.0) {
            return Err(param(
                "head features",
                "the head's activations do not vary over the frames, or are not finite",
            ));
        }
        let uy = u.transpose() * &yc;
        Ok(Ridge {
            zm,
            ym,
            zc,
            yc,
            u,
            s,
            uy,
            mean_eigenvalue,
        })
    }

    /// Exact leave-one-out squared error per axis at ridge weight `lam`: the hat matrix is
    /// 11ᵀ/n + U diag(s/(s+λ)) Uᵀ, and removing frame i moves its residual to r_i/(1 − H_ii).
    fn loo_sse(&self, lam: f64) -> [f64; 3] {
        let n = self.u.nrows();
        let shrink: Vec<f64> = self.s.iter().map(|&sj| sj / (sj + lam)).collect();
        let mut sse = [0.0; 3];
        for i in 0..n {
            let mut h = 1.0 / n as f64;
            let mut fit = [0.0; 3];
            for (j, &sh) in shrink.iter().enumerate() {
                let uij = self.u[(i, j)];
                h += uij * uij * sh;
                for (a, f) in fit.iter_mut().enumerate() {
                    *f += uij * sh * self.uy[(j, a)];
                }
            }
            for a in 0..3 {
                let r = (self.yc[(i, a)] - fit[a]) / (1.0 - h).max(1e-12);
                sse[a] += r * r;
            }
        }
        sse
    }

    /// W (3 × d) and b at ridge weights `lam` per axis: α = U diag(1/(s+λ)) Uᵀ yc, W = αᵀ Zc,
    /// b = ȳ − W z̄.
    fn solve(&self, lam: [f64; 3]) -> (Mat<f64>, [f64; 3]) {
        let (n, d) = (self.zc.nrows(), self.zc.ncols());
        let mut w = Mat::<f64>::zeros(3, d);
        let mut b = [0.0; 3];
        for a in 0..3 {
            let coef: Vec<f64> = (0..self.s.len())
                .map(|j| self.uy[(j, a)] / (self.s[j] + lam[a]))
                .collect();
            let alpha: Vec<f64> = (0..n)
                .map(|i| {
                    coef.iter()
                        .enumerate()
                        .map(|(j, c)| self.u[(i, j)] * c)
                        .sum()
                })
                .collect();
            for k in 0..d {
                w[(a, k)] = (0..n).map(|i| alpha[i] * self.zc[(i, k)]).sum();
            }
            b[a] = self.ym[a] - (0..d).map(|k| w[(a, k)] * self.zm[k]).sum::<f64>();
        }
        (w, b)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn random(n: usize, d: usize, seed: u64) -> (Mat<f64>, Mat<f64>) {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let z = Mat::from_fn(n, d, |_, _| rng.random_range(-1.0..1.0));
        let y = Mat::from_fn(n, 3, |_, _| rng.random_range(-2.0..2.0));
        (z, y)
    }

    fn predict(w: &Mat<f64>, b: [f64; 3], z: &Mat<f64>, i: usize) -> [f64; 3] {
        std::array::from_fn(|a| b[a] + (0..z.ncols()).map(|k| w[(a, k)] * z[(i, k)]).sum::<f64>())
    }

    /// The closed-form leave-one-out error equals refitting without each frame in turn, in
    /// both regimes (more features than frames, and fewer).
    #[test]
    fn loo_matches_refitting_without_each_frame() {
        for (n, d, lam) in [(9, 20, 0.3), (15, 4, 0.05), (12, 12, 2.0)] {
            let (z, y) = random(n, d, n as u64);
            let loo = Ridge::new(&z, &y).unwrap().loo_sse(lam);
            let mut brute = [0.0; 3];
            for i in 0..n {
                let keep: Vec<usize> = (0..n).filter(|&r| r != i).collect();
                let zi = Mat::from_fn(n - 1, d, |r, k| z[(keep[r], k)]);
                let yi = Mat::from_fn(n - 1, 3, |r, a| y[(keep[r], a)]);
                let (w, b) = Ridge::new(&zi, &yi).unwrap().solve([lam; 3]);
                let p = predict(&w, b, &z, i);
                for a in 0..3 {
                    brute[a] += (p[a] - y[(i, a)]).powi(2);
                }
            }
            for a in 0..3 {
                assert!(
                    (loo[a] - brute[a]).abs() <= 1e-9 * brute[a],
                    "n {n} d {d} axis {a}: closed form {} vs refits {}",
                    loo[a],
                    brute[a]
                );
            }
        }
    }

    /// Noise-free linear targets with more frames than features: a vanishing ridge weight
    /// recovers the map and the intercept.
    #[test]
    fn recovers_an_exact_linear_map() {
        let (n, d) = (40, 6);
        let (z, _) = random(n, d, 7);
        let w0 = Mat::from_fn(3, d, |a, k| (a as f64 + 1.0) * (k as f64 - 2.5));
        let b0 = [0.5, -1.25, 3.0];
        let y = Mat::from_fn(n, 3, |i, a| predict(&w0, b0, &z, i)[a]);
        let (w, b) = Ridge::new(&z, &y).unwrap().solve([1e-12; 3]);
        for a in 0..3 {
            assert!((b[a] - b0[a]).abs() < 1e-9, "b[{a}] {} vs {}", b[a], b0[a]);
            for k in 0..d {
                assert!((w[(a, k)] - w0[(a, k)]).abs() < 1e-9);
            }
        }
    }

    /// Either side of the decomposition gives the same fit and leave-one-out error, with
    /// more frames than features and with fewer.
    #[test]
    fn both_sides_of_the_decomposition_agree() {
        for (n, d) in [(20, 5), (6, 9)] {
            let (z, y) = random(n, d, 11);
            let a = Ridge::decomposing(&z, &y, false).unwrap();
            let b = Ridge::decomposing(&z, &y, true).unwrap();
            assert!((a.mean_eigenvalue - b.mean_eigenvalue).abs() < 1e-12 * a.mean_eigenvalue);
            for lam in [1e-3, 0.7] {
                let (la, lb) = (a.loo_sse(lam), b.loo_sse(lam));
                let ((wa, ba), (wb, bb)) = (a.solve([lam; 3]), b.solve([lam; 3]));
                for k in 0..3 {
                    assert!(
                        (la[k] - lb[k]).abs() < 1e-9 * la[k],
                        "{n}×{d}: {la:?} {lb:?}"
                    );
                    assert!((ba[k] - bb[k]).abs() < 1e-9);
                    for j in 0..d {
                        assert!((wa[(k, j)] - wb[(k, j)]).abs() < 1e-9);
                    }
                }
            }
        }
    }

    /// Features that do not vary are refused, not fitted.
    #[test]
    fn constant_features_are_refused() {
        let z = Mat::from_fn(5, 3, |_, k| k as f64);
        let y = Mat::from_fn(5, 3, |i, _| i as f64);
        assert!(Ridge::new(&z, &y).is_err());
    }
}

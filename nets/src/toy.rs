//! A synthetic disk-mask task for smoke-training subnets, and the training loop that fits one.
//!
//! Generator (image i of a split with seed s, RNG ChaCha8 seeded from (s, i)): an S×S
//! single-channel image with a background of 0.55 + 0.15·x/S (an illumination ramp), a dark
//! disk (value 0.1) of centre uniform in [0.3S, 0.7S]² and radius uniform in [0.08S, 0.2S],
//! plus N(0, 0.03²) noise. Target mask: 1 where a pixel centre lies inside the disk. Slippage
//! stand-in target: Δt* = (4(c_x/S − ½), 4(c_y/S − ½), 10(r/S − 0.14)), dimensionless.
//! The held-out split uses a different seed stream than the training split.

use crate::arch::{Arch, SupernetConfig};
use crate::error::{NetsError, Result};
use crate::loss::{dice_loss, hard_dice, slip_mse};
use crate::norm::BnMode;
use crate::optim::{Adam, cosine_lr};
use crate::supernet::Supernet;
use crate::tensor::Tensor;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use serde::Serialize;
use std::time::Instant;

/// One synthetic sample: image (S·S), mask (S·S), slippage target. `size` must not exceed
/// [`MAX_TOY_SIZE`] ([`toy_batch`] checks it).
pub fn toy_sample(size: usize, seed: u64, index: u64) -> (Vec<f32>, Vec<f32>, [f32; 3]) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ index);
    let s = size as f32;
    let cx = rng.random_range(0.3 * s..=0.7 * s);
    let cy = rng.random_range(0.3 * s..=0.7 * s);
    let r = rng.random_range(0.08 * s..=0.2 * s);
    let noise = Normal::new(0.0f32, 0.03).expect("valid normal");
    let mut img = vec![0.0f32; size * size];
    let mut mask = vec![0.0f32; size * size];
    for y in 0..size {
        for x in 0..size {
            let (px, py) = (x as f32 + 0.5, y as f32 + 0.5);
            let inside = (px - cx).powi(2) + (py - cy).powi(2) <= r * r;
            let base = if inside { 0.1 } else { 0.55 + 0.15 * px / s };
            img[y * size + x] = base + noise.sample(&mut rng);
            mask[y * size + x] = if inside { 1.0 } else { 0.0 };
        }
    }
    (
        img,
        mask,
        [
            4.0 * (cx / s - 0.5),
            4.0 * (cy / s - 0.5),
            10.0 * (r / s - 0.14),
        ],
    )
}

/// A batch of samples `first..first+n` of a split: (images, masks, slippage targets).
pub fn toy_batch(size: usize, seed: u64, first: u64, n: usize) -> Result<(Tensor, Tensor, Tensor)> {
    if size == 0
        || size > MAX_TOY_SIZE
        || n.checked_mul(size * size)
            .is_none_or(|p| p > MAX_TOY_BATCH_PIXELS)
    {
        return Err(NetsError::Param(format!(
            "toy batch of {n} images of {size}² px: side must lie in 1..={MAX_TOY_SIZE} and the \
             batch hold at most {MAX_TOY_BATCH_PIXELS} pixels"
        )));
    }
    let (mut xs, mut ms, mut ts) = (Vec::new(), Vec::new(), Vec::new());
    for i in 0..n as u64 {
        let (x, m, t) = toy_sample(size, seed, first + i);
        xs.extend(x);
        ms.extend(m);
        ts.extend(t);
    }
    Ok((
        Tensor::from_vec(n, 1, size, size, xs)?,
        Tensor::from_vec(n, 1, size, size, ms)?,
        Tensor::from_vec(n, 3, 1, 1, ts)?,
    ))
}

/// Settings of a toy fit.
#[derive(Clone, Debug, Serialize)]
pub struct ToyConfig {
    /// Image side in pixels.
    pub size: usize,
    /// Training steps.
    pub steps: usize,
    /// Images per step.
    pub batch: usize,
    /// Distinct training images (cycled).
    pub n_train: usize,
    /// Held-out images.
    pub n_test: usize,
    /// Peak Adam learning rate (cosine decay to 1 % of it).
    pub lr: f64,
    /// Slippage weight λ_slip in L_task.
    pub lambda_slip: f64,
    /// Seed of weights and data.
    pub seed: u64,
}

impl Default for ToyConfig {
    fn default() -> Self {
        Self {
            size: 64,
            steps: 300,
            batch: 16,
            n_train: 1024,
            n_test: 128,
            lr: 3e-3,
            lambda_slip: 0.1,
            seed: 7,
        }
    }
}

/// Held-out metrics after a fit.
#[derive(Clone, Copy, Debug, Serialize)]
pub struct ToyResult {
    /// Mean hard Dice of the thresholded mask on the held-out split.
    pub dice: f64,
    /// Mean ‖Δt − Δt*‖² on the held-out split.
    pub slip_mse: f64,
    /// Final training L_task.
    pub train_loss: f64,
    /// Wall time of the fit in seconds.
    pub seconds: f64,
}

/// Largest image side of a toy fit.
pub const MAX_TOY_SIZE: usize = 4096;
/// Largest batch × side² of a toy fit: training the largest subnet takes ≈3.5 KiB per input
/// pixel of a batch (measured), so this keeps a step below ≈8 GiB.
pub const MAX_TOY_BATCH_PIXELS: usize = 1 << 21;
/// Largest peak learning rate of a toy fit (Adam steps of order lr per weight).
pub const MAX_TOY_LR: f64 = 1.0;

impl ToyConfig {
    /// Checks every field; the message starts with the field's name.
    pub fn validate(&self) -> Result<()> {
        let bad = |m: String| Err(NetsError::Param(m));
        if self.steps == 0 || self.n_train == 0 || self.n_test == 0 {
            return bad(format!(
                "steps, n_train, n_test must be positive: {}, {}, {}",
                self.steps, self.n_train, self.n_test
            ));
        }
        if self.batch < 2 {
            // The calibration head normalizes pooled (1×1) features over the batch: one image
            // gives zero variance in training and a meaningless running variance.
            return bad(format!(
                "batch: need at least 2 images per step (batch norm of the pooled head), got {}",
                self.batch
            ));
        }
        if !(8..=MAX_TOY_SIZE).contains(&self.size) {
            return bad(format!(
                "size: must lie in 8..={MAX_TOY_SIZE} px, got {}",
                self.size
            ));
        }
        let pixels = self.batch.checked_mul(self.size * self.size);
        if pixels.is_none_or(|p| p > MAX_TOY_BATCH_PIXELS) {
            return bad(format!(
                "batch: {} images of {}² px exceed the memory bound of {MAX_TOY_BATCH_PIXELS} \
                 input pixels per step (≈8 GiB)",
                self.batch, self.size
            ));
        }
        if !(self.lr.is_finite() && self.lr > 0.0 && self.lr <= MAX_TOY_LR) {
            return bad(format!(
                "lr: must lie in (0, {MAX_TOY_LR}], got {}",
                self.lr
            ));
        }
        if !(self.lambda_slip.is_finite() && self.lambda_slip >= 0.0) {
            return bad(format!(
                "lambda_slip: must be finite and >= 0, got {}",
                self.lambda_slip
            ));
        }
        Ok(())
    }
}

/// Trains subnet `arch` of a fresh supernet on the toy task, recalibrates BN, evaluates.
pub fn fit_toy(arch: &Arch, cfg: &ToyConfig) -> Result<ToyResult> {
    fit_toy_with_progress(arch, cfg, &mut |_, _| {})
}

/// [`fit_toy`], calling `progress(steps_done, training L_task)` after every step.
pub fn fit_toy_with_progress(
    arch: &Arch,
    cfg: &ToyConfig,
    progress: &mut dyn FnMut(usize, f64),
) -> Result<ToyResult> {
    cfg.validate()?;
    let t0 = Instant::now();
    let mut net = Supernet::new(SupernetConfig::default(), cfg.seed)?;
    let mut opt = Adam::default();
    let train_seed = cfg.seed;
    let test_seed = cfg.seed ^ 0xDEAD_BEEF;
    let mut last = 0.0;
    for step in 0..cfg.steps {
        let first = ((step * cfg.batch) % cfg.n_train) as u64;
        let (x, m, t) = toy_batch(cfg.size, train_seed, first, cfg.batch)?;
        let out = net.forward(arch, &x, BnMode::Train)?;
        let (ls, dl) = dice_loss(&out.mask_logits, &m)?;
        let (lc, mut ds) = slip_mse(&out.slip, &t)?;
        ds.data
            .iter_mut()
            .for_each(|g| *g *= cfg.lambda_slip as f32);
        last = ls + cfg.lambda_slip * lc;
        if !last.is_finite() {
            return Err(NetsError::Param(format!(
                "lr: training diverged at step {} (non-finite loss); lower the learning rate {}",
                step + 1,
                cfg.lr
            )));
        }
        net.zero_grad();
        net.backward(&dl, &ds)?;
        opt.step(&mut net, cosine_lr(cfg.lr, 0.01 * cfg.lr, step, cfg.steps))?;
        progress(step + 1, last);
    }
    let batches: Vec<Tensor> = (0..(cfg.n_train / cfg.batch).clamp(1, 8))
        .map(|b| toy_batch(cfg.size, train_seed, (b * cfg.batch) as u64, cfg.batch).map(|t| t.0))
        .collect::<Result<_>>()?;
    net.recalibrate_bn(arch, &batches)?;
    let (mut dice, mut mse, mut seen) = (0.0, 0.0, 0usize);
    while seen < cfg.n_test {
        let n = cfg.batch.min(cfg.n_test - seen);
        let (x, m, t) = toy_batch(cfg.size, test_seed, seen as u64, n)?;
        let out = net.forward(arch, &x, BnMode::Eval)?;
        dice += hard_dice(&out.mask_logits, &m)? * n as f64;
        mse += slip_mse(&out.slip, &t)?.0 * n as f64;
        seen += n;
    }
    let (dice, slip_mse) = held_out_means(dice, mse, cfg.n_test, cfg.lr)?;
    Ok(ToyResult {
        dice,
        slip_mse,
        train_loss: last,
        seconds: t0.elapsed().as_secs_f64(),
    })
}

/// The held-out means (Dice, slip MSE) of sums over `n` images, refused naming the learning
/// rate `lr` where either is not finite (the message gave the sums: a "Dice" of 16).
fn held_out_means(dice_sum: f64, mse_sum: f64, n: usize, lr: f64) -> Result<(f64, f64)> {
    let (dice, mse) = (dice_sum / n as f64, mse_sum / n as f64);
    if !(dice.is_finite() && mse.is_finite()) {
        return Err(NetsError::Param(format!(
            "lr: the trained subnet gives non-finite held-out metrics (mean Dice {dice}, slip \
             MSE {mse}); lower the learning rate {lr}"
        )));
    }
    Ok((dice, mse))
}

#[cfg(test)]
mod bad_input_tests {
    use super::*;

    fn refused(cfg: ToyConfig, field: &str) {
        let e = fit_toy(&Arch::min(), &cfg).unwrap_err().to_string();
        assert!(e.contains(field), "{field}: {e}");
    }

    #[test]
    fn degenerate_or_huge_toy_configs_are_refused_without_allocating() {
        let d = ToyConfig::default;
        refused(
            ToyConfig {
                size: usize::MAX,
                batch: 2,
                ..d()
            },
            "size",
        );
        refused(
            ToyConfig {
                size: 100_000_000,
                batch: 2,
                ..d()
            },
            "size",
        );
        refused(
            ToyConfig {
                batch: 1_000_000_000_000,
                ..d()
            },
            "batch",
        );
        refused(ToyConfig { batch: 1, ..d() }, "batch");
        refused(ToyConfig { lr: 1e30, ..d() }, "lr");
        refused(
            ToyConfig {
                lr: f64::NAN,
                ..d()
            },
            "lr",
        );
        assert!(toy_batch(usize::MAX, 0, 0, 1).is_err());
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The refusal gives the means, not the sums over the held-out images (a diverged run's
    /// message read "dice 16.07", a Dice score outside [0, 1]).
    #[test]
    fn held_out_metrics_are_means_and_a_non_finite_one_is_refused_with_means() {
        assert_eq!(held_out_means(12.0, 3.0, 16, 0.1).unwrap(), (0.75, 0.1875));
        let e = held_out_means(16.0, f64::INFINITY, 32, 1.0)
            .unwrap_err()
            .to_string();
        assert!(e.contains("mean Dice 0.5,") && e.contains("MSE inf"), "{e}");
        assert!(e.contains("learning rate 1"), "{e}");
    }
}

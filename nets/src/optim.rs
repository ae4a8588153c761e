//! Optimizers (SGD with momentum, Adam) over a supernet's parameters and the cosine schedule.

use crate::error::{NetsError, Result};
use crate::supernet::Supernet;

/// Learning rate at step `t` of `total` under cosine decay from `lr0` to `lr_min`.
pub fn cosine_lr(lr0: f64, lr_min: f64, t: usize, total: usize) -> f64 {
    if total == 0 {
        return lr0;
    }
    let p = (t.min(total) as f64) / total as f64;
    lr_min + 0.5 * (lr0 - lr_min) * (1.0 + (std::f64::consts::PI * p).cos())
}

fn check_lr(lr: f64) -> Result<()> {
    if !(lr.is_finite() && lr >= 0.0) {
        return Err(NetsError::Param(format!(
            "learning rate {lr} must be finite and ≥ 0"
        )));
    }
    Ok(())
}

/// SGD with (heavy-ball) momentum and decoupled-free L2 weight decay: v ← μv + g + λw, w ← w − ηv.
#[derive(Clone, Debug)]
pub struct Sgd {
    /// Momentum μ.
    pub momentum: f32,
    /// Weight decay λ.
    pub weight_decay: f32,
    velocity: Vec<Vec<f32>>,
}

impl Sgd {
    /// A new optimizer; state is created on the first step.
    pub fn new(momentum: f32, weight_decay: f32) -> Self {
        Self {
            momentum,
            weight_decay,
            velocity: Vec::new(),
        }
    }

    /// One update with learning rate `lr` from the accumulated gradients.
    pub fn step(&mut self, net: &mut Supernet, lr: f64) -> Result<()> {
        check_lr(lr)?;
        let (mu, wd, lr) = (self.momentum, self.weight_decay, lr as f32);
        let vel = &mut self.velocity;
        let mut i = 0;
        net.visit(&mut |_, p| {
            if vel.len() <= i {
                vel.push(vec![0.0; p.len()]);
            }
            for ((w, g), v) in p.value.iter_mut().zip(&p.grad).zip(vel[i].iter_mut()) {
                *v = mu * *v + g + wd * *w;
                *w -= lr * *v;
            }
            i += 1;
        });
        Ok(())
    }
}

/// Adam (Kingma & Ba 2015) with bias correction.
#[derive(Clone, Debug)]
pub struct Adam {
    /// First-moment decay β1.
    pub beta1: f64,
    /// Second-moment decay β2.
    pub beta2: f64,
    /// Denominator floor ε.
    pub eps: f64,
    t: i32,
    m: Vec<Vec<f32>>,
    v: Vec<Vec<f32>>,
}

impl Default for Adam {
    fn default() -> Self {
        Self {
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-8,
            t: 0,
            m: Vec::new(),
            v: Vec::new(),
        }
    }
}

/// The moments and step count of an [`Adam`], for checkpoints.
#[derive(Clone, Debug, PartialEq)]
pub struct AdamState {
    /// Steps taken.
    pub t: i32,
    /// First moments, one vector per parameter in `Supernet::visit` order.
    pub m: Vec<Vec<f32>>,
    /// Second moments, same layout.
    pub v: Vec<Vec<f32>>,
}

impl Adam {
    /// Its moments and step count.
    pub fn state(&self) -> AdamState {
        AdamState {
            t: self.t,
            m: self.m.clone(),
            v: self.v.clone(),
        }
    }

    /// Restores moments and step count saved by [`Adam::state`].
    pub fn set_state(&mut self, s: AdamState) -> Result<()> {
        if s.m.len() != s.v.len() || s.m.iter().zip(&s.v).any(|(a, b)| a.len() != b.len()) {
            return Err(NetsError::Checkpoint(
                "Adam state: first and second moments differ in shape".into(),
            ));
        }
        self.t = s.t;
        self.m = s.m;
        self.v = s.v;
        Ok(())
    }

    /// One update with learning rate `lr` from the accumulated gradients.
    pub fn step(&mut self, net: &mut Supernet, lr: f64) -> Result<()> {
        check_lr(lr)?;
        self.t += 1;
        let (b1, b2) = (self.beta1 as f32, self.beta2 as f32);
        let c1 = 1.0 - self.beta1.powi(self.t);
        let c2 = 1.0 - self.beta2.powi(self.t);
        let step = (lr * c2.sqrt() / c1) as f32;
        let eps = (self.eps * c2.sqrt()) as f32;
        let (ms, vs) = (&mut self.m, &mut self.v);
        let mut i = 0;
        net.visit(&mut |_, p| {
            if ms.len() <= i {
                ms.push(vec![0.0; p.len()]);
                vs.push(vec![0.0; p.len()]);
            }
            for (((w, &g), m), v) in p
                .value
                .iter_mut()
                .zip(&p.grad)
                .zip(ms[i].iter_mut())
                .zip(vs[i].iter_mut())
            {
                *m = b1 * *m + (1.0 - b1) * g;
                *v = b2 * *v + (1.0 - b2) * g * g;
                *w -= step * *m / (v.sqrt() + eps);
            }
            i += 1;
        });
        Ok(())
    }
}

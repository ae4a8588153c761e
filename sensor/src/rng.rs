//! Deterministic random streams: one ChaCha stream per (seed, index, column), so results do not
//! depend on the number of threads.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha12Rng;

/// A ChaCha12 generator for item `index`, sub-stream `sub` of run `seed`.
pub fn stream_rng(seed: u64, index: u64, sub: u64) -> ChaCha12Rng {
    // SplitMix64 of (seed, index) gives the key; `sub` selects the ChaCha stream.
    let mut z = seed ^ index.wrapping_mul(0x9E37_79B9_7F4A_7C15).rotate_left(17);
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^= z >> 31;
    let mut rng = ChaCha12Rng::seed_from_u64(z);
    rng.set_stream(sub);
    rng
}

/// A standard normal draw: `rand_distr`'s ziggurat (Marsaglia & Tsang, "The Ziggurat Method
/// for Generating Random Variables", J. Stat. Softw. 5(8), 2000), one 64-bit draw and a table
/// compare for nearly every value. Box–Muller's `ln`, `sqrt` and `cos` per value, two values a
/// pixel, took 9 % of the camera chain's forward on paper-size frames (docs/bench/chain.md).
pub fn standard_normal<R: Rng>(rng: &mut R) -> f64 {
    rng.sample(rand_distr::StandardNormal)
}

/// A Poisson draw of mean `mu` ≥ 0: inversion below 10, Hörmann's PTRS above
/// (W. Hörmann, "The transformed rejection method for generating Poisson random variables",
/// Insurance: Mathematics and Economics 12, 1993).
pub(crate) fn poisson<R: Rng>(rng: &mut R, mu: f64) -> f64 {
    if mu <= 0.0 {
        return 0.0;
    }
    if mu < 10.0 {
        let mut p = (-mu).exp();
        let mut s = p;
        let u: f64 = rng.random::<f64>();
        let mut k = 0.0;
        while u > s && k < 1000.0 {
            k += 1.0;
            p *= mu / k;
            s += p;
        }
        return k;
    }
    let smu = mu.sqrt();
    let b = 0.931 + 2.53 * smu;
    let a = -0.059 + 0.02483 * b;
    let inv_alpha = 1.1239 + 1.1328 / (b - 3.4);
    let vr = 0.9277 - 3.6224 / (b - 2.0);
    let log_mu = mu.ln();
    loop {
        let u = rng.random::<f64>() - 0.5;
        let v: f64 = rng.random::<f64>();
        let us = 0.5 - u.abs();
        let k = ((2.0 * a / us + b) * u + mu + 0.43).floor();
        if us >= 0.07 && v <= vr {
            return k;
        }
        if k < 0.0 || (us < 0.013 && v > us) {
            continue;
        }
        if v.ln() + inv_alpha.ln() - (a / (us * us) + b).ln()
            <= -mu + k * log_mu - libm::lgamma(k + 1.0)
        {
            return k;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn poisson_mean_and_variance_match() {
        // Poisson: mean = variance = mu, on both sides of the algorithm switch.
        for &mu in &[0.3, 4.0, 25.0, 3000.0] {
            let mut rng = stream_rng(7, 1, 0);
            let n = 40_000;
            let xs: Vec<f64> = (0..n).map(|_| poisson(&mut rng, mu)).collect();
            let m = xs.iter().sum::<f64>() / n as f64;
            let v = xs.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1) as f64;
            let se_m = (mu / n as f64).sqrt();
            assert!((m - mu).abs() < 5.0 * se_m, "mu {mu}: mean {m}");
            let se_v = mu * (2.0 / n as f64).sqrt() * (1.0 + 1.0 / mu).sqrt();
            assert!((v - mu).abs() < 5.0 * se_v, "mu {mu}: var {v}");
        }
    }

    #[test]
    fn normal_draws_have_the_standard_normal_moments_and_tails() {
        // Mean 0, variance 1, kurtosis 3, and the tail masses Φ(−x) at 1, 2 and 3 σ, each
        // within 5 standard errors: a sampler of the wrong shape or scale fails one of them.
        let n = 400_000;
        let mut rng = stream_rng(11, 4, 2);
        let xs: Vec<f64> = (0..n).map(|_| standard_normal(&mut rng)).collect();
        let nf = n as f64;
        let m = xs.iter().sum::<f64>() / nf;
        let v = xs.iter().map(|x| x * x).sum::<f64>() / nf;
        let k = xs.iter().map(|x| x.powi(4)).sum::<f64>() / nf;
        assert!(m.abs() < 5.0 / nf.sqrt(), "mean {m}");
        assert!((v - 1.0).abs() < 5.0 * (2.0 / nf).sqrt(), "variance {v}");
        // Var(x⁴) = E x⁸ − 9 = 105 − 9 for a standard normal.
        assert!((k - 3.0).abs() < 5.0 * (96.0 / nf).sqrt(), "kurtosis {k}");
        for t in [1.0, 2.0, 3.0] {
            let p = 0.5 * statrs::function::erf::erfc(t / std::f64::consts::SQRT_2);
            for sign in [1.0, -1.0] {
                let q = xs.iter().filter(|&&x| sign * x > t).count() as f64 / nf;
                let se = (p * (1.0 - p) / nf).sqrt();
                assert!((q - p).abs() < 5.0 * se, "P(±x > {t}) {q} against {p}");
            }
        }
    }

    #[test]
    fn streams_are_reproducible_and_distinct() {
        let a: Vec<f64> = (0..4)
            .map(|_| standard_normal(&mut stream_rng(1, 2, 3)))
            .collect();
        let b: f64 = standard_normal(&mut stream_rng(1, 2, 3));
        assert_eq!(a[0], b);
        let c: f64 = standard_normal(&mut stream_rng(1, 3, 3));
        assert_ne!(b, c);
    }
}

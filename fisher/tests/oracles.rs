//! Closed-form oracles (docs: ../shared/reference/oracles.md) and stability proptests.

use faer::Mat;
use nanoeye_fisher::{
    Compactness, DepthFisher, DesignLoss, Distinctness, FisherNoise, Precision, PsfStack,
    depth_fisher, fisher_matrix,
};
use nanoeye_sensor::BoxIntegrator;
use proptest::prelude::*;

/// Pixel-sampled normalized 2D Gaussian of std `s` (m) on an n×n grid of pitch `d` (m).
fn gaussian(n: usize, d: f64, s: f64) -> Mat<f64> {
    let c = (n as f64 - 1.0) / 2.0;
    let a = d * d / (std::f64::consts::TAU * s * s);
    Mat::from_fn(n, n, |i, j| {
        let (x, y) = ((j as f64 - c) * d, (i as f64 - c) * d);
        a * (-(x * x + y * y) / (2.0 * s * s)).exp()
    })
}

#[test]
fn gaussian_spot_fisher_is_n_over_s2() {
    let (d, s, n_ph) = (1e-7, 5e-7, 2500.0);
    let g = gaussian(61, d, s);
    let stack = PsfStack::from_f64(&[g.clone(), g], &[0.0, 1e-3], d).unwrap();
    let noise = FisherNoise {
        photons: n_ph,
        ..FisherNoise::default()
    };
    let f = fisher_matrix(&stack, 0, &noise).unwrap();
    let want = n_ph / (s * s);
    for (i, v) in [f[0][0], f[1][1]].into_iter().enumerate() {
        assert!(
            (v / want - 1.0).abs() < 0.01,
            "F[{i}{i}] = {v}, want {want}"
        );
    }
    assert!(f[0][1].abs() < 1e-6 * want && f[2][2] == 0.0);
}

#[test]
fn defocusing_gaussian_fzz_matches_closed_form() {
    // s(z) = s0 √(1+u²), u = z/z_R: F_zz = 4 N u² / (z_R² (1+u²)²).
    let (d, s0, zr, n_ph): (f64, f64, f64, f64) = (1e-7, 4e-7, 1e-4, 1e4);
    for u in [0.5f64, 1.0, 2.0] {
        let z = u * zr;
        let h = 1e-3 * zr;
        let planes: Vec<Mat<f64>> = [z - h, z, z + h]
            .iter()
            .map(|&zz| gaussian(121, d, s0 * (1.0 + (zz / zr).powi(2)).sqrt()))
            .collect();
        let stack = PsfStack::from_f64(&planes, &[z - h, z, z + h], d).unwrap();
        let noise = FisherNoise {
            photons: n_ph,
            ..FisherNoise::default()
        };
        let f = depth_fisher(&stack, &noise).unwrap()[1];
        let want = 4.0 * n_ph * u * u / (zr * zr * (1.0 + u * u).powi(2));
        assert!((f / want - 1.0).abs() < 0.01, "u {u}: {f} vs {want}");
        // S25 is the zz entry of the S3 matrix.
        let m = fisher_matrix(&stack, 1, &noise).unwrap();
        assert!((m[2][2] / f - 1.0).abs() < 1e-12);
    }
}

fn bin(m: &Mat<f64>, f: usize) -> Mat<f64> {
    let n = m.nrows();
    let op = BoxIntegrator::new(n, n, 1.0, f as f64, 1.0).unwrap();
    let m32 = Mat::from_fn(n, n, |i, j| m[(i, j)] as f32);
    let y = op.forward(&m32).unwrap();
    Mat::from_fn(y.nrows(), y.ncols(), |i, j| f64::from(y[(i, j)]))
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    #[test]
    fn binning_never_increases_poisson_fisher_information(
        a in proptest::collection::vec(1e-3f64..100.0, 144),
        b in proptest::collection::vec(1e-3f64..100.0, 144),
        factor in 2usize..5,
    ) {
        // Two planes 1 mm apart; pure Poisson (σ² = 0, negligible floor).
        let p0 = Mat::from_fn(12, 12, |i, j| a[j * 12 + i]);
        let p1 = Mat::from_fn(12, 12, |i, j| b[j * 12 + i]);
        let noise = FisherNoise { photons: 1.0, noise_var: 0.0, min_var: 1e-15, ..FisherNoise::default() };
        let fine = PsfStack::from_f64(&[p0.clone(), p1.clone()], &[0.0, 1e-3], 1e-6).unwrap();
        // Crop to a multiple of the factor so both grids cover the same pixels.
        let m = 12 / factor * factor;
        let crop = |p: &Mat<f64>| Mat::from_fn(m, m, |i, j| p[(i + (12 - m) / 2, j + (12 - m) / 2)]);
        let (c0, c1) = (crop(&p0), crop(&p1));
        let fine_c = PsfStack::from_f64(&[c0.clone(), c1.clone()], &[0.0, 1e-3], 1e-6).unwrap();
        let coarse = PsfStack::from_f64(&[bin(&c0, factor), bin(&c1, factor)], &[0.0, 1e-3], 1e-6 * factor as f64).unwrap();
        let ff = depth_fisher(&fine_c, &noise).unwrap();
        let fc = depth_fisher(&coarse, &noise).unwrap();
        prop_assert!(fc[0] <= ff[0] * (1.0 + 1e-5), "{} > {}", fc[0], ff[0]);
        prop_assert!(depth_fisher(&fine, &noise).unwrap()[0] >= ff[0]);
    }

    #[test]
    fn zero_and_constant_psfs_give_finite_losses_and_gradients(
        level in prop_oneof![Just(0.0f64), 1e-300f64..1e-200, 1e-6f64..1e6],
        k in 2usize..5,
        photons in prop_oneof![Just(1e-3f64), 1e-3f64..1e12],
    ) {
        let planes: Vec<Mat<f64>> = (0..k).map(|_| Mat::from_fn(7, 7, |_, _| level)).collect();
        let depths: Vec<f64> = (0..k).map(|i| 0.017 + 1.5e-3 * i as f64).collect();
        let stack = PsfStack::from_f64(&planes, &depths, 3e-6).unwrap();
        let noise = FisherNoise { photons, ..FisherNoise::default() };
        let losses: Vec<Box<dyn DesignLoss>> = vec![
            Box::new(Precision { noise }),
            Box::new(DepthFisher { noise }),
            Box::new(Distinctness::default()),
            Box::new(Compactness::default()),
        ];
        for l in &losses {
            let (v, g) = l.value_and_grad(&stack).unwrap();
            prop_assert!(v.is_finite());
            for p in &g.planes { for j in 0..7 { for i in 0..7 { prop_assert!(p[(i, j)].is_finite()); } } }
        }
    }
}

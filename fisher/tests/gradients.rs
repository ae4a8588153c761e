//! Every loss gradient against central finite differences.

use faer::Mat;
use nanoeye_fisher::{
    Compactness, DepthFisher, DesignLoss, Distinctness, FisherNoise, Precision, PsfStack,
    optical_embedding,
};

/// A smooth, asymmetric 3-plane stack (values ~1e-2) that changes with depth.
fn stack() -> PsfStack {
    let planes: Vec<Mat<f64>> = (0..4)
        .map(|k| {
            let s = 1.3 + 0.4 * k as f64;
            Mat::from_fn(9, 8, |i, j| {
                let (x, y) = (j as f64 - 3.6 + 0.3 * k as f64, i as f64 - 4.1);
                0.02 * (-(x * x + 0.6 * y * y + 0.3 * x * y) / (2.0 * s * s)).exp() + 1e-4
            })
        })
        .collect();
    PsfStack::from_f64(&planes, &[0.017, 0.0185, 0.0205, 0.022], 3e-6).unwrap()
}

fn check(loss: &dyn DesignLoss, name: &str) {
    let s = stack();
    let (_, g) = loss.value_and_grad(&s).unwrap();
    let mut worst = 0.0f64;
    for k in 0..s.len() {
        for &p in &[0usize, 10, 31, 40, 55, 71] {
            let v = s.plane(k)[p];
            let h = 1e-5 * v;
            let mut a = s.clone();
            a.plane_mut(k)[p] = v + h;
            let mut b = s.clone();
            b.plane_mut(k)[p] = v - h;
            let fd = (loss.value(&a).unwrap() - loss.value(&b).unwrap()) / (2.0 * h);
            let an = g.planes[k][(p % 9, p / 9)];
            let scale = fd.abs().max(an.abs()).max(1e-8);
            worst = worst.max((fd - an).abs() / scale);
            assert!(
                (fd - an).abs() < 1e-4 * scale + 1e-9,
                "{name} plane {k} px {p}: fd {fd} vs {an}"
            );
        }
    }
    eprintln!("{name}: worst relative FD error {worst:.2e}");
}

#[test]
fn precision_gradient_matches_fd() {
    check(
        &Precision {
            noise: FisherNoise {
                photons: 1e4,
                noise_var: 4.0,
                ..FisherNoise::default()
            },
        },
        "precision",
    );
}

#[test]
fn depth_fisher_gradient_matches_fd() {
    check(
        &DepthFisher {
            noise: FisherNoise {
                photons: 1e4,
                noise_var: 4.0,
                ..FisherNoise::default()
            },
        },
        "depth",
    );
}

#[test]
fn distinctness_gradient_matches_fd() {
    check(&Distinctness::default(), "distinctness");
}

#[test]
fn compactness_gradient_matches_fd() {
    check(&Compactness::default(), "compactness");
}

#[test]
fn embedding_terms_and_gradient() {
    let i0 = Mat::from_fn(6, 5, |i, j| 50.0 + (i * 3 + j) as f32);
    let i1 = Mat::from_fn(6, 5, |i, j| i0[(i, j)] + 2.0 * (i as f32 - 2.5));
    let i2 = Mat::from_fn(6, 5, |i, j| {
        i0[(i, j)] + 1.5 * (j as f32 - 2.0) + 0.5 * (i as f32 - 2.5)
    });
    let h = [0.1, 0.2];
    let (t, g) = optical_embedding(&i0, &i1, &i2, h, 3.0, 1e-9, 1.0, 2.0).unwrap();
    // Closed form: F_ij = Σ ΔI_i ΔI_j / (h_i h_j (I0 + σ²)).
    let (mut f11, mut f12) = (0.0, 0.0);
    for j in 0..5 {
        for i in 0..6 {
            let w = 1.0 / (f64::from(i0[(i, j)]) + 3.0);
            let d1 = f64::from(i1[(i, j)] - i0[(i, j)]) / h[0];
            let d2 = f64::from(i2[(i, j)] - i0[(i, j)]) / h[1];
            f11 += d1 * d1 * w;
            f12 += d1 * d2 * w;
        }
    }
    assert!((t.f11 / f11 - 1.0).abs() < 1e-6 && (t.f12 / f12 - 1.0).abs() < 1e-6);
    assert!((t.cos_phi - t.f12 / (t.f11 * t.f22).sqrt()).abs() < 1e-9);
    assert!(t.cos_phi.abs() <= 1.0);
    let total = |a: &Mat<f32>, b: &Mat<f32>, c: &Mat<f32>| {
        let (t, _) = optical_embedding(a, b, c, h, 3.0, 1e-9, 1.0, 2.0).unwrap();
        t.l_sens + 2.0 * t.l_orth
    };
    for (which, grad) in [(0, &g.d_i0), (1, &g.d_i1), (2, &g.d_i2)] {
        for &(r, c) in &[(0, 0), (3, 2), (5, 4)] {
            let mut ims = [i0.clone(), i1.clone(), i2.clone()];
            let mut jms = ims.clone();
            ims[which][(r, c)] += 0.05;
            jms[which][(r, c)] -= 0.05;
            let fd = (total(&ims[0], &ims[1], &ims[2]) - total(&jms[0], &jms[1], &jms[2])) / 0.1;
            let an = grad[(r, c)];
            assert!(
                (fd - an).abs() < 2e-3 * an.abs().max(1e-4),
                "image {which} ({r},{c}): {fd} vs {an}"
            );
        }
    }
}

#[test]
fn init_loss_gradient_matches_fd() {
    use nanoeye_fisher::InitLoss;
    let loss = InitLoss {
        precision: Precision {
            noise: FisherNoise {
                photons: 1e4,
                noise_var: 4.0,
                ..FisherNoise::default()
            },
        },
        ..InitLoss::default()
    };
    let s = stack();
    let lv = [0.3, -0.2, 0.1];
    let e = loss.evaluate(&s, &lv).unwrap();
    for k in 0..s.len() {
        for &p in &[10usize, 40] {
            let v = s.plane(k)[p];
            let h = 1e-5 * v;
            let mut a = s.clone();
            a.plane_mut(k)[p] = v + h;
            let mut b = s.clone();
            b.plane_mut(k)[p] = v - h;
            let fd = (loss.evaluate(&a, &lv).unwrap().value
                - loss.evaluate(&b, &lv).unwrap().value)
                / (2.0 * h);
            let an = e.grad.planes[k][(p % 9, p / 9)];
            assert!(
                (fd - an).abs() < 1e-4 * fd.abs().max(an.abs()) + 1e-9,
                "plane {k} px {p}: {fd} vs {an}"
            );
        }
    }
}

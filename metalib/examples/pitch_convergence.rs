//! Accuracy map of the sweep's truncation: for each pitch s and fill d/s, the worst |Δτ| and
//! |Δφ| over heights 100…1500 nm (step 100) of truncations N against a high-harmonic
//! reference, default rule (NV).
//! Usage: cargo run --release -p nanoeye-metalib --example pitch_convergence -- N_REF N1,N2,…
//! [PITCH_NM ...]
use nanoeye_metalib::material::Materials;
use nanoeye_metalib::rcwa::{CellSpec, DEFAULT_RULE, LayerModes};
use num_complex::Complex64;
use rayon::prelude::*;

/// Worst (|Δτ|, |Δφ|, |Δφ| where τ_ref ≥ 0.5) over heights of `n` against `reference`.
fn worst(spec: &CellSpec, heights: &[f64], reference: &[(f64, Complex64)]) -> (f64, f64, f64) {
    let m = LayerModes::new(spec).expect("modes");
    let mut w = (0.0f64, 0.0f64, 0.0f64);
    for (&h, &(tau_ref, t_ref)) in heights.iter().zip(reference) {
        let r = m.at_height(h).expect("height");
        let dphi = (r.t / t_ref).arg().abs();
        w.0 = w.0.max((r.transmittance - tau_ref).abs());
        w.1 = w.1.max(dphi);
        if tau_ref >= 0.5 {
            w.2 = w.2.max(dphi);
        }
    }
    w
}

fn main() {
    faer::set_global_parallelism(faer::Par::Seq);
    let a: Vec<String> = std::env::args().skip(1).collect();
    let n_ref: usize = a.first().and_then(|v| v.parse().ok()).unwrap_or(16);
    let ns: Vec<usize> = a
        .get(1)
        .map(|v| v.split(',').filter_map(|x| x.parse().ok()).collect())
        .unwrap_or_else(|| vec![10, 14]);
    let pitches: Vec<f64> = if a.len() > 2 {
        a[2..].iter().filter_map(|v| v.parse().ok()).collect()
    } else {
        vec![100.0, 200.0, 300.0, 400.0, 530.0, 700.0, 850.0, 1000.0]
    };
    let fractions = [0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9];
    let heights: Vec<f64> = (1..=15).map(|k| k as f64 * 100e-9).collect();
    let jobs: Vec<(f64, f64)> = pitches
        .iter()
        .flat_map(|&s| fractions.iter().map(move |&f| (s, f)))
        .collect();
    let t0 = std::time::Instant::now();
    let rows: Vec<Vec<(f64, f64, f64)>> = jobs
        .par_iter()
        .map(|&(s, f)| {
            let spec = |n: usize| CellSpec {
                wavelength_m: 940e-9,
                pitch_m: s * 1e-9,
                diameter_m: f * s * 1e-9,
                materials: Materials::default(),
                harmonics: n,
                rule: DEFAULT_RULE,
            };
            let m = LayerModes::new(&spec(n_ref)).expect("reference");
            let reference: Vec<(f64, Complex64)> = heights
                .iter()
                .map(|&h| {
                    let r = m.at_height(h).expect("reference height");
                    (r.transmittance, r.t)
                })
                .collect();
            ns.iter()
                .map(|&n| worst(&spec(n), &heights, &reference))
                .collect()
        })
        .collect();
    println!(
        "Reference N = {n_ref}; worst over h = 100..1500 nm step 100; {:.0} s",
        t0.elapsed().as_secs_f64()
    );
    let mut head = String::from("| s (nm) | d/s |");
    let mut rule = String::from("|---|---|");
    for n in &ns {
        head += &format!(" N={n} max|Δτ| | N={n} max|Δφ| | N={n} max|Δφ| (τ≥0.5) |");
        rule += "---|---|---|";
    }
    println!("{head}\n{rule}");
    for ((s, f), r) in jobs.iter().zip(&rows) {
        let mut line = format!("| {s} | {f} |");
        for w in r {
            line += &format!(" {:.1e} | {:.1e} | {:.1e} |", w.0, w.1, w.2);
        }
        println!("{line}");
    }
}

//! Convergence study: τ and phase vs harmonics at h = 700 nm, s = 530 nm for d = 100, 200, 275 nm,
//! both rules, against a high-harmonic reference; plus time per (s, d) eigen-solve and per height.
//! Usage: cargo run -p nanoeye-metalib --example rcwa_convergence -- [N_REF] [N_MAX]
use nanoeye_metalib::material::Materials;
use nanoeye_metalib::rcwa::{CellSpec, LayerModes, Rule};
use std::time::Instant;

fn main() {
    faer::set_global_parallelism(faer::Par::Seq);
    let args: Vec<usize> = std::env::args()
        .skip(1)
        .filter_map(|a| a.parse().ok())
        .collect();
    let n_ref = args.first().copied().unwrap_or(20);
    let n_max = args.get(1).copied().unwrap_or(12);
    let h = 700e-9;
    println!(
        "| rule | N | modes | d (nm) | tau | phase (rad) | |dtau| | |dphi| (rad) | eigen+interfaces (ms) | per height (us) |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|");
    for rule in [Rule::Laurent, Rule::Nv] {
        for d in [100.0, 200.0, 275.0] {
            let spec = |n| CellSpec {
                wavelength_m: 940e-9,
                pitch_m: 530e-9,
                diameter_m: d * 1e-9,
                materials: Materials::default(),
                harmonics: n,
                rule,
            };
            let reference = LayerModes::new(&spec(n_ref)).unwrap().at_height(h).unwrap();
            for n in 1..=n_max {
                let t0 = Instant::now();
                let reps = 3;
                let mut modes = None;
                for _ in 0..reps {
                    modes = Some(LayerModes::new(&spec(n)).unwrap());
                }
                let t_eig = t0.elapsed().as_secs_f64() / reps as f64;
                let modes = modes.unwrap();
                let t1 = Instant::now();
                let hs: Vec<f64> = (10..=150).map(|k| k as f64 * 10e-9).collect();
                for &hh in &hs {
                    std::hint::black_box(modes.at_height(hh).unwrap());
                }
                let t_h = t1.elapsed().as_secs_f64() / hs.len() as f64;
                let r = modes.at_height(h).unwrap();
                let dphi = (r.t / reference.t).arg().abs();
                println!(
                    "| {} | {n} | {} | {d} | {:.5} | {:.4} | {:.2e} | {:.2e} | {:.3} | {:.1} |",
                    rule.name(),
                    modes.mode_count(),
                    r.transmittance,
                    r.phase_rad,
                    (r.transmittance - reference.transmittance).abs(),
                    dphi,
                    t_eig * 1e3,
                    t_h * 1e6
                );
            }
            println!(
                "| {} | ref {n_ref} | | {d} | {:.5} | {:.4} | | | | |",
                rule.name(),
                reference.transmittance,
                reference.phase_rad
            );
        }
    }
}

//! Selection on a sweep directory without the CLI: `cargo run -p nanoeye-metalib --example
//! select_report -- SWEEP_DIR [H_NM S_NM]`; writes the figures to SWEEP_DIR/figures and prints the
//! selection of the marked pair.
use nanoeye_metalib::select::{Criteria, select_sweep, write_figures};

fn main() {
    let a: Vec<String> = std::env::args().skip(1).collect();
    let dir = std::path::PathBuf::from(
        a.first()
            .cloned()
            .unwrap_or_else(|| "/tmp/metalib_sweep_bench".into()),
    );
    let h: f64 = a.get(1).and_then(|v| v.parse().ok()).unwrap_or(700.0);
    let s: f64 = a.get(2).and_then(|v| v.parse().ok()).unwrap_or(530.0);
    let data = match nanoeye_metalib::sweep::load_sweep(&dir) {
        Ok(d) => d,
        Err(e) => {
            eprintln!("error: {e}");
            std::process::exit(1);
        }
    };
    let sel = select_sweep(&data, &Criteria::default());
    let viable: Vec<_> = sel
        .iter()
        .filter(|p| p.viable)
        .map(|p| ((p.height_m * 1e9).round(), (p.pitch_m * 1e9).round()))
        .collect();
    println!(
        "viable pairs: {} of {}: {viable:?}",
        viable.len(),
        sel.len()
    );
    for p in sel
        .iter()
        .filter(|p| ((p.height_m * 1e9) - h).abs() < 0.5 && ((p.pitch_m * 1e9) - s).abs() < 0.5)
    {
        println!(
            "{h}x{s}: viable {} d {:.1}-{:.1} nm coverage {:.3} rad ({:.3} x 2pi) min tau over 2pi {:.3}",
            p.viable,
            p.diameter_min_m * 1e9,
            p.diameter_max_m * 1e9,
            p.phase_coverage_rad,
            p.phase_coverage_rad / (2.0 * std::f64::consts::PI),
            p.min_transmittance_2pi
        );
    }
    match write_figures(
        &dir.join("figures"),
        &data,
        &sel,
        Some((h * 1e-9, s * 1e-9)),
        s * 1e-9,
    ) {
        Ok(f) => println!("figures: {f:?}"),
        Err(e) => eprintln!("figures: {e}"),
    }
}

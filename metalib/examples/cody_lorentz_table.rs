//! Prints the wavelength_nm,n,k rows of a model-evaluated material table
//! (metalib/data/materials/sputtered-2020-*.csv): the Cody–Lorentz parameters of
//! `nanoeye_metalib::cody_lorentz::SPUTTERED_2020` evaluated every 10 nm from 700 to 1200 nm.
//!
//! `cargo run --release -p nanoeye-metalib --example cody_lorentz_table -- NAME`

use nanoeye_metalib::cody_lorentz::SPUTTERED_2020;

fn main() {
    let name = std::env::args().nth(1).unwrap_or_default();
    let Some((_, model, _)) = SPUTTERED_2020.iter().find(|(n, _, _)| *n == name) else {
        let known: Vec<&str> = SPUTTERED_2020.iter().map(|(n, _, _)| *n).collect();
        eprintln!("usage: cody_lorentz_table NAME, NAME one of {known:?}");
        std::process::exit(2);
    };
    println!("wavelength_nm,n,k");
    for l in (700..=1200).step_by(10) {
        let (n, k) = model.nk_at(l as f64 * 1e-9).expect("valid model");
        println!("{l},{n:.6},{k:.6e}");
    }
}

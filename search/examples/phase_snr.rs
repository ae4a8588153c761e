//! How consistent a trained run's ∂L/∂φ is from batch to batch: the sandwich loss's gradient
//! in φ on `BATCHES` training batches at the run's final weights, φ and p̂, projected on the
//! Zernike modes of radial order 1..=ORDER; per mode the mean over batches, its standard error
//! and t = mean / SE, and the same for the per-sample gradient's total (the part of the
//! per-sample gradient's energy that its mean carries). A lens whose gradient has no mode with
//! a large |t| cannot descend at this batch size: its Adam steps are a random walk.
//! Usage: `cargo run --release -p nanoeye-search --example phase_snr -- RUN/checkpoint.bin
//! DATASET [ORDER] [BATCHES]` (docs/run.md, "A Zernike basis for φ's steps"). The chain is the
//! CLI's default one (Δ 1.5 µm, 0.1 ms, base pitch 3 µm or the dataset's if finer), as
//! `search train` builds it without chain flags.

use faer::Mat;
use nanoeye_datagen::render::Dataset;
use nanoeye_search::basis::Zernike;
use nanoeye_search::{CameraChain, ChainConfig, Trainer};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let (Some(ck), Some(dir)) = (args.get(1), args.get(2)) else {
        eprintln!("usage: phase_snr RUN/checkpoint.bin DATASET [ORDER] [BATCHES]");
        std::process::exit(2);
    };
    let order: u32 = args.get(3).and_then(|s| s.parse().ok()).unwrap_or(8);
    let batches: usize = args.get(4).and_then(|s| s.parse().ok()).unwrap_or(30);
    nanoeye_alloc::like_cli();
    let ds = Dataset::open(std::path::Path::new(dir)).expect("dataset");
    let mut cfg = ChainConfig::default();
    cfg.sensor.base_pitch = cfg
        .sensor
        .base_pitch
        .min(ds.manifest.rig.camera.pixel_pitch_m);
    let chain = CameraChain::for_dataset(&ds, cfg).expect("chain");
    let mut t = Trainer::from_checkpoint(&chain, &ds, std::path::Path::new(ck)).expect("run");
    let z = Zernike::new(order, *chain.aperture_grid()).expect("order");
    let n = chain.aperture_grid().n;
    let (m, b) = (z.len(), batches.max(2));
    let mut coefs = vec![vec![0.0; m]; b];
    let mut sum = Mat::<f64>::zeros(n, n);
    let mut energy = 0.0;
    let mut loss = 0.0;
    for (k, c) in coefs.iter_mut().enumerate() {
        // Batches of the steps after the run's last: frames and noise it has not stepped on.
        let (l, g) = t.phase_gradient(t.step + k).expect("gradient");
        loss += l / b as f64;
        *c = z.project(&g);
        energy += g.squared_norm_l2();
        sum += &g;
        eprint!("\rbatch {}/{b}", k + 1);
    }
    eprintln!();
    // ‖mean g‖² against the mean ‖g‖²: 1 for a gradient every batch agrees on, 1/B for
    // independent noise.
    let mean_energy = sum.squared_norm_l2() / (b * b) as f64;
    println!(
        "{{\"batches\":{b},\"order\":{order},\"loss\":{loss},\"pixel_mean_energy_fraction\":{},\"noise_only\":{}}}",
        mean_energy / (energy / b as f64),
        1.0 / b as f64
    );
    let mut rows: Vec<(usize, f64, f64)> = (0..m)
        .map(|j| {
            let mean = coefs.iter().map(|c| c[j]).sum::<f64>() / b as f64;
            let var = coefs.iter().map(|c| (c[j] - mean).powi(2)).sum::<f64>() / (b as f64 - 1.0);
            (j, mean, (var / b as f64).sqrt())
        })
        .collect();
    rows.sort_by(|x, y| (y.1 / y.2).abs().total_cmp(&(x.1 / x.2).abs()));
    println!("n\tm\tmean\tse\tt");
    for (j, mean, se) in rows {
        let (zn, zm) = z.index(j);
        println!("{zn}\t{zm}\t{mean:.4e}\t{se:.4e}\t{:.2}", mean / se);
    }
}

//! The initialization loop on a small optics model: L_init decreases, checkpoints round-trip,
//! and a resumed run continues exactly where the uninterrupted one would be.

use nanoeye_fisher::nanoeye_optics::{ApertureGrid, AsmPsf, Hyperbolic, PhaseProfile, PsfConfig};
use nanoeye_fisher::{FisherNoise, InitConfig, InitState, init_step};

fn setup() -> (ApertureGrid, AsmPsf, InitConfig) {
    // 0.3 mm aperture, 3 µm samples (slow lens: f-number ≈ 6.7, phase well sampled), 15 px window.
    let grid = ApertureGrid::new(0.3e-3, 3e-6).unwrap();
    let model = AsmPsf::new(
        PsfConfig {
            pitch_m: 3e-6,
            window_px: 15,
            ..PsfConfig::default()
        },
        grid,
    )
    .unwrap();
    let cfg = InitConfig {
        depths_m: vec![19e-3, 22e-3, 25e-3],
        sensor_pitch_m: 6e-6,
        lr_phase: 0.1,
        lr_log_var: 0.05,
        noise: FisherNoise {
            photons: 2e4,
            noise_var: 16.0,
            ..FisherNoise::default()
        },
    };
    (grid, model, cfg)
}

#[test]
fn loss_decreases_and_checkpoint_resumes_exactly() {
    let (grid, model, cfg) = setup();
    let phase = Hyperbolic::default().phase_map(&grid).unwrap().phase_rad;
    let mut a = InitState::new(phase);
    let first = init_step(&model, &grid, &cfg, &mut a).unwrap();
    // S6's balancing presumes every L_k > 0 (its optimum is e^{s_k} = L_k); L_prec is in µm²
    // for this reason, and a useful lens must give a positive value there.
    assert!(
        first.terms.iter().all(|&t| t > 0.0),
        "terms {:?}",
        first.terms
    );
    for _ in 0..5 {
        init_step(&model, &grid, &cfg, &mut a).unwrap();
    }
    let dir = tempfile::tempdir().unwrap();
    a.save(dir.path(), &cfg).unwrap();
    let (mut b, cfg_b) = InitState::load(dir.path()).unwrap();
    assert_eq!(cfg_b, cfg);
    assert_eq!(b.iteration, a.iteration);
    assert_eq!(b.phase, a.phase);
    let ra = init_step(&model, &grid, &cfg, &mut a).unwrap();
    let rb = init_step(&model, &grid, &cfg, &mut b).unwrap();
    assert_eq!(ra, rb);
    assert_eq!(a.phase, b.phase);
    assert!(
        ra.l_init < first.l_init,
        "L_init {} -> {}",
        first.l_init,
        ra.l_init
    );
    assert!(ra.l_init.is_finite());
    assert!(ra.terms.iter().all(|&t| t > 0.0), "terms {:?}", ra.terms);
}

/// The phase map `fisher init` writes has the mode `File::create` gives under this umask,
/// not a temporary file's 0600.
#[cfg(unix)]
#[test]
fn written_phase_map_has_the_mode_file_create_gives() {
    use std::os::unix::fs::PermissionsExt;
    let dir = tempfile::tempdir().unwrap();
    let mode = |p: &std::path::Path| std::fs::metadata(p).unwrap().permissions().mode() & 0o777;
    let plain = dir.path().join("plain");
    std::fs::write(&plain, b"x").unwrap();
    let out = dir.path().join("phase.npy");
    nanoeye_fisher::write_npy(&out, &faer::Mat::zeros(3, 3)).unwrap();
    assert_eq!(mode(&out), mode(&plain));
}

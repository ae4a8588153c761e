//! The optical-embedding objective through the camera chain (S15, C.2): its gradient against
//! central differences in φ and p̂, its exact scaling with the light, the triplets read from a
//! variational dataset, and the embedding run's descent, kill-and-resume bits and refusals.

use faer::Mat;
use nanoeye_datagen::render::{Dataset, DatasetOptions, LayerSpec, RenderSet, SceneSource};
use nanoeye_gaze::Rig;
use nanoeye_optics::PhaseMap;
use nanoeye_search::embed::triplets;
use nanoeye_search::{
    CameraChain, ChainConfig, EmbedConfig, EmbedWeights, Embedder, LensSpec, embedding_loss,
};

fn render(dir: &std::path::Path, set: RenderSet, n: usize) -> Dataset {
    nanoeye_datagen::render::write_dataset(&DatasetOptions {
        set,
        n,
        seed: 5,
        width_px: 80,
        height_px: 50,
        spp: 1,
        out_dir: dir.to_path_buf(),
        rig: Rig::default(),
        source: SceneSource::Procedural,
        progress: false,
        layers: LayerSpec::default(),
        blink_fraction: 0.0,
    })
    .unwrap();
    Dataset::open(dir).unwrap()
}

/// Coarse but fast (as tests/chain.rs): a 10 µm metasurface grid, 48 µm base pixels.
fn chain_cfg() -> ChainConfig {
    let mut c = ChainConfig {
        aperture_step_m: 10e-6,
        ..ChainConfig::default()
    };
    c.sensor.base_pitch = 48e-6;
    c.radiometry.exposure_s = 0.1e-3 / 256.0;
    c
}

fn hyperbolic(c: &CameraChain) -> PhaseMap {
    LensSpec::Hyperbolic
        .phase_map(c.aperture_grid(), 940e-9, 2e-3)
        .unwrap()
}

fn shifted(map: &PhaseMap, dir: &Mat<f64>, s: f64) -> PhaseMap {
    let n = map.grid.n;
    let ph = Mat::from_fn(n, n, |i, j| map.phase_rad[(i, j)] + s * dir[(i, j)]);
    PhaseMap::new(map.grid, ph, map.amplitude.clone()).unwrap()
}

fn dot(a: &Mat<f64>, b: &Mat<f64>) -> f64 {
    (0..a.nrows())
        .flat_map(|i| (0..a.ncols()).map(move |j| (i, j)))
        .map(|(i, j)| a[(i, j)] * b[(i, j)])
        .sum()
}

#[test]
fn embedding_gradient_matches_central_differences_and_scales_with_the_light() {
    let d = tempfile::tempdir().unwrap();
    let ds = render(d.path(), RenderSet::Variational, 2);
    let trips = triplets(&ds).unwrap();
    assert_eq!(trips.len(), 2);
    for (t, tr) in trips.iter().enumerate() {
        let roles: Vec<&str> = tr.iter().map(|&i| ds.records[i].role.as_str()).collect();
        assert_eq!(roles, ["anchor", "slip_plus", "gaze_plus"]);
        assert!(tr.iter().all(|&i| ds.records[i].item == t));
    }
    let chain = CameraChain::for_dataset(&ds, chain_cfg()).unwrap();
    let ids: Vec<usize> = trips.iter().flatten().copied().collect();
    let frames = chain.load(&ds, &ids).unwrap();
    let map = hyperbolic(&chain);
    // Inside one output size (tests/chain.rs): the grid keeps its shape for small p̂ steps.
    let p_hat = 103e-6;
    let w = EmbedWeights {
        w_sens: 1.0,
        w_orth: 3.0,
        ..EmbedWeights::default()
    };
    let loss = |m: &PhaseMap, p: f64| embedding_loss(&chain, m, &frames, p, &w, false).unwrap().0;
    let (ev, g) = embedding_loss(&chain, &map, &frames, p_hat, &w, true).unwrap();
    let g = g.unwrap();
    assert_eq!(ev.triplets, 2);
    assert!(ev.loss.is_finite() && ev.crlb_slip_um > 0.0 && ev.crlb_gaze_deg > 0.0);
    // The gradient-free forward gives the same objective, and it is deterministic.
    assert_eq!(loss(&map, p_hat), ev);
    let n = map.grid.n;
    for (t, seed) in [(0usize, 1.3f64), (1, 2.9)] {
        let dir = Mat::from_fn(n, n, |i, j| {
            ((i as f64 * 0.07 * seed).sin() + (j as f64 * 0.05 + t as f64).cos()) * 0.5
        });
        let an = dot(&g.phase_rad, &dir);
        let eps = 1e-2;
        let fd = (loss(&shifted(&map, &dir, eps), p_hat).loss
            - loss(&shifted(&map, &dir, -eps), p_hat).loss)
            / (2.0 * eps);
        assert!(
            (fd - an).abs() < 0.02 * fd.abs().max(an.abs()),
            "φ direction {t}: FD {fd:e} vs VJP {an:e}"
        );
    }
    let h = 1e-8;
    let fd = (loss(&map, p_hat + h).loss - loss(&map, p_hat - h).loss) / (2.0 * h);
    assert!(
        (fd - g.p_hat).abs() < 0.02 * fd.abs().max(g.p_hat.abs()),
        "p̂: FD {fd:e} vs VJP {:e}",
        g.p_hat
    );

    // Shot noise alone (no read noise, far below full well): every electron count doubles
    // with the exposure, J ∝ Δe/√e by √2, so F doubles, L_sens falls by exactly ln 2, cos φ
    // stays, and both bounds shrink by √2. (Bright enough that the DN image's f32 rounding
    // near the black level stays far below the frames' differences.)
    let quiet = |exposure: f64| {
        let mut c = chain_cfg();
        c.sensor.read_noise_e = 0.0;
        c.radiometry.exposure_s = exposure;
        let ch = CameraChain::for_dataset(&ds, c).unwrap();
        let fr = ch.load(&ds, &ids).unwrap();
        embedding_loss(&ch, &hyperbolic(&ch), &fr, p_hat, &w, false)
            .unwrap()
            .0
    };
    let (a, b) = (quiet(0.1e-3 / 512.0), quiet(0.1e-3 / 256.0));
    assert!(
        (a.l_sens - b.l_sens - std::f64::consts::LN_2).abs() < 1e-6,
        "L_sens {} → {}",
        a.l_sens,
        b.l_sens
    );
    assert!(
        (a.l_orth - b.l_orth).abs() < 1e-6,
        "{} vs {}",
        a.l_orth,
        b.l_orth
    );
    let r = std::f64::consts::SQRT_2;
    assert!((a.crlb_slip_um / b.crlb_slip_um - r).abs() < 1e-6);
    assert!((a.crlb_gaze_deg / b.crlb_gaze_deg - r).abs() < 1e-6);
}

#[test]
fn a_dataset_without_triplets_is_refused() {
    let d = tempfile::tempdir().unwrap();
    let ds = render(d.path(), RenderSet::Ambiguity, 1);
    let e = triplets(&ds).unwrap_err().to_string();
    assert!(
        e.contains("`dataset`") && e.contains("--set variational"),
        "{e}"
    );
}

#[test]
fn embedding_steps_lower_the_objective_and_resume_to_the_same_bits() {
    let d = tempfile::tempdir().unwrap();
    let ds = render(d.path(), RenderSet::Variational, 2);
    let chain = CameraChain::for_dataset(&ds, chain_cfg()).unwrap();
    let p0 = hyperbolic(&chain).phase_rad;
    let cfg = EmbedConfig {
        steps: 4,
        batch: 2,
        lr_rad: 2e-3,
        pitch_um: 103.0,
        seed: 3,
        weights: EmbedWeights::default(),
    };
    let mut a = Embedder::new(&chain, &ds, cfg.clone(), p0.clone()).unwrap();
    let before = a.evaluate(1).unwrap();
    // Evaluated a triplet at a time or both at once: the same objective.
    assert!((a.evaluate(2).unwrap().loss - before.loss).abs() < 1e-12);
    for _ in 0..4 {
        a.train_step().unwrap();
    }
    let after = a.evaluate(2).unwrap();
    // Full batches (2 of 2 triplets) and a small rate: steepest descent on the objective.
    assert!(after.loss < before.loss, "{} → {}", before.loss, after.loss);
    assert_ne!(a.phase(), &p0);

    // Killed after one step, resumed by a new run: the same φ, history and bits.
    let ck = d.path().join("embed/checkpoint.bin");
    let mut b = Embedder::new(&chain, &ds, cfg.clone(), p0.clone()).unwrap();
    b.train_step().unwrap();
    b.save(&ck).unwrap();
    let mut c = Embedder::new(&chain, &ds, cfg.clone(), p0.clone()).unwrap();
    c.load(&ck).unwrap();
    assert_eq!(c.step(), 1);
    while c.step() < 4 {
        c.train_step().unwrap();
    }
    assert_eq!(c.history(), a.history());
    let bits = |m: &Mat<f64>| {
        (0..m.nrows())
            .flat_map(|i| (0..m.ncols()).map(move |j| (i, j)))
            .map(|(i, j)| m[(i, j)].to_bits())
            .collect::<Vec<_>>()
    };
    assert_eq!(bits(c.phase()), bits(a.phase()));
    // Batches are a seeded permutation per pass: each pass takes every triplet once.
    let mut seen: Vec<[usize; 3]> = (0..2).flat_map(|t| a.batch_of(t)).collect();
    seen.sort();
    seen.dedup();
    assert_eq!(seen.len(), 2);

    // Another setting is refused by name; a cut-off file is refused.
    let mut other = Embedder::new(
        &chain,
        &ds,
        EmbedConfig {
            lr_rad: 1e-3,
            ..cfg.clone()
        },
        p0.clone(),
    )
    .unwrap();
    let e = other.load(&ck).unwrap_err().to_string();
    assert!(e.contains("`lr_rad`"), "{e}");
    let bytes = std::fs::read(&ck).unwrap();
    std::fs::write(&ck, &bytes[..bytes.len() - 9]).unwrap();
    let mut cut = Embedder::new(&chain, &ds, cfg.clone(), p0.clone()).unwrap();
    let e = cut.load(&ck).unwrap_err().to_string();
    assert!(e.contains("truncated") || e.contains("checksum"), "{e}");

    // Settings out of range are refused naming the field.
    for (bad, field) in [
        (
            EmbedConfig {
                batch: 3,
                ..cfg.clone()
            },
            "batch",
        ),
        (
            EmbedConfig {
                batch: 0,
                ..cfg.clone()
            },
            "batch",
        ),
        (
            EmbedConfig {
                lr_rad: f64::NAN,
                ..cfg.clone()
            },
            "lr_rad",
        ),
        (
            EmbedConfig {
                steps: usize::MAX,
                ..cfg.clone()
            },
            "steps",
        ),
        (
            EmbedConfig {
                weights: EmbedWeights {
                    w_sens: 0.0,
                    w_orth: 0.0,
                    ..EmbedWeights::default()
                },
                ..cfg.clone()
            },
            "w_sens",
        ),
    ] {
        let e = Embedder::new(&chain, &ds, bad, p0.clone())
            .err()
            .expect("refused")
            .to_string();
        assert!(e.contains(&format!("`{field}`")), "{field}: {e}");
    }
}

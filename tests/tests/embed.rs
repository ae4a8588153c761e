//! The optical-embedding objective through the camera chain (S15, C.2): its gradient against
//! central differences in φ and p̂, its exact scaling with the light, the triplets read from a
//! variational dataset, the embedding run's descent, kill-and-resume bits and refusals, and
//! the embedding as a term of the sandwich training's phase loss.

use faer::Mat;
use nanoeye_datagen::render::{Dataset, DatasetOptions, LayerSpec, RenderSet, SceneSource};
use nanoeye_gaze::Rig;
use nanoeye_optics::PhaseMap;
use nanoeye_search::embed::triplets;
use nanoeye_search::{
    CameraChain, ChainConfig, EmbedConfig, EmbedWeights, Embedder, LensSpec, TrainConfig, Trainer,
    embedding_loss,
};
use nanoeye_sensor::NoiseMode;

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
        protocol_grid: nanoeye_datagen::states::PROTOCOL_GRID,
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

/// At twice the default gain the DN reaches the ADC's top at half the full well: the objective
/// must saturate there too, where the sensor's VJP zeroes the gradient, or pixels between the
/// two change the loss without a gradient. Exposure set so the brightest pixel sits at 1.5× the
/// ADC's top (below full well); the φ gradient against central differences, as above.
#[test]
fn the_embedding_saturates_where_the_adc_does() {
    let d = tempfile::tempdir().unwrap();
    let ds = render(d.path(), RenderSet::Variational, 2);
    let ids: Vec<usize> = triplets(&ds).unwrap().iter().flatten().copied().collect();
    let p_hat = 103e-6;
    let mut c = chain_cfg();
    c.sensor.gain_dn_per_e *= 2.0;
    let top_e = (c.sensor.max_dn() - c.sensor.black_level_dn) / c.sensor.gain_dn_per_e;
    assert!(top_e < 0.6 * c.sensor.full_well_e);
    let probe = CameraChain::for_dataset(&ds, c.clone()).unwrap();
    let fr = probe.load(&ds, &ids).unwrap();
    let map = hyperbolic(&probe);
    let psfs = probe.psfs(&map, &probe.active(&fr)).unwrap();
    let fwd = probe
        .forward_with(&fr, &psfs, p_hat, NoiseMode::None, 0, false)
        .unwrap();
    let peak = fwd
        .electrons
        .iter()
        .flat_map(|e| {
            e.col_iter()
                .flat_map(|c| c.iter().copied().collect::<Vec<_>>())
        })
        .fold(0.0f32, f32::max) as f64;
    assert!(peak > 0.0);
    c.radiometry.exposure_s *= 1.5 * top_e / peak;
    let chain = CameraChain::for_dataset(&ds, c).unwrap();
    let frames = chain.load(&ds, &ids).unwrap();
    let w = EmbedWeights::default();
    let loss = |m: &PhaseMap| {
        embedding_loss(&chain, m, &frames, p_hat, &w, false)
            .unwrap()
            .0
    };
    let g = embedding_loss(&chain, &map, &frames, p_hat, &w, true)
        .unwrap()
        .1
        .unwrap();
    let n = map.grid.n;
    let dir = Mat::from_fn(n, n, |i, j| {
        ((i as f64 * 0.091).sin() + (j as f64 * 0.05).cos()) * 0.5
    });
    let an = dot(&g.phase_rad, &dir);
    let eps = 1e-2;
    let fd = (loss(&shifted(&map, &dir, eps)).loss - loss(&shifted(&map, &dir, -eps)).loss)
        / (2.0 * eps);
    assert!(
        (fd - an).abs() < 0.02 * fd.abs().max(an.abs()),
        "φ: FD {fd:e} vs VJP {an:e}"
    );
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

/// `steps` of search embed over two triplets per step at a small rate, p̂ inside one output
/// size of the tiny chain.
fn small_run(steps: usize) -> EmbedConfig {
    EmbedConfig {
        steps,
        batch: 2,
        lr_rad: 2e-3,
        pitch_um: 103.0,
        seed: 3,
        weights: EmbedWeights::default(),
    }
}

#[test]
fn embedding_steps_lower_the_objective_and_resume_to_the_same_bits() {
    let d = tempfile::tempdir().unwrap();
    let ds = render(d.path(), RenderSet::Variational, 2);
    let chain = CameraChain::for_dataset(&ds, chain_cfg()).unwrap();
    let p0 = hyperbolic(&chain).phase_rad;
    let cfg = small_run(4);
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

#[test]
fn the_embedding_term_steers_the_sandwich_trainings_lens_and_resumes_to_the_same_bits() {
    let d = tempfile::tempdir().unwrap();
    let ds = render(&d.path().join("v"), RenderSet::Variational, 2);
    let chain = CameraChain::for_dataset(&ds, chain_cfg()).unwrap();
    let p0 = hyperbolic(&chain).phase_rad;
    // p̂ held at search embed's pitch, φ at its rate and seed: the same triplet batches.
    let ecfg = small_run(3);
    let tcfg = |mu: f64| TrainConfig {
        steps: 3,
        batch: 3,
        n_random: 1,
        lr_net: 5e-3,
        lr_phase_rad: ecfg.lr_rad,
        lr_pitch_um: 0.0,
        pitch_init_um: ecfg.pitch_um,
        pitch_range_um: [48.0, 150.0],
        seed: ecfg.seed,
        embed_weight: mu,
        embed_batch: ecfg.batch,
        supernet: nanoeye_nets::SupernetConfig {
            head_expand: 32,
            head_hidden: 16,
            ..nanoeye_nets::SupernetConfig::default()
        },
        ..TrainConfig::default()
    };
    let run = |mu: f64, steps: usize| {
        let mut t = Trainer::new(&chain, &ds, tcfg(mu), p0.clone()).unwrap();
        if mu > 0.0 {
            t.set_embedding(&ds).unwrap();
        }
        for _ in 0..steps {
            t.train_step().unwrap();
        }
        t
    };
    // The two gradients at φ₀ apart: the task's of step 0 (its batch, subnets and noise) and
    // the embedding's on search embed's first batch of triplets at the same p̂.
    let (_, g_task) = Trainer::new(&chain, &ds, tcfg(0.0), p0.clone())
        .unwrap()
        .phase_gradient(0)
        .unwrap();
    let e = Embedder::new(&chain, &ds, ecfg.clone(), p0.clone()).unwrap();
    let ids: Vec<usize> = e.batch_of(0).iter().flatten().copied().collect();
    let frames = chain.load(&ds, &ids).unwrap();
    let map0 = PhaseMap::phase_only(*chain.aperture_grid(), p0.clone()).unwrap();
    let (ev, g) = embedding_loss(&chain, &map0, &frames, 103e-6, &ecfg.weights, true).unwrap();
    let g_embed = g.unwrap().phase_rad;
    let rms = |m: &Mat<f64>| dot(m, m).sqrt();
    // The μ that gives both terms the same size: the joint step is neither term's alone.
    let mu = rms(&g_task) / rms(&g_embed);
    assert!(mu.is_finite() && mu > 0.0 && mu < 1e3, "{mu}");
    let joint = run(mu, 1);
    // Adam's first step is lr·g/(|g| + 1e-12) per sample, g = ∂L_train/∂φ + μ·∂L_embed/∂φ:
    // the trainer's one PSF VJP of the summed ∂L/∂P against the two VJPs taken apart above.
    let lr = ecfg.lr_rad;
    let (mut worst, mut flipped, mut active) = (0.0f64, 0, 0);
    let task = run(0.0, 1);
    for i in 0..p0.nrows() {
        for j in 0..p0.ncols() {
            let g = g_task[(i, j)] + mu * g_embed[(i, j)];
            let want = p0[(i, j)] - lr * g / (g.abs() + 1e-12);
            worst = worst.max((joint.phase[(i, j)] - want).abs());
            if g.abs() > 1e-9 * rms(&g_task) {
                active += 1;
                // Opposite steps of the task alone and the joint loss: 2·lr apart.
                flipped += usize::from((joint.phase[(i, j)] - task.phase[(i, j)]).abs() > lr);
            }
        }
    }
    assert!(worst < 1e-9, "joint step off by {worst} rad");
    // The embedding term turns some samples' steps around (473 of 8008 when written; the
    // equal-size terms disagree in sign where the embedding's is the larger of the two).
    assert!(flipped * 50 > active, "{flipped} of {active}");
    // The step records the objective on its triplets before the step.
    assert_eq!(joint.history[0].embed_loss, Some(ev.loss));
    assert!(task.history.iter().all(|r| r.embed_loss.is_none()));

    // Killed after one step at μ = 1, resumed by a new trainer: the same bits.
    let full = run(1.0, 3);
    let ck = d.path().join("ck.bin");
    let mut a = Trainer::new(&chain, &ds, tcfg(1.0), p0.clone()).unwrap();
    a.set_embedding(&ds).unwrap();
    a.train_step().unwrap();
    a.save(&ck).unwrap();
    drop(a);
    let mut b = Trainer::new(&chain, &ds, tcfg(1.0), p0.clone()).unwrap();
    b.set_embedding(&ds).unwrap();
    b.load(&ck).unwrap();
    while b.step < 3 {
        b.train_step().unwrap();
    }
    assert_eq!(b.history, full.history);
    let bits = |m: &Mat<f64>| {
        m.col_iter()
            .flat_map(|c| c.iter().map(|v| v.to_bits()).collect::<Vec<_>>())
            .collect::<Vec<_>>()
    };
    assert_eq!(bits(&b.phase), bits(&full.phase));
    // A checkpoint of the task alone is another configuration.
    let mut other = Trainer::new(&chain, &ds, tcfg(0.0), p0.clone()).unwrap();
    let msg = other.load(&ck).unwrap_err().to_string();
    assert!(msg.contains("embed_weight"), "{msg}");

    // Refusals, naming the field.
    let named = |r: nanoeye_search::Result<()>, field: &str| {
        let m = r.expect_err("refused").to_string();
        assert!(m.contains(&format!("`{field}`")), "{field}: {m}");
    };
    named(
        TrainConfig {
            fixed_lens: true,
            ..tcfg(1.0)
        }
        .validate(),
        "embed_weight",
    );
    named(tcfg(f64::NAN).validate(), "embed_weight");
    named(tcfg(-1.0).validate(), "embed_weight");
    named(
        TrainConfig {
            embed_batch: 0,
            ..tcfg(1.0)
        }
        .validate(),
        "embed_batch",
    );
    // No triplets given: the first φ step says what is missing.
    let mut none = Trainer::new(&chain, &ds, tcfg(1.0), p0.clone()).unwrap();
    named(none.train_step().map(|_| ()), "embed_weight");
    // More triplets per step than the set holds; a set with no triplets.
    let mut big = Trainer::new(
        &chain,
        &ds,
        TrainConfig {
            embed_batch: 3,
            ..tcfg(1.0)
        },
        p0.clone(),
    )
    .unwrap();
    named(big.set_embedding(&ds), "embed_batch");
    let amb = render(&d.path().join("a"), RenderSet::Ambiguity, 1);
    let mut t = Trainer::new(&chain, &ds, tcfg(1.0), p0.clone()).unwrap();
    named(t.set_embedding(&amb), "dataset");
}

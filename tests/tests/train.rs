//! Sandwich-rule co-design training on a tiny configuration: the losses of N_max and N_min
//! fall, φ and p̂ move, a killed run resumes to the same bits, a resume with other parameters
//! is refused, and validation runs the full chain to gaze.

use nanoeye_datagen::render::{Dataset, DatasetOptions, LayerSpec, RenderSet, SceneSource};
use nanoeye_gaze::Rig;
use nanoeye_nets::{Arch, SupernetConfig};
use nanoeye_search::{CameraChain, ChainConfig, LensSpec, TrainConfig, Trainer};

fn dataset(dir: &std::path::Path, seed: u64) -> Dataset {
    nanoeye_datagen::render::write_dataset(&DatasetOptions {
        set: RenderSet::Ambiguity,
        n: 1,
        seed,
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

fn chain(ds: &Dataset) -> CameraChain {
    let mut c = ChainConfig {
        aperture_step_m: 10e-6,
        ..ChainConfig::default()
    };
    c.sensor.base_pitch = 48e-6;
    c.radiometry.exposure_s = 0.1e-3 / 256.0;
    CameraChain::for_dataset(ds, c).unwrap()
}

fn cfg(steps: usize) -> TrainConfig {
    TrainConfig {
        steps,
        batch: 3,
        n_random: 1,
        lr_net: 5e-3,
        lr_phase_rad: 5e-2,
        lr_pitch_um: 0.5,
        pitch_init_um: 70.0,
        pitch_range_um: [48.0, 150.0],
        supernet: SupernetConfig {
            head_expand: 32,
            head_hidden: 16,
            ..SupernetConfig::default()
        },
        ..TrainConfig::default()
    }
}

fn phase0(c: &CameraChain) -> faer::Mat<f64> {
    LensSpec::Hyperbolic
        .phase_map(c.aperture_grid(), 940e-9, 2e-3)
        .unwrap()
        .phase_rad
}

/// A run of `cfg.steps` killed after `kill_at` steps (checkpoint at `ck`) and resumed to the
/// end by a new trainer.
fn resumed_after<'a>(
    c: &'a CameraChain,
    ds: &'a Dataset,
    cfg: TrainConfig,
    p0: &faer::Mat<f64>,
    ck: &std::path::Path,
    kill_at: usize,
) -> Trainer<'a> {
    let steps = cfg.steps;
    let mut b = Trainer::new(c, ds, cfg.clone(), p0.clone()).unwrap();
    for _ in 0..kill_at {
        b.train_step().unwrap();
    }
    b.save(ck).unwrap();
    drop(b);
    let mut r = Trainer::new(c, ds, cfg, p0.clone()).unwrap();
    r.load(ck).unwrap();
    assert_eq!(r.step, kill_at);
    for _ in kill_at..steps {
        r.train_step().unwrap();
    }
    r
}

#[test]
fn sandwich_training_lowers_both_losses_and_moves_the_optics() {
    let d = tempfile::tempdir().unwrap();
    let ds = dataset(d.path(), 3);
    let c = chain(&ds);
    let mut t = Trainer::new(&c, &ds, cfg(8), phase0(&c)).unwrap();
    let p0 = t.phase.clone();
    for _ in 0..8 {
        t.train_step().unwrap();
    }
    let h = &t.history;
    let first = &h[0];
    let last = h.last().unwrap();
    assert!(last.loss_max < first.loss_max, "{h:?}");
    assert!(last.loss_min < first.loss_min, "{h:?}");
    assert!(t.pitch_um != 70.0, "p̂ did not move");
    let moved = (0..p0.nrows())
        .flat_map(|i| (0..p0.ncols()).map(move |j| (i, j)))
        .any(|(i, j)| t.phase[(i, j)] != p0[(i, j)]);
    assert!(moved, "φ did not move");
    // Validation: the full chain to gaze gives finite, bounded numbers. An angle between two
    // directions lies in [0°, 180°] (a failure counts 90°, a tracked frame after 8 steps may be
    // farther off than that).
    let m = t.evaluate(&ds, &Arch::min(), 1).unwrap();
    assert_eq!(m.frames, 3);
    assert!(
        m.v_deg.is_finite() && (0.0..=180.0).contains(&m.v_deg),
        "{m:?}"
    );
    assert!((0.0..=1.0).contains(&m.dice) && m.slip_mse.is_finite());
}

#[test]
fn a_set_through_the_chain_once_scores_every_subnet_as_the_chain_pass_does() {
    use nanoeye_gaze::{PupilCentre, SolverKind};
    use nanoeye_search::{ChainedSet, EvalSetup, SolverInput, evaluate_chained};
    let d = tempfile::tempdir().unwrap();
    let ds = dataset(d.path(), 5);
    let c = chain(&ds);
    let mut t = Trainer::new(&c, &ds, cfg(2), phase0(&c)).unwrap();
    for _ in 0..2 {
        t.train_step().unwrap();
    }
    let map = t.phase_map().unwrap();
    let p_hat = t.pitch_um * 1e-6;
    // Two frames per batch over three frames: a full batch and a partial one.
    let set = ChainedSet::new(&c, &ds, &map, p_hat, 2, 11).unwrap();
    let solves = [
        (
            SolverInput::Predicted,
            SolverKind::Refractive,
            PupilCentre::Centroid,
        ),
        (
            SolverInput::Truth,
            SolverKind::Refractive,
            PupilCentre::Centroid,
        ),
        (
            SolverInput::NoSlip,
            SolverKind::Refractive,
            PupilCentre::Centroid,
        ),
    ];
    let (h, w) = c.native().at(p_hat).unwrap().shape();
    assert_eq!(ChainedSet::bytes_for(3, h, w), 3 * h * w * 8);
    assert_eq!(ChainedSet::bytes_for(usize::MAX, h, w), usize::MAX);
    for arch in [Arch::max(), Arch::min()] {
        t.recalibrate(&arch, 1).unwrap();
        let s = EvalSetup {
            chain: &c,
            data: &ds,
            map: &map,
            p_hat_m: p_hat,
            arch: &arch,
            batch: 2,
            seed: 11,
        };
        let direct = nanoeye_search::evaluate_frames_multi(&mut t.net, &s, &solves).unwrap();
        let kept = evaluate_chained(&mut t.net, &arch, &set, &solves).unwrap();
        assert_eq!(direct[0].errors_deg.len(), 3);
        // Debug prints every f64 exactly (shortest round trip): equal text, equal bits.
        assert_eq!(format!("{direct:?}"), format!("{kept:?}"));
    }
    // Another noise seed is another set: the kept one is tied to its seed.
    let other = ChainedSet::new(&c, &ds, &map, p_hat, 2, 12).unwrap();
    let arch = Arch::max();
    let a = evaluate_chained(&mut t.net, &arch, &set, &solves[..1]).unwrap();
    let b = evaluate_chained(&mut t.net, &arch, &other, &solves[..1]).unwrap();
    assert_ne!(format!("{:?}", a[0].slip_mm), format!("{:?}", b[0].slip_mm));
}

#[test]
fn a_killed_run_resumes_to_the_same_bits_and_other_parameters_are_refused() {
    let d = tempfile::tempdir().unwrap();
    let ds = dataset(d.path(), 4);
    let c = chain(&ds);
    let ck = d.path().join("run/checkpoint.bin");
    let mut a = Trainer::new(&c, &ds, cfg(4), phase0(&c)).unwrap();
    for _ in 0..4 {
        a.train_step().unwrap();
    }
    let mut r = resumed_after(&c, &ds, cfg(4), &phase0(&c), &ck, 2);
    assert_eq!(r.history, a.history);
    assert_eq!(r.pitch_um, a.pitch_um);
    assert_eq!(r.phase, a.phase);
    let (na, nr) = (
        nanoeye_nets::checkpoint::to_bytes(&mut a.net).unwrap(),
        nanoeye_nets::checkpoint::to_bytes(&mut r.net).unwrap(),
    );
    assert!(na == nr, "network weights differ after resume");
    // Another learning rate: refused, naming it.
    let mut other = cfg(4);
    other.lr_phase_rad = 1e-3;
    let mut x = Trainer::new(&c, &ds, other, phase0(&c)).unwrap();
    let e = x.load(&ck).unwrap_err().to_string();
    assert!(e.contains("lr_phase_rad"), "{e}");
    // A flipped byte is detected.
    let mut bytes = std::fs::read(&ck).unwrap();
    let k = bytes.len() / 2;
    bytes[k] ^= 1;
    std::fs::write(&ck, bytes).unwrap();
    let mut y = Trainer::new(&c, &ds, cfg(4), phase0(&c)).unwrap();
    assert!(y.load(&ck).unwrap_err().to_string().contains("checksum"));
}

#[test]
fn a_zernike_basis_moves_phi_within_its_modes_and_resumes_to_the_same_bits() {
    use faer::linalg::solvers::Solve;
    use nanoeye_search::PhaseBasis;
    use nanoeye_search::basis::Zernike;
    let d = tempfile::tempdir().unwrap();
    let ds = dataset(d.path(), 5);
    let c = chain(&ds);
    let zcfg = |steps| TrainConfig {
        phase_basis: PhaseBasis::Zernike(3),
        ..cfg(steps)
    };
    let p0 = phase0(&c);
    let mut a = Trainer::new(&c, &ds, zcfg(4), p0.clone()).unwrap();
    for _ in 0..4 {
        a.train_step().unwrap();
    }
    // Δφ is a combination of the nine modes of orders 1–3: the least-squares fit (normal
    // equations on the grid) reconstructs it, zero outside the disc included.
    let g = *c.aperture_grid();
    let z = Zernike::new(3, g).unwrap();
    let n = g.n;
    let dphi = faer::Mat::from_fn(n, n, |i, j| a.phase[(i, j)] - p0[(i, j)]);
    let modes: Vec<faer::Mat<f64>> = (0..z.len())
        .map(|k| {
            let mut e = vec![0.0; z.len()];
            e[k] = 1.0;
            let mut m = faer::Mat::zeros(n, n);
            z.add_to(&e, &mut m);
            m
        })
        .collect();
    let gram = faer::Mat::from_fn(z.len(), z.len(), |p, q| z.project(&modes[q])[p]);
    let rhs = z.project(&dphi);
    let coef = gram
        .partial_piv_lu()
        .solve(&faer::Mat::from_fn(z.len(), 1, |p, _| rhs[p]));
    let norm = dphi.norm_l2();
    assert!(norm > 1e-6, "φ did not move: {norm}");
    let mut fit = faer::Mat::zeros(n, n);
    let cf: Vec<f64> = (0..z.len()).map(|p| coef[(p, 0)]).collect();
    z.add_to(&cf, &mut fit);
    let resid = (&fit - &dphi).norm_l2();
    assert!(
        resid <= 1e-9 * norm,
        "Δφ leaves the modes' span: {resid} of {norm}"
    );
    // The same start with a step per sample moves φ otherwise.
    let mut px = Trainer::new(&c, &ds, cfg(1), p0.clone()).unwrap();
    px.train_step().unwrap();
    let mut z1 = Trainer::new(&c, &ds, zcfg(1), p0.clone()).unwrap();
    z1.train_step().unwrap();
    assert_ne!(px.phase, z1.phase);
    // Killed after two steps and resumed: the same bits as the four uninterrupted steps.
    let ck = d.path().join("zrun/checkpoint.bin");
    let r = resumed_after(&c, &ds, zcfg(4), &p0, &ck, 2);
    assert_eq!(r.history, a.history);
    assert_eq!(r.phase, a.phase);
    assert_eq!(r.pitch_um, a.pitch_um);
    // Resumed under a per-sample basis: refused, naming the field.
    let mut x = Trainer::new(&c, &ds, cfg(4), p0).unwrap();
    let e = x.load(&ck).unwrap_err().to_string();
    assert!(e.contains("phase_basis"), "{e}");
}

#[test]
fn a_cosine_phase_schedule_halves_the_second_step_then_fixes_phi_and_resumes_exactly() {
    use nanoeye_search::PhaseSchedule;
    let d = tempfile::tempdir().unwrap();
    let ds = dataset(d.path(), 7);
    let sched = |steps| TrainConfig {
        phase_schedule: PhaseSchedule::Cosine(0.5),
        ..cfg(steps)
    };
    let p0 = {
        let c = chain(&ds);
        phase0(&c)
    };
    // Over 4 steps the decay lasts 2: factors 1, ½, 0, 0.
    let (cs, cc) = (chain(&ds), chain(&ds));
    let mut a = Trainer::new(&cs, &ds, sched(4), p0.clone()).unwrap();
    let mut k = Trainer::new(&cc, &ds, cfg(4), p0.clone()).unwrap();
    a.train_step().unwrap();
    k.train_step().unwrap();
    assert_eq!(a.phase, k.phase, "step 0 runs at the full rate under both");
    let p1 = a.phase.clone();
    a.train_step().unwrap();
    k.train_step().unwrap();
    // Same state, batch and gradient: Adam's step at half the rate is half the step.
    let (ds_a, ds_k) = (&a.phase - &p1, &k.phase - &p1);
    let half = &ds_k * faer::Scale(0.5);
    let diff = (&ds_a - &half).norm_l2();
    assert!(ds_k.norm_l2() > 1e-6, "φ did not move at step 1");
    assert!(
        diff <= 1e-12 * ds_k.norm_l2(),
        "step 1 is not half the constant rate's: {diff} of {}",
        ds_k.norm_l2()
    );
    let p2 = a.phase.clone();
    let pitch2 = a.pitch_um;
    // Past the decay φ stays, bit for bit, while p̂ and the network still train; the steps
    // take no gradient to φ, so S1's images come from the chain's cache (a step that moves φ
    // never reads or fills it).
    assert_eq!(cs.cached_s1_images(), 0);
    for _ in 2..4 {
        let rec = a.train_step().unwrap();
        assert_eq!(rec.phase_step_rad, 0.0);
    }
    assert_eq!(a.phase, p2);
    assert_ne!(a.pitch_um, pitch2);
    assert!(cs.cached_s1_images() > 0);
    assert_eq!(cc.cached_s1_images(), 0);
    // Killed past the decay and resumed: the same bits; resumed as constant: refused.
    let ck = d.path().join("srun/checkpoint.bin");
    let c2 = chain(&ds);
    let r = resumed_after(&c2, &ds, sched(4), &p0, &ck, 3);
    assert_eq!(r.history, a.history);
    assert_eq!(r.phase, a.phase);
    assert_eq!(r.pitch_um, a.pitch_um);
    let mut x = Trainer::new(&c2, &ds, cfg(4), p0).unwrap();
    let e = x.load(&ck).unwrap_err().to_string();
    assert!(e.contains("phase_schedule"), "{e}");
}

#[test]
fn phase_every_steps_phi_once_a_window_by_its_mean_gradient_and_resumes_mid_window() {
    let d = tempfile::tempdir().unwrap();
    let ds = dataset(d.path(), 8);
    let every = |m, steps| TrainConfig {
        phase_every: m,
        ..cfg(steps)
    };
    let c = chain(&ds);
    let p0 = phase0(&c);
    // Each step's gradient at the state that step sees: φ0 throughout the first window.
    let mut q = Trainer::new(&c, &ds, every(2, 4), p0.clone()).unwrap();
    let (_, g0) = q.phase_gradient(0).unwrap();
    assert_eq!(q.train_step().unwrap().phase_step_rad, 0.0);
    assert_eq!(q.phase, p0, "φ moved inside its window");
    let (_, g1) = q.phase_gradient(1).unwrap();
    assert!(q.train_step().unwrap().phase_step_rad > 0.0);
    // Adam's first step is lr · ḡ / (|ḡ| + ε) per sample for the window's mean ḡ (summed
    // before the PSF VJP in training, after it here: equal up to round-off, so samples where
    // ḡ is round-off of zero are skipped).
    let mean = (&g0 + &g1) * faer::Scale(0.5);
    let big = (0..p0.nrows())
        .flat_map(|i| (0..p0.ncols()).map(move |j| (i, j)))
        .map(|(i, j)| mean[(i, j)].abs())
        .fold(0.0, f64::max);
    let lr = cfg(4).lr_phase_rad;
    let (mut checked, mut unlike_last) = (0, 0);
    for i in 0..p0.nrows() {
        for j in 0..p0.ncols() {
            let m = mean[(i, j)];
            if m.abs() <= 1e-9 * big {
                continue;
            }
            let want = p0[(i, j)] - lr * m / (m.abs() + 1e-12);
            assert!((q.phase[(i, j)] - want).abs() <= 1e-12, "({i}, {j})");
            checked += 1;
            unlike_last += usize::from(g1[(i, j)].signum() != m.signum());
        }
    }
    assert!(checked > 0, "no gradient");
    // Otherwise the check could not tell the window's mean from its last step's gradient.
    assert!(unlike_last > 0, "ḡ has g1's signs everywhere");
    // The second window: φ fixed at step 2, stepped at 3.
    let p2 = q.phase.clone();
    assert_eq!(q.train_step().unwrap().phase_step_rad, 0.0);
    assert_eq!(q.phase, p2);
    assert!(q.train_step().unwrap().phase_step_rad > 0.0);
    // Killed inside a window (its sum in the checkpoint) or at its end, and resumed: the
    // uninterrupted run's bits.
    let cu = chain(&ds);
    let mut u = Trainer::new(&cu, &ds, every(2, 4), p0.clone()).unwrap();
    for _ in 0..4 {
        u.train_step().unwrap();
    }
    let ck = d.path().join("wrun/checkpoint.bin");
    for kill_at in [1, 2, 3] {
        let c2 = chain(&ds);
        let r = resumed_after(&c2, &ds, every(2, 4), &p0, &ck, kill_at);
        assert_eq!(r.history, u.history, "killed after {kill_at}");
        assert_eq!(r.phase, u.phase, "killed after {kill_at}");
        assert_eq!(r.pitch_um, u.pitch_um, "killed after {kill_at}");
    }
    // A checkpoint inside a window resumed with another window length: refused by name.
    let c3 = chain(&ds);
    let mut b = Trainer::new(&c3, &ds, every(2, 4), p0.clone()).unwrap();
    b.train_step().unwrap();
    b.save(&ck).unwrap();
    let mut x = Trainer::new(&c3, &ds, every(1, 4), p0).unwrap();
    let e = x.load(&ck).unwrap_err().to_string();
    assert!(e.contains("phase_every"), "{e}");
}

#[test]
fn the_phase_gradient_is_what_a_training_step_descends() {
    // Adam's first step is lr · g / (|g| + ε) per sample: a fresh trainer's first step moves φ
    // by exactly that for the g `phase_gradient(0)` reports (same batch, subnets and noise).
    let d = tempfile::tempdir().unwrap();
    let ds = dataset(d.path(), 6);
    let c = chain(&ds);
    let p0 = phase0(&c);
    let mut a = Trainer::new(&c, &ds, cfg(2), p0.clone()).unwrap();
    let (loss, g) = a.phase_gradient(0).unwrap();
    let mut b = Trainer::new(&c, &ds, cfg(2), p0.clone()).unwrap();
    let rec = b.train_step().unwrap();
    assert_eq!(loss, rec.loss_total);
    let lr = cfg(2).lr_phase_rad;
    let mut moved = 0;
    for i in 0..p0.nrows() {
        for j in 0..p0.ncols() {
            let want = p0[(i, j)] - lr * g[(i, j)] / (g[(i, j)].abs() + 1e-12);
            assert!((b.phase[(i, j)] - want).abs() <= 1e-12, "({i}, {j})");
            moved += usize::from(g[(i, j)] != 0.0);
        }
    }
    assert!(moved > 0, "no gradient");
}

fn trained_run(dir: &std::path::Path, c: &CameraChain, ds: &Dataset) -> std::path::PathBuf {
    let mut t = Trainer::new(c, ds, cfg(2), phase0(c)).unwrap();
    t.train_step().unwrap();
    t.train_step().unwrap();
    let p = dir.join("run/checkpoint.bin");
    t.save(&p).unwrap();
    p
}

fn rea_cfg() -> nanoeye_search::ReaConfig {
    nanoeye_search::ReaConfig {
        cycles: 3,
        population: 3,
        tournament: 2,
        epochs: 1.0,
        budget_macs: 200_000,
        recal_batches: nanoeye_search::BnBatches::Count(1),
        seed: 9,
        ..nanoeye_search::ReaConfig::default()
    }
}

#[test]
fn regularized_evolution_ages_out_the_oldest_and_resumes_exactly() {
    use nanoeye_search::{Rea, ReaState};
    let d = tempfile::tempdir().unwrap();
    let ds = dataset(d.path(), 5);
    let c = chain(&ds);
    let run = trained_run(d.path(), &c, &ds);
    let mut full = Rea::new(&c, &ds, &ds, &run, rea_cfg()).unwrap();
    full.run(&mut |_| Ok(())).unwrap();
    let st = &full.state;
    assert_eq!(st.evaluated.len(), 6);
    for rec in &st.history {
        // Aging: the oldest member leaves, whatever its fitness.
        assert_eq!(rec.removed, rec.population[0]);
        // The parent is the tournament's argmax of the S19 fitness.
        let best = rec
            .tournament
            .iter()
            .map(|&i| st.evaluated[i].fitness)
            .fold(f64::NEG_INFINITY, f64::max);
        assert_eq!(st.evaluated[rec.parent].fitness, best);
        assert!(rec.tournament.iter().all(|i| rec.population.contains(i)));
        // Children stay in the search space; fitness is −V − γ·𝕀(C > budget).
        rec.child.arch.validate().unwrap();
        let pen = if rec.child.macs > 200_000 { 10.0 } else { 0.0 };
        assert_eq!(rec.child.fitness, -rec.child.v - pen);
    }
    assert_eq!(st.population.len(), 3);
    // The pick: the best within the budget, though one over it has a better S19 fitness
    // (its V beats the others' by more than γ); the best fitness only when none fits.
    let mut ev: Vec<_> = st.evaluated[..3].to_vec();
    for (ind, (macs, v, fitness)) in ev.iter_mut().zip([
        (300_000, 5.0, -15.0),
        (150_000, 18.0, -18.0),
        (100_000, 16.0, -16.0),
    ]) {
        (ind.macs, ind.v, ind.fitness) = (macs, v, fitness);
    }
    let pick = |ev: &[nanoeye_search::Individual], budget| {
        nanoeye_search::rea::pick_best(ev, budget).map(|i| i.id)
    };
    assert_eq!(pick(&ev, 200_000), Some(ev[2].id));
    assert_eq!(pick(&ev, 0), Some(ev[0].id));
    assert_eq!(pick(&ev, 50_000), Some(ev[0].id));
    assert_eq!(pick(&[], 200_000), None);
    assert_eq!(full.best().map(|i| i.id), pick(&st.evaluated, 200_000));
    // Kill after 4 evaluations, resume from the saved state: the same search.
    let saved: std::cell::RefCell<Option<String>> = Default::default();
    let mut n = 0;
    let mut part = Rea::new(&c, &ds, &ds, &run, rea_cfg()).unwrap();
    let r = part.run(&mut |s: &ReaState| {
        n += 1;
        *saved.borrow_mut() = Some(serde_json::to_string(s).unwrap());
        if n == 4 {
            return Err(nanoeye_search::SearchError::Param {
                name: "kill",
                reason: "simulated".into(),
            });
        }
        Ok(())
    });
    assert!(r.is_err());
    let state_path = d.path().join("rea_state.json");
    std::fs::write(&state_path, saved.borrow().as_ref().unwrap()).unwrap();
    let mut resumed = Rea::new(&c, &ds, &ds, &run, rea_cfg()).unwrap();
    resumed.resume(&state_path).unwrap();
    resumed.run(&mut |_| Ok(())).unwrap();
    assert_eq!(
        serde_json::to_string(&resumed.state).unwrap(),
        serde_json::to_string(&full.state).unwrap()
    );
    // Other parameters are refused.
    let mut other = Rea::new(
        &c,
        &ds,
        &ds,
        &run,
        nanoeye_search::ReaConfig {
            gamma: 1.0,
            ..rea_cfg()
        },
    )
    .unwrap();
    let e = other.resume(&state_path).unwrap_err().to_string();
    assert!(e.contains("`gamma`: 10.0 there, 1.0 now"), "{e}");
    // A count is written as the bare number states held before "all" existed: such a state
    // resumes under `Count(n)` and is refused under `All`, naming the field.
    let saved = std::fs::read_to_string(&state_path).unwrap();
    assert!(saved.contains(r#""recal_batches":1,"#), "{saved}");
    let mut same = Rea::new(&c, &ds, &ds, &run, rea_cfg()).unwrap();
    same.resume(&state_path).unwrap();
    let all = nanoeye_search::ReaConfig {
        recal_batches: nanoeye_search::BnBatches::All,
        ..rea_cfg()
    };
    let mut other = Rea::new(&c, &ds, &ds, &run, all).unwrap();
    let e = other.resume(&state_path).unwrap_err().to_string();
    assert!(e.contains(r#"`recal_batches`: 1 there, "all" now"#), "{e}");
}

#[test]
fn a_fitted_pitch_is_the_budgets_edge_and_fine_tuning_keeps_it_inside() {
    use nanoeye_search::{Budget, Rea, ReaConfig};
    let d = tempfile::tempdir().unwrap();
    let ds = dataset(d.path(), 5);
    let c = chain(&ds);
    let mut t = Trainer::new(&c, &ds, cfg(2), phase0(&c)).unwrap();
    let arch = Arch::max();
    let p0 = t.pitch_um;
    let m0 = t.macs_at(&arch, p0).unwrap();
    let top = t.macs_at(&arch, 150.0).unwrap();
    assert!(
        top < m0 / 2,
        "the range's top must halve the cost: {top} vs {m0}"
    );
    // Inside already, no budget, or over it even at the range's top: p̂ stays.
    for (b, fits) in [(m0, true), (0, true), (top - 1, false)] {
        assert_eq!(t.fit_pitch_to_budget(&arch, b).unwrap(), fits);
        assert_eq!(t.pitch_um, p0);
    }
    let budget = m0 / 2;
    assert!(t.fit_pitch_to_budget(&arch, budget).unwrap());
    let p = t.pitch_um;
    assert!(p > p0 && p <= 150.0, "{p}");
    assert!(t.macs_at(&arch, p).unwrap() <= budget);
    // The smallest such pitch: a hair below it the subnet is over the budget.
    assert!(t.macs_at(&arch, p * (1.0 - 1e-6)).unwrap() > budget);
    // Projected fine-tune steps stay inside while the task gradient moves p̂; the hinge alone
    // (Adam, 0.5 µm a step here) leaves a fresh trainer over the budget after as many steps.
    let fit = Budget {
        macs: budget,
        lambda: 1.0,
        fit_pitch: true,
    };
    let hinge = Budget {
        fit_pitch: false,
        ..fit
    };
    let mut u = Trainer::new(&c, &ds, cfg(2), phase0(&c)).unwrap();
    for _ in 0..3 {
        let (_, macs) = t.finetune_step(&arch, &fit, 1.0).unwrap();
        assert!(macs <= budget);
        assert!(t.macs_at(&arch, t.pitch_um).unwrap() <= budget);
        u.finetune_step(&arch, &hinge, 1.0).unwrap();
    }
    assert!(
        u.macs_at(&arch, u.pitch_um).unwrap() > budget,
        "{}",
        u.pitch_um
    );
    // In the search, a candidate is over the budget only if it is over at the range's top.
    let run = trained_run(d.path(), &c, &ds);
    let rc = ReaConfig {
        cycles: 1,
        population: 2,
        tournament: 1,
        epochs: 1.0,
        budget_macs: 200_000,
        recal_batches: nanoeye_search::BnBatches::Count(1),
        fit_pitch: true,
        seed: 4,
        ..ReaConfig::default()
    };
    let mut rea = Rea::new(&c, &ds, &ds, &run, rc).unwrap();
    rea.run(&mut |_| Ok(())).unwrap();
    assert_eq!(rea.state.evaluated.len(), 3);
    for ind in &rea.state.evaluated {
        let reachable = t.macs_at(&ind.arch, 150.0).unwrap() <= 200_000;
        assert_eq!(
            ind.macs <= 200_000,
            reachable,
            "{} MACs at {} µm",
            ind.macs,
            ind.pitch_um
        );
        assert_eq!(ind.fitness, -ind.v - if reachable { 0.0 } else { 10.0 });
    }
}

/// Every learnable value of `t`'s network, as bits, in `visit` order.
fn weight_bits(t: &mut Trainer) -> Vec<u32> {
    let mut v = Vec::new();
    t.net
        .visit(&mut |_, p| v.extend(p.value.iter().map(|x| x.to_bits())));
    v
}

#[test]
fn a_fine_tune_with_phi_at_rate_zero_moves_the_network_and_pitch_alone() {
    use nanoeye_search::Budget;
    let d = tempfile::tempdir().unwrap();
    let ds = dataset(d.path(), 5);
    let c = chain(&ds);
    let arch = Arch::min();
    let budget = Budget {
        macs: 0,
        lambda: 0.0,
        fit_pitch: false,
    };
    let lr_phase = cfg(2).lr_phase_rad;
    let mut frozen = Trainer::new(&c, &ds, cfg(2), phase0(&c)).unwrap();
    let mut moving = Trainer::new(&c, &ds, cfg(2), phase0(&c)).unwrap();
    let (phi0, p0, w0) = (
        frozen.phase.clone(),
        frozen.pitch_um,
        weight_bits(&mut frozen),
    );
    let (lf, _) = frozen
        .finetune_step_phase_at(&arch, &budget, 1.0, 0.0)
        .unwrap();
    let (lm, _) = moving.finetune_step(&arch, &budget, 1.0).unwrap();
    // The same batch through the same optics: the loss does not see φ's rate.
    assert_eq!(lf.to_bits(), lm.to_bits());
    // φ keeps its bits; with the rate on, Adam's first step moves the samples with the
    // largest gradient by nearly the whole rate and none by more.
    assert_eq!(frozen.phase, phi0);
    let dphi = (0..phi0.nrows())
        .flat_map(|i| (0..phi0.ncols()).map(move |j| (i, j)))
        .map(|(i, j)| (moving.phase[(i, j)] - phi0[(i, j)]).abs())
        .fold(0.0f64, f64::max);
    assert!(
        dphi > 0.5 * lr_phase && dphi <= lr_phase * (1.0 + 1e-9),
        "max |Δφ| {dphi} rad at rate {lr_phase}"
    );
    // The network and p̂ take the same step either way: ∂L/∂p̂ without S1's PSF adjoint is the
    // same number as with it.
    let wf = weight_bits(&mut frozen);
    assert_ne!(wf, w0, "the network did not move");
    assert_eq!(wf, weight_bits(&mut moving));
    assert!(frozen.pitch_um != p0, "p̂ did not move");
    assert!(
        (frozen.pitch_um - moving.pitch_um).abs() <= 1e-12 * p0,
        "p̂ {} vs {}",
        frozen.pitch_um,
        moving.pitch_um
    );
}

/// Evaluates up to `slots` candidates "at once" and hands back the newest first, as a pool of
/// remote workers may.
struct NewestFirst<'a> {
    eval: nanoeye_search::Evaluator<'a>,
    queue: Vec<(usize, Arch)>,
    slots: usize,
    most_in_flight: usize,
    submitted: Vec<usize>,
}

impl nanoeye_search::EvalPool for NewestFirst<'_> {
    fn slots(&self) -> usize {
        self.slots
    }
    fn submit(&mut self, id: usize, arch: &Arch) -> nanoeye_search::Result<()> {
        self.queue.push((id, arch.clone()));
        self.submitted.push(id);
        self.most_in_flight = self.most_in_flight.max(self.queue.len());
        Ok(())
    }
    fn next(&mut self) -> nanoeye_search::Result<nanoeye_search::Individual> {
        let (id, arch) = self.queue.pop().expect("something submitted");
        self.eval.evaluate(id, &arch)
    }
}

/// A one-pair dataset, its chain and a 2-step trained run, in `dir`.
fn search_fixture(dir: &std::path::Path) -> (Dataset, CameraChain, std::path::PathBuf) {
    let ds = dataset(dir, 5);
    let c = chain(&ds);
    let run = trained_run(dir, &c, &ds);
    (ds, c, run)
}

type Save<'s> = dyn FnMut(&nanoeye_search::ReaState) -> nanoeye_search::Result<()> + 's;

/// Every state a search saves, as JSON, in order.
fn saved_states(search: impl FnOnce(&mut Save) -> nanoeye_search::Result<()>) -> Vec<String> {
    let mut saves = Vec::new();
    search(&mut |s| {
        saves.push(serde_json::to_string(s).unwrap());
        Ok(())
    })
    .unwrap();
    saves
}

#[test]
fn a_pool_answering_out_of_order_gives_the_sequential_search() {
    use nanoeye_search::Rea;
    let d = tempfile::tempdir().unwrap();
    let (ds, c, run) = search_fixture(d.path());
    let cfg = nanoeye_search::ReaConfig {
        epochs: 0.0,
        population: 4,
        cycles: 8,
        ..rea_cfg()
    };
    let seq_saves =
        saved_states(|save| Rea::new(&c, &ds, &ds, &run, cfg.clone()).unwrap().run(save));
    let mut par = Rea::new(&c, &ds, &ds, &run, cfg).unwrap();
    let mut pool = NewestFirst {
        eval: par.evaluator(),
        queue: Vec::new(),
        slots: 3,
        most_in_flight: 0,
        submitted: Vec::new(),
    };
    let par_saves = saved_states(|save| par.run_pool(&mut pool, save));
    assert_eq!(pool.most_in_flight, 3, "the pool was kept busy");
    // Some cycle's child went out before an earlier cycle's (its tournament was ready first).
    assert!(
        pool.submitted.windows(2).any(|w| w[1] < w[0]),
        "{:?}",
        pool.submitted
    );
    // Every saved state, not only the last, is the sequential one: a resume sees no
    // difference either.
    assert_eq!(par_saves, seq_saves);
}

#[test]
fn threads_with_their_own_chains_give_the_sequential_search() {
    use nanoeye_search::Rea;
    let d = tempfile::tempdir().unwrap();
    let (ds, c, run) = search_fixture(d.path());
    // With fine-tuning (φ moves), so each thread's chain computes its own PSF stacks.
    let cfg = nanoeye_search::ReaConfig {
        population: 3,
        cycles: 4,
        ..rea_cfg()
    };
    let seq_saves =
        saved_states(|save| Rea::new(&c, &ds, &ds, &run, cfg.clone()).unwrap().run(save));
    let c2 = chain(&ds);
    let mut par = Rea::new(&c, &ds, &ds, &run, cfg).unwrap();
    let par_saves = saved_states(|save| par.run_threads(&[&c, &c2], save));
    assert_eq!(par_saves.len(), 3 + 4);
    assert_eq!(par_saves, seq_saves);
}

#[test]
fn the_slip_head_refit_writes_the_layer_whose_error_it_reports() {
    let d = tempfile::tempdir().unwrap();
    let ds = dataset(d.path(), 6);
    let c = chain(&ds);
    let mut t = Trainer::new(&c, &ds, cfg(2), phase0(&c)).unwrap();
    for _ in 0..2 {
        t.train_step().unwrap();
    }
    let arch = Arch::min();
    t.recalibrate(&arch, 1).unwrap();
    let frames = t.all_frames().unwrap();
    assert_eq!(frames.inputs.iter().map(|x| x.n).sum::<usize>(), ds.len());
    // A memory bound below one batch still gives one whole batch, and no more.
    let one = t.frames_within(1).unwrap();
    assert_eq!((one.inputs.len(), one.targets_mm.len()), (1, 1));
    assert_eq!(one.inputs[0].data, frames.inputs[0].data);
    let before = t.net.head_out.w.value.clone();
    let fit = nanoeye_search::headfit::refit_slip_head(&mut t.net, &arch, &frames).unwrap();
    assert_eq!(fit.frames, ds.len());
    assert_ne!(before, t.net.head_out.w.value, "the layer did not change");
    // The network's own outputs after the refit give the in-sample error the solve reports
    // (the weights landed in the layout the forward pass reads), and the targets are read
    // in the same units.
    let (mut sse, mut scale) = ([0.0f64; 3], 0.0f64);
    for (x, y) in frames.inputs.iter().zip(&frames.targets_mm) {
        let o = t.net.forward(&arch, x, nanoeye_nets::BnMode::Eval).unwrap();
        for (k, (&p, &q)) in o.slip.data.iter().zip(&y.data).enumerate() {
            sse[k % 3] += (p as f64 - q as f64).powi(2);
            scale = scale.max((q as f64).abs());
        }
    }
    for (a, &e) in sse.iter().enumerate() {
        let rms = (e / fit.frames as f64).sqrt();
        assert!(
            (rms - fit.rmse_fit_mm[a]).abs() <= 1e-4 * scale.max(1.0),
            "axis {a}: network {rms} mm, solve {} mm ({fit:?})",
            fit.rmse_fit_mm[a]
        );
        assert!(fit.loo_rmse_mm[a].is_finite() && fit.loo_rmse_mm[a] >= fit.rmse_fit_mm[a]);
    }
    // The fit does not depend on the layer it replaces: subnets scored one after another on
    // one network (search pareto, the main job's min and max trackers) carry nothing over.
    nanoeye_search::headfit::recalibrate_and_refit(&mut t.net, &arch, &frames).unwrap();
    let (w, b) = (
        t.net.head_out.w.value.clone(),
        t.net.head_out.b.value.clone(),
    );
    t.net.head_out.w.value.iter_mut().for_each(|v| *v = 0.5);
    t.net.head_out.b.value.iter_mut().for_each(|v| *v = -3.0);
    nanoeye_search::headfit::recalibrate_and_refit(&mut t.net, &arch, &frames).unwrap();
    assert_eq!(
        (
            t.net.head_out.w.value.clone(),
            t.net.head_out.b.value.clone()
        ),
        (w, b)
    );
}

#[test]
fn a_search_with_the_head_refit_scores_the_model_the_main_job_deploys() {
    use nanoeye_search::{Rea, ReaConfig};
    let d = tempfile::tempdir().unwrap();
    let (ds, c, run) = search_fixture(d.path());
    let arch = Arch::min();
    let score = |head_refit| {
        let cfg = ReaConfig {
            epochs: 0.0,
            head_refit,
            ..rea_cfg()
        };
        let rea = Rea::new(&c, &ds, &ds, &run, cfg).unwrap();
        rea.evaluator().evaluate(0, &arch).unwrap()
    };
    let got = score(true);
    // By hand: BN over every training frame, the layer solved on them, then V.
    let mut t = Trainer::from_checkpoint(&c, &ds, &run).unwrap();
    let all = t.all_frames().unwrap();
    t.net.recalibrate_bn(&arch, &all.inputs).unwrap();
    nanoeye_search::headfit::refit_slip_head(&mut t.net, &arch, &all).unwrap();
    let want = t.validate(&ds, &arch).unwrap();
    assert_eq!(got.v, want.v_deg);
    assert_eq!(got.metrics.slip_mse, want.slip_mse);
    // The trained layer scores otherwise.
    assert_ne!(score(false).metrics.slip_mse, got.metrics.slip_mse);
}

#[test]
fn a_search_with_bn_over_every_frame_scores_as_the_main_job_recalibrates() {
    use nanoeye_search::{BnBatches, Rea, ReaConfig};
    let d = tempfile::tempdir().unwrap();
    let (ds, c, run) = search_fixture(d.path());
    let arch = Arch::min();
    let score = |recal_batches| {
        let cfg = ReaConfig {
            epochs: 0.0,
            recal_batches,
            ..rea_cfg()
        };
        let rea = Rea::new(&c, &ds, &ds, &run, cfg).unwrap();
        rea.evaluator().evaluate(0, &arch).unwrap()
    };
    let got = score(BnBatches::All);
    // By hand, as `nanoeye run` deploys the pick: BN over every training frame, then V with
    // the trained head.
    let mut t = Trainer::from_checkpoint(&c, &ds, &run).unwrap();
    let all = t.all_frames().unwrap();
    assert_eq!(all.inputs.iter().map(|x| x.n).sum::<usize>(), ds.len());
    t.net.recalibrate_bn(&arch, &all.inputs).unwrap();
    let want = t.validate(&ds, &arch).unwrap();
    assert_eq!(got.v, want.v_deg);
    assert_eq!(got.metrics.slip_mse, want.slip_mse);
    // One batch's statistics are other statistics.
    assert_ne!(
        score(BnBatches::Count(1)).metrics.slip_mse,
        got.metrics.slip_mse
    );
    // A count that cannot be held is refused after one batch, naming the setting.
    let e = t.recalibration_inputs(usize::MAX).unwrap_err().to_string();
    assert!(e.contains("bn_batches") && e.contains("MiB"), "{e}");
}

//! Regularized evolution (S17, S19–S21, B.3) over subnet architectures, each candidate scored
//! by the inner loop (S16, S18, S20): weights, φ and p̂ inherited from the trained run, a short
//! fine-tune with the MAC-budget hinge, then V on the validation set.
//!
//! Scores: v = V (mean angular gaze error, degrees; lower is better), and the S19 fitness,
//! maximised, = −v − γ·𝕀(C_total > C_budget). Aging: each cycle removes the oldest
//! individual, not the worst. Every draw of cycle c comes from ChaCha8(seed, stream c), so a
//! resumed search repeats the uninterrupted one exactly; the state (population, history,
//! next id) is one atomic JSON file rewritten after every evaluation.

use crate::bn::BnBatches;
use crate::chain::CameraChain;
use crate::error::{Result, param};
use crate::train::{Budget, Metrics, Trainer};
use nanoeye_datagen::render::Dataset;
use nanoeye_nets::Arch;
use rand::SeedableRng;
use rand::seq::index::sample;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::sync::{Mutex, mpsc};

/// REA hyper-parameters; defaults are Table S1's.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ReaConfig {
    /// Evolution cycles N_iter.
    pub cycles: usize,
    /// Population size P.
    pub population: usize,
    /// Tournament size k.
    pub tournament: usize,
    /// Inner-loop fine-tuning epochs.
    pub epochs: f64,
    /// Budget penalty γ of S19.
    pub gamma: f64,
    /// Mutation rate per layer.
    pub mutation_rate: f64,
    /// MAC budget C_budget (0: none).
    pub budget_macs: u64,
    /// Weight λ of the budget hinge in the inner loop (S16), on C/C_budget − 1.
    pub lambda_budget: f64,
    /// Learning-rate scale of the fine-tune relative to the run's.
    pub lr_scale: f64,
    /// BN recalibration set before each evaluation: every training frame (the default) or a
    /// count of training batches (2 until 2026-12-02); unused with `head_refit` (every frame
    /// then). A state written when this was a bare count reads as that count.
    pub recal_batches: BnBatches,
    /// Evaluate each candidate as `nanoeye run` deploys it: BN statistics over every training
    /// frame and the calibration head's output layer solved on them
    /// ([`crate::headfit::refit_slip_head`]). Off in Table S1's search.
    #[serde(default)]
    pub head_refit: bool,
    /// Start each candidate's inner loop at the smallest p̂ of the run's range at which it fits
    /// the budget ([`Trainer::fit_pitch_to_budget`]) instead of the inherited p_init (S18), which
    /// the hinge alone moves by about the pitch's learning rate a step. Off in Table S1's search.
    #[serde(default)]
    pub fit_pitch: bool,
    /// Seed.
    pub seed: u64,
}

impl Default for ReaConfig {
    /// Table S1: N_iter 150, P 100, k 10, 3 epochs, γ 10, rate 0.1.
    fn default() -> Self {
        ReaConfig {
            cycles: 150,
            population: 100,
            tournament: 10,
            epochs: 3.0,
            gamma: 10.0,
            mutation_rate: 0.1,
            budget_macs: 0,
            lambda_budget: 1.0,
            lr_scale: 0.1,
            // Two batches moved a candidate's V by 1–3° on average (up to 7°) against every
            // frame, as much as the tournaments decide on (docs/run.md, thirty-eighth session).
            recal_batches: BnBatches::All,
            head_refit: false,
            fit_pitch: false,
            seed: 0,
        }
    }
}

impl ReaConfig {
    /// The budget of each candidate's inner loop.
    pub fn budget(&self) -> Budget {
        Budget {
            macs: self.budget_macs,
            lambda: self.lambda_budget,
            fit_pitch: self.fit_pitch,
        }
    }

    /// Checks every field, naming the bad one.
    pub fn validate(&self) -> Result<()> {
        if self.population == 0 || self.population > 100_000 {
            return Err(param("population", "must be 1..=100000"));
        }
        if self.tournament == 0 || self.tournament > self.population {
            return Err(param(
                "tournament",
                format!(
                    "must be 1..=population ({}), got {}",
                    self.population, self.tournament
                ),
            ));
        }
        if self.cycles > 10_000_000 {
            return Err(param("cycles", "at most 1e7"));
        }
        if !(self.epochs.is_finite() && (0.0..=1000.0).contains(&self.epochs)) {
            return Err(param(
                "epochs",
                format!("must lie in [0, 1000], got {}", self.epochs),
            ));
        }
        for (n, v) in [
            ("gamma", self.gamma),
            ("lambda_budget", self.lambda_budget),
            ("lr_scale", self.lr_scale),
        ] {
            if !(v.is_finite() && (0.0..=1e6).contains(&v)) {
                return Err(param(n, format!("must be finite in [0, 1e6], got {v}")));
            }
        }
        if !(0.0..=1.0).contains(&self.mutation_rate) {
            return Err(param("mutation_rate", "must lie in [0, 1]"));
        }
        Ok(())
    }
}

/// One evaluated architecture.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Individual {
    /// Id (order of creation).
    pub id: usize,
    /// The architecture.
    pub arch: Arch,
    /// C_total at its fine-tuned p̂ (MACs, S23).
    pub macs: u64,
    /// V (degrees).
    pub v: f64,
    /// S19 fitness (maximised).
    pub fitness: f64,
    /// p̂ after fine-tuning (µm).
    pub pitch_um: f64,
    /// Validation details.
    pub metrics: Metrics,
}

/// One cycle of S19–S21, as written to rea.jsonl.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CycleRecord {
    /// Cycle index.
    pub cycle: usize,
    /// Population ids before the update, oldest first.
    pub population: Vec<usize>,
    /// Tournament ids.
    pub tournament: Vec<usize>,
    /// Parent id (the tournament's argmax of fitness).
    pub parent: usize,
    /// The child: {id, arch, macs, fitness, v, pitch_um}.
    pub child: ChildRecord,
    /// Id removed (the oldest).
    pub removed: usize,
}

/// The child of a cycle.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ChildRecord {
    /// Id.
    pub id: usize,
    /// Architecture.
    pub arch: Arch,
    /// MACs.
    pub macs: u64,
    /// Fitness.
    pub fitness: f64,
    /// V (degrees).
    pub v: f64,
    /// p̂ after its inner loop (µm); 0 in records written before this field existed.
    #[serde(default)]
    pub pitch_um: f64,
}

/// The resumable state of a search.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ReaState {
    /// The configuration it was started with.
    pub config: ReaConfig,
    /// Every individual evaluated, by id.
    pub evaluated: Vec<Individual>,
    /// Current population ids, oldest first.
    pub population: VecDeque<usize>,
    /// Cycles done.
    pub history: Vec<CycleRecord>,
}

impl ReaState {
    /// What a search could have written, checked before a resume trusts it (an edited state
    /// with an empty population panicked drawing a tournament; a history repeated five times
    /// reported 15 cycles of 3; a fitness of 1e308 was picked as best). A search commits its
    /// individuals in id order, the first `population` of them the initial population and
    /// each later one the child of cycle id − population, which adds it to the population and
    /// ages out the oldest: so ids run 0, 1, …; the population holds min(evaluated,
    /// population) distinct evaluated ids; there is one cycle record per child, naming it and
    /// evaluated ids only; and scores are finite.
    pub fn check(&self) -> std::result::Result<(), String> {
        let (n, c) = (self.evaluated.len(), &self.config);
        if n > c.population + c.cycles {
            return Err(format!(
                "{n} individuals, more than the {} initial and {} children of this search",
                c.population, c.cycles
            ));
        }
        if let Some((i, x)) = self.evaluated.iter().enumerate().find(|(i, x)| x.id != *i) {
            return Err(format!("evaluated[{i}] has id {}", x.id));
        }
        if let Some(x) = self.evaluated.iter().find(|x| {
            !(x.v.is_finite() && x.fitness.is_finite() && x.pitch_um.is_finite())
                || x.v < 0.0
                || x.fitness.abs() > 1e9
        }) {
            return Err(format!("individual {} has a score no search gives", x.id));
        }
        let mut seen = vec![false; n];
        for &id in &self.population {
            if id >= n || std::mem::replace(&mut seen[id], true) {
                return Err(format!("population id {id} is unknown or repeated"));
            }
        }
        if self.population.len() != n.min(c.population) {
            return Err(format!(
                "a population of {} where {n} evaluated individuals make {}",
                self.population.len(),
                n.min(c.population)
            ));
        }
        if self.history.len() != n.saturating_sub(c.population) {
            return Err(format!(
                "{} cycle records for {} children",
                self.history.len(),
                n.saturating_sub(c.population)
            ));
        }
        for (k, h) in self.history.iter().enumerate() {
            let ids = h.population.iter().chain(&h.tournament);
            let unknown = ids.chain([&h.parent, &h.removed]).any(|&id| id >= n);
            if h.cycle != k || h.child.id != c.population + k || unknown {
                return Err(format!(
                    "cycle record {k} does not fit the evaluated individuals"
                ));
            }
        }
        Ok(())
    }
}

/// Scores candidates with the inner loop; what a process evaluating candidates for a
/// search needs (cheap to clone: references and the configuration).
#[derive(Clone)]
pub struct Evaluator<'a> {
    chain: &'a CameraChain,
    train: &'a Dataset,
    val: &'a Dataset,
    run: PathBuf,
    config: ReaConfig,
}

/// Evaluates the candidates of [`Rea::run_pool`], possibly several at once and elsewhere
/// (other threads, processes or machines). Results may come back in any order.
pub trait EvalPool {
    /// Candidates it evaluates at once (at least 1).
    fn slots(&self) -> usize;
    /// Starts evaluating candidate `id` with architecture `arch`.
    fn submit(&mut self, id: usize, arch: &Arch) -> Result<()>;
    /// Waits for a submitted candidate to finish and returns it.
    fn next(&mut self) -> Result<Individual>;
}

/// The pool of one: evaluates each candidate when its result is asked for.
struct Inline<'a> {
    eval: Evaluator<'a>,
    queue: VecDeque<(usize, Arch)>,
}

impl EvalPool for Inline<'_> {
    fn slots(&self) -> usize {
        1
    }
    fn submit(&mut self, id: usize, arch: &Arch) -> Result<()> {
        self.queue.push_back((id, arch.clone()));
        Ok(())
    }
    fn next(&mut self) -> Result<Individual> {
        let (id, arch) = self
            .queue
            .pop_front()
            .ok_or_else(|| param("pool", "next() with nothing submitted"))?;
        self.eval.evaluate(id, &arch)
    }
}

/// Threads of this process, one [`Evaluator`] each, fed through a channel: what
/// [`Rea::run_threads`] hands to [`Rea::run_pool`].
struct Threads {
    slots: usize,
    tasks: mpsc::Sender<(usize, Arch)>,
    results: mpsc::Receiver<Result<Individual>>,
}

fn stopped() -> crate::error::SearchError {
    param("pool", "the evaluating threads have stopped")
}

impl EvalPool for Threads {
    fn slots(&self) -> usize {
        self.slots
    }
    fn submit(&mut self, id: usize, arch: &Arch) -> Result<()> {
        self.tasks.send((id, arch.clone())).map_err(|_| stopped())
    }
    fn next(&mut self) -> Result<Individual> {
        self.results.recv().map_err(|_| stopped())?
    }
}

/// A cycle whose child was sent out: what its record needs once the child is back.
struct Dispatched {
    population: Vec<usize>,
    tournament: Vec<usize>,
    parent: usize,
}

/// The search over one trained run.
pub struct Rea<'a> {
    chain: &'a CameraChain,
    train: &'a Dataset,
    val: &'a Dataset,
    run: PathBuf,
    /// State.
    pub state: ReaState,
}

impl Evaluator<'_> {
    /// The inner loop for `arch`: inherit, fine-tune `epochs`, recalibrate BN, validate.
    pub fn evaluate(&self, id: usize, arch: &Arch) -> Result<Individual> {
        let c = &self.config;
        let mut t = Trainer::from_checkpoint(self.chain, self.train, &self.run)?;
        let budget = c.budget();
        if budget.fit_pitch {
            t.fit_pitch_to_budget(arch, budget.macs)?;
        }
        let steps = (c.epochs * t.batches_per_epoch() as f64).round() as usize;
        let mut macs = 0;
        for _ in 0..steps {
            macs = t.finetune_step(arch, &budget, c.lr_scale)?.1;
        }
        let m = if c.head_refit {
            let all = t.all_frames()?;
            crate::headfit::recalibrate_and_refit(&mut t.net, arch, &all)?;
            t.validate(self.val, arch)?
        } else {
            let inputs = t.bn_inputs(c.recal_batches)?;
            t.net.recalibrate_bn(arch, &inputs)?;
            t.validate(self.val, arch)?
        };
        // With the fit, at the p̂ the candidate leaves with (the one its record names); without
        // it, at the last step's p̂, as the search always counted.
        if steps == 0 || budget.fit_pitch {
            macs = t.macs_at(arch, t.pitch_um)?;
        }
        let over = c.budget_macs > 0 && macs > c.budget_macs;
        Ok(Individual {
            id,
            arch: arch.clone(),
            macs,
            v: m.v_deg,
            fitness: -m.v_deg - if over { c.gamma } else { 0.0 },
            pitch_um: t.pitch_um,
            metrics: m,
        })
    }
}

impl<'a> Rea<'a> {
    /// A search starting from run checkpoint `run` (the trained supernet, φ and p̂).
    pub fn new(
        chain: &'a CameraChain,
        train: &'a Dataset,
        val: &'a Dataset,
        run: &Path,
        config: ReaConfig,
    ) -> Result<Rea<'a>> {
        config.validate()?;
        crate::train::read_config(run)?;
        Ok(Rea {
            chain,
            train,
            val,
            run: run.to_path_buf(),
            state: ReaState {
                config,
                evaluated: Vec::new(),
                population: VecDeque::new(),
                history: Vec::new(),
            },
        })
    }

    /// Restores the state file at `path` (refused if its configuration differs).
    pub fn resume(&mut self, path: &Path) -> Result<()> {
        let text = std::fs::read_to_string(path)
            .map_err(|e| param("state", format!("{}: {e}", path.display())))?;
        let st: ReaState = serde_json::from_str(&text)
            .map_err(|e| param("state", format!("{}: {e}", path.display())))?;
        if st.config != self.state.config {
            return Err(param(
                "state",
                format!(
                    "{} holds a search with other parameters ({}); give the same ones, or \
                     search a copy of the trained run in another directory",
                    path.display(),
                    crate::error::differences(&st.config, &self.state.config)
                ),
            ));
        }
        st.check()
            .map_err(|why| param("state", format!("{}: {why}", path.display())))?;
        self.state = st;
        Ok(())
    }

    fn rng(&self, stream: u64) -> ChaCha8Rng {
        let mut r = ChaCha8Rng::seed_from_u64(self.state.config.seed);
        r.set_stream(stream);
        r
    }

    /// The evaluator of this search's candidates.
    pub fn evaluator(&self) -> Evaluator<'a> {
        Evaluator {
            chain: self.chain,
            train: self.train,
            val: self.val,
            run: self.run.clone(),
            config: self.state.config.clone(),
        }
    }

    /// The inner loop for `arch`: inherit, fine-tune `epochs`, recalibrate BN, validate.
    pub fn evaluate(&self, id: usize, arch: &Arch) -> Result<Individual> {
        self.evaluator().evaluate(id, arch)
    }

    /// Runs (or continues) the search; `save` is called after every evaluation with the state.
    pub fn run(&mut self, save: &mut dyn FnMut(&ReaState) -> Result<()>) -> Result<()> {
        let mut pool = Inline {
            eval: self.evaluator(),
            queue: VecDeque::new(),
        };
        self.run_pool(&mut pool, save)
    }

    /// Runs (or continues) the search with `chains.len()` candidates evaluated at once, one
    /// thread per chain (their parallel parts share the rayon pool), with the result of
    /// [`Rea::run`]: same individuals, cycles and saved states. The chains must be built
    /// alike (as this search's own); each thread needs its own because a chain keeps the last
    /// PSF stack it computed.
    pub fn run_threads(
        &mut self,
        chains: &[&CameraChain],
        save: &mut dyn FnMut(&ReaState) -> Result<()>,
    ) -> Result<()> {
        if chains.len() <= 1 {
            return self.run(save);
        }
        let (task_tx, task_rx) = mpsc::channel::<(usize, Arch)>();
        let task_rx = Mutex::new(task_rx);
        let (res_tx, res_rx) = mpsc::channel::<Result<Individual>>();
        let (train, val) = (self.train, self.val);
        let (run, config) = (self.run.clone(), self.state.config.clone());
        std::thread::scope(|s| {
            for &chain in chains {
                let ev = Evaluator {
                    chain,
                    train,
                    val,
                    run: run.clone(),
                    config: config.clone(),
                };
                let (rx, tx) = (&task_rx, res_tx.clone());
                s.spawn(move || {
                    loop {
                        // Only waiting for a task holds the lock, not evaluating one.
                        let task = match rx.lock() {
                            Ok(r) => r.recv(),
                            Err(_) => break,
                        };
                        let Ok((id, arch)) = task else { break };
                        // A panic becomes an error, so the search does not wait for it forever.
                        let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                            ev.evaluate(id, &arch)
                        }))
                        .unwrap_or_else(|_| {
                            Err(param("pool", format!("evaluating candidate {id} panicked")))
                        });
                        if tx.send(r).is_err() {
                            break;
                        }
                    }
                });
            }
            drop(res_tx);
            let mut pool = Threads {
                slots: chains.len(),
                tasks: task_tx,
                results: res_rx,
            };
            // Dropping the pool closes the task channel: idle threads leave, busy ones after
            // their candidate.
            self.run_pool(&mut pool, save)
        })
    }

    /// Population ids, oldest first, at the start of cycle `c` (≥ cycles done): the current
    /// population aged by the cycles in between, each of which adds its child (id P + cycle)
    /// and removes the oldest.
    fn population_at(&self, c: usize) -> Vec<usize> {
        let p = self.state.config.population;
        let h = self.state.history.len();
        let ahead = c - h;
        // Before the initial population is all in, the population of cycle 0 is ids 0..P.
        let base: Vec<usize> = if h == 0 && self.state.population.len() < p {
            (0..p).collect()
        } else {
            self.state.population.iter().copied().collect()
        };
        base.into_iter()
            .skip(ahead)
            .chain((h..c).map(|cc| p + cc).skip(ahead.saturating_sub(p)))
            .collect()
    }

    /// Runs (or continues) the search with candidates evaluated by `pool`, with the result
    /// of [`Rea::run`] (same individuals, cycles and state files): each cycle's draws come
    /// from its own stream and its population is known ahead (ids age out in order), so
    /// cycle c's tournament is known early, and its child (id P + c) is sent out as soon as
    /// every tournament member has been evaluated, possibly before earlier cycles' children
    /// (the parent is then the sequential one). Results are committed, and `save` called, in
    /// id order.
    pub fn run_pool(
        &mut self,
        pool: &mut dyn EvalPool,
        save: &mut dyn FnMut(&ReaState) -> Result<()>,
    ) -> Result<()> {
        let p = self.state.config.population;
        let cycles = self.state.config.cycles;
        let slots = pool.slots().max(1);
        // Initial population: P uniform draws (stream 0), evaluated in id order.
        let initial: Vec<Arch> = {
            let mut rng = self.rng(0);
            (0..p).map(|_| Arch::sample(&mut rng)).collect()
        };
        let mut next_initial = self.state.evaluated.len().min(p);
        let mut next_cycle = self.state.history.len();
        let mut back: std::collections::BTreeMap<usize, Individual> = Default::default();
        let mut sent: std::collections::BTreeMap<usize, Dispatched> = Default::default();
        // Each pending cycle's population, tournament and generator after the draw, once drawn.
        type Drawn = (Vec<usize>, Vec<usize>, ChaCha8Rng);
        let mut drawn: std::collections::BTreeMap<usize, Drawn> = Default::default();
        let mut in_flight = 0usize;
        loop {
            // Commit every result whose predecessors are in, in id order.
            while let Some(ind) = back.remove(&self.state.evaluated.len()) {
                let id = ind.id;
                if id < p {
                    self.state.evaluated.push(ind);
                    self.state.population.push_back(id);
                } else {
                    let d = sent
                        .remove(&(id - p))
                        .ok_or_else(|| param("pool", format!("candidate {id} was never sent")))?;
                    let rec = CycleRecord {
                        cycle: id - p,
                        removed: d.population[0],
                        population: d.population,
                        tournament: d.tournament,
                        parent: d.parent,
                        child: ChildRecord {
                            id,
                            arch: ind.arch.clone(),
                            macs: ind.macs,
                            fitness: ind.fitness,
                            v: ind.v,
                            pitch_um: ind.pitch_um,
                        },
                    };
                    self.state.evaluated.push(ind);
                    self.state.population.push_back(id);
                    self.state.population.pop_front();
                    self.state.history.push(rec);
                }
                save(&self.state)?;
            }
            if self.state.evaluated.len() >= p && self.state.history.len() >= cycles {
                return Ok(());
            }
            // Send out every candidate whose architecture is known, while slots are free.
            while in_flight < slots {
                if next_initial < p {
                    pool.submit(next_initial, &initial[next_initial])?;
                    next_initial += 1;
                    in_flight += 1;
                    continue;
                }
                // The lowest cycle not sent yet; any cycle in the P cycles from it whose
                // tournament is all evaluated goes out, in whatever order they become ready.
                while next_cycle < cycles
                    && (next_cycle < self.state.history.len() || sent.contains_key(&next_cycle))
                {
                    next_cycle += 1;
                }
                let fitness = |id: usize| {
                    self.state
                        .evaluated
                        .get(id)
                        .or_else(|| back.get(&id))
                        .map(|i| i.fitness)
                };
                let mut ready = None;
                for c in next_cycle..cycles.min(next_cycle + p) {
                    if sent.contains_key(&c) {
                        continue;
                    }
                    let (_, tour, _) = drawn.entry(c).or_insert_with(|| {
                        let mut rng = self.rng(c as u64 + 1);
                        let pop = self.population_at(c);
                        let k = self.state.config.tournament.min(pop.len());
                        let tour: Vec<usize> = sample(&mut rng, pop.len(), k)
                            .into_iter()
                            .map(|i| pop[i])
                            .collect();
                        (pop, tour, rng)
                    });
                    // A member still being evaluated may be the parent: wait for it.
                    if tour.iter().all(|&id| fitness(id).is_some()) {
                        ready = Some(c);
                        break;
                    }
                }
                let Some(c) = ready else {
                    break;
                };
                let Some((pop, tour, mut rng)) = drawn.remove(&c) else {
                    break;
                };
                // argmax of fitness; ties go to the earlier tournament member.
                let parent = *tour
                    .iter()
                    .reduce(|a, b| {
                        // An unevaluated member (none is, once the cycle is ready) ranks last.
                        let up = match (fitness(*b), fitness(*a)) {
                            (Some(fb), Some(fa)) => fitter(fb, fa),
                            (Some(_), None) => true,
                            (None, _) => false,
                        };
                        if up { b } else { a }
                    })
                    .expect("k ≥ 1");
                let parent_arch = match self.state.evaluated.get(parent) {
                    Some(i) => &i.arch,
                    None => &back[&parent].arch,
                };
                let child_arch = parent_arch.mutate(&mut rng, self.state.config.mutation_rate)?;
                pool.submit(p + c, &child_arch)?;
                sent.insert(
                    c,
                    Dispatched {
                        population: pop,
                        tournament: tour,
                        parent,
                    },
                );
                in_flight += 1;
            }
            if in_flight == 0 {
                return Err(param(
                    "pool",
                    "nothing to evaluate and the search is not done",
                ));
            }
            let ind = pool.next()?;
            in_flight -= 1;
            if ind.id >= p + cycles || ind.id < self.state.evaluated.len() {
                return Err(param(
                    "pool",
                    format!("candidate {} came back unexpectedly", ind.id),
                ));
            }
            back.insert(ind.id, ind);
        }
    }

    /// The search's pick among every individual evaluated ([`pick_best`] under its budget).
    pub fn best(&self) -> Option<&Individual> {
        pick_best(&self.state.evaluated, self.state.config.budget_macs)
    }
}

/// Whether fitness `b` ranks strictly above `a`: as numbers, with a NaN below every number, −∞
/// included (first in a list, a NaN would otherwise beat all: no comparison with it is true).
fn fitter(b: f64, a: f64) -> bool {
    match (a.is_nan(), b.is_nan()) {
        (_, true) => false,
        (true, false) => true,
        (false, false) => b > a,
    }
}

/// The individual a search deploys: the best S19 fitness among those within `budget_macs`
/// (C ≤ C_budget; every one when the budget is 0, none), so the lowest V there; only when
/// none fits, the best fitness overall. S19's penalty γ steers the parents, but a subnet over
/// the budget whose V beats every one within it by more than γ would win the plain argmax
/// (the main job's seed 0 picked 238 M MACs against its 40 M budget that way). Ties go to the
/// earlier individual.
pub fn pick_best(evaluated: &[Individual], budget_macs: u64) -> Option<&Individual> {
    fn argmax<'a>(it: impl Iterator<Item = &'a Individual>) -> Option<&'a Individual> {
        it.reduce(|a, b| if fitter(b.fitness, a.fitness) { b } else { a })
    }
    let fits = |i: &&Individual| budget_macs == 0 || i.macs <= budget_macs;
    argmax(evaluated.iter().filter(fits)).or_else(|| argmax(evaluated.iter()))
}

#[cfg(test)]
mod props {
    use super::*;
    use proptest::prelude::*;

    fn individual(id: usize, macs: u64, fitness: f64) -> Individual {
        Individual {
            id,
            arch: Arch::min(),
            macs,
            v: -fitness,
            fitness,
            pitch_um: 14.0,
            metrics: Metrics {
                v_deg: -fitness,
                median_deg: 0.0,
                failures: 0,
                dice: 0.0,
                slip_mse: 0.0,
                frames: 1,
            },
        }
    }

    /// The cases a NaN first in the list decided: it now loses to any number, −∞ included.
    #[test]
    fn a_nan_fitness_loses_to_any_number() {
        for f in [f64::NEG_INFINITY, -f64::MAX, -3.0, 0.0] {
            let ind = [individual(0, 5, f64::NAN), individual(1, 5, f)];
            assert_eq!(pick_best(&ind, 0).map(|i| i.id), Some(1), "{f}");
            assert_eq!(pick_best(&ind, 10).map(|i| i.id), Some(1), "{f}");
        }
        let nan = [individual(0, 5, f64::NAN), individual(1, 5, f64::NAN)];
        assert_eq!(pick_best(&nan, 0).map(|i| i.id), Some(0));
    }

    proptest! {
        /// Any MACs, fitnesses (infinities and NaN among them) and budget: the pick fits the
        /// budget when any individual does; no individual it considers has a higher fitness,
        /// a NaN is never picked over a number, and ties go to the earliest.
        #[test]
        fn the_pick_is_the_fittest_within_the_budget(
            v in prop::collection::vec(
                (
                    prop_oneof![0..100u64, any::<u64>()],
                    prop_oneof![
                        4 => -180.0..0.0f64,
                        1 => prop::sample::select(vec![
                            f64::NAN, f64::INFINITY, f64::NEG_INFINITY, -f64::MAX, -10.0,
                        ]),
                    ],
                ),
                0..30,
            ),
            budget in prop_oneof![Just(0u64), 0..100u64, any::<u64>()],
        ) {
            let ind: Vec<Individual> =
                v.iter().enumerate().map(|(i, &(m, f))| individual(i, m, f)).collect();
            let Some(p) = pick_best(&ind, budget) else {
                prop_assert!(ind.is_empty());
                return Ok(());
            };
            let fits = |i: &Individual| budget == 0 || i.macs <= budget;
            let pool: Vec<&Individual> = if ind.iter().any(fits) {
                prop_assert!(fits(p));
                ind.iter().filter(|i| fits(i)).collect()
            } else {
                ind.iter().collect()
            };
            for i in &pool {
                prop_assert!(
                    i.fitness.partial_cmp(&p.fitness) != Some(std::cmp::Ordering::Greater),
                    "{} beats the pick {}",
                    i.fitness,
                    p.fitness
                );
                if p.fitness.is_nan() {
                    prop_assert!(i.fitness.is_nan());
                }
                if i.fitness == p.fitness {
                    prop_assert!(p.id <= i.id);
                }
            }
        }
    }
}

//! `nanoeye compare`: finished main-job runs side by side. One run's protocol error moves by
//! about ±2° with the seed alone (docs/run.md), so a lens or a setting is judged on paired
//! differences over seeds: runs whose configurations differ only in `seed` form a group; within
//! a group the learned lens is set against each fixed lens run by run, and two groups are set
//! against each other seed by seed, each difference as a mean with its standard error.

use crate::run::{LENSES, RunConfig};
use crate::util;
use anyhow::{Context, Result, bail};
use clap::Args;
use serde::Serialize;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// Most runs one comparison reads (each a config.json and a result.json held in memory).
const MAX_RUNS: usize = 1000;

/// Largest metric value read: far beyond any error in degrees or mm, and small enough that
/// the squares in a standard error stay finite (a value of 1e308 made it null).
const MAX_VALUE: f64 = 1e9;
/// Largest effective pitch a run's result may report (µm): a sensor pixel of 1 mm.
const MAX_PITCH_UM: f64 = 1000.0;

/// Up to this many groups every pair is compared; beyond, each group against group A only
/// (the pairs, and the text, grow with the square of the groups).
const ALL_PAIRS_GROUPS: usize = 8;

/// The protocol summary's field that `nanoeye compare` sets side by side (lower is better for
/// all but `dice`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
#[value(rename_all = "snake_case")]
pub enum Metric {
    /// Mean gaze error (deg).
    MeanDeg,
    /// Median gaze error (deg).
    MedianDeg,
    /// 95th-percentile gaze error (deg).
    P95Deg,
    /// RMS error of the tracked slippage (mm).
    SlipRmseMm,
    /// Dice of the predicted pupil mask (1: perfect).
    Dice,
}

impl Metric {
    /// Its key in result.json's protocol and demo summaries.
    pub fn key(self) -> &'static str {
        match self {
            Metric::MeanDeg => "mean_deg",
            Metric::MedianDeg => "median_deg",
            Metric::P95Deg => "p95_deg",
            Metric::SlipRmseMm => "slip_rmse_mm",
            Metric::Dice => "dice",
        }
    }

    /// The values the metric can take: Dice in [0, 1], errors in [0, MAX_VALUE].
    fn range(self) -> std::ops::RangeInclusive<f64> {
        match self {
            Metric::Dice => 0.0..=1.0,
            _ => 0.0..=MAX_VALUE,
        }
    }

    /// Whether a higher value is the better one (Dice; every error is better lower).
    pub fn higher_is_better(self) -> bool {
        self == Metric::Dice
    }

    /// "lowest" or "highest": the better end of the metric, in words.
    fn best_word(self) -> &'static str {
        if self.higher_is_better() {
            "highest"
        } else {
            "lowest"
        }
    }

    /// Orders two values better first (`Less`: `a` is the better one).
    fn cmp_better(self, a: f64, b: f64) -> std::cmp::Ordering {
        if self.higher_is_better() {
            b.total_cmp(&a)
        } else {
            a.total_cmp(&b)
        }
    }

    /// Its unit as printed after a number.
    fn unit(self) -> &'static str {
        match self {
            Metric::SlipRmseMm => " mm",
            Metric::Dice => "",
            _ => "°",
        }
    }

    /// The plot's axis title.
    fn title(self) -> &'static str {
        match self {
            Metric::MeanDeg => "protocol mean gaze error (°)",
            Metric::MedianDeg => "protocol median gaze error (°)",
            Metric::P95Deg => "protocol 95th-percentile gaze error (°)",
            Metric::SlipRmseMm => "protocol slippage RMS error (mm)",
            Metric::Dice => "protocol pupil Dice",
        }
    }
}

/// `nanoeye compare` options.
#[derive(Debug, Args)]
pub struct CompareArgs {
    /// Output folders of finished `nanoeye run` jobs (config.json and result.json in each).
    #[arg(required = true)]
    runs: Vec<PathBuf>,
    /// The protocol summary's field to compare.
    #[arg(long, value_enum, default_value = "mean_deg")]
    metric: Metric,
    /// Also draw every run's error per lens, by group, with lines joining equal seeds, as an
    /// SVG written to this path.
    #[arg(long)]
    svg: Option<PathBuf>,
    /// Print JSON.
    #[arg(long)]
    json: bool,
}

/// Mean of paired differences a − b (in the metric's unit) with its standard error.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Paired {
    /// Number of pairs.
    pub n: usize,
    /// Mean difference.
    pub mean: f64,
    /// Standard error of the mean: the sample standard deviation over √n; absent for one pair.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub se: Option<f64>,
    /// Pairs in which a is lower than b.
    pub lower: usize,
}

impl Paired {
    /// The summary of the differences `d` (deg); `d` is not empty.
    fn of(d: &[f64]) -> Paired {
        let n = d.len();
        let mean = d.iter().sum::<f64>() / n as f64;
        let se = (n > 1).then(|| {
            let var = d.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
            (var / n as f64).sqrt()
        });
        Paired {
            n,
            mean,
            se,
            lower: d.iter().filter(|&&x| x < 0.0).count(),
        }
    }

    fn text(&self, unit: &str) -> String {
        let se = self.se.map_or(String::new(), |s| format!(" ± {s:.2}"));
        format!("{:+.2}{se}{unit}", self.mean)
    }
}

/// One finished run.
#[derive(Debug, Clone, Serialize)]
pub struct RunRow {
    /// Its output folder.
    pub run: String,
    /// Its `seed`.
    pub seed: u64,
    /// Name of its group (A, B, …).
    pub group: String,
    /// The protocol's metric per lens, in [`lens_names`] order.
    pub values: Vec<f64>,
    /// The demo sequence's metric, where the run has one.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub demo: Option<f64>,
    /// MACs of the selected subnet.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub macs: Option<u64>,
    /// The learned lens's final p̂ (µm).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pitch_um: Option<f64>,
    /// The lens with the best value of the metric (the lowest; the highest for `dice`).
    pub best: String,
}

/// Runs that differ only in `seed`.
#[derive(Debug, Clone, Serialize)]
pub struct Group {
    /// A, B, … in the order of the first run of each.
    pub name: String,
    /// The configuration keys that tell this group from the others, with this group's values.
    pub differs: serde_json::Map<String, serde_json::Value>,
    /// Its runs' seeds, ascending.
    pub seeds: Vec<u64>,
    /// Mean over its runs of the metric per lens, in [`lens_names`] order.
    pub mean: Vec<f64>,
    /// Mean of the demo sequence's metric over its runs that have one.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub demo_mean: Option<f64>,
    /// The learned lens's error minus each fixed lens's, run by run (fixed lenses in
    /// [`lens_names`] order after the first).
    pub learned_minus: Vec<Paired>,
    /// Runs in which the learned lens has the best value (the lowest; the highest for `dice`).
    pub learned_best: usize,
}

/// Group b against group a on their common seeds.
#[derive(Debug, Clone, Serialize)]
pub struct Versus {
    /// The later group's name.
    pub b: String,
    /// The earlier group's name.
    pub a: String,
    /// Common seeds, ascending.
    pub seeds: Vec<u64>,
    /// b − a per lens, seed by seed, in [`lens_names`] order.
    pub per_lens: Vec<Paired>,
    /// b − a on the demo sequence, where both runs of a seed have one.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub demo: Option<Paired>,
}

/// The whole comparison.
#[derive(Debug, Clone, Serialize)]
pub struct Comparison {
    /// The protocol's field compared.
    pub metric: Metric,
    /// Lens names, the learned lens first.
    pub lenses: Vec<String>,
    pub runs: Vec<RunRow>,
    pub groups: Vec<Group>,
    pub versus: Vec<Versus>,
}

/// The main job's lens names, the learned lens first.
pub fn lens_names() -> Vec<String> {
    LENSES.iter().map(|(n, _)| n.to_string()).collect()
}

/// Reads one run: its configuration as JSON without `seed` (keys an older run lacks take
/// today's defaults, which by the job's rule keep the behaviour it had), and its row.
fn load(dir: &Path, lenses: &[String], metric: Metric) -> Result<(serde_json::Value, RunRow)> {
    let d = dir.display();
    let cpath = dir.join("config.json");
    // Regular files of bounded size: a FIFO blocked the read, `/dev/zero` was read until
    // memory ran out (and was then reported as a job not finished).
    let Some(text) = util::read_record(&cpath, util::MAX_RECORD_BYTES)? else {
        bail!("{d}: no config.json; is it the --out of `nanoeye run`?");
    };
    let cfg: RunConfig = serde_json::from_str(&text)
        .with_context(|| format!("{}: not a run configuration", cpath.display()))?;
    let mut config = serde_json::to_value(&cfg)?;
    if let Some(m) = config.as_object_mut() {
        m.remove("seed");
    }
    let rpath = dir.join("result.json");
    let Some(text) = util::read_record(&rpath, util::MAX_RECORD_BYTES)? else {
        bail!(
            "{d}: no result.json, the job has not finished (resume it: `nanoeye run --out {d}` \
             with its configuration)"
        );
    };
    let r: serde_json::Value =
        serde_json::from_str(&text).with_context(|| format!("{}: not JSON", rpath.display()))?;
    let key = metric.key();
    let range = metric.range();
    let value = |v: &serde_json::Value, what: &str| match v.as_f64() {
        Some(x) if range.contains(&x) => Ok(x),
        _ => Err(anyhow::anyhow!(
            "{}: {what} is missing or not a value in [{}, {:e}]",
            rpath.display(),
            range.start(),
            range.end()
        )),
    };
    let mut values = Vec::with_capacity(lenses.len());
    for lens in lenses {
        values.push(value(
            &r["protocol"][lens][key],
            &format!("protocol.{lens}.{key}"),
        )?);
    }
    // Optional, but when present a value like the protocol's: a demo of 1e308 printed its
    // mean as null and inf with exit 0.
    let optional = |v: &serde_json::Value, what: &str| match v {
        serde_json::Value::Null => Ok(None),
        v => value(v, what).map(Some),
    };
    let demo = optional(&r["demo_sequence"][key], &format!("demo_sequence.{key}"))?;
    let pitch_um = match r["pitch_um"].as_f64() {
        None => None,
        Some(p) if p > 0.0 && p <= MAX_PITCH_UM => Some(p),
        Some(p) => bail!(
            "{}: pitch_um {p} is not in (0, {MAX_PITCH_UM}] µm",
            rpath.display()
        ),
    };
    let best = lenses[values
        .iter()
        .enumerate()
        .min_by(|a, b| metric.cmp_better(*a.1, *b.1))
        .map_or(0, |(k, _)| k)]
    .clone();
    Ok((
        config,
        RunRow {
            run: d.to_string(),
            seed: cfg.seed,
            group: String::new(),
            values,
            demo,
            macs: r["macs"].as_u64(),
            pitch_um,
            best,
        },
    ))
}

/// Groups the runs by configuration (`seed` aside) and sets them against each other.
pub fn compare(dirs: &[PathBuf], metric: Metric) -> Result<Comparison> {
    if dirs.is_empty() {
        bail!("RUNS: give at least one run folder");
    }
    if dirs.len() > MAX_RUNS {
        bail!("RUNS: at most {MAX_RUNS} runs, got {}", dirs.len());
    }
    let lenses = lens_names();
    let mut keys: Vec<serde_json::Value> = Vec::new();
    let mut runs: Vec<RunRow> = Vec::with_capacity(dirs.len());
    let mut group_of = Vec::with_capacity(dirs.len());
    for dir in dirs {
        let (key, mut row) = load(dir, &lenses, metric)?;
        let g = match keys.iter().position(|k| *k == key) {
            Some(g) => g,
            None => {
                keys.push(key);
                keys.len() - 1
            }
        };
        if let Some(k) = (0..runs.len()).find(|&k| group_of[k] == g && runs[k].seed == row.seed) {
            let other: &RunRow = &runs[k];
            bail!(
                "RUNS: {} and {} have the same configuration and seed {}; give one of them",
                other.run,
                row.run,
                row.seed
            );
        }
        row.group = group_name(g);
        group_of.push(g);
        runs.push(row);
    }
    // The keys on which the groups' configurations do not all agree.
    let varying: Vec<String> = keys[0]
        .as_object()
        .map(|m| {
            m.keys()
                .filter(|k| keys.iter().any(|c| c[k.as_str()] != keys[0][k.as_str()]))
                .cloned()
                .collect()
        })
        .unwrap_or_default();
    let groups: Vec<Group> = keys
        .iter()
        .enumerate()
        .map(|(g, key)| {
            let members: Vec<&RunRow> = (0..runs.len())
                .filter(|&k| group_of[k] == g)
                .map(|k| &runs[k])
                .collect();
            summarize_group(g, key, &varying, &members, lenses.len(), metric)
        })
        .collect();
    let index: HashMap<(usize, u64), usize> = (0..runs.len())
        .map(|k| ((group_of[k], runs[k].seed), k))
        .collect();
    let mut versus = Vec::new();
    for b in 1..groups.len() {
        let firsts = if groups.len() <= ALL_PAIRS_GROUPS {
            b
        } else {
            1
        };
        for a in 0..firsts {
            if let Some(v) = against(&runs, &group_of, &index, a, b, lenses.len()) {
                versus.push(v);
            }
        }
    }
    Ok(Comparison {
        metric,
        lenses,
        runs,
        groups,
        versus,
    })
}

/// A, B, …, Z, then G27, G28, ….
fn group_name(g: usize) -> String {
    if g < 26 {
        char::from(b'A' + g as u8).to_string()
    } else {
        format!("G{}", g + 1)
    }
}

fn summarize_group(
    g: usize,
    key: &serde_json::Value,
    varying: &[String],
    members: &[&RunRow],
    n_lenses: usize,
    metric: Metric,
) -> Group {
    let n = members.len() as f64;
    let mean = (0..n_lenses)
        .map(|l| members.iter().map(|r| r.values[l]).sum::<f64>() / n)
        .collect();
    let demos: Vec<f64> = members.iter().filter_map(|r| r.demo).collect();
    let learned_minus = (1..n_lenses)
        .map(|l| {
            let d: Vec<f64> = members.iter().map(|r| r.values[0] - r.values[l]).collect();
            Paired::of(&d)
        })
        .collect();
    let mut seeds: Vec<u64> = members.iter().map(|r| r.seed).collect();
    seeds.sort_unstable();
    Group {
        name: group_name(g),
        differs: varying
            .iter()
            .map(|k| (k.clone(), key[k.as_str()].clone()))
            .collect(),
        seeds,
        mean,
        demo_mean: (!demos.is_empty()).then(|| demos.iter().sum::<f64>() / demos.len() as f64),
        learned_minus,
        learned_best: members
            .iter()
            .filter(|r| (1..n_lenses).all(|l| metric.cmp_better(r.values[0], r.values[l]).is_lt()))
            .count(),
    }
}

/// Group b − group a seed by seed (`index`: (group, seed) → run); `None` when they share no
/// seed.
fn against(
    runs: &[RunRow],
    group_of: &[usize],
    index: &HashMap<(usize, u64), usize>,
    a: usize,
    b: usize,
    n_lenses: usize,
) -> Option<Versus> {
    let mut pairs: Vec<(&RunRow, &RunRow)> = Vec::new();
    for (kb, rb) in runs.iter().enumerate() {
        if group_of[kb] != b {
            continue;
        }
        if let Some(&ka) = index.get(&(a, rb.seed)) {
            pairs.push((&runs[ka], rb));
        }
    }
    if pairs.is_empty() {
        return None;
    }
    pairs.sort_by_key(|(ra, _)| ra.seed);
    let per_lens = (0..n_lenses)
        .map(|l| {
            let d: Vec<f64> = pairs
                .iter()
                .map(|(ra, rb)| rb.values[l] - ra.values[l])
                .collect();
            Paired::of(&d)
        })
        .collect();
    let demo: Vec<f64> = pairs
        .iter()
        .filter_map(|(ra, rb)| Some(rb.demo? - ra.demo?))
        .collect();
    Some(Versus {
        b: group_name(b),
        a: group_name(a),
        seeds: pairs.iter().map(|(ra, _)| ra.seed).collect(),
        per_lens,
        demo: (!demo.is_empty()).then(|| Paired::of(&demo)),
    })
}

/// `key=value, …` of a group's distinguishing keys (strings unquoted); "all runs" for none.
fn differs_text(g: &Group) -> String {
    if g.differs.is_empty() {
        return "all runs".into();
    }
    g.differs
        .iter()
        .map(|(k, v)| match v.as_str() {
            Some(s) => format!("{k}={s}"),
            None => format!("{k}={v}"),
        })
        .collect::<Vec<_>>()
        .join(", ")
}

/// The comparison as the text `nanoeye compare` prints.
pub fn text(c: &Comparison) -> String {
    let unit = c.metric.unit();
    let better = if c.metric.higher_is_better() {
        "higher is better"
    } else {
        "lower is better"
    };
    let mut s = format!(
        "{}; {better}\n{:<32} {:>6} {:>5}",
        c.metric.title(),
        "run",
        "seed",
        "group"
    );
    for l in &c.lenses {
        s += &format!(" {l:>13}");
    }
    s += &format!(" {:>7} {:>11} {:>7}\n", "demo", "MACs", "p̂ µm");
    let opt = |v: Option<f64>| v.map_or("-".into(), |x| format!("{x:.2}"));
    for r in &c.runs {
        s += &format!("{:<32} {:>6} {:>5}", r.run, r.seed, r.group);
        for v in &r.values {
            s += &format!(" {v:>13.2}");
        }
        s += &format!(
            " {:>7} {:>11} {:>7}\n",
            opt(r.demo),
            r.macs.map_or("-".into(), |m| m.to_string()),
            opt(r.pitch_um)
        );
    }
    let learned = &c.lenses[0];
    for g in &c.groups {
        let n = g.seeds.len();
        s += &format!(
            "\ngroup {} ({}): {n} run{}, seeds {}\n  mean:",
            g.name,
            differs_text(g),
            if n == 1 { "" } else { "s" },
            seeds_text(&g.seeds)
        );
        for (l, v) in c.lenses.iter().zip(&g.mean) {
            s += &format!(" {l} {v:.2}{unit},");
        }
        s.pop();
        if let Some(d) = g.demo_mean {
            s += &format!("; demo {d:.2}{unit}");
        }
        s.push('\n');
        for (l, p) in c.lenses[1..].iter().zip(&g.learned_minus) {
            s += &format!(
                "  {learned} − {l}: {} ({learned} lower in {} of {})\n",
                p.text(unit),
                p.lower,
                p.n
            );
        }
        s += &format!(
            "  {learned} {} of the {} lenses in {} of {n}\n",
            c.metric.best_word(),
            c.lenses.len(),
            g.learned_best
        );
    }
    for v in &c.versus {
        s += &format!(
            "\n{} − {}, seed by seed ({} common: {}):\n",
            v.b,
            v.a,
            v.seeds.len(),
            seeds_text(&v.seeds)
        );
        for (l, p) in c.lenses.iter().zip(&v.per_lens) {
            s += &format!(
                "  {l}: {} ({} lower in {} of {})\n",
                p.text(unit),
                v.b,
                p.lower,
                p.n
            );
        }
        if let Some(p) = &v.demo {
            s += &format!(
                "  demo: {} ({} lower in {} of {})\n",
                p.text(unit),
                v.b,
                p.lower,
                p.n
            );
        }
    }
    s += "\n± is one standard error of the mean over runs (seeds); keys an older run's \
          config.json lacks count as today's defaults.\n";
    s
}

/// Ascending seeds with runs of consecutive ones shortened: "0–4, 7, 9, 10".
fn seeds_text(seeds: &[u64]) -> String {
    let mut parts: Vec<String> = Vec::new();
    let mut k = 0;
    while k < seeds.len() {
        let mut e = k;
        while e + 1 < seeds.len() && seeds[e + 1] == seeds[e] + 1 {
            e += 1;
        }
        parts.push(match e - k {
            0 => seeds[k].to_string(),
            1 => format!("{}, {}", seeds[k], seeds[e]),
            _ => format!("{}–{}", seeds[k], seeds[e]),
        });
        k = e + 1;
    }
    parts.join(", ")
}

/// Every run's error per lens as dots, one column per (lens, group), the group's mean as a
/// bar, grey lines joining the runs of one seed across groups; groups coloured and named in
/// the legend.
pub fn svg(c: &Comparison) -> String {
    const COLOURS: [&str; 6] = [
        "#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b",
    ];
    let (ng, nl, unit) = (c.groups.len(), c.lenses.len(), c.metric.unit());
    let col_w = 40.0;
    let (ml, mr, mt, mb) = (56.0, 16.0, 16.0, 48.0 + 16.0 * ng as f64);
    let panel = col_w * ng as f64 + 40.0;
    let (w, ht) = (ml + mr + panel * nl as f64, 320.0 + mb);
    let all = c.runs.iter().flat_map(|r| r.values.iter().copied());
    let hi = all.fold(0.0_f64, f64::max);
    // A 1-2-5 step with at most 8 of them to the top, at any magnitude (a fixed list ending
    // at 200 drew 500,000 gridlines for values of 1e8).
    let mag = 10f64.powf((hi / 8.0).max(0.1).log10().floor());
    let step = [1.0, 2.0, 5.0, 10.0]
        .into_iter()
        .map(|m| m * mag)
        .find(|s| hi / s <= 8.0)
        .unwrap_or(10.0 * mag);
    let top = ((hi / step).ceil() * step).max(step);
    let y = |d: f64| mt + (ht - mt - mb) * (1.0 - d / top);
    let x = |l: usize, g: usize| ml + panel * l as f64 + 20.0 + col_w * (g as f64 + 0.5);
    let mut s = format!(
        "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{w}\" height=\"{ht}\" \
         font-family=\"sans-serif\" font-size=\"12\">\n\
         <rect width=\"100%\" height=\"100%\" fill=\"white\"/>\n\
         <text x=\"12\" y=\"{cy}\" transform=\"rotate(-90 12 {cy})\" text-anchor=\"middle\">\
         {title}</text>\n",
        cy = (ht - mb + mt) / 2.0,
        title = c.metric.title()
    );
    let digits = if step < 1.0 { 1 } else { 0 };
    for k in 0..=(top / step).round() as usize {
        let t = k as f64 * step;
        s += &format!(
            "<line x1=\"{ml}\" y1=\"{yy:.1}\" x2=\"{r}\" y2=\"{yy:.1}\" stroke=\"#eee\"/>\
             <text x=\"{tx}\" y=\"{ty:.1}\" text-anchor=\"end\">{t:.digits$}</text>\n",
            yy = y(t),
            r = w - mr,
            tx = ml - 4.0,
            ty = y(t) + 4.0
        );
    }
    for (l, name) in c.lenses.iter().enumerate() {
        s += &format!(
            "<text x=\"{:.1}\" y=\"{:.1}\" text-anchor=\"middle\">{}</text>\n",
            ml + panel * (l as f64 + 0.5),
            ht - mb + 18.0,
            crate::report::esc(name)
        );
        // Lines joining one seed's runs across groups, under the dots.
        let seeds: std::collections::BTreeSet<u64> = c.runs.iter().map(|r| r.seed).collect();
        for seed in seeds {
            let pts: Vec<String> = (0..ng)
                .filter_map(|g| {
                    c.runs
                        .iter()
                        .find(|r| r.seed == seed && r.group == c.groups[g].name)
                        .map(|r| format!("{:.1},{:.1}", x(l, g), y(r.values[l])))
                })
                .collect();
            if pts.len() > 1 {
                s += &format!(
                    "<polyline fill=\"none\" stroke=\"#bbb\" points=\"{}\"/>\n",
                    pts.join(" ")
                );
            }
        }
        for (g, grp) in c.groups.iter().enumerate() {
            let colour = COLOURS[g % COLOURS.len()];
            for r in c.runs.iter().filter(|r| r.group == grp.name) {
                s += &format!(
                    "<circle cx=\"{:.1}\" cy=\"{:.1}\" r=\"3.5\" fill=\"{colour}\"><title>{} \
                     seed {}: {:.2}{unit}</title></circle>\n",
                    x(l, g),
                    y(r.values[l]),
                    crate::report::esc(&r.run),
                    r.seed,
                    r.values[l]
                );
            }
            s += &format!(
                "<line x1=\"{:.1}\" y1=\"{m:.1}\" x2=\"{:.1}\" y2=\"{m:.1}\" stroke=\"{colour}\" \
                 stroke-width=\"3\"/>\n",
                x(l, g) - 14.0,
                x(l, g) + 14.0,
                m = y(grp.mean[l])
            );
        }
    }
    for (g, grp) in c.groups.iter().enumerate() {
        s += &format!(
            "<circle cx=\"{ml}\" cy=\"{cy:.1}\" r=\"4\" fill=\"{}\"/><text x=\"{tx}\" \
             y=\"{ty:.1}\">{} ({}): {} run{}; bar = mean</text>\n",
            COLOURS[g % COLOURS.len()],
            grp.name,
            crate::report::esc(&differs_text(grp)),
            grp.seeds.len(),
            if grp.seeds.len() == 1 { "" } else { "s" },
            cy = ht - mb + 36.0 + 16.0 * g as f64,
            tx = ml + 10.0,
            ty = ht - mb + 40.0 + 16.0 * g as f64
        );
    }
    s + "</svg>\n"
}

/// `nanoeye compare`.
pub fn run(a: CompareArgs) -> Result<()> {
    if let Some(p) = &a.svg {
        // The plot replaces --svg whole: given a run's file, it destroyed the run (config.json,
        // result.json; then any other, a lens's rig.json, which `track` then refused).
        for run in &a.runs {
            if util::is_inside(p, run) {
                bail!(
                    "--svg: '{}' lies inside the run {}; write the plot elsewhere",
                    p.display(),
                    run.display()
                );
            }
        }
        util::check_output_target(p).context("--svg")?;
    }
    let c = compare(&a.runs, a.metric)?;
    if let Some(p) = &a.svg {
        util::check_output_target(p).context("--svg")?;
        util::write_atomic(p, svg(&c).as_bytes())
            .with_context(|| format!("--svg {}", p.display()))?;
    }
    if a.json {
        util::print_json(&c)
    } else {
        print!("{}", text(&c));
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A finished run in `root/name`: the default configuration with `set` applied and the
    /// protocol's mean error per lens `deg` (learned, hyperbolic, double-helix).
    fn fake_run(
        root: &Path,
        name: &str,
        set: &[(&str, serde_json::Value)],
        deg: [f64; 3],
        demo: f64,
    ) -> PathBuf {
        let dir = root.join(name);
        std::fs::create_dir_all(&dir).unwrap();
        let mut cfg = serde_json::to_value(RunConfig::default()).unwrap();
        for (k, v) in set {
            cfg[*k] = v.clone();
        }
        std::fs::write(dir.join("config.json"), cfg.to_string()).unwrap();
        let mut protocol = serde_json::Map::new();
        for (l, d) in lens_names().iter().zip(deg) {
            let v = serde_json::json!({"mean_deg": d, "slip_rmse_mm": d / 10.0,
                "dice": 1.0 - d / 20.0, "frames": 7});
            protocol.insert(l.clone(), v);
        }
        protocol.insert(
            "geometric_no_slip".into(),
            serde_json::json!({"mean_deg": 1.0}),
        );
        let r = serde_json::json!({"protocol": protocol, "demo_sequence": {"mean_deg": demo},
            "macs": 1000, "pitch_um": 15.5});
        std::fs::write(dir.join("result.json"), r.to_string()).unwrap();
        dir
    }

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() < 1e-12
    }

    #[test]
    fn groups_by_configuration_and_pairs_by_seed() {
        let t = tempfile::tempdir().unwrap();
        let joint = || ("learned_lens", serde_json::json!("joint"));
        // Group A (defaults), seeds 0..3; group B (joint), seeds 1..4, listed out of order.
        let a = [[10.0, 9.0, 8.0], [12.0, 11.0, 13.0], [9.0, 9.5, 10.0]];
        let b = [[11.0, 11.5, 12.5], [8.0, 9.5, 9.0], [7.0, 8.0, 6.0]];
        let mut dirs = Vec::new();
        for (s, d) in a.iter().enumerate() {
            let seed = ("seed", serde_json::json!(s));
            dirs.push(fake_run(
                t.path(),
                &format!("a{s}"),
                &[seed],
                *d,
                5.0 + s as f64,
            ));
        }
        for (k, d) in b.iter().enumerate().rev() {
            let seed = ("seed", serde_json::json!(k + 1));
            dirs.push(fake_run(
                t.path(),
                &format!("b{}", k + 1),
                &[seed, joint()],
                *d,
                4.0,
            ));
        }
        let c = compare(&dirs, Metric::MeanDeg).unwrap();
        assert_eq!(c.groups.len(), 2);
        let (ga, gb) = (&c.groups[0], &c.groups[1]);
        assert_eq!((ga.name.as_str(), gb.name.as_str()), ("A", "B"));
        // Only the key that differs names the groups.
        assert_eq!(ga.differs.len(), 1);
        assert_eq!(ga.differs["learned_lens"], "trained");
        assert_eq!(gb.differs["learned_lens"], "joint");
        assert_eq!(
            (ga.seeds.clone(), gb.seeds.clone()),
            (vec![0, 1, 2], vec![1, 2, 3])
        );
        assert!(close(ga.mean[0], 31.0 / 3.0));
        assert!(close(ga.demo_mean.unwrap(), 6.0));
        // learned − hyperbolic in A: 1, 1, −0.5 → mean 0.5, sd √0.75, SE 0.5.
        let p = &ga.learned_minus[0];
        assert!(close(p.mean, 0.5) && close(p.se.unwrap(), 0.5), "{p:?}");
        assert_eq!((p.n, p.lower), (3, 1));
        // Learned lowest: A's seed 2 (9 < 9.5, 10) only; B's seeds 1 and 2, not 3 (7 > 6).
        assert_eq!((ga.learned_best, gb.learned_best), (1, 2));
        assert_eq!(c.runs[0].best, "double_helix");
        // B − A on the common seeds 1 and 2, learned: (11 − 12, 8 − 9) = (−1, −1).
        let v = &c.versus[0];
        assert_eq!(
            (v.b.as_str(), v.a.as_str(), v.seeds.clone()),
            ("B", "A", vec![1, 2])
        );
        assert!(close(v.per_lens[0].mean, -1.0) && close(v.per_lens[0].se.unwrap(), 0.0));
        assert_eq!(v.per_lens[0].lower, 2);
        // Double-helix: (12.5 − 13, 9 − 10) = (−0.5, −1): mean −0.75, SE 0.25.
        let p = &v.per_lens[2];
        assert!(close(p.mean, -0.75) && close(p.se.unwrap(), 0.25), "{p:?}");
        // Demo: (4 − 6, 4 − 7).
        assert!(close(v.demo.as_ref().unwrap().mean, -2.5));
        let s = text(&c);
        assert!(
            s.contains("group B (learned_lens=joint): 3 runs, seeds 1–3"),
            "{s}"
        );
        assert!(
            s.contains("learned: -1.00 ± 0.00° (B lower in 2 of 2)"),
            "{s}"
        );
        assert_eq!(seeds_text(&[0, 1, 2, 3, 4, 7, 9, 10]), "0–4, 7, 9, 10");
        // Another field of the same summaries; the demo (no such field here) is left out.
        let slip = compare(&dirs, Metric::SlipRmseMm).unwrap();
        assert!(close(slip.groups[0].mean[0], 31.0 / 30.0));
        assert!(close(slip.versus[0].per_lens[2].mean, -0.075));
        assert!(slip.versus[0].demo.is_none() && slip.runs.iter().all(|r| r.demo.is_none()));
        assert!(text(&slip).contains("learned: -0.10 ± 0.00 mm (B lower in 2 of 2)"));
        // Dice (here 1 − error/20) is better higher: the same lens is best in every run, and
        // the count says "highest".
        let dice = compare(&dirs, Metric::Dice).unwrap();
        assert_eq!(
            (dice.groups[0].learned_best, dice.groups[1].learned_best),
            (1, 2)
        );
        assert!(dice.runs.iter().zip(&c.runs).all(|(d, m)| d.best == m.best));
        assert!(text(&dice).contains("learned highest of the 3 lenses in 2 of 3"));
        // One dot per run and lens, one legend dot per group; the JSON has no null.
        let svg = svg(&c);
        assert_eq!(svg.matches("<circle").count(), 6 * 3 + 2);
        assert!(!serde_json::to_string(&c).unwrap().contains("null"));
    }

    /// The plot's gridlines stay few at any magnitude (an audit: values of 1e8 drew 500,000
    /// of them, a 58 MB SVG); at degrees the steps are the 1-2-5 ones they were.
    #[test]
    fn the_plots_gridlines_stay_few_at_any_magnitude() {
        let t = tempfile::tempdir().unwrap();
        for (hi, step) in [
            (1e8, "20000000"),
            (1e9, "200000000"),
            (10.0, "2"),
            (0.9, "0.2"),
        ] {
            let dir = fake_run(t.path(), &format!("r{hi}"), &[], [hi, hi / 2.0, 1.0], hi);
            let c = compare(&[dir], Metric::MeanDeg).unwrap();
            let s = svg(&c);
            let lines = s.matches("stroke=\"#eee\"").count();
            assert!((2..=10).contains(&lines), "{hi}: {lines} gridlines");
            assert!(
                s.contains(&format!(">{step}</text>")),
                "{hi}: no tick {step}"
            );
            assert!(s.len() < 100_000, "{hi}: {} bytes", s.len());
        }
    }

    #[test]
    fn an_older_configuration_groups_with_todays_defaults() {
        let t = tempfile::tempdir().unwrap();
        let new = fake_run(t.path(), "new", &[], [9.0, 9.0, 9.0], 9.0);
        let old = fake_run(
            t.path(),
            "old",
            &[("seed", serde_json::json!(1))],
            [8.0; 3],
            8.0,
        );
        let mut cfg: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(old.join("config.json")).unwrap())
                .unwrap();
        cfg.as_object_mut().unwrap().remove("embed_weight");
        std::fs::write(old.join("config.json"), cfg.to_string()).unwrap();
        let c = compare(&[new, old], Metric::MeanDeg).unwrap();
        assert_eq!(c.groups.len(), 1);
        assert!(c.groups[0].differs.is_empty() && c.versus.is_empty());
        // One run per group has no standard error, and says so by leaving it out.
        let one = compare(&[t.path().join("new")], Metric::MeanDeg).unwrap();
        assert!(one.groups[0].learned_minus[0].se.is_none());
        assert!(!serde_json::to_string(&one).unwrap().contains("\"se\""));
    }

    #[test]
    fn many_groups_are_set_against_the_first_only() {
        let t = tempfile::tempdir().unwrap();
        let run = |n: usize| {
            let steps = ("train_steps", serde_json::json!(100 + n));
            fake_run(
                t.path(),
                &format!("r{n}"),
                &[steps],
                [9.0, 8.0, n as f64],
                9.0,
            )
        };
        let pairs = |n: usize| {
            let c = compare(&(0..n).map(run).collect::<Vec<_>>(), Metric::MeanDeg).unwrap();
            assert_eq!(c.groups.len(), n);
            c.versus
        };
        // 8 groups: all 28 pairs; 10: the 9 against A.
        assert_eq!(pairs(ALL_PAIRS_GROUPS).len(), 28);
        let v = pairs(10);
        assert_eq!(v.len(), 9);
        assert!(v.iter().all(|p| p.a == "A"));
        assert!(close(v[8].per_lens[2].mean, 9.0));
    }

    #[test]
    fn refuses_what_it_cannot_compare_and_names_it() {
        let t = tempfile::tempdir().unwrap();
        let a = fake_run(t.path(), "a", &[], [9.0; 3], 9.0);
        let b = fake_run(t.path(), "b", &[], [8.0; 3], 8.0);
        let err = |dirs: &[PathBuf]| format!("{:#}", compare(dirs, Metric::MeanDeg).unwrap_err());
        assert!(err(&[]).contains("at least one"));
        let e = err(&[a.clone(), b.clone()]);
        assert!(e.contains("same configuration and seed 0"), "{e}");
        // Unfinished: no result.json.
        std::fs::remove_file(b.join("result.json")).unwrap();
        let e = err(std::slice::from_ref(&b));
        assert!(
            e.contains("no result.json") && e.contains("nanoeye run --out"),
            "{e}"
        );
        // A lens without a finite error (JSON writes NaN as null).
        let r = serde_json::json!({"protocol": {"learned": {"mean_deg": null}}});
        std::fs::write(b.join("result.json"), r.to_string()).unwrap();
        assert!(err(std::slice::from_ref(&b)).contains("protocol.learned.mean_deg"));
        // A finite value whose square is not (1e308 gave a null standard error).
        let r = serde_json::json!({"protocol": {"learned": {"mean_deg": 1e308}}});
        std::fs::write(b.join("result.json"), r.to_string()).unwrap();
        assert!(err(std::slice::from_ref(&b)).contains("not a value in [0, 1e9]"));
        // Not a run folder; a configuration with an unknown key.
        assert!(err(&[t.path().join("nowhere")]).contains("no config.json"));
        std::fs::write(a.join("config.json"), r#"{"seed": 1, "bogus": 2}"#).unwrap();
        assert!(err(&[a]).contains("not a run configuration"));
    }
}

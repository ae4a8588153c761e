//! DIR/report.html of `nanoeye run`: one self-contained page (inline SVG and base64 PNG, no
//! external files) with the learned and baseline phase maps, training curves, the REA history
//! and the protocol error tables, and what each number means.

use anyhow::Result;
use nanoeye_search::StepRecord;
use std::fmt::Write;
use std::path::Path;

fn b64(bytes: &[u8]) -> String {
    const T: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut s = String::with_capacity(bytes.len().div_ceil(3) * 4);
    for c in bytes.chunks(3) {
        let n = (c[0] as u32) << 16
            | (*c.get(1).unwrap_or(&0) as u32) << 8
            | *c.get(2).unwrap_or(&0) as u32;
        for (i, sh) in [18, 12, 6, 0].iter().enumerate() {
            if i <= c.len() {
                s.push(T[(n >> sh & 63) as usize] as char);
            } else {
                s.push('=');
            }
        }
    }
    s
}

fn png_b64(m: usize, px: Vec<u8>) -> Option<String> {
    let img = image::GrayImage::from_raw(m as u32, m as u32, px)?;
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png).ok()?;
    Some(b64(&out.into_inner()))
}

/// The phase map wrapped to [0, 2π) as an 8-bit PNG at full resolution (a strided
/// downsample of the fast-varying hyperbolic phase would show moiré, not the lens).
fn phase_png(path: &Path) -> Option<String> {
    let phi = nanoeye_optics::io::read_phase_npy(path).ok()?;
    let n = phi.nrows();
    let tau = std::f64::consts::TAU;
    let px = (0..n * n)
        .map(|k| (phi[(k / n, k % n)].rem_euclid(tau) / tau * 255.0) as u8)
        .collect();
    png_b64(n, px)
}

/// φ_a − φ_b (unwrapped difference, mid-grey 0, black/white ∓ its largest magnitude) and that
/// magnitude (rad): what co-design changed.
fn difference_png(a: &Path, b: &Path) -> Option<(String, f64)> {
    let (pa, pb) = (
        nanoeye_optics::io::read_phase_npy(a).ok()?,
        nanoeye_optics::io::read_phase_npy(b).ok()?,
    );
    let n = pa.nrows();
    if pb.nrows() != n {
        return None;
    }
    let d: Vec<f64> = (0..n * n)
        .map(|k| pa[(k / n, k % n)] - pb[(k / n, k % n)])
        .collect();
    let m = d.iter().fold(1e-12f64, |x, v| x.max(v.abs()));
    let px = d
        .iter()
        .map(|v| ((v / m * 0.5 + 0.5) * 255.0) as u8)
        .collect();
    Some((png_b64(n, px)?, m))
}

fn history(path: &Path) -> Vec<StepRecord> {
    std::fs::read_to_string(path)
        .unwrap_or_default()
        .lines()
        .filter_map(|l| serde_json::from_str(l).ok())
        .collect()
}

/// True (lines) and tracked (dots) azimuth and elevation over the sequence (degrees).
fn demo_svg(rows: &[serde_json::Value]) -> String {
    series_svg(
        rows,
        ("true_deg", "tracked_deg"),
        &[(0, "#c0392b"), (1, "#2471a3")],
        (-40.0, 40.0),
        "degrees (−40 … 40)",
    )
}

/// True (lines) and estimated (dots) slippage x, y, z over the sequence (mm).
fn demo_slip_svg(rows: &[serde_json::Value]) -> String {
    series_svg(
        rows,
        ("true_slip_mm", "tracked_slip_mm"),
        &[(0, "#c0392b"), (1, "#27ae60"), (2, "#2471a3")],
        (-6.0, 6.0),
        "slippage, mm (−6 … 6)",
    )
}

/// One value per frame: `keys.0[axis]` as a line and `keys.1[axis]` as dots for each
/// (axis, colour), on a vertical range `lo … hi` (values beyond sit on its edge).
fn series_svg(
    rows: &[serde_json::Value],
    keys: (&str, &str),
    axes: &[(usize, &str)],
    (lo, hi): (f64, f64),
    label: &str,
) -> String {
    let (w, ht, m) = (720.0, 300.0, 45.0);
    let n = rows.len().max(2) as f64;
    let x = |k: usize| m + (w - 2.0 * m) * k as f64 / (n - 1.0);
    let y = |d: f64| ht - m - (ht - 2.0 * m) * ((d.clamp(lo, hi) - lo) / (hi - lo));
    let mut s = format!(
        r##"<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{ht}" font-family="sans-serif" font-size="12">
<rect width="100%" height="100%" fill="white"/>
<line x1="{m}" y1="{b}" x2="{r}" y2="{b}" stroke="black"/><line x1="{m}" y1="{m}" x2="{m}" y2="{b}" stroke="black"/>
<line x1="{m}" y1="{z}" x2="{r}" y2="{z}" stroke="#ccc"/>
<text x="{cx}" y="{tb}" text-anchor="middle">frame</text>
<text x="12" y="{cy}" transform="rotate(-90 12 {cy})" text-anchor="middle">{label}</text>
"##,
        b = ht - m,
        r = w - m,
        z = y(0.0),
        cx = w / 2.0,
        tb = ht - 10.0,
        cy = ht / 2.0
    );
    for &(axis, color) in axes {
        let pts: Vec<String> = rows
            .iter()
            .enumerate()
            .filter_map(|(k, r)| {
                r[keys.0][axis]
                    .as_f64()
                    .map(|d| format!("{:.1},{:.1}", x(k), y(d)))
            })
            .collect();
        s += &format!(
            "<polyline fill=\"none\" stroke=\"{color}\" stroke-width=\"1.5\" points=\"{}\"/>\n",
            pts.join(" ")
        );
        for (k, r) in rows.iter().enumerate() {
            if let Some(d) = r[keys.1][axis].as_f64() {
                s += &format!(
                    "<circle cx=\"{:.1}\" cy=\"{:.1}\" r=\"2.5\" fill=\"{color}\"/>\n",
                    x(k),
                    y(d)
                );
            }
        }
    }
    s + "</svg>\n"
}

/// Predicted against true slippage (mm), one panel per axis, from a lens's protocol.jsonl: one
/// dot per frame, the mean estimate of each slippage state (frames sharing a true slippage) as
/// an orange diamond, ticks every 2.5 mm; a value beyond ±7 mm is drawn on the frame as a red
/// ring and counted in the panel's corner.
fn slip_svg(rows: &[serde_json::Value]) -> String {
    let (pw, ml, mb, mt, lim) = (220.0, 46.0, 36.0, 8.0, 7.0);
    let (w, ht) = (3.0 * pw, pw + 4.0);
    let side = pw - ml - mt;
    let mut s = format!(
        r##"<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{ht}" font-family="sans-serif" font-size="11">
<rect width="100%" height="100%" fill="white"/>
"##
    );
    for (axis, name) in ["x", "y", "z"].iter().enumerate() {
        let x0 = axis as f64 * pw;
        let frac = |v: f64| (v.clamp(-lim, lim) + lim) / (2.0 * lim);
        let px = |v: f64| x0 + ml + side * frac(v);
        let py = |v: f64| pw - mb - side * frac(v);
        s += &format!(
            "<rect x=\"{:.1}\" y=\"{:.1}\" width=\"{side:.1}\" height=\"{side:.1}\" fill=\"none\" stroke=\"black\"/>\n\
<line x1=\"{:.1}\" y1=\"{:.1}\" x2=\"{:.1}\" y2=\"{:.1}\" stroke=\"#bbb\"/>\n\
<text x=\"{:.1}\" y=\"{:.1}\" text-anchor=\"middle\">true {name} (mm)</text>\n\
<text x=\"{:.1}\" y=\"{:.1}\" transform=\"rotate(-90 {:.1} {:.1})\" text-anchor=\"middle\">estimated {name} (mm)</text>\n",
            px(-lim),
            py(lim),
            px(-lim),
            py(-lim),
            px(lim),
            py(lim),
            px(0.0),
            pw - 6.0,
            x0 + 11.0,
            py(0.0),
            x0 + 11.0,
            py(0.0),
        );
        for v in [-5.0, -2.5, 0.0, 2.5, 5.0] {
            s += &format!(
                "<line x1=\"{0:.1}\" y1=\"{1:.1}\" x2=\"{0:.1}\" y2=\"{2:.1}\" stroke=\"black\"/>\n\
<text x=\"{0:.1}\" y=\"{3:.1}\" text-anchor=\"middle\">{v}</text>\n\
<line x1=\"{4:.1}\" y1=\"{5:.1}\" x2=\"{6:.1}\" y2=\"{5:.1}\" stroke=\"black\"/>\n\
<text x=\"{7:.1}\" y=\"{8:.1}\" text-anchor=\"end\">{v}</text>\n",
                px(v),
                py(-lim),
                py(-lim) + 4.0,
                py(-lim) + 15.0,
                px(-lim) - 4.0,
                py(v),
                px(-lim),
                px(-lim) - 6.0,
                py(v) + 4.0,
            );
        }
        let mut outside = 0;
        // Per slippage state: (Σ true, Σ estimate, frames).
        let mut states: std::collections::BTreeMap<u64, (f64, f64, usize)> = Default::default();
        for r in rows {
            let (Some(t), Some(e)) = (
                r["true_slip_mm"][axis].as_f64(),
                r["tracked_slip_mm"][axis].as_f64(),
            ) else {
                continue;
            };
            if let Some(k) = r["slip_state"].as_u64() {
                let st = states.entry(k).or_default();
                *st = (st.0 + t, st.1 + e, st.2 + 1);
            }
            let out = t.abs() > lim || e.abs() > lim;
            outside += usize::from(out);
            s += &if out {
                format!(
                    "<circle cx=\"{:.1}\" cy=\"{:.1}\" r=\"3\" fill=\"none\" stroke=\"#c0392b\"/>\n",
                    px(t),
                    py(e)
                )
            } else {
                format!(
                    "<circle cx=\"{:.1}\" cy=\"{:.1}\" r=\"2\" fill=\"#2471a3\" fill-opacity=\"0.5\"/>\n",
                    px(t),
                    py(e)
                )
            };
        }
        for (t, e, n) in states.values() {
            let (cx, cy) = (px(t / *n as f64), py(e / *n as f64));
            s += &format!(
                "<path d=\"M{:.1} {cy:.1} L{cx:.1} {:.1} L{:.1} {cy:.1} L{cx:.1} {:.1} Z\" fill=\"#e67e22\" stroke=\"black\" stroke-width=\"0.5\"/>\n",
                cx - 5.0,
                cy - 5.0,
                cx + 5.0,
                cy + 5.0
            );
        }
        if outside > 0 {
            s += &format!(
                "<text x=\"{:.1}\" y=\"{:.1}\" text-anchor=\"end\" fill=\"#c0392b\">{outside} beyond ±{lim} mm</text>\n",
                px(lim) - 3.0,
                py(-lim) - 4.0
            );
        }
    }
    s + "</svg>\n"
}

/// A JSON value of the run's own files as page text: a number as written, anything else
/// (a file edited or left by another build) escaped rather than pasted in as markup.
fn raw(v: &serde_json::Value) -> String {
    esc(&v.to_string())
}

/// `s` with the characters XML text may not hold escaped, and the control characters XML 1.0
/// allows in no form (a run directory named with ESC made an SVG no parser reads) replaced by
/// U+FFFD.
pub(crate) fn esc(s: &str) -> String {
    s.chars()
        .map(|c| match c {
            '\t' | '\n' | '\r' => c,
            c if c.is_control() && (c as u32) < 0x20 => '\u{fffd}',
            c => c,
        })
        .collect::<String>()
        .replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}

/// The page for run directory `out` and its result JSON.
pub fn html(out: &Path, r: &serde_json::Value) -> Result<String> {
    let mut h = String::new();
    // The run's own sizes, from the configuration it wrote ("–" where it is missing).
    let cfg: serde_json::Value = std::fs::read_to_string(out.join("config.json"))
        .ok()
        .and_then(|t| serde_json::from_str(&t).ok())
        .unwrap_or_default();
    let c = |k: &str| cfg[k].as_u64().map_or("–".to_string(), |v| v.to_string());
    writeln!(
        h,
        r#"<!doctype html><html lang="en"><head><meta charset="utf-8"><title>nanoeye run</title>
<style>body{{font-family:sans-serif;max-width:1100px;margin:2em auto;color:#222}}
table{{border-collapse:collapse;margin:1em 0}}td,th{{border:1px solid #bbb;padding:4px 8px;text-align:right}}
th{{background:#eee}}td:first-child,th:first-child{{text-align:left}}.row{{display:flex;gap:2em;flex-wrap:wrap}}
figure{{margin:0}}figcaption{{font-size:90%;color:#555}}</style></head><body>
<h1>nanoeye run</h1>
<p>A metasurface lens (from a Fisher-information initialization, A.2), its effective pixel
pitch p̂ and a MobileNetV3 supernet co-designed end to end (sandwich rule, S22), a short regularized evolution (S19–S21) choosing the subnet, that
subnet fine-tuned behind each lens (S16's inner loop: the deployed model), and
the acquisition protocol (D.4: 49 targets × 7 slippage states per subject{}) evaluated through
the whole simulated chain: rendered depth layers → lens PSFs (S1) → sensor at p̂ (S2) →
network → pupil centroid (S9) → ray–sphere gaze with the network's slippage (S10–S14). The
same network is trained behind the fixed hyperbolic and double-helix lenses for comparison.
Stage times add up to {:.0} s (table at the end).</p>
<p><b>Scale.</b> This run: {} training frames{} rendered at {}×{}, {} sandwich steps per lens and a
{} + {} candidate search (config.json). The built-in default is sized to finish within 15 minutes
on 2 cores, so its errors are far from the paper's; `nanoeye run --print-config` lists every
size, and `--config FILE` scales the run up (more frames, steps, REA cycles and a finer
render).</p>"#,
        match cfg["protocol_grid"].as_u64() {
            Some(g) if g != 7 => format!("; this run: a {g}×{g} grid, {} targets", g * g),
            _ => String::new(),
        },
        // The stages' sum: a resumed run's own wall time would count only what it redid.
        r["stages"]
            .as_object()
            .map_or(0.0, |m| m.values().filter_map(|v| v.as_f64()).sum::<f64>()),
        c("train_items"),
        match cfg["train_blink_fraction"].as_f64() {
            Some(b) if b > 0.0 => format!(
                " ({:.0} % of them in a blink or partial closure)",
                b * 100.0
            ),
            _ => String::new(),
        },
        c("width_px"),
        c("height_px"),
        c("train_steps"),
        c("rea_population"),
        c("rea_cycles"),
    )?;
    // Protocol table.
    writeln!(
        h,
        "<h2>Gaze error on the acquisition protocol</h2><p>Angular error between the \
estimated and the true optical axis (degrees). A frame where no pupil is found or the ray \
misses the sphere counts 90° and is listed under failures. <i>geometric_no_slip</i>: the \
learned lens and network, but the solver is told there is no slippage. \
<i>solver_true_mask_true_slip</i>: the true visible-pupil mask on the same sensor grid and the \
true slippage — the configured geometric solver's own error without the network; the \
difference to <i>learned</i> is the network's share. <i>network_mask_true_slip</i> / \
<i>true_mask_network_slip</i>: one of the network's two outputs replaced by the truth, so the \
segmentation's and the slippage estimate's shares are separate. <i>sphere_solver_…</i> / \
<i>refractive_solver_…</i>: the same with the other solver (the paper's S12 sphere of the \
rig's eye radius, or the refraction-aware solver that looks through the cornea, \
docs/gaze.md), so the refraction correction's effect is visible. \
<i>solver_true_mask_eye_equivalent_slip</i>: the true mask with the slippage's translation and \
the camera's rotation folded into one translation about the eye centre, so what S11's \
translation-only model costs is visible (docs/gaze.md). <i>…_ellipse_if_cut</i> / \
<i>…_centroid</i>: the same chain with the pupil centre the configuration (<i>pupil_centre</i>) \
does not use: S9's centroid of the whole mask, or, for a pupil the frame's edge cuts, the \
centre of the ellipse fitted to its boundary inside the frame (docs/gaze.md). Dice: mean \
overlap of the predicted and true pupil masks; slip RMSE: root mean square of the predicted slippage's error \
(mm) — the network's two outputs against the truth.</p>\
<table><tr><th>chain</th><th>mean °</th><th>median °</th><th>p95 °</th><th>failures</th><th>frames</th>\
<th>Dice</th><th>slip RMSE (mm)</th></tr>"
    )?;
    let proto = r["protocol"].as_object().cloned().unwrap_or_default();
    for (name, s) in &proto {
        writeln!(
            h,
            "<tr><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td></tr>",
            esc(name),
            num(&s["mean_deg"]),
            num(&s["median_deg"]),
            num(&s["p95_deg"]),
            raw(&s["failures"]),
            raw(&s["frames"]),
            num(&s["dice"]),
            num(&s["slip_rmse_mm"])
        )?;
    }
    writeln!(
        h,
        "</table><h3>Mean error per slippage state</h3><p>States 0–6 of the protocol's translation stages (origin, ±x, four z steps of 2.5 mm, D.4).</p><table><tr><th>chain</th>"
    )?;
    for k in 0..7 {
        write!(h, "<th>state {k}</th>")?;
    }
    writeln!(h, "</tr>")?;
    for (name, s) in &proto {
        write!(h, "<tr><td>{}</td>", esc(name))?;
        for row in s["per_slip"].as_array().cloned().unwrap_or_default() {
            write!(h, "<td>{}</td>", num(&row["mean_deg"]))?;
        }
        writeln!(h, "</tr>")?;
    }
    writeln!(h, "</table>")?;
    let e = &r["learned_lens_embedding"];
    let joint = e["learned_lens"] == "joint";
    if e.is_object() {
        let how = if joint {
            format!(
                "trained with the network on the task loss plus {} times the optical-embedding \
objective (S15, <code>learned_lens: \"joint\"</code>): each phase step also raises the Fisher \
information of the sensor image in the glasses' slippage and in the gaze (L_sens) and makes \
their two sensitivity fields orthogonal (cos²φ), on 4 of {} rendered triplets (anchor, slip+, \
gaze+). Below, the objective over every triplet at the Fisher initialization and after training.",
                num(&e["embed_weight"]),
                e["final"]["triplets"].as_u64().unwrap_or(0)
            )
        } else {
            format!(
                "designed by the optical-embedding objective (S15, <code>learned_lens: \
\"embedding\"</code>): from the Fisher initialization, Adam steps on the phase map that raise the \
Fisher information of the sensor image in the glasses' slippage and in the gaze (L_sens) and make \
their two sensitivity fields orthogonal (cos²φ), over {} rendered triplets (anchor, slip+, \
gaze+); it then stays fixed while the network trains.",
                e["final"]["triplets"].as_u64().unwrap_or(0)
            )
        };
        writeln!(
            h,
            "<h2>The learned lens's embedding objective</h2><p>The learned lens of this run was \
{how} The bounds are the two-parameter Cramér–Rao bounds of one frame with everything else \
about the scene known (geometric means over the triplets).</p><table><tr><th></th>\
<th>objective</th><th>L_sens</th><th>cos²φ</th><th>slip bound (µm)</th><th>gaze bound (°)</th></tr>"
        )?;
        // The bounds span 1e-4–1: three significant digits, not two decimals.
        let sig = |v: &serde_json::Value| v.as_f64().map_or("–".into(), |x| format!("{x:.3e}"));
        let after = if joint {
            "after joint training"
        } else {
            "after the embedding"
        };
        for (k, label) in [("init", "Fisher initialization"), ("final", after)] {
            let v = &e[k];
            writeln!(
                h,
                "<tr><td>{label}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td></tr>",
                num(&v["loss"]),
                num(&v["l_sens"]),
                sig(&v["l_orth"]),
                sig(&v["crlb_slip_um"]),
                sig(&v["crlb_gaze_deg"])
            )?;
        }
        writeln!(h, "</table>")?;
    }
    // Lenses.
    writeln!(
        h,
        "<h2>Phase maps</h2><p>Metasurface phase wrapped to [0, 2π) (black 0, white 2π) over the \
1 mm aperture. The learned lens starts from the Fisher initialization (itself started from the \
hyperbolic lens, unless the configuration's fisher_iterations is 0) and moves by gradient \
descent through the chain; the difference image is against the hyperbolic lens.</p><div class=\"row\">"
    )?;
    for name in ["learned", "hyperbolic", "double_helix"] {
        if let Some(png) = phase_png(&out.join(format!("runs/{name}/phase.npy"))) {
            writeln!(
                h,
                "<figure><img width=\"256\" alt=\"{name} phase\" src=\"data:image/png;base64,{png}\"><figcaption>{name}</figcaption></figure>"
            )?;
        }
    }
    if let Some((png, m)) = difference_png(
        &out.join("runs/learned/phase.npy"),
        &out.join("runs/hyperbolic/phase.npy"),
    ) {
        writeln!(
            h,
            "<figure><img width=\"256\" alt=\"learned minus hyperbolic\" src=\"data:image/png;base64,{png}\"><figcaption>learned − hyperbolic (black −{m:.3}, white +{m:.3} rad)</figcaption></figure>"
        )?;
    }
    // PSFs over depth and what the network sees.
    let depths: Vec<String> = r["psf_depths_mm"]
        .as_array()
        .map(|a| {
            a.iter()
                .filter_map(|v| v.as_f64())
                .map(|d| format!("{d:.1}"))
                .collect()
        })
        .unwrap_or_default();
    writeln!(
        h,
        "</div><h2>PSFs over depth</h2><p>The point-spread function of each lens at the \
representative depth of every scene slab, near to far ({} mm from the lens), as the chain uses \
it (normalised to unit sum, P̂ = P/η), each tile scaled to its own peak with a square-root \
tone curve so the out-of-focus tails show.</p>",
        depths.join(", ")
    )?;
    for name in ["learned", "hyperbolic", "double_helix"] {
        if let Ok(b) = std::fs::read(out.join(format!("runs/{name}/psfs.png"))) {
            writeln!(
                h,
                "<figure><img style=\"max-width:100%\" alt=\"{name} PSFs\" src=\"data:image/png;base64,{}\"><figcaption>{name}</figcaption></figure>",
                b64(&b)
            )?;
        }
    }
    writeln!(
        h,
        "<h2>What the network sees</h2><p>Protocol frames (centre target, next to the centre on an even \
grid; slippage states 0, 3 and 6) through each lens and the sensor at its p̂, as the selected subnet receives them \
(contrast stretched for display). Outline of the true visible pupil in green, of the \
network's predicted mask (p ≥ 0.5) in red, yellow where they coincide.</p>"
    )?;
    for name in ["learned", "hyperbolic", "double_helix"] {
        if let Ok(b) = std::fs::read(out.join(format!("runs/{name}/examples.png"))) {
            writeln!(
                h,
                "<figure><img style=\"max-width:100%\" alt=\"{name} sensor images\" src=\"data:image/png;base64,{}\"><figcaption>{name}</figcaption></figure>",
                b64(&b)
            )?;
        }
    }
    writeln!(
        h,
        "<h2>Training curves</h2><p>Task loss (Dice + λ·slip MSE in mm²) of the largest and smallest subnet per sandwich step.</p><div class=\"row\">"
    )?;
    for name in ["learned", "hyperbolic", "double_helix"] {
        let hist = history(&out.join(format!("runs/{name}/history.jsonl")));
        if !hist.is_empty() {
            let last = hist.last().map_or(0.0, |x| x.pitch_um);
            writeln!(
                h,
                "<figure>{}<figcaption>{name} (final p̂ {last:.2} µm)</figcaption></figure>",
                crate::train::svg_curves(&hist)
            )?;
        }
    }
    writeln!(h, "</div>")?;
    // REA.
    writeln!(
        h,
        "<h2>Regularized evolution</h2><p>Each cycle: a tournament of the population, its best \
(fitness = −V − γ·[MACs &gt; budget]) is mutated, the child fine-tuned and validated, the \
oldest member removed. V = mean gaze error on the validation set (degrees).</p><table>\
<tr><th>cycle</th><th>parent</th><th>child</th><th>child V °</th><th>child MACs</th><th>child p̂ µm</th><th>removed</th></tr>"
    )?;
    let rea = std::fs::read_to_string(out.join("runs/learned/rea.jsonl")).unwrap_or_default();
    for l in rea.lines() {
        if let Ok(c) = serde_json::from_str::<serde_json::Value>(l) {
            writeln!(
                h,
                "<tr><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td></tr>",
                raw(&c["cycle"]),
                raw(&c["parent"]),
                raw(&c["child"]["id"]),
                num(&c["child"]["v"]),
                raw(&c["child"]["macs"]),
                num(&c["child"]["pitch_um"]),
                raw(&c["removed"])
            )?;
        }
    }
    writeln!(
        h,
        "</table><p>Selected subnet: {} MACs ({}) at p̂ = {} µm, V = {}°.</p><pre>{}</pre>",
        raw(&r["macs"]),
        match (r["macs"].as_u64(), cfg["budget_macs"].as_u64()) {
            (Some(m), Some(b)) if b > 0 && m <= b => format!("within the {b} MAC budget"),
            (Some(_), Some(b)) if b > 0 => format!("over the {b} MAC budget"),
            _ => "no budget".to_string(),
        },
        num(&r["pitch_um"]),
        num(&r["v_deg"]),
        esc(&serde_json::to_string(&r["best_arch"])?)
    )?;
    // The calibration head against the truth, frame by frame, per lens.
    let mut slips = String::new();
    for lens in ["learned", "hyperbolic", "double_helix"] {
        if let Ok(text) = std::fs::read_to_string(out.join(format!("runs/{lens}/protocol.jsonl"))) {
            let rows: Vec<serde_json::Value> = text
                .lines()
                .filter_map(|l| serde_json::from_str(l).ok())
                .collect();
            if !rows.is_empty() {
                slips += &format!("<h3>{}</h3>{}", esc(lens), slip_svg(&rows));
                slips += &head_fit_line(&r["protocol"][lens]["slip_head_fit"]);
            }
        }
    }
    if !slips.is_empty() {
        writeln!(
            h,
            "<h2>Slippage estimate</h2><p>The calibration head's slippage against the truth on \
every protocol frame (blue dots; orange diamonds: the mean estimate of each slippage state; on \
the grey diagonal the estimate is exact; values beyond ±7 mm sit on the frame as red rings, \
counted in the panel). runs/&lt;lens&gt;/protocol.jsonl has every frame's gaze and slippage.</p>{slips}"
        )?;
    }
    if let Ok(text) = std::fs::read_to_string(out.join("demo.jsonl")) {
        let rows: Vec<serde_json::Value> = text
            .lines()
            .filter_map(|l| serde_json::from_str(l).ok())
            .collect();
        if !rows.is_empty() {
            writeln!(
                h,
                "<h2>Tracking a sequence</h2><p>A video-like sequence: the eye follows a smooth \
path while the glasses drift 3 mm down the nose. Lines: true azimuth (red) and elevation (blue); \
dots: tracked by the learned chain (mean error {}°). demo.jsonl has every frame.</p>{}",
                num(&r["demo_sequence"]["mean_deg"]),
                demo_svg(&rows)
            )?;
            if rows.iter().any(|r| r["tracked_slip_mm"].is_array()) {
                writeln!(
                    h,
                    "<p>The slippage the calibration head read on the same frames. Lines: the \
true slippage along x (red), y (green) and z (blue); dots: the network's estimate (RMSE {} mm), \
which the solver uses to place the eye.</p>{}",
                    num(&r["demo_sequence"]["slip_rmse_mm"]),
                    demo_slip_svg(&rows)
                )?;
            }
        }
    }
    writeln!(
        h,
        "<h2>Stages</h2><table><tr><th>stage</th><th>seconds</th></tr>"
    )?;
    for (k, v) in r["stages"].as_object().cloned().unwrap_or_default() {
        writeln!(h, "<tr><td>{}</td><td>{}</td></tr>", esc(&k), num(&v))?;
    }
    writeln!(h, "</table></body></html>")?;
    Ok(h)
}

/// One line on a lens's head refit (`slip_head_fit` in result.json): RMS error per axis on the
/// training frames before and after, and the leave-one-out estimate; empty without a refit.
fn head_fit_line(fit: &serde_json::Value) -> String {
    if !fit.is_object() {
        return String::new();
    }
    let axes = |k: &str| {
        (0..3)
            .map(|a| num(&fit[k][a]))
            .collect::<Vec<_>>()
            .join(" / ")
    };
    format!(
        "<p>Output layer solved on {} training frames (ridge, weight by leave-one-out error). \
RMS error x / y / z on those frames: {} mm with the trained layer, {} mm solved; leave-one-out \
{} mm.</p>",
        fit["frames"],
        axes("rmse_before_mm"),
        axes("rmse_fit_mm"),
        axes("loo_rmse_mm")
    )
}

/// A JSON number with two decimals, or "–".
fn num(v: &serde_json::Value) -> String {
    v.as_f64().map_or("–".into(), |x| format!("{x:.2}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Markup characters escaped, control characters (not allowed in XML 1.0 in any form)
    /// replaced; tabs and line ends kept.
    #[test]
    fn escaped_text_is_well_formed_xml_text() {
        assert_eq!(esc("a<b>&c"), "a&lt;b&gt;&amp;c");
        assert_eq!(esc("ctl\u{1}\u{1b}[31m"), "ctl\u{fffd}\u{fffd}[31m");
        assert_eq!(esc("t\tn\nr\r é"), "t\tn\nr\r é");
    }

    /// Values read from the run's own files (rea.jsonl, result.json) are page text: one edited
    /// to hold markup shows it escaped instead of adding elements to the page.
    #[test]
    fn values_from_the_runs_files_cannot_add_markup() {
        let d = tempfile::tempdir().unwrap();
        std::fs::create_dir_all(d.path().join("runs/learned")).unwrap();
        let line = serde_json::json!({"cycle": 1, "parent": "<b>p</b>", "child": {"id": "<i>c</i>",
            "v": 1.0, "macs": "<u>m</u>", "pitch_um": 9.0}, "removed": "<s>r</s>"});
        std::fs::write(d.path().join("runs/learned/rea.jsonl"), format!("{line}\n")).unwrap();
        let r = serde_json::json!({"stages": {}, "macs": "<em>x</em>",
            "protocol": {"learned": {"failures": "<q>f</q>", "frames": 3, "mean_deg": 1.0}}});
        let h = html(d.path(), &r).unwrap();
        for tag in ["<b>p", "<i>c", "<u>m", "<s>r", "<em>x", "<q>f"] {
            assert!(!h.contains(tag), "{tag} pasted into the page");
        }
        for text in [
            "&lt;b&gt;p",
            "&lt;i&gt;c",
            "&lt;u&gt;m",
            "&lt;s&gt;r",
            "&lt;em&gt;x",
            "&lt;q&gt;f",
        ] {
            assert!(h.contains(text), "{text} missing");
        }
        assert!(h.contains("<td>3</td>"), "a number stays as written");
    }

    /// A run whose learned lens came from the embedding objective shows its objective before
    /// and after, the bounds with three significant digits; a run without shows no such table.
    #[test]
    fn the_embedding_objective_is_shown_only_for_an_embedding_lens() {
        let d = tempfile::tempdir().unwrap();
        let ev = |l: f64, b: f64| {
            serde_json::json!({"triplets": 48, "loss": l, "l_sens": l - 0.1, "l_orth": 0.1346,
                "crlb_slip_um": b, "crlb_gaze_deg": 0.000_771_2})
        };
        let mut r = serde_json::json!({"stages": {}, "protocol": {}});
        let plain = html(d.path(), &r).unwrap();
        assert!(!plain.contains("embedding objective"));
        r["learned_lens_embedding"] =
            serde_json::json!({"init": ev(-15.8, 0.1666), "final": ev(-16.0, 0.1472)});
        let h = html(d.path(), &r).unwrap();
        assert!(h.contains("The learned lens's embedding objective"));
        assert!(h.contains("over 48 rendered triplets"));
        for s in [
            "-15.80", "-16.00", "1.666e-1", "1.472e-1", "7.712e-4", "1.346e-1",
        ] {
            assert!(h.contains(s), "{s} missing");
        }
        // A jointly trained lens says so, with its weight.
        r["learned_lens_embedding"]["learned_lens"] = "joint".into();
        r["learned_lens_embedding"]["embed_weight"] = 10.0.into();
        let h = html(d.path(), &r).unwrap();
        assert!(h.contains("plus 10.00 times the optical-embedding objective"));
        assert!(h.contains("after joint training"));
        assert!(!h.contains("after the embedding"));
    }

    /// Two slippage states of two frames each and one estimate off the chart: each panel draws
    /// every frame, one diamond per state at the state's mean, and counts the one outside.
    #[test]
    fn slip_chart_marks_state_means_and_counts_what_it_clamps() {
        let row = |state: u64, t: [f64; 3], e: [f64; 3]| serde_json::json!({"slip_state": state, "true_slip_mm": t, "tracked_slip_mm": e});
        let rows = [
            row(0, [0.0, 0.0, 0.0], [1.0, 0.0, 0.0]),
            row(0, [0.0, 0.0, 0.0], [-3.0, 0.0, 0.0]),
            row(1, [2.5, 0.0, 0.0], [2.0, 0.0, 9.0]),
            row(1, [2.5, 0.0, 0.0], [3.0, 0.0, 0.0]),
        ];
        let svg = slip_svg(&rows);
        assert_eq!(
            svg.matches("<circle").count(),
            12,
            "one dot per frame and axis"
        );
        assert_eq!(
            svg.matches("<path").count(),
            6,
            "one diamond per state and axis"
        );
        assert_eq!(
            svg.matches("1 beyond ±7 mm").count(),
            1,
            "only z has a clamped value"
        );
        assert_eq!(svg.matches("stroke=\"#c0392b\"").count(), 1);
        // Panel x: state 0's mean estimate is −1 mm and state 1's 2.5 mm, at their true values.
        let (ml, side, pw, mb) = (46.0, 220.0 - 46.0 - 8.0, 220.0, 36.0);
        let px = |v: f64| ml + side * (v + 7.0) / 14.0;
        let py = |v: f64| pw - mb - side * (v + 7.0) / 14.0;
        for (t, e) in [(0.0, -1.0), (2.5, 2.5)] {
            let d = format!(
                "M{:.1} {:.1} L{:.1} {:.1}",
                px(t) - 5.0,
                py(e),
                px(t),
                py(e) - 5.0
            );
            assert!(svg.contains(&d), "no diamond at ({t}, {e}): {d}");
        }
        // Tick labels on both axes of each panel.
        assert_eq!(svg.matches(">-2.5</text>").count(), 6);
    }
}

//! Figures of `nanoeye run` for the report: a lens's PSFs over depth, and example sensor
//! images (what the network sees) with the true and the predicted pupil outlines.

use anyhow::{Context, Result};
use image::{Rgb, RgbImage};
use nanoeye_nets::{BnMode, Supernet};
use nanoeye_optics::PhaseMap;
use nanoeye_search::{CameraChain, EvalSetup};
use nanoeye_sensor::NoiseMode;

/// Gap between tiles (px).
const GAP: u32 = 4;

fn encode(img: &RgbImage) -> Result<Vec<u8>> {
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png)
        .context("encoding a report figure")?;
    Ok(out.into_inner())
}

/// The PSF of every depth slab of `chain` through `map`, side by side (near to far), each
/// scaled to its own peak with a square-root tone curve so the out-of-focus tails show, each
/// tile upscaled to ≈ 96 px. Returns the PNG and the slab depths (mm).
pub fn psf_strip(chain: &CameraChain, map: &PhaseMap) -> Result<(Vec<u8>, Vec<f64>)> {
    let depths = chain.depths_m().to_vec();
    let psfs = chain.psfs(map, &vec![true; depths.len()])?;
    let planes = &psfs.unit;
    let n = planes.first().map_or(0, |p| p.nrows()) as u32;
    // Nearest-neighbour upscale so a tile is ≈ 96 px wide: the windows are a few dozen pixels.
    let z = (96 / n.max(1)).max(1);
    let t = n * z;
    let w = planes.len() as u32 * (t + GAP) - GAP;
    let mut img = RgbImage::from_pixel(w.max(1), t.max(1), Rgb([255, 255, 255]));
    for (k, p) in planes.iter().enumerate() {
        let peak = p
            .col_iter()
            .flat_map(|c| c.iter().copied())
            .fold(0.0f32, f32::max);
        let inv = if peak > 0.0 { 1.0 / peak } else { 0.0 };
        let x0 = k as u32 * (t + GAP);
        for i in 0..p.nrows() {
            for j in 0..p.ncols() {
                let v = ((p[(i, j)] * inv).max(0.0).sqrt() * 255.0).round() as u8;
                for di in 0..z {
                    for dj in 0..z {
                        img.put_pixel(x0 + j as u32 * z + dj, i as u32 * z + di, Rgb([v, v, v]));
                    }
                }
            }
        }
    }
    Ok((encode(&img)?, depths.iter().map(|d| d * 1e3).collect()))
}

/// Pixels of a binary mask (≥ 0.5) that touch a pixel outside it: the outline.
fn outline(m: &[f32], h: usize, w: usize) -> Vec<bool> {
    let inside = |i: isize, j: isize| {
        i >= 0
            && j >= 0
            && (i as usize) < h
            && (j as usize) < w
            && m[i as usize * w + j as usize] >= 0.5
    };
    let mut out = vec![false; h * w];
    for i in 0..h as isize {
        for j in 0..w as isize {
            if inside(i, j)
                && !(inside(i - 1, j) && inside(i + 1, j) && inside(i, j - 1) && inside(i, j + 1))
            {
                out[i as usize * w + j as usize] = true;
            }
        }
    }
    out
}

/// Frames `ids` of `s.data` through `s`'s chain, lens, p̂ and subnet (BN as it stands): the
/// normalised sensor image in grey (×2 upscaled), the true visible-pupil outline in green, the
/// predicted one (p ≥ 0.5) in red, yellow where they coincide; tiles side by side.
pub fn example_strip(net: &mut Supernet, s: &EvalSetup, ids: &[usize]) -> Result<Vec<u8>> {
    let frames = s.chain.load(s.data, ids)?;
    let psfs = s.chain.psfs(s.map, &s.chain.active(&frames))?;
    // Nothing differentiates the strip: no S1 tape.
    let fwd = s.chain.forward_with(
        &frames,
        &psfs,
        s.p_hat_m,
        NoiseMode::Gaussian,
        s.seed ^ 0xBEEF,
        false,
    )?;
    let o = net.forward(s.arch, &fwd.input, BnMode::Eval)?;
    let (h, w) = fwd.grid.shape();
    const S: u32 = 2;
    let tw = w as u32 * S;
    let total = ids.len() as u32 * (tw + GAP) - GAP;
    let mut img = RgbImage::from_pixel(total.max(1), (h as u32 * S).max(1), Rgb([255, 255, 255]));
    for b in 0..ids.len() {
        let x = fwd.input.image(b);
        let truth = outline(&fwd.mask.data[b * h * w..(b + 1) * h * w], h, w);
        let pred_p: Vec<f32> = o
            .mask_logits
            .image(b)
            .iter()
            .map(|&l| 1.0 / (1.0 + (-l).exp()))
            .collect();
        let pred = outline(&pred_p, h, w);
        // Stretch each tile to its own 1st–99th percentile: NIR frames are dark.
        let mut sorted: Vec<f32> = x.to_vec();
        sorted.sort_by(f32::total_cmp);
        let lo = sorted[sorted.len() / 100];
        let hi = sorted[sorted.len() * 99 / 100].max(lo + 1e-6);
        let x0 = b as u32 * (tw + GAP);
        for i in 0..h {
            for j in 0..w {
                let v = (((x[i * w + j] - lo) / (hi - lo)).clamp(0.0, 1.0) * 255.0) as u8;
                let k = i * w + j;
                let c = match (truth[k], pred[k]) {
                    (true, true) => Rgb([255, 230, 0]),
                    (true, false) => Rgb([0, 220, 0]),
                    (false, true) => Rgb([255, 40, 40]),
                    _ => Rgb([v, v, v]),
                };
                for di in 0..S {
                    for dj in 0..S {
                        img.put_pixel(x0 + j as u32 * S + dj, i as u32 * S + di, c);
                    }
                }
            }
        }
    }
    encode(&img)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn outline_of_a_disc_is_its_rim() {
        let (h, w) = (21, 21);
        let m: Vec<f32> = (0..h * w)
            .map(|k| {
                let (i, j) = ((k / w) as f64 - 10.0, (k % w) as f64 - 10.0);
                if i.hypot(j) <= 6.0 { 1.0 } else { 0.0 }
            })
            .collect();
        let o = outline(&m, h, w);
        let inside = m.iter().filter(|&&v| v >= 0.5).count();
        let rim = o.iter().filter(|&&b| b).count();
        assert!(rim > 0 && rim < inside / 2, "rim {rim} of {inside}");
        assert!(!o[10 * w + 10], "the centre is not on the outline");
        assert!(o[10 * w + 16], "the rightmost inside pixel is");
    }
}

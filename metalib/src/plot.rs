//! Minimal RGB raster canvas (PNG via the `image` crate) for heat maps and curves.

use crate::error::MetalibError;

/// An RGB8 canvas, row-major, origin top-left (pixels).
#[derive(Debug, Clone)]
pub struct Canvas {
    w: usize,
    h: usize,
    px: Vec<u8>,
}

impl Canvas {
    /// A black canvas of `w`×`h` pixels.
    pub fn new(w: usize, h: usize) -> Self {
        Self {
            w,
            h,
            px: vec![0; w * h * 3],
        }
    }

    /// Sets one pixel (ignored outside the canvas).
    pub fn set(&mut self, x: usize, y: usize, rgb: [u8; 3]) {
        if x < self.w && y < self.h {
            let k = 3 * (y * self.w + x);
            self.px[k..k + 3].copy_from_slice(&rgb);
        }
    }

    /// Fills an axis-aligned rectangle.
    pub fn fill_rect(&mut self, x: usize, y: usize, w: usize, h: usize, rgb: [u8; 3]) {
        for yy in y..(y + h).min(self.h) {
            for xx in x..(x + w).min(self.w) {
                self.set(xx, yy, rgb);
            }
        }
    }

    /// Draws a straight line between two points (pixel coordinates).
    pub fn line(&mut self, xa: f64, ya: f64, xb: f64, yb: f64, rgb: [u8; 3]) {
        let n = ((xb - xa).abs().max((yb - ya).abs()).ceil() as usize).max(1);
        for k in 0..=n {
            let t = k as f64 / n as f64;
            let (x, y) = (xa + t * (xb - xa), ya + t * (yb - ya));
            if x >= 0.0 && y >= 0.0 {
                self.set(x.round() as usize, y.round() as usize, rgb);
            }
        }
    }

    /// PNG encoding of the canvas.
    pub fn png(&self) -> Result<Vec<u8>, MetalibError> {
        let img = image::RgbImage::from_raw(self.w as u32, self.h as u32, self.px.clone())
            .ok_or_else(|| MetalibError::Numerical("canvas size mismatch".into()))?;
        let mut out = std::io::Cursor::new(Vec::new());
        img.write_to(&mut out, image::ImageFormat::Png)
            .map_err(|e| MetalibError::Numerical(format!("png encoding: {e}")))?;
        Ok(out.into_inner())
    }
}

/// Perceptually ordered colour map (viridis-like, piecewise linear) for v ∈ [0, 1].
pub fn colormap(v: f64) -> [u8; 3] {
    const STOPS: [[f64; 3]; 5] = [
        [68.0, 1.0, 84.0],
        [59.0, 82.0, 139.0],
        [33.0, 145.0, 140.0],
        [94.0, 201.0, 98.0],
        [253.0, 231.0, 37.0],
    ];
    let v = if v.is_finite() {
        v.clamp(0.0, 1.0)
    } else {
        0.0
    };
    let x = v * 4.0;
    let i = (x.floor() as usize).min(3);
    let f = x - i as f64;
    let mut out = [0u8; 3];
    for (c, o) in out.iter_mut().enumerate() {
        *o = (STOPS[i][c] + f * (STOPS[i + 1][c] - STOPS[i][c])).round() as u8;
    }
    out
}

fn svg_err<E: std::fmt::Display>(e: E) -> MetalibError {
    MetalibError::Numerical(format!("svg figure: {e}"))
}

/// Half the spacing of an ascending grid (nm), for cell edges; 5 nm for a single value.
fn half_step(v: &[f64]) -> f64 {
    if v.len() > 1 {
        0.5 * (v[1] - v[0])
    } else {
        5.0
    }
}

/// Heat map of `values` (`[height][pitch]`, NaN grey) over pitch (x, nm) and height (y, nm) as
/// SVG, with axes, a colour bar from `range.0` to `range.1` labelled `bar_label`, and a red
/// ring at grid index `mark` = (height index, pitch index).
pub fn heatmap_svg(
    title: &str,
    bar_label: &str,
    values: &[f64],
    heights_nm: &[f64],
    pitches_nm: &[f64],
    range: (f64, f64),
    mark: Option<(usize, usize)>,
) -> Result<String, MetalibError> {
    use plotters::prelude::*;
    let (nh, ns) = (heights_nm.len(), pitches_nm.len());
    if nh == 0 || ns == 0 || values.len() != nh * ns {
        return Err(MetalibError::Numerical(format!(
            "heat map of {} values on a {nh}×{ns} grid",
            values.len()
        )));
    }
    let (lo, hi) = range;
    let hi = if hi > lo { hi } else { lo + 1.0 };
    let (dh, ds) = (half_step(heights_nm), half_step(pitches_nm));
    let fill = |v: f64| {
        let c = if v.is_finite() {
            colormap((v - lo) / (hi - lo))
        } else {
            [160, 160, 160]
        };
        RGBColor(c[0], c[1], c[2]).filled()
    };
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, (860, 640)).into_drawing_area();
        root.fill(&WHITE).map_err(svg_err)?;
        let (main, bar) = root.split_horizontally(740);
        let mut chart = ChartBuilder::on(&main)
            .caption(title, ("sans-serif", 18))
            .margin(12)
            .x_label_area_size(45)
            .y_label_area_size(65)
            .build_cartesian_2d(
                pitches_nm[0] - ds..pitches_nm[ns - 1] + ds,
                heights_nm[0] - dh..heights_nm[nh - 1] + dh,
            )
            .map_err(svg_err)?;
        chart
            .configure_mesh()
            .disable_mesh()
            .x_desc("pitch s (nm)")
            .y_desc("pillar height h (nm)")
            .label_style(("sans-serif", 13))
            .axis_desc_style(("sans-serif", 15))
            .x_label_formatter(&|v| format!("{v:.0}"))
            .y_label_formatter(&|v| format!("{v:.0}"))
            .draw()
            .map_err(svg_err)?;
        chart
            .draw_series(
                (0..nh)
                    .flat_map(|ih| (0..ns).map(move |is| (ih, is)))
                    .map(|(ih, is)| {
                        let (s, h) = (pitches_nm[is], heights_nm[ih]);
                        Rectangle::new(
                            [(s - ds, h - dh), (s + ds, h + dh)],
                            fill(values[ih * ns + is]),
                        )
                    }),
            )
            .map_err(svg_err)?;
        if let Some((ih, is)) = mark.filter(|&(ih, is)| ih < nh && is < ns) {
            chart
                .draw_series(std::iter::once(Circle::new(
                    (pitches_nm[is], heights_nm[ih]),
                    6,
                    RED.stroke_width(2),
                )))
                .map_err(svg_err)?;
        }
        let mut cb = ChartBuilder::on(&bar)
            .margin_top(42)
            .margin_bottom(57)
            .margin_right(8)
            .y_label_area_size(55)
            .build_cartesian_2d(0.0..1.0, lo..hi)
            .map_err(svg_err)?;
        cb.configure_mesh()
            .disable_mesh()
            .disable_x_axis()
            .y_desc(bar_label)
            .y_labels(6)
            .label_style(("sans-serif", 13))
            .axis_desc_style(("sans-serif", 15))
            .draw()
            .map_err(svg_err)?;
        const STEPS: usize = 100;
        cb.draw_series((0..STEPS).map(|k| {
            let a = lo + (hi - lo) * k as f64 / STEPS as f64;
            let b = lo + (hi - lo) * (k + 1) as f64 / STEPS as f64;
            Rectangle::new([(0.0, a), (1.0, b)], fill(0.5 * (a + b)))
        }))
        .map_err(svg_err)?;
        root.present().map_err(svg_err)?;
    }
    Ok(svg)
}

/// One curve of [`curves_svg`]: its label and (x, y, emphasised) points.
pub struct Curve {
    /// Legend text.
    pub label: String,
    /// Points in plot units; segments ending on a point with `true` are drawn solid.
    pub points: Vec<(f64, f64, bool)>,
}

/// Line plot as SVG with axes and a legend: each curve pale where not emphasised, in its
/// colour-map colour where emphasised.
pub fn curves_svg(
    title: &str,
    x_desc: &str,
    y_desc: &str,
    curves: &[Curve],
) -> Result<String, MetalibError> {
    use plotters::prelude::*;
    let pts = curves.iter().flat_map(|c| c.points.iter());
    let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for &(x, y, _) in pts.filter(|p| p.0.is_finite() && p.1.is_finite()) {
        (x0, x1, y0, y1) = (x0.min(x), x1.max(x), y0.min(y), y1.max(y));
    }
    if x0 > x1 || y0 > y1 {
        return Err(MetalibError::Numerical("no finite points to plot".into()));
    }
    if x0 == x1 {
        // One x (a sweep of one diameter): an axis around it.
        let pad = (x0.abs() * 0.05).max(1e-9);
        (x0, x1) = (x0 - pad, x1 + pad);
    }
    let pad = 0.05 * (y1 - y0).max(1e-9);
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, (860, 640)).into_drawing_area();
        root.fill(&WHITE).map_err(svg_err)?;
        let mut chart = ChartBuilder::on(&root)
            .caption(title, ("sans-serif", 18))
            .margin(12)
            .x_label_area_size(45)
            .y_label_area_size(65)
            .build_cartesian_2d(x0..x1, y0 - pad..y1 + pad)
            .map_err(svg_err)?;
        chart
            .configure_mesh()
            .x_desc(x_desc)
            .y_desc(y_desc)
            .label_style(("sans-serif", 13))
            .axis_desc_style(("sans-serif", 15))
            .x_label_formatter(&|v| format!("{v:.0}"))
            .draw()
            .map_err(svg_err)?;
        let n = curves.len().max(2) as f64;
        for (k, c) in curves.iter().enumerate() {
            let rgb = colormap(k as f64 / (n - 1.0));
            let col = RGBColor(rgb[0], rgb[1], rgb[2]);
            let pale = RGBColor(rgb[0] / 3 + 170, rgb[1] / 3 + 170, rgb[2] / 3 + 170);
            chart
                .draw_series(LineSeries::new(
                    c.points.iter().map(|&(x, y, _)| (x, y)),
                    pale.stroke_width(1),
                ))
                .map_err(svg_err)?
                .label(c.label.as_str())
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], col));
            chart
                .draw_series(c.points.windows(2).filter(|w| w[1].2).map(|w| {
                    PathElement::new(
                        vec![(w[0].0, w[0].1), (w[1].0, w[1].1)],
                        col.stroke_width(2),
                    )
                }))
                .map_err(svg_err)?;
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .position(SeriesLabelPosition::UpperLeft)
            .draw()
            .map_err(svg_err)?;
        root.present().map_err(svg_err)?;
    }
    Ok(svg)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn svg_heat_map_draws_every_cell_with_axes_and_rejects_bad_shapes() {
        let (h, s) = ([100.0, 110.0, 120.0], [200.0, 210.0, 220.0, 230.0]);
        let mut v: Vec<f64> = (0..12).map(|k| k as f64 / 11.0).collect();
        v[5] = f64::NAN;
        let svg = heatmap_svg("t", "bar", &v, &h, &s, (0.0, 1.0), Some((1, 2))).unwrap();
        assert!(svg.contains("pitch s (nm)") && svg.contains("pillar height h (nm)"));
        // Exactly one grey cell: the NaN.
        assert_eq!(svg.matches("#A0A0A0").count(), 1, "NaN cells");
        assert!(svg.contains("<circle"), "marker");
        let bad = heatmap_svg("t", "bar", &v[..11], &h, &s, (0.0, 1.0), None);
        assert!(bad.is_err());
    }

    #[test]
    fn svg_curves_need_finite_points() {
        let c = Curve {
            label: "a".into(),
            points: vec![(0.0, 1.0, true), (1.0, 2.0, false), (2.0, 0.5, true)],
        };
        let svg = curves_svg("t", "x", "y", &[c]).unwrap();
        assert!(svg.contains(">\na\n</text>"), "legend label");
        let empty = Curve {
            label: "e".into(),
            points: vec![(f64::NAN, 1.0, true)],
        };
        assert!(curves_svg("t", "x", "y", &[empty]).is_err());
    }
}

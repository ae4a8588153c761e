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

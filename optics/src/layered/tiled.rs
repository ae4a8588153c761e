//! S1's spectral path on tiles. A large frame's layers cover a fraction of it (a depth slab of
//! an eye: 36 % of the 160×160 tiles of the paper-size frames, docs/bench/chain.md), yet the
//! whole-grid path transforms the whole padded grid per layer. Here each covered T×T tile is
//! transformed on its own N×N grid (N ≥ T + W_p − 1, so the linear convolution of the tile
//! does not wrap), multiplied by the kernel's N×N spectrum, inverse-transformed and its part
//! of the composition added into I⁽ᵏ⁾ and α∗P (overlap-add, exact up to round-off); the PSF
//! adjoint correlates each covered tile with its N×N window of the gradient and accumulates
//! the products per kernel on the N×N grid, so ∂loss/∂P needs one N×N inverse per kernel. A tile's grid (400 KB at N = 224)
//! stays in cache through its transforms, where the paper-size grid (9.3 MB) does not.
//!
//! Spectra are kept transposed (kx major, ky minor): the row transform, one transposition and
//! a second row transform give them, and the inverse runs the same steps back.

use super::*;
use crate::psf::fast_fft_size;

/// Padded grid points from which [`LayeredImager::new`] considers tiles: below it (4 MiB of
/// f32 complex values) the whole grid stays in the last-level cache, and the whole-grid path
/// skips the rows without data already.
const AUTO_GRID_POINTS: usize = 1 << 19;

/// Side of the blocks of the transpositions: 16 complex values of each of 16 rows, 2 KB read
/// and written per block, well inside L1.
const TB: usize = 16;

/// The tile side [`LayeredImager::new`] uses for an H×W image with W_p×W_p kernels whose
/// padded grid has `grid_points` points, `None` for the whole grid: tiles of about
/// 2.5 (W_p − 1) (160 for the paper's 65-pixel window: 5 × 8 tiles of 1280×800 on a 224²
/// grid) when the grid is beyond [`AUTO_GRID_POINTS`], the image holds at least 2 × 2 of them
/// and transforming every tile would cost at most twice the whole grid's points (so that a
/// layer covering under half the tiles gains).
pub(super) fn auto_tile(h: usize, w: usize, wp: usize, grid_points: usize) -> Option<usize> {
    if grid_points < AUTO_GRID_POINTS {
        return None;
    }
    let t0 = (5 * (wp - 1) / 2).max(32);
    let n = fast_fft_size(t0 + wp - 1);
    let t = n + 1 - wp;
    let tiles = h.div_ceil(t) * w.div_ceil(t);
    (h >= 2 * t && w >= 2 * t && tiles * n * n <= 2 * grid_points).then_some(t0)
}

/// Geometry, plans and work spaces of the tiled path.
pub(super) struct Tiling {
    /// Tile side (image pixels).
    pub(super) t: usize,
    /// Side of a tile's transform grid, T + W_p − 1 rounded up to a fast FFT size.
    pub(super) n: usize,
    /// Tiles down.
    pub(super) rows: usize,
    /// Tiles across.
    pub(super) cols: usize,
    h: usize,
    w: usize,
    fwd: Arc<dyn Fft<f32>>,
    inv: Arc<dyn Fft<f32>>,
    pool: Pool<TileBuffers>,
}

/// Where a tile's N×N grid meets the image ([`LayeredImager::tile_window`]).
struct TileWindow {
    /// Grid rows and columns that land in the image and hold the tile's convolution.
    ys: Range<usize>,
    xs: Range<usize>,
    /// The image rows and columns they are.
    rows: Range<usize>,
    cols: Range<usize>,
}

/// Work space of the tiled path: three tile grids and FFT scratch.
struct TileBuffers {
    a: Vec<c32>,
    b: Vec<c32>,
    c: Vec<c32>,
    scratch: Vec<c32>,
}

/// Dst[c·n + r] = src[r·n + c] for r in `rows`, c in `cols` (n×n row-major grids).
fn transpose(src: &[c32], dst: &mut [c32], n: usize, rows: Range<usize>, cols: Range<usize>) {
    // Checked once: the register blocks below read and write inside both grids.
    assert!(rows.end <= n && cols.end <= n && src.len() >= n * n && dst.len() >= n * n);
    for r0 in rows.clone().step_by(TB) {
        let r1 = (r0 + TB).min(rows.end);
        for c0 in cols.clone().step_by(TB) {
            let c1 = (c0 + TB).min(cols.end);
            // 4×4 values at a time in registers where AVX2 is compiled in (the workspace
            // builds for x86-64-v3); the block's last rows and columns one value at a time.
            #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
            let (r4, c4) = {
                let (r4, c4) = (r1 - (r1 - r0) % 4, c1 - (c1 - c0) % 4);
                for r in (r0..r4).step_by(4) {
                    for c in (c0..c4).step_by(4) {
                        // SAFETY: r + 3 < rows.end ≤ n and c + 3 < cols.end ≤ n, both grids
                        // hold n² values (asserted above).
                        unsafe { transpose4(src.as_ptr(), dst.as_mut_ptr(), n, r, c) };
                    }
                }
                (r4, c4)
            };
            #[cfg(not(all(target_arch = "x86_64", target_feature = "avx2")))]
            let (r4, c4) = (r0, c0);
            for r in r0..r1 {
                let cs = if r < r4 { c4..c1 } else { c0..c1 };
                for c in cs {
                    dst[c * n + r] = src[r * n + c];
                }
            }
        }
    }
}

/// Rows r .. r + 4, columns c .. c + 4 of the row-major n×n grid `src` into columns r .. r + 4,
/// rows c .. c + 4 of `dst`: a complex value is one 64-bit lane, so the 4×4 block is two
/// unpacks and two 128-bit permutes per pair of registers.
///
/// # Safety
/// r + 4 ≤ n, c + 4 ≤ n, both grids hold n² values.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
#[inline]
unsafe fn transpose4(src: *const c32, dst: *mut c32, n: usize, r: usize, c: usize) {
    use std::arch::x86_64::*;
    // SAFETY: the four rows of four values read and written lie inside the grids by the
    // contract; unaligned loads and stores; c32 is two f32 (repr(C)), one f64 lane.
    unsafe {
        let at = |i: usize| src.add((r + i) * n + c) as *const f64;
        let [a, b, cc, d] = [0, 1, 2, 3].map(|i| _mm256_loadu_pd(at(i)));
        let (ab_lo, ab_hi) = (_mm256_unpacklo_pd(a, b), _mm256_unpackhi_pd(a, b));
        let (cd_lo, cd_hi) = (_mm256_unpacklo_pd(cc, d), _mm256_unpackhi_pd(cc, d));
        let out = [
            _mm256_permute2f128_pd::<0x20>(ab_lo, cd_lo),
            _mm256_permute2f128_pd::<0x20>(ab_hi, cd_hi),
            _mm256_permute2f128_pd::<0x31>(ab_lo, cd_lo),
            _mm256_permute2f128_pd::<0x31>(ab_hi, cd_hi),
        ];
        for (j, v) in out.into_iter().enumerate() {
            _mm256_storeu_pd(dst.add((c + j) * n + r) as *mut f64, v);
        }
    }
}

/// One row of a tile's part of a layer's composition: I⁽ᵏ⁾ += gain·(L∗P) − (α∗P)·I⁽ᵏ⁻¹⁾
/// and, when given, α∗P += its occlusion channel, for the tile's inverse transform `s` (real:
/// radiance channel over the radiance scale, imaginary: occlusion channel).
#[inline]
fn add_tile_row(gain: f64, s: &[c32], prev: &[f32], cur: &mut [f32], o: Option<&mut [f32]>) {
    // In f32 where f32 holds the gain exactly (`exact_f32`): the same bits, eight lanes
    // instead of four and no conversions.
    if let Some(g) = exact_f32(gain) {
        compose_row(|s, p| g * s.re - s.im * p, s, prev, cur, o);
    } else {
        compose_row(
            |s, p| (gain * s.re as f64) as f32 - s.im * p,
            s,
            prev,
            cur,
            o,
        );
    }
}

/// [`add_tile_row`] with the part of pixel (s, I⁽ᵏ⁻¹⁾) given by `part`.
#[inline(always)]
fn compose_row(
    part: impl Fn(&c32, f32) -> f32,
    s: &[c32],
    prev: &[f32],
    cur: &mut [f32],
    o: Option<&mut [f32]>,
) {
    match o {
        Some(o) => {
            for (((s, &p), c), o) in s.iter().zip(prev).zip(cur).zip(o) {
                *c += part(s, p);
                *o += s.im;
            }
        }
        None => {
            for ((s, &p), c) in s.iter().zip(prev).zip(cur) {
                *c += part(s, p);
            }
        }
    }
}

/// The copy of I⁽ᵏ⁻¹⁾ `image` (rows of `w` pixels) over `reach` into `prev` and α∗P's zeros
/// into `o`, both packed, grown from row `band` to row `end` (nothing when `end ≤ band`).
fn grow_band(
    reach: &Reach,
    (image, w): (&[f32], usize),
    band: &mut usize,
    end: usize,
    (prev, o): (&mut Vec<f32>, &mut Option<Vec<f32>>),
) {
    if end <= *band {
        return;
    }
    for (r, cols, _) in reach.rows_in(*band..end) {
        prev.extend_from_slice(&image[r * w + cols.start..r * w + cols.end]);
    }
    if let Some(o) = o.as_mut() {
        o.resize(prev.len(), 0.0);
    }
    *band = end;
}

/// One row of a tile's window of the gradient: the complex value of each pixel of ∂L/∂I⁽ᵏ⁾
/// `gi` and I⁽ᵏ⁻¹⁾ `prev` by `value` ([`gradient_value`] or its f32 form).
#[inline(always)]
fn window_row(row: &mut [c32], gi: &[f32], prev: &[f32], value: impl Fn(f32, f32) -> c32) {
    for ((v, &gv), &p) in row.iter_mut().zip(gi).zip(prev) {
        *v = value(gv, p);
    }
}

impl Tiling {
    /// Tiles of at least `t_min` pixels for H×W images and W_p×W_p kernels: the side is
    /// widened to fill the fast transform size that holds its convolution.
    pub(super) fn new(h: usize, w: usize, wp: usize, t_min: usize) -> Self {
        let n = fast_fft_size(t_min + wp - 1);
        let t = n + 1 - wp;
        let mut pl = Planner::<f32>::new();
        Self {
            t,
            n,
            rows: h.div_ceil(t),
            cols: w.div_ceil(t),
            h,
            w,
            fwd: pl.plan_fft_forward(n),
            inv: pl.plan_fft_inverse(n),
            pool: Pool::new(POOL_MAX),
        }
    }

    /// A finished call's work space, or a new one.
    fn buffers(&self) -> TileBuffers {
        if let Some(tb) = self.pool.take() {
            return tb;
        }
        let z = c32::new(0.0, 0.0);
        let s = [&self.fwd, &self.inv]
            .iter()
            .map(|f| f.get_inplace_scratch_len())
            .max()
            .unwrap_or(0);
        let nn = self.n * self.n;
        TileBuffers {
            a: vec![z; nn],
            b: vec![z; nn],
            c: vec![z; nn],
            scratch: vec![z; s],
        }
    }

    /// Top-left pixel (y₀, x₀) and extent (rows, columns) of tile `tile` (row-major index).
    fn origin(&self, tile: u32) -> (usize, usize, usize, usize) {
        let (bi, bj) = (tile as usize / self.cols, tile as usize % self.cols);
        let (y0, x0) = (bi * self.t, bj * self.t);
        (y0, x0, self.t.min(self.h - y0), self.t.min(self.w - x0))
    }

    /// 2-D DFT of the row-major n×n grid `a`, whose rows outside `live` are zero, into `b`
    /// transposed; `a` is left holding its row transforms.
    fn fft2(&self, a: &mut [c32], live: Range<usize>, b: &mut [c32], scratch: &mut [c32]) {
        let n = self.n;
        if !live.is_empty() {
            self.fwd
                .process_with_scratch(&mut a[live.start * n..live.end * n], scratch);
        }
        for row in b.chunks_exact_mut(n) {
            row[..live.start].fill(c32::new(0.0, 0.0));
            row[live.end..].fill(c32::new(0.0, 0.0));
        }
        transpose(a, b, n, live, 0..n);
        self.fwd.process_with_scratch(b, scratch);
    }

    /// Inverse 2-D DFT (unnormalised) of the transposed spectrum `b` (overwritten) into the
    /// rows `out` of the row-major grid `a`; its other rows are not written.
    fn ifft2(&self, b: &mut [c32], out: Range<usize>, a: &mut [c32], scratch: &mut [c32]) {
        self.inv.process_with_scratch(b, scratch);
        self.ifft2_rest(b, out, a, scratch);
    }

    /// [`Self::ifft2`] of the product of the spectra `s` (or `b`'s own, `None`) and `p`
    /// (transposed, n×n), formed in `b` row by row, each row's first inverse pass run as soon
    /// as it is formed: it transforms in L1, while the next row's values are on their way
    /// from memory (a kept spectrum, 0.4 MB a tile, is read from memory).
    fn ifft2_product(
        &self,
        (s, p): (Option<&[c32]>, &[c32]),
        b: &mut [c32],
        out: Range<usize>,
        a: &mut [c32],
        scratch: &mut [c32],
    ) {
        let n = self.n;
        for (r, (row, p)) in b.chunks_exact_mut(n).zip(p.chunks_exact(n)).enumerate() {
            match s {
                Some(s) => row
                    .iter_mut()
                    .zip(&s[r * n..(r + 1) * n])
                    .zip(p)
                    .for_each(|((b, &s), p)| *b = s * p),
                None => row.iter_mut().zip(p).for_each(|(b, p)| *b *= p),
            }
            self.inv.process_with_scratch(row, scratch);
        }
        self.ifft2_rest(b, out, a, scratch);
    }

    /// [`Self::ifft2`] after its first pass over `b`'s rows.
    fn ifft2_rest(&self, b: &mut [c32], out: Range<usize>, a: &mut [c32], scratch: &mut [c32]) {
        let n = self.n;
        transpose(b, a, n, 0..n, out.clone());
        if !out.is_empty() {
            self.inv
                .process_with_scratch(&mut a[out.start * n..out.end * n], scratch);
        }
    }
}

impl LayeredImager {
    /// [`Self::kernel_spectra`] on the tiles' N×N grid (transposed).
    pub(super) fn tiled_kernel_spectra(
        &self,
        t: &Tiling,
        kernels: &[Option<&Mat<f32>>],
    ) -> Result<KernelSpectra> {
        let (n, wp) = (t.n, self.wp);
        let mut tb = t.buffers();
        let norm = 1.0 / (n * n) as f32;
        let mut spec = Vec::with_capacity(kernels.len());
        for k in kernels {
            let Some(m) = k else {
                spec.push(None);
                continue;
            };
            for r in 0..wp {
                let row = &mut tb.a[r * n..(r + 1) * n];
                for (c, v) in row.iter_mut().enumerate() {
                    *v = c32::new(if c < wp { m[(r, c)] } else { 0.0 }, 0.0);
                }
            }
            t.fft2(&mut tb.a, 0..wp, &mut tb.b, &mut tb.scratch);
            spec.push(Some(tb.b.iter().map(|p| p * norm).collect()));
        }
        t.pool.give(tb);
        Ok(KernelSpectra { spec })
    }

    /// One pass over a layer's planes: the tiles it covers (α ≠ 0 somewhere in them,
    /// row-major index) and its radiance scale ([`SpectralLayer::radiance_scale`]'s value),
    /// `None` for a layer without coverage; a non-finite α or weighted L, or a product of
    /// them that is not finite, is refused as the whole-grid path refuses it.
    pub(super) fn scan(
        &self,
        t: &Tiling,
        l: &SpectralLayer,
        k: usize,
    ) -> Result<Option<(Vec<u32>, f32)>> {
        let (by, al, rad, wt) = l.lines();
        let mut covered = vec![false; t.rows * t.cols];
        // Largest |α| and |α·w·L| as bit patterns: for non-negative floats the patterns order
        // as the values do, ∞ is 0x7f80_0000 and every NaN lies above it, so one integer
        // maximum (which vectorises, where f32::max's does not) gives the largest value, the
        // finiteness of all of them, and for α whether any is non-zero (NaN included, as
        // `x != 0.0` counts it).
        let (mut mv, mut mx) = (0u32, 0u32);
        let abs = |v: f32| v.to_bits() & 0x7fff_ffff;
        for (i, (a, r)) in al.iter().zip(&rad).enumerate() {
            let w = wt.as_ref().map(|wt| wt[i]);
            for (j, s0) in (0..a.len()).step_by(t.t).enumerate() {
                let span = s0..(s0 + t.t).min(a.len());
                let (x, y) = (&a[span.clone()], &r[span.clone()]);
                let (sx, sv) = match w {
                    Some(w) => x
                        .iter()
                        .zip(y)
                        .zip(&w[span])
                        .fold((0, 0), |(sx, sv), ((&x, &y), &s)| {
                            (sx.max(abs(x)), sv.max(abs(x * (s * y))))
                        }),
                    None => x.iter().zip(y).fold((0, 0), |(sx, sv), (&x, &y)| {
                        (sx.max(abs(x)), sv.max(abs(x * y)))
                    }),
                };
                if sx != 0 {
                    covered[match by {
                        Layout::Rows => (i / t.t) * t.cols + j,
                        Layout::Cols => j * t.cols + i / t.t,
                    }] = true;
                }
                (mx, mv) = (mx.max(sx), mv.max(sv));
            }
        }
        if mx.max(mv) >= f32::INFINITY.to_bits() {
            return Err(Self::non_finite(k, l.kernel));
        }
        let m = f32::from_bits(mv);
        let tiles: Vec<u32> = (0..covered.len() as u32)
            .filter(|&b| covered[b as usize])
            .collect();
        Ok((!tiles.is_empty()).then(|| (tiles, scale_of(m))))
    }

    /// Packs αL/s + iα of tile `tile` of a layer (its `lines`, taken once per layer) into
    /// the top-left of the n×n grid `a` (zero beyond its columns), the same values the
    /// whole-grid path packs; returns its rows.
    fn pack_tile(
        &self,
        t: &Tiling,
        lines: &Lines,
        tile: u32,
        scale: f32,
        a: &mut [c32],
    ) -> Range<usize> {
        let n = t.n;
        let (y0, x0, th, tw) = t.origin(tile);
        let inv = 1.0 / scale;
        let pack = |x: f32, y: f32| c32::new(x * y * inv, x);
        let (by, al, rad, wt) = lines;
        for row in a[..th * n].chunks_exact_mut(n) {
            row[tw..].fill(c32::new(0.0, 0.0));
        }
        match by {
            Layout::Rows => {
                for (r, row) in a[..th * n].chunks_exact_mut(n).enumerate() {
                    let span = x0..x0 + tw;
                    let (al, rad) = (&al[y0 + r][span.clone()], &rad[y0 + r][span.clone()]);
                    match &wt {
                        Some(wt) => {
                            for (o, ((&x, &y), &s)) in row
                                .iter_mut()
                                .zip(al.iter().zip(rad).zip(&wt[y0 + r][span]))
                            {
                                *o = pack(x, s * y);
                            }
                        }
                        None => {
                            for (o, (&x, &y)) in row.iter_mut().zip(al.iter().zip(rad)) {
                                *o = pack(x, y);
                            }
                        }
                    }
                }
            }
            Layout::Cols => {
                for c in 0..tw {
                    let span = y0..y0 + th;
                    let (al, rad) = (&al[x0 + c][span.clone()], &rad[x0 + c][span.clone()]);
                    match &wt {
                        Some(wt) => {
                            for (r, ((&x, &y), &s)) in
                                al.iter().zip(rad).zip(&wt[x0 + c][span]).enumerate()
                            {
                                a[r * n + c] = pack(x, s * y);
                            }
                        }
                        None => {
                            for (r, (&x, &y)) in al.iter().zip(rad).enumerate() {
                                a[r * n + c] = pack(x, y);
                            }
                        }
                    }
                }
            }
        }
        0..th
    }

    /// The rows (or columns, with x₀ and W) of a tile's N×N grid that land in the image and
    /// hold its linear convolution: grid index m is image index y₀ + m − c.
    fn window(&self, t: &Tiling, y0: usize, th: usize, h: usize) -> Range<usize> {
        let c = self.wp / 2;
        c.saturating_sub(y0)..t.n.min(h + c - y0).min(th + self.wp - 1)
    }

    /// Where tile `tile`'s N×N grid meets the image ([`Self::window`] both ways): grid rows
    /// `ys` are image rows `rows`, grid columns `xs` image columns `cols`, in order. The
    /// forward's overlap-add, the adjoint's windows and the layer's reach all take it from
    /// here, so every window lies inside its layer's reach.
    fn tile_window(&self, t: &Tiling, tile: u32) -> TileWindow {
        let (y0, x0, th, tw) = t.origin(tile);
        let c = self.wp / 2;
        let (ys, xs) = (
            self.window(t, y0, th, self.h),
            self.window(t, x0, tw, self.w),
        );
        TileWindow {
            rows: y0 + ys.start - c..y0 + ys.end - c,
            cols: x0 + xs.start - c..x0 + xs.end - c,
            ys,
            xs,
        }
    }

    /// The pixels the windows of `tiles` cover, as one span per image row from the first
    /// window's column to the last's; the spans' ends rounded out to multiples of
    /// [`DOT_LANES`] (or the row's end), so that the adjoint's partial sums over a span take
    /// each pixel in the lane a whole row gives it.
    fn reach(&self, t: &Tiling, tiles: &[u32]) -> Reach {
        let w = self.w;
        let mut spans = vec![(usize::MAX, 0); self.h];
        for &tile in tiles {
            let win = self.tile_window(t, tile);
            let (a, b) = (win.cols.start, win.cols.end);
            let (a, b) = (a - a % DOT_LANES, b.next_multiple_of(DOT_LANES).min(w));
            for s in &mut spans[win.rows] {
                *s = (s.0.min(a), s.1.max(b));
            }
        }
        Reach::from_spans(spans)
    }

    /// [`Self::layer_spectra`] on tiles.
    pub(super) fn tiled_layer_spectra(
        &self,
        t: &Tiling,
        layers: &[SpectralLayer],
    ) -> Result<LayerSpectra> {
        let nn = t.n * t.n;
        let mut tb = t.buffers();
        let (mut out, mut scales, mut all) = (Vec::new(), Vec::new(), Vec::new());
        for (k, l) in layers.iter().enumerate() {
            let Some((tiles, scale)) = self.scan(t, l, k)? else {
                out.push(None);
                scales.push(1.0);
                all.push(Vec::new());
                continue;
            };
            let mut spec = Vec::with_capacity(tiles.len() * nn);
            let lines = l.lines();
            for &tile in &tiles {
                let rows = self.pack_tile(t, &lines, tile, scale, &mut tb.a);
                t.fft2(&mut tb.a, rows, &mut tb.b, &mut tb.scratch);
                spec.extend_from_slice(&tb.b);
            }
            out.push(Some(spec));
            scales.push(scale);
            all.push(tiles);
        }
        t.pool.give(tb);
        Ok(LayerSpectra {
            layers: out,
            scales,
            nx: t.n,
            ny: t.n,
            tile: t.t,
            tiles: all,
            image: (self.h, self.w),
        })
    }

    /// [`Self::spectral`] on tiles: per covered tile its transform (or its given spectrum)
    /// times P̂, the inverse, and its part of the layer's composition. The whole-grid path's
    /// I⁽ᵏ⁾ = gain·(L∗P) + (1 − α∗P)·I⁽ᵏ⁻¹⁾ is linear in the convolution, so each tile's part
    /// goes straight into the image, updated in place from I⁽ᵏ⁻¹⁾ to I⁽ᵏ⁾ (where no tile
    /// reaches, α∗P is 0 and it stays so exactly) while the tiles read I⁽ᵏ⁻¹⁾ from a copy of
    /// the layer's reach alone; with a tape, that copy and α∗P over the reach are kept. No
    /// complex plane of the convolution is written and read back, and no pass over the whole
    /// frame is made per layer.
    pub(super) fn tiled_spectral(
        &self,
        t: &Tiling,
        layers: &[SpectralLayer],
        ks: &KernelSpectra,
        (spectra, cover): (Option<&LayerSpectra>, Option<&LayerCover>),
        keep: bool,
    ) -> Result<(Mat<f32>, Option<S1Tape>)> {
        let (h, w, n) = (self.h, self.w, t.n);
        let nn = n * n;
        let mut image = vec![0.0f32; h * w];
        // Without a tape, each layer's copy of I⁽ᵏ⁻¹⁾ reuses this buffer.
        let mut spare = Vec::new();
        let mut saved = Vec::with_capacity(layers.len());
        let mut record = (keep && spectra.is_none()).then(|| (Vec::new(), Vec::new()));
        let mut scales = Vec::with_capacity(layers.len());
        let mut tb = t.buffers();
        for (k, l) in layers.iter().enumerate() {
            let p = ks.spec[l.kernel].as_ref().expect("checked");
            let scanned;
            let (tiles, scale, given): (&[u32], f32, Option<&[c32]>) = match spectra {
                Some(s) => match s.layers[k].as_deref() {
                    Some(sp) => (&s.tiles[k], s.scales[k], Some(sp)),
                    None => {
                        saved.push(None);
                        scales.push(1.0);
                        continue;
                    }
                },
                None => {
                    let found = match cover {
                        Some(c) => &c.layers[k],
                        None => {
                            scanned = self.scan(t, l, k)?;
                            &scanned
                        }
                    };
                    match found {
                        Some((tiles, scale)) => (tiles, *scale, None),
                        None => {
                            saved.push(None);
                            scales.push(1.0);
                            if let Some((r, tl)) = record.as_mut() {
                                r.push(None);
                                tl.push(Vec::new());
                            }
                            continue;
                        }
                    }
                }
            };
            let gain = l.gain as f64 * scale as f64;
            let reach = self.reach(t, tiles);
            let mut prev = if keep {
                Vec::with_capacity(reach.len())
            } else {
                let mut c = std::mem::take(&mut spare);
                c.clear();
                c
            };
            let mut o = keep.then(|| Vec::with_capacity(reach.len()));
            // I⁽ᵏ⁻¹⁾ copied and α∗P's zeros written a band of rows at a time, just before the
            // first tile that adds into the band, so that the tiles find both in cache (a copy
            // and a fill of the whole reach up front left them in memory). Rows below `band`
            // hold both; no tile has added into a row at or past it, so the copy there is
            // still I⁽ᵏ⁻¹⁾. Zeros are written, not calloc'd: fresh pages that the tiles first
            // read and then write fault twice, the second time with a TLB shootdown across
            // the threads (the forward at batch 16 on 2 cores took 0.75–0.79 s instead of
            // 0.64–0.67 s).
            let mut band = 0;
            let mut rec = record
                .as_ref()
                .map(|_| Vec::with_capacity(tiles.len() * nn));
            let lines = given.is_none().then(|| l.lines());
            for (i, &tile) in tiles.iter().enumerate() {
                let win = self.tile_window(t, tile);
                grow_band(
                    &reach,
                    (&image, w),
                    &mut band,
                    win.rows.end,
                    (&mut prev, &mut o),
                );
                // The tile's spectrum: the kept one, or computed into b.
                let spectrum = match given {
                    Some(s) => Some(&s[i * nn..(i + 1) * nn]),
                    None => {
                        let lines = lines.as_ref().expect("taken when not given");
                        let rows = self.pack_tile(t, lines, tile, scale, &mut tb.a);
                        t.fft2(&mut tb.a, rows, &mut tb.b, &mut tb.scratch);
                        if let Some(rec) = rec.as_mut() {
                            rec.extend_from_slice(&tb.b);
                        }
                        None
                    }
                };
                let out = win.ys.clone();
                t.ifft2_product((spectrum, p), &mut tb.b, out, &mut tb.a, &mut tb.scratch);
                for (m, y) in win.ys.zip(win.rows) {
                    let src = &tb.a[m * n + win.xs.start..m * n + win.xs.end];
                    let at = reach.packed(y, win.cols.start);
                    let packed = at..at + src.len();
                    let o = o.as_mut().map(|o| &mut o[packed.clone()]);
                    let span = y * w + win.cols.start..y * w + win.cols.end;
                    add_tile_row(gain, src, &prev[packed], &mut image[span], o);
                }
            }
            grow_band(&reach, (&image, w), &mut band, self.h, (&mut prev, &mut o));
            debug_assert_eq!(prev.len(), reach.len());
            if let Some((r, tl)) = record.as_mut() {
                r.push(rec);
                tl.push(tiles.to_vec());
            }
            scales.push(scale);
            match o {
                Some(o) => saved.push(Some(Planes {
                    prev,
                    o,
                    reach,
                    tiles: tiles.to_vec(),
                })),
                None => spare = prev,
            }
        }
        t.pool.give(tb);
        self.finish_pass(image, saved, scales, record, keep)
    }

    /// [`Self::vjp_kernels`] on tiles for ∂loss/∂I = `gi` (row-major): per tile the forward
    /// imaged (the tape's), the transform of its N×N window of the gradient times the tile's
    /// conjugate spectrum, into the kernel's N×N accumulator, then the adjoint's pass over
    /// the layer's reach.
    pub(super) fn tiled_vjp_kernels(
        &self,
        t: &Tiling,
        layers: &[SpectralLayer],
        tape: &S1Tape,
        mut gi: Vec<f32>,
        acc: &mut KernelGradAccumulator,
        spectra: Option<&LayerSpectra>,
    ) -> Result<()> {
        let (w, n) = (self.w, t.n);
        let nn = n * n;
        let norm = 1.0 / nn as f32;
        let mut tb = t.buffers();
        // I⁽ᵏ⁾ of the layer at hand: the final image, set back to I⁽ᵏ⁻¹⁾ over each layer's
        // reach once the layer is done (outside its reach the two are equal).
        let mut above = tape.image.clone();
        for k in (0..layers.len()).rev() {
            let Some(Planes {
                prev,
                o,
                reach,
                tiles,
            }) = &tape.saved[k]
            else {
                continue;
            };
            let l = &layers[k];
            let gain = l.gain as f64 * tape.scales[k] as f64;
            // The tiles the forward imaged, which the tape's planes cover: spectra of other
            // tiles (another frame's) are refused, not read against them.
            let spec = match spectra.map(|s| (s.layers[k].as_deref(), &s.tiles[k])) {
                Some((None, _)) => {
                    return Err(OpticsError::Shape(format!(
                        "layer {k} has no spectrum but was imaged: spectra of other layers"
                    )));
                }
                Some((Some(_), st)) if st != tiles => {
                    return Err(OpticsError::Shape(format!(
                        "layer {k}'s spectra are of other tiles than its forward's: spectra \
                         of another frame"
                    )));
                }
                Some((Some(s), _)) => Some(s),
                None => None,
            };
            let mut fresh = acc.spec[l.kernel].is_none();
            let slot = acc.spec[l.kernel].get_or_insert_with(|| self.spare_spectrum());
            let lines = spec.is_none().then(|| l.lines());
            let exact = exact_f32(gain);
            for (i, &tile) in tiles.iter().enumerate() {
                let a: &[c32] = match (spec, &lines) {
                    (Some(s), _) => &s[i * nn..(i + 1) * nn],
                    (None, lines) => {
                        let lines = lines.as_ref().expect("taken when not given");
                        let rows = self.pack_tile(t, lines, tile, tape.scales[k], &mut tb.a);
                        t.fft2(&mut tb.a, rows, &mut tb.c, &mut tb.scratch);
                        &tb.c
                    }
                };
                let TileWindow { ys, xs, rows, cols } = self.tile_window(t, tile);
                // The gradient's window, computed where it is read: ∂L/∂I⁽ᵏ⁾ and I⁽ᵏ⁻¹⁾ are
                // 8 bytes a pixel as its complex plane would be, and no plane is written.
                for (m, y) in ys.clone().zip(rows) {
                    let row = &mut tb.a[m * n..(m + 1) * n];
                    row[..xs.start].fill(c32::new(0.0, 0.0));
                    row[xs.end..].fill(c32::new(0.0, 0.0));
                    let span = y * w + cols.start..y * w + cols.end;
                    let at = reach.packed(y, cols.start);
                    let (row, gi, prev) =
                        (&mut row[xs.clone()], &gi[span], &prev[at..at + cols.len()]);
                    match exact {
                        Some(g) => window_row(row, gi, prev, |gv, p| gradient_value_f32(g, gv, p)),
                        None => window_row(row, gi, prev, |gv, p| gradient_value(gain, gv, p)),
                    }
                }
                t.fft2(&mut tb.a, ys, &mut tb.b, &mut tb.scratch);
                accumulate(
                    slot,
                    fresh,
                    0..nn,
                    tb.b.iter().zip(a).map(|(g, a)| g * a.conj() * norm),
                );
                fresh = false;
            }
            // With every window read, ∂L/∂I⁽ᵏ⁻¹⁾ over ∂L/∂I⁽ᵏ⁾ and the radiance scale's term,
            // over the reach alone: outside it ∂L/∂I⁽ᵏ⁻¹⁾ = ∂L/∂I⁽ᵏ⁾ and the term is 0
            // exactly. The spans start at multiples of DOT_LANES, so the partial sums are
            // those of whole rows.
            let mut dots = [0.0f64; DOT_LANES];
            for (r, cols, packed) in reach.rows() {
                let span = r * w + cols.start..r * w + cols.end;
                adjoint_row(
                    gain,
                    &mut gi[span.clone()],
                    &prev[packed.clone()],
                    &o[packed.clone()],
                    &above[span.clone()],
                    None,
                    &mut dots,
                );
                above[span].copy_from_slice(&prev[packed]);
            }
            acc.radiance_scale[l.kernel] += dots.iter().sum::<f64>();
        }
        t.pool.give(tb);
        Ok(())
    }

    /// [`Self::kernel_grads`] on tiles: one N×N inverse per kernel, of the W_p rows kept.
    pub(super) fn tiled_kernel_grads(
        &self,
        t: &Tiling,
        acc: KernelGradAccumulator,
    ) -> Vec<Mat<f64>> {
        let (n, wp) = (t.n, self.wp);
        let mut tb = t.buffers();
        let grads = acc
            .spec
            .into_iter()
            .map(|s| match s {
                None => Mat::zeros(wp, wp),
                Some(mut v) => {
                    t.ifft2(&mut v, 0..wp, &mut tb.a, &mut tb.scratch);
                    self.spare.give(v);
                    Mat::from_fn(wp, wp, |r, c| tb.a[r * n + c].re as f64)
                }
            })
            .collect();
        t.pool.give(tb);
        grads
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `tape` with each layer's planes widened to the whole image (I⁽ᵏ⁻¹⁾ outside its reach
    /// from the layers above it, α∗P zero there): what the tape held before reaches.
    fn whole_planes(im: &LayeredImager, tape: &S1Tape) -> S1Tape {
        let (h, w) = (im.h, im.w);
        let mut above = tape.image.clone();
        let mut saved: Vec<Option<Planes>> = tape.saved.iter().map(|_| None).collect();
        for k in (0..tape.saved.len()).rev() {
            let Some(p) = &tape.saved[k] else { continue };
            let (mut prev, mut o) = (above.clone(), vec![0.0f32; h * w]);
            for (r, cols, packed) in p.reach.rows() {
                let span = r * w + cols.start..r * w + cols.end;
                prev[span.clone()].copy_from_slice(&p.prev[packed.clone()]);
                o[span].copy_from_slice(&p.o[packed]);
            }
            above = prev.clone();
            saved[k] = Some(Planes {
                prev,
                o,
                reach: Reach::full(h, w),
                tiles: p.tiles.clone(),
            });
        }
        S1Tape {
            saved,
            image: tape.image.clone(),
            grid: tape.grid,
            scales: tape.scales.clone(),
            spectra: None,
        }
    }

    /// The PSF adjoint over each layer's reach gives the bits of the pass over whole rows:
    /// outside the reach its terms are exact zeros and ∂L/∂I passes unchanged, and the spans
    /// start and end where whole rows put each pixel in the same partial sum (a layer over
    /// everything, a band, a 3×3 patch in one tile, and a block whose reach starts mid-row).
    #[test]
    fn the_adjoint_over_the_reach_gives_the_whole_rows_bits() {
        let (h, w, wp) = (40, 45, 5);
        let im = LayeredImager::with_tiles(h, w, wp, Some(12)).unwrap();
        let t = im.tiling.as_ref().expect("tiled");
        let psf = Mat::from_fn(wp, wp, |i, j| 1.0 / (1.0 + (i * 2 + j) as f32));
        let ks = im.kernel_spectra(&[Some(&psf), Some(&psf)]).unwrap();
        let rad = Mat::from_fn(h, w, |i, j| 0.1 + ((i * 7 + j * 13) % 17) as f32 / 7.0);
        let ones = Mat::from_fn(h, w, |_, _| 1.0f32);
        // Tile columns 2 and 3: windows from column 22, the reach from 16.
        let block = Mat::from_fn(h, w, |i, j| {
            if (5..35).contains(&i) && j >= 27 {
                0.3 + (i * j % 5) as f32 / 9.0
            } else {
                0.0
            }
        });
        let patch = Mat::from_fn(h, w, |i, j| {
            if (14..17).contains(&i) && (29..32).contains(&j) {
                0.8
            } else {
                0.0
            }
        });
        let band = Mat::from_fn(h, w, |i, j| {
            if (26..30).contains(&i) && j > 3 {
                0.6
            } else {
                0.0
            }
        });
        let layers = [
            SpectralLayer::new(rad.as_ref(), ones.as_ref(), 0),
            SpectralLayer::new(rad.as_ref(), band.as_ref(), 1),
            SpectralLayer::new(rad.as_ref(), patch.as_ref(), 0),
            SpectralLayer::new(rad.as_ref(), block.as_ref(), 1),
        ];
        let (_, mut tape) = im.forward_spectral(&layers, &ks, None).unwrap();
        // The reaches differ from whole rows, and one starts past column 0.
        let reach = |k: usize| &tape.saved[k].as_ref().expect("covered").reach;
        assert!((1..4).all(|k| reach(k).len() < h * w));
        assert!(reach(3).rows().all(|(_, c, _)| c.start == 16));
        let spectra = tape.take_spectra().expect("recorded");
        let whole = whole_planes(&im, &tape);
        let g = Mat::from_fn(h, w, |i, j| ((i * 5 + j * 3) % 7) as f32 / 3.0 - 1.1);
        let mut gi = vec![0.0f32; h * w];
        f32::rows_into(&g, &mut gi);
        let run = |tape: &S1Tape| {
            let mut acc = im.kernel_grad_accumulator(2);
            im.tiled_vjp_kernels(t, &layers, tape, gi.clone(), &mut acc, Some(&spectra))
                .unwrap();
            acc
        };
        let (a, b) = (run(&tape), run(&whole));
        let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&a.radiance_scale), bits(&b.radiance_scale));
        assert!(a.spec == b.spec, "∂L/∂P's spectra differ");
    }

    /// The blocked transposition (register blocks and the one-value edges) moves every value
    /// of the given rows and columns to its transposed place and writes nothing else: ranges
    /// of every length mod 4 and mod 16, starting anywhere, on grids of odd and even sides.
    #[test]
    fn transpose_moves_exactly_the_given_block() {
        for n in [1usize, 3, 4, 7, 16, 17, 33, 224] {
            let src: Vec<c32> = (0..n * n)
                .map(|i| c32::new(i as f32, -(i as f32) - 0.5))
                .collect();
            let bounds = [0, 1, n / 3, n / 2, n.saturating_sub(5), n - 1, n];
            for &r0 in &bounds {
                for &r1 in bounds.iter().filter(|&&b| b >= r0) {
                    for (c0, c1) in [(0, n), (n / 4, n - n / 5), (1, n.min(6))] {
                        let (c0, c1) = (c0.min(c1), c1);
                        let mut dst = vec![c32::new(f32::NAN, 7.0); n * n];
                        transpose(&src, &mut dst, n, r0..r1, c0..c1);
                        for (i, v) in dst.iter().enumerate() {
                            let (c, r) = (i / n, i % n);
                            let expect = if (r0..r1).contains(&r) && (c0..c1).contains(&c) {
                                src[r * n + c]
                            } else {
                                c32::new(f32::NAN, 7.0)
                            };
                            assert_eq!(
                                (v.re.to_bits(), v.im.to_bits()),
                                (expect.re.to_bits(), expect.im.to_bits()),
                                "n {n}, rows {r0}..{r1}, cols {c0}..{c1}, dst[{i}]"
                            );
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn the_paper_size_frame_gets_tiles_the_default_job_the_whole_grid() {
        // 1280×800 at 3 µm with the 65-pixel window: 160-pixel tiles on 224² grids, 5 × 8.
        let im = LayeredImager::new(800, 1280, 65).unwrap();
        let t = im.tiling.as_ref().expect("tiled");
        assert_eq!((t.t, t.n, t.rows, t.cols), (160, 224, 5, 8));
        // The default job's 320×200 at 12 µm (17-pixel window): 0.07 M grid points.
        assert!(LayeredImager::new(200, 320, 17).unwrap().tile().is_none());
        // A grid beyond the threshold with a window as wide as the image: a tile's grid
        // would not pay.
        assert!(LayeredImager::new(800, 1280, 801).unwrap().tile().is_none());
    }
}

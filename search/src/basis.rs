//! How the phase map's updates are parametrised: every aperture sample on its own (the
//! supplement's φ_opt), or the Zernike polynomials over the aperture disc up to a radial order.
//!
//! Why a basis: at the default job's size ∂L/∂φ per sample is dominated by the batch's noise,
//! and Adam, which normalises each coordinate's step, turns that noise into a random walk of
//! ripples tens of µm across (docs/run.md, "The phase map's steps at this size"). Steps in a
//! low-order basis average each mode's gradient over the whole disc, and ripples finer than the
//! highest order cannot form. The map itself stays a full phase map: each step adds
//! Σ_j Δc_j Z_j to it, so a run can start from any phase map and checkpoints keep the same
//! format.

use crate::error::{Result, param};
use faer::Mat;
use nanoeye_optics::ApertureGrid;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Highest radial order accepted (231 modes): beyond it the explicit radial sums lose digits
/// and the modes are finer than a per-sample update would give anyway.
pub const MAX_ZERNIKE_ORDER: u32 = 20;

/// The parametrisation of φ's updates. Written `"pixels"` or `"zernike:N"`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(try_from = "String", into = "String")]
pub enum PhaseBasis {
    /// Every aperture sample is a parameter (S22's φ_opt).
    #[default]
    Pixels,
    /// The Zernike modes of radial order 1..=N over the aperture disc (piston, which no PSF
    /// depends on, left out): (N + 1)(N + 2)/2 − 1 parameters.
    Zernike(u32),
}

impl std::str::FromStr for PhaseBasis {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        if s == "pixels" {
            return Ok(PhaseBasis::Pixels);
        }
        let bad = || {
            format!(
                "`{s}` is neither `pixels` nor `zernike:N` with a radial order N in \
                 1..={MAX_ZERNIKE_ORDER}"
            )
        };
        let n = s.strip_prefix("zernike:").ok_or_else(bad)?;
        match n.parse::<u32>() {
            Ok(n) if (1..=MAX_ZERNIKE_ORDER).contains(&n) => Ok(PhaseBasis::Zernike(n)),
            _ => Err(bad()),
        }
    }
}

impl std::fmt::Display for PhaseBasis {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            PhaseBasis::Pixels => write!(f, "pixels"),
            PhaseBasis::Zernike(n) => write!(f, "zernike:{n}"),
        }
    }
}

impl TryFrom<String> for PhaseBasis {
    type Error = String;
    fn try_from(s: String) -> std::result::Result<Self, String> {
        s.parse()
    }
}

impl From<PhaseBasis> for String {
    fn from(b: PhaseBasis) -> String {
        b.to_string()
    }
}

impl PhaseBasis {
    /// Refuses an order outside 1..=[`MAX_ZERNIKE_ORDER`] (a value built in code, not parsed).
    pub fn validate(self) -> Result<()> {
        match self {
            PhaseBasis::Zernike(n) if !(1..=MAX_ZERNIKE_ORDER).contains(&n) => Err(param(
                "phase_basis",
                format!("the Zernike radial order must be 1..={MAX_ZERNIKE_ORDER}, got {n}"),
            )),
            _ => Ok(()),
        }
    }
}

/// One Zernike mode Z_n^m: radial order `n`, azimuthal frequency `m` (cos for m ≥ 0, sin for
/// m < 0), normalised to unit mean square over the unit disc.
#[derive(Clone, Debug)]
struct Mode {
    /// Radial order n.
    n: usize,
    /// |m|.
    am: usize,
    /// Whether the azimuthal factor is sin(|m|θ).
    sine: bool,
    /// Coefficients of the radial polynomial R_n^|m|(ρ)/ρ^|m| in powers of ρ², lowest first,
    /// times the normalisation √((2 − δ_m0)(n + 1)).
    radial: Vec<f64>,
}

/// The Zernike modes of radial order 1..=N on an aperture grid: ρ = r / (D/2), modes zero
/// outside the disc.
#[derive(Clone, Debug)]
pub struct Zernike {
    order: usize,
    modes: Vec<Mode>,
    grid: ApertureGrid,
}

impl Zernike {
    /// The modes of radial order 1..=`order` on `grid`, ordered by n, then m from −n to n.
    pub fn new(order: u32, grid: ApertureGrid) -> Result<Zernike> {
        PhaseBasis::Zernike(order).validate()?;
        let order = order as usize;
        let fact = |k: usize| (1..=k).map(|i| i as f64).product::<f64>();
        let mut modes = Vec::new();
        for n in 1..=order {
            for m in (-(n as isize)..=n as isize).step_by(2) {
                let am = m.unsigned_abs();
                let half = (n - am) / 2;
                let norm = (if am == 0 { 1.0 } else { 2.0 } * (n as f64 + 1.0)).sqrt();
                // R_n^m(ρ) = Σ_k (−1)^k (n−k)! / (k! ((n+m)/2−k)! ((n−m)/2−k)!) ρ^(n−2k);
                // divided by ρ^m, the power of ρ² is half − k.
                let mut radial = vec![0.0; half + 1];
                for k in 0..=half {
                    let a = fact(n - k) / (fact(k) * fact((n + am) / 2 - k) * fact(half - k));
                    radial[half - k] = if k % 2 == 0 { a } else { -a } * norm;
                }
                modes.push(Mode {
                    n,
                    am,
                    sine: m < 0,
                    radial,
                });
            }
        }
        Ok(Zernike { order, modes, grid })
    }

    /// Number of modes (parameters).
    pub fn len(&self) -> usize {
        self.modes.len()
    }

    /// (n, m) of mode `j` (m < 0: the sin(|m|θ) mode), in the order of the coefficients.
    pub fn index(&self, j: usize) -> (usize, isize) {
        let md = &self.modes[j];
        let am = md.am as isize;
        (md.n, if md.sine { -am } else { am })
    }

    /// Whether there are no modes (never: order ≥ 1 gives tip and tilt).
    pub fn is_empty(&self) -> bool {
        self.modes.is_empty()
    }

    /// Every mode's value at sample (row `i`, column `j`) into `out` (zeros outside the disc);
    /// `pw` is scratch for the powers (u + iv)^k.
    fn values(&self, i: usize, j: usize, out: &mut [f64], pw: &mut [(f64, f64)]) {
        let r = 0.5 * self.grid.diameter_m;
        let (u, v) = (self.grid.coord(j) / r, self.grid.coord(i) / r);
        let s = u * u + v * v;
        if s > 1.0 {
            out.fill(0.0);
            return;
        }
        // ρ^m e^{imθ} = (u + iv)^m: the azimuthal factors without trigonometry.
        pw[0] = (1.0, 0.0);
        for k in 1..=self.order {
            let (a, b) = pw[k - 1];
            pw[k] = (a * u - b * v, a * v + b * u);
        }
        for (o, md) in out.iter_mut().zip(&self.modes) {
            let p = md.radial.iter().rev().fold(0.0, |acc, &c| acc * s + c);
            let (re, im) = pw[md.am];
            *o = p * if md.sine { im } else { re };
        }
    }

    /// ∂L/∂c_j = Σ_x g(x) Z_j(x) for ∂L/∂φ = `g` on the grid, for φ = φ₀ + Σ_j c_j Z_j.
    /// Rows are summed in order, so the result does not depend on the thread count.
    pub fn project(&self, g: &Mat<f64>) -> Vec<f64> {
        let (n, m) = (self.grid.n, self.len());
        let rows: Vec<Vec<f64>> = (0..n)
            .into_par_iter()
            .map(|i| {
                let (mut acc, mut z) = (vec![0.0; m], vec![0.0; m]);
                let mut pw = vec![(0.0, 0.0); self.order + 1];
                for j in 0..n {
                    let gv = g[(i, j)];
                    if gv == 0.0 {
                        continue;
                    }
                    self.values(i, j, &mut z, &mut pw);
                    for (a, &zv) in acc.iter_mut().zip(&z) {
                        *a += gv * zv;
                    }
                }
                acc
            })
            .collect();
        rows.iter().fold(vec![0.0; m], |mut t, r| {
            t.iter_mut().zip(r).for_each(|(t, r)| *t += r);
            t
        })
    }

    /// φ += Σ_j c_j Z_j over the grid; returns Σ_x (Σ_j c_j Z_j(x))², the squared change.
    pub fn add_to(&self, c: &[f64], phi: &mut Mat<f64>) -> f64 {
        let (n, m) = (self.grid.n, self.len());
        assert_eq!(c.len(), m, "one coefficient per mode");
        let deltas: Vec<Vec<f64>> = (0..n)
            .into_par_iter()
            .map(|i| {
                let mut z = vec![0.0; m];
                let mut pw = vec![(0.0, 0.0); self.order + 1];
                (0..n)
                    .map(|j| {
                        self.values(i, j, &mut z, &mut pw);
                        z.iter().zip(c).map(|(z, c)| z * c).sum::<f64>()
                    })
                    .collect()
            })
            .collect();
        let mut ss = 0.0;
        for (i, row) in deltas.iter().enumerate() {
            for (j, &d) in row.iter().enumerate() {
                phi[(i, j)] += d;
                ss += d * d;
            }
        }
        ss
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid(n: usize) -> ApertureGrid {
        ApertureGrid::new(1e-3, 1e-3 / n as f64).unwrap()
    }

    fn mode(z: &Zernike, k: usize) -> Mat<f64> {
        let mut c = vec![0.0; z.len()];
        c[k] = 1.0;
        let mut phi = Mat::zeros(z.grid.n, z.grid.n);
        z.add_to(&c, &mut phi);
        phi
    }

    #[test]
    fn text_round_trips_and_bad_text_is_refused() {
        for b in [
            PhaseBasis::Pixels,
            PhaseBasis::Zernike(1),
            PhaseBasis::Zernike(8),
            PhaseBasis::Zernike(MAX_ZERNIKE_ORDER),
        ] {
            assert_eq!(b.to_string().parse::<PhaseBasis>(), Ok(b));
            let j = serde_json::to_string(&b).unwrap();
            assert_eq!(serde_json::from_str::<PhaseBasis>(&j).unwrap(), b);
        }
        assert_eq!(
            serde_json::to_string(&PhaseBasis::Zernike(6)).unwrap(),
            "\"zernike:6\""
        );
        for bad in [
            "",
            "pixel",
            "zernike",
            "zernike:",
            "zernike:0",
            "zernike:-1",
            "zernike:21",
            "zernike:1.5",
            "zernike:nan",
            "Zernike:4",
            "zernike:99999999999",
        ] {
            let e = bad.parse::<PhaseBasis>().unwrap_err();
            assert!(
                e.contains("pixels") && e.contains("zernike:N"),
                "{bad}: {e}"
            );
        }
        assert!(serde_json::from_str::<PhaseBasis>("4").is_err());
        assert!(PhaseBasis::Zernike(0).validate().is_err());
        assert!(Zernike::new(21, grid(8)).is_err());
    }

    #[test]
    fn the_modes_are_counted_and_the_low_ones_have_their_closed_forms() {
        let g = grid(64);
        for n in 1..=10u32 {
            let z = Zernike::new(n, g).unwrap();
            assert_eq!(z.len(), ((n + 1) * (n + 2) / 2 - 1) as usize);
        }
        // Order 2: Z(1,−1) = 2v, Z(1,1) = 2u, Z(2,−2) = 2√6 uv, Z(2,0) = √3 (2ρ² − 1),
        // Z(2,2) = √6 (u² − v²).
        let z = Zernike::new(2, g).unwrap();
        let (mut out, mut pw) = (vec![0.0; 5], vec![(0.0, 0.0); 3]);
        let (i, j) = (20, 41);
        z.values(i, j, &mut out, &mut pw);
        let r = 0.5 * g.diameter_m;
        let (u, v) = (g.coord(j) / r, g.coord(i) / r);
        let s = u * u + v * v;
        assert!(s < 1.0);
        let want = [
            2.0 * v,
            2.0 * u,
            2.0 * 6f64.sqrt() * u * v,
            3f64.sqrt() * (2.0 * s - 1.0),
            6f64.sqrt() * (u * u - v * v),
        ];
        for (a, b) in out.iter().zip(want) {
            assert!((a - b).abs() < 1e-12, "{out:?} against {want:?}");
        }
        assert_eq!(
            (0..5).map(|j| z.index(j)).collect::<Vec<_>>(),
            [(1, -1), (1, 1), (2, -2), (2, 0), (2, 2)]
        );
        // Outside the disc: zero.
        z.values(0, 0, &mut out, &mut pw);
        assert!(out.iter().all(|&x| x == 0.0));
    }

    #[test]
    fn the_modes_are_orthonormal_over_the_disc() {
        // Sampled on 200² points the disc's mean of Z_i Z_j is δ_ij up to the rim's
        // discretisation (O(1/n) of the highest order's mean square).
        let g = grid(200);
        let z = Zernike::new(6, g).unwrap();
        let modes: Vec<Mat<f64>> = (0..z.len()).map(|k| mode(&z, k)).collect();
        let inside = (0..g.n)
            .flat_map(|i| (0..g.n).map(move |j| (i, j)))
            .filter(|&(i, j)| {
                let r = 0.5 * g.diameter_m;
                g.coord(i).hypot(g.coord(j)) <= r
            })
            .count() as f64;
        for a in 0..z.len() {
            for b in 0..=a {
                let dot = (0..g.n)
                    .flat_map(|i| (0..g.n).map(move |j| (i, j)))
                    .map(|(i, j)| modes[a][(i, j)] * modes[b][(i, j)])
                    .sum::<f64>()
                    / inside;
                let want = if a == b { 1.0 } else { 0.0 };
                assert!((dot - want).abs() < 0.03, "modes {a}, {b}: {dot}");
            }
        }
    }

    #[test]
    fn the_projection_is_the_adjoint_of_the_synthesis() {
        // ⟨g, Σ c_j Z_j⟩ = ⟨project(g), c⟩: the gradient in the coefficients is the chain rule
        // of φ = φ₀ + Σ c_j Z_j, whatever g is.
        let g = grid(37);
        let z = Zernike::new(5, g).unwrap();
        let gm = Mat::from_fn(g.n, g.n, |i, j| ((i * 31 + j * 17) % 23) as f64 - 11.0);
        let c: Vec<f64> = (0..z.len()).map(|k| ((k * 7) % 5) as f64 - 2.0).collect();
        let mut phi = Mat::zeros(g.n, g.n);
        let ss = z.add_to(&c, &mut phi);
        let lhs: f64 = (0..g.n)
            .flat_map(|i| (0..g.n).map(move |j| (i, j)))
            .map(|(i, j)| gm[(i, j)] * phi[(i, j)])
            .sum();
        let rhs: f64 = z.project(&gm).iter().zip(&c).map(|(a, b)| a * b).sum();
        assert!(
            (lhs - rhs).abs() <= 1e-10 * lhs.abs().max(1.0),
            "{lhs} {rhs}"
        );
        let sq: f64 = (0..g.n)
            .flat_map(|i| (0..g.n).map(move |j| (i, j)))
            .map(|(i, j)| phi[(i, j)].powi(2))
            .sum();
        assert!((ss - sq).abs() <= 1e-12 * sq, "{ss} {sq}");
        // The same on one thread: rows are summed in order.
        let one = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap();
        assert_eq!(one.install(|| z.project(&gm)), z.project(&gm));
    }
}

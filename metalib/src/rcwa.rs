//! RCWA (Fourier modal method) for a square lattice of cylindrical pillars at normal incidence.
//!
//! Conventions (see docs/metalib.md): time dependence e^{-iωt}; x-polarised plane wave incident
//! from the superstrate (z < 0) onto the layer 0 ≤ z ≤ h; `t` = E_x of the zero transmitted order
//! at z = h⁺ divided by E_x of the incident wave at z = 0⁻. Fields are expanded in the
//! mirror-symmetric subspace that x-polarised normal incidence excites (E_x even/even,
//! E_y odd/odd in (x, y)), which shrinks the eigenproblem about fourfold. One eigen-decomposition
//! per (λ, s, d, materials) is reused for every height ([`LayerModes::at_height`]).

use crate::error::MetalibError;
use crate::material::Materials;
use faer::linalg::solvers::{DenseSolveCore, Solve};
use faer::{Col, Mat, c64};
use num_complex::Complex64;
use std::f64::consts::PI;

/// Fourier factorisation rule for the permittivity products.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Rule {
    /// Plain Laurent rule (Toeplitz of ε everywhere).
    Laurent,
    /// Normal-vector method (Li's inverse rule for the normal component) with the circle's
    /// radial normal field.
    Nv,
}

impl Rule {
    /// Lowercase name as used on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Rule::Laurent => "laurent",
            Rule::Nv => "nv",
        }
    }
}

impl std::str::FromStr for Rule {
    type Err = MetalibError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "laurent" => Ok(Rule::Laurent),
            "nv" | "normal-vector" | "li" => Ok(Rule::Nv),
            other => Err(MetalibError::param(
                "rule",
                format!("unknown rule `{other}` (laurent|nv)"),
            )),
        }
    }
}

/// Default factorisation rule (chosen from the convergence study in docs/metalib.md).
pub const DEFAULT_RULE: Rule = Rule::Nv;
/// Default truncation: Fourier orders −N..N in x and y (chosen from the convergence study).
pub const DEFAULT_HARMONICS: usize = 10;
/// Largest accepted truncation order (the dense eigenproblem grows as N⁶).
pub const MAX_HARMONICS: usize = 40;
/// Slack on energy conservation (R, T ∈ [0, 1], R + T ≤ 1) before a solve counts as failed.
pub const ENERGY_TOLERANCE: f64 = 0.05;
/// Wavelengths (m) the solver accepts: near-UV to far-IR. Far outside, the optical constants
/// are meaningless and the eigenproblem ill-conditioned (1 km gave R = −98304).
pub const WAVELENGTH_RANGE_M: (f64, f64) = (1e-7, 1e-4);
/// Largest pitch / wavelength ratio: beyond it the retained orders cannot resolve the
/// propagating ones (1e-3 nm at a 530 nm pitch gave R = 4.9e6).
pub const MAX_PITCH_PER_WAVELENGTH: f64 = 20.0;
/// Smallest pitch / wavelength ratio: a pitch of 1e-300 nm made the grating vector overflow
/// (a non-finite response); a thousandth of a wavelength is far inside the effective-medium
/// regime, where every metasurface pillar is larger.
pub const MIN_PITCH_PER_WAVELENGTH: f64 = 1e-3;
/// Modes whose one-way amplitude factor |e^{iγk₀h}| is below this are dropped from the
/// height-dependent multiple-reflection solve of [`LayerModes::at_height`] (their contribution
/// is below this size; R + T = 1 holds to ~1e-12 for lossless pillars).
const EVANESCENT_CUTOFF: f64 = 1e-12;
/// The same cut-off for the sweep's fast path [`LayerModes::transmission_at`]. Measured on the
/// s = 530 nm sweep slice against 1e-12: |Δt| ≤ 4.2e-7, |Δφ| ≤ 4.5e-6 rad, three orders below
/// the N = 10 truncation error, for 1.5× fewer seconds (docs/bench/metalib.md).
const SWEEP_CUTOFF: f64 = 1e-6;
/// Largest error of the probe x ↦ W⁻¹Wx (and V⁻¹Vx) for which the transpose-symmetry
/// inverses are used; above it (near-degenerate modes) the LU path is taken. Probe errors of
/// 1e-8–1e-7 occur for nearly degenerate modes at large pitch; they perturb the interface
/// matrices at that relative level, below the sweep fast path's 1e-6 cut-off.
const SYMMETRY_PROBE_TOL: f64 = 1e-6;
/// Smallest |γ| admitted: a Rayleigh anomaly (grazing order) is shifted off the branch point.
const GAMMA_FLOOR: f64 = 1e-9;

/// Geometry and materials of one unit cell (without the height, which is free).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CellSpec {
    /// Wavelength (m).
    pub wavelength_m: f64,
    /// Square-lattice pitch (m).
    pub pitch_m: f64,
    /// Pillar diameter (m), 0 ≤ d ≤ pitch.
    pub diameter_m: f64,
    /// Optical constants.
    pub materials: Materials,
    /// Truncation order N (orders −N..N per direction).
    pub harmonics: usize,
    /// Factorisation rule.
    pub rule: Rule,
}

impl CellSpec {
    /// Validates every field; errors name the offending one.
    pub fn validate(&self) -> Result<(), MetalibError> {
        if !(self.wavelength_m.is_finite() && self.wavelength_m > 0.0) {
            return Err(MetalibError::param("wavelength", "must be finite and > 0"));
        }
        let (lo, hi) = WAVELENGTH_RANGE_M;
        if !(lo..=hi).contains(&self.wavelength_m) {
            return Err(MetalibError::param(
                "wavelength",
                format!(
                    "{} m lies outside the supported range [{lo:e}, {hi:e}] m",
                    self.wavelength_m
                ),
            ));
        }
        if !(self.pitch_m.is_finite() && self.pitch_m > 0.0) {
            return Err(MetalibError::param("pitch", "must be finite and > 0"));
        }
        if self.pitch_m < MIN_PITCH_PER_WAVELENGTH * self.wavelength_m {
            return Err(MetalibError::param(
                "pitch",
                format!(
                    "pitch {} m is below {MIN_PITCH_PER_WAVELENGTH} wavelengths ({} m)",
                    self.pitch_m, self.wavelength_m
                ),
            ));
        }
        if self.pitch_m > MAX_PITCH_PER_WAVELENGTH * self.wavelength_m {
            return Err(MetalibError::param(
                "pitch",
                format!(
                    "pitch {} m exceeds {MAX_PITCH_PER_WAVELENGTH} wavelengths ({} m)",
                    self.pitch_m, self.wavelength_m
                ),
            ));
        }
        if !(self.diameter_m.is_finite() && self.diameter_m >= 0.0) {
            return Err(MetalibError::param("diameter", "must be finite and >= 0"));
        }
        if self.diameter_m > self.pitch_m * (1.0 + 1e-12) {
            return Err(MetalibError::param(
                "diameter",
                format!(
                    "diameter {} m exceeds the pitch {} m",
                    self.diameter_m, self.pitch_m
                ),
            ));
        }
        if self.harmonics > MAX_HARMONICS {
            return Err(MetalibError::param(
                "harmonics",
                format!("must be <= {MAX_HARMONICS}"),
            ));
        }
        self.materials.validate()
    }
}

/// Result of one cell at one height.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CellResult {
    /// Complex zero-order co-polarised transmission coefficient (E_x out / E_x in).
    pub t: Complex64,
    /// Zero-order power transmittance τ = Re(γ_sub,0)/γ_sup,0 · |t|².
    pub transmittance: f64,
    /// Total reflected power over all propagating orders (normalised to the incident flux).
    pub reflectance: f64,
    /// Total transmitted power over all propagating orders.
    pub transmitted_total: f64,
    /// arg t (rad) in (−π, π].
    pub phase_rad: f64,
}

/// Fourier orders of one mirror-parity subspace: representatives (m, n) with m, n ≥ 0
/// (≥ 1 in an odd direction).
#[derive(Debug, Clone)]
struct Parity {
    odd_x: bool,
    odd_y: bool,
    reps: Vec<(i32, i32)>,
    /// index[(m)*(N+1)+n] = position of rep (m,n) in `reps`.
    index: Vec<Option<usize>>,
}

impl Parity {
    fn new(n: usize, odd_x: bool, odd_y: bool) -> Self {
        let n = n as i32;
        let mut reps = Vec::new();
        let mut index = vec![None; ((n + 1) * (n + 1)) as usize];
        for m in i32::from(odd_x)..=n {
            for k in i32::from(odd_y)..=n {
                index[(m * (n + 1) + k) as usize] = Some(reps.len());
                reps.push((m, k));
            }
        }
        Self {
            odd_x,
            odd_y,
            reps,
            index,
        }
    }

    fn len(&self) -> usize {
        self.reps.len()
    }

    fn find(&self, n: usize, m: i32, k: i32) -> Option<usize> {
        if m < 0 || k < 0 {
            return None;
        }
        self.index[m as usize * (n + 1) + k as usize]
    }

    /// Orbit members of a representative with their parity signs.
    fn orbit(&self, (m, k): (i32, i32), out: &mut Vec<(i32, i32, f64)>) {
        out.clear();
        let sx: &[i32] = if m > 0 { &[1, -1] } else { &[1] };
        let sy: &[i32] = if k > 0 { &[1, -1] } else { &[1] };
        for &a in sx {
            for &b in sy {
                let mut sign = 1.0;
                if self.odd_x && a < 0 {
                    sign = -sign;
                }
                if self.odd_y && b < 0 {
                    sign = -sign;
                }
                out.push((a * m, b * k, sign));
            }
        }
    }

    /// Number of full Fourier orders a representative stands for.
    fn multiplicity(&self, i: usize) -> f64 {
        let (m, k) = self.reps[i];
        (if m > 0 { 2.0 } else { 1.0 }) * (if k > 0 { 2.0 } else { 1.0 })
    }
}

/// Fourier-coefficient table over differences (dm, dn) ∈ [−2N, 2N]².
struct Table {
    n2: i32,
    v: Vec<Complex64>,
}

impl Table {
    fn new(n: usize, f: impl Fn(i32, i32) -> Complex64) -> Self {
        let n2 = 2 * n as i32;
        let w = (2 * n2 + 1) as usize;
        let mut v = Vec::with_capacity(w * w);
        for a in -n2..=n2 {
            for b in -n2..=n2 {
                v.push(f(a, b));
            }
        }
        Self { n2, v }
    }
    fn get(&self, a: i32, b: i32) -> Complex64 {
        let w = 2 * self.n2 + 1;
        self.v[((a + self.n2) * w + (b + self.n2)) as usize]
    }
}

/// Reduced Toeplitz operator from subspace `pin` to `pout`: A[i,j] = Σ_orbit f(G_i − G_k)·sign_k.
fn toeplitz(t: &Table, pin: &Parity, pout: &Parity, orbit: &mut Vec<(i32, i32, f64)>) -> Mat<c64> {
    let mut a = Mat::<c64>::zeros(pout.len(), pin.len());
    for (j, &rep) in pin.reps.iter().enumerate() {
        pin.orbit(rep, orbit);
        for (i, &(mi, ni)) in pout.reps.iter().enumerate() {
            let mut s = Complex64::new(0.0, 0.0);
            for &(mk, nk, sg) in orbit.iter() {
                s += t.get(mi - mk, ni - nk) * sg;
            }
            a[(i, j)] = s;
        }
    }
    a
}

/// 2 J1(x)/x, continuous at 0.
fn jinc(x: f64) -> f64 {
    if x.abs() < 1e-8 {
        1.0 - x * x / 8.0
    } else {
        2.0 * libm::j1(x) / x
    }
}

/// (1/s²)∫_{r<ρ} cos2θ e^{−iG·r} dA without the angular factor: −2π(2 − 2J0(Gρ) − GρJ1(Gρ))/(G²s²).
fn radial_j2_integral(g: f64, rho: f64, s: f64) -> f64 {
    let a = g * rho;
    let core = if a < 1e-3 {
        a.powi(4) / 32.0 - a.powi(6) / 576.0
    } else {
        2.0 - 2.0 * libm::j0(a) - a * libm::j1(a)
    };
    -2.0 * PI * core / (g * g * s * s)
}

fn csqrt_branch(z: Complex64) -> Complex64 {
    let mut g = z.sqrt();
    // Forward modes: Im γ > 0 (decaying) or, when lossless-propagating, Re γ > 0.
    if g.im < -1e-12 * g.norm() || (g.im.abs() <= 1e-12 * g.norm() && g.re < 0.0) {
        g = -g;
    }
    if g.norm() < GAMMA_FLOOR {
        g = Complex64::new(0.0, GAMMA_FLOOR);
    }
    g
}

/// Eigen-solution of one layer plus the height-independent interface matrices.
#[derive(Debug, Clone)]
pub struct LayerModes {
    spec: CellSpec,
    /// k₀ = 2π/λ (1/m).
    k0: f64,
    /// Layer propagation constants γ (normalised by k₀), one per reduced mode.
    gamma: Vec<Complex64>,
    /// C1·e₀: downward mode amplitudes excited at z = 0 by the unit incident wave.
    c1e0: Vec<Complex64>,
    /// A1·e₀: direct reflection at z = 0.
    a1e0: Vec<Complex64>,
    /// D1 = (W⁻¹ − U)(W⁻¹ + U)⁻¹: reflection of upward modes back down at z = 0.
    d1: Mat<c64>,
    /// R2: reflection of downward modes back up at z = h.
    r2: Mat<c64>,
    /// Row 0 of T2 = 2(W⁻¹ + V⁻¹V_sub)⁻¹ (transmission of downward modes into the zero
    /// substrate order), the only row the sweep's fast path needs.
    t2_row0: Vec<Complex64>,
    /// LU of W⁻¹ + V⁻¹V_sub, for the full transmitted field T2 u = 2(W⁻¹ + V⁻¹V_sub)⁻¹u.
    ss_lu: faer::linalg::solvers::PartialPivLu<c64>,
    /// LU of S = W⁻¹ + U (for the reflected field B1 = 2S⁻¹).
    s_lu: faer::linalg::solvers::PartialPivLu<c64>,
    /// Superstrate and substrate admittance-like matrices V (reduced basis) for flux sums.
    v_sup: Mat<c64>,
    v_sub: Mat<c64>,
    /// Multiplicity of each reduced component in [Ex(ee); Ey(oo)] order.
    mult: Vec<f64>,
    n1: usize,
    /// Whether W⁻¹ and V⁻¹ came from the transpose symmetry (else from LU factorizations).
    symmetric: bool,
    gamma_sup0: f64,
    gamma_sub0: Complex64,
}

struct Bases {
    ee: Parity,
    oo: Parity,
    oe: Parity,
}

/// Homogeneous-medium Q matrix in the reduced basis (rows [hx(oo); hy(ee)], cols [Ex(ee); Ey(oo)]).
fn q_homogeneous(
    b: &Bases,
    kx: &dyn Fn(i32) -> f64,
    ky: &dyn Fn(i32) -> f64,
    eps: Complex64,
) -> Mat<c64> {
    let (n1, n2) = (b.ee.len(), b.oo.len());
    let mut q = Mat::<c64>::zeros(n1 + n2, n1 + n2);
    // Q11 (oo×ee) = −KxKy; Q22 (ee×oo) = KyKx: entries where the (m, n) representatives coincide.
    for (i, &(m, n)) in b.oo.reps.iter().enumerate() {
        if let Some(j) = b.ee.find(usize_n(b), m, n) {
            let v = Complex64::new(kx(m) * ky(n), 0.0);
            q[(i, j)] = -v;
            q[(n2 + j, n1 + i)] = v;
        }
        q[(i, n1 + i)] = Complex64::new(kx(m) * kx(m), 0.0) - eps;
    }
    for (j, &(_, n)) in b.ee.reps.iter().enumerate() {
        q[(n2 + j, j)] = eps - Complex64::new(ky(n) * ky(n), 0.0);
    }
    q
}

fn usize_n(b: &Bases) -> usize {
    b.ee.reps.last().map_or(0, |r| r.0 as usize)
}

fn lu_solve(lu: &faer::linalg::solvers::PartialPivLu<c64>, rhs: &Mat<c64>) -> Mat<c64> {
    lu.solve(rhs)
}

fn check_finite(m: &Mat<c64>, what: &str) -> Result<(), MetalibError> {
    for j in 0..m.ncols() {
        for i in 0..m.nrows() {
            let v = m[(i, j)];
            if !(v.re.is_finite() && v.im.is_finite()) {
                return Err(MetalibError::Numerical(format!(
                    "non-finite entry in {what}"
                )));
            }
        }
    }
    Ok(())
}

/// W⁻¹, V⁻¹V_sup and V⁻¹V_sub from the transpose symmetry of the mode problem
/// instead of LU factorizations; `None` when the result fails its check (degenerate
/// eigenvalues, where eigenvectors of one eigenvalue need not be biorthogonal).
///
/// With M = diag(multiplicity) every reduced operator A here satisfies Aᵀ M = M A (the full
/// Toeplitz and K matrices are symmetric). Reordering Q's rows to [h_y(ee); h_x(oo)] and
/// negating the h_x rows gives Q_s = SΠQ with Q_sᵀ M = M Q_s, and Ω² = P Q = P̃ Q_s with
/// P̃ = PΠᵀS of the same kind. So M Q_s w_j are left eigenvectors of Ω²:
/// W⁻¹ = D⁻¹ (Q_s W)ᵀ M with D = diag((Q_s W)ᵀ M W), and since V = Q W Γ⁻¹,
/// V⁻¹ = Γ D⁻¹ Wᵀ M S Π. Q W is formed for V anyway, and the homogeneous V_sup, V_sub have at
/// most two non-zeros per column, so this is O(n²) after Q W against 2⅓ n³ for the LU path.
fn symmetric_inverses(
    w: &Mat<c64>,
    qw: &Mat<c64>,
    gamma: &[Complex64],
    mult: &[f64],
    n1: usize,
    v_sup: &Mat<c64>,
    v_sub: &Mat<c64>,
) -> Option<(Mat<c64>, Mat<c64>, Mat<c64>)> {
    let dim = w.nrows();
    let n2 = dim - n1;
    // Row i of S Π: which row r_i of an h-ordered vector [h_x(oo); h_y(ee)] and its sign.
    let rows: Vec<(usize, f64)> = (0..dim)
        .map(|i| {
            if i < n1 {
                (n2 + i, 1.0)
            } else {
                (i - n1, -1.0)
            }
        })
        .collect();
    // Column j of Q W is contiguous, so d_j = Σ_i M_i (S Π Q W)_ij W_ij runs down columns.
    let mut dinv = vec![Complex64::new(0.0, 0.0); dim];
    for (j, di) in dinv.iter_mut().enumerate() {
        let mut dj = Complex64::new(0.0, 0.0);
        for (i, &(r, sg)) in rows.iter().enumerate() {
            dj += qw[(r, j)] * w[(i, j)] * (sg * mult[i]);
        }
        if !(dj.norm() > 0.0 && dj.re.is_finite() && dj.im.is_finite()) {
            return None;
        }
        *di = dj.inv();
    }
    // W⁻¹[j, i] = M_i (S Π Q W)_ij / d_j: column i of W⁻¹ is row r_i of Q W, i.e. column r_i of
    // (Q W)ᵀ.
    let qwt = qw.transpose().to_owned();
    let wi = Mat::<c64>::from_fn(dim, dim, |j, i| {
        let (r, sg) = rows[i];
        qwt[(j, r)] * dinv[j] * (sg * mult[i])
    });
    // Probe W⁻¹ W x = x and V⁻¹ V x = x with one fixed, generic x: O(n²). Where eigenvalues
    // (nearly) coincide, the solver's eigenvectors of one eigenvalue need not be biorthogonal
    // and the probe fails.
    let x = Col::<c64>::from_fn(dim, |i| c64::from_polar(1.0, 0.7 + 1.3 * i as f64));
    let gd: Vec<Complex64> = gamma.iter().zip(&dinv).map(|(g, di)| g * di).collect();
    let back = &wi * (w * &x);
    // V⁻¹ V x = Γ D⁻¹ Wᵀ M S Π (Q W Γ⁻¹ x).
    let vx = qw * Col::<c64>::from_fn(dim, |i| x[i] / gamma[i]);
    let msz = Col::<c64>::from_fn(dim, |i| {
        let (r, sg) = rows[i];
        vx[r] * (sg * mult[i])
    });
    let wtz = w.transpose() * &msz;
    let back_v = Col::<c64>::from_fn(dim, |j| wtz[j] * gd[j]);
    let err = |b: &Col<c64>| (0..dim).map(|i| (b[i] - x[i]).norm()).fold(0.0, f64::max);
    if !(err(&back) < SYMMETRY_PROBE_TOL && err(&back_v) < SYMMETRY_PROBE_TOL) {
        return None;
    }
    // V⁻¹ B = Γ D⁻¹ Wᵀ (M S Π B); M S Π B has a few non-zeros per column, and column i of Wᵀ
    // is row i of W.
    let wt = w.transpose().to_owned();
    let apply = |blk: &Mat<c64>| {
        let mut u = Mat::<c64>::zeros(dim, dim);
        for c in 0..dim {
            for (i, &(r, sg)) in rows.iter().enumerate() {
                let m = blk[(r, c)];
                if m == Complex64::new(0.0, 0.0) {
                    continue;
                }
                let m = m * (sg * mult[i]);
                for j in 0..dim {
                    u[(j, c)] += wt[(j, i)] * m;
                }
            }
            for j in 0..dim {
                u[(j, c)] *= gd[j];
            }
        }
        u
    };
    Some((wi, apply(v_sup), apply(v_sub)))
}

impl LayerModes {
    /// Solves the layer eigenproblem and the two interfaces for `spec` (all heights at once).
    pub fn new(spec: &CellSpec) -> Result<Self, MetalibError> {
        Self::build(spec, true)
    }

    /// [`Self::new`]; `use_symmetry` = false forces the LU path for W⁻¹ and V⁻¹ (tests).
    fn build(spec: &CellSpec, use_symmetry: bool) -> Result<Self, MetalibError> {
        spec.validate()?;
        let n = spec.harmonics;
        let s = spec.pitch_m;
        let lam = spec.wavelength_m;
        let k0 = 2.0 * PI / lam;
        let b = Bases {
            ee: Parity::new(n, false, false),
            oo: Parity::new(n, true, true),
            oe: Parity::new(n, true, false),
        };
        let (n1, n2) = (b.ee.len(), b.oo.len());
        let dim = n1 + n2;
        let kx = |m: i32| m as f64 * lam / s;
        let ky = kx;

        let mat = &spec.materials;
        let (ep, eb) = (mat.eps_pillar(), mat.eps_background());
        let r = 0.5 * spec.diameter_m;
        let fill = PI * r * r / (s * s);
        let gnorm = |a: i32, c: i32| 2.0 * PI * ((a * a + c * c) as f64).sqrt() / s;
        let eps_t = Table::new(n, |a, c| {
            let v = (ep - eb) * fill * jinc(gnorm(a, c) * r);
            if a == 0 && c == 0 { v + eb } else { v }
        });
        let mut orbit = Vec::with_capacity(4);
        let e_oe = toeplitz(&eps_t, &b.oe, &b.oe, &mut orbit);
        let e_ee = toeplitz(&eps_t, &b.ee, &b.ee, &mut orbit);
        let e_oo = toeplitz(&eps_t, &b.oo, &b.oo, &mut orbit);
        let ei = e_oe.partial_piv_lu().inverse();
        check_finite(&ei, "inverse permittivity matrix")?;

        // P (rows [Ex(ee); Ey(oo)], cols [hx(oo); hy(ee)]).
        let mut p = Mat::<c64>::zeros(dim, dim);
        // Gather Kx·Ei·Ky etc.: Ky maps oo→oe and ee→eo… but Ei lives on oe, so only the
        // products through oe appear (Ez is odd in x, even in y).
        let oe_of = |m: i32, c: i32| b.oe.find(n, m, c);
        for (i, &(mi, ni)) in b.ee.reps.iter().enumerate() {
            let ri = oe_of(mi, ni);
            // P11: Kx Ei Ky (ee×oo)
            for (j, &(mj, nj)) in b.oo.reps.iter().enumerate() {
                if let (Some(ri), Some(cj)) = (ri, oe_of(mj, nj)) {
                    p[(i, j)] = ei[(ri, cj)] * (kx(mi) * ky(nj));
                }
            }
            // P12: I − Kx Ei Kx (ee×ee)
            for (j, &(mj, nj)) in b.ee.reps.iter().enumerate() {
                let mut v = if i == j {
                    Complex64::new(1.0, 0.0)
                } else {
                    Complex64::new(0.0, 0.0)
                };
                if let (Some(ri), Some(cj)) = (ri, oe_of(mj, nj)) {
                    v -= ei[(ri, cj)] * (kx(mi) * kx(mj));
                }
                p[(i, n2 + j)] = v;
            }
        }
        for (i, &(mi, ni)) in b.oo.reps.iter().enumerate() {
            let ri = oe_of(mi, ni);
            // P21: Ky Ei Ky − I (oo×oo)
            for (j, &(mj, nj)) in b.oo.reps.iter().enumerate() {
                let mut v = if i == j {
                    Complex64::new(-1.0, 0.0)
                } else {
                    Complex64::new(0.0, 0.0)
                };
                if let (Some(ri), Some(cj)) = (ri, oe_of(mj, nj)) {
                    v += ei[(ri, cj)] * (ky(ni) * ky(nj));
                }
                p[(n1 + i, j)] = v;
            }
            // P22: −Ky Ei Kx (oo×ee)
            for (j, &(mj, nj)) in b.ee.reps.iter().enumerate() {
                if let (Some(ri), Some(cj)) = (ri, oe_of(mj, nj)) {
                    p[(n1 + i, n2 + j)] = -ei[(ri, cj)] * (ky(ni) * kx(mj));
                }
            }
        }

        // Q (rows [hx(oo); hy(ee)], cols [Ex(ee); Ey(oo)]): homogeneous part with ε = 0, then
        // the permittivity blocks.
        let mut q = q_homogeneous(&b, &kx, &ky, Complex64::new(0.0, 0.0));
        let (exx, eyy, exy, eyx) = match spec.rule {
            Rule::Laurent => (e_ee, e_oo, None, None),
            Rule::Nv => {
                let inv_t = Table::new(n, |a, c| {
                    let v = (ep.inv() - eb.inv()) * fill * jinc(gnorm(a, c) * r);
                    if a == 0 && c == 0 { v + eb.inv() } else { v }
                });
                let rho = 0.5 * s;
                let cos_t = Table::new(n, |a, c| {
                    if a == 0 && c == 0 {
                        return Complex64::new(0.0, 0.0);
                    }
                    let g2 = (a * a + c * c) as f64;
                    let c2 = (a * a - c * c) as f64 / g2;
                    Complex64::new(c2 * radial_j2_integral(gnorm(a, c), rho, s), 0.0)
                });
                let sin_t = Table::new(n, |a, c| {
                    if a == 0 && c == 0 {
                        return Complex64::new(0.0, 0.0);
                    }
                    let g2 = (a * a + c * c) as f64;
                    let s2 = 2.0 * (a * c) as f64 / g2;
                    Complex64::new(s2 * radial_j2_integral(gnorm(a, c), rho, s), 0.0)
                });
                let delta = |e: &Mat<c64>, p: &Parity, orbit: &mut Vec<(i32, i32, f64)>| {
                    let pinv = toeplitz(&inv_t, p, p, orbit).partial_piv_lu().inverse();
                    e - pinv
                };
                let d_ee = delta(&e_ee, &b.ee, &mut orbit);
                let d_oo = delta(&e_oo, &b.oo, &mut orbit);
                check_finite(&d_ee, "NV Δ matrix")?;
                check_finite(&d_oo, "NV Δ matrix")?;
                let c_ee = toeplitz(&cos_t, &b.ee, &b.ee, &mut orbit);
                let c_oo = toeplitz(&cos_t, &b.oo, &b.oo, &mut orbit);
                let s_oo_ee = toeplitz(&sin_t, &b.ee, &b.oo, &mut orbit);
                let s_ee_oo = toeplitz(&sin_t, &b.oo, &b.ee, &mut orbit);
                let half = c64::new(0.5, 0.0);
                // N_xx = ½(I + C), N_yy = ½(I − C), N_xy = ½S; ε_ij = [[ε]]δ_ij − Δ N_ij.
                let i1 = Mat::<c64>::identity(n1, n1);
                let i2 = Mat::<c64>::identity(n2, n2);
                let nxx = (&i1 + &c_ee) * faer::Scale(half);
                let nyy = (&i2 - &c_oo) * faer::Scale(half);
                // Symmetrised products ½(ΔN + NΔ) keep the truncated tensor Hermitian for a
                // lossless pillar, which makes the truncated problem conserve energy exactly.
                let quarter = c64::new(0.25, 0.0);
                let exx = &e_ee - (&d_ee * &nxx + &nxx * &d_ee) * faer::Scale(half);
                let eyy = &e_oo - (&d_oo * &nyy + &nyy * &d_oo) * faer::Scale(half);
                let exy = (&d_ee * &s_ee_oo + &s_ee_oo * &d_oo) * faer::Scale(-quarter);
                let eyx = (&d_oo * &s_oo_ee + &s_oo_ee * &d_ee) * faer::Scale(-quarter);
                (exx, eyy, Some(exy), Some(eyx))
            }
        };
        // Q11 −= eyx (oo×ee); Q12 −= eyy (oo×oo); Q21 += exx (ee×ee); Q22 += exy (ee×oo).
        for j in 0..n1 {
            for i in 0..n2 {
                if let Some(eyx) = &eyx {
                    q[(i, j)] -= eyx[(i, j)];
                }
            }
            for i in 0..n1 {
                q[(n2 + i, j)] += exx[(i, j)];
            }
        }
        for j in 0..n2 {
            for i in 0..n2 {
                q[(i, n1 + j)] -= eyy[(i, j)];
            }
            if let Some(exy) = &exy {
                for i in 0..n1 {
                    q[(n2 + i, n1 + j)] += exy[(i, j)];
                }
            }
        }

        let omega2 = &p * &q;
        check_finite(&omega2, "PQ")?;
        let evd = omega2
            .eigen()
            .map_err(|e| MetalibError::Numerical(format!("eigen-decomposition failed: {e:?}")))?;
        let w = evd.U().to_owned();
        let gamma: Vec<Complex64> = evd
            .S()
            .column_vector()
            .iter()
            .map(|&l| csqrt_branch(l))
            .collect();
        // V = Q W Γ⁻¹ (γ is floored away from 0, so V is finite iff Q W is); V itself is only
        // formed on the LU path below.
        let qw = &q * &w;
        check_finite(&qw, "mode magnetic-field matrix")?;

        let homogeneous = |eps: Complex64| -> (Mat<c64>, Vec<Complex64>) {
            let qh = q_homogeneous(&b, &kx, &ky, eps);
            let mut g = Vec::with_capacity(dim);
            for &(m, c) in &b.ee.reps {
                g.push(csqrt_branch(eps - kx(m) * kx(m) - ky(c) * ky(c)));
            }
            for &(m, c) in &b.oo.reps {
                g.push(csqrt_branch(eps - kx(m) * kx(m) - ky(c) * ky(c)));
            }
            let mut vh = qh;
            for (j, gj) in g.iter().enumerate() {
                let gi = gj.inv();
                for i in 0..dim {
                    vh[(i, j)] *= gi;
                }
            }
            (vh, g)
        };
        let nsup = mat.n_superstrate;
        let nsub = mat.n_substrate;
        let (v_sup, g_sup) = homogeneous(Complex64::new(nsup * nsup, 0.0));
        let (v_sub, g_sub) = homogeneous(Complex64::new(nsub * nsub, 0.0));

        let mult: Vec<f64> = (0..n1)
            .map(|i| b.ee.multiplicity(i))
            .chain((0..n2).map(|i| b.oo.multiplicity(i)))
            .collect();
        let sym = if use_symmetry {
            symmetric_inverses(&w, &qw, &gamma, &mult, n1, &v_sup, &v_sub)
        } else {
            None
        };
        let symmetric = sym.is_some();
        let (wi, u, us) = match sym {
            Some(inverses) => inverses,
            None => {
                let v = Mat::<c64>::from_fn(dim, dim, |i, j| qw[(i, j)] / gamma[j]);
                let v_lu = v.partial_piv_lu();
                (
                    w.partial_piv_lu().inverse(),
                    lu_solve(&v_lu, &v_sup),
                    lu_solve(&v_lu, &v_sub),
                )
            }
        };
        let s_mat = &wi + &u;
        let dm = &wi - &u;
        let s_lu = s_mat.partial_piv_lu();
        // D1 = Dm S⁻¹ and R2 = (W⁻¹ − Us)(W⁻¹ + Us)⁻¹ by right solves on the LUs: no
        // explicit inverse and no product with it.
        let mut d1 = dm.clone();
        s_lu.rsolve_in_place(d1.as_mut());
        let ss_lu = (&wi + &us).partial_piv_lu();
        let mut r2 = &wi - &us;
        ss_lu.rsolve_in_place(r2.as_mut());
        // Row 0 of 2 Ss⁻¹ is 2 (Ss⁻ᵀ e₀)ᵀ.
        let mut e0 = Mat::<c64>::zeros(dim, 1);
        e0[(0, 0)] = c64::new(2.0, 0.0);
        ss_lu.solve_transpose_in_place(e0.as_mut());
        let t2_row0: Vec<Complex64> = (0..dim).map(|j| e0[(j, 0)]).collect();
        check_finite(&d1, "interface reflection matrix")?;
        check_finite(&r2, "interface reflection matrix")?;
        // Incident e₀ = Ex of order (0,0) = reduced index 0 of ee.
        let dm_e0 = Mat::<c64>::from_fn(dim, 1, |i, _| dm[(i, 0)]);
        let a1 = s_lu.solve(&dm_e0);
        let a1e0: Vec<Complex64> = (0..dim).map(|i| -a1[(i, 0)]).collect();
        // C1 e0 = ½(S e0 + Dm A1 e0).
        let mut c1e0 = vec![Complex64::new(0.0, 0.0); dim];
        for (i, c) in c1e0.iter_mut().enumerate() {
            let mut acc = s_mat[(i, 0)];
            for k in 0..dim {
                acc += dm[(i, k)] * a1e0[k];
            }
            *c = 0.5 * acc;
        }
        Ok(Self {
            spec: *spec,
            k0,
            gamma,
            c1e0,
            a1e0,
            d1,
            r2,
            t2_row0,
            ss_lu,
            s_lu,
            v_sup,
            v_sub,
            mult,
            n1,
            symmetric,
            gamma_sup0: g_sup[0].re,
            gamma_sub0: g_sub[0],
        })
    }

    /// Specification the modes were computed for.
    pub fn spec(&self) -> &CellSpec {
        &self.spec
    }

    /// Whether W⁻¹ and V⁻¹ came from the transpose symmetry of the mode problem (false: the
    /// LU path, taken when near-degenerate modes fail the probe).
    pub fn used_transpose_symmetry(&self) -> bool {
        self.symmetric
    }

    /// Number of reduced modes (size of the eigenproblem).
    pub fn mode_count(&self) -> usize {
        self.gamma.len()
    }

    /// Flux Σ mult·Re(Ex hy* − Ey hx*) of a field given by reduced E amplitudes and V.
    fn flux(&self, e: &[Complex64], v: &Mat<c64>) -> f64 {
        let dim = e.len();
        let n1 = self.n1;
        let n2 = dim - n1;
        let mut total = 0.0;
        for i in 0..dim {
            // h = V e; h rows: [hx(oo) (n2); hy(ee) (n1)].
            let mut h = Complex64::new(0.0, 0.0);
            let row = if i < n1 { n2 + i } else { i - n1 };
            for (k, ek) in e.iter().enumerate() {
                h += v[(row, k)] * ek;
            }
            let term = if i < n1 {
                e[i] * h.conj()
            } else {
                -(e[i] * h.conj())
            };
            total += self.mult[i] * term.re;
        }
        total
    }

    /// Zero-order transmission coefficient t only (the sweep's fast path, modes below
    /// `SWEEP_CUTOFF` dropped: within ~1e-6 of `at_height(h).t`), h ≥ 0 (m).
    pub fn transmission_at(&self, height_m: f64) -> Result<Complex64, MetalibError> {
        if !(height_m.is_finite() && height_m >= 0.0) {
            return Err(MetalibError::param("height", "must be finite and >= 0"));
        }
        let (_, keep, u) = self.downward_amplitudes(height_m, SWEEP_CUTOFF);
        let mut t0 = Complex64::new(0.0, 0.0);
        for (a, &ja) in keep.iter().enumerate() {
            t0 += self.t2_row0[ja] * u[a];
        }
        if !(t0.re.is_finite() && t0.im.is_finite()) {
            return Err(MetalibError::Numerical("non-finite cell response".into()));
        }
        Ok(t0)
    }

    /// Zero-order power transmittance for a transmission coefficient `t` of this cell.
    pub fn transmittance_of(&self, t: Complex64) -> f64 {
        self.gamma_sub0.re / self.gamma_sup0 * t.norm_sqr()
    }

    /// Mode factors X, kept-mode indices and the downward amplitudes u at z = h on them.
    fn downward_amplitudes(
        &self,
        height_m: f64,
        cutoff: f64,
    ) -> (Vec<Complex64>, Vec<usize>, Vec<Complex64>) {
        let kh = self.k0 * height_m;
        let dim = self.gamma.len();
        let x: Vec<Complex64> = self
            .gamma
            .iter()
            .map(|g| (Complex64::i() * g * kh).exp())
            .collect();
        let keep: Vec<usize> = (0..dim).filter(|&j| x[j].norm() > cutoff).collect();
        let k = keep.len();
        // (I − X D1 X R2) u = X C1 e0 on the kept modes.
        let mut u = vec![Complex64::new(0.0, 0.0); k];
        if k > 0 {
            let mut m = Mat::<c64>::zeros(k, k);
            // D1_KK X_K R2_KK
            let mut tmp = Mat::<c64>::zeros(k, k);
            for (a, &ja) in keep.iter().enumerate() {
                let xa = x[ja];
                for (c, &jc) in keep.iter().enumerate() {
                    tmp[(a, c)] = xa * self.r2[(ja, jc)];
                }
            }
            let d1k = Mat::<c64>::from_fn(k, k, |a, c| self.d1[(keep[a], keep[c])]);
            let prod = &d1k * &tmp;
            for a in 0..k {
                let xa = x[keep[a]];
                for c in 0..k {
                    m[(a, c)] = -xa * prod[(a, c)];
                }
                m[(a, a)] += Complex64::new(1.0, 0.0);
            }
            let rhs = Mat::<c64>::from_fn(k, 1, |a, _| x[keep[a]] * self.c1e0[keep[a]]);
            let sol = m.partial_piv_lu().solve(&rhs);
            for (a, ua) in u.iter_mut().enumerate() {
                *ua = sol[(a, 0)];
            }
        }
        (x, keep, u)
    }

    /// Response at height `height_m` (m), h ≥ 0.
    pub fn at_height(&self, height_m: f64) -> Result<CellResult, MetalibError> {
        if !(height_m.is_finite() && height_m >= 0.0) {
            return Err(MetalibError::param("height", "must be finite and >= 0"));
        }
        let dim = self.gamma.len();
        let (x, keep, u) = self.downward_amplitudes(height_m, EVANESCENT_CUTOFF);
        // Transmitted reduced amplitudes t = T2_{:,K} u = 2 Ss⁻¹ (u on K, 0 elsewhere).
        let mut tm = Mat::<c64>::zeros(dim, 1);
        for (a, &ja) in keep.iter().enumerate() {
            tm[(ja, 0)] = 2.0 * u[a];
        }
        self.ss_lu.solve_in_place(tm.as_mut());
        let t_vec: Vec<Complex64> = (0..dim).map(|i| tm[(i, 0)]).collect();
        // Reflected r = A1 e0 + 2 S⁻¹ X R2 u.
        let mut y = Mat::<c64>::zeros(dim, 1);
        for i in 0..dim {
            let mut acc = Complex64::new(0.0, 0.0);
            for (a, &ja) in keep.iter().enumerate() {
                acc += self.r2[(i, ja)] * u[a];
            }
            y[(i, 0)] = 2.0 * x[i] * acc;
        }
        let y = self.s_lu.solve(&y);
        let r_vec: Vec<Complex64> = (0..dim).map(|i| self.a1e0[i] + y[(i, 0)]).collect();
        let inc = self.gamma_sup0;
        let t0 = t_vec[0];
        let res = CellResult {
            t: t0,
            transmittance: self.gamma_sub0.re / inc * t0.norm_sqr(),
            reflectance: self.flux(&r_vec, &self.v_sup) / inc,
            transmitted_total: self.flux(&t_vec, &self.v_sub) / inc,
            phase_rad: t0.arg(),
        };
        if !(res.t.re.is_finite() && res.t.im.is_finite() && res.reflectance.is_finite()) {
            return Err(MetalibError::Numerical("non-finite cell response".into()));
        }
        // Passive structure: powers lie in [0, 1] and R + T ≤ 1. A gross violation means the
        // modal solution broke down numerically (e.g. a wavelength far from the pitch scale);
        // such a cell is a failure, not a result.
        let tol = ENERGY_TOLERANCE;
        let (r, t) = (res.reflectance, res.transmitted_total);
        if !(r >= -tol && t >= -tol && res.transmittance >= -tol && r + t <= 1.0 + tol) {
            return Err(MetalibError::Numerical(format!(
                "energy conservation violated (R = {r}, T = {t}): the solution is numerically \
                 unreliable for this wavelength, pitch and harmonic count"
            )));
        }
        Ok(res)
    }
}

/// Convenience: solves one cell at one height.
pub fn solve_cell(spec: &CellSpec, height_m: f64) -> Result<CellResult, MetalibError> {
    LayerModes::new(spec)?.at_height(height_m)
}

#[cfg(test)]
mod tests {

    #[test]
    fn wavelengths_outside_the_safe_range_are_refused() {
        for (wl, pitch) in [(1e3, 530e-9), (1e-12, 530e-9), (100e-9, 3e-6)] {
            let spec = CellSpec {
                wavelength_m: wl,
                pitch_m: pitch,
                diameter_m: 0.4 * pitch,
                materials: Materials::default(),
                harmonics: 2,
                rule: DEFAULT_RULE,
            };
            assert!(spec.validate().is_err(), "{wl} {pitch}");
        }
    }
    use super::*;
    use crate::material::Materials;

    /// The transpose-symmetry inverses give the same cell responses as the LU path, for both
    /// rules, lossy and lossless pillars, several fills and pitches, short and tall pillars;
    /// and a homogeneous layer (degenerate modes) falls back to LU.
    #[test]
    fn symmetric_inverses_match_the_lu_path() {
        let lossless = Materials {
            k_pillar: 0.0,
            ..Materials::default()
        };
        for rule in [Rule::Nv, Rule::Laurent] {
            for (pitch, frac, mat) in [
                (530e-9, 0.38, Materials::default()),
                (530e-9, 0.8, lossless),
                (300e-9, 0.2, Materials::default()),
                (900e-9, 0.55, lossless),
            ] {
                let spec = CellSpec {
                    wavelength_m: 940e-9,
                    pitch_m: pitch,
                    diameter_m: frac * pitch,
                    materials: mat,
                    harmonics: 5,
                    rule,
                };
                let fast = LayerModes::build(&spec, true).unwrap();
                let lu = LayerModes::build(&spec, false).unwrap();
                assert!(fast.symmetric, "{spec:?} fell back to LU");
                assert!(!lu.symmetric);
                for h in [0.0, 100e-9, 700e-9, 1500e-9, 20e-6] {
                    let (a, b) = (fast.at_height(h).unwrap(), lu.at_height(h).unwrap());
                    assert!(
                        (a.t - b.t).norm() < 1e-10,
                        "{spec:?} h {h}: {} vs {}",
                        a.t,
                        b.t
                    );
                    assert!((a.reflectance - b.reflectance).abs() < 1e-10);
                    assert!((a.transmitted_total - b.transmitted_total).abs() < 1e-10);
                }
            }
        }
        let film = CellSpec {
            wavelength_m: 940e-9,
            pitch_m: 530e-9,
            diameter_m: 200e-9,
            materials: Materials {
                n_pillar: 1.0,
                k_pillar: 0.0,
                ..Materials::default()
            },
            harmonics: 4,
            rule: Rule::Nv,
        };
        let m = LayerModes::build(&film, true).unwrap();
        assert!(
            !m.symmetric,
            "degenerate plane-wave modes must fall back to LU"
        );
    }
}

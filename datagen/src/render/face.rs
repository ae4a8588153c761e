//! The periocular region around the procedural eye (C.1): eyelids with a palpebral fissure that
//! follow the eye, canthi and caruncle, an upper-lid crease, brow ridge, cheek and the side of
//! the nose as one triangle mesh, and eyelashes as crossed ribbons. Conventions and sources in
//! docs/renderer.md ("Eye region").
//!
//! The skin is a radial surface about the eye's rotation centre: along each direction ω it lies
//! at the eye's own surface radius plus a thickness that grows away from the fissure. The mesh
//! is laid out in fissure-polar coordinates (a ring around the fissure, rows outward), so the
//! lid margin is sampled exactly and no triangle straddles it.

use super::scene::{EyeGeometry, Subject};
use crate::states::State;
use nanoeye_gaze::{Vec3, geom};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::f64::consts::{PI, TAU};

/// Fraction of the eye's elevation the upper lid margin follows (1: in steady fixation the eye
/// and the upper lid take essentially equal positions, Becker & Fuchs, J. Neurophysiol. 60,
/// 1227 (1988)).
pub const UPPER_LID_GAIN: f64 = 1.0;
/// Fraction of the eye's elevation the lower lid margin follows in downgaze (0.6: the vertical
/// fissure narrows from 9.7 to 6.4 mm between primary gaze and 40° downgaze, Read et al.,
/// Optom. Vis. Sci. 83, 715 (2006), with the upper lid following the eye).
pub const LOWER_LID_GAIN_DOWN: f64 = 0.6;
/// Fraction of the eye's elevation the lower lid follows in upgaze (0.3, a modelling choice:
/// the lower lid lags the eye in upgaze, so the fissure opens).
pub const LOWER_LID_GAIN_UP: f64 = 0.3;
/// Fraction of the eye's azimuth the fissure's centre follows (0.15, a modelling choice: the
/// lids' highest and lowest points shift slightly with horizontal gaze).
pub const FISSURE_AZIMUTH_GAIN: f64 = 0.15;
/// Gap (m) between the eye's surface and the lid margin resting on it: keeps the two surfaces
/// from touching in floating point while staying far below a native pixel's footprint.
pub const LID_GAP_M: f64 = 0.05e-3;
/// Skin thickness (m) at the lid margin (the intermarginal strip's width).
pub const LID_MARGIN_THICKNESS_M: f64 = 0.8e-3;
/// Fissure-polar samples around the fissure.
pub const RING_SAMPLES: usize = 256;
/// Rows from the lid margin to the outer edge of the face.
pub const ROWS: usize = 48;
/// Segments per eyelash.
pub const LASH_SEGMENTS: usize = 4;

/// Which part of the face a triangle belongs to (drives its material).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum FacePart {
    /// Lid, periocular, brow, cheek and nose skin.
    Skin,
    /// The intermarginal strip of the lid margin (wet: tear meniscus).
    Margin,
    /// An eyelash.
    Lash,
}

/// The posed palpebral fissure in angular coordinates about the rotation centre (rad):
/// azimuth a = atan2(x, z) (+ nasal for the right eye), elevation e = atan2(y, √(x²+z²)).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Fissure {
    /// Centre azimuth.
    pub center_az: f64,
    /// Centre elevation.
    pub center_el: f64,
    /// Angular half length towards the medial (nasal, +a) canthus.
    pub medial: f64,
    /// Angular half length towards the lateral (temporal, −a) canthus.
    pub lateral: f64,
    /// Angular height of the upper margin above the centre.
    pub upper: f64,
    /// Angular depth of the lower margin below the centre.
    pub lower: f64,
    /// Superellipse exponent of the margin (2: ellipse; smaller: pointed canthi).
    pub exponent: f64,
    /// Canthal tilt (rad): positive raises the lateral canthus.
    pub tilt: f64,
    /// Stand-off (m) of the lid margin from the globe at the medial canthus.
    pub lift_medial: f64,
    /// Stand-off (m) of the lid margin from the globe at the lateral canthus.
    pub lift_lateral: f64,
}

impl Fissure {
    /// The fissure of `subject` in `state`: lid kinematics (elevation gains above, azimuth
    /// follow) and the state's lid closure (0 open … 1 closed: the margins meet 15 % of the
    /// fissure's height above the lower margin).
    pub fn posed(subject: &Subject, state: &State) -> Fissure {
        let el = state.elevation_rad;
        let lower_gain = if el < 0.0 {
            LOWER_LID_GAIN_DOWN
        } else {
            LOWER_LID_GAIN_UP
        };
        let top0 = subject.fissure_center_el_rad + subject.fissure_upper_rad + UPPER_LID_GAIN * el;
        let bottom0 = subject.fissure_center_el_rad - subject.fissure_lower_rad + lower_gain * el;
        let bottom0 = bottom0.min(top0);
        let c = state.lid_closure.clamp(0.0, 1.0);
        let meet = bottom0 + 0.15 * (top0 - bottom0);
        let top = top0 + c * (meet - top0);
        let bottom = bottom0 + c * (meet - bottom0);
        let height = (top - bottom).max(0.0);
        let share =
            subject.fissure_upper_rad / (subject.fissure_upper_rad + subject.fissure_lower_rad);
        // A closed fissure keeps a vanishing opening so the ring stays a proper curve.
        let min_half = 1e-6;
        Fissure {
            center_az: subject.fissure_center_az_rad + FISSURE_AZIMUTH_GAIN * state.azimuth_rad,
            center_el: bottom + height * (1.0 - share),
            medial: subject.fissure_medial_rad,
            lateral: subject.fissure_lateral_rad,
            upper: (height * share).max(min_half),
            lower: (height * (1.0 - share)).max(min_half),
            exponent: subject.fissure_exponent,
            tilt: subject.canthal_tilt_rad,
            lift_medial: subject.canthus_lift_medial_m,
            lift_lateral: subject.canthus_lift_lateral_m,
        }
    }

    /// Stand-off (m) of the lid margin from the eye's surface at fissure-polar angle `theta`:
    /// zero over the middle of the fissure, rising smoothly over the outer 25 % of each half
    /// length to the canthus's own value. The lids hug the globe, but the canthi lie off it
    /// (medially by the caruncle's width), so the fissure can be longer than the globe is wide.
    pub fn lift(&self, theta: f64) -> f64 {
        let c = theta.cos();
        let (half, lift) = if c >= 0.0 {
            (self.medial, self.lift_medial)
        } else {
            (self.lateral, self.lift_lateral)
        };
        let u = (self.margin_radius(theta) * c / half).abs();
        lift * smoothstep((u - 0.75) / 0.25)
    }

    /// Radius (rad) of the margin at fissure-polar angle `theta` (0 towards the medial canthus,
    /// π/2 up), in the fissure's tilted frame.
    pub fn margin_radius(&self, theta: f64) -> f64 {
        let (s, c) = theta.sin_cos();
        let a = if c >= 0.0 { self.medial } else { self.lateral };
        let b = if s >= 0.0 { self.upper } else { self.lower };
        let p = self.exponent;
        let q = (c / a).abs().powf(p) + (s / b).abs().powf(p);
        q.powf(-1.0 / p)
    }

    /// Angular position (azimuth, elevation) of the point at polar angle `theta`, radius `rho`.
    pub fn at(&self, theta: f64, rho: f64) -> (f64, f64) {
        let (s, c) = theta.sin_cos();
        let (x, y) = (rho * c, rho * s);
        // Rotating by −tilt lifts the lateral (x < 0) end for a positive tilt.
        let (st, ct) = (-self.tilt).sin_cos();
        (
            self.center_az + x * ct - y * st,
            self.center_el + x * st + y * ct,
        )
    }

    /// True when direction (a, e) looks through the open fissure.
    pub fn is_open(&self, a: f64, e: f64) -> bool {
        let (da, de) = (a - self.center_az, e - self.center_el);
        let (st, ct) = self.tilt.sin_cos();
        let (x, y) = (da * ct - de * st, da * st + de * ct);
        let rho = (x * x + y * y).sqrt();
        rho < self.margin_radius(y.atan2(x))
    }
}

/// Unit direction of azimuth `a`, elevation `e` (the inverse of the angles above).
#[inline]
pub fn direction(a: f64, e: f64) -> Vec3 {
    let (sa, ca) = a.sin_cos();
    let (se, ce) = e.sin_cos();
    [sa * ce, se, ca * ce]
}

/// Distance (m) from the rotation centre to the eye's outer surface along unit `w`: the
/// cornea where the ray leaves through the corneal cap of the eye gazing along `g`, the
/// eyeball elsewhere.
pub fn eye_radius(geo: &EyeGeometry, g: Vec3, w: Vec3) -> f64 {
    let cos_psi = geom::dot(w, g).clamp(-1.0, 1.0);
    let c = geo.cornea_center_m;
    let disc = geo.cornea_radius_m * geo.cornea_radius_m - c * c * (1.0 - cos_psi * cos_psi);
    if disc > 0.0 {
        let t = c * cos_psi + disc.sqrt();
        if t * cos_psi >= geo.pupil_plane_m {
            return t.max(geo.eyeball_radius_m);
        }
    }
    geo.eyeball_radius_m
}

#[inline]
fn smoothstep(x: f64) -> f64 {
    let x = x.clamp(0.0, 1.0);
    x * x * (3.0 - 2.0 * x)
}

/// Skin thickness (m) over the eye's surface `d` rad outside the margin at fissure-polar angle
/// `theta`: 0.8 mm at the margin growing to 2 mm, minus the upper lid's crease.
fn lid_thickness(s: &Subject, d: f64, theta: f64) -> f64 {
    let lid = LID_MARGIN_THICKNESS_M + (2.0e-3 - LID_MARGIN_THICKNESS_M) * smoothstep(d / 0.35);
    let upper = smoothstep((theta.sin() - 0.3) / 0.4);
    let crease = if s.crease_rad > 0.0 {
        s.crease_depth_m * (-((d - s.crease_rad) / 0.05).powi(2)).exp() * upper
    } else {
        0.0
    };
    lid - crease
}

/// A smooth bump of height 1 at 0 falling to 0 at |u| = 1 (C¹, cheap: no `exp`).
#[inline]
fn bump(u: f64) -> f64 {
    let v = 1.0 - u * u;
    if v > 0.0 { v * v } else { 0.0 }
}

/// Depth (m, eye frame z) of the face surface's base plane, through the orbital rims: 6 mm in
/// front of the rotation centre, about 7 mm behind the corneal apex (a modelling choice; the
/// lateral rim lies ≈ 16 mm behind the apex, Hertel exophthalmometry, reached through the
/// temple term below).
pub const FACE_BASE_Z_M: f64 = 6e-3;

/// Depth z (m) of the face surface in front of the eye at (x, y) (m, eye frame at primary gaze;
/// +x nasal): a base plane with the subject's brow ridge above, cheek below, the side of the
/// nose nasally, and the temple falling back laterally. Far from the fissure the skin lies on
/// it; near the fissure the lids hug the globe (docs/renderer.md).
pub fn face_z(s: &Subject, x: f64, y: f64) -> f64 {
    let mm = 1e-3;
    // The brow ridge rises 8–20 mm above the eye's centre; the forehead recedes above it.
    let brow = smoothstep((y - 8.0 * mm) / (12.0 * mm))
        * (1.0 - 0.4 * smoothstep((y - 30.0 * mm) / (30.0 * mm)));
    // The cheek's prominence lies below and slightly lateral of the eye.
    let cheek = bump((y + 24.0 * mm) / (18.0 * mm)) * bump((x + 4.0 * mm) / (30.0 * mm));
    // The side of the nose rises from 8 mm nasal of the eye's centre to the dorsum at the
    // midline (≈ 32 mm), stronger below the brow.
    let nose = 1.5
        * smoothstep((x - 8.0 * mm) / (24.0 * mm))
        * (1.0 - 0.5 * smoothstep((y - 10.0 * mm) / (20.0 * mm)));
    let lateral = (-x - 8.0 * mm).max(0.0);
    let temple = lateral * lateral / (2.0 * 20.0 * mm);
    // Past the dorsum the other side of the nose falls away, so that directions nasal of the
    // nose still meet skin (the far side, facing away from the light).
    let beyond = (x - 32.0 * mm).max(0.0);
    let far_side = beyond * beyond / (2.0 * 10.0 * mm);
    FACE_BASE_Z_M + s.brow_m * brow + s.cheek_m * cheek + s.nose_m * nose - temple - far_side
}

/// Smooth maximum of `a` and `b`, rounding the corner over a width ≈ `k`.
#[inline]
fn smax(a: f64, b: f64, k: f64) -> f64 {
    0.5 * (a + b + ((a - b) * (a - b) + k * k).sqrt())
}

/// Skin thickness (m) over the globe where the face surface does not lie in front of it.
pub const ORBIT_SKIN_M: f64 = 2e-3;

/// Depth z (m) of the skin at (x, y) away from the lids: the face surface [`face_z`], or the
/// skin over the globe (eyeball radius `r_eye` plus [`ORBIT_SKIN_M`]) where that lies in front,
/// joined smoothly.
fn skin_z(s: &Subject, r_eye: f64, x: f64, y: f64) -> f64 {
    let r = r_eye + ORBIT_SKIN_M;
    let q = r * r - x * x - y * y;
    let face = face_z(s, x, y);
    if q <= 0.0 {
        return face;
    }
    smax(face, q.sqrt(), 2e-3)
}

/// The posed face: triangles with their part, and the posed fissure.
#[derive(Debug, Clone)]
pub struct Face {
    /// Triangles (m, world), vertices rounded to f32 so an exported mesh reproduces them
    /// exactly.
    pub triangles: Vec<([Vec3; 3], FacePart)>,
    /// Per triangle, the surface normals at its three vertices for smooth shading (unit, not
    /// oriented): the skin's, averaged over the skin triangles around each vertex; `None` for
    /// the lid margin's strip (a crisp edge) and the lashes.
    pub shading: Vec<Option<[Vec3; 3]>>,
    /// The caruncle: (centre, radius) in m.
    pub caruncle: (Vec3, f64),
    /// The fissure the lids form in this state.
    pub fissure: Fissure,
    /// The medial and lateral canthus: where the lid margins meet (m, same frame as the
    /// triangles).
    pub canthi: [Vec3; 2],
}

#[inline]
fn f32_round(p: Vec3) -> Vec3 {
    p.map(|x| x as f32 as f64)
}

/// Angular width (rad) of the lid band beyond the upper and lower margins (a quarter of it at
/// the canthi): the skin there lies on the globe (and on the cornea where it bulges under the
/// lids); beyond it the face surface takes over.
pub const LID_BAND_RAD: f64 = 0.4;
/// Of the [`ROWS`] rows outward, those across the lid band; the rest cross the face.
pub const LID_ROWS: usize = 20;
/// Outer edge of the mesh: half extents (m) in x towards the nose and the temple, and in y,
/// about the fissure's centre, far enough that the rig's wide field of view meets skin in
/// every direction that does not look through the fissure.
const OUTER_X_MEDIAL_M: f64 = 0.06;
const OUTER_X_LATERAL_M: f64 = 0.07;
const OUTER_Y_M: f64 = 0.06;
/// Fraction of the face rows over which the skin blends from the lid band onto the face.
const FACE_BLEND: f64 = 0.3;

/// Builds the face of `subject` in `state` around the eye `geo` gazing along `g`.
pub fn face(geo: &EyeGeometry, subject: &Subject, state: &State, g: Vec3) -> Face {
    let f = Fissure::posed(subject, state);
    let n = RING_SAMPLES;
    let rows = ROWS + 2;
    let face_rows = ROWS - LID_ROWS;
    let mut verts = vec![[0.0; 3]; n * rows];
    // The globe under each margin point: where the margin stands off the globe, a wet wall
    // (conjunctiva) closes the gap so that no ray slips between lid and eyeball.
    let mut fornix = vec![[0.0; 3]; n];
    let c = direction(f.center_az, f.center_el);
    let (cx, cy) = (c[0] * geo.eyeball_radius_m, c[1] * geo.eyeball_radius_m);
    for i in 0..n {
        let theta = TAU * i as f64 / n as f64;
        let rho_m = f.margin_radius(theta);
        let (am, em) = f.at(theta, rho_m);
        let w = direction(am, em);
        let r_eye = eye_radius(geo, g, w);
        let lift = f.lift(theta);
        verts[i] = geom::scale(w, r_eye + LID_GAP_M + lift);
        verts[n + i] = geom::scale(w, r_eye + LID_MARGIN_THICKNESS_M + lift);
        fornix[i] = geom::scale(w, r_eye + LID_GAP_M);
        // The lid band: radial from the rotation centre, on the eye's surface plus the lid;
        // narrower towards the canthi, where the globe curves away behind the face. The
        // canthus's stand-off fades out across it.
        let band = LID_BAND_RAD * (0.25 + 0.75 * theta.sin().powi(2));
        for j in 1..=LID_ROWS {
            let d = band * (j as f64 / LID_ROWS as f64).powi(2);
            let (a, e) = f.at(theta, rho_m + d);
            let w = direction(a, e);
            let r = eye_radius(geo, g, w)
                + lid_thickness(subject, d, theta)
                + lift * (1.0 - smoothstep(d / band));
            verts[(j + 1) * n + i] = geom::scale(w, r);
        }
        // The face: a height field z(x, y) laid out from the band's edge straight out to a
        // squarish boundary about the fissure's centre. A height field samples the side of the
        // nose and the temple evenly, where rays from the rotation centre would graze them.
        let p0 = verts[(LID_ROWS + 1) * n + i];
        let (st, ct) = (theta - f.tilt).sin_cos();
        let k = (ct.powi(4) + st.powi(4)).powf(-0.25);
        let half_x = if ct >= 0.0 {
            OUTER_X_MEDIAL_M
        } else {
            OUTER_X_LATERAL_M
        };
        let (bx, by) = (cx + k * half_x * ct, cy + k * OUTER_Y_M * st);
        let dz0 = p0[2] - skin_z(subject, geo.eyeball_radius_m, p0[0], p0[1]);
        for j in 1..=face_rows {
            let u = j as f64 / face_rows as f64;
            // Rows denser near the lids, where the surface bends most.
            let t = u.powf(1.5);
            let (x, y) = (p0[0] + t * (bx - p0[0]), p0[1] + t * (by - p0[1]));
            let z = skin_z(subject, geo.eyeball_radius_m, x, y)
                + dz0 * (1.0 - smoothstep(u / FACE_BLEND));
            verts[(LID_ROWS + 1 + j) * n + i] = [x, y, z];
        }
    }
    let verts: Vec<Vec3> = verts.into_iter().map(f32_round).collect();
    let mut triangles = Vec::with_capacity(2 * n * rows + lash_capacity(subject));
    // Corner indices of each grid triangle, for the vertex normals below.
    let mut corners = Vec::with_capacity(2 * n * (rows - 1));
    for j in 0..rows - 1 {
        let part = if j == 0 {
            FacePart::Margin
        } else {
            FacePart::Skin
        };
        for i in 0..n {
            let i1 = (i + 1) % n;
            let (ia, ib) = (j * n + i, j * n + i1);
            let (ic, id) = ((j + 1) * n + i, (j + 1) * n + i1);
            for tri in [[ia, ib, id], [ia, id, ic]] {
                triangles.push((tri.map(|k| verts[k]), part));
                corners.push(tri);
            }
        }
    }
    // Area-weighted vertex normals of the skin: with the face surface tens of millimetres from
    // the eye, flat facets 1–2 mm wide would show as streaks under the near light.
    let mut vn = vec![[0.0; 3]; verts.len()];
    for (tri, (v, part)) in corners.iter().zip(&triangles) {
        if *part == FacePart::Skin {
            let c = geom::cross(geom::sub(v[1], v[0]), geom::sub(v[2], v[0]));
            for &k in tri {
                vn[k] = geom::add(vn[k], c);
            }
        }
    }
    let mut shading: Vec<Option<[Vec3; 3]>> = corners
        .iter()
        .zip(&triangles)
        .map(|(tri, (_, part))| {
            let ns = tri.map(|k| vn[k]);
            (*part == FacePart::Skin && ns.iter().all(|n| geom::norm(*n) > 0.0))
                .then(|| ns.map(geom::normalize))
        })
        .collect();
    let fornix: Vec<Vec3> = fornix.into_iter().map(f32_round).collect();
    for i in 0..n {
        let i1 = (i + 1) % n;
        if verts[i] != fornix[i] || verts[i1] != fornix[i1] {
            let (a, b, c, d) = (verts[i], verts[i1], fornix[i], fornix[i1]);
            triangles.push(([a, b, d], FacePart::Margin));
            triangles.push(([a, d, c], FacePart::Margin));
        }
    }
    lashes(geo, subject, &f, g, &mut triangles);
    shading.resize(triangles.len(), None);
    // The caruncle sits in the medial canthus on the globe; an epicanthic fold hides part of it.
    // It fills the space the lifted canthus leaves between lids and globe.
    let (ac, ec) = f.at(0.0, 0.9 * f.medial);
    let wc = direction(ac, ec);
    let rc = subject.caruncle_radius_m * (1.0 - 0.6 * subject.epicanthus);
    let caruncle = (
        f32_round(geom::scale(
            wc,
            geo.eyeball_radius_m + 0.1e-3 + 0.5 * f.lift_medial,
        )),
        rc as f32 as f64,
    );
    Face {
        triangles,
        shading,
        caruncle,
        fissure: f,
        // Ring samples 0 and n/2 lie at fissure-polar angles 0 (medial) and π (lateral).
        canthi: [verts[0], verts[n / 2]],
    }
}

fn lash_capacity(s: &Subject) -> usize {
    (s.lashes_upper + s.lashes_lower) as usize * LASH_SEGMENTS * 4
}

/// One lash's random shape, fixed per subject: where on the margin it grows and how it bends.
struct LashShape {
    /// Fraction along the lashed part of the margin (0 lateral … 1 medial).
    u: f64,
    /// Length (m).
    len: f64,
    /// Angle from the radial direction towards the side away from the fissure at the root (rad).
    beta0: f64,
    /// Extra bend from root to tip (rad).
    curl: f64,
    /// Sideways splay along the margin (fraction of the direction).
    splay: f64,
}

fn lash_shapes(s: &Subject, upper: bool) -> Vec<LashShape> {
    let mut rng = ChaCha8Rng::seed_from_u64(s.lash_seed ^ if upper { 0x11 } else { 0x22 });
    let count = if upper {
        s.lashes_upper
    } else {
        s.lashes_lower
    } as usize;
    let (len, beta, curl) = if upper {
        (s.lash_length_upper_m, 0.55, 0.7)
    } else {
        (s.lash_length_lower_m, 0.45, 0.35)
    };
    (0..count)
        .map(|k| {
            // Stratified positions; lashes thin out towards the medial end.
            let u0 = (k as f64 + rng.random::<f64>()) / count as f64;
            let u = 1.0 - (1.0 - u0).sqrt() * 0.999;
            LashShape {
                u: u.clamp(0.0, 1.0),
                len: len * (0.7 + 0.3 * rng.random::<f64>()) * (1.0 - 0.35 * u),
                beta0: beta + 0.25 * (rng.random::<f64>() - 0.5),
                curl: curl * (0.7 + 0.6 * rng.random::<f64>()),
                splay: 0.3 * (rng.random::<f64>() - 0.5),
            }
        })
        .collect()
}

/// Appends the upper and lower lashes as crossed ribbons (two quads per segment).
fn lashes(
    geo: &EyeGeometry,
    s: &Subject,
    f: &Fissure,
    g: Vec3,
    out: &mut Vec<([Vec3; 3], FacePart)>,
) {
    let margin_point = |theta: f64| {
        let (a, e) = f.at(theta, f.margin_radius(theta));
        let w = direction(a, e);
        geom::scale(
            w,
            eye_radius(geo, g, w) + 0.7 * LID_MARGIN_THICKNESS_M + f.lift(theta),
        )
    };
    for upper in [true, false] {
        // Lashes grow from 5 % of the arc at the lateral canthus to 85 % (none medially,
        // where the lacrimal part of the margin is).
        let (th_lat, th_med) = if upper {
            (PI - 0.05 * PI, 0.15 * PI)
        } else {
            (PI + 0.05 * PI, TAU - 0.15 * PI)
        };
        for l in lash_shapes(s, upper) {
            let theta = th_lat + l.u * (th_med - th_lat);
            let root = margin_point(theta);
            let h = 1e-4;
            let tangent =
                geom::normalize(geom::sub(margin_point(theta + h), margin_point(theta - h)));
            let radial = geom::normalize(root);
            let mut away = geom::normalize(geom::cross(radial, tangent));
            // Away from the fissure: up for the upper lid, down for the lower.
            let want_up = upper;
            if (away[1] > 0.0) != want_up {
                away = geom::scale(away, -1.0);
            }
            let mut p = root;
            let step = l.len / LASH_SEGMENTS as f64;
            // Lower lashes are finer than upper ones.
            let root_width = s.lash_width_m * if upper { 1.0 } else { 0.75 };
            let width = |k: usize| {
                let t = k as f64 / LASH_SEGMENTS as f64;
                (root_width * (1.0 - 0.7 * t)) as f32 as f64
            };
            for k in 0..LASH_SEGMENTS {
                let beta = l.beta0 + l.curl * (k as f64 + 0.5) / LASH_SEGMENTS as f64;
                let dir = geom::normalize(geom::add(
                    geom::add(
                        geom::scale(radial, beta.cos()),
                        geom::scale(away, beta.sin()),
                    ),
                    geom::scale(tangent, l.splay),
                ));
                let q = geom::add(p, geom::scale(dir, step));
                let e1 = geom::normalize(geom::cross(dir, radial));
                let e2 = geom::normalize(geom::cross(dir, e1));
                for e in [e1, e2] {
                    let (w0, w1) = (0.5 * width(k), 0.5 * width(k + 1));
                    let v = [
                        f32_round(geom::add(p, geom::scale(e, -w0))),
                        f32_round(geom::add(p, geom::scale(e, w0))),
                        f32_round(geom::add(q, geom::scale(e, w1))),
                        f32_round(geom::add(q, geom::scale(e, -w1))),
                    ];
                    out.push(([v[0], v[1], v[2]], FacePart::Lash));
                    out.push(([v[0], v[2], v[3]], FacePart::Lash));
                }
                p = q;
            }
        }
    }
}

/// Elevation (rad) of the upper margin above the fissure's centre, before the canthal tilt.
pub fn upper_margin_el(f: &Fissure) -> f64 {
    f.center_el + f.upper
}

/// Elevation (rad) of the lower margin below the fissure's centre, before the canthal tilt.
pub fn lower_margin_el(f: &Fissure) -> f64 {
    f.center_el - f.lower
}

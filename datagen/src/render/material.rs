//! The documented material set (skin, sclera, iris, pupil, cornea) and NIR reflectance textures.

use nanoeye_gaze::{Vec3, geom};

/// Material classes every scene (procedural or mesh) maps onto.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum MaterialKind {
    /// Periocular skin and eyelids (Lambertian, occludes the eye).
    Skin,
    /// White of the eye (Lambertian).
    Sclera,
    /// Iris (Lambertian with a radial texture).
    Iris,
    /// Pupil (near-black Lambertian; labelled in the masks).
    Pupil,
    /// Cornea front surface (Fresnel specular reflection + refraction).
    Cornea,
    /// Eyelashes (dark Lambertian; occlude like skin).
    Lash,
}

impl MaterialKind {
    /// Maps a mesh material/object name onto the set: the first of the class names it
    /// contains (case-insensitive); anything else is skin.
    pub fn from_name(name: &str) -> MaterialKind {
        let n = name.to_ascii_lowercase();
        for (key, kind) in [
            ("pupil", MaterialKind::Pupil),
            ("iris", MaterialKind::Iris),
            ("cornea", MaterialKind::Cornea),
            ("sclera", MaterialKind::Sclera),
            ("lash", MaterialKind::Lash),
            ("skin", MaterialKind::Skin),
        ] {
            if n.contains(key) {
                return kind;
            }
        }
        MaterialKind::Skin
    }

    /// True for parts that rotate with the eye.
    pub fn is_eye(self) -> bool {
        !self.is_occluder()
    }

    /// True for the face's parts (skin and lashes): what the unoccluded pupil mask removes.
    pub fn is_occluder(self) -> bool {
        matches!(self, MaterialKind::Skin | MaterialKind::Lash)
    }
}

/// Procedural radial iris texture: crypts and radial fibres in the iris plane.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IrisTexture {
    /// Iris centre (m, world).
    pub center: Vec3,
    /// In-plane unit axis (rotates with torsion).
    pub u: Vec3,
    /// Second in-plane unit axis.
    pub v: Vec3,
    /// Pupil radius (m).
    pub r_pupil_m: f64,
    /// Limbus radius (m).
    pub r_limbus_m: f64,
    /// Angular frequencies of the fibres.
    pub freq: [f64; 3],
    /// Phases of the fibres (rad).
    pub phase: [f64; 3],
    /// Fibre contrast (0–1).
    pub contrast: f64,
}

impl IrisTexture {
    /// Multiplicative albedo factor at point `p` on the iris (≈0.4–1.6).
    #[inline]
    pub fn factor(&self, p: Vec3) -> f64 {
        let d = geom::sub(p, self.center);
        let (x, y) = (geom::dot(d, self.u), geom::dot(d, self.v));
        let r = (x * x + y * y).sqrt();
        let a = y.atan2(x);
        let s = ((r - self.r_pupil_m) / (self.r_limbus_m - self.r_pupil_m)).clamp(0.0, 1.0);
        let mut f = 0.0;
        for k in 0..3 {
            f += (self.freq[k] * a + self.phase[k] + 6.0 * s).sin();
        }
        // Collarette brightening near the pupil, dark limbal ring at the edge.
        let collarette = 0.25 * (-((s - 0.3) / 0.08).powi(2)).exp();
        let limbal = 1.0 - 0.6 * ((s - 0.85) / 0.15).clamp(0.0, 1.0);
        (1.0 + self.contrast * f / 3.0 + collarette) * limbal
    }
}

/// Skin micro-texture: two octaves of 3D value noise (pores and fine wrinkles at 0.25 mm,
/// blotches at 1.2 mm) modulating the albedo.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SkinTexture {
    /// Seed of the noise lattice.
    pub seed: u64,
    /// Relative albedo modulation (0–0.5).
    pub amplitude: f64,
}

impl SkinTexture {
    /// Multiplicative albedo factor at point `p` (m), within 1 ± amplitude.
    #[inline]
    pub fn factor(&self, p: Vec3) -> f64 {
        let fine = value_noise(self.seed, geom::scale(p, 1.0 / 0.25e-3));
        let coarse = value_noise(self.seed ^ 0x9E37, geom::scale(p, 1.0 / 1.2e-3));
        1.0 + self.amplitude * (0.6 * fine + 0.4 * coarse)
    }
}

/// Lattice value in [−1, 1] at integer point (i, j, k).
#[inline]
fn lattice(seed: u64, i: i64, j: i64, k: i64) -> f64 {
    let mut h = seed
        ^ (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ (j as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F)
        ^ (k as u64).wrapping_mul(0x1656_67B1_9E37_79F9);
    h = (h ^ (h >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    h = (h ^ (h >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    h ^= h >> 31;
    (h >> 11) as f64 * (2.0 / (1u64 << 53) as f64) - 1.0
}

/// Smooth 3D value noise in [−1, 1] (trilinear with smoothstep weights).
fn value_noise(seed: u64, p: Vec3) -> f64 {
    if !geom::is_finite(p) {
        return 0.0;
    }
    let f = p.map(f64::floor);
    let (i, j, k) = (f[0] as i64, f[1] as i64, f[2] as i64);
    let w = [0, 1, 2].map(|a| {
        let t = p[a] - f[a];
        t * t * (3.0 - 2.0 * t)
    });
    let mut acc = 0.0;
    for dk in 0..2 {
        for dj in 0..2 {
            for di in 0..2 {
                let wx = if di == 0 { 1.0 - w[0] } else { w[0] };
                let wy = if dj == 0 { 1.0 - w[1] } else { w[1] };
                let wz = if dk == 0 { 1.0 - w[2] } else { w[2] };
                acc += wx * wy * wz * lattice(seed, i + di, j + dj, k + dk);
            }
        }
    }
    acc
}

/// Refractive index of the tear film (the wet coat of sclera, lid margin and caruncle).
pub const TEAR_FILM_INDEX: f64 = 1.337;

/// A surface material: class, NIR albedo and optional texture.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Material {
    /// Class (drives shading and the masks).
    pub kind: MaterialKind,
    /// Lambertian albedo at the illuminator wavelength (0–1); unused by the cornea.
    pub albedo: f64,
    /// Iris texture, if any.
    pub iris: Option<IrisTexture>,
    /// Skin micro-texture, if any.
    pub skin: Option<SkinTexture>,
    /// Refractive index of a specular wet coat over the Lambertian base (0: none): the
    /// illuminator's mirror image appears where the reflected ray meets it.
    pub coat_index: f64,
}

impl Material {
    /// A plain Lambertian material.
    pub fn lambertian(kind: MaterialKind, albedo: f64) -> Material {
        Material {
            kind,
            albedo,
            iris: None,
            skin: None,
            coat_index: 0.0,
        }
    }

    /// Albedo at surface point `p`.
    #[inline]
    pub fn albedo_at(&self, p: Vec3) -> f64 {
        let mut a = self.albedo;
        if let Some(t) = &self.iris {
            a *= t.factor(p);
        }
        if let Some(t) = &self.skin {
            a *= t.factor(p);
        }
        a.clamp(0.0, 1.0)
    }
}

/// Fresnel reflectance of unpolarized light from a medium of index `n1` into `n2` at incidence
/// cosine `cos_i` (exact Fresnel equations; 1 beyond the critical angle).
pub fn fresnel(cos_i: f64, n1: f64, n2: f64) -> f64 {
    let cos_i = cos_i.clamp(0.0, 1.0);
    let sin_t = n1 / n2 * (1.0 - cos_i * cos_i).max(0.0).sqrt();
    if sin_t >= 1.0 {
        return 1.0;
    }
    let cos_t = (1.0 - sin_t * sin_t).sqrt();
    let rs = (n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t);
    let rp = (n2 * cos_i - n1 * cos_t) / (n2 * cos_i + n1 * cos_t);
    0.5 * (rs * rs + rp * rp)
}

/// Refracts unit direction `d` at a surface with unit normal `n` facing against `d`, index
/// ratio `eta` = n1/n2; None on total internal reflection.
pub fn refract(d: Vec3, n: Vec3, eta: f64) -> Option<Vec3> {
    let cos_i = -geom::dot(d, n);
    let k = 1.0 - eta * eta * (1.0 - cos_i * cos_i);
    if k < 0.0 {
        return None;
    }
    Some(geom::normalize(geom::add(
        geom::scale(d, eta),
        geom::scale(n, eta * cos_i - k.sqrt()),
    )))
}

/// Mirror reflection of `d` about unit normal `n`.
pub fn reflect(d: Vec3, n: Vec3) -> Vec3 {
    geom::sub(d, geom::scale(n, 2.0 * geom::dot(d, n)))
}

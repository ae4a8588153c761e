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
        !matches!(self, MaterialKind::Skin)
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

/// A surface material: class, NIR albedo and optional texture.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Material {
    /// Class (drives shading and the masks).
    pub kind: MaterialKind,
    /// Lambertian albedo at the illuminator wavelength (0–1); unused by the cornea.
    pub albedo: f64,
    /// Iris texture, if any.
    pub iris: Option<IrisTexture>,
}

impl Material {
    /// Albedo at surface point `p`.
    #[inline]
    pub fn albedo_at(&self, p: Vec3) -> f64 {
        match &self.iris {
            Some(t) => (self.albedo * t.factor(p)).clamp(0.0, 1.0),
            None => self.albedo,
        }
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

//! Scenes: primitives + materials + BVH + illuminator; the procedural right-eye region.

use super::bvh::Bvh;
use super::face::{self, Face, FacePart};
use super::lanes::{LANES, TriLanes};
use super::material::{IrisTexture, Material, MaterialKind, SkinTexture, TEAR_FILM_INDEX};
use super::prim::{Clip, Shape, T_EPS};
use super::{Ray, RenderError};
use crate::states::State;
use nanoeye_gaze::{Mat3, Pose, Rig, Vec3, geom};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

/// Visibility class bit: sclera, iris, pupil (what lies behind the cornea or beside it).
pub const LAYER_EYE: u8 = 1;
/// Visibility class bit: the refracting cornea.
pub const LAYER_CORNEA: u8 = 2;
/// Visibility class bit: skin and lids (occluders).
pub const LAYER_SKIN: u8 = 4;
/// Every class.
pub const LAYER_ALL: u8 = LAYER_EYE | LAYER_CORNEA | LAYER_SKIN;

/// One scene primitive.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Prim {
    /// Geometry (m).
    pub shape: Shape,
    /// Index into [`Scene::materials`].
    pub material: u16,
    /// Visibility class bit (`LAYER_*`).
    pub layer: u8,
}

/// The NIR illuminator: a small spherical emitter (m, W/sr) with an optional beam pattern
/// I(θ) = I₀ cosᵐθ about its axis (an LED aimed at the eye).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Light {
    /// Centre (m, world).
    pub position_m: Vec3,
    /// Emitter radius (m): sets the glint size and the shadow penumbra.
    pub radius_m: f64,
    /// Radiant intensity I₀ (W/sr) on the beam axis (everywhere when isotropic).
    pub intensity_w_per_sr: f64,
    /// Unit beam axis (world); zero for an isotropic emitter.
    #[serde(default)]
    pub axis: Vec3,
    /// Beam exponent m of cosᵐθ (0: isotropic).
    #[serde(default)]
    pub beam_exponent: f64,
}

/// Beam exponent of the default illuminator: cos⁸θ falls to half at 24° off axis, a modelling
/// choice for a NIR LED aimed at the eye (it keeps the skin next to the glasses from
/// outshining the eye).
pub const LED_BEAM_EXPONENT: f64 = 8.0;

/// Where the default illuminator is aimed (m, eye frame): the corneal apex at primary gaze of
/// the average eye.
pub const LED_TARGET_M: Vec3 = [0.0, 0.0, 13.3e-3];

impl Light {
    /// An isotropic emitter.
    pub fn isotropic(position_m: Vec3, radius_m: f64, intensity_w_per_sr: f64) -> Light {
        Light {
            position_m,
            radius_m,
            intensity_w_per_sr,
            axis: [0.0; 3],
            beam_exponent: 0.0,
        }
    }

    /// The default illuminator for a camera pose: 4 mm along the camera's +x axis, 0.5 mm
    /// radius, 1 mW/sr on its axis (≈0.14 mW/cm² at the cornea, far below the 10 mW/cm² IEC
    /// 62471 exempt limit), a cos⁸ beam aimed at [`LED_TARGET_M`] (along the optical axis when
    /// the camera does not face it). The aim follows the target when the glasses slip (a
    /// mount-fixed aim would drift by a few degrees).
    pub fn near_camera(pose: &Pose) -> Light {
        let x = [
            pose.rotation[0][0],
            pose.rotation[1][0],
            pose.rotation[2][0],
        ];
        let z = [
            pose.rotation[0][2],
            pose.rotation[1][2],
            pose.rotation[2][2],
        ];
        let position_m = geom::add(pose.position, geom::scale(x, 4e-3));
        let to = geom::sub(LED_TARGET_M, position_m);
        // A camera that does not face the target (a test rig, a user mesh elsewhere) gets its
        // LED along its own optical axis.
        let axis = if geom::dot(to, z) > 0.0 {
            geom::normalize(to)
        } else {
            geom::normalize(z)
        };
        Light {
            position_m,
            radius_m: 0.5e-3,
            intensity_w_per_sr: 1e-3,
            axis,
            beam_exponent: LED_BEAM_EXPONENT,
        }
    }

    /// Radiant intensity (W/sr) emitted along unit direction `dir` (from the emitter outward).
    #[inline]
    pub fn intensity_along(&self, dir: Vec3) -> f64 {
        if self.beam_exponent == 0.0 {
            return self.intensity_w_per_sr;
        }
        let c = geom::dot(self.axis, dir).max(0.0);
        self.intensity_w_per_sr * c.powf(self.beam_exponent)
    }

    /// Radiant intensity (W/sr) towards point `p` (m).
    pub fn intensity_toward(&self, p: Vec3) -> f64 {
        self.intensity_along(geom::normalize(geom::sub(p, self.position_m)))
    }

    /// Radiance (W/(m²·sr)) of the emitter's disc seen from point `p`.
    #[inline]
    pub fn radiance_toward(&self, p: Vec3) -> f64 {
        self.intensity_toward(p) / (std::f64::consts::PI * self.radius_m * self.radius_m)
    }

    fn validate(&self) -> Result<(), RenderError> {
        if !(geom::is_finite(self.position_m)
            && self.radius_m.is_finite()
            && self.radius_m > 0.0
            && self.intensity_w_per_sr.is_finite()
            && self.intensity_w_per_sr >= 0.0
            && geom::is_finite(self.axis)
            && (self.beam_exponent == 0.0
                || ((geom::norm(self.axis) - 1.0).abs() < 1e-6
                    && self.beam_exponent > 0.0
                    && self.beam_exponent <= 1000.0)))
        {
            return Err(RenderError::Invalid {
                what: "light",
                reason: format!(
                    "{self:?}: position finite, radius > 0, intensity ≥ 0, and for a beam a unit axis and 0 < exponent ≤ 1000 required"
                ),
            });
        }
        Ok(())
    }
}

/// A renderable scene.
#[derive(Debug, Clone)]
pub struct Scene {
    /// Primitives.
    pub prims: Vec<Prim>,
    /// Materials.
    pub materials: Vec<Material>,
    /// Hierarchy over `prims`.
    pub bvh: Bvh,
    /// `prims` in the BVH's leaf order: a leaf's primitives are then contiguous in memory.
    /// Built by [`Scene::new`]; rebuild the scene after changing `prims`.
    pub slots: Vec<Slot>,
    /// The slots' triangles (first vertex and edges precomputed) component by component, so
    /// that a leaf's triangles are tested four at a time with no second lookup.
    lanes: TriLanes,
    /// For each query mask made only of classes short enough to scan without the BVH (see
    /// [`FEW`]), its primitives (indexed by mask; empty for other masks), and those classes'
    /// bits.
    few: (Vec<Vec<u32>>, u8),
    /// Illuminator.
    pub light: Light,
    /// Refractive index of the cornea (and the aqueous behind it).
    pub cornea_index: f64,
    /// A sphere (centre, radius; m) that every ray reaching the pupil enters, when known: rays
    /// missing it skip the skin-free re-trace of the unoccluded pupil mask.
    pub pupil_bound: Option<(Vec3, f64)>,
    /// Vertex normals for smooth shading, indexed like `prims` (empty: every primitive shades
    /// with its geometric normal). Only triangles use them.
    pub shading: Vec<Option<[Vec3; 3]>>,
}

/// A query whose class bits hold at most this many primitives scans them instead of walking
/// the BVH: the rays inside the eye ask for the four eye parts only, and a BVH walk would cross
/// every skin and lash node on the way only to reject their primitives.
pub const FEW: usize = 16;

/// A primitive in traversal order (see [`Scene::slots`]).
#[derive(Debug, Clone, Copy)]
pub struct Slot {
    /// Index into [`Scene::prims`].
    pub prim: u32,
    /// Visibility class bit of the primitive.
    pub layer: u8,
    /// True for a triangle (else the primitive's own shape is intersected).
    pub triangle: bool,
}

/// A ray–scene hit.
#[derive(Debug, Clone, Copy)]
pub struct Hit {
    /// Distance along the ray (m).
    pub t: f64,
    /// Primitive index.
    pub prim: u32,
}

impl Scene {
    /// Builds the BVH over `prims` and validates the parts.
    pub fn new(
        prims: Vec<Prim>,
        materials: Vec<Material>,
        light: Light,
        cornea_index: f64,
    ) -> Result<Scene, RenderError> {
        light.validate()?;
        if !(cornea_index.is_finite() && cornea_index >= 1.0) {
            return Err(RenderError::Invalid {
                what: "cornea_index",
                reason: format!("must be finite and ≥ 1, got {cornea_index}"),
            });
        }
        if let Some(p) = prims
            .iter()
            .find(|p| p.material as usize >= materials.len())
        {
            return Err(RenderError::Invalid {
                what: "prim.material",
                reason: format!("index {} ≥ {} materials", p.material, materials.len()),
            });
        }
        let bounds: Vec<_> = prims.iter().map(|p| p.shape.bounds()).collect();
        if bounds
            .iter()
            .any(|b| !(geom::is_finite(b.min) && geom::is_finite(b.max)))
        {
            return Err(RenderError::Invalid {
                what: "geometry",
                reason: "a primitive has non-finite coordinates".into(),
            });
        }
        let bvh = Bvh::build(&bounds);
        let slots: Vec<Slot> = bvh
            .order
            .iter()
            .map(|&i| {
                let p = &prims[i as usize];
                Slot {
                    prim: i,
                    layer: p.layer,
                    triangle: matches!(p.shape, Shape::Triangle { .. }),
                }
            })
            .collect();
        let lanes = TriLanes::new(bvh.order.iter().map(|&i| match prims[i as usize].shape {
            Shape::Triangle { v } => (v[0], geom::sub(v[1], v[0]), geom::sub(v[2], v[0])),
            _ => ([0.0; 3], [0.0; 3], [0.0; 3]),
        }));
        let mut lists: [Vec<u32>; 8] = Default::default();
        for (i, p) in prims.iter().enumerate() {
            for (b, l) in lists.iter_mut().enumerate() {
                if p.layer & (1 << b) != 0 && l.len() <= FEW {
                    l.push(i as u32);
                }
            }
        }
        let few_bits = (0..8)
            .filter(|&b| lists[b].len() <= FEW)
            .fold(0u8, |m, b| m | (1 << b));
        // Each mask's list, class by class in bit order (a primitive in several of the mask's
        // classes repeats, which leaves a nearest or any hit unchanged), made once here
        // instead of chained per ray.
        let few_lists = (0..=255u8)
            .map(|m| {
                if m & !few_bits != 0 {
                    return Vec::new();
                }
                (0..8)
                    .filter(|b| m & (1 << b) != 0)
                    .flat_map(|b| lists[b].iter().copied())
                    .collect()
            })
            .collect();
        Ok(Scene {
            prims,
            materials,
            bvh,
            slots,
            lanes,
            few: (few_lists, few_bits),
            light,
            cornea_index,
            pupil_bound: None,
            shading: Vec::new(),
        })
    }

    /// Nearest hit among primitives whose class bit is in `mask`.
    #[inline]
    pub fn closest(&self, ray: &Ray, t_max: f64, mask: u8) -> Option<Hit> {
        if self.is_few(mask) {
            let mut best = None;
            let mut t_best = t_max;
            for i in self.few_prims(mask) {
                if let Some(t) = self.prims[i as usize].shape.intersect(ray, t_best) {
                    best = Some(Hit { t, prim: i });
                    t_best = t;
                }
            }
            return best;
        }
        self.bvh
            .closest(
                ray,
                t_max,
                #[inline(always)]
                |first, count, tm| self.leaf_hit::<false>(first, count, ray, tm, mask),
            )
            .map(|(s, t)| Hit {
                t,
                prim: self.slots[s as usize].prim,
            })
    }

    /// True when a primitive in `mask` blocks the ray before `t_max`.
    #[inline]
    pub fn occluded(&self, ray: &Ray, t_max: f64, mask: u8) -> bool {
        if self.is_few(mask) {
            return self
                .few_prims(mask)
                .any(|i| self.prims[i as usize].shape.intersect(ray, t_max).is_some());
        }
        self.bvh.any(
            ray,
            t_max,
            #[inline(always)]
            |first, count, tm| self.leaf_hit::<true>(first, count, ray, tm, mask).is_some(),
        )
    }

    /// True when every class bit of `mask` holds at most [`FEW`] primitives.
    #[inline]
    fn is_few(&self, mask: u8) -> bool {
        mask & !self.few.1 == 0
    }

    /// The primitives of the classes in `mask` (`mask` passes [`Scene::is_few`]).
    #[inline]
    fn few_prims(&self, mask: u8) -> impl Iterator<Item = u32> + '_ {
        self.few.0[mask as usize].iter().copied()
    }

    /// Nearest hit below `t_max` among slots `first .. first + count` whose class bit is in
    /// `mask` (the lowest slot on a tie), as (slot, distance); with `ANY`, the first hit
    /// found instead. Triangles are tested four at a time ([`TriLanes::hit4`]); the
    /// lanes are then taken in slot order, as a one-by-one scan would.
    #[inline(always)]
    fn leaf_hit<const ANY: bool>(
        &self,
        first: u32,
        count: u32,
        ray: &Ray,
        t_max: f64,
        mask: u8,
    ) -> Option<(u32, f64)> {
        let mut best = None;
        let mut t_best = t_max;
        let end = (first + count) as usize;
        for base in (first as usize..end).step_by(LANES) {
            let (met, t) = self.lanes.hit4(base, ray);
            for (l, sl) in self.slots[base..end.min(base + LANES)].iter().enumerate() {
                if sl.layer & mask == 0 {
                    continue;
                }
                let h = if sl.triangle {
                    (met & (1 << l) != 0 && t[l] < t_best).then_some(t[l])
                } else {
                    self.prims[sl.prim as usize].shape.intersect(ray, t_best)
                };
                if let Some(th) = h {
                    best = Some(((base + l) as u32, th));
                    if ANY {
                        return best;
                    }
                    t_best = th;
                }
            }
        }
        best
    }

    /// Material of primitive `prim`.
    #[inline]
    pub fn material(&self, prim: u32) -> &Material {
        &self.materials[self.prims[prim as usize].material as usize]
    }

    /// Smooth-shading normal at point `p` on primitive `prim` (unit, not oriented): the vertex
    /// normals interpolated barycentrically, or `None` where the primitive has none.
    #[inline]
    pub fn shading_normal(&self, prim: u32, p: Vec3) -> Option<Vec3> {
        let ns = (*self.shading.get(prim as usize)?)?;
        let Shape::Triangle { v } = self.prims[prim as usize].shape else {
            return None;
        };
        let (e1, e2, d) = (
            geom::sub(v[1], v[0]),
            geom::sub(v[2], v[0]),
            geom::sub(p, v[0]),
        );
        let (d00, d01, d11) = (geom::dot(e1, e1), geom::dot(e1, e2), geom::dot(e2, e2));
        let (d20, d21) = (geom::dot(d, e1), geom::dot(d, e2));
        let den = d00 * d11 - d01 * d01;
        let (b1, b2) = ((d11 * d20 - d01 * d21) / den, (d00 * d21 - d01 * d20) / den);
        // A zero-area triangle or a non-finite point or triangle has no barycentrics (and
        // `clamp` panics on a NaN bound).
        if den <= 0.0 || !(b1.is_finite() && b2.is_finite()) {
            return None;
        }
        let b1 = b1.clamp(0.0, 1.0);
        let b2 = b2.clamp(0.0, 1.0 - b1);
        let b0 = 1.0 - b1 - b2;
        let n = geom::add(
            geom::add(geom::scale(ns[0], b0), geom::scale(ns[1], b1)),
            geom::scale(ns[2], b2),
        );
        let len = geom::norm(n);
        (len > 0.0).then(|| geom::scale(n, 1.0 / len))
    }

    /// Distance (m) at which `ray` meets the emitter sphere, if it does before `t_max`.
    #[inline]
    pub fn light_hit(&self, ray: &Ray, t_max: f64) -> Option<f64> {
        Shape::Sphere {
            center: self.light.position_m,
            radius_m: self.light.radius_m,
            clip: Clip::None,
        }
        .intersect(ray, t_max)
        .filter(|t| *t > T_EPS)
    }
}

/// Layer bit for a material class.
pub fn layer_of(kind: MaterialKind) -> u8 {
    match kind {
        MaterialKind::Skin | MaterialKind::Lash => LAYER_SKIN,
        MaterialKind::Cornea => LAYER_CORNEA,
        _ => LAYER_EYE,
    }
}

/// Per-subject appearance and anatomy (SI units, angles in rad about the eye's rotation
/// centre), drawn from a seed or set by hand. Ranges and sources: docs/renderer.md.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Subject {
    /// Cornea front radius (m), ≈7.8 mm.
    pub cornea_radius_m: f64,
    /// Corneal apex distance from the rotation centre (m), ≈13.3 mm.
    pub cornea_apex_m: f64,
    /// Cornea refractive index, ≈1.376.
    pub cornea_index: f64,
    /// Pupil diameter (m), 2–8 mm.
    pub pupil_diameter_m: f64,
    /// NIR albedo of the skin at 940 nm.
    pub skin_albedo: f64,
    /// Relative amplitude of the skin's micro-texture (0–0.5).
    pub skin_texture: f64,
    /// NIR albedo of the sclera.
    pub sclera_albedo: f64,
    /// Mean NIR albedo of the iris.
    pub iris_albedo: f64,
    /// NIR albedo of the pupil (the dark fundus seen off-axis).
    pub pupil_albedo: f64,
    /// NIR albedo of the eyelashes.
    pub lash_albedo: f64,
    /// Iris fibre frequencies (cycles per turn) and phases (rad).
    pub iris_freq: [f64; 3],
    /// Iris fibre phases (rad).
    pub iris_phase: [f64; 3],
    /// Iris texture contrast (0–1).
    pub iris_contrast: f64,
    /// Azimuth of the palpebral fissure's centre at primary gaze (rad, + nasal).
    pub fissure_center_az_rad: f64,
    /// Elevation of the fissure's centre at primary gaze (rad).
    pub fissure_center_el_rad: f64,
    /// Angular half length of the fissure towards the medial canthus (rad).
    pub fissure_medial_rad: f64,
    /// Angular half length towards the lateral canthus (rad).
    pub fissure_lateral_rad: f64,
    /// Angular height of the upper lid margin above the fissure's centre (rad).
    pub fissure_upper_rad: f64,
    /// Angular depth of the lower lid margin below the centre (rad).
    pub fissure_lower_rad: f64,
    /// Superellipse exponent of the margins (2: ellipse; 1.5: almond with pointed canthi).
    pub fissure_exponent: f64,
    /// Canthal tilt (rad): positive raises the lateral canthus.
    pub canthal_tilt_rad: f64,
    /// Upper-lid crease: angular distance above the margin (rad; 0 = no crease).
    pub crease_rad: f64,
    /// Depth of the crease (m).
    pub crease_depth_m: f64,
    /// Epicanthic fold (0–1): shortens the fissure medially and hides the caruncle.
    pub epicanthus: f64,
    /// Forward relief of the brow ridge (m).
    pub brow_m: f64,
    /// Forward relief of the cheek (m).
    pub cheek_m: f64,
    /// Forward relief of the side of the nose (m).
    pub nose_m: f64,
    /// Caruncle radius (m).
    pub caruncle_radius_m: f64,
    /// Upper eyelashes.
    pub lashes_upper: u32,
    /// Lower eyelashes.
    pub lashes_lower: u32,
    /// Upper lash length (m).
    pub lash_length_upper_m: f64,
    /// Lower lash length (m).
    pub lash_length_lower_m: f64,
    /// Lash width at the root (m); tapers to 30 % at the tip.
    pub lash_width_m: f64,
    /// Seed of the lash layout and of the skin texture.
    pub lash_seed: u64,
    /// How far (m) the lid margin stands off the globe at the medial canthus, where the
    /// caruncle and the plica fill the space between the canthus and the eyeball.
    #[serde(default = "default_lift_medial")]
    pub canthus_lift_medial_m: f64,
    /// How far (m) the lid margin stands off the globe at the lateral canthus.
    #[serde(default = "default_lift_lateral")]
    pub canthus_lift_lateral_m: f64,
}

fn default_lift_medial() -> f64 {
    Subject::default().canthus_lift_medial_m
}

fn default_lift_lateral() -> f64 {
    Subject::default().canthus_lift_lateral_m
}

impl Default for Subject {
    /// The average eye of oracles.md (7.8 mm cornea, apex 13.3 mm, n = 1.376, 4 mm pupil) in a
    /// typical eye region.
    fn default() -> Self {
        Subject {
            cornea_radius_m: 7.8e-3,
            cornea_apex_m: 13.3e-3,
            cornea_index: 1.376,
            pupil_diameter_m: 4e-3,
            skin_albedo: 0.5,
            skin_texture: 0.12,
            sclera_albedo: 0.6,
            iris_albedo: 0.3,
            pupil_albedo: 0.02,
            lash_albedo: 0.1,
            iris_freq: [17.0, 29.0, 43.0],
            iris_phase: [0.0, 1.0, 2.0],
            iris_contrast: 0.5,
            fissure_center_az_rad: 0.0,
            fissure_center_el_rad: -0.03,
            fissure_medial_rad: 1.15,
            fissure_lateral_rad: 1.25,
            fissure_upper_rad: 0.38,
            fissure_lower_rad: 0.42,
            fissure_exponent: 1.7,
            canthal_tilt_rad: 0.07,
            crease_rad: 0.3,
            crease_depth_m: 0.6e-3,
            epicanthus: 0.0,
            brow_m: 6e-3,
            cheek_m: 3e-3,
            nose_m: 8e-3,
            caruncle_radius_m: 1.3e-3,
            lashes_upper: 120,
            lashes_lower: 55,
            lash_length_upper_m: 9.5e-3,
            lash_length_lower_m: 6.5e-3,
            lash_width_m: 0.09e-3,
            lash_seed: 0,
            canthus_lift_medial_m: 4e-3,
            canthus_lift_lateral_m: 2e-3,
        }
    }
}

impl Subject {
    /// A subject drawn from `seed` over the documented ranges (docs/renderer.md): cornea
    /// radius 7.6–8.0 mm, pupil 3–6 mm, NIR albedos, fissure size, shape and tilt, crease
    /// (absent for 30 %), epicanthic fold (40 %), facial relief, lash count and length.
    pub fn from_seed(seed: u64) -> Subject {
        let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x005E_ED0F_EE1D);
        let d = Subject::default();
        let mut u = |lo: f64, hi: f64| lo + (hi - lo) * rng.random::<f64>();
        let mut s = Subject {
            cornea_radius_m: u(7.6e-3, 8.0e-3),
            pupil_diameter_m: u(3e-3, 6e-3),
            skin_albedo: u(0.35, 0.6),
            skin_texture: u(0.06, 0.2),
            sclera_albedo: u(0.45, 0.65),
            iris_albedo: u(0.2, 0.4),
            lash_albedo: u(0.06, 0.14),
            iris_contrast: u(0.3, 0.7),
            fissure_center_az_rad: u(-0.05, 0.05),
            fissure_center_el_rad: u(-0.08, 0.02),
            fissure_medial_rad: u(1.05, 1.22),
            fissure_lateral_rad: u(1.15, 1.32),
            fissure_upper_rad: u(0.3, 0.45),
            fissure_lower_rad: u(0.36, 0.48),
            fissure_exponent: u(1.5, 2.0),
            canthal_tilt_rad: u(-0.02, 0.15),
            crease_depth_m: u(0.3e-3, 0.9e-3),
            brow_m: u(4e-3, 9e-3),
            cheek_m: u(1.5e-3, 5e-3),
            nose_m: u(5e-3, 12e-3),
            caruncle_radius_m: u(1.0e-3, 1.6e-3),
            lash_length_upper_m: u(8e-3, 11e-3),
            lash_length_lower_m: u(5e-3, 7.5e-3),
            lash_width_m: u(0.07e-3, 0.11e-3),
            ..d
        };
        s.crease_rad = if u(0.0, 1.0) < 0.3 { 0.0 } else { u(0.2, 0.4) };
        s.epicanthus = if u(0.0, 1.0) < 0.6 { 0.0 } else { u(0.2, 1.0) };
        s.fissure_medial_rad -= 0.2 * s.epicanthus;
        s.lashes_upper = u(90.0, 160.0).round() as u32;
        s.lashes_lower = u(40.0, 70.0).round() as u32;
        for k in 0..3 {
            s.iris_freq[k] = (11.0 + 40.0 * rng.random::<f64>()).round();
            s.iris_phase[k] = std::f64::consts::TAU * rng.random::<f64>();
        }
        s.lash_seed = rng.random::<u64>();
        // Drawn last so that every earlier field keeps the value it had before these existed.
        s.canthus_lift_medial_m = 3e-3 + 2e-3 * rng.random::<f64>();
        s.canthus_lift_lateral_m = 1.5e-3 + 1.5e-3 * rng.random::<f64>();
        s
    }
}

/// Eye geometry implied by a rig and a subject (m, eye frame at primary gaze).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct EyeGeometry {
    /// Distance of the iris/pupil plane from the rotation centre (the rig's pupil sphere).
    pub pupil_plane_m: f64,
    /// Distance of the cornea sphere's centre from the rotation centre.
    pub cornea_center_m: f64,
    /// Cornea radius.
    pub cornea_radius_m: f64,
    /// Limbus radius: where the cornea meets the iris plane.
    pub limbus_radius_m: f64,
    /// Eyeball (sclera) radius, chosen so the sclera meets the cornea at the limbus.
    pub eyeball_radius_m: f64,
    /// Pupil radius.
    pub pupil_radius_m: f64,
}

impl EyeGeometry {
    /// Derives and checks the geometry.
    pub fn new(rig: &Rig, s: &Subject) -> Result<EyeGeometry, RenderError> {
        let bad = |what: &'static str, reason: String| Err(RenderError::Invalid { what, reason });
        let d = rig.pupil_sphere_radius_m;
        if !(s.cornea_radius_m.is_finite() && s.cornea_radius_m > 0.0) {
            return bad("subject.cornea_radius_m", format!("{}", s.cornea_radius_m));
        }
        if !(s.cornea_apex_m.is_finite() && s.cornea_apex_m > d) {
            return bad(
                "subject.cornea_apex_m",
                format!(
                    "{} must lie beyond the pupil plane at {d} m",
                    s.cornea_apex_m
                ),
            );
        }
        if !(s.cornea_index.is_finite() && (1.0..3.0).contains(&s.cornea_index)) {
            return bad(
                "subject.cornea_index",
                format!("{} outside [1, 3)", s.cornea_index),
            );
        }
        let c = s.cornea_apex_m - s.cornea_radius_m;
        let h = d - c;
        if h.is_nan() || h.abs() >= s.cornea_radius_m {
            return bad(
                "subject.cornea_radius_m",
                format!("cornea sphere does not reach the pupil plane (centre {c} m, plane {d} m)"),
            );
        }
        let r_l = (s.cornea_radius_m * s.cornea_radius_m - h * h).sqrt();
        let r_p = 0.5 * s.pupil_diameter_m;
        if !(r_p.is_finite() && r_p > 0.0 && r_p < 0.95 * r_l) {
            return bad(
                "subject.pupil_diameter_m",
                format!(
                    "{} must be positive and smaller than the limbus diameter {}",
                    s.pupil_diameter_m,
                    2.0 * r_l
                ),
            );
        }
        for (what, v) in [
            ("subject.skin_albedo", s.skin_albedo),
            ("subject.sclera_albedo", s.sclera_albedo),
            ("subject.iris_albedo", s.iris_albedo),
            ("subject.pupil_albedo", s.pupil_albedo),
            ("subject.lash_albedo", s.lash_albedo),
        ] {
            if !(0.0..=1.0).contains(&v) {
                return bad(what, format!("albedo {v} outside [0, 1]"));
            }
        }
        validate_face(s)?;
        Ok(EyeGeometry {
            pupil_plane_m: d,
            cornea_center_m: c,
            cornea_radius_m: s.cornea_radius_m,
            limbus_radius_m: r_l,
            eyeball_radius_m: (d * d + r_l * r_l).sqrt(),
            pupil_radius_m: r_p,
        })
    }
}

/// Checks the eye-region parameters of a subject against their documented ranges (wide enough
/// for any plausible face, tight enough that the mesh stays a proper surface).
fn validate_face(s: &Subject) -> Result<(), RenderError> {
    let checks: [(&'static str, f64, f64, f64); 19] = [
        ("subject.skin_texture", s.skin_texture, 0.0, 0.5),
        (
            "subject.fissure_center_az_rad",
            s.fissure_center_az_rad,
            -0.3,
            0.3,
        ),
        (
            "subject.fissure_center_el_rad",
            s.fissure_center_el_rad,
            -0.3,
            0.3,
        ),
        ("subject.fissure_medial_rad", s.fissure_medial_rad, 0.5, 1.4),
        (
            "subject.fissure_lateral_rad",
            s.fissure_lateral_rad,
            0.5,
            1.4,
        ),
        ("subject.fissure_upper_rad", s.fissure_upper_rad, 0.05, 0.8),
        ("subject.fissure_lower_rad", s.fissure_lower_rad, 0.05, 0.8),
        ("subject.fissure_exponent", s.fissure_exponent, 1.2, 4.0),
        ("subject.canthal_tilt_rad", s.canthal_tilt_rad, -0.4, 0.4),
        ("subject.crease_rad", s.crease_rad, 0.0, 0.8),
        ("subject.crease_depth_m", s.crease_depth_m, 0.0, 2e-3),
        ("subject.epicanthus", s.epicanthus, 0.0, 1.0),
        ("subject.brow_m", s.brow_m, 0.0, 20e-3),
        ("subject.cheek_m", s.cheek_m, 0.0, 10e-3),
        ("subject.nose_m", s.nose_m, 0.0, 25e-3),
        ("subject.caruncle_radius_m", s.caruncle_radius_m, 0.0, 3e-3),
        ("subject.lash_width_m", s.lash_width_m, 0.0, 0.5e-3),
        (
            "subject.canthus_lift_medial_m",
            s.canthus_lift_medial_m,
            0.0,
            6e-3,
        ),
        (
            "subject.canthus_lift_lateral_m",
            s.canthus_lift_lateral_m,
            0.0,
            6e-3,
        ),
    ];
    for (what, v, lo, hi) in checks {
        if !(lo..=hi).contains(&v) {
            return Err(RenderError::Invalid {
                what,
                reason: format!("{v} outside [{lo}, {hi}]"),
            });
        }
    }
    for (what, v) in [
        ("subject.lash_length_upper_m", s.lash_length_upper_m),
        ("subject.lash_length_lower_m", s.lash_length_lower_m),
    ] {
        if v.is_nan() || v <= 0.0 || v > 20e-3 {
            return Err(RenderError::Invalid {
                what,
                reason: format!("{v} outside (0, 0.02] m"),
            });
        }
    }
    for (what, v) in [
        ("subject.lashes_upper", s.lashes_upper),
        ("subject.lashes_lower", s.lashes_lower),
    ] {
        if v > 1000 {
            return Err(RenderError::Invalid {
                what,
                reason: format!("{v} lashes: at most 1000"),
            });
        }
    }
    Ok(())
}

/// Material slots of the procedural scene.
const M_SCLERA: u16 = 0;
const M_CORNEA: u16 = 1;
const M_IRIS: u16 = 2;
const M_PUPIL: u16 = 3;
const M_SKIN: u16 = 4;
const M_MARGIN: u16 = 5;
const M_LASH: u16 = 6;
const M_CARUNCLE: u16 = 7;

/// Names of the procedural scene's materials (glTF export; each maps back onto its class
/// through [`MaterialKind::from_name`]).
pub const MATERIAL_NAMES: [&str; 8] = [
    "sclera",
    "cornea",
    "iris",
    "pupil",
    "skin",
    "skin_lid_margin",
    "lash",
    "skin_caruncle",
];

/// The procedural scene split the way a file stores it: the eye's parts at primary gaze (they
/// rotate with the eye), the face posed for the state, and the materials.
#[derive(Debug, Clone)]
pub struct ProceduralParts {
    /// Eye parts (sclera, cornea, iris, pupil) at primary gaze (m).
    pub eye_rest: Vec<Prim>,
    /// Face parts (skin, lid margins, lashes, caruncle) posed for the state (m).
    pub face: Vec<Prim>,
    /// Smooth-shading vertex normals of the face parts, indexed like `face` (see
    /// [`Scene::shading`]).
    pub face_shading: Vec<Option<[Vec3; 3]>>,
    /// Materials, indexed by `Prim::material`; names in [`MATERIAL_NAMES`].
    pub materials: Vec<Material>,
    /// The eye's rotation in the state.
    pub rotation: Mat3,
    /// The posed fissure.
    pub fissure: face::Fissure,
    /// The eye geometry the parts were built from.
    pub geometry: EyeGeometry,
}

/// Rotates an eye part about the rotation centre.
pub fn rotate_shape(shape: &Shape, r: &Mat3) -> Shape {
    let rot = |p: Vec3| geom::mul_mv(r, p);
    match *shape {
        Shape::Sphere {
            center,
            radius_m,
            clip,
        } => Shape::Sphere {
            center: rot(center),
            radius_m,
            clip: match clip {
                Clip::None => Clip::None,
                Clip::Plane {
                    normal,
                    offset_m,
                    sign,
                } => Clip::Plane {
                    normal: rot(normal),
                    offset_m,
                    sign,
                },
            },
        },
        Shape::Disc {
            center,
            normal,
            r_in_m,
            r_out_m,
        } => Shape::Disc {
            center: rot(center),
            normal: rot(normal),
            r_in_m,
            r_out_m,
        },
        Shape::Triangle { v } => Shape::Triangle { v: v.map(rot) },
    }
}

/// The procedural right-eye region for `state`, split into rest-pose eye and posed face.
pub fn procedural_parts(
    rig: &Rig,
    state: &State,
    subject: &Subject,
) -> Result<ProceduralParts, RenderError> {
    let g = EyeGeometry::new(rig, subject)?;
    let half_pi = std::f64::consts::FRAC_PI_2;
    for (what, v, limit) in [
        ("state.azimuth_rad", state.azimuth_rad, half_pi),
        ("state.elevation_rad", state.elevation_rad, half_pi),
        ("state.torsion_rad", state.torsion_rad, half_pi),
    ] {
        if v.is_nan() || v.abs() >= limit {
            return Err(RenderError::Invalid {
                what,
                reason: format!("{v} outside (−{limit}, {limit})"),
            });
        }
    }
    // Vectors by their length, shown with the components given (a length of 1e300² printed
    // as `inf`).
    for (what, v, limit) in [
        ("state.slip_m", state.slip_m, 0.1),
        ("state.cam_rot_rad", state.cam_rot_rad, std::f64::consts::PI),
    ] {
        let n = geom::norm(v);
        if n.is_nan() || n >= limit {
            return Err(RenderError::Invalid {
                what,
                reason: format!("{v:?} has length {n}, not below {limit}"),
            });
        }
    }
    if !(state.lid_closure.is_finite() && (0.0..=1.0).contains(&state.lid_closure)) {
        return Err(RenderError::Invalid {
            what: "state.lid_closure",
            reason: format!("{} outside [0, 1]", state.lid_closure),
        });
    }
    let r: Mat3 = state.eye_rotation()?;
    let axis = |k: usize| [r[0][k], r[1][k], r[2][k]];
    let (u, v, gz) = (axis(0), axis(1), axis(2));
    let z = [0.0, 0.0, 1.0];
    let iris_center = geom::scale(gz, g.pupil_plane_m);
    let skin_tex = Some(SkinTexture {
        seed: subject.lash_seed,
        amplitude: subject.skin_texture,
    });
    let wet = |kind, albedo| Material {
        coat_index: TEAR_FILM_INDEX,
        ..Material::lambertian(kind, albedo)
    };
    let materials = vec![
        wet(MaterialKind::Sclera, subject.sclera_albedo),
        Material::lambertian(MaterialKind::Cornea, 0.0),
        Material {
            iris: Some(IrisTexture {
                center: iris_center,
                u,
                v,
                r_pupil_m: g.pupil_radius_m,
                r_limbus_m: g.limbus_radius_m,
                freq: subject.iris_freq,
                phase: subject.iris_phase,
                contrast: subject.iris_contrast,
            }),
            ..Material::lambertian(MaterialKind::Iris, subject.iris_albedo)
        },
        Material::lambertian(MaterialKind::Pupil, subject.pupil_albedo),
        Material {
            skin: skin_tex,
            ..Material::lambertian(MaterialKind::Skin, subject.skin_albedo)
        },
        wet(MaterialKind::Skin, 0.9 * subject.skin_albedo),
        Material::lambertian(MaterialKind::Lash, subject.lash_albedo),
        wet(MaterialKind::Skin, 0.8 * subject.skin_albedo),
    ];
    let iris_rest = geom::scale(z, g.pupil_plane_m);
    let eye_rest = vec![
        Prim {
            shape: Shape::Sphere {
                center: [0.0; 3],
                radius_m: g.eyeball_radius_m,
                clip: Clip::Plane {
                    normal: z,
                    offset_m: g.pupil_plane_m,
                    sign: -1.0,
                },
            },
            material: M_SCLERA,
            layer: LAYER_EYE,
        },
        Prim {
            shape: Shape::Sphere {
                center: geom::scale(z, g.cornea_center_m),
                radius_m: g.cornea_radius_m,
                clip: Clip::Plane {
                    normal: z,
                    offset_m: g.pupil_plane_m,
                    sign: 1.0,
                },
            },
            material: M_CORNEA,
            layer: LAYER_CORNEA,
        },
        Prim {
            shape: Shape::Disc {
                center: iris_rest,
                normal: z,
                r_in_m: g.pupil_radius_m,
                r_out_m: g.limbus_radius_m,
            },
            material: M_IRIS,
            layer: LAYER_EYE,
        },
        Prim {
            shape: Shape::Disc {
                center: iris_rest,
                normal: z,
                r_in_m: 0.0,
                r_out_m: g.pupil_radius_m,
            },
            material: M_PUPIL,
            layer: LAYER_EYE,
        },
    ];
    let Face {
        triangles,
        mut shading,
        caruncle,
        fissure,
        ..
    } = face::face(&g, subject, state, gz);
    let mut face_prims: Vec<Prim> = triangles
        .into_iter()
        .map(|(v, part)| Prim {
            shape: Shape::Triangle { v },
            material: match part {
                FacePart::Skin => M_SKIN,
                FacePart::Margin => M_MARGIN,
                FacePart::Lash => M_LASH,
            },
            layer: LAYER_SKIN,
        })
        .collect();
    if caruncle.1 > 0.0 {
        face_prims.push(Prim {
            shape: Shape::Sphere {
                center: caruncle.0,
                radius_m: caruncle.1,
                clip: Clip::None,
            },
            material: M_CARUNCLE,
            layer: LAYER_SKIN,
        });
        shading.push(None);
    }
    Ok(ProceduralParts {
        eye_rest,
        face: face_prims,
        face_shading: shading,
        materials,
        rotation: r,
        fissure,
        geometry: g,
    })
}

/// The procedural right-eye region for `state`: eyeball, cornea, iris, pupil (rotated by the
/// state's eye rotation), lids that follow the eye and close with `state.lid_closure`, lashes,
/// caruncle and the periocular skin (docs/renderer.md); the illuminator `light`.
pub fn procedural_scene(
    rig: &Rig,
    state: &State,
    subject: &Subject,
    light: Light,
) -> Result<Scene, RenderError> {
    let parts = procedural_parts(rig, state, subject)?;
    let (r, g) = (parts.rotation, parts.geometry);
    let shading = std::iter::repeat_n(None, parts.eye_rest.len())
        .chain(parts.face_shading)
        .collect();
    let prims = parts
        .eye_rest
        .iter()
        .map(|p| Prim {
            shape: rotate_shape(&p.shape, &r),
            ..*p
        })
        .chain(parts.face)
        .collect();
    let mut scene = Scene::new(prims, parts.materials, light, subject.cornea_index)?;
    scene.shading = shading;
    // The pupil disc lies inside the cornea's sphere (its rim, the limbus, is on it), so a ray
    // that misses the sphere cannot reach the pupil.
    let gz = [r[0][2], r[1][2], r[2][2]];
    scene.pupil_bound = Some((
        geom::scale(gz, g.cornea_center_m),
        g.cornea_radius_m * (1.0 + 1e-9),
    ));
    Ok(scene)
}

//! Scenes: primitives + materials + BVH + illuminator; the procedural right-eye region.

use super::bvh::Bvh;
use super::material::{IrisTexture, Material, MaterialKind};
use super::prim::{Aperture, Clip, Shape, T_EPS};
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

/// The NIR illuminator: a small spherical emitter (m, W/sr).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Light {
    /// Centre (m, world).
    pub position_m: Vec3,
    /// Emitter radius (m): sets the glint size and the shadow penumbra.
    pub radius_m: f64,
    /// Radiant intensity (W/sr) towards the eye.
    pub intensity_w_per_sr: f64,
}

impl Light {
    /// The default illuminator for a camera pose: 4 mm along the camera's +x axis, 0.5 mm
    /// radius, 1 mW/sr (≈0.14 mW/cm² at 27 mm, far below the 10 mW/cm² IEC 62471 exempt limit).
    pub fn near_camera(pose: &Pose) -> Light {
        let x = [
            pose.rotation[0][0],
            pose.rotation[1][0],
            pose.rotation[2][0],
        ];
        Light {
            position_m: geom::add(pose.position, geom::scale(x, 4e-3)),
            radius_m: 0.5e-3,
            intensity_w_per_sr: 1e-3,
        }
    }

    /// Emitted radiance (W/(m²·sr)) of the emitter's disc as seen from anywhere.
    pub fn radiance(&self) -> f64 {
        self.intensity_w_per_sr / (std::f64::consts::PI * self.radius_m * self.radius_m)
    }

    fn validate(&self) -> Result<(), RenderError> {
        if !(geom::is_finite(self.position_m)
            && self.radius_m.is_finite()
            && self.radius_m > 0.0
            && self.intensity_w_per_sr.is_finite()
            && self.intensity_w_per_sr >= 0.0)
        {
            return Err(RenderError::Invalid {
                what: "light",
                reason: format!("{self:?}: position finite, radius > 0, intensity ≥ 0 required"),
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
    /// Illuminator.
    pub light: Light,
    /// Refractive index of the cornea (and the aqueous behind it).
    pub cornea_index: f64,
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
        Ok(Scene {
            prims,
            materials,
            bvh,
            light,
            cornea_index,
        })
    }

    /// Nearest hit among primitives whose class bit is in `mask`.
    #[inline]
    pub fn closest(&self, ray: &Ray, t_max: f64, mask: u8) -> Option<Hit> {
        self.bvh
            .closest(ray, t_max, |i, tm| {
                let p = &self.prims[i as usize];
                if p.layer & mask == 0 {
                    return None;
                }
                p.shape.intersect(ray, tm)
            })
            .map(|(prim, t)| Hit { t, prim })
    }

    /// True when a primitive in `mask` blocks the ray before `t_max`.
    #[inline]
    pub fn occluded(&self, ray: &Ray, t_max: f64, mask: u8) -> bool {
        self.bvh.any(ray, t_max, |i, tm| {
            let p = &self.prims[i as usize];
            if p.layer & mask == 0 {
                return None;
            }
            p.shape.intersect(ray, tm)
        })
    }

    /// Material of primitive `prim`.
    #[inline]
    pub fn material(&self, prim: u32) -> &Material {
        &self.materials[self.prims[prim as usize].material as usize]
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
        MaterialKind::Skin => LAYER_SKIN,
        MaterialKind::Cornea => LAYER_CORNEA,
        _ => LAYER_EYE,
    }
}

/// Per-subject appearance and anatomy (SI units), drawn from a seed or set by hand.
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
    /// NIR albedo of the skin.
    pub skin_albedo: f64,
    /// NIR albedo of the sclera.
    pub sclera_albedo: f64,
    /// Mean NIR albedo of the iris.
    pub iris_albedo: f64,
    /// NIR albedo of the pupil (the dark fundus seen off-axis).
    pub pupil_albedo: f64,
    /// Iris fibre frequencies (cycles per turn) and phases (rad).
    pub iris_freq: [f64; 3],
    /// Iris fibre phases (rad).
    pub iris_phase: [f64; 3],
    /// Iris texture contrast (0–1).
    pub iris_contrast: f64,
    /// Upper lid margin elevation at primary gaze (rad above the eye centre).
    pub lid_upper_rad: f64,
    /// Lower lid margin elevation at primary gaze (rad, negative).
    pub lid_lower_rad: f64,
    /// Half width of the palpebral fissure in azimuth (rad).
    pub lid_half_width_rad: f64,
    /// Fraction of the eye's elevation the upper lid follows.
    pub lid_upper_follow: f64,
    /// Fraction of the eye's elevation the lower lid follows.
    pub lid_lower_follow: f64,
}

impl Default for Subject {
    /// The average eye of oracles.md: 7.8 mm cornea, apex 13.3 mm, n = 1.376, 4 mm pupil.
    fn default() -> Self {
        Subject {
            cornea_radius_m: 7.8e-3,
            cornea_apex_m: 13.3e-3,
            cornea_index: 1.376,
            pupil_diameter_m: 4e-3,
            skin_albedo: 0.5,
            sclera_albedo: 0.65,
            iris_albedo: 0.3,
            pupil_albedo: 0.02,
            iris_freq: [17.0, 29.0, 43.0],
            iris_phase: [0.0, 1.0, 2.0],
            iris_contrast: 0.5,
            lid_upper_rad: 26f64.to_radians(),
            lid_lower_rad: -22f64.to_radians(),
            lid_half_width_rad: 55f64.to_radians(),
            lid_upper_follow: 0.8,
            lid_lower_follow: 0.4,
        }
    }
}

impl Subject {
    /// A subject drawn from `seed`: cornea radius 7.6–8.0 mm, pupil 3–6 mm, albedos and lid
    /// aperture within ±20 % of the defaults, a random iris texture.
    pub fn from_seed(seed: u64) -> Subject {
        let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x005E_ED0F_EE1D);
        let d = Subject::default();
        let mut j = |x: f64, rel: f64| x * (1.0 + rel * (2.0 * rng.random::<f64>() - 1.0));
        let mut s = Subject {
            cornea_radius_m: j(7.8e-3, 0.025),
            pupil_diameter_m: j(4.5e-3, 1.5 / 4.5),
            skin_albedo: j(d.skin_albedo, 0.2),
            sclera_albedo: j(d.sclera_albedo, 0.15),
            iris_albedo: j(d.iris_albedo, 0.3),
            iris_contrast: j(d.iris_contrast, 0.4),
            lid_upper_rad: j(d.lid_upper_rad, 0.15),
            lid_lower_rad: j(d.lid_lower_rad, 0.15),
            lid_half_width_rad: j(d.lid_half_width_rad, 0.1),
            ..d
        };
        for k in 0..3 {
            s.iris_freq[k] = (11.0 + 40.0 * rng.random::<f64>()).round();
            s.iris_phase[k] = std::f64::consts::TAU * rng.random::<f64>();
        }
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
    /// Radius of the lid/skin shell about the rotation centre (just clears the apex).
    pub lid_radius_m: f64,
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
        ] {
            if !(0.0..=1.0).contains(&v) {
                return bad(what, format!("albedo {v} outside [0, 1]"));
            }
        }
        Ok(EyeGeometry {
            pupil_plane_m: d,
            cornea_center_m: c,
            cornea_radius_m: s.cornea_radius_m,
            limbus_radius_m: r_l,
            eyeball_radius_m: (d * d + r_l * r_l).sqrt(),
            pupil_radius_m: r_p,
            lid_radius_m: s.cornea_apex_m + 0.4e-3,
        })
    }
}

/// The procedural right-eye region for `state`: eyeball, cornea, iris, pupil (rotated by the
/// state's eye rotation), lids that follow elevation, and the periocular skin plane; the
/// illuminator `light`.
pub fn procedural_scene(
    rig: &Rig,
    state: &State,
    subject: &Subject,
    light: Light,
) -> Result<Scene, RenderError> {
    let g = EyeGeometry::new(rig, subject)?;
    let r: Mat3 = state.eye_rotation()?;
    let axis = |k: usize| [r[0][k], r[1][k], r[2][k]];
    let (u, v, gz) = (axis(0), axis(1), axis(2));
    let mat = |kind, albedo| Material {
        kind,
        albedo,
        iris: None,
    };
    let iris_center = geom::scale(gz, g.pupil_plane_m);
    let materials = vec![
        mat(MaterialKind::Sclera, subject.sclera_albedo),
        mat(MaterialKind::Cornea, 0.0),
        Material {
            kind: MaterialKind::Iris,
            albedo: subject.iris_albedo,
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
        },
        mat(MaterialKind::Pupil, subject.pupil_albedo),
        mat(MaterialKind::Skin, subject.skin_albedo),
    ];
    let el = state.elevation_rad;
    let z_face = 4e-3;
    let prims = vec![
        Prim {
            shape: Shape::Sphere {
                center: [0.0; 3],
                radius_m: g.eyeball_radius_m,
                clip: Clip::Plane {
                    normal: gz,
                    offset_m: g.pupil_plane_m,
                    sign: -1.0,
                },
            },
            material: 0,
            layer: LAYER_EYE,
        },
        Prim {
            shape: Shape::Sphere {
                center: geom::scale(gz, g.cornea_center_m),
                radius_m: g.cornea_radius_m,
                clip: Clip::Plane {
                    normal: gz,
                    offset_m: g.pupil_plane_m,
                    sign: 1.0,
                },
            },
            material: 1,
            layer: LAYER_CORNEA,
        },
        Prim {
            shape: Shape::Disc {
                center: iris_center,
                normal: gz,
                r_in_m: g.pupil_radius_m,
                r_out_m: g.limbus_radius_m,
            },
            material: 2,
            layer: LAYER_EYE,
        },
        Prim {
            shape: Shape::Disc {
                center: iris_center,
                normal: gz,
                r_in_m: 0.0,
                r_out_m: g.pupil_radius_m,
            },
            material: 3,
            layer: LAYER_EYE,
        },
        Prim {
            shape: Shape::Sphere {
                center: [0.0; 3],
                radius_m: g.lid_radius_m,
                clip: Clip::Lids(Aperture {
                    half_width_rad: subject.lid_half_width_rad,
                    upper_rad: subject.lid_upper_rad + subject.lid_upper_follow * el,
                    lower_rad: subject.lid_lower_rad + subject.lid_lower_follow * el,
                    z_min_m: z_face,
                }),
            },
            material: 4,
            layer: LAYER_SKIN,
        },
        Prim {
            shape: Shape::Disc {
                center: [0.0, 0.0, z_face],
                normal: [0.0, 0.0, 1.0],
                r_in_m: (g.lid_radius_m * g.lid_radius_m - z_face * z_face).sqrt(),
                r_out_m: 0.2,
            },
            material: 4,
            layer: LAYER_SKIN,
        },
    ];
    Scene::new(prims, materials, light, subject.cornea_index)
}

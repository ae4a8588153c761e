//! The path tracer: pinhole camera rays, Lambertian direct light with shadows from a small
//! spherical NIR emitter, a Fresnel cornea (glint by reflection, pupil and iris by refraction),
//! pupil masks, depth and the depth-layer decomposition. Rayon over image rows.

use super::material::{Material, MaterialKind, fresnel, reflect, refract};
use super::scene::{Hit, LAYER_ALL, LAYER_EYE, LAYER_SKIN, Scene};
use super::{Ray, RenderError};
use faer::Mat;
use nanoeye_gaze::{Camera, Pose, Vec3, geom};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

/// Depth-layer bounds: `count` equal slabs of ray distance between `near_m` and `far_m`;
/// content nearer/farther than the bounds goes to the first/last layer.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LayerSpec {
    /// Number of layers K (≥ 1).
    pub count: usize,
    /// Near bound (m).
    pub near_m: f64,
    /// Far bound (m).
    pub far_m: f64,
}

impl Default for LayerSpec {
    /// 8 layers over 15–35 mm: the eye region seen from the default rig's camera.
    fn default() -> Self {
        LayerSpec {
            count: 8,
            near_m: 15e-3,
            far_m: 35e-3,
        }
    }
}

/// Renderer settings.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RenderOptions {
    /// Samples per pixel (≥ 1): sample 0 is the pixel centre, the rest jittered uniformly.
    pub spp: usize,
    /// Seed of the per-pixel sample streams.
    pub seed: u64,
    /// Depth layers.
    pub layers: LayerSpec,
}

impl RenderOptions {
    /// Refuses a sample count outside 1..=65536 and a layer spec without 1..=256 layers over
    /// a finite near < far.
    pub fn validate(&self) -> Result<(), RenderError> {
        if self.spp == 0 || self.spp > 1 << 16 {
            return Err(RenderError::Invalid {
                what: "spp",
                reason: format!("must be in 1..=65536, got {}", self.spp),
            });
        }
        let ls = self.layers;
        if ls.count == 0
            || ls.count > 256
            || !(ls.near_m.is_finite() && ls.far_m.is_finite() && ls.near_m < ls.far_m)
        {
            return Err(RenderError::Invalid {
                what: "layers",
                reason: format!("need 1 ≤ count ≤ 256 and finite near < far, got {ls:?}"),
            });
        }
        Ok(())
    }
}

impl Default for RenderOptions {
    fn default() -> Self {
        RenderOptions {
            spp: 4,
            seed: 0,
            layers: LayerSpec::default(),
        }
    }
}

/// One depth layer: premultiplied radiance L_k and coverage α_k (f32, height × width).
#[derive(Debug, Clone)]
pub struct DepthLayer {
    /// Near bound of the slab (m).
    pub near_m: f64,
    /// Far bound of the slab (m).
    pub far_m: f64,
    /// Radiance of the samples whose first surface lies in the slab, divided by spp
    /// (W/(m²·sr)); Σ_k L_k is the radiance image.
    pub radiance: Mat<f32>,
    /// Fraction of the pixel's samples whose first surface lies in the slab.
    pub alpha: Mat<f32>,
    /// True when no sample landed in the slab (α ≡ 0): optics can skip it.
    pub empty: bool,
}

/// The depth-layer decomposition of a frame.
#[derive(Debug, Clone)]
pub struct DepthLayers {
    /// Layers, near to far.
    pub layers: Vec<DepthLayer>,
}

/// A rendered frame (f32, height × width).
#[derive(Debug, Clone)]
pub struct Frame {
    /// Linear radiance (W/(m²·sr)).
    pub radiance: Mat<f32>,
    /// Ray distance (m) to the first surface (cornea included) along the pixel-centre ray;
    /// +∞ where the ray meets nothing.
    pub depth_m: Mat<f32>,
    /// Fraction of samples that see the pupil (through the cornea, lids occluding).
    pub mask_visible_pupil: Mat<f32>,
    /// Fraction of samples that would see the pupil with skin and lids removed.
    pub mask_pupil: Mat<f32>,
    /// Depth layers.
    pub layers: DepthLayers,
}

/// SplitMix64: a tiny counter-based stream, seeded per pixel so results do not depend on the
/// thread count.
struct Rng64(u64);

impl Rng64 {
    #[inline]
    fn new(seed: u64, pixel: u64) -> Rng64 {
        let mut r = Rng64(seed ^ pixel.wrapping_mul(0xD1B5_4A32_D192_ED03));
        r.next();
        r
    }
    #[inline]
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    /// Uniform in [0, 1).
    #[inline]
    fn f(&mut self) -> f64 {
        (self.next() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }
}

/// What one camera sample saw.
struct Sample {
    radiance: f64,
    /// Distance to the first surface (∞ on a miss).
    t_first: f64,
    /// Class seen (behind the cornea where refracted).
    seen: Option<MaterialKind>,
    /// True when the first surface was skin.
    skin_first: bool,
}

/// Offset (m) of secondary-ray origins off a surface.
const OFFSET_M: f64 = 1e-8;

/// Renders `scene` through `camera` at `pose`.
pub fn render(
    scene: &Scene,
    camera: &Camera,
    pose: &Pose,
    opts: &RenderOptions,
) -> Result<Frame, RenderError> {
    camera.validate()?;
    opts.validate()?;
    let ls = opts.layers;
    let (w, h) = (camera.width_px, camera.height_px);
    let k = ls.count;
    // Per pixel: radiance, depth, visible mask, pupil mask, then K radiance and K alpha.
    let stride = 4 + 2 * k;
    let mut buf = vec![0f32; w * h * stride];
    let inv_spp = 1.0 / opts.spp as f64;
    buf.par_chunks_mut(w * stride)
        .enumerate()
        .for_each(|(row, out)| {
            for col in 0..w {
                let o = &mut out[col * stride..(col + 1) * stride];
                let mut rng = Rng64::new(opts.seed, (row * w + col) as u64);
                let (mut rad, mut vis, mut pup) = (0.0, 0.0, 0.0);
                for s in 0..opts.spp {
                    let (jx, jy) = if s == 0 {
                        (0.5, 0.5)
                    } else {
                        (rng.f(), rng.f())
                    };
                    let dir = pixel_dir(camera, pose, [col as f64 + jx, row as f64 + jy]);
                    let ray = Ray::new(pose.position, dir);
                    let smp = trace_sample(scene, &ray, &mut rng);
                    rad += smp.radiance;
                    if s == 0 {
                        o[1] = smp.t_first as f32;
                    }
                    let is_pupil = smp.seen == Some(MaterialKind::Pupil);
                    if is_pupil {
                        vis += 1.0;
                    }
                    // Only samples stopped by skin can differ once the skin is removed.
                    let unoccluded = if smp.skin_first {
                        may_reach_pupil(scene, &ray)
                            && classify(scene, &ray, LAYER_ALL & !LAYER_SKIN)
                                == Some(MaterialKind::Pupil)
                    } else {
                        is_pupil
                    };
                    if unoccluded {
                        pup += 1.0;
                    }
                    if smp.t_first.is_finite() {
                        let x = (smp.t_first - ls.near_m) / (ls.far_m - ls.near_m) * k as f64;
                        let li = (x.max(0.0) as usize).min(k - 1);
                        o[4 + li] += (smp.radiance * inv_spp) as f32;
                        o[4 + k + li] += inv_spp as f32;
                    }
                }
                o[0] = (rad * inv_spp) as f32;
                o[2] = (vis * inv_spp) as f32;
                o[3] = (pup * inv_spp) as f32;
            }
        });
    let plane = |c: usize| Mat::<f32>::from_fn(h, w, |i, j| buf[(i * w + j) * stride + c]);
    let dz = (ls.far_m - ls.near_m) / k as f64;
    // Gathering a plane reads the interleaved buffer with a stride of `stride` floats; run on
    // one thread the 4 + 2K gathers took ~3 ms of a 320×200 frame.
    let (layers, mut main) = rayon::join(
        || {
            (0..k)
                .into_par_iter()
                .map(|li| {
                    let alpha = plane(4 + k + li);
                    let empty = (0..w * h).all(|p| buf[p * stride + 4 + k + li] == 0.0);
                    DepthLayer {
                        near_m: ls.near_m + dz * li as f64,
                        far_m: ls.near_m + dz * (li + 1) as f64,
                        radiance: plane(4 + li),
                        alpha,
                        empty,
                    }
                })
                .collect()
        },
        || (0..4).into_par_iter().map(plane).collect::<Vec<_>>(),
    );
    let mut next = || main.remove(0);
    Ok(Frame {
        radiance: next(),
        depth_m: next(),
        mask_visible_pupil: next(),
        mask_pupil: next(),
        layers: DepthLayers { layers },
    })
}

/// World direction through image point `px` (pixel units, origin at the top-left corner).
#[inline]
pub fn pixel_dir(camera: &Camera, pose: &Pose, px: [f64; 2]) -> Vec3 {
    let a = [
        (px[0] - camera.cx_px) / camera.fx_px,
        (px[1] - camera.cy_px) / camera.fy_px,
        1.0,
    ];
    geom::mul_mv(&pose.rotation, a)
}

/// The ray that continues into the eye after refraction at the cornea hit `hit`, with the
/// Fresnel reflectance and the reflected direction.
#[inline]
fn cornea_split(scene: &Scene, ray: &Ray, hit: &Hit) -> (f64, Vec3, Option<Ray>, Vec3) {
    let p = ray.at(hit.t);
    let mut n = scene.prims[hit.prim as usize].shape.normal(p);
    let mut eta = 1.0 / scene.cornea_index;
    let (mut n1, mut n2) = (1.0, scene.cornea_index);
    if geom::dot(n, ray.dir) > 0.0 {
        // Leaving the cornea from inside.
        n = geom::scale(n, -1.0);
        eta = scene.cornea_index;
        std::mem::swap(&mut n1, &mut n2);
    }
    let f = fresnel(-geom::dot(ray.dir, n), n1, n2);
    let t = refract(ray.dir, n, eta).map(|d| Ray::new(geom::add(p, geom::scale(n, -OFFSET_M)), d));
    (f, reflect(ray.dir, n), t, p)
}

/// False when `ray` misses the scene's pupil bound (then it cannot see the pupil).
#[inline]
fn may_reach_pupil(scene: &Scene, ray: &Ray) -> bool {
    let Some((c, r)) = scene.pupil_bound else {
        return true;
    };
    let oc = geom::sub(ray.origin, c);
    let b = geom::dot(oc, ray.dir);
    let q = geom::dot(oc, oc) - r * r;
    // Inside the sphere, or it lies ahead and the line meets it.
    q <= 0.0 || (b < 0.0 && b * b - q >= 0.0)
}

/// Class seen along `ray` through the cornea among `mask` (no shading).
fn classify(scene: &Scene, ray: &Ray, mask: u8) -> Option<MaterialKind> {
    let hit = scene.closest(ray, f64::INFINITY, mask)?;
    let kind = scene.material(hit.prim).kind;
    if kind != MaterialKind::Cornea {
        return Some(kind);
    }
    let (_, _, inner, _) = cornea_split(scene, ray, &hit);
    let inner = inner?;
    let h2 = scene.closest(&inner, f64::INFINITY, mask & LAYER_EYE)?;
    Some(scene.material(h2.prim).kind)
}

fn trace_sample(scene: &Scene, ray: &Ray, rng: &mut Rng64) -> Sample {
    let Some(hit) = scene.closest(ray, f64::INFINITY, LAYER_ALL) else {
        return Sample {
            radiance: 0.0,
            t_first: f64::INFINITY,
            seen: None,
            skin_first: false,
        };
    };
    let m = scene.material(hit.prim);
    if m.kind != MaterialKind::Cornea {
        return Sample {
            radiance: diffuse(scene, ray, &hit, rng),
            t_first: hit.t,
            seen: Some(m.kind),
            skin_first: m.kind.is_occluder(),
        };
    }
    let (f, refl_dir, inner, p) = cornea_split(scene, ray, &hit);
    let mut radiance = 0.0;
    // Specular reflection: the glint where it meets the emitter, else one diffuse bounce.
    let n_out = geom::normalize(geom::sub(refl_dir, ray.dir));
    let refl = Ray::new(geom::add(p, geom::scale(n_out, OFFSET_M)), refl_dir);
    let t_scene = scene.closest(
        &refl,
        f64::INFINITY,
        LAYER_ALL & !super::scene::LAYER_CORNEA,
    );
    let t_limit = t_scene.map_or(f64::INFINITY, |h| h.t);
    if scene.light_hit(&refl, t_limit).is_some() {
        radiance += f * scene.light.radiance_toward(p);
    } else if let Some(h2) = t_scene {
        radiance += f * diffuse(scene, &refl, &h2, rng);
    }
    let mut seen = None;
    if let Some(inner) = inner
        && let Some(h2) = scene.closest(&inner, f64::INFINITY, LAYER_EYE)
    {
        seen = Some(scene.material(h2.prim).kind);
        // Radiance crossing the interface twice: the n² factors cancel, (1 − F) remains.
        radiance += (1.0 - f) * diffuse(scene, &inner, &h2, rng);
    }
    Sample {
        radiance,
        t_first: hit.t,
        seen,
        skin_first: false,
    }
}

/// Radiance leaving hit `hit` towards the ray origin: Lambertian, from one sample of the
/// emitter's disc (as seen from the point) with a shadow ray, under a wet coat where the
/// material has one (Fresnel-weighted mirror image of the emitter). The cornea does not cast
/// shadows (its refraction of the illumination is ignored; see docs/renderer.md).
#[inline]
fn diffuse(scene: &Scene, ray: &Ray, hit: &Hit, rng: &mut Rng64) -> f64 {
    let p = ray.at(hit.t);
    let m = scene.material(hit.prim);
    let mut n = scene.prims[hit.prim as usize].shape.normal(p);
    if geom::dot(n, ray.dir) > 0.0 {
        n = geom::scale(n, -1.0);
    }
    // Shading uses the smooth normal on the geometric side; offsets and the test for light
    // below the surface keep the geometric one, so smoothing never lets light through a facet.
    let ns = match scene.shading_normal(hit.prim, p) {
        Some(s) if geom::dot(s, n) < 0.0 => geom::scale(s, -1.0),
        Some(s) => s,
        None => n,
    };
    let (f, glint) = if m.coat_index > 0.0 {
        coat_glint(scene, ray, p, ns, m.coat_index)
    } else {
        (0.0, 0.0)
    };
    (1.0 - f) * lambert(scene, m, p, n, ns, rng) + glint
}

/// Fresnel reflectance of a wet coat of index `index` seen along `ray` at `p` (normal `n`
/// facing the ray), and the emitter radiance it mirrors there (0 unless the mirrored ray meets
/// the emitter unobstructed).
#[inline]
fn coat_glint(scene: &Scene, ray: &Ray, p: Vec3, n: Vec3, index: f64) -> (f64, f64) {
    let f = fresnel(-geom::dot(ray.dir, n), 1.0, index);
    let refl = Ray::new(geom::add(p, geom::scale(n, OFFSET_M)), reflect(ray.dir, n));
    let glint = match scene.light_hit(&refl, f64::INFINITY) {
        Some(t) if !scene.occluded(&refl, t, LAYER_EYE | LAYER_SKIN) => {
            f * scene.light.radiance_toward(p)
        }
        _ => 0.0,
    };
    (f, glint)
}

/// Lambertian radiance (albedo of material `m` at `p`) at `p` with geometric normal `n` and
/// shading normal `ns` facing the viewer. The albedo (a texture lookup) is evaluated only for
/// a lit sample.
#[inline]
fn lambert(scene: &Scene, m: &Material, p: Vec3, n: Vec3, ns: Vec3, rng: &mut Rng64) -> f64 {
    let light = &scene.light;
    let to_c = geom::sub(light.position_m, p);
    let dist_c = geom::norm(to_c);
    if dist_c.is_nan() || dist_c <= light.radius_m {
        return 0.0;
    }
    let w = geom::scale(to_c, 1.0 / dist_c);
    // Uniform point on the emitter's disc facing p (concentric-free polar sampling).
    let (e1, e2) = super::prim::perpendicular_basis(w);
    let (r, phi) = (light.radius_m * rng.f().sqrt(), 2.0 * PI * rng.f());
    let q = geom::add(
        light.position_m,
        geom::add(
            geom::scale(e1, r * phi.cos()),
            geom::scale(e2, r * phi.sin()),
        ),
    );
    let l = geom::sub(q, p);
    let dist = geom::norm(l);
    let l = geom::scale(l, 1.0 / dist);
    let cos = geom::dot(ns, l);
    if cos <= 0.0 || geom::dot(n, l) <= 0.0 {
        return 0.0;
    }
    let shadow = Ray::new(geom::add(p, geom::scale(n, OFFSET_M)), l);
    if scene.occluded(&shadow, dist - OFFSET_M, LAYER_EYE | LAYER_SKIN) {
        return 0.0;
    }
    // Disc facing p: E = I(−l)·cosθ/d² (the disc's cos on the emitter side is 1).
    let e = light.intensity_along(geom::scale(l, -1.0)) * cos / (dist * dist);
    m.albedo_at(p) / PI * e
}

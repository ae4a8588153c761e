//! The eye-region renderer (C.1): procedural scene or user mesh, BVH ray tracing, ground truth
//! (radiance, depth, pupil masks, landmarks, depth layers) and the dataset writer.
//!
//! Units: metres and radians; radiance in W/(m²·sr) (f32); depth is the distance (m) along the
//! pixel's ray from the camera centre to the first surface. Conventions in docs/renderer.md.

pub mod bvh;
pub mod cgroup;
pub mod dataset;
pub mod export;
pub mod face;
pub mod landmarks;
pub mod lanes;
pub mod material;
pub mod mesh;
pub mod prim;
pub mod read;
pub mod scene;
pub mod trace;

pub use dataset::{
    BLINK_CLOSURE, DATASET_FORMAT, DatasetManifest, DatasetOptions, DatasetPlan, DatasetSummary,
    FrameFiles, FrameRecord, LayerInfo, RenderSet, SceneSource, finish_dataset, manifest_for,
    open_dataset, plan_dataset, render_frames, write_dataset,
};
pub use export::export_glb;
pub use landmarks::{Landmark, Landmarks, aim_refracted_pupil, landmarks, refracted_pupil_px};
pub use material::{Material, MaterialKind};
pub use mesh::{Mesh, MeshUnits};
pub use read::{Batcher, Dataset, FrameRef, StoredFrame, StoredLayer, read_npy_f32};
pub use scene::{
    EyeGeometry, Light, ProceduralParts, Scene, Subject, procedural_parts, procedural_scene,
};
pub use trace::{DepthLayer, DepthLayers, Frame, LayerSpec, RenderOptions, render};

use nanoeye_gaze::{Camera, GazeError, Pose, Vec3, geom};

/// The rendering stage: a scene seen by a camera at a pose → a [`Frame`] (radiance, depth,
/// masks and depth layers). Swap this to plug in another renderer behind the same data flow.
pub trait Renderer: Send + Sync {
    /// Renders `scene` through `camera` at `pose`.
    fn render(&self, scene: &Scene, camera: &Camera, pose: &Pose) -> Result<Frame, RenderError>;
}

/// The built-in BVH ray tracer ([`render`]) with fixed options.
#[derive(Debug, Clone, Copy)]
pub struct RayTracer {
    /// Samples per pixel, depth layers and seed.
    pub opts: RenderOptions,
}

impl Renderer for RayTracer {
    fn render(&self, scene: &Scene, camera: &Camera, pose: &Pose) -> Result<Frame, RenderError> {
        trace::render(scene, camera, pose, &self.opts)
    }
}

/// Errors of the renderer and dataset writer.
#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    /// A parameter is out of range; `what` names it.
    #[error("invalid {what}: {reason}")]
    Invalid {
        /// The parameter.
        what: &'static str,
        /// What is wrong.
        reason: String,
    },
    /// Rig or eye-orientation failure.
    #[error(transparent)]
    Geometry(#[from] GazeError),
    /// State sampling failed.
    #[error(transparent)]
    States(#[from] crate::states::StatesError),
    /// A mesh file could not be read or is malformed.
    #[error("mesh {path}: {reason}")]
    Mesh {
        /// File.
        path: String,
        /// What is wrong.
        reason: String,
    },
    /// File output failed.
    #[error("{path}: {cause}")]
    Io {
        /// File.
        path: String,
        /// Cause.
        cause: std::io::Error,
    },
    /// Image encoding failed.
    #[error("{path}: {reason}")]
    Encode {
        /// File.
        path: String,
        /// Cause.
        reason: String,
    },
}

/// A ray with unit direction (m).
#[derive(Debug, Clone, Copy)]
pub struct Ray {
    /// Origin.
    pub origin: Vec3,
    /// Unit direction.
    pub dir: Vec3,
    /// Component-wise 1/dir for slab tests.
    pub inv_dir: Vec3,
}

impl Ray {
    /// A ray from `origin` along `dir` (normalized here).
    #[inline]
    pub fn new(origin: Vec3, dir: Vec3) -> Ray {
        let d = geom::normalize(dir);
        Ray {
            origin,
            dir: d,
            inv_dir: [1.0 / d[0], 1.0 / d[1], 1.0 / d[2]],
        }
    }

    /// Point at distance `t`.
    #[inline]
    pub fn at(&self, t: f64) -> Vec3 {
        geom::add(self.origin, geom::scale(self.dir, t))
    }
}

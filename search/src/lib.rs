//! Co-design composition: the simulated camera chain (rendered depth layers → metasurface PSFs
//! → S1 → sensor S2 → network input, and its gradients back to the phase map and the pixel
//! pitch), the task loss through the supernet (S7, S8), and — in later modules — sandwich
//! training (S22) and the evolutionary search (S16–S21). Crates compose here; the CLI wires it.

pub mod basis;
pub mod bn;
pub mod chain;
pub mod embed;
pub mod error;
pub mod geometry;
pub mod headfit;
pub mod lens;
pub mod pareto;
pub mod radiometry;
pub mod rea;
pub mod schedule;
pub mod spectra;
pub mod split;
pub mod task;
pub mod train;

pub use basis::PhaseBasis;
pub use bn::BnBatches;
pub use chain::{
    CameraChain, ChainConfig, ChainForward, ChainFrame, ChainGrad, PsfGradAccumulator, SlipTarget,
    StepPsfs,
};
pub use embed::{EmbedConfig, EmbedEval, EmbedRecord, EmbedWeights, Embedder, embedding_loss};
pub use error::{Result, SearchError};
pub use geometry::{NativeGrid, PitchGrid};
pub use lens::LensSpec;
pub use radiometry::Radiometry;
pub use rea::{CycleRecord, EvalPool, Evaluator, Individual, Rea, ReaConfig, ReaState};
pub use schedule::PhaseSchedule;
pub use split::{DepthSplit, OneProcess};
pub use task::{TaskGrads, TaskLoss, task_loss};
pub use train::{
    Budget, ChainedSet, EvalSetup, FrameEval, Metrics, SolverInput, StepRecord, TrainConfig,
    Trainer, evaluate_chained, evaluate_frames, evaluate_frames_multi, evaluate_net, load_model,
};

//! The model seam between the bus side and the trainer thread.
//!
//! The trainer thread (`worker.rs`) drives any [`Learner`]: the online Sun-aware trainer
//! (gs-core) when it is wired in, or the [`crate::nearest_learner::NearestKeyframeLearner`]
//! baseline. Everything the trainer needs crosses this seam as plain owned data, so the
//! bus side never shares model state.
//!
//! Invariants for implementations: deterministic (same calls in the same order give the same
//! [`Learner::save`] bytes); non-finite inputs never enter the model; `load` either
//! replaces the whole model or leaves it untouched and returns an error; `inspect` accepts
//! exactly the bytes `load` accepts. Failures come back as values (the worker turns them
//! into bus events), never as log lines.

use crate::sync::SyncedTelemetry;
use glam::{DQuat, DVec3};
use gs_core::Intrinsics;
use interfaces::messages::{EventKind, PixelFormat};
use std::fmt;

/// A synchronised camera frame, owned, ready for the trainer.
#[derive(Clone, Debug, PartialEq)]
pub struct ObservedFrame {
    pub frame_id: u32,
    pub time_us: u64,
    pub width: u16,
    pub height: u16,
    pub format: PixelFormat,
    pub pixels: Vec<u8>,
    pub mask: Option<Vec<u8>>,
    /// The intrinsics of this frame (its own camera model, or the configured camera);
    /// `width` and `height` equal the frame's.
    pub camera: Intrinsics,
    pub telemetry: SyncedTelemetry,
}

/// Where to render: camera pose relative to the target and the Sun in the target frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ViewRequest {
    pub camera_from_target: DQuat,
    pub target_in_camera_m: DVec3,
    pub sun_in_target: DVec3,
    pub width: u16,
    pub height: u16,
    pub format: PixelFormat,
    /// The camera to render with; its `width` and `height` equal the request's.
    pub intrinsics: Intrinsics,
}

impl ViewRequest {
    /// Unit direction from the target to the camera, target frame (None at zero range).
    pub fn view_in_target(&self) -> Option<DVec3> {
        let camera_in_target = -(self.camera_from_target.inverse() * self.target_in_camera_m);
        let range_m = camera_in_target.length();
        (range_m.is_finite() && range_m > 0.0).then(|| camera_in_target / range_m)
    }
}

/// A rendered image in the requested size and format.
#[derive(Clone, Debug, PartialEq)]
pub struct PredictedImage {
    pub width: u16,
    pub height: u16,
    pub format: PixelFormat,
    pub pixels: Vec<u8>,
}

/// What `offer` did with a frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum OfferResult {
    /// Entered the keyframe window.
    Added,
    /// Not a new keyframe (too close to the newest view, duplicate id).
    NotAdded,
    /// Skipped on purpose (eclipse, unlit); counted by the learner.
    Skipped,
    /// Refused: the frame failed the model's own checks (reported as an event).
    Refused,
}

/// One finished training round.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RoundSummary {
    pub rounds: u32,
    pub duration_ms: u32,
    pub loss: f32,
    pub gaussians: u32,
    /// Optimisation steps of this round refused for a non-finite render, loss or gradient.
    pub skipped_steps: u32,
}

/// Model figures for health reports.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct LearnerStats {
    pub gaussians: u32,
    pub rounds: u32,
    pub window_fill: u8,
    pub window_capacity: u8,
}

#[derive(Clone, Debug, PartialEq)]
pub enum LearnerError {
    /// Nothing learned yet, or no view to render from.
    NothingToRender,
    BadRequest(String),
    BadCheckpoint(String),
    /// A training round or a reset failed; the model is as before the call.
    Training(String),
}

impl fmt::Display for LearnerError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::NothingToRender => f.write_str("the model has nothing to render yet"),
            Self::BadRequest(why) => write!(f, "bad render request: {why}"),
            Self::BadCheckpoint(why) => write!(f, "bad checkpoint: {why}"),
            Self::Training(why) => write!(f, "training failed: {why}"),
        }
    }
}

impl std::error::Error for LearnerError {}

/// What the trainer thread needs from a model.
pub trait Learner: Send {
    /// Offers a frame to the keyframe window.
    fn offer(&mut self, frame: &ObservedFrame) -> OfferResult;
    /// Runs one training round if the window calls for one.
    fn run_round_if_due(&mut self) -> Result<Option<RoundSummary>, LearnerError>;
    /// Renders the current model (no training).
    fn predict(&self, view: &ViewRequest) -> Result<PredictedImage, LearnerError>;
    /// Forgets everything learned (window, model, rounds); on error the model is unchanged.
    fn reset(&mut self) -> Result<(), LearnerError>;
    /// The whole model state as checkpoint bytes.
    fn save(&self) -> Vec<u8>;
    /// Replaces the whole state from checkpoint bytes; on error the model is unchanged.
    fn load(&mut self, bytes: &[u8]) -> Result<(), LearnerError>;
    /// Checks `bytes` exactly as `load` would, without changing the model; returns the
    /// training rounds they hold (checkpoints are never replaced by fewer rounds).
    fn inspect(&self, bytes: &[u8]) -> Result<u64, LearnerError>;
    fn stats(&self) -> LearnerStats;
    /// Events the model has to report since the last call (e.g. how it was initialised).
    fn take_events(&mut self) -> Vec<EventKind> {
        Vec::new()
    }
}

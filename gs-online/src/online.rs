//! The online trainer of the paper: keyframe window, training rounds, Sun-aware model.
//!
//! Pure and synchronous (no bus, no async): the flight component and the simulator drive
//! the same code. Per frame, [`OnlineTrainer::offer`] applies, in order:
//! 1. validation (sizes, finiteness, camera, Sun vector): a bad frame is an error;
//! 2. eclipse frames, and unlit frames (mean masked brightness below
//!    `min_mean_brightness`; without a mask the full frame's, or no test when
//!    `unlit_full_frame` is off), teach nothing: skipped and counted (each skip switchable);
//!    a frame whose mask is zero everywhere (the target is not in it) has nothing for the
//!    masked loss to read: always skipped and counted (`skipped_empty_mask`), never an
//!    error, since a sensor pipeline can legitimately send one;
//! 3. the paper's keyframe rule ([`KeyframeWindow::offer`]): add when the view vector
//!    moved more than 10 degrees, keep the two newest, evict the most redundant beyond W.
//!
//! [`OnlineTrainer::run_round_if_due`] runs one round when the window is full and its
//! composition changed since the last round (the change requirement is switchable): W
//! steps, each keyframe once in a seeded shuffle, the position learning rate decaying
//! through the round and restarting at the next (sawtooth). Densify and prune every
//! `densify_every_rounds` rounds. With a replay memory (`replay_capacity` > 0, off in the
//! paper), keyframes the window evicts are kept as a bounded uniform sample of the past
//! (reservoir rule) and each round adds `replay_steps_per_round` steps on them, so views
//! that left the window are not forgotten.
//!
//! Invariants: the view vector of a frame is the unit vector from the target centre (the
//! body-frame origin) to the camera; everything is deterministic given the frames, the
//! configuration and the thread count (the shuffle of round r is seeded by
//! `(shuffle_seed, r)`); nothing non-finite enters the model (validated inputs, and the
//! model trainer skips and counts non-finite steps).

use std::time::Instant;

use glam::{DVec3, Quat, Vec3};
use gs_core::densify::DensifyReport;
use gs_core::init::{from_points, random_in_sphere, SplitMix64};
use gs_core::model::Param;
use gs_core::nn::SceneBox;
use gs_core::sunaware::trainer::RenderedImages;
use gs_core::sunaware::{
    Observation, SunAwareConfig, SunAwareError, SunAwareModel, SunAwareTrainer,
};
use gs_core::Camera;

use crate::keyframe::{
    Keyframe, KeyframeError, KeyframeWindow, NotAddedReason, OfferOutcome, ViewDirection,
    WindowConfig,
};

/// One camera frame with everything training needs.
#[derive(Clone, Debug, PartialEq)]
pub struct Frame {
    /// Unique id (e.g. the image counter).
    pub id: u64,
    /// Capture time, seconds (any epoch; reported, not used for training).
    pub time_s: f64,
    /// Intrinsics and the camera-from-target pose.
    pub camera: Camera,
    /// Unit vector from the target towards the Sun, target body frame.
    pub sun_dir_target: Vec3,
    /// `H * W * 3` RGB in [0, 1], pixel-major.
    pub image: Vec<f32>,
    /// Optional `H * W` foreground weights in [0, 1].
    pub mask: Option<Vec<f32>>,
    /// The target is in the Earth's shadow.
    pub eclipse: bool,
}

impl Frame {
    fn observation(&self) -> Observation<'_> {
        Observation {
            camera: self.camera,
            sun_dir: self.sun_dir_target,
            image: &self.image,
            mask: self.mask.as_deref(),
        }
    }

    /// Mean image value over the mask (weighted), or over the whole image without one.
    /// Whether the frame carries a mask that is zero everywhere (NaN is not zero: such a
    /// mask fails validation instead).
    pub fn mask_is_empty(&self) -> bool {
        self.mask
            .as_ref()
            .is_some_and(|m| m.iter().all(|&v| v == 0.0))
    }

    pub fn mean_brightness(&self) -> f32 {
        let (mut sum, mut weight) = (0.0f64, 0.0f64);
        for (px, rgb) in self.image.chunks_exact(3).enumerate() {
            let w = self.mask.as_ref().map_or(1.0, |m| m[px] as f64);
            sum += w * rgb.iter().map(|&v| v as f64).sum::<f64>() / 3.0;
            weight += w;
        }
        if weight > 0.0 {
            (sum / weight) as f32
        } else {
            0.0
        }
    }
}

/// How the first Gaussians are placed.
#[derive(Clone, Debug, PartialEq)]
pub enum Initialisation {
    /// Points on the target's surface (the paper: 10,000 sampled by area), with optional
    /// outward normals and colours in [0, 1].
    SurfaceSamples {
        points: Vec<Vec3>,
        normals: Option<Vec<Vec3>>,
        colours: Option<Vec<[f32; 3]>>,
    },
    /// Uniform random points in a ball (3DGS's random initialisation).
    RandomSphere {
        count: usize,
        centre: Vec3,
        radius_m: f32,
        seed: u64,
    },
}

/// Online training settings.
#[derive(Clone, Debug, PartialEq)]
pub struct OnlineConfig {
    /// W and theta_VIEW.
    pub window: WindowConfig,
    /// The model, its variant (a-d) and its optimiser settings.
    pub model: SunAwareConfig,
    /// Passes over the window per round (paper: 1), each in its own shuffled order.
    pub passes_per_round: u32,
    /// Densify and prune every this many rounds (paper: 10).
    pub densify_every_rounds: u64,
    /// Skip frames flagged as in eclipse.
    pub skip_eclipse: bool,
    /// Skip frames whose mean masked brightness is below `min_mean_brightness`.
    pub skip_unlit: bool,
    pub min_mean_brightness: f32,
    /// Apply the unlit test to frames without a mask, on the full frame's brightness (the
    /// black background then also turns away frames where the lit target is small:
    /// docs/runtime-vs-error.md recommends off without masks).
    pub unlit_full_frame: bool,
    /// Run a round only when the window's composition changed since the last one.
    pub require_window_change: bool,
    /// Seeds the per-round shuffles.
    pub shuffle_seed: u64,
    /// With surface normals, the Gaussian's axis along the normal is scaled by this
    /// (1 keeps the isotropic 3DGS start; below 1 starts them as surface discs).
    pub normal_flatten: f32,
    /// Keyframes the window evicted are kept in a bounded replay memory of this many frames
    /// (0: none, the paper). Memory: one frame's image and mask each (`H * W * 4 * 4`
    /// bytes: 0.26 MB at 160x100, 2.3 MB at 480x300).
    pub replay_capacity: usize,
    /// Steps per round on frames drawn from the replay memory, after the window's steps
    /// (against forgetting views that left the window).
    pub replay_steps_per_round: usize,
    /// Each training step sees its frame's Sun turned by a random angle up to this (radians,
    /// uniform over the spherical cap; 0: the frame's own Sun, the paper). The appearance
    /// network otherwise fits each trained Sun direction as a peak and draws the target too
    /// dark 5-10 degrees away (docs/results/accuracy.md); the jitter asks it for a colour
    /// that holds around each trained Sun.
    pub sun_jitter_rad: f32,
}

impl Default for OnlineConfig {
    fn default() -> Self {
        Self {
            window: WindowConfig::default(),
            model: SunAwareConfig::default(),
            passes_per_round: 1,
            densify_every_rounds: 10,
            skip_eclipse: true,
            skip_unlit: true,
            min_mean_brightness: 0.01,
            unlit_full_frame: true,
            require_window_change: true,
            shuffle_seed: 0,
            normal_flatten: 1.0,
            replay_capacity: 0,
            replay_steps_per_round: 0,
            sun_jitter_rad: 0.0,
        }
    }
}

/// Error from the online trainer.
#[derive(Debug)]
pub enum OnlineError {
    /// A frame is unusable; the message says why.
    BadFrame(String),
    Config(String),
    Keyframe(KeyframeError),
    Model(SunAwareError),
}

impl std::fmt::Display for OnlineError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            OnlineError::BadFrame(m) => write!(f, "bad frame: {m}"),
            OnlineError::Config(m) => write!(f, "invalid online configuration: {m}"),
            OnlineError::Keyframe(e) => write!(f, "keyframe window: {e}"),
            OnlineError::Model(e) => write!(f, "model: {e}"),
        }
    }
}

impl std::error::Error for OnlineError {}

impl From<SunAwareError> for OnlineError {
    fn from(e: SunAwareError) -> Self {
        OnlineError::Model(e)
    }
}

impl From<KeyframeError> for OnlineError {
    fn from(e: KeyframeError) -> Self {
        OnlineError::Keyframe(e)
    }
}

impl From<gs_core::init::InitError> for OnlineError {
    fn from(e: gs_core::init::InitError) -> Self {
        OnlineError::Model(SunAwareError::Init(e))
    }
}

/// Why a frame did not enter the window.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum SkipReason {
    Eclipse,
    /// The frame's mask is zero everywhere.
    EmptyMask,
    Unlit {
        mean_brightness: f32,
    },
    ViewTooClose {
        cos_to_newest: f64,
    },
    DuplicateId,
}

/// What [`OnlineTrainer::offer`] did.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum OfferReport {
    /// Now the newest keyframe; `evicted` names the keyframe removed to make room.
    Added {
        evicted: Option<u64>,
    },
    Skipped(SkipReason),
}

/// Frame counters since creation.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct OfferCounters {
    pub offered: u64,
    pub added: u64,
    pub evicted: u64,
    pub skipped_eclipse: u64,
    pub skipped_empty_mask: u64,
    pub skipped_unlit: u64,
    pub skipped_view: u64,
    pub skipped_duplicate: u64,
}

/// What one training round did.
#[derive(Clone, Debug, PartialEq)]
pub struct RoundReport {
    /// Rounds run so far, this one included.
    pub rounds: u64,
    /// Mean total loss over the round's applied steps (NaN if all were skipped).
    pub mean_loss: f32,
    pub duration_s: f64,
    pub gaussians: usize,
    /// Steps of this round refused as non-finite.
    pub skipped_steps: u64,
    /// Keyframe ids in the order they were trained.
    pub trained_ids: Vec<u64>,
    pub densified: Option<DensifyReport>,
}

/// Keyframe window + Sun-aware trainer + round bookkeeping.
#[derive(Clone, Debug)]
pub struct OnlineTrainer {
    pub(crate) config: OnlineConfig,
    pub(crate) window: KeyframeWindow<Frame>,
    pub(crate) trainer: SunAwareTrainer,
    pub(crate) last_trained_generation: Option<u64>,
    pub(crate) rounds: u64,
    pub(crate) counters: OfferCounters,
    /// Evicted keyframes (at most `replay_capacity`), in the order they were kept.
    pub(crate) replay: Vec<Frame>,
    /// Evictions seen so far: seeds which replay slot a new eviction replaces.
    pub(crate) evictions: u64,
}

fn check_vec(what: &str, v: Vec3) -> Result<(), OnlineError> {
    if v.is_finite() {
        Ok(())
    } else {
        Err(OnlineError::BadFrame(format!("{what} {v:?} is not finite")))
    }
}

/// Initial Gaussians for the configured layout.
fn initial_gaussians(
    init: &Initialisation,
    config: &OnlineConfig,
) -> Result<gs_core::GaussianModel, OnlineError> {
    let layout = config.model.layout();
    match init {
        Initialisation::RandomSphere {
            count,
            centre,
            radius_m,
            seed,
        } => Ok(random_in_sphere(*count, *centre, *radius_m, layout, *seed)?.model),
        Initialisation::SurfaceSamples {
            points,
            normals,
            colours,
        } => {
            if let Some(n) = normals {
                if n.len() != points.len() {
                    return Err(OnlineError::Config(format!(
                        "{} surface points but {} normals",
                        points.len(),
                        n.len()
                    )));
                }
                if n.iter().any(|v| !v.is_finite()) {
                    return Err(OnlineError::Config("a surface normal is not finite".into()));
                }
            }
            let result = from_points(points, colours.as_deref(), layout)?;
            let mut model = result.model;
            if let Some(n) = normals {
                if result.dropped_non_finite > 0 {
                    return Err(OnlineError::Config(format!(
                        "{} surface points are not finite: normals no longer match",
                        result.dropped_non_finite
                    )));
                }
                let flatten_log = config.normal_flatten.ln();
                for (i, normal) in n.iter().enumerate() {
                    if normal.length_squared() < 1e-12 {
                        continue;
                    }
                    // Local z along the normal; stored quaternions are [w, x, y, z].
                    let q = Quat::from_rotation_arc(Vec3::Z, normal.normalize());
                    model
                        .params
                        .row_mut(Param::Rotation, i)
                        .copy_from_slice(&[q.w, q.x, q.y, q.z]);
                    model.params.row_mut(Param::LogScale, i)[2] += flatten_log;
                    // A learned shading normal starts as the surface's (`shading =
                    // "lambert_learned"`; other models have no such group).
                    if model.params.dim(Param::Normal) == 3 {
                        model
                            .params
                            .row_mut(Param::Normal, i)
                            .copy_from_slice(&normal.normalize().to_array());
                    }
                }
            }
            Ok(model)
        }
    }
}

/// `sun` turned by an angle up to `max_rad`, uniform over the spherical cap around it, in a
/// uniformly random direction; still a unit vector.
fn jittered_sun(sun: Vec3, max_rad: f32, rng: &mut SplitMix64) -> Vec3 {
    let (u, v) = (rng.next_f32(), rng.next_f32());
    // Uniform over the cap: cos(angle) uniform in [cos(max), 1].
    let cos_angle = 1.0 - u * (1.0 - max_rad.cos());
    let angle = cos_angle.clamp(-1.0, 1.0).acos();
    let axis = Quat::from_axis_angle(sun, v * std::f32::consts::TAU) * sun.any_orthonormal_vector();
    (Quat::from_axis_angle(axis, angle) * sun).normalize()
}

impl OnlineTrainer {
    /// A trainer with initial Gaussians from `init`; `scene_box` bounds the target (body
    /// frame) and normalises means for Psi.
    pub fn new(
        config: OnlineConfig,
        init: &Initialisation,
        scene_box: SceneBox,
    ) -> Result<Self, OnlineError> {
        if config.densify_every_rounds == 0 {
            return Err(OnlineError::Config(
                "densify_every_rounds must be positive".into(),
            ));
        }
        if !(config.min_mean_brightness.is_finite() && config.min_mean_brightness >= 0.0) {
            return Err(OnlineError::Config(
                "min_mean_brightness must be finite and >= 0".into(),
            ));
        }
        if !(config.normal_flatten.is_finite() && config.normal_flatten > 0.0) {
            return Err(OnlineError::Config(
                "normal_flatten must be finite and positive".into(),
            ));
        }
        if !(config.sun_jitter_rad.is_finite()
            && (0.0..=std::f32::consts::FRAC_PI_2).contains(&config.sun_jitter_rad))
        {
            return Err(OnlineError::Config(format!(
                "sun_jitter_rad {} is outside [0, pi/2]",
                config.sun_jitter_rad
            )));
        }
        let window = KeyframeWindow::new(config.window)?;
        let gaussians = initial_gaussians(init, &config)?;
        let model = SunAwareModel::new(gaussians, scene_box, config.model.clone())?;
        Ok(Self {
            config,
            window,
            trainer: SunAwareTrainer::new(model),
            last_trained_generation: None,
            rounds: 0,
            counters: OfferCounters::default(),
            replay: Vec::new(),
            evictions: 0,
        })
    }

    pub fn config(&self) -> &OnlineConfig {
        &self.config
    }

    /// Replaces the model (Gaussians from `init`, fresh networks and optimiser state, the
    /// new scene box) and keeps the window, the counters and the round count: how a start
    /// carved from the first keyframes takes over before the first round. The new trainer
    /// runs on `backend`. On error nothing changes.
    pub fn restart_model(
        &mut self,
        init: &Initialisation,
        scene_box: SceneBox,
        backend: &gs_core::engine::Backend,
    ) -> Result<(), OnlineError> {
        let gaussians = initial_gaussians(init, &self.config)?;
        let model = SunAwareModel::new(gaussians, scene_box, self.config.model.clone())?;
        let mut trainer = SunAwareTrainer::new(model);
        trainer.set_backend(backend)?;
        self.trainer = trainer;
        Ok(())
    }

    pub fn window(&self) -> &KeyframeWindow<Frame> {
        &self.window
    }

    pub fn trainer(&self) -> &SunAwareTrainer {
        &self.trainer
    }

    /// Mutable access for checkpoint restore or manual densification.
    pub fn trainer_mut(&mut self) -> &mut SunAwareTrainer {
        &mut self.trainer
    }

    pub fn counters(&self) -> OfferCounters {
        self.counters
    }

    pub fn rounds(&self) -> u64 {
        self.rounds
    }

    /// Sets the round count (which seeds the next round's shuffle and sets the densify
    /// cadence): how a model restored without its online state continues its count.
    pub fn set_rounds(&mut self, rounds: u64) {
        self.rounds = rounds;
    }

    pub(crate) fn validate(&self, frame: &Frame) -> Result<ViewDirection, OnlineError> {
        let bad = |m: String| Err(OnlineError::BadFrame(format!("frame {}: {m}", frame.id)));
        let cam = &frame.camera;
        check_vec("camera translation", cam.translation)?;
        if !(cam.rotation.is_finite() && cam.rotation.length_squared() > 1e-6) {
            return bad("camera rotation is not a finite non-zero quaternion".into());
        }
        let k = &cam.intrinsics;
        if !(k.fx.is_finite() && k.fy.is_finite() && k.fx > 0.0 && k.fy > 0.0) {
            return bad("focal lengths must be finite and positive".into());
        }
        if !frame.time_s.is_finite() {
            return bad("time is not finite".into());
        }
        // An all-zero mask is validated for its size and values here and skipped by
        // `offer`; the trainer's own check (an error) never sees it.
        let mut observation = frame.observation();
        if frame.mask_is_empty() {
            let pixels = cam.intrinsics.width as usize * cam.intrinsics.height as usize;
            if observation.mask.map(<[f32]>::len) != Some(pixels) {
                return bad(format!(
                    "mask has {} values, the camera needs {pixels} (H * W)",
                    observation.mask.map_or(0, <[f32]>::len)
                ));
            }
            observation.mask = None;
        }
        observation
            .validate()
            .map_err(|e| OnlineError::BadFrame(format!("frame {}: {e}", frame.id)))?;
        let position = cam.position();
        ViewDirection::new(DVec3::new(
            position.x as f64,
            position.y as f64,
            position.z as f64,
        ))
        .map_err(|e| OnlineError::BadFrame(format!("frame {}: view vector: {e}", frame.id)))
    }

    /// Offers a frame to the window (see the module docs for the order of the rules).
    pub fn offer(&mut self, frame: Frame) -> Result<OfferReport, OnlineError> {
        let view = self.validate(&frame)?;
        self.counters.offered += 1;
        if frame.eclipse && self.config.skip_eclipse {
            self.counters.skipped_eclipse += 1;
            return Ok(OfferReport::Skipped(SkipReason::Eclipse));
        }
        if frame.mask_is_empty() {
            self.counters.skipped_empty_mask += 1;
            return Ok(OfferReport::Skipped(SkipReason::EmptyMask));
        }
        if self.config.skip_unlit && (frame.mask.is_some() || self.config.unlit_full_frame) {
            let mean_brightness = frame.mean_brightness();
            if mean_brightness < self.config.min_mean_brightness {
                self.counters.skipped_unlit += 1;
                return Ok(OfferReport::Skipped(SkipReason::Unlit { mean_brightness }));
            }
        }
        let keyframe = Keyframe {
            id: frame.id,
            view,
            payload: frame,
        };
        match self.window.offer(keyframe) {
            OfferOutcome::Added { evicted } => {
                self.counters.added += 1;
                let evicted_id = evicted.as_ref().map(|k| k.id);
                if let Some(k) = evicted {
                    self.counters.evicted += 1;
                    self.remember(k.payload);
                }
                Ok(OfferReport::Added {
                    evicted: evicted_id,
                })
            }
            OfferOutcome::NotAdded { reason, .. } => Ok(OfferReport::Skipped(match reason {
                NotAddedReason::ViewTooClose { cos_to_newest } => {
                    self.counters.skipped_view += 1;
                    SkipReason::ViewTooClose { cos_to_newest }
                }
                NotAddedReason::DuplicateId => {
                    self.counters.skipped_duplicate += 1;
                    SkipReason::DuplicateId
                }
            })),
        }
    }

    /// Keeps an evicted keyframe in the replay memory: appended while there is room, then
    /// replacing a slot drawn by a seeded reservoir rule (eviction n replaces a random slot
    /// with probability capacity / n), so the memory stays a uniform sample of everything
    /// evicted, early views included, in bounded space.
    fn remember(&mut self, frame: Frame) {
        let capacity = self.config.replay_capacity;
        if capacity == 0 {
            return;
        }
        self.evictions += 1;
        if self.replay.len() < capacity {
            self.replay.push(frame);
            return;
        }
        let mut rng = SplitMix64::new(
            self.config.shuffle_seed
                ^ 0x5245_504C
                ^ self.evictions.wrapping_mul(0x9E37_79B9_7F4A_7C15),
        );
        let slot = (rng.next_u64() % self.evictions) as usize;
        if slot < capacity {
            self.replay[slot] = frame;
        }
    }

    /// Frames in the replay memory.
    pub fn replay_len(&self) -> usize {
        self.replay.len()
    }

    /// Whether [`OnlineTrainer::run_round_if_due`] would train now.
    pub fn round_due(&self) -> bool {
        self.window.is_full()
            && !(self.config.require_window_change
                && self.last_trained_generation == Some(self.window.generation()))
    }

    /// Runs one round if due (window full and, unless switched off, changed since the last).
    pub fn run_round_if_due(&mut self) -> Result<Option<RoundReport>, OnlineError> {
        if !self.round_due() {
            return Ok(None);
        }
        let start = Instant::now();
        let n = self.window.len();
        let passes = self.config.passes_per_round.max(1) as usize;
        let mut order: Vec<usize> = (0..n).collect();
        let mut rng = SplitMix64::new(
            self.config.shuffle_seed ^ self.rounds.wrapping_mul(0x9E37_79B9_7F4A_7C15),
        );
        let skipped_before = self.trainer.skipped_nonfinite;
        let (mut loss_sum, mut applied) = (0.0f64, 0u64);
        let mut trained_ids = Vec::with_capacity(n * passes);
        let mut batch = Vec::with_capacity(n * passes);
        for pass in 0..passes {
            // Reshuffling the previous order keeps pass 0 identical to a one-pass round.
            rng.shuffle(&mut order);
            for (k, &i) in order.iter().enumerate() {
                let frame = &self.window.keyframes()[i].payload;
                trained_ids.push(frame.id);
                // The learning rates decay over the whole round (sawtooth per round).
                let progress = (pass * n + k) as f32 / (passes * n) as f32;
                batch.push((frame.observation(), progress));
            }
        }
        // Replayed frames after the window's, at the round's end rates.
        if !self.replay.is_empty() {
            for _ in 0..self.config.replay_steps_per_round {
                let i = (rng.next_u64() % self.replay.len() as u64) as usize;
                let frame = &self.replay[i];
                trained_ids.push(frame.id);
                batch.push((frame.observation(), 1.0));
            }
        }
        if self.config.sun_jitter_rad > 0.0 {
            // Its own stream, so a zero jitter leaves the shuffles and replay draws as they were.
            let mut jitter = SplitMix64::new(
                self.config.shuffle_seed ^ self.rounds.wrapping_mul(0xD1B5_4A32_D192_ED03) ^ 0x5A,
            );
            for (observation, _) in &mut batch {
                observation.sun_dir =
                    jittered_sun(observation.sun_dir, self.config.sun_jitter_rad, &mut jitter);
            }
        }
        // One batch: on a device-resident trainer the round's state stays on the device.
        for stats in self.trainer.step_many(&batch)? {
            if !stats.skipped {
                loss_sum += stats.loss as f64;
                applied += 1;
            }
        }
        self.rounds += 1;
        self.last_trained_generation = Some(self.window.generation());
        let densified = if self.rounds.is_multiple_of(self.config.densify_every_rounds) {
            Some(self.trainer.densify_and_prune()?)
        } else {
            None
        };
        Ok(Some(RoundReport {
            rounds: self.rounds,
            mean_loss: if applied > 0 {
                (loss_sum / applied as f64) as f32
            } else {
                f32::NAN
            },
            duration_s: start.elapsed().as_secs_f64(),
            gaussians: self.trainer.model.len(),
            skipped_steps: self.trainer.skipped_nonfinite - skipped_before,
            trained_ids,
            densified,
        }))
    }

    /// Renders the current model (before or during training).
    pub fn predict(
        &self,
        camera: &Camera,
        sun_dir_target: Vec3,
    ) -> Result<RenderedImages, OnlineError> {
        Ok(self.trainer.render(camera, sun_dir_target)?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The jitter stays a unit vector within the cap, reaches its edge, turns every way
    /// around the Sun, and repeats for a seed.
    #[test]
    fn jittered_sun_covers_the_cap_and_no_more() {
        let sun = Vec3::new(0.3, -0.5, 0.81).normalize();
        let max = 10f32.to_radians();
        let mut rng = SplitMix64::new(7);
        let mut widest = 0.0f32;
        let (mut left, mut right) = (0, 0);
        let side = sun.any_orthonormal_vector();
        for _ in 0..2000 {
            let j = jittered_sun(sun, max, &mut rng);
            assert!((j.length() - 1.0).abs() < 1e-6, "{j}");
            let angle = sun.dot(j).clamp(-1.0, 1.0).acos();
            assert!(angle <= max + 1e-5, "{angle} beyond {max}");
            widest = widest.max(angle);
            if (j - sun).dot(side) > 0.0 {
                left += 1;
            } else {
                right += 1;
            }
        }
        assert!(widest > 0.95 * max, "never near the cap's edge: {widest}");
        assert!(left > 800 && right > 800, "one-sided: {left} / {right}");
        let (mut a, mut b) = (SplitMix64::new(3), SplitMix64::new(3));
        assert_eq!(
            jittered_sun(sun, max, &mut a),
            jittered_sun(sun, max, &mut b)
        );
    }

    #[test]
    fn a_sun_jitter_outside_a_quarter_turn_is_refused() {
        let init = Initialisation::RandomSphere {
            count: 10,
            centre: Vec3::ZERO,
            radius_m: 1.0,
            seed: 1,
        };
        for bad in [-0.1, 1.6, f32::NAN] {
            let config = OnlineConfig {
                sun_jitter_rad: bad,
                ..OnlineConfig::default()
            };
            let scene_box = SceneBox::new([-1.0; 3], [1.0; 3]).unwrap();
            let Err(e) = OnlineTrainer::new(config, &init, scene_box) else {
                panic!("sun_jitter_rad {bad} was accepted");
            };
            assert!(e.to_string().contains("sun_jitter_rad"), "{e}");
        }
    }
}

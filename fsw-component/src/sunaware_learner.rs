//! The Sun-aware online trainer (`online.rs`, gs-core) behind the component's [`Learner`] seam.
//!
//! Converts bus frames (8-bit RGB or gray, pose and Sun from the synchronizer) into
//! `online::Frame`s (RGB in [0, 1], camera = intrinsics + camera-from-target pose, Sun in
//! the target frame) and renders predictions back to 8-bit images.
//!
//! Camera intrinsics: each frame's own (`ObservedFrame::camera`: its camera model, or the
//! configured `[camera]`, `crate::camera`); predictions use the request's. Eclipse comes from
//! the synchronised telemetry (the ICD's rule); the unlit skip runs on frames with a mask
//! only (masked mean brightness), never on full-frame brightness.
//! Initialisation (`[model]`, `crate::hull_start`): random points in the ball of
//! `target_radius_m` around the target origin, scene box its bounding cube; with
//! `init = "hull"` a visual hull carved from the window's keyframes replaces them when the
//! window first fills, before the first round, with the scene box fitted to the hull (or the
//! random start stays when too few keyframes carry masks or carving fails). Each start is
//! reported once as `EventKind::ModelInitialised`. With `shading = "lambert_learned"` both
//! starts give the learned normals gs-core's start (`shading::initial_normals`: the hull's
//! points carry no normals, so each round Gaussian's points away from the scene box's
//! centre); a resume takes them from the checkpoint.
//!
//! Checkpoint format (little-endian), version 2: magic `FSWSAL02`, hull start pending u8,
//! trainer length u64, the gs-core Sun-aware trainer checkpoint (Gaussians, features,
//! latents, MLP weights, optimiser state, step counters, RNG state, the model
//! configuration; its own magic and checksum), online state length u64, the online
//! trainer's state (`gs_online::resume`: keyframe window as compact copies, round counter
//! and so the shuffle, replay memory, counters), then CRC-32/IEEE of all before. Loading
//! it resumes exactly: the next frames train the same model, bit for bit, as a run that
//! never stopped (a resumed hull start is not carved again). Version 1 (`FSWSAL01`: rounds
//! u64, trainer length u64, trainer, CRC) is still read: it resumes the model and the
//! round count only, the window starts empty (logged), and a model of 0 rounds still waits
//! for its hull start. A checkpoint whose model configuration differs from the configured
//! one is refused, or used with a log line (`[checkpoint] on_config_mismatch`); with
//! `use_checkpoint` the checkpoint's window, shuffle seed and replay capacity are used too.
//! Invariants: frames the online trainer refuses are skipped, never half-applied; nothing
//! non-finite enters the model (the online trainer validates, gs-core skips non-finite steps).

use crate::hull_start::{self, HullStartError, InitKind, ModelSettings};
use crate::learner::{
    Learner, LearnerError, LearnerStats, ObservedFrame, OfferResult, PredictedImage, RoundSummary,
    ViewRequest,
};
use glam::{DQuat, DVec3, Quat, Vec3};
use gs_core::sunaware::checkpoint;
use gs_core::{Camera, Intrinsics};
use gs_online::keyframe::WindowConfig;
use gs_online::online::{
    Frame, Initialisation, OfferReport, OnlineConfig, OnlineTrainer, SkipReason,
};
use gs_online::resume;
use interfaces::crc::crc32_ieee;
use interfaces::messages::{EventKind, InitSource, PixelFormat};

pub const CHECKPOINT_MAGIC: &[u8; 8] = b"FSWSAL02";
/// Version 1: the model and round count only.
pub(crate) const CHECKPOINT_MAGIC_V1: &[u8; 8] = b"FSWSAL01";
/// Largest frame a checkpoint's window may hold, in pixels (16 Mpx: 4096 x 4096).
pub(crate) const MAX_CHECKPOINT_FRAME_PIXELS: usize = 1 << 24;

/// What to do when a checkpoint's model configuration differs from the configured one.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum OnConfigMismatch {
    /// Refuse the checkpoint (the default).
    #[default]
    Refuse,
    /// Load it and train on with its configuration (logged).
    UseCheckpoint,
}

/// How the adapter builds its online trainer.
#[derive(Clone, Debug)]
pub struct SunAwareSettings {
    pub online: OnlineConfig,
    /// How the model starts (`[model]`).
    pub model: ModelSettings,
    /// Where the rasterizer and the shadow pass run (`[training] backend`, opened by the
    /// runtime); the networks and Adam stay on the CPU. Not saved in checkpoints.
    pub backend: gs_core::engine::Backend,
    /// `[checkpoint] on_config_mismatch`.
    pub on_config_mismatch: OnConfigMismatch,
}

impl SunAwareSettings {
    /// The online trainer's defaults with the component's window; the unlit skip only on
    /// masked frames.
    pub fn with_window(window: WindowConfig) -> Self {
        Self {
            online: OnlineConfig {
                window,
                unlit_full_frame: false,
                ..OnlineConfig::default()
            },
            model: ModelSettings::default(),
            backend: gs_core::engine::Backend::Cpu,
            on_config_mismatch: OnConfigMismatch::Refuse,
        }
    }

    fn init_kind(&self) -> Result<InitKind, String> {
        self.model.validate().map_err(|e| e.to_string())
    }

    fn random_init(&self) -> Initialisation {
        Initialisation::RandomSphere {
            count: self.model.initial_gaussians,
            centre: Vec3::ZERO,
            radius_m: self.model.target_radius_m,
            seed: self.model.seed,
        }
    }

    /// A trainer on the random start.
    fn build(&self) -> Result<OnlineTrainer, String> {
        self.build_with(self.online.clone())
    }

    fn build_with(&self, online_config: OnlineConfig) -> Result<OnlineTrainer, String> {
        let mut online = OnlineTrainer::new(
            online_config,
            &self.random_init(),
            self.model.ball_scene_box()?,
        )
        .map_err(|e| e.to_string())?;
        online
            .trainer_mut()
            .set_backend(&self.backend)
            .map_err(|e| e.to_string())?;
        Ok(online)
    }
}

pub struct SunAwareLearner {
    settings: SunAwareSettings,
    init: InitKind,
    online: OnlineTrainer,
    /// The hull start is still to be carved (when the window first fills).
    hull_pending: bool,
    /// Events for the bus, taken by [`Learner::take_events`].
    events: Vec<EventKind>,
}

impl SunAwareLearner {
    pub fn new(settings: SunAwareSettings) -> Result<Self, String> {
        let init = settings.init_kind()?;
        let online = settings.build()?;
        let mut learner = Self {
            settings,
            init,
            online,
            hull_pending: false,
            events: Vec::new(),
        };
        learner.started();
        Ok(learner)
    }

    /// After a fresh random start: wait for the hull, or report the random start.
    fn started(&mut self) {
        self.hull_pending = self.init == InitKind::Hull;
        if !self.hull_pending {
            self.initialised(InitSource::Random);
        }
    }

    fn initialised(&mut self, source: InitSource) {
        let gaussians = u32::try_from(self.online.trainer().model.len()).unwrap_or(u32::MAX);
        self.events
            .push(EventKind::ModelInitialised { source, gaussians });
    }

    /// Carves the hull from the full window and restarts the model from it (or keeps the
    /// random start and says why).
    fn start_from_hull(&mut self) {
        self.hull_pending = false;
        let keyframes: Vec<&Frame> = self
            .online
            .window()
            .keyframes()
            .iter()
            .map(|k| &k.payload)
            .collect();
        let started = std::time::Instant::now();
        let source = match hull_start::carve(&keyframes, &self.settings.model) {
            Ok(start) => {
                eprintln!(
                    "fsw-component: visual hull from {} keyframes in {:.2} s: {} points, \
                     scene box {:?}..{:?} m",
                    start.views,
                    started.elapsed().as_secs_f64(),
                    start.points.len(),
                    start.scene_box.min_m(),
                    start.scene_box.max_m()
                );
                let init = Initialisation::SurfaceSamples {
                    points: start.points,
                    normals: None,
                    colours: Some(start.colours),
                };
                match self
                    .online
                    .restart_model(&init, start.scene_box, &self.settings.backend)
                {
                    Ok(()) => InitSource::Hull,
                    Err(error) => {
                        // Nothing changed: the random start stays.
                        eprintln!("fsw-component: hull start refused: {error}");
                        InitSource::RandomCarveFailed
                    }
                }
            }
            Err(HullStartError::TooFewMasks { .. }) => InitSource::RandomNoMasks,
            Err(error) => {
                eprintln!("fsw-component: visual hull not carved: {error}");
                InitSource::RandomCarveFailed
            }
        };
        self.initialised(source);
    }

    fn camera(intrinsics: Intrinsics, q: DQuat, t: DVec3) -> Camera {
        let q = q.normalize();
        Camera {
            intrinsics,
            rotation: Quat::from_xyzw(q.x as f32, q.y as f32, q.z as f32, q.w as f32),
            translation: t.as_vec3(),
        }
    }

    fn rounds(&self) -> u64 {
        self.online.rounds()
    }

    /// The online configuration to resume `parsed` with: the configured one when the
    /// checkpoint agrees with it, else refused or the checkpoint's (logged), as
    /// `on_config_mismatch` says; `log` reports a used mismatch.
    fn resumed_config(&self, parsed: &Parsed, log: bool) -> Result<OnlineConfig, LearnerError> {
        let configured = &self.settings.online;
        let stored_model = &parsed.trainer.model.config;
        let stored = parsed
            .resume
            .map(|(state, _)| resume::peek_settings(state))
            .transpose()
            .map_err(|e| LearnerError::BadCheckpoint(e.to_string()))?;
        let mut differences = Vec::new();
        if stored_model != &configured.model {
            // By name, so an operator sees which [training] key to set (e.g. a checkpoint
            // of the paper's model under the default learned-normal shading).
            differences.push(format!(
                "model settings (checkpoint, configured): {}",
                stored_model.differences(&configured.model).join("; ")
            ));
        }
        if let Some(s) = stored {
            if (s.shuffle_seed, s.window, s.replay_capacity)
                != (
                    configured.shuffle_seed,
                    configured.window,
                    configured.replay_capacity,
                )
            {
                differences.push(format!(
                    "online trainer: checkpoint window {:?}, shuffle seed {}, replay capacity \
                     {}; configured {:?}, {}, {}",
                    s.window,
                    s.shuffle_seed,
                    s.replay_capacity,
                    configured.window,
                    configured.shuffle_seed,
                    configured.replay_capacity
                ));
            }
        }
        if differences.is_empty() {
            return Ok(configured.clone());
        }
        let what = differences.join("; ");
        match self.settings.on_config_mismatch {
            OnConfigMismatch::Refuse => Err(LearnerError::BadCheckpoint(format!(
                "configuration differs from the checkpoint's (refused: [checkpoint] \
                 on_config_mismatch = \"refuse\"): {what}"
            ))),
            OnConfigMismatch::UseCheckpoint => {
                if log {
                    eprintln!(
                        "fsw-component: checkpoint configuration used instead of the configured \
                     one (on_config_mismatch = \"use_checkpoint\"): {what}"
                    );
                }
                let mut online = configured.clone();
                online.model = stored_model.clone();
                if let Some(s) = stored {
                    online.window = s.window;
                    online.shuffle_seed = s.shuffle_seed;
                    online.replay_capacity = s.replay_capacity;
                }
                Ok(online)
            }
        }
    }
}

fn to_unit_rgb(pixels: &[u8], format: PixelFormat) -> Vec<f32> {
    match format {
        PixelFormat::Rgb8 => pixels.iter().map(|&v| f32::from(v) / 255.0).collect(),
        PixelFormat::Gray8 => pixels
            .iter()
            .flat_map(|&v| [f32::from(v) / 255.0; 3])
            .collect(),
    }
}

fn to_u8(value: f32) -> u8 {
    // NaN maps to 0 (`as` saturates); the clamp keeps the rounding in range.
    (value.clamp(0.0, 1.0) * 255.0).round() as u8
}

/// The seam's summary of a round: `skipped_steps` travels on, so the worker can report
/// non-finite steps (the ICD's `TrainingNonFinite`).
fn round_summary(report: &gs_online::online::RoundReport, rounds: u64) -> RoundSummary {
    RoundSummary {
        rounds: u32::try_from(rounds).unwrap_or(u32::MAX),
        duration_ms: (report.duration_s * 1000.0).min(f64::from(u32::MAX)) as u32,
        loss: report.mean_loss,
        gaussians: u32::try_from(report.gaussians).unwrap_or(u32::MAX),
        skipped_steps: u32::try_from(report.skipped_steps).unwrap_or(u32::MAX),
    }
}

/// A checkpoint, checked and parsed.
struct Parsed<'a> {
    /// Rounds run (version 1: the stored count; version 2: the online state's).
    rounds: u64,
    trainer: gs_core::sunaware::SunAwareTrainer,
    /// Version 2: the online state and the hull start flag.
    resume: Option<(&'a [u8], bool)>,
}

fn word(bytes: &[u8], at: usize) -> u64 {
    let mut b = [0u8; 8];
    b.copy_from_slice(&bytes[at..at + 8]);
    u64::from_le_bytes(b)
}

/// Checks the component wrapper (magic, lengths, CRC) and parses the gs-core trainer, which
/// bounds every size and checks every value, and the online state's header.
fn parse_checkpoint(bytes: &[u8]) -> Result<Parsed<'_>, LearnerError> {
    let bad = |why: String| LearnerError::BadCheckpoint(why);
    let v2 = bytes.get(..8) == Some(CHECKPOINT_MAGIC);
    if bytes.len() < 28 || !(v2 || &bytes[..8] == CHECKPOINT_MAGIC_V1) {
        return Err(bad("not a Sun-aware component checkpoint (magic)".into()));
    }
    let (body, crc) = bytes.split_at(bytes.len() - 4);
    if crc32_ieee(body).to_le_bytes() != crc {
        return Err(bad("checksum mismatch".into()));
    }
    let (rounds, trainer_bytes, resume) = if v2 {
        let hull_pending = match body[8] {
            0 => false,
            1 => true,
            v => return Err(bad(format!("hull start flag {v} is neither 0 nor 1"))),
        };
        let len = usize::try_from(word(body, 9)).unwrap_or(usize::MAX);
        let trainer_end = len
            .checked_add(17)
            .filter(|&end| end.checked_add(8).is_some_and(|e| e <= body.len()))
            .ok_or_else(|| bad(format!("trainer length {len} exceeds the file")))?;
        let state_len = usize::try_from(word(body, trainer_end)).unwrap_or(usize::MAX);
        let state = &body[trainer_end + 8..];
        if state.len() != state_len {
            return Err(bad(format!(
                "online state length {state_len} disagrees with the file"
            )));
        }
        let settings = resume::peek_settings(state).map_err(|e| bad(e.to_string()))?;
        (
            settings.rounds,
            &body[17..trainer_end],
            Some((state, hull_pending)),
        )
    } else {
        let len = usize::try_from(word(body, 16)).unwrap_or(usize::MAX);
        if body.len() - 24 != len {
            return Err(bad(format!("trainer length {len} disagrees with the file")));
        }
        (word(body, 8), &body[24..], None)
    };
    // Health reports rounds as u32, and the count keeps growing after a load.
    if rounds > u64::from(u32::MAX / 2) {
        return Err(bad(format!("round count {rounds} is implausible")));
    }
    let trainer = checkpoint::from_bytes(trainer_bytes).map_err(|e| bad(e.to_string()))?;
    Ok(Parsed {
        rounds,
        trainer,
        resume,
    })
}

impl Learner for SunAwareLearner {
    fn offer(&mut self, frame: &ObservedFrame) -> OfferResult {
        let t = &frame.telemetry;
        let online_frame = Frame {
            id: u64::from(frame.frame_id),
            time_s: frame.time_us as f64 / 1e6,
            camera: Self::camera(frame.camera, t.camera_from_target, t.target_in_camera_m),
            sun_dir_target: t.sun_in_target.as_vec3(),
            image: to_unit_rgb(&frame.pixels, frame.format),
            mask: frame
                .mask
                .as_ref()
                .map(|m| m.iter().map(|&v| if v == 0 { 0.0 } else { 1.0 }).collect()),
            eclipse: t.eclipse,
        };
        match self.online.offer(online_frame) {
            Ok(OfferReport::Added { .. }) => OfferResult::Added,
            Ok(OfferReport::Skipped(SkipReason::ViewTooClose { .. } | SkipReason::DuplicateId)) => {
                OfferResult::NotAdded
            }
            Ok(OfferReport::Skipped(_)) => OfferResult::Skipped,
            // The worker reports it as an event; the frame never reaches the model.
            Err(_) => OfferResult::Refused,
        }
    }

    fn run_round_if_due(&mut self) -> Result<Option<RoundSummary>, LearnerError> {
        if self.hull_pending && self.online.round_due() {
            self.start_from_hull();
        }
        match self.online.run_round_if_due() {
            Ok(Some(report)) => Ok(Some(round_summary(&report, self.rounds()))),
            Ok(None) => Ok(None),
            Err(error) => Err(LearnerError::Training(error.to_string())),
        }
    }

    fn predict(&self, view: &ViewRequest) -> Result<PredictedImage, LearnerError> {
        if view.width == 0 || view.height == 0 {
            return Err(LearnerError::BadRequest("zero image size".into()));
        }
        if (view.intrinsics.width, view.intrinsics.height)
            != (u32::from(view.width), u32::from(view.height))
        {
            return Err(LearnerError::BadRequest(
                "camera size differs from the image size".into(),
            ));
        }
        let camera = Self::camera(
            view.intrinsics,
            view.camera_from_target,
            view.target_in_camera_m,
        );
        let rendered = self
            .online
            .predict(&camera, view.sun_in_target.as_vec3())
            .map_err(|e| LearnerError::BadRequest(e.to_string()))?;
        let pixels = match view.format {
            PixelFormat::Rgb8 => rendered.image.iter().map(|&v| to_u8(v)).collect(),
            PixelFormat::Gray8 => rendered
                .image
                .chunks_exact(3)
                .map(|c| to_u8((c[0] + c[1] + c[2]) / 3.0))
                .collect(),
        };
        Ok(PredictedImage {
            width: view.width,
            height: view.height,
            format: view.format,
            pixels,
        })
    }

    fn reset(&mut self) -> Result<(), LearnerError> {
        self.online = self.settings.build().map_err(LearnerError::Training)?;
        self.started();
        Ok(())
    }

    fn save(&self) -> Vec<u8> {
        let trainer = checkpoint::to_bytes(self.online.trainer());
        let state = self.online.state_bytes();
        let mut out = Vec::with_capacity(trainer.len() + state.len() + 32);
        out.extend_from_slice(CHECKPOINT_MAGIC);
        out.push(u8::from(self.hull_pending));
        out.extend_from_slice(&(trainer.len() as u64).to_le_bytes());
        out.extend_from_slice(&trainer);
        out.extend_from_slice(&(state.len() as u64).to_le_bytes());
        out.extend_from_slice(&state);
        let crc = crc32_ieee(&out);
        out.extend_from_slice(&crc.to_le_bytes());
        out
    }

    fn load(&mut self, bytes: &[u8]) -> Result<(), LearnerError> {
        let parsed = parse_checkpoint(bytes)?;
        let bad = LearnerError::BadCheckpoint;
        let online_config = self.resumed_config(&parsed, true)?;
        let mut online = self.settings.build_with(online_config).map_err(bad)?;
        *online.trainer_mut() = parsed.trainer;
        // A checkpoint holds no backend: the restored trainer runs where this one did.
        online
            .trainer_mut()
            .set_backend(&self.settings.backend)
            .map_err(|e| bad(e.to_string()))?;
        match parsed.resume {
            Some((state, hull_pending)) => {
                online
                    .restore_state(state, MAX_CHECKPOINT_FRAME_PIXELS)
                    .map_err(|e| bad(e.to_string()))?;
                self.online = online;
                self.hull_pending = hull_pending;
            }
            None => {
                eprintln!(
                    "fsw-component: version-1 checkpoint: model and {} rounds resumed, the \
                     keyframe window starts empty",
                    parsed.rounds
                );
                online.set_rounds(parsed.rounds);
                self.online = online;
                // A model that never trained is still the random start.
                self.hull_pending = self.init == InitKind::Hull && parsed.rounds == 0;
            }
        }
        Ok(())
    }

    fn inspect(&self, bytes: &[u8]) -> Result<u64, LearnerError> {
        let parsed = parse_checkpoint(bytes)?;
        // Inspecting is not using: the log line comes with the load.
        self.resumed_config(&parsed, false)?;
        Ok(parsed.rounds)
    }

    fn stats(&self) -> LearnerStats {
        LearnerStats {
            gaussians: u32::try_from(self.online.trainer().model.len()).unwrap_or(u32::MAX),
            rounds: u32::try_from(self.rounds()).unwrap_or(u32::MAX),
            window_fill: self.online.window().len().min(255) as u8,
            window_capacity: self.online.window().capacity().min(255) as u8,
        }
    }

    fn take_events(&mut self) -> Vec<EventKind> {
        std::mem::take(&mut self.events)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn skipped_steps_cross_the_seam() {
        let report = gs_online::online::RoundReport {
            rounds: 7,
            mean_loss: 0.25,
            duration_s: 1.5,
            gaussians: 2000,
            skipped_steps: 3,
            trained_ids: vec![1, 2],
            densified: None,
        };
        let summary = round_summary(&report, 9);
        assert_eq!(summary.skipped_steps, 3);
        assert_eq!(summary.rounds, 9);
        assert_eq!(summary.duration_ms, 1500);
        assert_eq!(summary.gaussians, 2000);
    }

    #[test]
    fn inspect_accepts_what_load_accepts_and_bounds_the_round_count() {
        let mut settings = SunAwareSettings::with_window(WindowConfig::default());
        settings.model.initial_gaussians = 50;
        let mut learner = SunAwareLearner::new(settings).unwrap();
        learner.online.set_rounds(7);
        let bytes = learner.save();
        assert_eq!(learner.inspect(&bytes), Ok(7));
        learner.load(&bytes).unwrap();
        assert_eq!(learner.stats().rounds, 7);
        // A checksummed file with an absurd round count is refused by both.
        let mut hostile = bytes[..bytes.len() - 4].to_vec();
        // Version 2: the round count follows the online state's magic and settings.
        let trainer_len = word(&hostile, 9) as usize;
        let rounds_at = 17 + trainer_len + 8 + 8 + 32;
        assert_eq!(word(&hostile, rounds_at), 7);
        hostile[rounds_at..rounds_at + 8].copy_from_slice(&u64::MAX.to_le_bytes());
        let crc = crc32_ieee(&hostile);
        hostile.extend_from_slice(&crc.to_le_bytes());
        assert!(learner.inspect(&hostile).is_err());
        assert!(learner.load(&hostile).is_err());
        assert_eq!(learner.stats().rounds, 7, "a refused load changes nothing");
    }
}

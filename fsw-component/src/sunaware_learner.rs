//! The Sun-aware online trainer (`online.rs`, gs-core) behind the component's [`Learner`] seam.
//!
//! Converts bus frames (8-bit RGB or gray, pose and Sun from the synchronizer) into
//! `online::Frame`s (RGB in [0, 1], camera = intrinsics + camera-from-target pose, Sun in
//! the target frame) and renders predictions back to 8-bit images.
//!
//! Camera intrinsics: the bus carries only the image size, and the component configuration has
//! no camera model yet, so the horizontal field of view is [`DEFAULT_FOV_X_RAD`] (the
//! simulator's default camera, SPEED: 1920 px wide, f = 3003.41 px) with square pixels and the
//! principal point at the image centre. Initialisation: random points in a ball of
//! [`DEFAULT_TARGET_RADIUS_M`] around the target origin (no surface samples on board); the
//! scene box is the ball's bounding cube.
//!
//! Checkpoint format (little-endian): magic `FSWSAL01`, rounds u64, trainer length u64, the
//! gs-core Sun-aware trainer checkpoint (Gaussians, features, latents, MLP weights, optimiser
//! state, step counters, RNG state; its own magic and checksum), then CRC-32/IEEE of all
//! before. Loading restores the model and optimiser exactly and continues the round count;
//! the keyframe window restarts empty (`OnlineTrainer` has no window restore yet).
//! Invariants: frames the online trainer refuses are skipped, never half-applied; nothing
//! non-finite enters the model (the online trainer validates, gs-core skips non-finite steps).

use crate::learner::{
    Learner, LearnerError, LearnerStats, ObservedFrame, OfferResult, PredictedImage, RoundSummary,
    ViewRequest,
};
use glam::{DQuat, DVec3, Quat, Vec3};
use gs_core::nn::SceneBox;
use gs_core::sunaware::checkpoint;
use gs_core::{Camera, Intrinsics};
use gs_online::keyframe::WindowConfig;
use gs_online::online::{
    Frame, Initialisation, OfferReport, OnlineConfig, OnlineTrainer, SkipReason,
};
use interfaces::crc::crc32_ieee;
use interfaces::messages::PixelFormat;

pub const CHECKPOINT_MAGIC: &[u8; 8] = b"FSWSAL01";
/// SPEED camera: 2 atan(960 / 3003.41).
pub const DEFAULT_FOV_X_RAD: f32 = 0.618_238;
pub const DEFAULT_TARGET_RADIUS_M: f32 = 5.0;
pub const DEFAULT_INITIAL_GAUSSIANS: usize = 2000;

/// How the adapter builds its online trainer.
#[derive(Clone, Debug)]
pub struct SunAwareSettings {
    pub online: OnlineConfig,
    pub fov_x_rad: f32,
    pub target_radius_m: f32,
    pub initial_gaussians: usize,
    pub init_seed: u64,
    /// Where the rasterizer and the shadow pass run (`[training] backend`, opened by the
    /// runtime); the networks and Adam stay on the CPU. Not saved in checkpoints.
    pub backend: gs_core::train::Backend,
}

impl SunAwareSettings {
    /// The online trainer's defaults with the component's window.
    pub fn with_window(window: WindowConfig) -> Self {
        Self {
            online: OnlineConfig {
                window,
                ..OnlineConfig::default()
            },
            fov_x_rad: DEFAULT_FOV_X_RAD,
            target_radius_m: DEFAULT_TARGET_RADIUS_M,
            initial_gaussians: DEFAULT_INITIAL_GAUSSIANS,
            init_seed: 0,
            backend: gs_core::train::Backend::Cpu,
        }
    }

    fn init(&self) -> Initialisation {
        Initialisation::RandomSphere {
            count: self.initial_gaussians,
            centre: Vec3::ZERO,
            radius_m: self.target_radius_m,
            seed: self.init_seed,
        }
    }

    fn scene_box(&self) -> Result<SceneBox, String> {
        let r = self.target_radius_m;
        SceneBox::new([-r; 3], [r; 3]).map_err(|e| e.to_string())
    }

    fn build(&self) -> Result<OnlineTrainer, String> {
        let mut online = OnlineTrainer::new(self.online.clone(), &self.init(), self.scene_box()?)
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
    online: OnlineTrainer,
    /// Rounds run before the last checkpoint load (the online trainer restarts at zero).
    rounds_offset: u64,
}

impl SunAwareLearner {
    pub fn new(settings: SunAwareSettings) -> Result<Self, String> {
        let online = settings.build()?;
        Ok(Self {
            settings,
            online,
            rounds_offset: 0,
        })
    }

    fn camera(&self, q: DQuat, t: DVec3, width: u16, height: u16) -> Camera {
        let q = q.normalize();
        Camera {
            intrinsics: Intrinsics::from_fov_x(
                self.settings.fov_x_rad,
                u32::from(width),
                u32::from(height),
            ),
            rotation: Quat::from_xyzw(q.x as f32, q.y as f32, q.z as f32, q.w as f32),
            translation: t.as_vec3(),
        }
    }

    fn rounds(&self) -> u64 {
        self.rounds_offset + self.online.rounds()
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

/// Checks the component wrapper (magic, length, CRC) and parses the gs-core trainer, which
/// bounds every size and checks every value; returns the stored round count.
fn parse_checkpoint(
    bytes: &[u8],
) -> Result<(u64, gs_core::sunaware::SunAwareTrainer), LearnerError> {
    let bad = |why: String| LearnerError::BadCheckpoint(why);
    if bytes.len() < 28 || &bytes[..8] != CHECKPOINT_MAGIC {
        return Err(bad("not a Sun-aware component checkpoint (magic)".into()));
    }
    let (body, crc) = bytes.split_at(bytes.len() - 4);
    if crc32_ieee(body).to_le_bytes() != crc {
        return Err(bad("checksum mismatch".into()));
    }
    let word = |at: usize| {
        let mut b = [0u8; 8];
        b.copy_from_slice(&body[at..at + 8]);
        u64::from_le_bytes(b)
    };
    let rounds = word(8);
    // Health reports rounds as u32, and the count keeps growing after a load.
    if rounds > u64::from(u32::MAX / 2) {
        return Err(bad(format!("round count {rounds} is implausible")));
    }
    let len = usize::try_from(word(16)).unwrap_or(usize::MAX);
    if body.len() - 24 != len {
        return Err(bad(format!("trainer length {len} disagrees with the file")));
    }
    let trainer = checkpoint::from_bytes(&body[24..]).map_err(|e| bad(e.to_string()))?;
    Ok((rounds, trainer))
}

impl Learner for SunAwareLearner {
    fn offer(&mut self, frame: &ObservedFrame) -> OfferResult {
        let t = &frame.telemetry;
        let online_frame = Frame {
            id: u64::from(frame.frame_id),
            time_s: frame.time_us as f64 / 1e6,
            camera: self.camera(
                t.camera_from_target,
                t.target_in_camera_m,
                frame.width,
                frame.height,
            ),
            sun_dir_target: t.sun_in_target.as_vec3(),
            image: to_unit_rgb(&frame.pixels, frame.format),
            mask: frame
                .mask
                .as_ref()
                .map(|m| m.iter().map(|&v| if v == 0 { 0.0 } else { 1.0 }).collect()),
            eclipse: false,
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
        let camera = self.camera(
            view.camera_from_target,
            view.target_in_camera_m,
            view.width,
            view.height,
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
        self.rounds_offset = 0;
        Ok(())
    }

    fn save(&self) -> Vec<u8> {
        let trainer = checkpoint::to_bytes(self.online.trainer());
        let mut out = Vec::with_capacity(trainer.len() + 32);
        out.extend_from_slice(CHECKPOINT_MAGIC);
        out.extend_from_slice(&self.rounds().to_le_bytes());
        out.extend_from_slice(&(trainer.len() as u64).to_le_bytes());
        out.extend_from_slice(&trainer);
        let crc = crc32_ieee(&out);
        out.extend_from_slice(&crc.to_le_bytes());
        out
    }

    fn load(&mut self, bytes: &[u8]) -> Result<(), LearnerError> {
        let (rounds, trainer) = parse_checkpoint(bytes)?;
        let bad = LearnerError::BadCheckpoint;
        let mut online = self.settings.build().map_err(bad)?;
        *online.trainer_mut() = trainer;
        // A checkpoint holds no backend: the restored trainer runs where this one did.
        online
            .trainer_mut()
            .set_backend(&self.settings.backend)
            .map_err(|e| bad(e.to_string()))?;
        self.online = online;
        self.rounds_offset = rounds;
        Ok(())
    }

    fn inspect(&self, bytes: &[u8]) -> Result<u64, LearnerError> {
        parse_checkpoint(bytes).map(|(rounds, _)| rounds)
    }

    fn stats(&self) -> LearnerStats {
        LearnerStats {
            gaussians: u32::try_from(self.online.trainer().model.len()).unwrap_or(u32::MAX),
            rounds: u32::try_from(self.rounds()).unwrap_or(u32::MAX),
            window_fill: self.online.window().len().min(255) as u8,
            window_capacity: self.online.window().capacity().min(255) as u8,
        }
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
        settings.initial_gaussians = 50;
        let mut learner = SunAwareLearner::new(settings).unwrap();
        learner.rounds_offset = 7;
        let bytes = learner.save();
        assert_eq!(learner.inspect(&bytes), Ok(7));
        learner.load(&bytes).unwrap();
        assert_eq!(learner.stats().rounds, 7);
        // A checksummed file with an absurd round count is refused by both.
        let mut hostile = bytes[..bytes.len() - 4].to_vec();
        hostile[8..16].copy_from_slice(&u64::MAX.to_le_bytes());
        let crc = crc32_ieee(&hostile);
        hostile.extend_from_slice(&crc.to_le_bytes());
        assert!(learner.inspect(&hostile).is_err());
        assert!(learner.load(&hostile).is_err());
        assert_eq!(learner.stats().rounds, 7, "a refused load changes nothing");
    }
}

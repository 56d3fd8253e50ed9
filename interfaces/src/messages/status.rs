//! What the component reports about itself: periodic health (1 Hz, also during training
//! rounds) and events (mode changes, errors). Quantities that may not exist yet (no round run,
//! no prediction made) are `Option`s rather than NaN sentinels.

use super::command::Mode;
use super::validate::{check_finite, check_non_negative, ValidationError};
use super::{port, Direction, Message, Version};
use serde::{Deserialize, Serialize};

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct HealthStatus {
    pub time_us: u64,
    pub mode: Mode,
    pub uptime_s: u32,
    pub frames_received: u32,
    /// Frames that entered the keyframe window.
    pub frames_used: u32,
    /// Frames dropped (queue full, telemetry missing/stale/invalid, eclipse).
    pub frames_dropped: u32,
    /// Messages that failed to decode or validate.
    pub decode_errors: u32,
    /// CAN transfer CRC and CCSDS message CRC failures.
    pub crc_errors: u32,
    pub commands_accepted: u32,
    pub commands_rejected: u32,
    pub gaussians: u32,
    pub rounds: u32,
    pub last_round_duration_ms: Option<u32>,
    pub last_loss: Option<f32>,
    pub last_prediction_psnr_db: Option<f32>,
    pub window_fill: u8,
    pub window_capacity: u8,
    /// Depth of the frame queue towards the trainer.
    pub frame_queue_depth: u16,
    /// Depth of the outgoing publication queue.
    pub publish_queue_depth: u16,
    /// Resident memory of the component, bytes.
    pub memory_bytes: u64,
}

impl HealthStatus {
    /// Largest possible encoding, bytes.
    pub const MAX_ENCODED_LEN: usize = 95;
}

impl Message for HealthStatus {
    const PORT_ID: u16 = port::HEALTH_STATUS;
    const VERSION: Version = Version { major: 1, minor: 0 };
    const NAME: &'static str = "HealthStatus";
    const DIRECTION: Direction = Direction::FromComponent;

    fn validate(&self) -> Result<(), ValidationError> {
        if let Some(loss) = self.last_loss {
            check_non_negative("last_loss", loss)?;
        }
        if let Some(psnr) = self.last_prediction_psnr_db {
            check_finite("last_prediction_psnr_db", &[psnr])?;
        }
        if self.window_fill > self.window_capacity {
            return Err(ValidationError::OutOfRange {
                field: "window_fill",
            });
        }
        Ok(())
    }
}

/// Error codes carried by [`EventKind::Error`]; the wire value is the variant index.
/// Never reorder, only append.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum ErrorCode {
    DecodeError,
    CrcError,
    QueueOverflow,
    TelemetryMissing,
    TelemetryStale,
    TelemetryInvalid,
    CheckpointSaveFailed,
    CheckpointLoadFailed,
    TrainingNonFinite,
    RenderFailed,
    Internal,
    // Version 1.1 of `Event` appends these.
    /// A command from a source outside the allow-list (no acknowledgement is sent).
    CommandUnauthorised,
    /// RESET_MODEL or LOAD_CHECKPOINT without a valid ARM from the same source.
    CommandNotArmed,
    /// An expensive command (RENDER) above its rate limit.
    CommandRateLimited,
    /// A telemetry time tag too far from the receive clock: the sample was dropped.
    TelemetryTimeOutOfBounds,
    /// Consistent telemetry on a new clock: a stream's buffer was cleared to follow it.
    TelemetryClockJump,
    // Version 1.2 of `Event` appends this.
    /// A camera frame without its own camera model whose size is not the configured
    /// camera's (detail: frames since the last such event).
    CameraMismatch,
    // Version 1.3 of `Event` appends this.
    /// A rendered prediction too large for CAN FD (`[can] prediction_max_bytes`) went out
    /// on UDP only; sent once per run, for the first one (detail: its encoded size, bytes).
    PredictionNotOnCan,
}

impl ErrorCode {
    /// Every code in wire order (index = wire value).
    pub const ALL: [ErrorCode; 18] = [
        ErrorCode::DecodeError,
        ErrorCode::CrcError,
        ErrorCode::QueueOverflow,
        ErrorCode::TelemetryMissing,
        ErrorCode::TelemetryStale,
        ErrorCode::TelemetryInvalid,
        ErrorCode::CheckpointSaveFailed,
        ErrorCode::CheckpointLoadFailed,
        ErrorCode::TrainingNonFinite,
        ErrorCode::RenderFailed,
        ErrorCode::Internal,
        ErrorCode::CommandUnauthorised,
        ErrorCode::CommandNotArmed,
        ErrorCode::CommandRateLimited,
        ErrorCode::TelemetryTimeOutOfBounds,
        ErrorCode::TelemetryClockJump,
        ErrorCode::CameraMismatch,
        ErrorCode::PredictionNotOnCan,
    ];
    /// Number of codes: size per-code tables with this, never with a literal.
    pub const COUNT: usize = Self::ALL.len();

    /// The wire value, usable as an index below [`ErrorCode::COUNT`].
    pub const fn index(self) -> usize {
        self as usize
    }
}

/// Where the component's starting model came from ([`EventKind::ModelInitialised`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum InitSource {
    /// Random points, as configured (`[model] init = "random"`).
    Random,
    /// A visual hull carved from the first keyframes' masks and poses.
    Hull,
    /// Random points because the keyframes carried too few masks to carve a hull.
    RandomNoMasks,
    /// Random points because carving failed (e.g. every voxel carved away).
    RandomCarveFailed,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum EventKind {
    ModeChanged {
        from: Mode,
        to: Mode,
    },
    Error {
        code: ErrorCode,
        detail: u32,
    },
    CheckpointSaved {
        rounds: u32,
    },
    CheckpointLoaded {
        rounds: u32,
    },
    ModelReset,
    /// The model that training starts from (random at start, or when the window first
    /// fills with `init = "hull"`), and its Gaussian count.
    ModelInitialised {
        source: InitSource,
        gaussians: u32,
    },
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Event {
    pub time_us: u64,
    pub kind: EventKind,
}

impl Event {
    /// Largest possible encoding, bytes.
    pub const MAX_ENCODED_LEN: usize = 17;
}

impl Message for Event {
    const PORT_ID: u16 = port::EVENT;
    const VERSION: Version = Version { major: 1, minor: 3 };
    const NAME: &'static str = "Event";
    const DIRECTION: Direction = Direction::FromComponent;

    fn validate(&self) -> Result<(), ValidationError> {
        Ok(())
    }
}

/// `detail` values of [`EventKind::Error`] for the codes whose detail is a reason, not a
/// count (the ICD's table lists them). `TrainingNonFinite`'s detail is the number of
/// optimisation steps the round skipped.
pub mod event_detail {
    /// `CheckpointSaveFailed`: writing, syncing or renaming the file failed.
    pub const SAVE_IO: u32 = 0;
    /// `CheckpointSaveFailed`: the file read back differs from what was written.
    pub const SAVE_VERIFY_FAILED: u32 = 1;
    /// `CheckpointSaveFailed`: refused, the model has fewer training rounds than the one on
    /// disk (RESET_MODEL is the command that allows replacing it).
    pub const SAVE_REFUSED_FEWER_ROUNDS: u32 = 2;
    /// `CheckpointSaveFailed`: refused, the model's own reader would not accept the bytes
    /// (e.g. a non-finite optimiser moment).
    pub const SAVE_REFUSED_UNREADABLE: u32 = 3;
    /// `CheckpointLoadFailed`: no slot holds a checkpoint the model accepts.
    pub const LOAD_NOTHING_USABLE: u32 = 0;
    /// `CheckpointLoadFailed`: the newest slot was refused; the previous one was loaded.
    pub const LOAD_NEWEST_FAILED_PREVIOUS_USED: u32 = 1;
    /// `Internal`: the trainer panicked; the learner was restarted from the newest usable
    /// checkpoint (or afresh).
    pub const TRAINER_PANICKED: u32 = 1;
    /// `Internal`: a trainer job (a frame with its round, or a command) ran past
    /// `training.round_deadline_ms`.
    pub const ROUND_DEADLINE_MISSED: u32 = 2;
    /// `Internal`: the model refused a synchronised frame (it failed its own checks).
    pub const FRAME_REFUSED_BY_MODEL: u32 = 3;
    /// `Internal`: a training round failed with an error (nothing was applied).
    pub const ROUND_FAILED: u32 = 4;
    /// `Internal`: the trainer panicked three times without a job completing in between
    /// (or its restart failed); the component stays in Idle until commanded.
    pub const TRAINER_GAVE_UP: u32 = 5;
    /// `Internal`: RESET_MODEL failed; the model is as before.
    pub const RESET_FAILED: u32 = 6;
}

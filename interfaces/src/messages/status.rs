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
    /// A camera frame without its own camera model whose size is not the configured
    /// camera's (detail: frames since the last such event).
    CameraMismatch,
}

impl ErrorCode {
    /// Number of codes (the last wire value + 1).
    pub const COUNT: usize = ErrorCode::CameraMismatch as usize + 1;
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
    const VERSION: Version = Version { major: 1, minor: 1 };
    const NAME: &'static str = "Event";
    const DIRECTION: Direction = Direction::FromComponent;

    fn validate(&self) -> Result<(), ValidationError> {
        Ok(())
    }
}

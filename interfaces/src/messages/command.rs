//! Commands to the component and their acknowledgements.
//!
//! Wire layout of a command (postcard): `varint sequence | varint opcode | arguments`.
//! The opcode is the [`CommandKind`] variant index (NOOP = 0 ... ARM = 7), so
//! [`decode_command`] can tell an unknown opcode (INVALID_OPCODE) from malformed bytes
//! (FORMAT_ERROR) and from bad arguments (VALIDATION_ERROR), and still report the sequence
//! number in the acknowledgement whenever it could be read.

use super::validate::{check_finite, check_unit_norm, ValidationError};
use super::{decode, port, CodecError, Direction, Message, Version};
use crate::ccsds::PacketType;
use serde::{Deserialize, Serialize};

/// Operating mode of the component.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Mode {
    /// Listens and publishes health; neither trains nor predicts.
    Idle,
    /// Keyframe window, training rounds and per-frame predictions.
    Train,
    /// Predictions only; the model is frozen.
    PredictOnly,
}

/// Arguments of RENDER: a pose and a Sun direction to render the current model for.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct RenderRequest {
    /// Unit quaternion [w, x, y, z], target body -> camera.
    pub q_camera_from_target: [f32; 4],
    /// Target origin in the camera frame, metres.
    pub t_camera_from_target_m: [f32; 3],
    /// Unit Sun direction in the target body frame.
    pub sun_target: [f32; 3],
}

/// Opcode and arguments. Variant order is the opcode: never reorder, only append.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum CommandKind {
    Noop,
    ResetCounters,
    ResetModel,
    SaveCheckpoint,
    LoadCheckpoint,
    SetMode(Mode),
    Render(RenderRequest),
    /// Version 1.1: arms the destructive command with this opcode (RESET_MODEL or
    /// LOAD_CHECKPOINT) for the component's configured arm time, for the same source.
    Arm(u32),
}

impl CommandKind {
    /// Number of defined opcodes.
    pub const OPCODE_COUNT: u32 = 8;
    pub const RESET_MODEL: u32 = 2;
    pub const LOAD_CHECKPOINT: u32 = 4;
    pub const RENDER: u32 = 6;

    /// Commands that destroy or replace the model: they need an ARM first.
    pub const fn is_destructive_opcode(opcode: u32) -> bool {
        opcode == Self::RESET_MODEL || opcode == Self::LOAD_CHECKPOINT
    }

    pub const fn opcode(&self) -> u32 {
        match self {
            CommandKind::Noop => 0,
            CommandKind::ResetCounters => 1,
            CommandKind::ResetModel => 2,
            CommandKind::SaveCheckpoint => 3,
            CommandKind::LoadCheckpoint => 4,
            CommandKind::SetMode(_) => 5,
            CommandKind::Render(_) => 6,
            CommandKind::Arm(_) => 7,
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Command {
    /// Sender's running command counter, echoed in the acknowledgement.
    pub sequence: u32,
    pub kind: CommandKind,
}

impl Command {
    /// Largest possible encoding (a RENDER command), bytes.
    pub const MAX_ENCODED_LEN: usize = 46;
}

impl Message for Command {
    const PORT_ID: u16 = port::COMMAND;
    const VERSION: Version = Version { major: 1, minor: 1 };
    const NAME: &'static str = "Command";
    const DIRECTION: Direction = Direction::ToComponent;
    const CCSDS_PACKET_TYPE: PacketType = PacketType::Telecommand;

    fn validate(&self) -> Result<(), ValidationError> {
        if let CommandKind::Render(r) = &self.kind {
            check_unit_norm("q_camera_from_target", &r.q_camera_from_target)?;
            check_finite("t_camera_from_target_m", &r.t_camera_from_target_m)?;
            check_unit_norm("sun_target", &r.sun_target)?;
        }
        if let CommandKind::Arm(opcode) = self.kind {
            if !CommandKind::is_destructive_opcode(opcode) {
                return Err(ValidationError::OutOfRange {
                    field: "arm opcode",
                });
            }
        }
        Ok(())
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum AckStatus {
    Ok,
    InvalidOpcode,
    ValidationError,
    FormatError,
    ExecutionError,
    Busy,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct CommandAck {
    /// The command's sequence number, `None` when not even that could be read.
    pub sequence: Option<u32>,
    /// The command's opcode as received, when it could be read.
    pub opcode: Option<u32>,
    pub status: AckStatus,
    /// Status-specific detail code (0 when none), e.g. an [`super::ErrorCode`] index.
    pub detail: u16,
}

impl CommandAck {
    /// Largest possible encoding, bytes.
    pub const MAX_ENCODED_LEN: usize = 16;
}

impl Message for CommandAck {
    const PORT_ID: u16 = port::COMMAND_ACK;
    const VERSION: Version = Version { major: 1, minor: 0 };
    const NAME: &'static str = "CommandAck";
    const DIRECTION: Direction = Direction::FromComponent;

    fn validate(&self) -> Result<(), ValidationError> {
        Ok(())
    }
}

/// Why a command was refused before execution, with what could be read of it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CommandDecodeError {
    pub sequence: Option<u32>,
    pub opcode: Option<u32>,
    pub status: AckStatus,
    /// Set for [`AckStatus::ValidationError`].
    pub validation: Option<ValidationError>,
}

impl core::fmt::Display for CommandDecodeError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        write!(f, "command refused ({:?})", self.status)?;
        if let Some(sequence) = self.sequence {
            write!(f, ", sequence {sequence}")?;
        }
        if let Some(opcode) = self.opcode {
            write!(f, ", opcode {opcode}")?;
        }
        if let Some(v) = &self.validation {
            write!(f, ": {v}")?;
        }
        Ok(())
    }
}

impl core::error::Error for CommandDecodeError {}

impl CommandDecodeError {
    /// The acknowledgement to send back.
    pub fn ack(&self) -> CommandAck {
        CommandAck {
            sequence: self.sequence,
            opcode: self.opcode,
            status: self.status,
            detail: 0,
        }
    }
}

impl Command {
    /// The OK acknowledgement of this command.
    pub fn ack(&self, status: AckStatus) -> CommandAck {
        CommandAck {
            sequence: Some(self.sequence),
            opcode: Some(self.kind.opcode()),
            status,
            detail: 0,
        }
    }
}

/// Decodes a command, classifying failures as the acknowledgement statuses require.
pub fn decode_command(bytes: &[u8]) -> Result<Command, CommandDecodeError> {
    let format = |sequence, opcode| CommandDecodeError {
        sequence,
        opcode,
        status: AckStatus::FormatError,
        validation: None,
    };
    let (sequence, rest) =
        postcard::take_from_bytes::<u32>(bytes).map_err(|_| format(None, None))?;
    let (opcode, _) =
        postcard::take_from_bytes::<u32>(rest).map_err(|_| format(Some(sequence), None))?;
    if opcode >= CommandKind::OPCODE_COUNT {
        return Err(CommandDecodeError {
            sequence: Some(sequence),
            opcode: Some(opcode),
            status: AckStatus::InvalidOpcode,
            validation: None,
        });
    }
    decode::<Command>(bytes).map_err(|e| match e {
        CodecError::Invalid(v) => CommandDecodeError {
            sequence: Some(sequence),
            opcode: Some(opcode),
            status: AckStatus::ValidationError,
            validation: Some(v),
        },
        _ => format(Some(sequence), Some(opcode)),
    })
}

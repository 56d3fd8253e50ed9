//! The message catalogue: every struct that travels on the bus, its fixed port ID (Cyphal
//! subject-ID on CAN and CCSDS APID on UDP: the same number, below 2047), its version, and
//! the postcard codec with validation.
//!
//! Invariants: [`encode`] refuses an invalid message (so we never emit NaN or non-unit
//! rotations); [`decode`] accepts trailing zero bytes only (CAN FD padding) and validates.
//! Large payloads are borrowed `&[u8]` slices of the caller's buffer: no copies, no allocation.

pub mod appended;
pub mod command;
pub mod image;
pub mod status;
pub mod telemetry;
pub mod validate;

pub use command::{
    decode_command, AckStatus, Command, CommandAck, CommandDecodeError, CommandKind, Mode,
    RenderRequest,
};
pub use image::{
    CameraFrame, CameraModel, Distortion, FrameHeader, PixelFormat, PredictionSource,
    RenderedPrediction,
};
pub use status::{event_detail, ErrorCode, Event, EventKind, HealthStatus, InitSource};
pub use telemetry::{SunVector, TargetPose};
pub use validate::ValidationError;

use crate::ccsds::PacketType;
use core::fmt;
use serde::{Deserialize, Serialize};

/// Message version: a minor bump adds fields at the end only; a major bump breaks layout.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Version {
    pub major: u8,
    pub minor: u8,
}

/// Who sends a message, seen from the flight component.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Direction {
    ToComponent,
    FromComponent,
}

/// Static facts about a catalogue entry.
pub trait Message {
    /// Cyphal subject-ID and CCSDS APID (0..=2046).
    const PORT_ID: u16;
    const VERSION: Version;
    const NAME: &'static str;
    const DIRECTION: Direction;
    /// Telecommand for commands, telemetry for everything else.
    const CCSDS_PACKET_TYPE: PacketType = PacketType::Telemetry;
    /// Field checks (finite values, unit norms, buffer sizes).
    fn validate(&self) -> Result<(), ValidationError>;
}

/// Port IDs in one place, so a collision is visible at a glance (and tested).
pub mod port {
    pub const SUN_VECTOR: u16 = 100;
    pub const TARGET_POSE: u16 = 101;
    pub const CAMERA_FRAME: u16 = 200;
    pub const RENDERED_PREDICTION: u16 = 201;
    pub const COMMAND: u16 = 300;
    pub const COMMAND_ACK: u16 = 301;
    pub const HEALTH_STATUS: u16 = 400;
    pub const EVENT: u16 = 401;
    pub const ALL: [u16; 8] = [
        SUN_VECTOR,
        TARGET_POSE,
        CAMERA_FRAME,
        RENDERED_PREDICTION,
        COMMAND,
        COMMAND_ACK,
        HEALTH_STATUS,
        EVENT,
    ];
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub enum CodecError {
    /// The output buffer cannot hold the encoded message.
    BufferTooSmall,
    /// Bytes are not a postcard encoding of the message (truncated, bad enum tag, bad varint).
    Format,
    /// Non-zero bytes after the message.
    TrailingBytes,
    /// Decoded fine, but a field is invalid.
    Invalid(ValidationError),
}

impl core::error::Error for CodecError {}

impl fmt::Display for CodecError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            CodecError::BufferTooSmall => f.write_str("output buffer too small"),
            CodecError::Format => f.write_str("malformed message bytes"),
            CodecError::TrailingBytes => f.write_str("non-zero bytes after the message"),
            CodecError::Invalid(e) => write!(f, "invalid field: {e}"),
        }
    }
}

/// Validates and encodes `msg` into `buf`, returning the used prefix.
pub fn encode<'b, M: Message + Serialize>(
    msg: &M,
    buf: &'b mut [u8],
) -> Result<&'b mut [u8], CodecError> {
    msg.validate().map_err(CodecError::Invalid)?;
    postcard::to_slice(msg, buf).map_err(|e| match e {
        postcard::Error::SerializeBufferFull => CodecError::BufferTooSmall,
        _ => CodecError::Format,
    })
}

/// Encoded size of `msg` in bytes (no validation).
pub fn encoded_len<M: Serialize>(msg: &M) -> Result<usize, CodecError> {
    postcard::serialize_with_flavor(msg, postcard::ser_flavors::Size::default())
        .map_err(|_| CodecError::Format)
}

/// Decodes and validates; trailing zero bytes (CAN FD padding) are ignored.
pub fn decode<'de, M: Message + Deserialize<'de>>(bytes: &'de [u8]) -> Result<M, CodecError> {
    let (msg, rest) = postcard::take_from_bytes::<M>(bytes).map_err(|_| CodecError::Format)?;
    if rest.iter().any(|&b| b != 0) {
        return Err(CodecError::TrailingBytes);
    }
    msg.validate().map_err(CodecError::Invalid)?;
    Ok(msg)
}

/// serde helpers that write byte slices as postcard byte strings (length + raw bytes) in one
/// call instead of element by element; reading uses serde's borrowed `&[u8]` as is.
pub(crate) mod bytes {
    use serde::Serializer;

    pub fn serialize<S: Serializer>(bytes: &&[u8], s: S) -> Result<S::Ok, S::Error> {
        s.serialize_bytes(bytes)
    }

    pub fn serialize_option<S: Serializer>(bytes: &Option<&[u8]>, s: S) -> Result<S::Ok, S::Error> {
        struct Raw<'a>(&'a [u8]);
        impl serde::Serialize for Raw<'_> {
            fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
                s.serialize_bytes(self.0)
            }
        }
        match bytes {
            Some(b) => s.serialize_some(&Raw(b)),
            None => s.serialize_none(),
        }
    }
}

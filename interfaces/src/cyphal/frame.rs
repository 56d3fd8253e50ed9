//! Cyphal/CAN v1.0 frame-level pieces: the 29-bit message CAN ID, the tail byte and CAN FD
//! data-length rounding.
//!
//! Message CAN ID layout (Cyphal Specification v1.0, section 4.2):
//! `priority[28:26] | service=0 [25] | anonymous [24] | reserved=0 [23] | reserved=1 [22:21]
//!  | subject-ID [20:8] | reserved=0 [7] | source node-ID [6:0]`.
//! Bits 22 and 21 are set on transmit and ignored on receive; bits 23 and 7 must be zero
//! (a frame with either set belongs to another protocol and is rejected).
//! Service CAN ID layout (same section):
//! `priority[28:26] | service=1 [25] | request-not-response [24] | reserved=0 [23]
//!  | service-ID [22:14] | destination node-ID [13:7] | source node-ID [6:0]`.
//! Tail byte: `start [7] | end [6] | toggle [5] | transfer-ID [4:0]`.

use core::fmt;

/// Classic CAN payload capacity in bytes (including the tail byte).
pub const CLASSIC_MTU: usize = 8;
/// CAN FD payload capacity in bytes (including the tail byte).
pub const FD_MTU: usize = 64;
/// Subject-IDs are 13 bits.
pub const MAX_SUBJECT_ID: u16 = 8191;
/// Service-IDs are 9 bits.
pub const MAX_SERVICE_ID: u16 = 511;
/// Node-IDs are 7 bits.
pub const MAX_NODE_ID: u8 = 127;
/// Transfer-IDs on CAN are 5 bits and wrap modulo 32.
pub const TRANSFER_ID_MODULO: u8 = 32;

/// The data lengths a CAN FD frame can have (DLC 0..15).
pub const FD_VALID_LENGTHS: [usize; 16] = [0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64];

const BIT_SERVICE: u32 = 1 << 25;
const BIT_ANONYMOUS: u32 = 1 << 24;
const BIT_R23: u32 = 1 << 23;
const BITS_R22_R21: u32 = 3 << 21;
const BIT_R7: u32 = 1 << 7;
const CAN_EXT_ID_MASK: u32 = (1 << 29) - 1;

/// Which CAN flavour a transfer is split for.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Mtu {
    /// Classic CAN 2.0: 8 data bytes per frame.
    Classic,
    /// CAN FD: up to 64 data bytes per frame.
    Fd,
}

impl Mtu {
    /// Frame data capacity in bytes, tail byte included.
    pub const fn bytes(self) -> usize {
        match self {
            Mtu::Classic => CLASSIC_MTU,
            Mtu::Fd => FD_MTU,
        }
    }
}

/// Smallest valid CAN FD data length that holds `len` bytes, or `None` above 64.
pub fn round_up_frame_length(len: usize) -> Option<usize> {
    FD_VALID_LENGTHS.iter().copied().find(|&valid| valid >= len)
}

/// Whether `len` is a data length some CAN frame (classic or FD) can have.
pub fn is_valid_frame_length(len: usize) -> bool {
    FD_VALID_LENGTHS.contains(&len)
}

/// Cyphal transfer priority (0 = most urgent).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Priority {
    Exceptional = 0,
    Immediate = 1,
    Fast = 2,
    High = 3,
    Nominal = 4,
    Low = 5,
    Slow = 6,
    Optional = 7,
}

impl Priority {
    /// Priority from its 3-bit code; higher bits are ignored.
    pub const fn from_bits(bits: u8) -> Self {
        match bits & 7 {
            0 => Priority::Exceptional,
            1 => Priority::Immediate,
            2 => Priority::Fast,
            3 => Priority::High,
            4 => Priority::Nominal,
            5 => Priority::Low,
            6 => Priority::Slow,
            _ => Priority::Optional,
        }
    }
}

/// Why a CAN ID is not a Cyphal/CAN message ID we can take.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CanIdError {
    /// More than 29 bits: not an extended CAN ID.
    NotExtended,
    /// Service (request/response) transfers are not supported by this implementation.
    ServiceTransfer,
    /// Reserved bit 23 or bit 7 set: another protocol (or a future Cyphal version).
    ReservedBitSet,
    /// A field is out of its range on transmit.
    FieldOutOfRange,
    /// A message ID where a service ID was expected.
    NotService,
}

impl core::error::Error for CanIdError {}

impl fmt::Display for CanIdError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            CanIdError::NotExtended => f.write_str("CAN ID wider than 29 bits"),
            CanIdError::ServiceTransfer => f.write_str("service transfers are not supported"),
            CanIdError::ReservedBitSet => f.write_str("reserved bit 23 or 7 set: not Cyphal"),
            CanIdError::FieldOutOfRange => {
                f.write_str("subject-ID, service-ID or node-ID out of range")
            }
            CanIdError::NotService => f.write_str("message CAN ID where a service ID was expected"),
        }
    }
}

/// The header fields carried by a message frame's CAN ID.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct MessageCanId {
    pub priority: Priority,
    /// 0..=8191.
    pub subject_id: u16,
    /// `None` for anonymous transfers (single-frame only).
    pub source_node_id: Option<u8>,
}

impl MessageCanId {
    /// The 29-bit identifier for a named (non-anonymous) source.
    pub fn to_raw(&self) -> Result<u32, CanIdError> {
        let source = self.source_node_id.ok_or(CanIdError::FieldOutOfRange)?;
        if self.subject_id > MAX_SUBJECT_ID || source > MAX_NODE_ID {
            return Err(CanIdError::FieldOutOfRange);
        }
        Ok(((self.priority as u32) << 26)
            | BITS_R22_R21
            | (u32::from(self.subject_id) << 8)
            | u32::from(source))
    }

    /// The 29-bit identifier of an anonymous message with the given pseudo node-ID
    /// (the specification asks the sender to derive it from the payload so that colliding
    /// anonymous frames differ).
    pub fn to_raw_anonymous(&self, pseudo_node_id: u8) -> Result<u32, CanIdError> {
        if self.subject_id > MAX_SUBJECT_ID || pseudo_node_id > MAX_NODE_ID {
            return Err(CanIdError::FieldOutOfRange);
        }
        Ok(((self.priority as u32) << 26)
            | BIT_ANONYMOUS
            | BITS_R22_R21
            | (u32::from(self.subject_id) << 8)
            | u32::from(pseudo_node_id))
    }

    /// Parses a received identifier; bits 22-21 are ignored as the specification requires.
    pub fn from_raw(raw: u32) -> Result<Self, CanIdError> {
        if raw & !CAN_EXT_ID_MASK != 0 {
            return Err(CanIdError::NotExtended);
        }
        if raw & BIT_SERVICE != 0 {
            return Err(CanIdError::ServiceTransfer);
        }
        if raw & (BIT_R23 | BIT_R7) != 0 {
            return Err(CanIdError::ReservedBitSet);
        }
        let anonymous = raw & BIT_ANONYMOUS != 0;
        Ok(Self {
            priority: Priority::from_bits((raw >> 26) as u8),
            subject_id: ((raw >> 8) & u32::from(MAX_SUBJECT_ID)) as u16,
            source_node_id: if anonymous {
                None
            } else {
                Some((raw & 0x7F) as u8)
            },
        })
    }
}

/// The header fields carried by a service (request or response) frame's CAN ID.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct ServiceCanId {
    pub priority: Priority,
    /// 0..=511.
    pub service_id: u16,
    /// `true` for a request, `false` for a response.
    pub is_request: bool,
    /// 0..=127: the server (request) or the client (response).
    pub destination_node_id: u8,
    /// 0..=127: service transfers are never anonymous.
    pub source_node_id: u8,
}

impl ServiceCanId {
    /// The 29-bit identifier.
    pub fn to_raw(&self) -> Result<u32, CanIdError> {
        if self.service_id > MAX_SERVICE_ID
            || self.destination_node_id > MAX_NODE_ID
            || self.source_node_id > MAX_NODE_ID
        {
            return Err(CanIdError::FieldOutOfRange);
        }
        Ok(((self.priority as u32) << 26)
            | BIT_SERVICE
            | (u32::from(self.is_request) << 24)
            | (u32::from(self.service_id) << 14)
            | (u32::from(self.destination_node_id) << 7)
            | u32::from(self.source_node_id))
    }

    /// Parses a received service identifier; a message ID is [`CanIdError::NotService`].
    pub fn from_raw(raw: u32) -> Result<Self, CanIdError> {
        if raw & !CAN_EXT_ID_MASK != 0 {
            return Err(CanIdError::NotExtended);
        }
        if raw & BIT_SERVICE == 0 {
            return Err(CanIdError::NotService);
        }
        if raw & BIT_R23 != 0 {
            return Err(CanIdError::ReservedBitSet);
        }
        Ok(Self {
            priority: Priority::from_bits((raw >> 26) as u8),
            service_id: ((raw >> 14) & u32::from(MAX_SERVICE_ID)) as u16,
            is_request: raw & BIT_ANONYMOUS != 0,
            destination_node_id: ((raw >> 7) & 0x7F) as u8,
            source_node_id: (raw & 0x7F) as u8,
        })
    }
}

/// The last byte of every Cyphal/CAN frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TailByte {
    pub start_of_transfer: bool,
    pub end_of_transfer: bool,
    pub toggle: bool,
    /// 0..=31.
    pub transfer_id: u8,
}

impl TailByte {
    pub const fn to_byte(self) -> u8 {
        ((self.start_of_transfer as u8) << 7)
            | ((self.end_of_transfer as u8) << 6)
            | ((self.toggle as u8) << 5)
            | (self.transfer_id & 0x1F)
    }

    pub const fn from_byte(byte: u8) -> Self {
        Self {
            start_of_transfer: byte & 0x80 != 0,
            end_of_transfer: byte & 0x40 != 0,
            toggle: byte & 0x20 != 0,
            transfer_id: byte & 0x1F,
        }
    }
}

/// One CAN frame: 29-bit extended ID and up to 64 data bytes (a valid CAN FD length).
/// `is_fd` tells the driver to send it as an FD frame; classic frames never exceed 8 bytes.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct CanFrame {
    pub id: u32,
    pub data: heapless::Vec<u8, FD_MTU>,
    pub is_fd: bool,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spec_example_can_ids() {
        // Cyphal Specification v1.0, section 4.2.3 examples.
        let heartbeat = MessageCanId {
            priority: Priority::Nominal,
            subject_id: 7509,
            source_node_id: Some(42),
        };
        assert_eq!(heartbeat.to_raw().unwrap(), 0x107D_552A);
        assert_eq!(MessageCanId::from_raw(0x107D_552A).unwrap(), heartbeat);

        let array_message = MessageCanId {
            priority: Priority::Nominal,
            subject_id: 4919,
            source_node_id: Some(59),
        };
        assert_eq!(array_message.to_raw().unwrap(), 0x1073_373B);

        let anonymous = MessageCanId {
            priority: Priority::Nominal,
            subject_id: 4919,
            source_node_id: None,
        };
        assert_eq!(anonymous.to_raw_anonymous(0x75).unwrap(), 0x1173_3775);
        assert_eq!(MessageCanId::from_raw(0x1173_3775).unwrap(), anonymous);
    }

    #[test]
    fn receive_ignores_bits_22_21_and_rejects_reserved_and_service() {
        let with_bits_clear = 0x107D_552A & !(3 << 21);
        assert_eq!(
            MessageCanId::from_raw(with_bits_clear).unwrap().subject_id,
            7509
        );
        assert_eq!(
            MessageCanId::from_raw(0x107D_552A | (1 << 23)),
            Err(CanIdError::ReservedBitSet)
        );
        assert_eq!(
            MessageCanId::from_raw(0x107D_552A | (1 << 7)),
            Err(CanIdError::ReservedBitSet)
        );
        // Node info request from the spec examples is a service frame.
        assert_eq!(
            MessageCanId::from_raw(0x136B_957B),
            Err(CanIdError::ServiceTransfer)
        );
        assert_eq!(
            MessageCanId::from_raw(1 << 29),
            Err(CanIdError::NotExtended)
        );
    }

    #[test]
    fn service_can_ids_match_the_spec_examples() {
        // Cyphal Specification v1.0, 4.2.3: uavcan.node.GetInfo request from node 123 to
        // node 42 is 0x136B957B; the response from 42 to 123 is 0x126BBDAA.
        let request = ServiceCanId {
            priority: Priority::Nominal,
            service_id: 430,
            is_request: true,
            destination_node_id: 42,
            source_node_id: 123,
        };
        assert_eq!(request.to_raw().unwrap(), 0x136B_957B);
        assert_eq!(ServiceCanId::from_raw(0x136B_957B).unwrap(), request);
        let response = ServiceCanId {
            is_request: false,
            destination_node_id: 123,
            source_node_id: 42,
            ..request
        };
        assert_eq!(response.to_raw().unwrap(), 0x126B_BDAA);
        assert_eq!(ServiceCanId::from_raw(0x126B_BDAA).unwrap(), response);
        assert_eq!(
            ServiceCanId::from_raw(0x107D_552A),
            Err(CanIdError::NotService)
        );
        assert_eq!(
            ServiceCanId::from_raw(0x136B_957B | (1 << 23)),
            Err(CanIdError::ReservedBitSet)
        );
        let too_big = ServiceCanId {
            service_id: 512,
            ..request
        };
        assert_eq!(too_big.to_raw(), Err(CanIdError::FieldOutOfRange));
    }

    #[test]
    fn out_of_range_fields_are_rejected_on_transmit() {
        let mut id = MessageCanId {
            priority: Priority::Slow,
            subject_id: 8192,
            source_node_id: Some(1),
        };
        assert_eq!(id.to_raw(), Err(CanIdError::FieldOutOfRange));
        id.subject_id = 8191;
        id.source_node_id = Some(128);
        assert_eq!(id.to_raw(), Err(CanIdError::FieldOutOfRange));
        id.source_node_id = Some(127);
        let raw = id.to_raw().unwrap();
        assert_eq!(raw >> 26, 6);
        assert_eq!(MessageCanId::from_raw(raw).unwrap(), id);
    }

    #[test]
    fn tail_byte_round_trip_and_spec_value() {
        // Single-frame transfer, transfer-ID 0: start, end, toggle set.
        let tail = TailByte {
            start_of_transfer: true,
            end_of_transfer: true,
            toggle: true,
            transfer_id: 0,
        };
        assert_eq!(tail.to_byte(), 0xE0);
        for byte in 0..=255u8 {
            assert_eq!(TailByte::from_byte(byte).to_byte(), byte);
        }
    }

    #[test]
    fn fd_length_rounding() {
        assert_eq!(round_up_frame_length(0), Some(0));
        assert_eq!(round_up_frame_length(8), Some(8));
        assert_eq!(round_up_frame_length(9), Some(12));
        assert_eq!(round_up_frame_length(33), Some(48));
        assert_eq!(round_up_frame_length(49), Some(64));
        assert_eq!(round_up_frame_length(65), None);
        assert!(is_valid_frame_length(20));
        assert!(!is_valid_frame_length(9));
    }
}

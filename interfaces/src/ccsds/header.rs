//! CCSDS Space Packet primary header (CCSDS 133.0-B-2), 6 bytes, big-endian:
//! `version(3)=0 | type(1) | secondary-header flag(1) | APID(11)` `| sequence flags(2) |
//! sequence count(14)` `| packet data length(16) = data field bytes - 1`.
//! A packet always has at least one data byte. APID 2047 is reserved for idle packets.

use core::fmt;

pub const PRIMARY_HEADER_LEN: usize = 6;
/// Largest UDP payload on a 1500-byte Ethernet MTU (1500 - 20 IPv4 - 8 UDP).
pub const MAX_DATAGRAM_BYTES: usize = 1472;
pub const MAX_APID: u16 = 2047;
pub const IDLE_APID: u16 = 2047;
pub const SEQUENCE_COUNT_MODULO: u16 = 1 << 14;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum PacketType {
    Telemetry = 0,
    Telecommand = 1,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum SequenceFlags {
    Continuation = 0b00,
    First = 0b01,
    Last = 0b10,
    Unsegmented = 0b11,
}

impl SequenceFlags {
    pub const fn from_bits(bits: u8) -> Self {
        match bits & 3 {
            0b00 => SequenceFlags::Continuation,
            0b01 => SequenceFlags::First,
            0b10 => SequenceFlags::Last,
            _ => SequenceFlags::Unsegmented,
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PrimaryHeader {
    pub packet_type: PacketType,
    pub secondary_header: bool,
    /// 0..=2047.
    pub apid: u16,
    pub sequence_flags: SequenceFlags,
    /// 0..=16383.
    pub sequence_count: u16,
    /// Bytes in the packet data field (1..=65536); the header stores this minus one.
    pub data_field_len: usize,
}

/// Why bytes are not a packet we take.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum HeaderError {
    /// Fewer than 6 bytes.
    Truncated,
    /// Version field not 0.
    BadVersion,
    /// A field out of range on encode.
    FieldOutOfRange,
}

impl core::error::Error for HeaderError {}

impl fmt::Display for HeaderError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            HeaderError::Truncated => "shorter than a primary header",
            HeaderError::BadVersion => "packet version number is not 0",
            HeaderError::FieldOutOfRange => "APID, sequence count or length out of range",
        })
    }
}

impl PrimaryHeader {
    pub fn encode(&self) -> Result<[u8; PRIMARY_HEADER_LEN], HeaderError> {
        if self.apid > MAX_APID
            || self.sequence_count >= SEQUENCE_COUNT_MODULO
            || self.data_field_len == 0
            || self.data_field_len > 65536
        {
            return Err(HeaderError::FieldOutOfRange);
        }
        let word0: u16 =
            ((self.packet_type as u16) << 12) | ((self.secondary_header as u16) << 11) | self.apid;
        let word1: u16 = ((self.sequence_flags as u16) << 14) | self.sequence_count;
        let word2: u16 = (self.data_field_len - 1) as u16;
        let mut out = [0u8; PRIMARY_HEADER_LEN];
        out[0..2].copy_from_slice(&word0.to_be_bytes());
        out[2..4].copy_from_slice(&word1.to_be_bytes());
        out[4..6].copy_from_slice(&word2.to_be_bytes());
        Ok(out)
    }

    pub fn decode(bytes: &[u8]) -> Result<Self, HeaderError> {
        if bytes.len() < PRIMARY_HEADER_LEN {
            return Err(HeaderError::Truncated);
        }
        let word0 = u16::from_be_bytes([bytes[0], bytes[1]]);
        let word1 = u16::from_be_bytes([bytes[2], bytes[3]]);
        let word2 = u16::from_be_bytes([bytes[4], bytes[5]]);
        if word0 >> 13 != 0 {
            return Err(HeaderError::BadVersion);
        }
        Ok(Self {
            packet_type: if word0 & (1 << 12) != 0 {
                PacketType::Telecommand
            } else {
                PacketType::Telemetry
            },
            secondary_header: word0 & (1 << 11) != 0,
            apid: word0 & 0x07FF,
            sequence_flags: SequenceFlags::from_bits((word1 >> 14) as u8),
            sequence_count: word1 & 0x3FFF,
            data_field_len: usize::from(word2) + 1,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn known_header_bytes() {
        // Telecommand, no secondary header, APID 0x123, unsegmented, count 5, 4 data bytes:
        // 0001 0001 0010 0011 | 1100 0000 0000 0101 | 0000 0000 0000 0011.
        let header = PrimaryHeader {
            packet_type: PacketType::Telecommand,
            secondary_header: false,
            apid: 0x123,
            sequence_flags: SequenceFlags::Unsegmented,
            sequence_count: 5,
            data_field_len: 4,
        };
        let bytes = header.encode().unwrap();
        assert_eq!(bytes, [0x11, 0x23, 0xC0, 0x05, 0x00, 0x03]);
        assert_eq!(PrimaryHeader::decode(&bytes).unwrap(), header);
    }

    #[test]
    fn all_fields_round_trip_and_reject_bad_input() {
        for flags in [0u8, 1, 2, 3] {
            let header = PrimaryHeader {
                packet_type: PacketType::Telemetry,
                secondary_header: true,
                apid: 2047,
                sequence_flags: SequenceFlags::from_bits(flags),
                sequence_count: 16383,
                data_field_len: 65536,
            };
            let bytes = header.encode().unwrap();
            assert_eq!(PrimaryHeader::decode(&bytes).unwrap(), header);
        }
        let mut bad = PrimaryHeader {
            packet_type: PacketType::Telemetry,
            secondary_header: false,
            apid: 2048,
            sequence_flags: SequenceFlags::First,
            sequence_count: 0,
            data_field_len: 1,
        };
        assert_eq!(bad.encode(), Err(HeaderError::FieldOutOfRange));
        bad.apid = 1;
        bad.sequence_count = 16384;
        assert_eq!(bad.encode(), Err(HeaderError::FieldOutOfRange));
        bad.sequence_count = 0;
        bad.data_field_len = 0;
        assert_eq!(bad.encode(), Err(HeaderError::FieldOutOfRange));
        assert_eq!(
            PrimaryHeader::decode(&[0x20, 0, 0, 0, 0, 0]),
            Err(HeaderError::BadVersion)
        );
        assert_eq!(
            PrimaryHeader::decode(&[0, 0, 0]),
            Err(HeaderError::Truncated)
        );
    }
}

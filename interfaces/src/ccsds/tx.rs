//! CCSDS transmit side: one message -> one or more Space Packets, one per UDP datagram.
//!
//! The message travels as `payload ++ CRC-32/IEEE(payload)` (CRC big-endian). If that fits one
//! packet's data field (`max_datagram_bytes - 6`), it goes as one unsegmented packet;
//! otherwise as First, Continuation..., Last packets filled to the maximum, with consecutive
//! sequence counts (modulo 16384) starting at the caller's per-APID counter.
//! No secondary header. Allocation-free; never panics.

use super::header::{
    HeaderError, PacketType, PrimaryHeader, SequenceFlags, MAX_APID, MAX_DATAGRAM_BYTES,
    PRIMARY_HEADER_LEN, SEQUENCE_COUNT_MODULO,
};
use crate::crc::crc32_ieee;

/// The smallest datagram we segment into: header plus 1 data byte.
pub const MIN_DATAGRAM_BYTES: usize = PRIMARY_HEADER_LEN + 1;

/// One packet, ready to be sent as a datagram.
pub type Datagram = heapless::Vec<u8, MAX_DATAGRAM_BYTES>;

/// Iterator over the packets of one message.
#[derive(Clone, Debug)]
pub struct MessagePackets<'a> {
    packet_type: PacketType,
    apid: u16,
    payload: &'a [u8],
    crc_be: [u8; 4],
    stream_len: usize,
    max_data_field: usize,
    offset: usize,
    sequence_count: u16,
    index: usize,
}

/// Packets for one message on `apid`, the first with `first_sequence_count`.
/// Fails if `apid > 2047` (or is the idle APID) or `max_datagram_bytes` is outside 7..=1472.
pub fn message_packets(
    packet_type: PacketType,
    apid: u16,
    payload: &[u8],
    first_sequence_count: u16,
    max_datagram_bytes: usize,
) -> Result<MessagePackets<'_>, HeaderError> {
    if apid >= MAX_APID || !(MIN_DATAGRAM_BYTES..=MAX_DATAGRAM_BYTES).contains(&max_datagram_bytes)
    {
        return Err(HeaderError::FieldOutOfRange);
    }
    Ok(MessagePackets {
        packet_type,
        apid,
        payload,
        crc_be: crc32_ieee(payload).to_be_bytes(),
        stream_len: payload.len() + 4,
        max_data_field: max_datagram_bytes - PRIMARY_HEADER_LEN,
        offset: 0,
        sequence_count: first_sequence_count % SEQUENCE_COUNT_MODULO,
        index: 0,
    })
}

impl MessagePackets<'_> {
    pub fn packet_count(&self) -> usize {
        self.stream_len.div_ceil(self.max_data_field)
    }

    /// The sequence count the next message on this APID should start with.
    pub fn next_message_sequence_count(&self) -> u16 {
        let after_first = (self.packet_count() - self.index) % usize::from(SEQUENCE_COUNT_MODULO);
        ((usize::from(self.sequence_count) + after_first) % usize::from(SEQUENCE_COUNT_MODULO))
            as u16
    }
}

impl Iterator for MessagePackets<'_> {
    type Item = Datagram;

    fn next(&mut self) -> Option<Datagram> {
        if self.offset >= self.stream_len {
            return None;
        }
        let end = (self.offset + self.max_data_field).min(self.stream_len);
        let first = self.offset == 0;
        let last = end == self.stream_len;
        let sequence_flags = match (first, last) {
            (true, true) => SequenceFlags::Unsegmented,
            (true, false) => SequenceFlags::First,
            (false, false) => SequenceFlags::Continuation,
            (false, true) => SequenceFlags::Last,
        };
        let header = PrimaryHeader {
            packet_type: self.packet_type,
            secondary_header: false,
            apid: self.apid,
            sequence_flags,
            sequence_count: self.sequence_count,
            data_field_len: end - self.offset,
        }
        .encode()
        .ok()?;
        let mut out = Datagram::new();
        out.extend_from_slice(&header).ok()?;
        let payload_end = end.min(self.payload.len());
        if self.offset < payload_end {
            out.extend_from_slice(&self.payload[self.offset..payload_end])
                .ok()?;
        }
        for i in self.offset.max(self.payload.len())..end {
            out.push(self.crc_be[i - self.payload.len()]).ok()?;
        }
        self.offset = end;
        self.index += 1;
        self.sequence_count = (self.sequence_count + 1) % SEQUENCE_COUNT_MODULO;
        Some(out)
    }

    fn size_hint(&self) -> (usize, Option<usize>) {
        let remaining = self.packet_count() - self.index;
        (remaining, Some(remaining))
    }
}

impl ExactSizeIterator for MessagePackets<'_> {}

#[cfg(test)]
mod tests {
    use super::*;
    extern crate std;
    use std::vec::Vec;

    #[test]
    fn small_message_is_one_unsegmented_packet_with_crc() {
        let packets: Vec<Datagram> =
            message_packets(PacketType::Telemetry, 100, b"123456789", 16383, 1472)
                .unwrap()
                .collect();
        assert_eq!(packets.len(), 1);
        let p = &packets[0];
        assert_eq!(&p[..6], &[0x00, 100, 0xFF, 0xFF, 0x00, 12]);
        assert_eq!(&p[6..15], b"123456789");
        assert_eq!(&p[15..], &0xCBF4_3926u32.to_be_bytes());
    }

    #[test]
    fn large_message_segments_with_flags_and_wrapping_counts() {
        let payload: Vec<u8> = (0..3000u32).map(|i| (i * 7) as u8).collect();
        let it = message_packets(PacketType::Telecommand, 7, &payload, 16382, 1472).unwrap();
        assert_eq!(it.packet_count(), 3);
        assert_eq!(it.next_message_sequence_count(), 1);
        let packets: Vec<Datagram> = it.collect();
        let flags: Vec<(u8, u16, usize)> = packets
            .iter()
            .map(|p| {
                let h = PrimaryHeader::decode(p).unwrap();
                assert_eq!(h.data_field_len, p.len() - 6);
                assert_eq!(h.packet_type, PacketType::Telecommand);
                (h.sequence_flags as u8, h.sequence_count, p.len())
            })
            .collect();
        assert_eq!(
            flags,
            [
                (0b01, 16382, 1472),
                (0b00, 16383, 1472),
                (0b10, 0, 3004 - 2 * 1466 + 6)
            ]
        );
        let mut stream: Vec<u8> = packets.iter().flat_map(|p| p[6..].to_vec()).collect();
        let crc = stream.split_off(3000);
        assert_eq!(stream, payload);
        assert_eq!(crc, crc32_ieee(&payload).to_be_bytes());
    }

    #[test]
    fn crc_may_straddle_packets_and_bad_arguments_fail() {
        // 1464 payload bytes + 4 CRC bytes = 1468 > 1466: the CRC splits 2 + 2.
        let payload = [0xAAu8; 1464];
        let packets: Vec<Datagram> = message_packets(PacketType::Telemetry, 1, &payload, 0, 1472)
            .unwrap()
            .collect();
        assert_eq!(packets.len(), 2);
        assert_eq!(packets[1].len(), 6 + 2);
        assert!(message_packets(PacketType::Telemetry, 2047, &payload, 0, 1472).is_err());
        assert!(message_packets(PacketType::Telemetry, 1, &payload, 0, 1473).is_err());
        assert!(message_packets(PacketType::Telemetry, 1, &payload, 0, 6).is_err());
    }
}

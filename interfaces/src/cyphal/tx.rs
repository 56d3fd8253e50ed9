//! Cyphal/CAN transmit side: split one message or service transfer's payload into CAN frames.
//!
//! The frames are a view of the byte stream `payload ++ padding ++ crc` cut into pieces of
//! `mtu - 1` bytes, each followed by a tail byte:
//! - single-frame (payload <= mtu - 1): `payload ++ zeros` up to the next valid CAN FD length,
//!   no CRC; tail start = end = toggle = 1;
//! - multi-frame: the transfer CRC-16/CCITT-FALSE over `payload ++ padding`, appended
//!   big-endian. Zero padding is only inserted when the whole CRC lands in the last frame, so
//!   that the last frame has a valid CAN FD length (classic CAN never needs padding).
//!   The toggle starts at 1 and alternates. This is the layout libcanard and pycyphal emit.
//!
//! The iterator allocates nothing and never panics; the header is checked up front.

use super::frame::{
    round_up_frame_length, CanFrame, CanIdError, MessageCanId, Mtu, Priority, ServiceCanId,
    TailByte,
};
use crate::crc::Crc16CcittFalse;

/// Who sends which transfer on which subject.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TransferHeader {
    pub priority: Priority,
    /// 0..=8191.
    pub subject_id: u16,
    /// 0..=127.
    pub source_node_id: u8,
    /// Taken modulo 32: pass the sender's running per-subject counter.
    pub transfer_id: u64,
}

/// Iterator over the CAN frames of one transfer (see the module header for the layout).
#[derive(Clone, Debug)]
pub struct TransferFrames<'a> {
    can_id: u32,
    transfer_id: u8,
    mtu: Mtu,
    payload: &'a [u8],
    multi_frame: bool,
    padding: usize,
    crc_be: [u8; 2],
    stream_len: usize,
    offset: usize,
    frame_index: usize,
}

/// Number of zero bytes inserted before the tail (single-frame) or before the CRC (multi-frame).
fn padding_for(payload_len: usize, mtu: Mtu) -> (bool, usize) {
    let cap = mtu.bytes() - 1;
    if payload_len <= cap {
        let padded = round_up_frame_length(payload_len + 1).unwrap_or(mtu.bytes()) - 1;
        return (false, padded - payload_len);
    }
    let with_crc = payload_len + 2;
    let last = with_crc - (with_crc - 1) / cap * cap;
    if last < 2 {
        // The CRC straddles the last two frames: the last frame holds a single byte.
        return (true, 0);
    }
    let padded = round_up_frame_length(last + 1).unwrap_or(mtu.bytes()) - 1;
    (true, padded - last)
}

/// Frames for one message transfer.
pub fn transfer_frames<'a>(
    header: &TransferHeader,
    payload: &'a [u8],
    mtu: Mtu,
) -> Result<TransferFrames<'a>, CanIdError> {
    let can_id = MessageCanId {
        priority: header.priority,
        subject_id: header.subject_id,
        source_node_id: Some(header.source_node_id),
    }
    .to_raw()?;
    Ok(frames_for_id(can_id, header.transfer_id, payload, mtu))
}

/// Frames for one service transfer (a request or a response). A response must repeat the
/// request's priority and transfer-ID (Cyphal v1.0, 4.2.1), so the caller passes both.
pub fn service_transfer_frames<'a>(
    id: &ServiceCanId,
    transfer_id: u64,
    payload: &'a [u8],
    mtu: Mtu,
) -> Result<TransferFrames<'a>, CanIdError> {
    Ok(frames_for_id(id.to_raw()?, transfer_id, payload, mtu))
}

fn frames_for_id(can_id: u32, transfer_id: u64, payload: &[u8], mtu: Mtu) -> TransferFrames<'_> {
    let (multi_frame, padding) = padding_for(payload.len(), mtu);
    let mut crc_be = [0u8; 2];
    let mut stream_len = payload.len() + padding;
    if multi_frame {
        let mut crc = Crc16CcittFalse::new();
        crc.update(payload);
        for _ in 0..padding {
            crc.update(&[0]);
        }
        crc_be = crc.value().to_be_bytes();
        stream_len += 2;
    }
    TransferFrames {
        can_id,
        transfer_id: (transfer_id % 32) as u8,
        mtu,
        payload,
        multi_frame,
        padding,
        crc_be,
        stream_len,
        offset: 0,
        frame_index: 0,
    }
}

impl TransferFrames<'_> {
    /// Total number of frames of this transfer.
    pub fn frame_count(&self) -> usize {
        if self.multi_frame {
            self.stream_len.div_ceil(self.mtu.bytes() - 1)
        } else {
            1
        }
    }

    fn stream_byte(&self, index: usize) -> u8 {
        let payload_len = self.payload.len();
        if index < payload_len {
            self.payload[index]
        } else if index < payload_len + self.padding {
            0
        } else {
            self.crc_be[index - payload_len - self.padding]
        }
    }
}

impl Iterator for TransferFrames<'_> {
    type Item = CanFrame;

    fn next(&mut self) -> Option<CanFrame> {
        let first = self.frame_index == 0;
        if !first && self.offset >= self.stream_len {
            return None;
        }
        let cap = self.mtu.bytes() - 1;
        let end = (self.offset + cap).min(self.stream_len);
        let mut data = heapless::Vec::new();
        for i in self.offset..end {
            // Capacity is 64 and end - offset <= 63: the push cannot fail.
            let _ = data.push(self.stream_byte(i));
        }
        let last = end >= self.stream_len;
        let tail = TailByte {
            start_of_transfer: first,
            end_of_transfer: last,
            toggle: self.frame_index.is_multiple_of(2),
            transfer_id: self.transfer_id,
        };
        let _ = data.push(tail.to_byte());
        self.offset = end;
        self.frame_index += 1;
        if last {
            // Mark exhausted even for the empty single-frame transfer.
            self.offset = self.stream_len;
            self.frame_index = self.frame_index.max(1);
        }
        Some(CanFrame {
            id: self.can_id,
            data,
            is_fd: self.mtu == Mtu::Fd,
        })
    }

    fn size_hint(&self) -> (usize, Option<usize>) {
        let remaining = if self.frame_index == 0 {
            self.frame_count()
        } else {
            self.stream_len
                .saturating_sub(self.offset)
                .div_ceil(self.mtu.bytes() - 1)
        };
        (remaining, Some(remaining))
    }
}

impl ExactSizeIterator for TransferFrames<'_> {}

#[cfg(test)]
mod tests {
    use super::*;
    extern crate std;
    use std::vec::Vec;

    fn header(subject_id: u16, source_node_id: u8, transfer_id: u64) -> TransferHeader {
        TransferHeader {
            priority: Priority::Nominal,
            subject_id,
            source_node_id,
            transfer_id,
        }
    }

    fn frames(h: &TransferHeader, payload: &[u8], mtu: Mtu) -> Vec<CanFrame> {
        let it = transfer_frames(h, payload, mtu).unwrap();
        let n = it.frame_count();
        let out: Vec<CanFrame> = it.collect();
        assert_eq!(out.len(), n);
        out
    }

    #[test]
    fn spec_heartbeat_single_frame() {
        // Cyphal spec 4.2.3: heartbeat from node 42, uptime 0: 00 00 00 00 04 78 68 | E0.
        let payload = [0x00, 0x00, 0x00, 0x00, 0x04, 0x78, 0x68];
        let out = frames(&header(7509, 42, 0), &payload, Mtu::Classic);
        assert_eq!(out.len(), 1);
        assert_eq!(out[0].id, 0x107D_552A);
        assert_eq!(&out[0].data[..], &[0, 0, 0, 0, 0x04, 0x78, 0x68, 0xE0]);
        assert!(!out[0].is_fd);
    }

    #[test]
    fn spec_array_message_fd_multi_frame() {
        // Cyphal spec 4.2.3 "array message" on CAN FD: 94 payload bytes, padding 14, CRC C0 48.
        let mut payload = Vec::from([0x00u8, 0xB8]);
        payload.extend(0u8..=0x5B);
        let out = frames(&header(4919, 59, 0), &payload, Mtu::Fd);
        assert_eq!(out.len(), 2);
        assert!(out.iter().all(|f| f.id == 0x1073_373B));
        let mut first = payload[..63].to_vec();
        first.push(0xA0);
        assert_eq!(&out[0].data[..], &first[..]);
        let mut second = payload[63..].to_vec();
        second.extend([0u8; 14]);
        second.extend([0xC0, 0x48, 0x40]);
        assert_eq!(&out[1].data[..], &second[..]);
        assert_eq!(out[1].data.len(), 48);
    }

    #[test]
    fn pycyphal_vector_classic_multi_frame() {
        // pycyphal reassembler test vector: 30 bytes 0x00..0x1D, CRC 0x3554, classic CAN.
        let payload: Vec<u8> = (0u8..30).collect();
        let out = frames(&header(1, 1, 1), &payload, Mtu::Classic);
        let tails: Vec<u8> = out.iter().map(|f| *f.data.last().unwrap()).collect();
        assert_eq!(tails, [0xA1, 0x01, 0x21, 0x01, 0x61]);
        assert_eq!(&out[4].data[..], &[0x1C, 0x1D, 0x35, 0x54, 0x61]);
    }

    #[test]
    fn crc_split_across_last_two_frames() {
        // 13 bytes on classic CAN: 7 + 6 payload + CRC high | CRC low.
        let payload: Vec<u8> = (0u8..13).collect();
        let out = frames(&header(5, 3, 31), &payload, Mtu::Classic);
        assert_eq!(out.len(), 3);
        let crc = crate::crc::crc16_ccitt_false(&payload).to_be_bytes();
        assert_eq!(out[1].data[6], crc[0]);
        assert_eq!(&out[2].data[..], &[crc[1], 0x7F]); // end, toggle 1 (third frame), TID 31
    }

    #[test]
    fn spec_get_info_request_and_response_ids() {
        // Cyphal spec 4.2.3: GetInfo request (empty) from 123 to 42, transfer-ID 1: 0x136B957B, E1.
        let request = ServiceCanId {
            priority: Priority::Nominal,
            service_id: 430,
            is_request: true,
            destination_node_id: 42,
            source_node_id: 123,
        };
        let out: Vec<CanFrame> = service_transfer_frames(&request, 1, &[], Mtu::Classic)
            .unwrap()
            .collect();
        assert_eq!(out.len(), 1);
        assert_eq!(out[0].id, 0x136B_957B);
        assert_eq!(&out[0].data[..], &[0xE1]);
        let response = ServiceCanId {
            is_request: false,
            destination_node_id: 123,
            source_node_id: 42,
            ..request
        };
        let payload: Vec<u8> = (0u8..40).collect();
        let out: Vec<CanFrame> = service_transfer_frames(&response, 1, &payload, Mtu::Classic)
            .unwrap()
            .collect();
        assert_eq!(out.len(), 6, "40 bytes + CRC on classic CAN: 6 frames of 7");
        assert!(out.iter().all(|f| f.id == 0x126B_BDAA));
        assert_eq!(*out[0].data.last().unwrap(), 0xA1);
        let bad = ServiceCanId {
            destination_node_id: 128,
            ..response
        };
        assert!(service_transfer_frames(&bad, 0, &[], Mtu::Fd).is_err());
    }

    #[test]
    fn empty_payload_is_one_tail_only_frame() {
        let out = frames(&header(5, 3, 33), &[], Mtu::Fd);
        assert_eq!(out.len(), 1);
        assert_eq!(&out[0].data[..], &[0xE1]);
    }

    #[test]
    fn fd_single_frame_padding() {
        let out = frames(&header(5, 3, 0), &[7u8; 8], Mtu::Fd);
        assert_eq!(out.len(), 1);
        assert_eq!(out[0].data.len(), 12);
        assert_eq!(&out[0].data[8..11], &[0, 0, 0]);
        let out = frames(&header(5, 3, 0), &[7u8; 63], Mtu::Fd);
        assert_eq!(out.len(), 1);
        assert_eq!(out[0].data.len(), 64);
    }

    #[test]
    fn every_frame_has_valid_length_and_toggles() {
        for mtu in [Mtu::Classic, Mtu::Fd] {
            for len in 0..400usize {
                let payload: Vec<u8> = (0..len).map(|i| i as u8).collect();
                let out = frames(&header(9, 9, 9), &payload, mtu);
                for (i, f) in out.iter().enumerate() {
                    assert!(crate::cyphal::frame::is_valid_frame_length(f.data.len()));
                    assert!(f.data.len() <= mtu.bytes());
                    if i + 1 < out.len() {
                        assert_eq!(f.data.len(), mtu.bytes(), "non-last frames are full");
                    }
                    let tail = TailByte::from_byte(*f.data.last().unwrap());
                    assert_eq!(tail.toggle, i % 2 == 0);
                    assert_eq!(tail.start_of_transfer, i == 0);
                    assert_eq!(tail.end_of_transfer, i + 1 == out.len());
                }
            }
        }
    }
}

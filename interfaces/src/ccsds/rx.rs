//! CCSDS receive side: rebuild messages from Space Packets (one per datagram).
//!
//! One session per (packet type, APID), at most `N`, each with `storage.len() / N` bytes of the
//! caller's storage: memory never grows. Rules:
//! - datagram <= 1472 bytes, version 0, no secondary header, header length field equal to the
//!   datagram's data bytes, APID not idle (2047);
//! - the same sequence count as the previous packet of the session, within the timeout,
//!   is a duplicate (dropped, state unchanged);
//! - Unsegmented: a whole message. First: starts one (abandoning an unfinished one, counted).
//!   Continuation/Last: must follow with the next sequence count (mod 16384), else the
//!   message is abandoned (gap, reorder); Last completes it;
//! - a message unfinished `timeout` after its first packet is abandoned;
//! - the last 4 bytes of the message are CRC-32/IEEE (big-endian) of the rest; they are
//!   checked and stripped.
//!
//! Every rejected datagram returns a [`CcsdsRxError`] and bumps its counter; never panics.

use super::header::{
    HeaderError, PacketType, PrimaryHeader, SequenceFlags, IDLE_APID, MAX_DATAGRAM_BYTES,
    PRIMARY_HEADER_LEN, SEQUENCE_COUNT_MODULO,
};
use crate::crc::crc32_ieee;
use crate::sessions::{self, Claim, SessionTimes};
use core::fmt;

pub const DEFAULT_MESSAGE_TIMEOUT_US: u64 = 2_000_000;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CcsdsRxError {
    /// Datagram larger than 1472 bytes.
    Oversized,
    /// Shorter than a primary header.
    Truncated,
    /// Packet version not 0.
    BadVersion,
    /// Secondary header flag set: none is defined on this bus.
    SecondaryHeaderUnsupported,
    /// Header length field disagrees with the datagram size.
    LengthMismatch,
    /// Idle packet (APID 2047): carries nothing.
    IdlePacket,
    /// An APID the APID filter does not accept.
    NotSubscribed,
    /// Continuation or Last without a started message.
    MissingFirst,
    /// Sequence count not the expected next one (loss or reordering).
    SequenceGap,
    /// Repeated sequence count.
    Duplicate,
    /// Message CRC-32 wrong, or message shorter than its CRC.
    CrcMismatch,
    /// Message larger than a session slot.
    PayloadOverflow,
    /// All sessions busy with unfinished, unexpired messages.
    NoSessionSlot,
    /// Packet of a message that exceeded the timeout.
    Timeout,
}

impl core::error::Error for CcsdsRxError {}

impl fmt::Display for CcsdsRxError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            CcsdsRxError::Oversized => "datagram larger than 1472 bytes",
            CcsdsRxError::Truncated => "datagram shorter than a primary header",
            CcsdsRxError::BadVersion => "packet version number is not 0",
            CcsdsRxError::SecondaryHeaderUnsupported => "secondary header not supported",
            CcsdsRxError::LengthMismatch => "packet length field disagrees with datagram size",
            CcsdsRxError::IdlePacket => "idle packet",
            CcsdsRxError::NotSubscribed => "APID not subscribed",
            CcsdsRxError::MissingFirst => "continuation without a first segment",
            CcsdsRxError::SequenceGap => "sequence count gap or reorder",
            CcsdsRxError::Duplicate => "duplicate sequence count",
            CcsdsRxError::CrcMismatch => "message CRC-32 mismatch",
            CcsdsRxError::PayloadOverflow => "message larger than the reassembly slot",
            CcsdsRxError::NoSessionSlot => "no free reassembly session",
            CcsdsRxError::Timeout => "message not completed within the timeout",
        })
    }
}

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct CcsdsRxCounters {
    pub datagrams: u64,
    pub messages: u64,
    pub abandoned_messages: u64,
    pub rejected_oversized: u64,
    pub rejected_truncated: u64,
    pub rejected_bad_version: u64,
    pub rejected_secondary_header: u64,
    pub rejected_length_mismatch: u64,
    pub rejected_idle: u64,
    pub rejected_not_subscribed: u64,
    pub rejected_missing_first: u64,
    pub rejected_sequence_gap: u64,
    pub rejected_duplicate: u64,
    pub rejected_crc_mismatch: u64,
    pub rejected_payload_overflow: u64,
    pub rejected_no_session_slot: u64,
    pub rejected_timeout: u64,
}

impl CcsdsRxCounters {
    fn count(&mut self, error: CcsdsRxError) {
        let counter = match error {
            CcsdsRxError::Oversized => &mut self.rejected_oversized,
            CcsdsRxError::Truncated => &mut self.rejected_truncated,
            CcsdsRxError::BadVersion => &mut self.rejected_bad_version,
            CcsdsRxError::SecondaryHeaderUnsupported => &mut self.rejected_secondary_header,
            CcsdsRxError::LengthMismatch => &mut self.rejected_length_mismatch,
            CcsdsRxError::IdlePacket => &mut self.rejected_idle,
            CcsdsRxError::NotSubscribed => &mut self.rejected_not_subscribed,
            CcsdsRxError::MissingFirst => &mut self.rejected_missing_first,
            CcsdsRxError::SequenceGap => &mut self.rejected_sequence_gap,
            CcsdsRxError::Duplicate => &mut self.rejected_duplicate,
            CcsdsRxError::CrcMismatch => &mut self.rejected_crc_mismatch,
            CcsdsRxError::PayloadOverflow => &mut self.rejected_payload_overflow,
            CcsdsRxError::NoSessionSlot => &mut self.rejected_no_session_slot,
            CcsdsRxError::Timeout => &mut self.rejected_timeout,
        };
        *counter = counter.saturating_add(1);
    }

    pub fn rejected_total(&self) -> u64 {
        [
            self.rejected_oversized,
            self.rejected_truncated,
            self.rejected_bad_version,
            self.rejected_secondary_header,
            self.rejected_length_mismatch,
            self.rejected_idle,
            self.rejected_not_subscribed,
            self.rejected_missing_first,
            self.rejected_sequence_gap,
            self.rejected_duplicate,
            self.rejected_crc_mismatch,
            self.rejected_payload_overflow,
            self.rejected_no_session_slot,
            self.rejected_timeout,
        ]
        .iter()
        .fold(0u64, |acc, v| acc.saturating_add(*v))
    }
}

/// A complete message, CRC checked and removed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ReceivedMessage<'a> {
    pub packet_type: PacketType,
    pub apid: u16,
    /// Sequence count of the first packet.
    pub first_sequence_count: u16,
    pub packet_count: u32,
    /// Timestamp of the first packet.
    pub timestamp_us: u64,
    pub payload: &'a [u8],
}

#[derive(Clone, Copy, Debug)]
struct Session {
    in_use: bool,
    packet_type: PacketType,
    apid: u16,
    in_progress: bool,
    expected_count: u16,
    first_count: u16,
    packet_count: u32,
    start_us: u64,
    last_activity_us: u64,
    stored_len: usize,
    last_count: Option<u16>,
}

impl SessionTimes for Session {
    fn in_use(&self) -> bool {
        self.in_use
    }
    fn in_progress(&self) -> bool {
        self.in_progress
    }
    fn start_us(&self) -> u64 {
        self.start_us
    }
    fn last_activity_us(&self) -> u64 {
        self.last_activity_us
    }
    fn abandon(&mut self) {
        self.in_progress = false;
    }
}

const IDLE_SESSION: Session = Session {
    in_use: false,
    packet_type: PacketType::Telemetry,
    apid: 0,
    in_progress: false,
    expected_count: 0,
    first_count: 0,
    packet_count: 0,
    start_us: 0,
    last_activity_us: 0,
    stored_len: 0,
    last_count: None,
};

enum PayloadAt {
    Datagram { start: usize, len: usize },
    Slot { slot: usize, len: usize },
}

struct Completed {
    header: PrimaryHeader,
    first_count: u16,
    packet_count: u32,
    timestamp_us: u64,
    at: PayloadAt,
}

/// Bounded CCSDS message reassembler (see the module header). Each message plus its CRC must
/// fit `storage.len() / N` bytes.
pub struct CcsdsReassembler<B, const N: usize> {
    storage: B,
    slot_len: usize,
    sessions: [Session; N],
    timeout_us: u64,
    apid_filter: Option<fn(u16) -> bool>,
    counters: CcsdsRxCounters,
}

fn crc_ok(message_with_crc: &[u8]) -> bool {
    if message_with_crc.len() < 4 {
        return false;
    }
    let (body, crc) = message_with_crc.split_at(message_with_crc.len() - 4);
    crc32_ieee(body).to_be_bytes() == crc
}

impl<B: AsRef<[u8]> + AsMut<[u8]>, const N: usize> CcsdsReassembler<B, N> {
    pub fn new(storage: B) -> Self {
        let slot_len = storage.as_ref().len().checked_div(N).unwrap_or(0);
        Self {
            storage,
            slot_len,
            sessions: [IDLE_SESSION; N],
            timeout_us: DEFAULT_MESSAGE_TIMEOUT_US,
            apid_filter: None,
            counters: CcsdsRxCounters::default(),
        }
    }

    pub fn with_timeout_us(mut self, timeout_us: u64) -> Self {
        self.timeout_us = timeout_us;
        self
    }

    /// Only APIDs for which `filter` returns true get a session; others are rejected as
    /// [`CcsdsRxError::NotSubscribed`] before they can occupy memory.
    pub fn with_apid_filter(mut self, filter: fn(u16) -> bool) -> Self {
        self.apid_filter = Some(filter);
        self
    }

    /// Bytes available to one message including its 4-byte CRC.
    pub fn slot_bytes(&self) -> usize {
        self.slot_len
    }

    pub fn counters(&self) -> &CcsdsRxCounters {
        &self.counters
    }

    pub fn reset_counters(&mut self) {
        self.counters = CcsdsRxCounters::default();
    }

    pub fn messages_in_progress(&self) -> usize {
        self.sessions.iter().filter(|s| s.in_progress).count()
    }

    /// Abandons unfinished messages older than the timeout.
    pub fn expire(&mut self, now_us: u64) {
        self.counters.abandoned_messages +=
            sessions::expire(&mut self.sessions, now_us, self.timeout_us);
    }

    /// Feeds one received datagram.
    pub fn push<'a>(
        &'a mut self,
        datagram: &'a [u8],
        timestamp_us: u64,
    ) -> Result<Option<ReceivedMessage<'a>>, CcsdsRxError> {
        self.counters.datagrams += 1;
        match self.accept(datagram, timestamp_us) {
            Err(error) => {
                self.counters.count(error);
                Err(error)
            }
            Ok(None) => Ok(None),
            Ok(Some(done)) => {
                self.counters.messages += 1;
                let payload: &'a [u8] = match done.at {
                    PayloadAt::Datagram { start, len } => &datagram[start..start + len],
                    PayloadAt::Slot { slot, len } => {
                        let start = slot * self.slot_len;
                        &self.storage.as_ref()[start..start + len]
                    }
                };
                Ok(Some(ReceivedMessage {
                    packet_type: done.header.packet_type,
                    apid: done.header.apid,
                    first_sequence_count: done.first_count,
                    packet_count: done.packet_count,
                    timestamp_us: done.timestamp_us,
                    payload,
                }))
            }
        }
    }

    fn accept(
        &mut self,
        datagram: &[u8],
        timestamp_us: u64,
    ) -> Result<Option<Completed>, CcsdsRxError> {
        if datagram.len() > MAX_DATAGRAM_BYTES {
            return Err(CcsdsRxError::Oversized);
        }
        let header = PrimaryHeader::decode(datagram).map_err(|e| match e {
            HeaderError::BadVersion => CcsdsRxError::BadVersion,
            _ => CcsdsRxError::Truncated,
        })?;
        if header.secondary_header {
            return Err(CcsdsRxError::SecondaryHeaderUnsupported);
        }
        let data = &datagram[PRIMARY_HEADER_LEN..];
        if header.data_field_len != data.len() {
            return Err(CcsdsRxError::LengthMismatch);
        }
        if header.apid == IDLE_APID {
            return Err(CcsdsRxError::IdlePacket);
        }
        if let Some(filter) = self.apid_filter {
            if !filter(header.apid) {
                return Err(CcsdsRxError::NotSubscribed);
            }
        }
        let starts = matches!(
            header.sequence_flags,
            SequenceFlags::First | SequenceFlags::Unsegmented
        );
        let index = match self.find_session(header.packet_type, header.apid) {
            Some(index) => index,
            None if !starts => return Err(CcsdsRxError::MissingFirst),
            None => self.claim_session(header.packet_type, header.apid, timestamp_us)?,
        };
        let timeout = self.timeout_us;
        let slot_len = self.slot_len;
        let session = &mut self.sessions[index];
        let count = header.sequence_count;
        if session.last_count == Some(count)
            && timestamp_us.saturating_sub(session.last_activity_us) <= timeout
        {
            return Err(CcsdsRxError::Duplicate);
        }
        let mut timed_out = false;
        if session.in_progress && timestamp_us.saturating_sub(session.start_us) > timeout {
            session.in_progress = false;
            self.counters.abandoned_messages += 1;
            timed_out = true;
        }
        session.last_count = Some(count);
        session.last_activity_us = timestamp_us;
        if starts {
            if session.in_progress {
                session.in_progress = false;
                self.counters.abandoned_messages += 1;
            }
            if header.sequence_flags == SequenceFlags::Unsegmented {
                if !crc_ok(data) {
                    return Err(CcsdsRxError::CrcMismatch);
                }
                return Ok(Some(Completed {
                    header,
                    first_count: count,
                    packet_count: 1,
                    timestamp_us,
                    at: PayloadAt::Datagram {
                        start: PRIMARY_HEADER_LEN,
                        len: data.len() - 4,
                    },
                }));
            }
            session.in_progress = true;
            session.first_count = count;
            session.packet_count = 0;
            session.start_us = timestamp_us;
            session.stored_len = 0;
        } else if !session.in_progress {
            return Err(if timed_out {
                CcsdsRxError::Timeout
            } else {
                CcsdsRxError::MissingFirst
            });
        } else if count != session.expected_count {
            session.in_progress = false;
            self.counters.abandoned_messages += 1;
            return Err(CcsdsRxError::SequenceGap);
        }

        let stored = session.stored_len;
        if stored + data.len() > slot_len {
            session.in_progress = false;
            self.counters.abandoned_messages += 1;
            return Err(CcsdsRxError::PayloadOverflow);
        }
        session.stored_len += data.len();
        session.packet_count += 1;
        session.expected_count = (count + 1) % SEQUENCE_COUNT_MODULO;
        let finished = header.sequence_flags == SequenceFlags::Last;
        if finished {
            session.in_progress = false;
        }
        let (first_count, packet_count, start_us, total) = (
            session.first_count,
            session.packet_count,
            session.start_us,
            session.stored_len,
        );
        let slot_start = index * slot_len;
        let slot = &mut self.storage.as_mut()[slot_start..slot_start + slot_len];
        slot[stored..total].copy_from_slice(data);
        if !finished {
            return Ok(None);
        }
        if !crc_ok(&slot[..total]) {
            return Err(CcsdsRxError::CrcMismatch);
        }
        Ok(Some(Completed {
            header,
            first_count,
            packet_count,
            timestamp_us: start_us,
            at: PayloadAt::Slot {
                slot: index,
                len: total - 4,
            },
        }))
    }

    fn find_session(&self, packet_type: PacketType, apid: u16) -> Option<usize> {
        self.sessions
            .iter()
            .position(|s| s.in_use && s.packet_type == packet_type && s.apid == apid)
    }

    fn claim_session(
        &mut self,
        packet_type: PacketType,
        apid: u16,
        now_us: u64,
    ) -> Result<usize, CcsdsRxError> {
        let index = match sessions::claim(&self.sessions, now_us, self.timeout_us) {
            Some(Claim::Free(index)) => index,
            Some(Claim::Evict { index, abandons }) => {
                if abandons {
                    self.counters.abandoned_messages += 1;
                }
                index
            }
            None => return Err(CcsdsRxError::NoSessionSlot),
        };
        self.sessions[index] = Session {
            in_use: true,
            packet_type,
            apid,
            last_activity_us: now_us,
            ..IDLE_SESSION
        };
        Ok(index)
    }
}

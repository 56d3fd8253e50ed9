//! Cyphal/CAN receive side: reassemble message transfers from CAN frames.
//!
//! One session per (source node-ID, subject-ID), at most `N` sessions, each with a fixed slice
//! of the caller's storage (`storage.len() / N` bytes) for multi-frame payloads: memory never
//! grows. Rules (Cyphal Specification v1.0, 4.2.4, as libcanard and pycyphal apply them):
//! - a transfer starts with a start frame (toggle must be 1, else it is a UAVCAN v0 frame);
//!   following frames must carry the same transfer-ID and the alternating toggle;
//! - a new start frame with another transfer-ID abandons an unfinished transfer (counted);
//! - a start frame repeating the transfer-ID of the last completed transfer within the
//!   transfer-ID timeout (default 2 s, measured from that transfer's first frame) is a duplicate;
//! - an unfinished transfer older than the timeout is abandoned (counted);
//! - multi-frame transfers must pass the CRC-16/CCITT-FALSE residue check; the two CRC bytes
//!   are stripped. Payloads keep any CAN FD padding (zeros): decoders ignore trailing zeros.
//! - anonymous transfers are accepted only as single frames and are never deduplicated.
//!
//! Every rejected frame returns a [`CanRxError`] and bumps the matching counter; nothing panics
//! whatever the input. Frames of transfers longer than a slot are rejected (overflow), not
//! truncated as the specification's implicit truncation would: postcard needs all bytes.

use super::frame::{is_valid_frame_length, CanIdError, MessageCanId, Priority, TailByte};
use crate::crc::Crc16CcittFalse;
use crate::sessions::{self, Claim, SessionTimes};
use core::fmt;

/// Default transfer-ID timeout, as recommended by the specification.
pub const DEFAULT_TRANSFER_ID_TIMEOUT_US: u64 = 2_000_000;

/// Why a frame was not taken.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CanRxError {
    /// A standard (11-bit ID) frame: Cyphal/CAN uses extended frames only.
    StandardFrame,
    /// The CAN ID is not a Cyphal/CAN message ID (too wide, reserved bits set).
    ForeignCanId,
    /// A service transfer frame: not supported here.
    ServiceFrame,
    /// A subject the subject filter does not accept.
    NotSubscribed,
    /// No data at all: a Cyphal frame has at least the tail byte.
    MissingTailByte,
    /// Data length not a valid CAN/CAN FD length.
    InvalidLength,
    /// Start of transfer with toggle 0 (UAVCAN v0 convention).
    StartToggleClear,
    /// Anonymous transfers must be single-frame.
    AnonymousMultiFrame,
    /// A continuation frame with no transfer in progress.
    MissedStart,
    /// A continuation frame whose transfer-ID is not the one in progress.
    UnexpectedTransferId,
    /// Toggle bit out of sequence (lost or repeated frame).
    ToggleMismatch,
    /// The transfer-ID of the last completed transfer again, within the timeout.
    DuplicateTransfer,
    /// Multi-frame transfer CRC mismatch (or too short to hold a CRC).
    CrcMismatch,
    /// The transfer does not fit the session's slot.
    PayloadOverflow,
    /// All sessions busy with unfinished, unexpired transfers.
    NoSessionSlot,
    /// The continuation frame arrived after the transfer-ID timeout.
    TransferTimeout,
}

impl core::error::Error for CanRxError {}

impl fmt::Display for CanRxError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let text = match self {
            CanRxError::StandardFrame => "standard 11-bit frame: not Cyphal",
            CanRxError::ForeignCanId => "CAN ID is not a Cyphal message ID",
            CanRxError::ServiceFrame => "service transfers are not supported",
            CanRxError::NotSubscribed => "subject not subscribed",
            CanRxError::MissingTailByte => "frame has no tail byte",
            CanRxError::InvalidLength => "frame length is not a valid CAN FD length",
            CanRxError::StartToggleClear => "start frame with toggle 0 (UAVCAN v0)",
            CanRxError::AnonymousMultiFrame => "anonymous transfer spans several frames",
            CanRxError::MissedStart => "continuation frame without a started transfer",
            CanRxError::UnexpectedTransferId => {
                "frame transfer-ID differs from the one in progress"
            }
            CanRxError::ToggleMismatch => "toggle bit out of sequence",
            CanRxError::DuplicateTransfer => "duplicate transfer-ID within the timeout",
            CanRxError::CrcMismatch => "multi-frame transfer CRC mismatch",
            CanRxError::PayloadOverflow => "transfer larger than the reassembly slot",
            CanRxError::NoSessionSlot => "no free reassembly session",
            CanRxError::TransferTimeout => "transfer not completed within the timeout",
        };
        f.write_str(text)
    }
}

/// Frame and transfer counters; `rejected_*` count frames, `abandoned_transfers` counts
/// unfinished transfers dropped because a new one started or they timed out.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct CanRxCounters {
    pub frames: u64,
    pub transfers: u64,
    pub abandoned_transfers: u64,
    pub rejected_standard_frame: u64,
    pub rejected_foreign_can_id: u64,
    pub rejected_service_frame: u64,
    pub rejected_not_subscribed: u64,
    pub rejected_missing_tail_byte: u64,
    pub rejected_invalid_length: u64,
    pub rejected_start_toggle_clear: u64,
    pub rejected_anonymous_multi_frame: u64,
    pub rejected_missed_start: u64,
    pub rejected_unexpected_transfer_id: u64,
    pub rejected_toggle_mismatch: u64,
    pub rejected_duplicate_transfer: u64,
    pub rejected_crc_mismatch: u64,
    pub rejected_payload_overflow: u64,
    pub rejected_no_session_slot: u64,
    pub rejected_transfer_timeout: u64,
}

impl CanRxCounters {
    fn count(&mut self, error: CanRxError) {
        let counter = match error {
            CanRxError::StandardFrame => &mut self.rejected_standard_frame,
            CanRxError::ForeignCanId => &mut self.rejected_foreign_can_id,
            CanRxError::ServiceFrame => &mut self.rejected_service_frame,
            CanRxError::NotSubscribed => &mut self.rejected_not_subscribed,
            CanRxError::MissingTailByte => &mut self.rejected_missing_tail_byte,
            CanRxError::InvalidLength => &mut self.rejected_invalid_length,
            CanRxError::StartToggleClear => &mut self.rejected_start_toggle_clear,
            CanRxError::AnonymousMultiFrame => &mut self.rejected_anonymous_multi_frame,
            CanRxError::MissedStart => &mut self.rejected_missed_start,
            CanRxError::UnexpectedTransferId => &mut self.rejected_unexpected_transfer_id,
            CanRxError::ToggleMismatch => &mut self.rejected_toggle_mismatch,
            CanRxError::DuplicateTransfer => &mut self.rejected_duplicate_transfer,
            CanRxError::CrcMismatch => &mut self.rejected_crc_mismatch,
            CanRxError::PayloadOverflow => &mut self.rejected_payload_overflow,
            CanRxError::NoSessionSlot => &mut self.rejected_no_session_slot,
            CanRxError::TransferTimeout => &mut self.rejected_transfer_timeout,
        };
        *counter = counter.saturating_add(1);
    }

    /// All rejected frames, whatever the reason.
    pub fn rejected_total(&self) -> u64 {
        [
            self.rejected_standard_frame,
            self.rejected_foreign_can_id,
            self.rejected_service_frame,
            self.rejected_not_subscribed,
            self.rejected_missing_tail_byte,
            self.rejected_invalid_length,
            self.rejected_start_toggle_clear,
            self.rejected_anonymous_multi_frame,
            self.rejected_missed_start,
            self.rejected_unexpected_transfer_id,
            self.rejected_toggle_mismatch,
            self.rejected_duplicate_transfer,
            self.rejected_crc_mismatch,
            self.rejected_payload_overflow,
            self.rejected_no_session_slot,
            self.rejected_transfer_timeout,
        ]
        .iter()
        .fold(0u64, |acc, v| acc.saturating_add(*v))
    }
}

/// A completed transfer; `payload` borrows the reassembler (or the frame for single frames).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ReceivedTransfer<'a> {
    pub priority: Priority,
    pub subject_id: u16,
    /// `None` for anonymous transfers.
    pub source_node_id: Option<u8>,
    pub transfer_id: u8,
    /// Timestamp of the transfer's first frame.
    pub timestamp_us: u64,
    /// Payload including any CAN FD padding zeros; CRC removed.
    pub payload: &'a [u8],
}

#[derive(Clone, Copy, Debug)]
struct Session {
    in_use: bool,
    source_node_id: u8,
    subject_id: u16,
    in_progress: bool,
    transfer_id: u8,
    expected_toggle: bool,
    start_us: u64,
    last_activity_us: u64,
    stored_len: usize,
    crc: Crc16CcittFalse,
    last_completed_transfer_id: Option<u8>,
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
    source_node_id: 0,
    subject_id: 0,
    in_progress: false,
    transfer_id: 0,
    expected_toggle: true,
    start_us: 0,
    last_activity_us: 0,
    stored_len: 0,
    crc: Crc16CcittFalse::new(),
    last_completed_transfer_id: None,
};

enum PayloadAt {
    Frame(usize),
    Slot { slot: usize, len: usize },
}

struct Completed {
    meta: MessageCanId,
    transfer_id: u8,
    timestamp_us: u64,
    at: PayloadAt,
}

/// Bounded reassembler for Cyphal/CAN message transfers (see the module header).
///
/// `B` is the payload storage (`[u8; K]`, `&mut [u8]`, or a `Vec<u8>` on hosts); `N` the number
/// of concurrent (source, subject) sessions. Each multi-frame transfer must fit
/// `storage.len() / N` bytes including up to 15 padding bytes and the 2-byte CRC.
pub struct CanReassembler<B, const N: usize> {
    storage: B,
    slot_len: usize,
    sessions: [Session; N],
    transfer_id_timeout_us: u64,
    subject_filter: Option<SubjectFilter>,
    counters: CanRxCounters,
}

/// Which subjects get a session: a predicate, or a set fixed at run time (configured
/// subject-IDs), 8192 bits inline so that no allocator is needed.
// No allocator here, so the set stays inline: one 1 KiB filter per reassembler.
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Copy)]
enum SubjectFilter {
    Predicate(fn(u16) -> bool),
    Set(SubjectSet),
}

/// A set of subject-IDs (0..=8191).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SubjectSet([u64; 128]);

impl Default for SubjectSet {
    fn default() -> Self {
        Self([0; 128])
    }
}

impl SubjectSet {
    /// Adds `subject_id`; false (and nothing added) above 8191.
    pub fn insert(&mut self, subject_id: u16) -> bool {
        let i = usize::from(subject_id);
        match self.0.get_mut(i / 64) {
            Some(word) => {
                *word |= 1 << (i % 64);
                true
            }
            None => false,
        }
    }

    pub fn contains(&self, subject_id: u16) -> bool {
        let i = usize::from(subject_id);
        self.0.get(i / 64).is_some_and(|w| w & (1 << (i % 64)) != 0)
    }
}

impl<B: AsRef<[u8]> + AsMut<[u8]>, const N: usize> CanReassembler<B, N> {
    pub fn new(storage: B) -> Self {
        let slot_len = storage.as_ref().len().checked_div(N).unwrap_or(0);
        Self {
            storage,
            slot_len,
            sessions: [IDLE_SESSION; N],
            transfer_id_timeout_us: DEFAULT_TRANSFER_ID_TIMEOUT_US,
            subject_filter: None,
            counters: CanRxCounters::default(),
        }
    }

    pub fn with_transfer_id_timeout_us(mut self, timeout_us: u64) -> Self {
        self.transfer_id_timeout_us = timeout_us;
        self
    }

    /// Only subjects for which `filter` returns true get a session; others are rejected as
    /// [`CanRxError::NotSubscribed`] before they can occupy memory.
    pub fn with_subject_filter(mut self, filter: fn(u16) -> bool) -> Self {
        self.subject_filter = Some(SubjectFilter::Predicate(filter));
        self
    }

    /// Like [`Self::with_subject_filter`] with the subjects in `set` (configured at start).
    pub fn with_subject_set(mut self, set: SubjectSet) -> Self {
        self.subject_filter = Some(SubjectFilter::Set(set));
        self
    }

    /// Bytes available to one multi-frame transfer (payload + padding + CRC).
    pub fn slot_bytes(&self) -> usize {
        self.slot_len
    }

    pub fn counters(&self) -> &CanRxCounters {
        &self.counters
    }

    pub fn reset_counters(&mut self) {
        self.counters = CanRxCounters::default();
    }

    /// Number of sessions with a transfer in progress.
    pub fn transfers_in_progress(&self) -> usize {
        self.sessions.iter().filter(|s| s.in_progress).count()
    }

    /// Abandons unfinished transfers older than the timeout (call periodically so that a
    /// silent sender does not hold a slot).
    pub fn expire(&mut self, now_us: u64) {
        self.counters.abandoned_transfers +=
            sessions::expire(&mut self.sessions, now_us, self.transfer_id_timeout_us);
    }

    /// Feeds one received frame of either CAN ID format: standard (11-bit) frames are not
    /// Cyphal and are counted and rejected here, extended ones go to [`Self::push`].
    pub fn push_frame<'a>(
        &'a mut self,
        is_extended: bool,
        can_id: u32,
        data: &'a [u8],
        timestamp_us: u64,
    ) -> Result<Option<ReceivedTransfer<'a>>, CanRxError> {
        if !is_extended {
            self.counters.frames += 1;
            self.counters.count(CanRxError::StandardFrame);
            return Err(CanRxError::StandardFrame);
        }
        self.push(can_id, data, timestamp_us)
    }

    /// Feeds one received extended frame: `can_id` is the bare 29-bit identifier (no
    /// SocketCAN EFF/RTR/ERR flag bits, which would make it a foreign ID), `data` includes the
    /// tail byte. Use [`Self::push_frame`] when standard frames may arrive too.
    pub fn push<'a>(
        &'a mut self,
        can_id: u32,
        data: &'a [u8],
        timestamp_us: u64,
    ) -> Result<Option<ReceivedTransfer<'a>>, CanRxError> {
        self.counters.frames += 1;
        match self.accept(can_id, data, timestamp_us) {
            Err(error) => {
                self.counters.count(error);
                Err(error)
            }
            Ok(None) => Ok(None),
            Ok(Some(done)) => {
                self.counters.transfers += 1;
                let payload: &'a [u8] = match done.at {
                    PayloadAt::Frame(len) => &data[..len],
                    PayloadAt::Slot { slot, len } => {
                        let start = slot * self.slot_len;
                        &self.storage.as_ref()[start..start + len]
                    }
                };
                Ok(Some(ReceivedTransfer {
                    priority: done.meta.priority,
                    subject_id: done.meta.subject_id,
                    source_node_id: done.meta.source_node_id,
                    transfer_id: done.transfer_id,
                    timestamp_us: done.timestamp_us,
                    payload,
                }))
            }
        }
    }

    fn accept(
        &mut self,
        can_id: u32,
        data: &[u8],
        timestamp_us: u64,
    ) -> Result<Option<Completed>, CanRxError> {
        let meta = MessageCanId::from_raw(can_id).map_err(|e| match e {
            CanIdError::ServiceTransfer => CanRxError::ServiceFrame,
            _ => CanRxError::ForeignCanId,
        })?;
        let subscribed = match &self.subject_filter {
            None => true,
            Some(SubjectFilter::Predicate(filter)) => filter(meta.subject_id),
            Some(SubjectFilter::Set(set)) => set.contains(meta.subject_id),
        };
        if !subscribed {
            return Err(CanRxError::NotSubscribed);
        }
        let Some((&tail_byte, body)) = data.split_last() else {
            return Err(CanRxError::MissingTailByte);
        };
        if !is_valid_frame_length(data.len()) {
            return Err(CanRxError::InvalidLength);
        }
        let tail = TailByte::from_byte(tail_byte);
        if tail.start_of_transfer && !tail.toggle {
            return Err(CanRxError::StartToggleClear);
        }
        let Some(source) = meta.source_node_id else {
            if !(tail.start_of_transfer && tail.end_of_transfer) {
                return Err(CanRxError::AnonymousMultiFrame);
            }
            return Ok(Some(Completed {
                meta,
                transfer_id: tail.transfer_id,
                timestamp_us,
                at: PayloadAt::Frame(body.len()),
            }));
        };

        let index = match self.find_session(source, meta.subject_id) {
            Some(index) => index,
            None if !tail.start_of_transfer => return Err(CanRxError::MissedStart),
            None => self.claim_session(source, meta.subject_id, timestamp_us)?,
        };
        let timeout = self.transfer_id_timeout_us;
        let slot_len = self.slot_len;
        let session = &mut self.sessions[index];
        let since_start = timestamp_us.saturating_sub(session.start_us);
        let mut timed_out_in_progress = false;
        if session.in_progress && since_start > timeout {
            session.in_progress = false;
            self.counters.abandoned_transfers += 1;
            timed_out_in_progress = true;
        }

        if tail.start_of_transfer {
            if session.in_progress {
                if tail.transfer_id == session.transfer_id {
                    return Err(CanRxError::ToggleMismatch);
                }
                session.in_progress = false;
                self.counters.abandoned_transfers += 1;
            } else if session.last_completed_transfer_id == Some(tail.transfer_id)
                && since_start <= timeout
            {
                return Err(CanRxError::DuplicateTransfer);
            }
            session.in_progress = true;
            session.transfer_id = tail.transfer_id;
            session.expected_toggle = true;
            session.start_us = timestamp_us;
            session.stored_len = 0;
            session.crc = Crc16CcittFalse::new();
        } else if !session.in_progress {
            return Err(if timed_out_in_progress {
                CanRxError::TransferTimeout
            } else {
                CanRxError::MissedStart
            });
        } else if tail.transfer_id != session.transfer_id {
            return Err(CanRxError::UnexpectedTransferId);
        }
        if tail.toggle != session.expected_toggle {
            return Err(CanRxError::ToggleMismatch);
        }
        session.expected_toggle = !session.expected_toggle;
        session.last_activity_us = timestamp_us;

        if tail.start_of_transfer && tail.end_of_transfer {
            session.in_progress = false;
            session.last_completed_transfer_id = Some(tail.transfer_id);
            return Ok(Some(Completed {
                meta,
                transfer_id: tail.transfer_id,
                timestamp_us,
                at: PayloadAt::Frame(body.len()),
            }));
        }

        let stored = session.stored_len;
        if stored + body.len() > slot_len {
            session.in_progress = false;
            self.counters.abandoned_transfers += 1;
            return Err(CanRxError::PayloadOverflow);
        }
        let slot_start = index * slot_len;
        self.storage.as_mut()[slot_start + stored..slot_start + stored + body.len()]
            .copy_from_slice(body);
        let session = &mut self.sessions[index];
        session.stored_len += body.len();
        session.crc.update(body);
        if !tail.end_of_transfer {
            return Ok(None);
        }
        session.in_progress = false;
        if session.stored_len < 2 || session.crc.value() != 0 {
            return Err(CanRxError::CrcMismatch);
        }
        session.last_completed_transfer_id = Some(tail.transfer_id);
        Ok(Some(Completed {
            meta,
            transfer_id: tail.transfer_id,
            timestamp_us: session.start_us,
            at: PayloadAt::Slot {
                slot: index,
                len: session.stored_len - 2,
            },
        }))
    }

    fn find_session(&self, source: u8, subject_id: u16) -> Option<usize> {
        self.sessions
            .iter()
            .position(|s| s.in_use && s.source_node_id == source && s.subject_id == subject_id)
    }

    /// A free session, else the least recently active one that is idle or whose transfer
    /// has timed out. Evicting an idle session forgets its last transfer-ID (documented loss
    /// of duplicate protection under session pressure).
    fn claim_session(
        &mut self,
        source: u8,
        subject_id: u16,
        now_us: u64,
    ) -> Result<usize, CanRxError> {
        let index = match sessions::claim(&self.sessions, now_us, self.transfer_id_timeout_us) {
            Some(Claim::Free(index)) => index,
            Some(Claim::Evict { index, abandons }) => {
                if abandons {
                    self.counters.abandoned_transfers += 1;
                }
                index
            }
            None => return Err(CanRxError::NoSessionSlot),
        };
        self.sessions[index] = Session {
            in_use: true,
            source_node_id: source,
            subject_id,
            last_activity_us: now_us,
            ..IDLE_SESSION
        };
        Ok(index)
    }
}

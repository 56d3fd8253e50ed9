//! Outbound framing: catalogue messages to CCSDS datagrams (UDP) and Cyphal/CAN frames.
//!
//! Each framer keeps the per-port counters the protocols require: a 14-bit CCSDS sequence
//! count per APID and a Cyphal transfer-ID per subject. On CAN a message goes out on its
//! configured subject-ID (`crate::cyphal_config`; the ICD port when not configured). Messages are validated by
//! `interfaces::messages::encode` before anything is sent, so nothing invalid (NaN, non-unit
//! rotations) leaves the component.
//!
//! Rendered predictions ([`CanPredictions`]) go on CAN FD only when their encoding fits the
//! configured size; a larger one is never cut or dropped silently: it stays on UDP, is
//! counted, and the first one is flagged for the caller to report.

use crate::cyphal_config::SubjectIds;
use crate::transport::RawCanFrame;
use interfaces::ccsds::{message_packets, MAX_DATAGRAM_BYTES};
use interfaces::cyphal::{transfer_frames, Mtu, Priority, TransferHeader};
use interfaces::messages::{encode, encoded_len, CodecError, Message, RenderedPrediction};
use serde::Serialize;
use std::collections::BTreeMap;
use std::fmt;

#[derive(Debug, Clone, PartialEq)]
pub enum OutboundError {
    Codec {
        message: &'static str,
        error: CodecError,
    },
    Framing {
        message: &'static str,
        detail: String,
    },
}

impl fmt::Display for OutboundError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Codec { message, error } => write!(f, "cannot encode {message}: {error}"),
            Self::Framing { message, detail } => write!(f, "cannot frame {message}: {detail}"),
        }
    }
}

impl std::error::Error for OutboundError {}

fn encode_owned<M: Message + Serialize>(msg: &M) -> Result<Vec<u8>, OutboundError> {
    let codec = |error| OutboundError::Codec {
        message: M::NAME,
        error,
    };
    let len = encoded_len(msg).map_err(codec)?;
    let mut buffer = vec![0u8; len];
    let used = encode(msg, &mut buffer).map_err(codec)?.len();
    buffer.truncate(used);
    Ok(buffer)
}

/// CCSDS Space Packet framing with one sequence counter per APID.
#[derive(Debug, Default)]
pub struct UdpFramer {
    next_sequence_count: BTreeMap<u16, u16>,
}

impl UdpFramer {
    /// The datagrams (each <= 1472 bytes) carrying `msg`.
    pub fn datagrams<M: Message + Serialize>(
        &mut self,
        msg: &M,
    ) -> Result<Vec<Vec<u8>>, OutboundError> {
        let payload = encode_owned(msg)?;
        let first = self
            .next_sequence_count
            .get(&M::PORT_ID)
            .copied()
            .unwrap_or(0);
        let packets = message_packets(
            M::CCSDS_PACKET_TYPE,
            M::PORT_ID,
            &payload,
            first,
            MAX_DATAGRAM_BYTES,
        )
        .map_err(|e| OutboundError::Framing {
            message: M::NAME,
            detail: e.to_string(),
        })?;
        self.next_sequence_count
            .insert(M::PORT_ID, packets.next_message_sequence_count());
        Ok(packets.map(|p| p.to_vec()).collect())
    }
}

/// Cyphal/CAN message transfers from one node, one transfer-ID counter per subject.
#[derive(Debug)]
pub struct CanFramer {
    node_id: u8,
    mtu: Mtu,
    subjects: SubjectIds,
    next_transfer_id: BTreeMap<u16, u64>,
}

impl CanFramer {
    pub fn new(node_id: u8, fd: bool) -> Self {
        Self {
            node_id,
            mtu: if fd { Mtu::Fd } else { Mtu::Classic },
            subjects: SubjectIds::default(),
            next_transfer_id: BTreeMap::new(),
        }
    }

    /// Sends each message on its configured subject-ID.
    pub fn with_subjects(mut self, subjects: SubjectIds) -> Self {
        self.subjects = subjects;
        self
    }

    /// The frames carrying `msg` on its configured subject.
    pub fn frames<M: Message + Serialize>(
        &mut self,
        msg: &M,
    ) -> Result<Vec<RawCanFrame>, OutboundError> {
        let subject_id = self.subjects.subject_of(M::PORT_ID).unwrap_or(M::PORT_ID);
        self.frames_on(subject_id, &encode_owned(msg)?, M::NAME)
    }

    /// The frames carrying the encoded `payload` of message `name` on `subject_id`.
    fn frames_on(
        &mut self,
        subject_id: u16,
        payload: &[u8],
        name: &'static str,
    ) -> Result<Vec<RawCanFrame>, OutboundError> {
        let transfer_id = self.next_transfer_id.entry(subject_id).or_insert(0);
        let header = TransferHeader {
            priority: Priority::Nominal,
            subject_id,
            source_node_id: self.node_id,
            transfer_id: *transfer_id,
        };
        *transfer_id += 1;
        let framing = |detail: String| OutboundError::Framing {
            message: name,
            detail,
        };
        let frames =
            transfer_frames(&header, payload, self.mtu).map_err(|e| framing(e.to_string()))?;
        frames
            .map(|f| {
                let built = if f.is_fd {
                    RawCanFrame::fd(f.id, &f.data)
                } else {
                    RawCanFrame::classic(f.id, &f.data)
                };
                built.map_err(|e| framing(e.to_string()))
            })
            .collect()
    }
}

/// What happens to a rendered prediction on CAN FD (it goes on UDP in every case).
#[derive(Debug, PartialEq)]
pub enum PredictionOnCan {
    /// The frames of its multi-frame CAN FD transfer.
    Frames(Vec<RawCanFrame>),
    /// Its encoding exceeds the configured size: UDP only. `first` for the first such
    /// prediction of this publisher (the one to report).
    TooLarge { encoded_bytes: usize, first: bool },
}

/// Rendered predictions as Cyphal/CAN FD transfers on a configured subject, up to a
/// configured encoded size; one transfer-ID counter for the subject.
#[derive(Debug)]
pub struct CanPredictions {
    framer: CanFramer,
    subject_id: u16,
    max_bytes: usize,
    /// Predictions framed for CAN FD.
    pub framed: u64,
    /// Predictions too large for CAN FD (UDP only).
    pub too_large: u64,
}

impl CanPredictions {
    /// Predictions from `node_id` on `subject_id`, at most `max_bytes` encoded.
    pub fn new(node_id: u8, subject_id: u16, max_bytes: usize) -> Self {
        Self {
            framer: CanFramer::new(node_id, true),
            subject_id,
            max_bytes,
            framed: 0,
            too_large: 0,
        }
    }

    pub fn subject_id(&self) -> u16 {
        self.subject_id
    }

    /// The CAN FD frames of `prediction`, or why it stays on UDP.
    pub fn route(
        &mut self,
        prediction: &RenderedPrediction<'_>,
    ) -> Result<PredictionOnCan, OutboundError> {
        let codec = |error| OutboundError::Codec {
            message: RenderedPrediction::NAME,
            error,
        };
        // Sized before encoding: an image far over the limit is never copied.
        let encoded_bytes = encoded_len(prediction).map_err(codec)?;
        if encoded_bytes > self.max_bytes {
            self.too_large += 1;
            return Ok(PredictionOnCan::TooLarge {
                encoded_bytes,
                first: self.too_large == 1,
            });
        }
        let payload = encode_owned(prediction)?;
        let frames = self
            .framer
            .frames_on(self.subject_id, &payload, RenderedPrediction::NAME)?;
        self.framed += 1;
        Ok(PredictionOnCan::Frames(frames))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use interfaces::ccsds::CcsdsReassembler;
    use interfaces::cyphal::CanReassembler;
    use interfaces::messages::{decode, SunVector};

    #[test]
    fn framed_messages_reassemble_and_counters_advance() {
        let sun = SunVector {
            time_us: 5,
            sun_body: [0.0, 0.6, 0.8],
            valid: true,
            eclipse: None,
        };
        let mut udp = UdpFramer::default();
        let mut rx: CcsdsReassembler<Vec<u8>, 2> = CcsdsReassembler::new(vec![0; 2 * 256]);
        for i in 0..2u64 {
            let datagrams = udp.datagrams(&sun).unwrap();
            assert_eq!(datagrams.len(), 1);
            let got = rx.push(&datagrams[0], i).unwrap().unwrap();
            assert_eq!(got.first_sequence_count, i as u16);
            assert_eq!(decode::<SunVector>(got.payload).unwrap(), sun);
        }
        let mut can = CanFramer::new(42, false);
        let mut crx: CanReassembler<Vec<u8>, 2> = CanReassembler::new(vec![0; 2 * 256]);
        let frames = can.frames(&sun).unwrap();
        assert!(
            frames.len() > 1,
            "23-byte message needs a multi-frame classic transfer"
        );
        let mut done = None;
        for f in &frames {
            if let Some(t) = crx.push(f.id(), f.data(), 0).unwrap() {
                assert_eq!(t.source_node_id, Some(42));
                done = Some(decode::<SunVector>(t.payload).unwrap());
            }
        }
        assert_eq!(done, Some(sun));
    }

    #[test]
    fn invalid_messages_are_not_sent() {
        let bad = SunVector {
            time_us: 5,
            sun_body: [f32::NAN, 0.0, 1.0],
            valid: true,
            eclipse: None,
        };
        assert!(matches!(
            UdpFramer::default().datagrams(&bad),
            Err(OutboundError::Codec { .. })
        ));
    }
}

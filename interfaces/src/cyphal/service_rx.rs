//! Reassembly of service requests addressed to this node, single- or multi-frame (a register
//! Access request with a long name spans several classic CAN frames).
//!
//! The session rules are exactly the message reassembler's ([`super::rx`]: toggle, transfer-ID,
//! timeout, deduplication, CRC, bounded slots), so this wraps a [`CanReassembler`] whose
//! sessions are keyed by (client node-ID, service-ID): each request frame is handed to it
//! under a message CAN ID with the service-ID in the subject field and the same priority and
//! source. Responses and requests to other nodes never reach it.
//!
//! Invariants: memory is the fixed storage given at construction; every frame that is a
//! request to us and is not taken is returned as an error and counted in
//! [`ServiceRequestRx::counters`]; nothing panics whatever the input.

use super::frame::{MessageCanId, ServiceCanId};
use super::node::{ServiceFrameError, ServiceRequest};
use super::rx::{CanReassembler, CanRxCounters, CanRxError};

/// Multi-frame service request reassembly for one local node.
pub struct ServiceRequestRx<B, const N: usize> {
    rx: CanReassembler<B, N>,
}

/// Why a frame addressed to us did not (yet) give a request.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ServiceRxError {
    /// Not a service request to this node: see [`ServiceFrameError`].
    NotOurs(ServiceFrameError),
    /// A request frame to us rejected by the session rules (counted).
    Rejected(CanRxError),
}

impl<B: AsRef<[u8]> + AsMut<[u8]>, const N: usize> ServiceRequestRx<B, N> {
    /// `storage.len() / N` bytes per concurrent request (payload, padding and CRC).
    pub fn new(storage: B) -> Self {
        Self {
            rx: CanReassembler::new(storage),
        }
    }

    /// Frame and transfer counters of the requests to this node.
    pub fn counters(&self) -> &CanRxCounters {
        self.rx.counters()
    }

    /// Abandons requests left unfinished longer than the transfer-ID timeout.
    pub fn expire(&mut self, now_us: u64) {
        self.rx.expire(now_us);
    }

    /// Feeds one received extended frame; `Ok(Some)` when it completes a request to
    /// `local_node_id`, `Ok(None)` while a multi-frame request is still in progress.
    pub fn push<'a>(
        &'a mut self,
        can_id: u32,
        data: &'a [u8],
        local_node_id: u8,
        now_us: u64,
    ) -> Result<Option<ServiceRequest<'a>>, ServiceRxError> {
        let id = ServiceCanId::from_raw(can_id)
            .map_err(|_| ServiceRxError::NotOurs(ServiceFrameError::NotService))?;
        if !id.is_request || id.destination_node_id != local_node_id {
            return Err(ServiceRxError::NotOurs(ServiceFrameError::NotForUs));
        }
        let keyed = MessageCanId {
            priority: id.priority,
            subject_id: id.service_id,
            source_node_id: Some(id.source_node_id),
        }
        .to_raw()
        // Service-IDs (<= 511) and node-IDs (<= 127) always fit a message ID.
        .map_err(|_| ServiceRxError::NotOurs(ServiceFrameError::NotService))?;
        match self.rx.push(keyed, data, now_us) {
            Ok(Some(transfer)) => Ok(Some(ServiceRequest {
                id,
                transfer_id: transfer.transfer_id,
                payload: transfer.payload,
            })),
            Ok(None) => Ok(None),
            Err(e) => Err(ServiceRxError::Rejected(e)),
        }
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use crate::cyphal::{service_transfer_frames, Mtu, Priority};
    use std::vec;
    use std::vec::Vec;

    fn request_frames(payload: &[u8], tid: u64, mtu: Mtu) -> Vec<(u32, Vec<u8>)> {
        let id = ServiceCanId {
            priority: Priority::High,
            service_id: 384,
            is_request: true,
            destination_node_id: 42,
            source_node_id: 7,
        };
        service_transfer_frames(&id, tid, payload, mtu)
            .unwrap()
            .map(|f| (f.id, f.data.to_vec()))
            .collect()
    }

    #[test]
    fn multi_frame_requests_reassemble_with_their_ids() {
        let mut rx = ServiceRequestRx::<_, 2>::new(vec![0u8; 2 * 600]);
        let payload: Vec<u8> = (0..40u8).collect();
        let frames = request_frames(&payload, 3, Mtu::Classic);
        assert!(frames.len() > 1);
        let (last, head) = frames.split_last().unwrap();
        for (id, data) in head {
            assert_eq!(rx.push(*id, data, 42, 0), Ok(None));
        }
        let request = rx.push(last.0, &last.1, 42, 0).unwrap().unwrap();
        assert_eq!(request.payload, &payload[..]);
        assert_eq!(request.transfer_id, 3);
        assert_eq!(request.id.service_id, 384);
        assert_eq!(request.id.source_node_id, 7);
        assert_eq!(request.id.priority, Priority::High);
        // The same transfer again is a duplicate; another node's request is not ours.
        assert_eq!(
            rx.push(frames[0].0, &frames[0].1, 42, 1),
            Err(ServiceRxError::Rejected(CanRxError::DuplicateTransfer))
        );
        assert_eq!(
            rx.push(frames[0].0, &frames[0].1, 43, 1),
            Err(ServiceRxError::NotOurs(ServiceFrameError::NotForUs))
        );
        let mut corrupt = request_frames(&payload, 4, Mtu::Classic);
        let end = corrupt.len() - 1;
        corrupt[end].1[0] ^= 1;
        let results: Vec<_> = corrupt
            .iter()
            .map(|(id, data)| rx.push(*id, data, 42, 2).map(|r| r.is_some()))
            .collect();
        assert_eq!(
            results.last(),
            Some(&Err(ServiceRxError::Rejected(CanRxError::CrcMismatch)))
        );
        assert_eq!(rx.counters().rejected_crc_mismatch, 1);
    }

    #[test]
    fn single_frame_requests_pass_through() {
        let mut rx = ServiceRequestRx::<_, 1>::new(vec![0u8; 300]);
        let frames = request_frames(&[1, 0], 0, Mtu::Fd);
        assert_eq!(frames.len(), 1);
        let request = rx.push(frames[0].0, &frames[0].1, 42, 0).unwrap().unwrap();
        assert_eq!(request.payload, &[1, 0]);
    }
}

//! Cyphal/CAN reassembly against the specification's examples and against the reassembly
//! rules (duplicates, toggle, transfer-ID, timeouts, CRC, overflow, session pressure), with
//! every rejection checked in the counters.

use interfaces::cyphal::frame::{CanFrame, MessageCanId};
use interfaces::cyphal::{
    transfer_frames, CanReassembler, CanRxError, Mtu, Priority, TransferHeader,
};

type Rx = CanReassembler<Vec<u8>, 4>;

fn rx() -> Rx {
    CanReassembler::new(vec![0u8; 4 * 512])
}

fn frames(subject: u16, node: u8, tid: u64, payload: &[u8], mtu: Mtu) -> Vec<CanFrame> {
    let header = TransferHeader {
        priority: Priority::High,
        subject_id: subject,
        source_node_id: node,
        transfer_id: tid,
    };
    transfer_frames(&header, payload, mtu).unwrap().collect()
}

/// Feeds frames; returns the payloads of completed transfers and the errors.
fn feed<const N: usize>(
    rx: &mut CanReassembler<Vec<u8>, N>,
    frames: &[CanFrame],
    t_us: u64,
) -> (Vec<Vec<u8>>, Vec<CanRxError>) {
    let mut done = Vec::new();
    let mut errors = Vec::new();
    for f in frames {
        match rx.push(f.id, &f.data, t_us) {
            Ok(Some(t)) => done.push(t.payload.to_vec()),
            Ok(None) => {}
            Err(e) => errors.push(e),
        }
    }
    (done, errors)
}

#[test]
fn spec_heartbeat_frame_is_received() {
    let mut rx = rx();
    let data = [0x00, 0x00, 0x00, 0x00, 0x04, 0x78, 0x68, 0xE0];
    let t = rx.push(0x107D_552A, &data, 42).unwrap().unwrap();
    assert_eq!(t.subject_id, 7509);
    assert_eq!(t.source_node_id, Some(42));
    assert_eq!(t.priority, Priority::Nominal);
    assert_eq!(t.transfer_id, 0);
    assert_eq!(t.timestamp_us, 42);
    assert_eq!(t.payload, &data[..7]);
}

#[test]
fn spec_fd_array_message_is_received_with_padding() {
    let mut rx = rx();
    let mut payload = vec![0x00u8, 0xB8];
    payload.extend(0u8..=0x5B);
    let mut f1 = payload[..63].to_vec();
    f1.push(0xA0);
    let mut f2 = payload[63..].to_vec();
    f2.extend([0u8; 14]);
    f2.extend([0xC0, 0x48, 0x40]);
    assert_eq!(rx.push(0x1073_373B, &f1, 0), Ok(None));
    let t = rx.push(0x1073_373B, &f2, 1).unwrap().unwrap();
    assert_eq!(t.source_node_id, Some(59));
    assert_eq!(&t.payload[..94], &payload[..]);
    assert!(t.payload[94..].iter().all(|&b| b == 0));
    assert_eq!(t.payload.len(), 94 + 14);
    assert_eq!(t.timestamp_us, 0);
}

#[test]
fn spec_anonymous_single_frame_is_received_and_multi_frame_is_not() {
    let mut rx = rx();
    let t = rx
        .push(0x1173_3775, &[b'h', b'i', 0xE0], 0)
        .unwrap()
        .unwrap();
    assert_eq!(t.source_node_id, None);
    assert_eq!(t.subject_id, 4919);
    assert_eq!(
        rx.push(0x1173_3775, &[b'h', b'i', 0xA0], 0),
        Err(CanRxError::AnonymousMultiFrame)
    );
    assert_eq!(rx.counters().rejected_anonymous_multi_frame, 1);
}

#[test]
fn duplicates_are_rejected_until_the_transfer_id_timeout() {
    let mut rx = rx();
    let f = frames(10, 5, 3, b"abc", Mtu::Classic);
    assert_eq!(feed(&mut rx, &f, 1_000).0, vec![b"abc".to_vec()]);
    assert_eq!(
        feed(&mut rx, &f, 1_500_000).1,
        vec![CanRxError::DuplicateTransfer]
    );
    // After the 2 s timeout the same transfer-ID is a new transfer (sender restarted).
    assert_eq!(feed(&mut rx, &f, 2_100_000).0.len(), 1);
    // The next transfer-ID is accepted at once, and so is a wrap from 31 to 0.
    assert_eq!(
        feed(&mut rx, &frames(10, 5, 4, b"d", Mtu::Classic), 2_100_001)
            .0
            .len(),
        1
    );
    let long: Vec<u8> = (0..50).collect();
    assert_eq!(
        feed(&mut rx, &frames(10, 5, 31, &long, Mtu::Classic), 2_200_000).0,
        vec![long.clone()]
    );
    assert_eq!(
        feed(&mut rx, &frames(10, 5, 32, &long, Mtu::Classic), 2_200_001).0,
        vec![long.clone()]
    );
    assert_eq!(rx.counters().rejected_duplicate_transfer, 1);
    assert_eq!(rx.counters().transfers, 5);
    // Same transfer-ID from another node or on another subject is another session.
    assert_eq!(
        feed(&mut rx, &frames(10, 6, 0, b"x", Mtu::Fd), 2_300_000)
            .0
            .len(),
        1
    );
    assert_eq!(
        feed(&mut rx, &frames(11, 5, 0, b"x", Mtu::Fd), 2_300_000)
            .0
            .len(),
        1
    );
}

#[test]
fn lost_repeated_and_reordered_frames_are_rejected_and_counted() {
    let payload: Vec<u8> = (0..40).collect();
    let f = frames(20, 7, 9, &payload, Mtu::Classic);
    assert_eq!(f.len(), 6);

    // Lost middle frame: the next one has the wrong toggle; the tail then misses its start.
    let mut rx = rx();
    let mut lossy = f.clone();
    lossy.remove(2);
    let (done, errors) = feed(&mut rx, &lossy, 0);
    assert!(done.is_empty());
    assert_eq!(errors[0], CanRxError::ToggleMismatch);
    assert!(!errors.is_empty());

    // Repeated frame (bus retransmission after a lost ACK): the copy is refused, the
    // transfer still completes.
    let mut rx2 = rx2_fresh();
    let mut repeated = f.clone();
    repeated.insert(3, f[2].clone());
    let (done, errors) = feed(&mut rx2, &repeated, 0);
    assert_eq!(done, vec![payload.clone()]);
    assert_eq!(errors, vec![CanRxError::ToggleMismatch]);

    // Swapped frames: toggle mismatch, nothing delivered.
    let mut rx3 = rx2_fresh();
    let mut swapped = f.clone();
    swapped.swap(1, 2);
    let (done, errors) = feed(&mut rx3, &swapped, 0);
    assert!(done.is_empty());
    assert!(errors.contains(&CanRxError::ToggleMismatch));
    assert_eq!(rx3.counters().rejected_total(), errors.len() as u64);

    // Continuation frames alone: missed start.
    let mut rx4 = rx2_fresh();
    let (_, errors) = feed(&mut rx4, &f[1..], 0);
    assert!(errors.iter().all(|e| *e == CanRxError::MissedStart));
    assert_eq!(rx4.counters().rejected_missed_start, 5);
}

fn rx2_fresh() -> Rx {
    rx()
}

#[test]
fn interleaved_transfer_id_is_rejected_and_new_start_abandons() {
    let a: Vec<u8> = (0..20).collect();
    let fa = frames(30, 1, 1, &a, Mtu::Classic);
    let fb = frames(30, 1, 2, &a, Mtu::Classic);
    let mut rx = rx();
    assert_eq!(rx.push(fa[0].id, &fa[0].data, 0), Ok(None));
    // A continuation frame of another transfer-ID.
    assert_eq!(
        rx.push(fb[1].id, &fb[1].data, 0),
        Err(CanRxError::UnexpectedTransferId)
    );
    // A new start with another transfer-ID abandons transfer 1 and completes transfer 2.
    assert_eq!(feed(&mut rx, &fb, 0).0, vec![a.clone()]);
    assert_eq!(rx.counters().abandoned_transfers, 1);
}

#[test]
fn corrupted_multi_frame_payload_fails_the_crc() {
    let payload: Vec<u8> = (0..100).collect();
    for mtu in [Mtu::Classic, Mtu::Fd] {
        let f = frames(40, 2, 0, &payload, mtu);
        for frame_index in 0..f.len() {
            let mut bad = f.clone();
            let data_len = bad[frame_index].data.len();
            if data_len < 2 {
                continue;
            }
            bad[frame_index].data[0] ^= 0x10;
            let mut rx = rx();
            let (done, errors) = feed(&mut rx, &bad, 0);
            assert!(done.is_empty());
            assert_eq!(errors, vec![CanRxError::CrcMismatch]);
            assert_eq!(rx.counters().rejected_crc_mismatch, 1);
        }
    }
}

#[test]
fn stale_transfer_times_out_and_expire_frees_sessions() {
    let payload: Vec<u8> = (0..30).collect();
    let f = frames(50, 3, 5, &payload, Mtu::Classic);
    let mut rx = rx();
    feed(&mut rx, &f[..2], 0);
    assert_eq!(rx.transfers_in_progress(), 1);
    assert_eq!(
        rx.push(f[2].id, &f[2].data, 2_500_000),
        Err(CanRxError::TransferTimeout)
    );
    assert_eq!(rx.counters().abandoned_transfers, 1);
    feed(&mut rx, &f[..2], 3_000_000);
    rx.expire(5_100_000);
    assert_eq!(rx.transfers_in_progress(), 0);
    assert_eq!(rx.counters().abandoned_transfers, 2);
}

#[test]
fn oversized_transfer_overflows_its_slot_without_touching_others() {
    // 4 sessions x 64 bytes.
    let mut rx: CanReassembler<[u8; 256], 4> = CanReassembler::new([0u8; 256]);
    assert_eq!(rx.slot_bytes(), 64);
    let fits: Vec<u8> = (0..62).collect();
    let too_big: Vec<u8> = (0..63).collect();
    let big = frames(60, 1, 0, &too_big, Mtu::Classic);
    let ok = frames(61, 1, 0, &fits, Mtu::Classic);
    let mut errors = Vec::new();
    let mut delivered = Vec::new();
    // Interleave the two transfers frame by frame.
    for i in 0..big.len().max(ok.len()) {
        for f in [big.get(i), ok.get(i)].into_iter().flatten() {
            match rx.push(f.id, &f.data, 0) {
                Ok(Some(t)) => delivered.push(t.payload.to_vec()),
                Ok(None) => {}
                Err(e) => errors.push(e),
            }
        }
    }
    assert_eq!(delivered, vec![fits]);
    assert_eq!(errors[0], CanRxError::PayloadOverflow);
    assert_eq!(rx.counters().rejected_payload_overflow, 1);
}

#[test]
fn session_pressure_evicts_idle_sessions_but_never_active_ones() {
    let mut rx: CanReassembler<Vec<u8>, 2> = CanReassembler::new(vec![0u8; 2 * 128]);
    let long: Vec<u8> = (0..30).collect();
    let a = frames(1, 1, 0, &long, Mtu::Classic);
    let b = frames(1, 2, 0, &long, Mtu::Classic);
    let c = frames(1, 3, 0, &long, Mtu::Classic);
    rx.push(a[0].id, &a[0].data, 0).unwrap();
    rx.push(b[0].id, &b[0].data, 0).unwrap();
    // Both sessions mid-transfer: a third source finds no slot.
    assert_eq!(
        rx.push(c[0].id, &c[0].data, 10),
        Err(CanRxError::NoSessionSlot)
    );
    assert_eq!(feed(&mut rx, &a[1..], 20).0, vec![long.clone()]);
    // Session A is idle now: C takes it.
    assert_eq!(feed(&mut rx, &c, 30).0, vec![long.clone()]);
    assert_eq!(feed(&mut rx, &b[1..], 40).0, vec![long.clone()]);
    assert_eq!(rx.counters().rejected_no_session_slot, 1);
}

#[test]
fn malformed_frames_are_counted_by_reason() {
    let mut rx = rx();
    let id = MessageCanId {
        priority: Priority::Nominal,
        subject_id: 5,
        source_node_id: Some(5),
    }
    .to_raw()
    .unwrap();
    assert_eq!(rx.push(id, &[], 0), Err(CanRxError::MissingTailByte));
    assert_eq!(rx.push(id, &[0u8; 9], 0), Err(CanRxError::InvalidLength));
    assert_eq!(rx.push(id, &[0u8; 65], 0), Err(CanRxError::InvalidLength));
    assert_eq!(
        rx.push(id, &[1, 0x80], 0),
        Err(CanRxError::StartToggleClear)
    );
    assert_eq!(
        rx.push(id | 1 << 23, &[0xE0], 0),
        Err(CanRxError::ForeignCanId)
    );
    assert_eq!(
        rx.push(id | 1 << 25, &[0xE0], 0),
        Err(CanRxError::ServiceFrame)
    );
    assert_eq!(
        rx.push(0xFFFF_FFFF, &[0xE0], 0),
        Err(CanRxError::ForeignCanId)
    );
    // A CANopen-style standard frame would parse as a Cyphal ID if its format were ignored.
    assert_eq!(
        rx.push_frame(false, 0x701, &[0xE0], 0),
        Err(CanRxError::StandardFrame)
    );
    // Multi-frame transfer whose frames carry no CRC bytes at all.
    assert_eq!(rx.push(id, &[0xA0], 0), Ok(None));
    assert_eq!(rx.push(id, &[0x40], 0), Err(CanRxError::CrcMismatch));
    let c = rx.counters();
    assert_eq!(c.frames, 10);
    assert_eq!(c.rejected_total(), 9);
    assert_eq!(c.rejected_standard_frame, 1);
    assert_eq!(c.rejected_missing_tail_byte, 1);
    assert_eq!(c.rejected_invalid_length, 2);
    assert_eq!(c.rejected_start_toggle_clear, 1);
    assert_eq!(c.rejected_foreign_can_id, 2);
    assert_eq!(c.rejected_service_frame, 1);
    assert_eq!(c.rejected_crc_mismatch, 1);
    rx.reset_counters();
    assert_eq!(rx.counters().frames, 0);
}

#[test]
fn subject_filter_rejects_before_allocating_a_session() {
    let mut rx: CanReassembler<Vec<u8>, 1> =
        CanReassembler::new(vec![0u8; 256]).with_subject_filter(|s| s == 100);
    let long: Vec<u8> = (0..30).collect();
    let foreign = frames(7509, 9, 0, &long, Mtu::Classic);
    let wanted = frames(100, 9, 0, &long, Mtu::Classic);
    // The foreign transfer would hold the only session mid-transfer; filtered, it cannot.
    rx.push(foreign[0].id, &foreign[0].data, 0).unwrap_err();
    assert_eq!(feed(&mut rx, &wanted, 0).0, vec![long]);
    assert_eq!(rx.counters().rejected_not_subscribed, 1);
}

//! Fuzz harness shared by the `cargo fuzz` target (`fuzz_targets/decoders.rs`) and the
//! committed-corpus replay test (`tests/corpus.rs`): one input drives one decoder or
//! reassembler, chosen by its first byte. Any panic, or a broken invariant (asserted here),
//! is a finding. Invariants: counters account for every input, memory stays in the fixed
//! storage, and a payload framed by our own transmit side always comes back unchanged.

use interfaces::ccsds::{message_packets, CcsdsReassembler, PacketType};
use interfaces::cyphal::{transfer_frames, CanReassembler, Mtu, Priority, TransferHeader};
use interfaces::messages::{
    decode, decode_command, CameraFrame, Command, CommandAck, Event, HealthStatus,
    RenderedPrediction, SunVector, TargetPose,
};

/// Runs one fuzz input. Panics on a finding.
pub fn run(input: &[u8]) {
    let Some((&selector, rest)) = input.split_first() else {
        return;
    };
    match selector % 5 {
        0 => messages(rest),
        1 => can_frames(rest),
        2 => ccsds_datagrams(rest),
        3 => can_round_trip(rest),
        _ => ccsds_round_trip(rest),
    }
}

fn messages(bytes: &[u8]) {
    let _ = decode::<SunVector>(bytes);
    let _ = decode::<TargetPose>(bytes);
    let _ = decode::<CameraFrame>(bytes);
    let _ = decode::<RenderedPrediction>(bytes);
    let _ = decode::<CommandAck>(bytes);
    let _ = decode::<HealthStatus>(bytes);
    let _ = decode::<Event>(bytes);
    if let Ok(c) = decode_command(bytes) {
        assert_eq!(decode::<Command>(bytes), Ok(c));
    }
}

/// Records: `len(1) id(4, LE) dt_us(2, LE) data(len % 65)`.
fn can_frames(mut bytes: &[u8]) {
    let mut rx: CanReassembler<[u8; 1024], 4> = CanReassembler::new([0u8; 1024]);
    let mut t_us = 0u64;
    let (mut pushed, mut delivered, mut rejected) = (0u64, 0u64, 0u64);
    while bytes.len() >= 7 {
        let len = usize::from(bytes[0]) % 65;
        let id = u32::from_le_bytes([bytes[1], bytes[2], bytes[3], bytes[4]]);
        t_us += u64::from(u16::from_le_bytes([bytes[5], bytes[6]])) * 100;
        let end = (7 + len).min(bytes.len());
        match rx.push(id, &bytes[7..end], t_us) {
            Ok(Some(t)) => {
                assert!(t.payload.len() <= 256);
                delivered += 1;
            }
            Ok(None) => {}
            Err(_) => rejected += 1,
        }
        pushed += 1;
        assert!(rx.transfers_in_progress() <= 4);
        bytes = &bytes[end..];
    }
    let c = rx.counters();
    assert_eq!(c.frames, pushed);
    assert_eq!(c.transfers, delivered);
    assert_eq!(c.rejected_total(), rejected);
}

/// Records: `len(2, LE) dt_us(2, LE) datagram(len % 1500)`.
fn ccsds_datagrams(mut bytes: &[u8]) {
    let mut rx: CcsdsReassembler<[u8; 4096], 2> = CcsdsReassembler::new([0u8; 4096]);
    let mut t_us = 0u64;
    let (mut pushed, mut delivered, mut rejected) = (0u64, 0u64, 0u64);
    while bytes.len() >= 4 {
        let len = usize::from(u16::from_le_bytes([bytes[0], bytes[1]])) % 1500;
        t_us += u64::from(u16::from_le_bytes([bytes[2], bytes[3]])) * 100;
        let end = (4 + len).min(bytes.len());
        match rx.push(&bytes[4..end], t_us) {
            Ok(Some(m)) => {
                assert!(m.payload.len() <= 2048);
                delivered += 1;
            }
            Ok(None) => {}
            Err(_) => rejected += 1,
        }
        pushed += 1;
        assert!(rx.messages_in_progress() <= 2);
        bytes = &bytes[end..];
    }
    let c = rx.counters();
    assert_eq!(c.datagrams, pushed);
    assert_eq!(c.messages, delivered);
    assert_eq!(c.rejected_total(), rejected);
}

/// `mtu_selector(1) transfer_id(1) payload...`: frames from our encoder come back whole.
fn can_round_trip(bytes: &[u8]) {
    let [mtu_sel, tid, payload @ ..] = bytes else {
        return;
    };
    let mtu = if mtu_sel % 2 == 0 {
        Mtu::Classic
    } else {
        Mtu::Fd
    };
    let header = TransferHeader {
        priority: Priority::from_bits(*mtu_sel >> 5),
        subject_id: u16::from(*tid) * 31,
        source_node_id: tid % 128,
        transfer_id: u64::from(*tid),
    };
    let mut rx: CanReassembler<[u8; 8192], 1> = CanReassembler::new([0u8; 8192]);
    let payload = &payload[..payload.len().min(8192 - 17)];
    let mut got = None;
    for f in transfer_frames(&header, payload, mtu).expect("valid header") {
        assert!(f.data.len() <= mtu.bytes());
        if let Some(t) = rx.push(f.id, &f.data, 0).expect("own frames are accepted") {
            got = Some(t.payload.len());
            assert_eq!(&t.payload[..payload.len()], payload);
            assert!(t.payload[payload.len()..].iter().all(|&b| b == 0));
        }
    }
    assert!(got.is_some());
}

/// `max_datagram(2, LE) first_count(2, LE) payload...`: packets from our segmenter come back.
fn ccsds_round_trip(bytes: &[u8]) {
    let [m0, m1, c0, c1, payload @ ..] = bytes else {
        return;
    };
    let max = 7 + usize::from(u16::from_le_bytes([*m0, *m1])) % (1472 - 6);
    let first = u16::from_le_bytes([*c0, *c1]);
    let mut rx: CcsdsReassembler<[u8; 16384], 1> = CcsdsReassembler::new([0u8; 16384]);
    let payload = &payload[..payload.len().min(16384 - 4)];
    let mut got = 0;
    for p in message_packets(PacketType::Telemetry, 5, payload, first, max).expect("valid args") {
        assert!(p.len() <= max);
        if let Some(m) = rx.push(&p, 0).expect("own packets are accepted") {
            assert_eq!(m.payload, payload);
            got += 1;
        }
    }
    assert_eq!(got, 1);
}

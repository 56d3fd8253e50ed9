//! Property tests for every decoder and reassembler:
//! - arbitrary bytes never panic, counters account for every input, memory stays within the
//!   fixed storage;
//! - any payload survives any MTU / any datagram size, also interleaved with other sessions;
//! - corrupted, truncated, reordered and duplicated input is rejected and counted, and never
//!   yields a wrong payload.

mod common;

use common::{all_encoded, SplitMix64};
use interfaces::ccsds::{message_packets, CcsdsReassembler, Datagram, PacketType};
use interfaces::cyphal::frame::CanFrame;
use interfaces::cyphal::{transfer_frames, CanReassembler, Mtu, Priority, TransferHeader};
use interfaces::messages::{
    decode, decode_command, CameraFrame, Command, CommandAck, Event, HealthStatus,
    RenderedPrediction, SunVector, TargetPose,
};
use proptest::prelude::*;

fn can_frames(subject: u16, node: u8, tid: u64, payload: &[u8], mtu: Mtu) -> Vec<CanFrame> {
    let header = TransferHeader {
        priority: Priority::Nominal,
        subject_id: subject,
        source_node_id: node,
        transfer_id: tid,
    };
    transfer_frames(&header, payload, mtu).unwrap().collect()
}

fn mtu_strategy() -> impl Strategy<Value = Mtu> {
    prop_oneof![Just(Mtu::Classic), Just(Mtu::Fd)]
}

/// Payload delivered over CAN equals the sent one up to trailing zero padding.
fn same_up_to_padding(received: &[u8], sent: &[u8]) -> bool {
    received.len() >= sent.len()
        && &received[..sent.len()] == sent
        && received[sent.len()..].iter().all(|&b| b == 0)
        && received.len() - sent.len() <= 15
}

type CanRx = CanReassembler<Vec<u8>, 8>;

fn can_rx() -> CanRx {
    CanReassembler::new(vec![0u8; 8 * 4096])
}

/// Pushes frames; returns delivered payloads and the number of rejections.
fn can_feed(rx: &mut CanRx, frames: &[CanFrame]) -> (Vec<Vec<u8>>, usize) {
    let mut done = Vec::new();
    let mut rejected = 0;
    for f in frames {
        match rx.push(f.id, &f.data, 1000) {
            Ok(Some(t)) => done.push(t.payload.to_vec()),
            Ok(None) => {}
            Err(_) => rejected += 1,
        }
    }
    (done, rejected)
}

type UdpRx = CcsdsReassembler<Vec<u8>, 8>;

fn udp_rx() -> UdpRx {
    CcsdsReassembler::new(vec![0u8; 8 * 32768])
}

fn udp_feed(rx: &mut UdpRx, packets: &[Datagram]) -> (Vec<Vec<u8>>, usize) {
    let mut done = Vec::new();
    let mut rejected = 0;
    for p in packets {
        match rx.push(p, 1000) {
            Ok(Some(m)) => done.push(m.payload.to_vec()),
            Ok(None) => {}
            Err(_) => rejected += 1,
        }
    }
    (done, rejected)
}

/// Merges per-transfer frame lists in a random order that keeps each list's own order.
fn interleave<T: Clone>(lists: &[Vec<T>], seed: u64) -> Vec<T> {
    let mut rng = SplitMix64(seed);
    let mut cursors = vec![0usize; lists.len()];
    let mut out = Vec::new();
    loop {
        let open: Vec<usize> = (0..lists.len())
            .filter(|&i| cursors[i] < lists[i].len())
            .collect();
        if open.is_empty() {
            return out;
        }
        let pick = open[(rng.next_u64() % open.len() as u64) as usize];
        out.push(lists[pick][cursors[pick]].clone());
        cursors[pick] += 1;
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 256, ..ProptestConfig::default() })]

    #[test]
    fn message_decoders_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..600)) {
        let _ = decode::<SunVector>(&bytes);
        let _ = decode::<TargetPose>(&bytes);
        let _ = decode::<CameraFrame>(&bytes);
        let _ = decode::<RenderedPrediction>(&bytes);
        let _ = decode::<Command>(&bytes);
        let _ = decode::<CommandAck>(&bytes);
        let _ = decode::<HealthStatus>(&bytes);
        let _ = decode::<Event>(&bytes);
        // The classified command decoder agrees with the plain one on success.
        if let Ok(c) = decode_command(&bytes) {
            prop_assert_eq!(decode::<Command>(&bytes), Ok(c));
        }
    }

    #[test]
    fn can_reassembler_never_panics_and_accounts_for_every_frame(
        frames in proptest::collection::vec(
            (
                prop_oneof![any::<u32>(), (0u16..4, 0u8..3).prop_map(|(s, n)| 0x1060_0000 | u32::from(s) << 8 | u32::from(n))],
                proptest::collection::vec(any::<u8>(), 0..70),
                0u64..5_000_000,
            ),
            0..300,
        )
    ) {
        let mut rx: CanReassembler<[u8; 512], 4> = CanReassembler::new([0u8; 512]);
        let mut delivered = 0u64;
        let mut pending = 0u64;
        let mut rejected = 0u64;
        for (id, data, t) in &frames {
            match rx.push(*id, data, *t) {
                Ok(Some(t)) => {
                    prop_assert!(t.payload.len() <= 64);
                    delivered += 1;
                }
                Ok(None) => pending += 1,
                Err(_) => rejected += 1,
            }
            prop_assert!(rx.transfers_in_progress() <= 4);
        }
        let c = *rx.counters();
        prop_assert_eq!(c.frames, frames.len() as u64);
        prop_assert_eq!(c.transfers, delivered);
        prop_assert_eq!(c.rejected_total(), rejected);
        prop_assert_eq!(delivered + pending + rejected, frames.len() as u64);
    }

    #[test]
    fn ccsds_reassembler_never_panics_and_accounts_for_every_datagram(
        datagrams in proptest::collection::vec(
            prop_oneof![
                proptest::collection::vec(any::<u8>(), 0..1500),
                // Near-valid: a plausible header (version 0, no secondary header, few APIDs).
                (0u16..3, 0u8..4, 0u16..8, proptest::collection::vec(any::<u8>(), 1..300)).prop_map(
                    |(apid, flags, count, data)| {
                        let mut d = vec![(apid >> 8) as u8, apid as u8, flags << 6, count as u8];
                        d.extend(((data.len() - 1) as u16).to_be_bytes());
                        d.extend(data);
                        d
                    }
                ),
            ],
            0..100,
        ),
        timestamps in proptest::collection::vec(0u64..5_000_000, 100),
    ) {
        let mut rx: CcsdsReassembler<Vec<u8>, 2> = CcsdsReassembler::new(vec![0u8; 2 * 700]);
        let (mut delivered, mut pending, mut rejected) = (0u64, 0u64, 0u64);
        for (d, t) in datagrams.iter().zip(&timestamps) {
            match rx.push(d, *t) {
                Ok(Some(m)) => {
                    prop_assert!(m.payload.len() <= 1466);
                    delivered += 1;
                }
                Ok(None) => pending += 1,
                Err(_) => rejected += 1,
            }
            prop_assert!(rx.messages_in_progress() <= 2);
        }
        let c = *rx.counters();
        prop_assert_eq!(c.datagrams, datagrams.len() as u64);
        prop_assert_eq!(c.messages, delivered);
        prop_assert_eq!(c.rejected_total(), rejected);
        prop_assert_eq!(delivered + pending + rejected, datagrams.len() as u64);
    }

    #[test]
    fn any_payload_survives_any_mtu_interleaved(
        payloads in proptest::collection::vec(proptest::collection::vec(any::<u8>(), 0..1500), 1..5),
        mtu in mtu_strategy(),
        first_tid in any::<u64>(),
        seed in any::<u64>(),
    ) {
        // One transfer per source node, all on one subject, frames interleaved across nodes.
        let lists: Vec<Vec<CanFrame>> = payloads
            .iter()
            .enumerate()
            .map(|(i, p)| can_frames(77, i as u8 + 1, first_tid.wrapping_add(i as u64), p, mtu))
            .collect();
        let mut rx = can_rx();
        let (done, rejected) = can_feed(&mut rx, &interleave(&lists, seed));
        prop_assert_eq!(rejected, 0);
        prop_assert_eq!(done.len(), payloads.len());
        // Completion order follows the interleaving; match each delivered payload to its sender.
        let mut unmatched: Vec<&Vec<u8>> = payloads.iter().collect();
        for d in &done {
            let pos = unmatched.iter().position(|p| same_up_to_padding(d, p));
            prop_assert!(pos.is_some());
            unmatched.remove(pos.unwrap());
        }
    }

    #[test]
    fn any_payload_survives_any_datagram_size_interleaved(
        sizes in proptest::collection::vec(0usize..20_000, 1..4),
        max_datagram in 7usize..=1472,
        first_count in 0u16..16384,
        seed in any::<u64>(),
    ) {
        let mut rng = SplitMix64(seed);
        let payloads: Vec<Vec<u8>> = sizes.iter().map(|&n| rng.bytes(n)).collect();
        let lists: Vec<Vec<Datagram>> = payloads
            .iter()
            .enumerate()
            .map(|(i, p)| {
                message_packets(PacketType::Telemetry, 10 + i as u16, p, first_count, max_datagram)
                    .unwrap()
                    .collect()
            })
            .collect();
        for list in &lists {
            prop_assert!(list.iter().all(|d| d.len() <= max_datagram));
        }
        let mut rx = udp_rx();
        let (done, rejected) = udp_feed(&mut rx, &interleave(&lists, seed ^ 1));
        prop_assert_eq!(rejected, 0);
        let mut done_sorted = done.clone();
        done_sorted.sort();
        let mut expected = payloads.clone();
        expected.sort();
        prop_assert_eq!(done_sorted, expected);
    }

    #[test]
    fn catalogue_messages_survive_both_transports(seed in any::<u64>(), max_datagram in 7usize..=1472, mtu in mtu_strategy()) {
        let mut rng = SplitMix64(seed);
        for (port, bytes) in all_encoded(&mut rng) {
            let frames = can_frames(port, 9, seed, &bytes, mtu);
            let mut rx = can_rx();
            let (done, _) = can_feed(&mut rx, &frames);
            prop_assert_eq!(done.len(), 1);
            prop_assert!(same_up_to_padding(&done[0], &bytes));
            let packets: Vec<Datagram> =
                message_packets(PacketType::Telemetry, port, &bytes, 0, max_datagram).unwrap().collect();
            let mut urx = udp_rx();
            let (done, _) = udp_feed(&mut urx, &packets);
            prop_assert_eq!(&done, &vec![bytes.clone()]);
        }
    }

    #[test]
    fn can_bit_flips_in_multi_frame_data_are_caught_by_the_crc(
        payload in proptest::collection::vec(any::<u8>(), 8..600),
        mtu in mtu_strategy(),
        pick in any::<u64>(),
        bit in 0u8..8,
    ) {
        let mut frames = can_frames(5, 5, 0, &payload, mtu);
        prop_assume!(frames.len() > 1);
        // Any data byte except tail bytes: payload, padding and CRC are all covered.
        let positions: Vec<(usize, usize)> = frames
            .iter()
            .enumerate()
            .flat_map(|(i, f)| (0..f.data.len() - 1).map(move |j| (i, j)))
            .collect();
        let (fi, bi) = positions[(pick % positions.len() as u64) as usize];
        frames[fi].data[bi] ^= 1 << bit;
        let mut rx = can_rx();
        let (done, rejected) = can_feed(&mut rx, &frames);
        prop_assert!(done.is_empty());
        prop_assert_eq!(rejected, 1);
        prop_assert_eq!(rx.counters().rejected_crc_mismatch, 1);
    }

    #[test]
    fn can_duplicated_frames_deliver_once_and_reordered_frames_never_deliver(
        payload in proptest::collection::vec(any::<u8>(), 0..400),
        mtu in mtu_strategy(),
        pick in any::<u64>(),
    ) {
        let frames = can_frames(6, 6, 3, &payload, mtu);
        let i = (pick % frames.len() as u64) as usize;
        let mut doubled = frames.clone();
        doubled.insert(i + 1, frames[i].clone());
        let mut rx = can_rx();
        let (done, rejected) = can_feed(&mut rx, &doubled);
        prop_assert_eq!(done.len(), 1);
        prop_assert!(same_up_to_padding(&done[0], &payload));
        prop_assert_eq!(rejected, 1);
        prop_assert_eq!(rx.counters().rejected_total(), 1);

        if frames.len() > 1 {
            let j = (pick % (frames.len() as u64 - 1)) as usize;
            let mut swapped = frames.clone();
            swapped.swap(j, j + 1);
            let mut rx = can_rx();
            let (done, rejected) = can_feed(&mut rx, &swapped);
            prop_assert!(done.is_empty());
            prop_assert!(rejected >= 1);
            // Truncated transfer: nothing delivered, the stale session is expired and counted.
            let mut rx = can_rx();
            let (done, _) = can_feed(&mut rx, &frames[..frames.len() - 1]);
            prop_assert!(done.is_empty());
            rx.expire(10_000_000);
            prop_assert_eq!(rx.counters().abandoned_transfers, 1);
        }
    }

    #[test]
    fn ccsds_corruption_truncation_reorder_and_duplication_are_rejected(
        size in 0usize..6000,
        max_datagram in 7usize..=1472,
        pick in any::<u64>(),
        bit in 0u8..8,
        seed in any::<u64>(),
    ) {
        let payload = SplitMix64(seed).bytes(size);
        let packets: Vec<Datagram> =
            message_packets(PacketType::Telemetry, 33, &payload, 100, max_datagram).unwrap().collect();
        let n = packets.len();
        let i = (pick % n as u64) as usize;

        // Bit flip in a data field.
        let mut flipped = packets.clone();
        let data_len = flipped[i].len() - 6;
        let pos = 6 + ((pick >> 20) % data_len as u64) as usize;
        flipped[i][pos] ^= 1 << bit;
        let mut rx = udp_rx();
        let (done, rejected) = udp_feed(&mut rx, &flipped);
        prop_assert!(done.is_empty());
        prop_assert_eq!(rejected, 1);

        // Truncated datagram.
        let mut truncated = packets.clone();
        let cut = truncated[i].len() - 1;
        truncated[i].truncate(cut);
        let mut rx = udp_rx();
        let (done, rejected) = udp_feed(&mut rx, &truncated);
        prop_assert!(done.is_empty());
        prop_assert!(rejected >= 1);
        prop_assert!(rx.counters().rejected_length_mismatch >= 1);

        // Duplicated datagram: delivered once, one rejection.
        let mut doubled = packets.clone();
        doubled.insert(i + 1, packets[i].clone());
        let mut rx = udp_rx();
        let (done, rejected) = udp_feed(&mut rx, &doubled);
        prop_assert_eq!(&done, &vec![payload.clone()]);
        prop_assert_eq!(rejected, 1);

        // Swapped neighbours: never delivered.
        if n > 1 {
            let j = (pick % (n as u64 - 1)) as usize;
            let mut swapped = packets.clone();
            swapped.swap(j, j + 1);
            let mut rx = udp_rx();
            let (done, rejected) = udp_feed(&mut rx, &swapped);
            prop_assert!(done.is_empty());
            prop_assert!(rejected >= 1);
        }
    }
}

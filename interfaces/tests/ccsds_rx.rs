//! CCSDS reassembly rules: whole messages in one and many packets, loss, reordering,
//! duplication, corruption, timeouts, overflow, malformed datagrams; every rejection counted.

use interfaces::ccsds::header::{PrimaryHeader, PRIMARY_HEADER_LEN};
use interfaces::ccsds::{
    message_packets, CcsdsReassembler, CcsdsRxError, Datagram, PacketType, SequenceFlags,
};

type Rx = CcsdsReassembler<Vec<u8>, 4>;

fn rx() -> Rx {
    CcsdsReassembler::new(vec![0u8; 4 * 8192])
}

fn packets(apid: u16, payload: &[u8], first_count: u16, max: usize) -> Vec<Datagram> {
    message_packets(PacketType::Telemetry, apid, payload, first_count, max)
        .unwrap()
        .collect()
}

fn feed(rx: &mut Rx, packets: &[Datagram], t_us: u64) -> (Vec<Vec<u8>>, Vec<CcsdsRxError>) {
    let mut done = Vec::new();
    let mut errors = Vec::new();
    for p in packets {
        match rx.push(p, t_us) {
            Ok(Some(m)) => done.push(m.payload.to_vec()),
            Ok(None) => {}
            Err(e) => errors.push(e),
        }
    }
    (done, errors)
}

fn payload(n: usize) -> Vec<u8> {
    (0..n).map(|i| (i * 31 % 251) as u8).collect()
}

#[test]
fn unsegmented_and_segmented_messages_arrive_whole() {
    let mut rx = rx();
    let small = payload(100);
    let m = {
        let p = packets(200, &small, 5, 1472);
        assert_eq!(p.len(), 1);
        let msg = rx.push(&p[0], 7).unwrap().unwrap();
        assert_eq!(msg.apid, 200);
        assert_eq!(msg.first_sequence_count, 5);
        assert_eq!(msg.packet_count, 1);
        msg.payload.to_vec()
    };
    assert_eq!(m, small);
    let big = payload(5000);
    let p = packets(200, &big, 6, 1472);
    assert_eq!(p.len(), 4);
    assert!(p.iter().all(|d| d.len() <= 1472));
    let (done, errors) = feed(&mut rx, &p, 10);
    assert_eq!(done, vec![big]);
    assert!(errors.is_empty());
    assert_eq!(rx.counters().messages, 2);
    // Empty message: just the CRC.
    assert_eq!(
        feed(&mut rx, &packets(200, &[], 10, 1472), 11).0,
        vec![Vec::<u8>::new()]
    );
}

#[test]
fn loss_reorder_and_duplication_are_rejected_and_counted() {
    let big = payload(4000);
    let p = packets(201, &big, 100, 1000);
    assert_eq!(p.len(), 5);

    let mut lossy = p.clone();
    lossy.remove(2);
    let mut r = rx();
    let (done, errors) = feed(&mut r, &lossy, 0);
    assert!(done.is_empty());
    assert_eq!(errors[0], CcsdsRxError::SequenceGap);
    assert!(errors[1..].iter().all(|e| *e == CcsdsRxError::MissingFirst));
    assert_eq!(r.counters().abandoned_messages, 1);

    let mut swapped = p.clone();
    swapped.swap(1, 3);
    let mut r = rx();
    let (done, errors) = feed(&mut r, &swapped, 0);
    assert!(done.is_empty());
    assert_eq!(errors[0], CcsdsRxError::SequenceGap);

    // A duplicated datagram right after itself is dropped; the message still completes.
    let mut doubled = p.clone();
    doubled.insert(2, p[1].clone());
    let mut r = rx();
    let (done, errors) = feed(&mut r, &doubled, 0);
    assert_eq!(done, vec![big.clone()]);
    assert_eq!(errors, vec![CcsdsRxError::Duplicate]);
    // The whole message again, at once: the first packet is a duplicate of nothing recent
    // (the last count was the Last packet), so it is a new message and arrives again.
    let (done, _) = feed(&mut r, &p, 0);
    assert_eq!(done.len(), 1);
    // A duplicated unsegmented message is caught.
    let small = packets(202, b"hello", 9, 1472);
    let (done, errors) = feed(&mut r, &[small[0].clone(), small[0].clone()], 5);
    assert_eq!(done.len(), 1);
    assert_eq!(errors, vec![CcsdsRxError::Duplicate]);
    assert_eq!(r.counters().rejected_duplicate, 2);
}

#[test]
fn corruption_anywhere_in_the_data_fails_the_crc() {
    let big = payload(3000);
    let p = packets(203, &big, 0, 1472);
    for packet in 0..p.len() {
        for pos in [PRIMARY_HEADER_LEN, p[packet].len() - 1] {
            let mut bad = p.clone();
            bad[packet][pos] ^= 0x01;
            let mut r = rx();
            let (done, errors) = feed(&mut r, &bad, 0);
            assert!(done.is_empty());
            assert_eq!(errors, vec![CcsdsRxError::CrcMismatch]);
        }
    }
}

#[test]
fn malformed_datagrams_are_counted_by_reason() {
    let mut r = rx();
    let good = packets(204, b"abc", 0, 1472).remove(0);
    assert_eq!(r.push(&good[..5], 0), Err(CcsdsRxError::Truncated));
    assert_eq!(
        r.push(&good[..good.len() - 1], 0),
        Err(CcsdsRxError::LengthMismatch)
    );
    let mut longer = good.to_vec();
    longer.push(0);
    assert_eq!(r.push(&longer, 0), Err(CcsdsRxError::LengthMismatch));
    let mut version = good.to_vec();
    version[0] |= 0x20;
    assert_eq!(r.push(&version, 0), Err(CcsdsRxError::BadVersion));
    let mut secondary = good.to_vec();
    secondary[0] |= 0x08;
    assert_eq!(
        r.push(&secondary, 0),
        Err(CcsdsRxError::SecondaryHeaderUnsupported)
    );
    let mut idle = good.to_vec();
    idle[0] |= 0x07;
    idle[1] = 0xFF;
    assert_eq!(r.push(&idle, 0), Err(CcsdsRxError::IdlePacket));
    assert_eq!(r.push(&vec![0u8; 1473], 0), Err(CcsdsRxError::Oversized));
    // Data shorter than a CRC.
    let tiny = PrimaryHeader {
        packet_type: PacketType::Telemetry,
        secondary_header: false,
        apid: 204,
        sequence_flags: SequenceFlags::Unsegmented,
        sequence_count: 1,
        data_field_len: 2,
    }
    .encode()
    .unwrap();
    let mut tiny = tiny.to_vec();
    tiny.extend([0, 0]);
    assert_eq!(r.push(&tiny, 0), Err(CcsdsRxError::CrcMismatch));
    let c = r.counters();
    assert_eq!(c.datagrams, 8);
    assert_eq!(c.rejected_total(), 8);
    assert_eq!(c.rejected_length_mismatch, 2);
    assert_eq!(c.rejected_crc_mismatch, 1);
}

#[test]
fn timeout_abandons_and_overflow_is_contained() {
    let big = payload(3000);
    let p = packets(205, &big, 0, 1472);
    let mut r = rx();
    feed(&mut r, &p[..2], 0);
    assert_eq!(r.messages_in_progress(), 1);
    assert_eq!(r.push(&p[2], 3_000_000), Err(CcsdsRxError::Timeout));
    assert_eq!(r.counters().abandoned_messages, 1);
    feed(&mut r, &p[..1], 4_000_000);
    r.expire(7_000_000);
    assert_eq!(r.messages_in_progress(), 0);

    let mut small: CcsdsReassembler<Vec<u8>, 2> = CcsdsReassembler::new(vec![0u8; 2 * 2000]);
    let (done, errors) = {
        let mut done = Vec::new();
        let mut errors = Vec::new();
        for d in &p {
            match small.push(d, 0) {
                Ok(Some(m)) => done.push(m.payload.to_vec()),
                Ok(None) => {}
                Err(e) => errors.push(e),
            }
        }
        (done, errors)
    };
    assert!(done.is_empty());
    assert_eq!(errors[0], CcsdsRxError::PayloadOverflow);
    // Another APID still gets through.
    let ok = packets(206, &payload(1900), 0, 1472);
    let mut last = None;
    for d in &ok {
        last = small.push(d, 0).unwrap().map(|m| m.payload.len());
    }
    assert_eq!(last, Some(1900));
}

#[test]
fn telecommand_and_telemetry_on_one_apid_are_separate_sessions() {
    let mut r = rx();
    let tm: Vec<Datagram> = message_packets(PacketType::Telemetry, 300, &payload(2000), 0, 1472)
        .unwrap()
        .collect();
    let tc: Vec<Datagram> = message_packets(PacketType::Telecommand, 300, b"cmd", 0, 1472)
        .unwrap()
        .collect();
    assert_eq!(r.push(&tm[0], 0), Ok(None));
    let m = r.push(&tc[0], 0).unwrap().unwrap();
    assert_eq!(m.packet_type, PacketType::Telecommand);
    assert_eq!(m.payload, b"cmd");
    let m = r.push(&tm[1], 0).unwrap().unwrap();
    assert_eq!(m.packet_type, PacketType::Telemetry);
    assert_eq!(m.payload.len(), 2000);
}

#[test]
fn apid_filter_rejects_before_allocating_a_session() {
    let mut r: CcsdsReassembler<Vec<u8>, 1> =
        CcsdsReassembler::new(vec![0u8; 8192]).with_apid_filter(|a| a == 200);
    let foreign = packets(999, &payload(3000), 0, 1472);
    let wanted = packets(200, &payload(3000), 0, 1472);
    assert_eq!(r.push(&foreign[0], 0), Err(CcsdsRxError::NotSubscribed));
    let mut last = None;
    for p in &wanted {
        last = r.push(p, 0).unwrap().map(|m| m.payload.len());
    }
    assert_eq!(last, Some(3000));
    assert_eq!(r.counters().rejected_not_subscribed, 1);
}

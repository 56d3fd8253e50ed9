//! Round trips and robustness of the log formats: any valid record survives write then
//! read unchanged; arbitrary text or bytes never make a reader panic or over-allocate.

use fsw_component::logfmt::candump::{
    format_record, parse_line, CanId, CanLogFrame, CanLogReader, CanLogRecord, CanLogWriter,
    Direction, FrameData, MalformedLinePolicy,
};
use fsw_component::logfmt::udprec::{
    UdpRecord, UdpRecordingReader, UdpRecordingWriter, MAGIC, MAX_DATAGRAM_BYTES,
};
use proptest::prelude::*;

fn can_id() -> impl Strategy<Value = CanId> {
    prop_oneof![
        (0u16..=0x7FF).prop_map(CanId::Standard),
        (0u32..=0x1FFF_FFFF).prop_map(CanId::Extended),
    ]
}

fn bytes(max: usize) -> impl Strategy<Value = FrameData> {
    prop::collection::vec(any::<u8>(), 0..=max).prop_map(|v| FrameData::new(&v).unwrap())
}

fn frame() -> impl Strategy<Value = CanLogFrame> {
    prop_oneof![
        (can_id(), bytes(8)).prop_map(|(id, data)| CanLogFrame::Classic {
            id,
            data,
            len8_dlc: None
        }),
        (can_id(), prop::collection::vec(any::<u8>(), 8), 9u8..=15).prop_map(|(id, d, dlc)| {
            CanLogFrame::Classic {
                id,
                data: FrameData::new(&d).unwrap(),
                len8_dlc: Some(dlc),
            }
        }),
        (can_id(), 0u8..=8).prop_map(|(id, dlc)| CanLogFrame::Remote { id, dlc }),
        (can_id(), 0u8..=15, bytes(64)).prop_map(|(id, flags, data)| CanLogFrame::Fd {
            id,
            flags,
            data
        }),
        (0u32..=0x1FFF_FFFF, bytes(8)).prop_map(|(class, data)| CanLogFrame::Error { class, data }),
    ]
}

fn can_record() -> impl Strategy<Value = CanLogRecord> {
    (
        0u64..=u64::MAX / 2,
        "[a-z][a-z0-9_.-]{0,14}",
        frame(),
        prop_oneof![
            Just(None),
            Just(Some(Direction::Rx)),
            Just(Some(Direction::Tx))
        ],
    )
        .prop_map(|(timestamp_us, interface, frame, direction)| CanLogRecord {
            timestamp_us,
            interface,
            frame,
            direction,
        })
}

fn udp_record() -> impl Strategy<Value = UdpRecord> {
    (
        any::<u64>(),
        any::<u16>(),
        any::<u16>(),
        prop_oneof![
            prop::collection::vec(any::<u8>(), 0..64),
            prop::collection::vec(any::<u8>(), 1400..1473),
        ],
    )
        .prop_map(
            |(time_us, source_port, destination_port, payload)| UdpRecord {
                time_us,
                source_port,
                destination_port,
                payload,
            },
        )
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(300))]

    #[test]
    fn can_records_round_trip(records in prop::collection::vec(can_record(), 0..20)) {
        let mut writer = CanLogWriter::new(Vec::new());
        for r in &records {
            writer.write_record(r).unwrap();
        }
        let text = writer.into_inner();
        let back: Vec<CanLogRecord> = CanLogReader::new(&text[..], MalformedLinePolicy::Report)
            .map(|r| r.unwrap())
            .collect();
        prop_assert_eq!(&back, &records);
        for r in &records {
            let line = format_record(r).unwrap();
            let parsed = parse_line(&line, 1).unwrap();
            prop_assert_eq!(parsed.as_ref(), Some(r));
        }
    }

    #[test]
    fn arbitrary_text_never_panics(text in "\\PC{0,120}", mutated in "[0-9A-Fa-f#R.()_ rtvcan]{0,60}") {
        let _ = parse_line(&text, 1);
        let _ = parse_line(&mutated, 1);
        let _ = parse_line(&format!("(1.0) vcan0 {mutated}"), 1);
        let combined = format!("{text}\n{mutated}\n(1.0) vcan0 {mutated}\n");
        let mut reader = CanLogReader::new(combined.as_bytes(), MalformedLinePolicy::Skip);
        let parsed = reader.by_ref().count() as u64;
        prop_assert!(parsed + reader.skipped_lines() <= 3);
    }

    #[test]
    fn udp_records_round_trip(records in prop::collection::vec(udp_record(), 0..12)) {
        let mut writer = UdpRecordingWriter::new(Vec::new()).unwrap();
        for r in &records {
            writer.write_record(r).unwrap();
        }
        let bytes = writer.into_inner();
        let back: Vec<UdpRecord> = UdpRecordingReader::new(&bytes[..])
            .unwrap()
            .map(|r| r.unwrap())
            .collect();
        prop_assert_eq!(back, records);
    }

    #[test]
    fn arbitrary_bytes_never_panic_or_overallocate(tail in prop::collection::vec(any::<u8>(), 0..400)) {
        let mut bytes = MAGIC.to_vec();
        bytes.extend_from_slice(&tail);
        let reader = UdpRecordingReader::new(&bytes[..]).unwrap();
        let mut ok = 0usize;
        let mut errors = 0usize;
        for r in reader {
            match r {
                Ok(rec) => {
                    ok += 1;
                    prop_assert!(rec.payload.len() <= MAX_DATAGRAM_BYTES);
                }
                Err(_) => errors += 1,
            }
        }
        prop_assert!(errors <= 1);
        prop_assert!(ok * 16 <= tail.len());
    }
}

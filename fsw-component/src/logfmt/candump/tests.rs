//! Tests of `candump` (a child module, so they reach its private items).

use super::*;

fn parse(text: &str) -> CanLogRecord {
    parse_line(text, 1).unwrap().unwrap()
}

fn kind(text: &str) -> LineErrorKind {
    parse_line(text, 7).unwrap_err().kind
}

#[test]
fn parses_the_design_example() {
    let r = parse("(1700000000.000000) vcan0 1A2B3C4D#0011");
    assert_eq!(r.timestamp_us, 1_700_000_000_000_000);
    assert_eq!(r.interface, "vcan0");
    assert_eq!(r.direction, None);
    assert_eq!(
        r.frame,
        CanLogFrame::Classic {
            id: CanId::Extended(0x1A2B_3C4D),
            data: FrameData::new(&[0x00, 0x11]).unwrap(),
            len8_dlc: None
        }
    );
}

#[test]
fn parses_every_frame_kind() {
    let r = parse("(0.5) can0 123##5.11.22.33 T");
    assert_eq!(r.timestamp_us, 500_000);
    assert_eq!(r.direction, Some(Direction::Tx));
    assert_eq!(
        r.frame,
        CanLogFrame::Fd {
            id: CanId::Standard(0x123),
            flags: CANFD_BRS | CANFD_FDF,
            data: FrameData::new(&[0x11, 0x22, 0x33]).unwrap()
        }
    );
    assert_eq!(
        parse("(1.000001)   vcan1 7FF#R5").frame,
        CanLogFrame::Remote {
            id: CanId::Standard(0x7FF),
            dlc: 5
        }
    );
    assert_eq!(
        parse("(1.000001) vcan1 20000080#0000000000000000").frame,
        CanLogFrame::Error {
            class: 0x80,
            data: FrameData::new(&[0; 8]).unwrap()
        }
    );
    assert_eq!(
        parse("(1.0) vcan1 001#0102030405060708_C").frame,
        CanLogFrame::Classic {
            id: CanId::Standard(1),
            data: FrameData::new(&[1, 2, 3, 4, 5, 6, 7, 8]).unwrap(),
            len8_dlc: Some(0xC)
        }
    );
    // Empty classic and FD payloads.
    assert_eq!(
        parse("(1.0) vcan1 001#").frame,
        CanLogFrame::Classic {
            id: CanId::Standard(1),
            data: FrameData::EMPTY,
            len8_dlc: None
        }
    );
    assert!(matches!(
        parse("(1.0) vcan1 00000001##0").frame,
        CanLogFrame::Fd { flags: 0, data, .. } if data.is_empty()
    ));
}

#[test]
fn malformed_lines_name_the_problem() {
    use LineErrorKind as K;
    assert_eq!(kind("(1.0) vcan0"), K::WrongFieldCount { found: 2 });
    assert!(matches!(kind("1.0 vcan0 123#00"), K::BadTimestamp { .. }));
    assert!(matches!(
        kind("(1.1234567) vcan0 123#00"),
        K::BadTimestamp { .. }
    ));
    assert!(matches!(
        kind("(-1.0) vcan0 123#00"),
        K::BadTimestamp { .. }
    ));
    assert!(matches!(
        kind("(99999999999999999999.0) vcan0 123#00"),
        K::BadTimestamp { .. }
    ));
    assert!(matches!(kind("(1.0) vcan0 800#00"), K::BadCanId { .. }));
    assert!(matches!(kind("(1.0) vcan0 1234#00"), K::BadCanId { .. }));
    assert!(matches!(
        kind("(1.0) vcan0 7FFFFFFF#00"),
        K::BadCanId { .. }
    ));
    assert!(matches!(
        kind("(1.0) vcan0 40000000#00"),
        K::BadCanId { .. }
    ));
    assert!(matches!(
        kind("(1.0) vcan0 80000001#00"),
        K::BadCanId { .. }
    ));
    assert!(matches!(kind("(1.0) vcan0 12G#00"), K::BadCanId { .. }));
    assert_eq!(kind("(1.0) vcan0 123"), K::MissingSeparator);
    assert_eq!(kind("(1.0) vcan0 123#0G"), K::BadHex { position: 5 });
    assert_eq!(kind("(1.0) vcan0 123#001"), K::OddHexDigits);
    assert_eq!(
        kind("(1.0) vcan0 123#000102030405060708"),
        K::TooMuchData { bytes: 9, max: 8 }
    );
    assert_eq!(kind("(1.0) vcan0 123##"), K::BadFdFlags);
    assert_eq!(kind("(1.0) vcan0 123##X00"), K::BadFdFlags);
    assert_eq!(
        kind(&format!("(1.0) vcan0 123##0{}", "00".repeat(65))),
        K::TooMuchData { bytes: 65, max: 64 }
    );
    assert_eq!(kind("(1.0) vcan0 123#R9"), K::BadRemoteDlc);
    assert_eq!(kind("(1.0) vcan0 123#0011_9"), K::BadLen8Dlc);
    assert_eq!(kind("(1.0) vcan0 123#0011223344556677_8"), K::BadLen8Dlc);
    assert_eq!(kind("(1.0) vcan0 123###00"), K::CanXlUnsupported);
    assert!(matches!(
        kind("(1.0) vcan0 123#00 X"),
        K::BadDirection { .. }
    ));
    let e = parse_line("(1.0) vcan0 123#0G", 42).unwrap_err();
    assert!(e.to_string().starts_with("candump log line 42: non-hex"));
}

#[test]
fn format_round_trips_and_refuses_bad_records() {
    for line in [
        "(1700000000.000001) vcan0 1A2B3C4D#0011",
        "(1700000000.123456) can0 123##5112233 R",
        "(1700000000.999999) can0 123#R T",
        "(1700000000.500000) can0 7FF#R3",
        "(1700000000.500000) can0 20000080#0000000000000000",
        "(1700000000.500000) can0 001#0102030405060708_F",
        "(0000000012.500000) can0 001#",
    ] {
        assert_eq!(format_record(&parse(line)).unwrap(), line);
    }
    let mut record = parse("(1.0) vcan0 123#00");
    record.frame = CanLogFrame::Classic {
        id: CanId::Standard(0x800),
        data: FrameData::EMPTY,
        len8_dlc: None,
    };
    assert!(format_record(&record).is_err());
    record.frame = CanLogFrame::Classic {
        id: CanId::Standard(1),
        data: FrameData::new(&[0; 9]).unwrap(),
        len8_dlc: None,
    };
    assert!(format_record(&record).is_err());
    record.frame = CanLogFrame::Remote {
        id: CanId::Standard(1),
        dlc: 0,
    };
    record.interface = "vcan 0".into();
    assert!(format_record(&record).is_err());
}

#[test]
fn reader_reports_or_skips_with_line_numbers() {
    let text = b"(1.0) vcan0 123#00\n\nbroken\n(2.0) vcan0 124#01\r\n\xff\n";
    let mut reader = CanLogReader::new(&text[..], MalformedLinePolicy::Report);
    assert_eq!(reader.next().unwrap().unwrap().timestamp_us, 1_000_000);
    match reader.next().unwrap() {
        Err(ReadError::Line(e)) => {
            assert_eq!(e.line, 3);
            assert_eq!(e.kind, LineErrorKind::WrongFieldCount { found: 1 });
        }
        other => panic!("expected a line error, got {other:?}"),
    }
    let r = reader.next().unwrap().unwrap();
    assert_eq!((r.timestamp_us, r.interface.as_str()), (2_000_000, "vcan0"));
    assert!(reader.next().unwrap().is_err());
    assert!(reader.next().is_none());

    let bytes = b"(1.0) vcan0 123#00\nbad\n\xff\xfe\n(2.0) vcan0 124#01".to_vec();
    let mut skipping = CanLogReader::new(&bytes[..], MalformedLinePolicy::Skip);
    let ok: Vec<_> = skipping.by_ref().map(|r| r.unwrap().timestamp_us).collect();
    assert_eq!(ok, vec![1_000_000, 2_000_000]);
    assert_eq!(skipping.skipped_lines(), 2);
    assert_eq!(skipping.last_skipped().unwrap().line, 3);
    assert_eq!(
        skipping.last_skipped().unwrap().kind,
        LineErrorKind::NotUtf8
    );
}

#[test]
fn overlong_lines_are_bounded_and_reported() {
    let mut text = "(1.0) vcan0 123#".to_string();
    text.push_str(&"0".repeat(100_000));
    text.push_str("\n(2.0) vcan0 124#01\n");
    let mut reader = CanLogReader::new(text.as_bytes(), MalformedLinePolicy::Report);
    match reader.next().unwrap() {
        Err(ReadError::Line(LineError {
            line: 1,
            kind: LineErrorKind::TooLong { bytes },
        })) => assert_eq!(bytes, 100_016),
        other => panic!("expected TooLong, got {other:?}"),
    }
    assert_eq!(reader.next().unwrap().unwrap().timestamp_us, 2_000_000);
    assert!(reader.buffer.capacity() < 4 * MAX_LINE_BYTES);
}

#[test]
fn writer_writes_lines() {
    let mut writer = CanLogWriter::new(Vec::new());
    writer
        .write_record(&parse("(1700000000.000001) vcan0 1A2B3C4D#0011"))
        .unwrap();
    writer
        .write_record(&parse("(1700000000.000002) vcan0 123##1"))
        .unwrap();
    assert_eq!(writer.records_written(), 2);
    assert_eq!(
        String::from_utf8(writer.into_inner()).unwrap(),
        "(1700000000.000001) vcan0 1A2B3C4D#0011\n(1700000000.000002) vcan0 123##1\n"
    );
}

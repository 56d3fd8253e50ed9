//! Traffic-log harness: the candump reader, the UDP-recording reader and the replay loader
//! (`replay::load` on a real file) over arbitrary bytes; the first byte picks which.
//!
//! Asserted: no panic; the reader ends (at most one item per input line, nothing after a
//! recording error); the `Report` and `Skip` policies agree (same records, skipped lines =
//! reported line errors) and line numbers increase; every record read is written back by
//! the writer and reads back equal (candump line and UDP recording round trips); UDP
//! payloads stay within `MAX_DATAGRAM_BYTES`; the replay loader's records are time-ordered
//! and its counts match the records.

use fsw_component::logfmt::candump::{
    format_record, parse_line, CanLogReader, MalformedLinePolicy, ReadError,
};
use fsw_component::logfmt::udprec::{
    UdpRecordingReader, UdpRecordingWriter, MAGIC, MAX_DATAGRAM_BYTES,
};
use fsw_component::replay;
use std::io::Cursor;
use std::path::PathBuf;

pub fn run(input: &[u8]) {
    let Some((&selector, rest)) = input.split_first() else {
        return;
    };
    match selector % 3 {
        0 => candump(rest),
        1 => udp_recording(rest),
        _ => replay_file(rest),
    }
}

fn candump(bytes: &[u8]) {
    let lines = bytes.split(|&b| b == b'\n').count();
    let mut records = Vec::new();
    let mut line_errors = 0u64;
    let mut last_line = 0usize;
    let reader = CanLogReader::new(Cursor::new(bytes), MalformedLinePolicy::Report);
    for (items, item) in reader.enumerate() {
        assert!(items < lines, "more items than lines");
        match item {
            Ok(record) => {
                let line = format_record(&record)
                    .unwrap_or_else(|e| panic!("read record {record:?} not writable: {e}"));
                let again = parse_line(&line, 1)
                    .unwrap_or_else(|e| panic!("written line {line:?} not readable: {e}"));
                assert_eq!(again.as_ref(), Some(&record), "line {line:?}");
                records.push(record);
            }
            Err(ReadError::Line(e)) => {
                assert!(e.line > last_line, "line numbers go forward");
                last_line = e.line;
                line_errors += 1;
                // The message must be printable (used in replay errors).
                assert!(!e.to_string().is_empty());
            }
            Err(ReadError::Io { .. }) => panic!("a byte slice has no I/O errors"),
        }
    }
    let mut skipping = CanLogReader::new(Cursor::new(bytes), MalformedLinePolicy::Skip);
    let skipped: Vec<_> = skipping
        .by_ref()
        .map(|r| r.expect("Skip policy yields only records"))
        .collect();
    assert_eq!(skipped, records);
    assert_eq!(skipping.skipped_lines(), line_errors);
}

fn udp_recording(bytes: &[u8]) {
    let Ok(reader) = UdpRecordingReader::new(Cursor::new(bytes)) else {
        assert!(bytes.len() < MAGIC.len() || &bytes[..MAGIC.len()] != MAGIC);
        return;
    };
    let mut records = Vec::new();
    let mut failed = false;
    for item in reader {
        assert!(!failed, "an item after a recording error");
        match item {
            Ok(record) => {
                assert!(record.payload.len() <= MAX_DATAGRAM_BYTES);
                records.push(record);
            }
            Err(e) => {
                assert!(!e.to_string().is_empty());
                failed = true;
            }
        }
    }
    let mut writer = UdpRecordingWriter::new(Vec::new()).expect("writing to memory");
    for record in &records {
        writer
            .write_record(record)
            .expect("read records are writable");
    }
    let written = writer.into_inner();
    let again: Vec<_> = UdpRecordingReader::new(Cursor::new(&written))
        .expect("own magic")
        .map(|r| r.expect("own records read back"))
        .collect();
    assert_eq!(again, records);
    if !failed {
        assert_eq!(
            written, bytes,
            "a clean recording is written back byte for byte"
        );
    }
}

/// The replay loader reads real files: the input goes to a file of this process's own.
fn replay_file(bytes: &[u8]) {
    let path = scratch_file();
    std::fs::write(&path, bytes).expect("scratch file is writable");
    match replay::load(std::slice::from_ref(&path)) {
        Ok((records, stats)) => {
            assert_eq!(
                records.len() as u64,
                stats.datagrams + stats.can_frames,
                "{stats:?}"
            );
            assert!(records.windows(2).all(|w| w[0].time_us <= w[1].time_us));
        }
        Err(e) => assert!(!e.to_string().is_empty()),
    }
}

fn scratch_file() -> PathBuf {
    let dir = std::env::temp_dir().join(format!("fsw-fuzz-logs-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("scratch directory");
    dir.join("input.log")
}

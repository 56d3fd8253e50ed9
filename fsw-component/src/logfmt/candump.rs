//! candump `.log` lines (can-utils `candump -L`, python-can `CanutilsLogReader/Writer`).
//!
//! Line grammar (whitespace-separated fields, blank lines ignored):
//! `(<secs>.<frac>) <interface> <frame> [R|T]`
//! - `<secs>.<frac>`: decimal seconds, 1 to 6 fraction digits (kept as integer microseconds).
//! - `<frame>`, after can-utils `lib.c`:
//!   - `123#11223344`          classic, 3 hex digits = 11-bit ID, 0-8 data bytes
//!   - `12345678#1122`         classic, 8 hex digits = 29-bit ID
//!   - `123#1122334455667788_E` classic with 8 bytes and a raw DLC 9-15 (`len8_dlc`)
//!   - `123#R`, `123#R5`       remote request, optional DLC 0-8
//!   - `123##5112233`          CAN FD: one hex flags digit (BRS 1, ESI 2, FDF 4), 0-64 bytes
//!   - `20000080#0000000000000000` error frame (CAN_ERR_FLAG 0x20000000 in the 8-digit ID)
//!   - data bytes may be separated by `.` (accepted on input, never written)
//! - `R`/`T`: receive/transmit direction, written by python-can and `candump -x`.
//!
//! The writer produces exactly what python-can 4.6 writes for timestamps of 1e9 s or more
//! (candump's `%010` padding and python-can's `%f` agree there), upper-case hex.
//! CAN XL (`###`) is refused as unsupported.

use std::fmt::{self, Write as _};
use std::io::{self, BufRead, Write};

pub const CAN_ERR_FLAG: u32 = 0x2000_0000;
pub(crate) const CAN_SFF_MASK: u32 = 0x7FF;
pub(crate) const CAN_EFF_MASK: u32 = 0x1FFF_FFFF;
pub const CANFD_BRS: u8 = 0x01;
pub const CANFD_ESI: u8 = 0x02;
pub const CANFD_FDF: u8 = 0x04;
/// Longer lines are malformed (the longest valid CAN FD line is under 200 bytes).
pub(crate) const MAX_LINE_BYTES: usize = 1024;
/// Interface names longer than this are refused.
pub(crate) const MAX_INTERFACE_BYTES: usize = 64;

/// An arbitration ID.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum CanId {
    /// 11-bit, written with 3 hex digits.
    Standard(u16),
    /// 29-bit, written with 8 hex digits.
    Extended(u32),
}

impl CanId {
    pub fn raw(self) -> u32 {
        match self {
            Self::Standard(id) => u32::from(id),
            Self::Extended(id) => id,
        }
    }

    fn is_in_range(self) -> bool {
        match self {
            Self::Standard(id) => u32::from(id) <= CAN_SFF_MASK,
            Self::Extended(id) => id <= CAN_EFF_MASK,
        }
    }
}

/// Up to 64 payload bytes, stored inline.
#[derive(Clone, Copy, PartialEq, Eq)]
pub struct FrameData {
    len: u8,
    bytes: [u8; 64],
}

impl FrameData {
    pub const EMPTY: Self = Self {
        len: 0,
        bytes: [0; 64],
    };

    /// `None` when longer than 64 bytes.
    pub fn new(data: &[u8]) -> Option<Self> {
        if data.len() > 64 {
            return None;
        }
        let mut bytes = [0; 64];
        bytes[..data.len()].copy_from_slice(data);
        Some(Self {
            len: data.len() as u8,
            bytes,
        })
    }

    pub fn as_slice(&self) -> &[u8] {
        &self.bytes[..usize::from(self.len)]
    }

    pub fn len(&self) -> usize {
        usize::from(self.len)
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    fn push(&mut self, byte: u8) -> bool {
        if self.len == 64 {
            return false;
        }
        self.bytes[usize::from(self.len)] = byte;
        self.len += 1;
        true
    }
}

impl fmt::Debug for FrameData {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "FrameData({:02X?})", self.as_slice())
    }
}

/// The frame part of a log line.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CanLogFrame {
    /// Classic data frame, 0-8 bytes; `len8_dlc` (9-15) only with 8 bytes.
    Classic {
        id: CanId,
        data: FrameData,
        len8_dlc: Option<u8>,
    },
    /// Remote transmission request with its DLC (0-8).
    Remote { id: CanId, dlc: u8 },
    /// CAN FD frame: flags nibble (BRS, ESI, FDF) and 0-64 bytes.
    Fd {
        id: CanId,
        flags: u8,
        data: FrameData,
    },
    /// Error frame: error class bits (without CAN_ERR_FLAG) and 0-8 bytes of detail.
    Error { class: u32, data: FrameData },
}

/// Direction suffix written by python-can and `candump -x`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Direction {
    Rx,
    Tx,
}

/// One log line.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct CanLogRecord {
    pub timestamp_us: u64,
    pub interface: String,
    pub frame: CanLogFrame,
    pub direction: Option<Direction>,
}

/// What is wrong with a line.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum LineErrorKind {
    WrongFieldCount {
        found: usize,
    },
    BadTimestamp {
        field: String,
    },
    BadInterface {
        field: String,
    },
    BadDirection {
        field: String,
    },
    /// The ID is not 3 or 8 hex digits, or out of range, or has flag bits other than ERR.
    BadCanId {
        field: String,
    },
    MissingSeparator,
    BadHex {
        position: usize,
    },
    OddHexDigits,
    TooMuchData {
        bytes: usize,
        max: usize,
    },
    BadFdFlags,
    BadRemoteDlc,
    BadLen8Dlc,
    CanXlUnsupported,
    NotUtf8,
    TooLong {
        bytes: usize,
    },
    /// A record the writer refuses (e.g. an out-of-range ID), not a parse error.
    InvalidRecord {
        what: &'static str,
    },
}

/// A malformed line, with its 1-based line number (0 when formatting a record).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct LineError {
    pub line: usize,
    pub kind: LineErrorKind,
}

impl fmt::Display for LineError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "candump log line {}: ", self.line)?;
        match &self.kind {
            LineErrorKind::WrongFieldCount { found } => write!(
                f,
                "expected `(time) interface frame [R|T]`, found {found} fields"
            ),
            LineErrorKind::BadTimestamp { field } => write!(
                f,
                "bad timestamp {field:?}: expected (seconds.fraction) with 1-6 fraction digits"
            ),
            LineErrorKind::BadInterface { field } => write!(f, "bad interface name {field:?}"),
            LineErrorKind::BadDirection { field } => {
                write!(f, "bad direction {field:?}: expected R or T")
            }
            LineErrorKind::BadCanId { field } => write!(
                f,
                "bad CAN ID {field:?}: expected 3 hex digits (<= 7FF) or 8 (<= 1FFFFFFF, or an error frame)"
            ),
            LineErrorKind::MissingSeparator => write!(f, "frame has no '#' after the CAN ID"),
            LineErrorKind::BadHex { position } => {
                write!(f, "non-hex character at frame position {position}")
            }
            LineErrorKind::OddHexDigits => write!(f, "odd number of hex digits in the data"),
            LineErrorKind::TooMuchData { bytes, max } => {
                write!(f, "{bytes} data bytes, at most {max} allowed for this frame type")
            }
            LineErrorKind::BadFdFlags => write!(f, "CAN FD frame needs one hex flags digit after '##'"),
            LineErrorKind::BadRemoteDlc => write!(f, "remote frame DLC must be one digit 0-8"),
            LineErrorKind::BadLen8Dlc => {
                write!(f, "'_' DLC suffix needs exactly 8 data bytes and one hex digit 9-F")
            }
            LineErrorKind::CanXlUnsupported => write!(f, "CAN XL frames ('###') are not supported"),
            LineErrorKind::NotUtf8 => write!(f, "line is not valid UTF-8"),
            LineErrorKind::TooLong { bytes } => {
                write!(f, "line longer than {MAX_LINE_BYTES} bytes ({bytes} read)")
            }
            LineErrorKind::InvalidRecord { what } => write!(f, "record cannot be written: {what}"),
        }
    }
}

impl std::error::Error for LineError {}

/// Parses one line; `Ok(None)` for a blank line. `line` numbers the error.
pub fn parse_line(text: &str, line: usize) -> Result<Option<CanLogRecord>, LineError> {
    let err = |kind| LineError { line, kind };
    let fields: Vec<&str> = text.split_whitespace().collect();
    if fields.is_empty() {
        return Ok(None);
    }
    if fields.len() != 3 && fields.len() != 4 {
        return Err(err(LineErrorKind::WrongFieldCount {
            found: fields.len(),
        }));
    }
    let timestamp_us = parse_timestamp(fields[0]).ok_or_else(|| {
        err(LineErrorKind::BadTimestamp {
            field: clip(fields[0]),
        })
    })?;
    let interface = fields[1];
    if interface.len() > MAX_INTERFACE_BYTES || interface.starts_with('(') {
        return Err(err(LineErrorKind::BadInterface {
            field: clip(interface),
        }));
    }
    let direction = match fields.get(3) {
        None => None,
        Some(&"R" | &"r") => Some(Direction::Rx),
        Some(&"T" | &"t") => Some(Direction::Tx),
        Some(other) => return Err(err(LineErrorKind::BadDirection { field: clip(other) })),
    };
    let frame = parse_frame(fields[2]).map_err(err)?;
    Ok(Some(CanLogRecord {
        timestamp_us,
        interface: interface.to_string(),
        frame,
        direction,
    }))
}

fn clip(field: &str) -> String {
    field.chars().take(40).collect()
}

fn parse_timestamp(field: &str) -> Option<u64> {
    let inner = field.strip_prefix('(')?.strip_suffix(')')?;
    let (secs, frac) = inner.split_once('.')?;
    let all_digits = |s: &str| !s.is_empty() && s.bytes().all(|b| b.is_ascii_digit());
    if !all_digits(secs) || !all_digits(frac) || frac.len() > 6 {
        return None;
    }
    let secs: u64 = secs.parse().ok()?;
    let micros: u64 = frac.parse::<u64>().ok()? * 10u64.pow(6 - frac.len() as u32);
    secs.checked_mul(1_000_000)?.checked_add(micros)
}

fn hex_value(byte: u8) -> Option<u8> {
    match byte {
        b'0'..=b'9' => Some(byte - b'0'),
        b'A'..=b'F' => Some(byte - b'A' + 10),
        b'a'..=b'f' => Some(byte - b'a' + 10),
        _ => None,
    }
}

/// Hex bytes with optional '.' separators; `offset` positions errors within the frame field.
fn parse_data(text: &[u8], offset: usize, max: usize) -> Result<FrameData, LineErrorKind> {
    let mut data = FrameData::EMPTY;
    let mut count = 0usize;
    let mut i = 0;
    while i < text.len() {
        if text[i] == b'.' {
            i += 1;
            continue;
        }
        let high = hex_value(text[i]).ok_or(LineErrorKind::BadHex {
            position: offset + i,
        })?;
        let low_byte = *text.get(i + 1).ok_or(LineErrorKind::OddHexDigits)?;
        if low_byte == b'.' {
            return Err(LineErrorKind::OddHexDigits);
        }
        let low = hex_value(low_byte).ok_or(LineErrorKind::BadHex {
            position: offset + i + 1,
        })?;
        count += 1;
        if count > max || !data.push(high << 4 | low) {
            // Keep counting so the message says how much data there was.
            let total = count + text[i + 2..].iter().filter(|b| **b != b'.').count() / 2;
            return Err(LineErrorKind::TooMuchData { bytes: total, max });
        }
        i += 2;
    }
    Ok(data)
}

fn parse_frame(field: &str) -> Result<CanLogFrame, LineErrorKind> {
    let bad_id = || LineErrorKind::BadCanId {
        field: clip(field.split('#').next().unwrap_or(field)),
    };
    let (id_text, rest) = field
        .split_once('#')
        .ok_or(LineErrorKind::MissingSeparator)?;
    let id_offset = id_text.len() + 1;
    let id_value = if id_text.bytes().all(|b| hex_value(b).is_some()) {
        u32::from_str_radix(id_text, 16).map_err(|_| bad_id())?
    } else {
        return Err(bad_id());
    };
    let rest = rest.as_bytes();
    if rest.starts_with(b"##") {
        return Err(LineErrorKind::CanXlUnsupported);
    }
    // 8-digit IDs with CAN_ERR_FLAG are error frames.
    let id = match id_text.len() {
        3 => CanId::Standard(id_value as u16),
        8 if id_value & CAN_ERR_FLAG != 0 => {
            if id_value & !(CAN_EFF_MASK | CAN_ERR_FLAG) != 0 {
                return Err(bad_id());
            }
            let data = parse_data(rest, id_offset, 8)?;
            return Ok(CanLogFrame::Error {
                class: id_value & CAN_EFF_MASK,
                data,
            });
        }
        8 => CanId::Extended(id_value),
        _ => return Err(bad_id()),
    };
    if !id.is_in_range() {
        return Err(bad_id());
    }
    match rest.first() {
        Some(b'#') => {
            let flags = rest
                .get(1)
                .and_then(|b| hex_value(*b))
                .ok_or(LineErrorKind::BadFdFlags)?;
            let data = parse_data(&rest[2..], id_offset + 2, 64)?;
            Ok(CanLogFrame::Fd { id, flags, data })
        }
        Some(b'R' | b'r') => {
            let dlc = match &rest[1..] {
                [] => 0,
                [digit] if (b'0'..=b'8').contains(digit) => digit - b'0',
                _ => return Err(LineErrorKind::BadRemoteDlc),
            };
            Ok(CanLogFrame::Remote { id, dlc })
        }
        _ => {
            let (data_text, len8_dlc) = match rest.iter().position(|b| *b == b'_') {
                None => (rest, None),
                Some(at) => {
                    let dlc = match &rest[at + 1..] {
                        [digit] => hex_value(*digit).filter(|d| *d >= 9),
                        _ => None,
                    }
                    .ok_or(LineErrorKind::BadLen8Dlc)?;
                    (&rest[..at], Some(dlc))
                }
            };
            let data = parse_data(data_text, id_offset, 8)?;
            if len8_dlc.is_some() && data.len() != 8 {
                return Err(LineErrorKind::BadLen8Dlc);
            }
            Ok(CanLogFrame::Classic { id, data, len8_dlc })
        }
    }
}

fn push_hex(out: &mut String, data: &FrameData) {
    for byte in data.as_slice() {
        let _ = write!(out, "{byte:02X}");
    }
}

fn push_id(out: &mut String, id: CanId) {
    let _ = match id {
        CanId::Standard(raw) => write!(out, "{raw:03X}"),
        CanId::Extended(raw) => write!(out, "{raw:08X}"),
    };
}

/// Formats a record as one line (without the newline), refusing records that do not fit
/// the format.
pub fn format_record(record: &CanLogRecord) -> Result<String, LineError> {
    let invalid = |what| LineError {
        line: 0,
        kind: LineErrorKind::InvalidRecord { what },
    };
    let name = &record.interface;
    if name.is_empty()
        || name.len() > MAX_INTERFACE_BYTES
        || name.starts_with('(')
        || name.chars().any(char::is_whitespace)
    {
        return Err(invalid(
            "interface name must be 1-64 characters without whitespace",
        ));
    }
    let mut out = String::with_capacity(64 + 2 * 64);
    let _ = write!(
        out,
        "({:010}.{:06}) {} ",
        record.timestamp_us / 1_000_000,
        record.timestamp_us % 1_000_000,
        name
    );
    match &record.frame {
        CanLogFrame::Classic { id, data, len8_dlc } => {
            if !id.is_in_range() || data.len() > 8 {
                return Err(invalid(
                    "classic frame with an out-of-range ID or over 8 bytes",
                ));
            }
            push_id(&mut out, *id);
            out.push('#');
            push_hex(&mut out, data);
            if let Some(dlc) = len8_dlc {
                if data.len() != 8 || !(9..=15).contains(dlc) {
                    return Err(invalid("len8_dlc needs 8 bytes and a DLC of 9-15"));
                }
                let _ = write!(out, "_{dlc:X}");
            }
        }
        CanLogFrame::Remote { id, dlc } => {
            if !id.is_in_range() || *dlc > 8 {
                return Err(invalid(
                    "remote frame with an out-of-range ID or DLC over 8",
                ));
            }
            push_id(&mut out, *id);
            out.push_str("#R");
            if *dlc > 0 {
                let _ = write!(out, "{dlc}");
            }
        }
        CanLogFrame::Fd { id, flags, data } => {
            if !id.is_in_range() || *flags > 0xF {
                return Err(invalid(
                    "CAN FD frame with an out-of-range ID or flags over 0xF",
                ));
            }
            push_id(&mut out, *id);
            let _ = write!(out, "##{flags:X}");
            push_hex(&mut out, data);
        }
        CanLogFrame::Error { class, data } => {
            if *class > CAN_EFF_MASK || data.len() > 8 {
                return Err(invalid("error frame class over 29 bits or over 8 bytes"));
            }
            let _ = write!(out, "{:08X}#", class | CAN_ERR_FLAG);
            push_hex(&mut out, data);
        }
    }
    match record.direction {
        None => {}
        Some(Direction::Rx) => out.push_str(" R"),
        Some(Direction::Tx) => out.push_str(" T"),
    }
    Ok(out)
}

/// What a reader does with a malformed line.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MalformedLinePolicy {
    /// Yield the error (the reader continues with the next line if polled again).
    Report,
    /// Count it in [`CanLogReader::skipped_lines`], remember it, and go on.
    Skip,
}

/// Reads records line by line.
pub struct CanLogReader<R> {
    reader: R,
    policy: MalformedLinePolicy,
    line: usize,
    skipped_lines: u64,
    last_skipped: Option<LineError>,
    buffer: Vec<u8>,
    failed_io: bool,
}

/// A reader failure: a malformed line or an I/O error.
#[derive(Debug)]
pub enum ReadError {
    Line(LineError),
    Io { line: usize, error: io::Error },
}

impl fmt::Display for ReadError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Line(e) => e.fmt(f),
            Self::Io { line, error } => {
                write!(f, "candump log: I/O error after line {line}: {error}")
            }
        }
    }
}

impl std::error::Error for ReadError {}

impl<R: BufRead> CanLogReader<R> {
    pub fn new(reader: R, policy: MalformedLinePolicy) -> Self {
        Self {
            reader,
            policy,
            line: 0,
            skipped_lines: 0,
            last_skipped: None,
            buffer: Vec::with_capacity(256),
            failed_io: false,
        }
    }

    pub fn skipped_lines(&self) -> u64 {
        self.skipped_lines
    }

    pub fn last_skipped(&self) -> Option<&LineError> {
        self.last_skipped.as_ref()
    }

    /// Reads one line into `self.buffer`, keeping at most MAX_LINE_BYTES + 1 bytes of it.
    /// Returns the full length read (newline excluded), or None at end of input.
    fn read_bounded_line(&mut self) -> io::Result<Option<usize>> {
        self.buffer.clear();
        let mut total = 0usize;
        let mut saw_any = false;
        loop {
            let available = match self.reader.fill_buf() {
                Ok(bytes) => bytes,
                Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
                Err(e) => return Err(e),
            };
            if available.is_empty() {
                return Ok(saw_any.then_some(total));
            }
            saw_any = true;
            let (chunk, consumed, done) = match available.iter().position(|b| *b == b'\n') {
                Some(at) => (&available[..at], at + 1, true),
                None => (available, available.len(), false),
            };
            let room = (MAX_LINE_BYTES + 1).saturating_sub(self.buffer.len());
            self.buffer
                .extend_from_slice(&chunk[..chunk.len().min(room)]);
            total += chunk.len();
            self.reader.consume(consumed);
            if done {
                return Ok(Some(total));
            }
        }
    }
}

impl<R: BufRead> Iterator for CanLogReader<R> {
    type Item = Result<CanLogRecord, ReadError>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.failed_io {
            return None;
        }
        loop {
            let total = match self.read_bounded_line() {
                Ok(None) => return None,
                Ok(Some(total)) => total,
                Err(error) => {
                    self.failed_io = true;
                    return Some(Err(ReadError::Io {
                        line: self.line,
                        error,
                    }));
                }
            };
            self.line += 1;
            let parsed = if total > MAX_LINE_BYTES {
                Err(LineError {
                    line: self.line,
                    kind: LineErrorKind::TooLong { bytes: total },
                })
            } else {
                match std::str::from_utf8(&self.buffer) {
                    Ok(text) => parse_line(text, self.line),
                    Err(_) => Err(LineError {
                        line: self.line,
                        kind: LineErrorKind::NotUtf8,
                    }),
                }
            };
            match parsed {
                Ok(Some(record)) => return Some(Ok(record)),
                Ok(None) => continue,
                Err(e) => match self.policy {
                    MalformedLinePolicy::Report => return Some(Err(ReadError::Line(e))),
                    MalformedLinePolicy::Skip => {
                        self.skipped_lines += 1;
                        self.last_skipped = Some(e);
                    }
                },
            }
        }
    }
}

/// Writes records, one line each.
pub struct CanLogWriter<W> {
    writer: W,
    records: u64,
}

/// A writer failure.
#[derive(Debug)]
pub enum WriteError {
    Record(LineError),
    Io(io::Error),
}

impl fmt::Display for WriteError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Record(e) => e.fmt(f),
            Self::Io(e) => write!(f, "candump log: write failed: {e}"),
        }
    }
}

impl std::error::Error for WriteError {}

impl<W: Write> CanLogWriter<W> {
    pub fn new(writer: W) -> Self {
        Self { writer, records: 0 }
    }

    pub fn write_record(&mut self, record: &CanLogRecord) -> Result<(), WriteError> {
        let mut line = format_record(record).map_err(WriteError::Record)?;
        line.push('\n');
        self.writer
            .write_all(line.as_bytes())
            .map_err(WriteError::Io)?;
        self.records += 1;
        Ok(())
    }

    pub fn records_written(&self) -> u64 {
        self.records
    }

    pub fn flush(&mut self) -> io::Result<()> {
        self.writer.flush()
    }

    pub fn into_inner(self) -> W {
        self.writer
    }
}

#[cfg(test)]
mod tests;

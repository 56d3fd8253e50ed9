//! UDP datagram recording: a small binary format that replays through the same decoders.
//!
//! Layout (all integers little-endian):
//! ```text
//! file   := magic record*
//! magic  := "FSWUDPR1"                      8 bytes; the trailing digit is the version
//! record := time_us:u64 src_port:u16 dst_port:u16 len:u32 payload[len]
//! ```
//! `time_us` is the receive (or send) time in microseconds; `len` is at most
//! [`MAX_DATAGRAM_BYTES`] (the largest UDP payload over IPv4). The file ends cleanly
//! after a complete record; anything else is a truncated record.
//!
//! Invariants: the reader allocates at most `MAX_DATAGRAM_BYTES` per record whatever the
//! input claims, reports the byte offset of any problem, and stops after the first one
//! (a binary stream cannot be resynchronised). The writer refuses oversized datagrams.

use std::fmt;
use std::io::{self, Read, Write};

pub const MAGIC: &[u8; 8] = b"FSWUDPR1";
/// 65535 - 8 (UDP header) - 20 (IPv4 header).
pub const MAX_DATAGRAM_BYTES: usize = 65_507;
pub(crate) const RECORD_HEADER_BYTES: usize = 16;

/// One recorded datagram.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct UdpRecord {
    pub time_us: u64,
    pub source_port: u16,
    pub destination_port: u16,
    pub payload: Vec<u8>,
}

/// Recording failures, with the byte offset where they were found.
#[derive(Debug)]
pub enum UdpRecordingError {
    BadMagic {
        found: [u8; 8],
    },
    /// The input ended inside a record's header or payload.
    Truncated {
        record: u64,
        offset: u64,
        needed: usize,
        got: usize,
    },
    Oversized {
        record: u64,
        offset: u64,
        len: u64,
    },
    Io {
        offset: u64,
        error: io::Error,
    },
}

impl fmt::Display for UdpRecordingError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::BadMagic { found } => write!(
                f,
                "not a UDP recording: expected magic {:?}, found {:?}",
                String::from_utf8_lossy(MAGIC),
                String::from_utf8_lossy(found)
            ),
            Self::Truncated {
                record,
                offset,
                needed,
                got,
            } => write!(
                f,
                "UDP recording truncated in record {record} at byte {offset}: needed {needed} bytes, got {got}"
            ),
            Self::Oversized {
                record,
                offset,
                len,
            } => write!(
                f,
                "UDP recording record {record} at byte {offset} claims {len} bytes, more than {MAX_DATAGRAM_BYTES}"
            ),
            Self::Io { offset, error } => {
                write!(f, "UDP recording I/O error at byte {offset}: {error}")
            }
        }
    }
}

impl std::error::Error for UdpRecordingError {}

/// Reads as many bytes as available up to `buf.len()`; returns the count (short only at EOF).
fn read_full<R: Read>(reader: &mut R, buf: &mut [u8]) -> io::Result<usize> {
    let mut filled = 0;
    while filled < buf.len() {
        match reader.read(&mut buf[filled..]) {
            Ok(0) => break,
            Ok(n) => filled += n,
            Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(filled)
}

/// Iterates over the records of a recording.
pub struct UdpRecordingReader<R> {
    reader: R,
    offset: u64,
    records: u64,
    done: bool,
}

impl<R: Read> UdpRecordingReader<R> {
    /// Checks the magic.
    pub fn new(mut reader: R) -> Result<Self, UdpRecordingError> {
        let mut magic = [0u8; 8];
        let got = read_full(&mut reader, &mut magic)
            .map_err(|error| UdpRecordingError::Io { offset: 0, error })?;
        if got < magic.len() || &magic != MAGIC {
            return Err(UdpRecordingError::BadMagic { found: magic });
        }
        Ok(Self {
            reader,
            offset: MAGIC.len() as u64,
            records: 0,
            done: false,
        })
    }

    /// Records read so far.
    pub fn records_read(&self) -> u64 {
        self.records
    }

    fn read_record(&mut self) -> Result<Option<UdpRecord>, UdpRecordingError> {
        let record_offset = self.offset;
        let io_error = |error| UdpRecordingError::Io {
            offset: record_offset,
            error,
        };
        let mut header = [0u8; RECORD_HEADER_BYTES];
        let got = read_full(&mut self.reader, &mut header).map_err(io_error)?;
        if got == 0 {
            return Ok(None);
        }
        if got < header.len() {
            return Err(UdpRecordingError::Truncated {
                record: self.records,
                offset: record_offset,
                needed: header.len(),
                got,
            });
        }
        let time_us = u64::from_le_bytes(header[0..8].try_into().unwrap_or_default());
        let source_port = u16::from_le_bytes([header[8], header[9]]);
        let destination_port = u16::from_le_bytes([header[10], header[11]]);
        let len = u32::from_le_bytes([header[12], header[13], header[14], header[15]]) as usize;
        if len > MAX_DATAGRAM_BYTES {
            return Err(UdpRecordingError::Oversized {
                record: self.records,
                offset: record_offset,
                len: len as u64,
            });
        }
        let mut payload = vec![0u8; len];
        let got = read_full(&mut self.reader, &mut payload).map_err(io_error)?;
        if got < len {
            return Err(UdpRecordingError::Truncated {
                record: self.records,
                offset: record_offset,
                needed: RECORD_HEADER_BYTES + len,
                got: RECORD_HEADER_BYTES + got,
            });
        }
        self.offset += (RECORD_HEADER_BYTES + len) as u64;
        self.records += 1;
        Ok(Some(UdpRecord {
            time_us,
            source_port,
            destination_port,
            payload,
        }))
    }
}

impl<R: Read> Iterator for UdpRecordingReader<R> {
    type Item = Result<UdpRecord, UdpRecordingError>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.done {
            return None;
        }
        let result = self.read_record();
        if !matches!(result, Ok(Some(_))) {
            self.done = true;
        }
        result.transpose()
    }
}

/// Writes a recording: the magic on creation, then one record per datagram.
pub struct UdpRecordingWriter<W: Write> {
    writer: W,
    records: u64,
}

/// A refused or failed write.
#[derive(Debug)]
pub enum UdpWriteError {
    Oversized { len: usize },
    Io(io::Error),
}

impl fmt::Display for UdpWriteError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Oversized { len } => write!(
                f,
                "datagram of {len} bytes exceeds the {MAX_DATAGRAM_BYTES}-byte UDP maximum"
            ),
            Self::Io(e) => write!(f, "UDP recording write failed: {e}"),
        }
    }
}

impl std::error::Error for UdpWriteError {}

impl<W: Write> UdpRecordingWriter<W> {
    pub fn new(mut writer: W) -> io::Result<Self> {
        writer.write_all(MAGIC)?;
        Ok(Self { writer, records: 0 })
    }

    pub fn write_record(&mut self, record: &UdpRecord) -> Result<(), UdpWriteError> {
        let len = record.payload.len();
        if len > MAX_DATAGRAM_BYTES {
            return Err(UdpWriteError::Oversized { len });
        }
        let mut header = [0u8; RECORD_HEADER_BYTES];
        header[0..8].copy_from_slice(&record.time_us.to_le_bytes());
        header[8..10].copy_from_slice(&record.source_port.to_le_bytes());
        header[10..12].copy_from_slice(&record.destination_port.to_le_bytes());
        header[12..16].copy_from_slice(&(len as u32).to_le_bytes());
        self.writer
            .write_all(&header)
            .and_then(|()| self.writer.write_all(&record.payload))
            .map_err(UdpWriteError::Io)?;
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
mod tests {
    use super::*;

    fn record(time_us: u64, payload: &[u8]) -> UdpRecord {
        UdpRecord {
            time_us,
            source_port: 40_000,
            destination_port: 5_005,
            payload: payload.to_vec(),
        }
    }

    #[test]
    fn layout_is_as_documented() {
        let mut w = UdpRecordingWriter::new(Vec::new()).unwrap();
        w.write_record(&record(0x0102_0304_0506_0708, &[0xAA, 0xBB]))
            .unwrap();
        let bytes = w.into_inner();
        let mut expected = b"FSWUDPR1".to_vec();
        expected.extend_from_slice(&[8, 7, 6, 5, 4, 3, 2, 1]);
        expected.extend_from_slice(&40_000u16.to_le_bytes());
        expected.extend_from_slice(&5_005u16.to_le_bytes());
        expected.extend_from_slice(&[2, 0, 0, 0, 0xAA, 0xBB]);
        assert_eq!(bytes, expected);
    }

    #[test]
    fn errors_carry_positions_and_stop_the_reader() {
        assert!(matches!(
            UdpRecordingReader::new(&b"FSWUDPR2"[..]),
            Err(UdpRecordingError::BadMagic { .. })
        ));
        assert!(matches!(
            UdpRecordingReader::new(&b"FSW"[..]),
            Err(UdpRecordingError::BadMagic { .. })
        ));
        let mut w = UdpRecordingWriter::new(Vec::new()).unwrap();
        w.write_record(&record(1, &[1, 2, 3])).unwrap();
        w.write_record(&record(2, &[4, 5, 6])).unwrap();
        let bytes = w.into_inner();
        // Cut in the second record's payload.
        let cut = &bytes[..bytes.len() - 1];
        let mut r = UdpRecordingReader::new(cut).unwrap();
        assert_eq!(r.next().unwrap().unwrap().payload, vec![1, 2, 3]);
        match r.next().unwrap() {
            Err(UdpRecordingError::Truncated {
                record: 1,
                offset: 27,
                needed: 19,
                got: 18,
            }) => {}
            other => panic!("expected truncation, got {other:?}"),
        }
        assert!(r.next().is_none());
        // A huge claimed length is refused before allocating.
        let mut huge = b"FSWUDPR1".to_vec();
        huge.extend_from_slice(&[0; 12]);
        huge.extend_from_slice(&u32::MAX.to_le_bytes());
        let mut r = UdpRecordingReader::new(&huge[..]).unwrap();
        assert!(matches!(
            r.next(),
            Some(Err(UdpRecordingError::Oversized {
                len: 4_294_967_295,
                ..
            }))
        ));
        let mut w = UdpRecordingWriter::new(Vec::new()).unwrap();
        assert!(matches!(
            w.write_record(&record(0, &vec![0; MAX_DATAGRAM_BYTES + 1])),
            Err(UdpWriteError::Oversized { .. })
        ));
        assert_eq!(w.records_written(), 0);
    }
}

//! Replay input: candump `.log` files and UDP recordings merged into one time-ordered stream.
//!
//! A file starting with the `FSWUDPR1` magic is a UDP recording, anything else is read as a
//! candump log. Records are merged by time stamp; equal times keep file order, then record
//! order (a stable sort), so a replay is deterministic. Malformed candump lines are skipped
//! and counted; a damaged UDP recording stops at the damage with an error naming the offset.

use crate::logfmt::candump::{CanLogFrame, CanLogReader, MalformedLinePolicy};
use crate::logfmt::udprec::{UdpRecordingReader, MAGIC};
use std::fmt;
use std::fs::File;
use std::io::{BufReader, Read};
use std::path::{Path, PathBuf};

/// One input event of a replay.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum ReplayInput {
    Datagram(Vec<u8>),
    CanFrame {
        extended: bool,
        id: u32,
        data: Vec<u8>,
    },
}

#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ReplayRecord {
    pub time_us: u64,
    pub input: ReplayInput,
}

/// What was read.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ReplayLoadStats {
    pub datagrams: u64,
    pub can_frames: u64,
    /// Remote and error frames in candump logs (not bus data).
    pub can_non_data_frames: u64,
    pub skipped_lines: u64,
}

#[derive(Debug)]
pub enum ReplayError {
    Open {
        path: PathBuf,
        source: std::io::Error,
    },
    Udp {
        path: PathBuf,
        detail: String,
    },
    Can {
        path: PathBuf,
        detail: String,
    },
}

impl fmt::Display for ReplayError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Open { path, source } => write!(f, "cannot open {}: {source}", path.display()),
            Self::Udp { path, detail } => {
                write!(f, "UDP recording {}: {detail}", path.display())
            }
            Self::Can { path, detail } => write!(f, "candump log {}: {detail}", path.display()),
        }
    }
}

impl std::error::Error for ReplayError {}

fn is_udp_recording(path: &Path) -> Result<bool, ReplayError> {
    let open = |source| ReplayError::Open {
        path: path.to_path_buf(),
        source,
    };
    let mut head = [0u8; 8];
    let mut file = File::open(path).map_err(open)?;
    let mut got = 0;
    while got < head.len() {
        match file.read(&mut head[got..]).map_err(open)? {
            0 => break,
            n => got += n,
        }
    }
    Ok(got == head.len() && &head == MAGIC)
}

/// Reads and merges every log.
pub fn load(paths: &[PathBuf]) -> Result<(Vec<ReplayRecord>, ReplayLoadStats), ReplayError> {
    let mut records = Vec::new();
    let mut stats = ReplayLoadStats::default();
    for path in paths {
        let open = |source| ReplayError::Open {
            path: path.clone(),
            source,
        };
        let reader = BufReader::new(File::open(path).map_err(open)?);
        if is_udp_recording(path)? {
            let udp = UdpRecordingReader::new(reader).map_err(|e| ReplayError::Udp {
                path: path.clone(),
                detail: e.to_string(),
            })?;
            for record in udp {
                let record = record.map_err(|e| ReplayError::Udp {
                    path: path.clone(),
                    detail: e.to_string(),
                })?;
                stats.datagrams += 1;
                records.push(ReplayRecord {
                    time_us: record.time_us,
                    input: ReplayInput::Datagram(record.payload),
                });
            }
        } else {
            let mut can = CanLogReader::new(reader, MalformedLinePolicy::Skip);
            for record in can.by_ref() {
                let record = record.map_err(|e| ReplayError::Can {
                    path: path.clone(),
                    detail: e.to_string(),
                })?;
                let (id, data) = match record.frame {
                    CanLogFrame::Classic { id, data, .. } | CanLogFrame::Fd { id, data, .. } => {
                        (id, data)
                    }
                    CanLogFrame::Remote { .. } | CanLogFrame::Error { .. } => {
                        stats.can_non_data_frames += 1;
                        continue;
                    }
                };
                stats.can_frames += 1;
                records.push(ReplayRecord {
                    time_us: record.timestamp_us,
                    input: ReplayInput::CanFrame {
                        extended: matches!(id, crate::logfmt::candump::CanId::Extended(_)),
                        id: id.raw(),
                        data: data.as_slice().to_vec(),
                    },
                });
            }
            stats.skipped_lines += can.skipped_lines();
        }
    }
    records.sort_by_key(|r| r.time_us);
    Ok((records, stats))
}

//! Recorder of the component's bus input, in the formats replay reads back.
//!
//! `DIR/udp.rec`: every received UDP datagram (the `FSWUDPR1` recording of `logfmt::udprec`);
//! `DIR/can.log`: every received CAN frame as a candump line. Times are the receive clock the
//! bus core used, so a replay feeds the core the very same (time, bytes) sequence.
//! Files are buffered and flushed at least once a second and on drop; a failed write is
//! reported once and counted, and the component keeps running.

use crate::logfmt::candump::{CanId, CanLogFrame, CanLogRecord, CanLogWriter, FrameData};
use crate::logfmt::udprec::{UdpRecord, UdpRecordingWriter};
use std::fs::File;
use std::io::{self, BufWriter};
use std::path::{Path, PathBuf};

pub const UDP_FILE: &str = "udp.rec";
pub const CAN_FILE: &str = "can.log";

pub struct Recorder {
    udp: UdpRecordingWriter<BufWriter<File>>,
    can: CanLogWriter<BufWriter<File>>,
    interface: String,
    pub write_errors: u64,
    directory: PathBuf,
}

impl Recorder {
    /// Creates (truncates) both files in `directory`.
    pub fn create(directory: &Path, can_interface: &str) -> io::Result<Self> {
        std::fs::create_dir_all(directory)?;
        let open = |name| File::create(directory.join(name)).map(BufWriter::new);
        Ok(Self {
            udp: UdpRecordingWriter::new(open(UDP_FILE)?)?,
            can: CanLogWriter::new(open(CAN_FILE)?),
            interface: can_interface.to_string(),
            write_errors: 0,
            directory: directory.to_path_buf(),
        })
    }

    fn failed(&mut self, what: &str, error: &dyn std::fmt::Display) {
        if self.write_errors == 0 {
            eprintln!(
                "fsw-component: recording to {} failed ({what}): {error}",
                self.directory.display()
            );
        }
        self.write_errors += 1;
    }

    pub fn udp(&mut self, time_us: u64, source_port: u16, destination_port: u16, payload: &[u8]) {
        let record = UdpRecord {
            time_us,
            source_port,
            destination_port,
            payload: payload.to_vec(),
        };
        if let Err(e) = self.udp.write_record(&record) {
            self.failed("udp", &e);
        }
    }

    pub fn can(&mut self, time_us: u64, id: u32, data: &[u8], fd: bool) {
        let Some(data) = FrameData::new(data) else {
            return self.failed("can", &"frame longer than 64 bytes");
        };
        let frame = if fd {
            CanLogFrame::Fd {
                id: CanId::Extended(id),
                flags: 0,
                data,
            }
        } else {
            CanLogFrame::Classic {
                id: CanId::Extended(id),
                data,
                len8_dlc: None,
            }
        };
        let record = CanLogRecord {
            timestamp_us: time_us,
            interface: self.interface.clone(),
            frame,
            direction: None,
        };
        if let Err(e) = self.can.write_record(&record) {
            self.failed("can", &e);
        }
    }

    pub fn flush(&mut self) {
        if let Err(e) = self.udp.flush() {
            self.failed("udp flush", &e);
        }
        if let Err(e) = self.can.flush() {
            self.failed("can flush", &e);
        }
    }
}

impl Drop for Recorder {
    fn drop(&mut self) {
        self.flush();
    }
}

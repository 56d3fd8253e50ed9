//! A Rust CAN peer for bus tests with other stacks (tests/bus, python-can on vcan).
//!
//! Usage: `can_echo_peer <interface>`. Opens an FD [`CanTransport`] and prints `READY`.
//! Then, for every frame it receives:
//! - ID `STOP_ID`: prints one `STATS key=value ...` line and exits 0;
//! - ID `BURST_ID`, data `[count]`: sends `count` frames, frame `i` with ID
//!   `BURST_REPLY_BASE_ID + i`, classic with `i % 9` bytes for even `i`, FD with the
//!   `(i / 2) % 16`-th valid FD length for odd `i`, byte `k` = `(37 i + 11 k + 5) mod 256`;
//! - any other ID: echoes it with ID bit 28 flipped, data reversed, same classic/FD kind,
//!   which shows the frame went through our receive and send paths, not a loopback.
//!
//! Any transport error goes to stderr with exit status 1.

use std::io::Write;
use std::process::ExitCode;

use fsw_component::transport::can_frame::is_valid_fd_data_len;
use fsw_component::transport::{CanTransport, CanTransportConfig, RawCanFrame, TransportError};

const STOP_ID: u32 = 0x1FFF_FF00;
const BURST_ID: u32 = 0x1FFF_FF01;
const BURST_REPLY_BASE_ID: u32 = 0x0F00_0000;
const ECHO_ID_FLIP: u32 = 1 << 28;

fn burst_frame(index: usize) -> Result<RawCanFrame, TransportError> {
    let fd_lengths: Vec<usize> = (0..=64).filter(|&len| is_valid_fd_data_len(len)).collect();
    let id = BURST_REPLY_BASE_ID + index as u32;
    let data_of =
        |len: usize| -> Vec<u8> { (0..len).map(|k| (37 * index + 11 * k + 5) as u8).collect() };
    if index.is_multiple_of(2) {
        RawCanFrame::classic(id, &data_of(index % 9))
    } else {
        RawCanFrame::fd(id, &data_of(fd_lengths[(index / 2) % fd_lengths.len()]))
    }
}

fn echo_frame(frame: &RawCanFrame) -> Result<RawCanFrame, TransportError> {
    let reversed: Vec<u8> = frame.data().iter().rev().copied().collect();
    let id = frame.id() ^ ECHO_ID_FLIP;
    if frame.is_fd() {
        RawCanFrame::fd(id, &reversed)
    } else {
        RawCanFrame::classic(id, &reversed)
    }
}

async fn serve(interface: String) -> Result<(), TransportError> {
    let transport = CanTransport::open(&CanTransportConfig {
        interface,
        fd: true,
    })?;
    println!("READY {}", transport.interface());
    let _ = std::io::stdout().flush();
    loop {
        let frame = transport.recv().await?;
        match frame.id() {
            STOP_ID => {
                let stats = transport.stats();
                println!(
                    "STATS frames_received={} frames_sent={} dropped_standard_id={} \
                     dropped_remote={} dropped_error_frames={} dropped_malformed={} \
                     dropped_receive_queue_full={} send_errors={}",
                    stats.frames_received,
                    stats.frames_sent,
                    stats.dropped_standard_id,
                    stats.dropped_remote,
                    stats.dropped_error_frames,
                    stats.dropped_malformed,
                    stats.dropped_receive_queue_full,
                    stats.send_errors
                );
                return Ok(());
            }
            BURST_ID => {
                let count = frame.data().first().copied().unwrap_or(0);
                for index in 0..usize::from(count) {
                    transport.send(&burst_frame(index)?).await?;
                }
            }
            _ => transport.send(&echo_frame(&frame)?).await?,
        }
    }
}

const USAGE: &str = "usage: can_echo_peer <interface>

Opens an FD SocketCAN transport on <interface> (e.g. vcan0), prints READY, echoes frames
(ID bit 28 flipped, data reversed), answers burst requests, and exits 0 on the stop frame
after one STATS line (see the source's header for the IDs).

  -h, --help   this text";

fn main() -> ExitCode {
    let Some(interface) = std::env::args().nth(1) else {
        eprintln!("{USAGE}");
        return ExitCode::from(2);
    };
    if interface == "--help" || interface == "-h" {
        println!("{USAGE}");
        return ExitCode::SUCCESS;
    }
    let runtime = match tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
    {
        Ok(runtime) => runtime,
        Err(error) => {
            eprintln!("can_echo_peer: cannot start tokio: {error}");
            return ExitCode::FAILURE;
        }
    };
    match runtime.block_on(serve(interface)) {
        Ok(()) => ExitCode::SUCCESS,
        Err(error) => {
            eprintln!("can_echo_peer: {error}");
            ExitCode::FAILURE
        }
    }
}

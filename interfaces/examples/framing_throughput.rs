//! Prints a table of encode/frame/reassemble/decode throughput for representative messages:
//! a 960x600 RGB camera frame over CCSDS/UDP, a 64x48 gray frame over CAN FD, and health
//! status over classic CAN. Timing belongs here, not in tests.
//!
//! `cargo run -p interfaces --example framing_throughput` (add `--release` for flight-like numbers).

use interfaces::ccsds::{message_packets, CcsdsReassembler, PacketType};
use interfaces::cyphal::{transfer_frames, CanReassembler, Mtu, Priority, TransferHeader};
use interfaces::messages::{
    decode, encode, CameraFrame, FrameHeader, HealthStatus, Mode, PixelFormat,
};
use std::time::Instant;

fn camera_frame(pixels: &[u8], width: u16, height: u16, format: PixelFormat) -> CameraFrame<'_> {
    CameraFrame {
        header: FrameHeader {
            frame_id: 1,
            time_us: 1,
            width,
            height,
            format,
        },
        mask: None,
        pixels,
        camera: None,
    }
}

fn health() -> HealthStatus {
    HealthStatus {
        time_us: 1_700_000_000_000_000,
        mode: Mode::Train,
        uptime_s: 86_400,
        frames_received: 17_280,
        frames_used: 900,
        frames_dropped: 12,
        decode_errors: 0,
        crc_errors: 0,
        commands_accepted: 40,
        commands_rejected: 1,
        gaussians: 120_000,
        rounds: 800,
        last_round_duration_ms: Some(4200),
        last_loss: Some(0.041),
        last_prediction_psnr_db: Some(28.4),
        window_fill: 10,
        window_capacity: 10,
        frame_queue_depth: 0,
        publish_queue_depth: 1,
        memory_bytes: 900 << 20,
    }
}

fn report(
    name: &str,
    bytes: usize,
    units: usize,
    unit_name: &str,
    iterations: usize,
    seconds: f64,
) {
    let per_msg_us = seconds / iterations as f64 * 1e6;
    let mb_s = (bytes * iterations) as f64 / seconds / 1e6;
    println!(
        "| {name:<36} | {bytes:>9} | {units:>6} {unit_name:<9} | {per_msg_us:>12.1} | {mb_s:>8.1} |"
    );
}

const USAGE: &str =
    "framing_throughput: encode/frame/reassemble/decode throughput of representative messages
usage: cargo run --release -p interfaces --example framing_throughput
  (no options; prints a Markdown table, the CPU model first)";

/// The CPU model (Linux `/proc/cpuinfo`) and the CPUs available, for the header: timings
/// from different machines must not be compared unnamed. (gs-core's `machine` module says
/// more; this crate does not depend on it.)
fn cpu_line() -> String {
    let model = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split_once(':'))
                .map(|(_, v)| v.trim().to_string())
        })
        .unwrap_or_else(|| "unknown CPU".into());
    let cpus = std::thread::available_parallelism().map_or(0, std::num::NonZero::get);
    format!("cpu: {model}, {cpus} CPUs available")
}

fn main() {
    if std::env::args().any(|a| a == "--help" || a == "-h") {
        println!("{USAGE}");
        return;
    }
    println!("{}\n", cpu_line());
    println!("| message / path                       | msg bytes | units            | us / message | MB/s     |");
    println!("|--------------------------------------|-----------|------------------|--------------|----------|");

    // Large camera frame over CCSDS: encode + segment + reassemble + decode.
    let pixels: Vec<u8> = (0..960 * 600 * 3).map(|i| (i * 7 % 256) as u8).collect();
    let frame = camera_frame(&pixels, 960, 600, PixelFormat::Rgb8);
    let mut enc = vec![0u8; pixels.len() + 64];
    let mut rx: CcsdsReassembler<Vec<u8>, 2> =
        CcsdsReassembler::new(vec![0u8; 2 * (pixels.len() + 64)]);
    let iterations = 20;
    let mut packets_per_msg = 0;
    let start = Instant::now();
    for i in 0..iterations {
        let len = encode(&frame, &mut enc).expect("valid frame").len();
        let mut done = false;
        packets_per_msg = 0;
        for p in message_packets(
            PacketType::Telemetry,
            200,
            &enc[..len],
            (i * 2000) as u16,
            1472,
        )
        .expect("valid APID")
        {
            packets_per_msg += 1;
            if let Some(m) = rx.push(&p, i as u64 * 10).expect("own packets") {
                let back: CameraFrame = decode(m.payload).expect("decodes");
                assert_eq!(back.pixels.len(), pixels.len());
                done = true;
            }
        }
        assert!(done);
    }
    report(
        "CameraFrame 960x600 RGB8, CCSDS/UDP",
        pixels.len(),
        packets_per_msg,
        "datagrams",
        iterations,
        start.elapsed().as_secs_f64(),
    );

    // Small gray frame over CAN FD.
    let gray: Vec<u8> = (0..64 * 48).map(|i| i as u8).collect();
    let frame = camera_frame(&gray, 64, 48, PixelFormat::Gray8);
    let mut can_rx: CanReassembler<Vec<u8>, 4> = CanReassembler::new(vec![0u8; 4 * 4096]);
    let iterations = 2000;
    let mut frames_per_msg = 0;
    let start = Instant::now();
    for i in 0..iterations {
        let len = encode(&frame, &mut enc).expect("valid").len();
        let header = TransferHeader {
            priority: Priority::Low,
            subject_id: 200,
            source_node_id: 5,
            transfer_id: i as u64,
        };
        frames_per_msg = 0;
        for f in transfer_frames(&header, &enc[..len], Mtu::Fd).expect("valid header") {
            frames_per_msg += 1;
            if let Some(t) = can_rx.push(f.id, &f.data, i as u64).expect("own frames") {
                let back: CameraFrame = decode(t.payload).expect("decodes");
                assert_eq!(back.pixels.len(), gray.len());
            }
        }
    }
    report(
        "CameraFrame 64x48 Gray8, CAN FD",
        gray.len(),
        frames_per_msg,
        "frames",
        iterations,
        start.elapsed().as_secs_f64(),
    );

    // Health over classic CAN.
    let h = health();
    let iterations = 20_000;
    let mut frames_per_msg = 0;
    let mut encoded_len = 0;
    let start = Instant::now();
    for i in 0..iterations {
        encoded_len = encode(&h, &mut enc).expect("valid").len();
        let header = TransferHeader {
            priority: Priority::Nominal,
            subject_id: 400,
            source_node_id: 5,
            transfer_id: i as u64,
        };
        frames_per_msg = 0;
        for f in transfer_frames(&header, &enc[..encoded_len], Mtu::Classic).expect("valid header")
        {
            frames_per_msg += 1;
            if let Some(t) = can_rx.push(f.id, &f.data, i as u64).expect("own frames") {
                let back: HealthStatus = decode(t.payload).expect("decodes");
                assert_eq!(back.rounds, 800);
            }
        }
    }
    report(
        "HealthStatus, classic CAN",
        encoded_len,
        frames_per_msg,
        "frames",
        iterations,
        start.elapsed().as_secs_f64(),
    );
}

//! Replays the committed fuzz corpora (`fuzz/corpus/<target>/`) through the fuzz harnesses
//! (`fuzz/harness/`) on every test run, so stable CI without cargo-fuzz exercises them, and
//! runs each harness on random inputs. The seeds are real traffic and files written by the
//! code itself (telemetry, frames and commands over CCSDS and Cyphal, candump logs and UDP
//! recordings, learner checkpoints), so mutations start deep inside the parsers.
//! `cargo test -p fsw-component --test fuzz_corpus -- --ignored` rewrites the seeds.

#[path = "../fuzz/harness/mod.rs"]
mod harness;

use fsw_component::learner::Learner;
use fsw_component::logfmt::candump::{CanId, CanLogFrame, CanLogRecord, CanLogWriter, FrameData};
use fsw_component::logfmt::udprec::{UdpRecord, UdpRecordingWriter};
use glam::DVec3;
use interfaces::ccsds::{message_packets, PacketType};
use interfaces::cyphal::{transfer_frames, Mtu, Priority, TransferHeader};
use interfaces::messages::{
    encode, port, CameraFrame, Command, CommandKind, FrameHeader, Message, Mode, PixelFormat,
    RenderRequest, SunVector, TargetPose,
};
use proptest::prelude::*;
use serde::Serialize;
use std::path::PathBuf;

const TARGETS: [&str; 4] = ["sync", "logs", "nearest_checkpoint", "bus_core"];

fn corpus_dir(target: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("fuzz/corpus")
        .join(target)
}

fn harness(target: &str) -> fn(&[u8]) {
    match target {
        "sync" => harness::sync::run,
        "logs" => harness::logs::run,
        "nearest_checkpoint" => harness::nearest_checkpoint::run,
        "bus_core" => harness::bus_core::run,
        _ => unreachable!("unknown target {target}"),
    }
}

#[test]
fn committed_corpora_replay_without_findings() {
    for target in TARGETS {
        let run = harness(target);
        let mut files = 0;
        for entry in std::fs::read_dir(corpus_dir(target)).expect("corpus directory exists") {
            let path = entry.unwrap().path();
            run(&std::fs::read(&path).unwrap());
            files += 1;
        }
        assert!(files >= 6, "{target}: corpus has only {files} files");
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 128, ..ProptestConfig::default() })]
    #[test]
    fn harnesses_survive_random_inputs(
        target in 0..TARGETS.len(),
        bytes in proptest::collection::vec(any::<u8>(), 0..2000),
    ) {
        harness(TARGETS[target])(&bytes);
    }
}

#[test]
#[ignore = "rewrites the committed seed corpora"]
fn regenerate_seed_corpora() {
    for (target, seeds) in [
        ("sync", sync_seeds()),
        ("logs", log_seeds()),
        ("nearest_checkpoint", checkpoint_seeds()),
        ("bus_core", bus_seeds()),
    ] {
        let dir = corpus_dir(target);
        std::fs::create_dir_all(&dir).unwrap();
        for (i, seed) in seeds.iter().enumerate() {
            harness(target)(seed);
            std::fs::write(dir.join(format!("seed-{i:03}")), seed).unwrap();
        }
    }
}

// ---- synchronizer programs (layout in harness/sync.rs) ----

/// Absolute time tags (`op` time mode 3), so each seed reads as a timeline.
struct SyncProgram(Vec<u8>);

impl SyncProgram {
    fn new(capacity: u8) -> Self {
        // capacity - 2, max gap 2 s (x 100 us), stale after 10 s (x 1 ms), quality, mounting.
        let mut v = vec![capacity - 2];
        v.extend(20_000u16.to_le_bytes());
        v.extend(10_000u16.to_le_bytes());
        v.extend([0, 16]);
        Self(v)
    }
    fn op(&mut self, op: u8, time_us: u64) -> &mut Self {
        self.0.push(op | 0x0C);
        self.0.extend(time_us.to_le_bytes());
        self
    }
    fn pose(&mut self, time_us: u64, q_xyzw: [i8; 4], t: [i8; 3], scale: u8) -> &mut Self {
        self.op(0, time_us);
        self.0.extend(q_xyzw.map(|x| x as u8));
        self.0.extend(t.map(|x| x as u8));
        self.0.extend([scale, 255]);
        self
    }
    fn sun(&mut self, time_us: u64, s: [i8; 3], valid: bool) -> &mut Self {
        self.op(if valid { 1 } else { 0x21 }, time_us);
        self.0.extend(s.map(|x| x as u8));
        self
    }
    fn query(&mut self, time_us: u64, wait: bool) -> &mut Self {
        self.op(if wait { 2 } else { 0x22 }, time_us)
    }
}

fn sync_seeds() -> Vec<Vec<u8>> {
    let mut out = Vec::new();
    let nominal = |p: &mut SyncProgram, steps: u64| {
        for k in 0..steps {
            let t = k * 1_000_000;
            let angle = (k as i8).wrapping_mul(20);
            p.pose(t, [0, angle, 0, 100], [0, 0, 127], 10);
            p.sun(t, [90, 0, 90], true);
            if k > 0 {
                p.query(t - 500_000, k % 2 == 0);
            }
        }
    };
    for capacity in [2, 4, 16] {
        let mut p = SyncProgram::new(capacity);
        nominal(&mut p, 6);
        out.push(p.0);
    }
    // Invalid samples, a far-future sample, a backwards jump, raw NaN values, a clear.
    let mut p = SyncProgram::new(8);
    nominal(&mut p, 3);
    p.sun(3_000_000, [0, 0, 0], true)
        .sun(4_000_000, [1, 0, 0], false)
        .query(3_500_000, false);
    p.pose(u64::MAX / 2, [0, 0, 0, 127], [0, 0, 127], 10)
        .pose(5_000_000, [0, 0, 0, 127], [0, 0, 127], 10)
        .query(4_500_000, true);
    p.0.push(0x10 | 0x0C);
    p.0.extend(6_000_000u64.to_le_bytes());
    for v in [f32::NAN, 0.0, 0.0, 1.0, f32::INFINITY, 0.0, 1.0] {
        p.0.extend(v.to_le_bytes());
    }
    p.0.push(1);
    p.0.extend(0.5f32.to_le_bytes());
    p.op(3, 0);
    nominal(&mut p, 3);
    out.push(p.0);
    // Opposite Suns, zero range, exact-time query.
    let mut p = SyncProgram::new(4);
    p.pose(0, [0, 0, 0, 127], [0, 0, 0], 10)
        .sun(0, [127, 0, 0], true)
        .pose(1_000_000, [0, 0, 0, 127], [0, 0, 0], 10)
        .sun(1_000_000, [-127, 0, 0], true)
        .query(500_000, false)
        .query(1_000_000, false);
    out.push(p.0);
    // Relative time modes: fine and coarse forward steps, backward steps.
    let mut v = SyncProgram::new(3).0;
    for (k, op) in [0u8, 1, 4, 5, 8, 2, 6, 0, 1, 2].iter().enumerate() {
        v.push(*op);
        v.extend(((k as u16 + 1) * 300).to_le_bytes());
        v.extend([0, 20, 0, 100, 0, 0, 127, 10, 255]);
    }
    out.push(v);
    out
}

// ---- bus programs (layout in harness/bus_core.rs) ----

struct BusProgram(Vec<u8>);

impl BusProgram {
    fn new(mode: u8) -> Self {
        Self(vec![mode])
    }
    fn datagram(&mut self, dt_10us: u16, bytes: &[u8]) {
        self.0.push(0);
        self.0.extend(dt_10us.to_le_bytes());
        self.0.extend((bytes.len() as u16).to_le_bytes());
        self.0.extend(bytes);
    }
    fn can(&mut self, dt_10us: u16, id: u32, data: &[u8]) {
        self.0.push(1);
        self.0.extend(dt_10us.to_le_bytes());
        self.0.extend(id.to_le_bytes());
        self.0.push(data.len() as u8);
        self.0.extend(data);
    }
    fn tick_s(&mut self, seconds: u16) {
        self.0.push(2 | 8);
        self.0.extend(seconds.to_le_bytes());
    }
}

fn encoded<M: Message + Serialize>(msg: &M) -> Vec<u8> {
    let mut buf = vec![0u8; 4096];
    let n = encode(msg, &mut buf).expect("valid message").len();
    buf.truncate(n);
    buf
}

fn pose(time_us: u64) -> Vec<u8> {
    let half = (time_us as f32 / 1e6) * 0.1;
    encoded(&TargetPose {
        time_us,
        q_camera_from_target: [half.cos(), 0.0, half.sin(), 0.0],
        t_camera_from_target_m: [0.0, 0.0, 10.0],
        position_sigma_m: 0.01,
        attitude_sigma_rad: 0.001,
        valid: true,
    })
}

fn sun(time_us: u64) -> Vec<u8> {
    encoded(&SunVector {
        time_us,
        sun_body: [0.6, 0.0, 0.8],
        valid: true,
        eclipse: None,
    })
}

fn frame(frame_id: u32, time_us: u64) -> Vec<u8> {
    let pixels: Vec<u8> = (0..4 * 4 * 3).map(|i| (i * 5 + frame_id) as u8).collect();
    encoded(&CameraFrame {
        header: FrameHeader {
            frame_id,
            time_us,
            width: 4,
            height: 4,
            format: PixelFormat::Rgb8,
        },
        mask: None,
        pixels: &pixels,
        camera: Some(interfaces::messages::CameraModel {
            fx_px: 4.0,
            fy_px: 4.0,
            cx_px: 2.0,
            cy_px: 2.0,
            distortion: interfaces::messages::Distortion::None,
        }),
    })
}

fn commands() -> Vec<Vec<u8>> {
    [
        CommandKind::Noop,
        CommandKind::SetMode(Mode::PredictOnly),
        CommandKind::Render(RenderRequest {
            q_camera_from_target: [1.0, 0.0, 0.0, 0.0],
            t_camera_from_target_m: [0.0, 0.0, 10.0],
            sun_target: [0.0, 0.0, 1.0],
        }),
        CommandKind::SaveCheckpoint,
        CommandKind::ResetModel,
        CommandKind::LoadCheckpoint,
        CommandKind::SetMode(Mode::Train),
    ]
    .into_iter()
    .enumerate()
    .map(|(i, kind)| {
        encoded(&Command {
            sequence: 100 + i as u32,
            kind,
        })
    })
    .collect()
}

/// The nominal timeline: telemetry each second, a frame half way, then the commands.
fn timeline() -> Vec<(u16, Vec<u8>)> {
    let mut out = Vec::new();
    for k in 0..3u64 {
        out.push((port::TARGET_POSE, pose(k * 1_000_000)));
        out.push((port::SUN_VECTOR, sun(k * 1_000_000)));
        if k > 0 {
            out.push((port::CAMERA_FRAME, frame(k as u32, k * 1_000_000 - 500_000)));
        }
    }
    out.extend(commands().into_iter().map(|c| (port::COMMAND, c)));
    out
}

fn bus_seeds() -> Vec<Vec<u8>> {
    let mut out = Vec::new();
    for mode in 0..3u8 {
        let mut udp = BusProgram::new(mode);
        let mut count = 0u16;
        for (port_id, payload) in timeline() {
            let kind = if port_id == port::COMMAND {
                PacketType::Telecommand
            } else {
                PacketType::Telemetry
            };
            for p in message_packets(
                kind,
                port_id,
                &payload,
                count,
                64 + 200 * u16::from(mode) as usize,
            )
            .unwrap()
            {
                udp.datagram(1000, &p);
                count = (count + 1) % 16384;
            }
        }
        udp.tick_s(2);
        out.push(udp.0);
        let mut can = BusProgram::new(mode);
        for (i, (port_id, payload)) in timeline().into_iter().enumerate() {
            let header = TransferHeader {
                priority: Priority::Nominal,
                subject_id: port_id,
                source_node_id: 10 + mode,
                transfer_id: i as u64,
            };
            let mtu = if mode == 1 { Mtu::Classic } else { Mtu::Fd };
            for f in transfer_frames(&header, &payload, mtu).unwrap() {
                can.can(100, f.id, &f.data);
            }
        }
        can.tick_s(2);
        out.push(can.0);
    }
    // Damage: a flipped CRC byte, a truncated datagram, garbage command bytes.
    let mut bad = BusProgram::new(0);
    let cmd = &commands()[0];
    let mut packets: Vec<Vec<u8>> =
        message_packets(PacketType::Telecommand, port::COMMAND, cmd, 7, 1472)
            .unwrap()
            .map(|p| p.to_vec())
            .collect();
    let last = packets[0].len() - 1;
    packets[0][last] ^= 0xFF;
    bad.datagram(10, &packets[0]);
    bad.datagram(10, &packets[0][..5]);
    let reset = encoded(&Command {
        sequence: 9,
        kind: CommandKind::ResetCounters,
    });
    for p in message_packets(PacketType::Telecommand, port::COMMAND, &reset, 1, 1472).unwrap() {
        bad.datagram(10, &p);
    }
    let junk = [0xFFu8, 0xFF, 0xFF, 0xFF, 0x0F, 9, 9];
    for p in message_packets(PacketType::Telecommand, port::COMMAND, &junk, 8, 1472).unwrap() {
        bad.datagram(10, &p);
    }
    out.push(bad.0);
    out
}

// ---- traffic logs (layout in harness/logs.rs) ----

fn log_seeds() -> Vec<Vec<u8>> {
    let fixtures = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures");
    let mut texts = vec![
        std::fs::read(fixtures.join("candump_can_utils.log")).unwrap(),
        std::fs::read(fixtures.join("python_can_4_6_1.log")).unwrap(),
    ];
    let mut writer = CanLogWriter::new(Vec::new());
    for (i, (port_id, payload)) in timeline().into_iter().take(6).enumerate() {
        let header = TransferHeader {
            priority: Priority::Nominal,
            subject_id: port_id,
            source_node_id: 42,
            transfer_id: i as u64,
        };
        for f in transfer_frames(&header, &payload, Mtu::Fd).unwrap() {
            let record = CanLogRecord {
                timestamp_us: 1_700_000_000_000_000 + i as u64 * 1000,
                interface: "vcan0".into(),
                frame: CanLogFrame::Fd {
                    id: CanId::Extended(f.id),
                    flags: 1,
                    data: FrameData::new(&f.data).unwrap(),
                },
                direction: None,
            };
            writer.write_record(&record).unwrap();
        }
    }
    texts.push(writer.into_inner());
    let mut recording = UdpRecordingWriter::new(Vec::new()).unwrap();
    let mut count = 0;
    for (i, (port_id, payload)) in timeline().into_iter().enumerate() {
        for p in message_packets(PacketType::Telemetry, port_id, &payload, count, 200).unwrap() {
            recording
                .write_record(&UdpRecord {
                    time_us: 1000 * i as u64,
                    source_port: 40000,
                    destination_port: 15000 + port_id,
                    payload: p.to_vec(),
                })
                .unwrap();
            count += 1;
        }
    }
    let recording = recording.into_inner();
    let mut out = Vec::new();
    for text in &texts {
        for selector in [0u8, 2] {
            let mut s = vec![selector];
            s.extend(text);
            out.push(s);
        }
    }
    for selector in [1u8, 2] {
        let mut s = vec![selector];
        s.extend(&recording);
        out.push(s);
        // Cut inside the last record: a truncation error.
        let mut s = vec![selector];
        s.extend(&recording[..recording.len() - 3]);
        out.push(s);
    }
    out
}

// ---- nearest-keyframe checkpoints (layout in harness/nearest_checkpoint.rs) ----

fn checkpoint_seeds() -> Vec<Vec<u8>> {
    let views = [
        DVec3::X,
        DVec3::Y,
        DVec3::Z,
        DVec3::NEG_X,
        DVec3::new(1.0, 1.0, 0.0).normalize(),
    ];
    let mut out = Vec::new();
    for keyframes in [0, 1, 3, 5] {
        let mut learner = harness::nearest_checkpoint::learner(3);
        for (i, view) in views.iter().take(keyframes).enumerate() {
            learner.offer(&harness::nearest_checkpoint::frame(i as u32, *view));
            learner.run_round_if_due().expect("round");
        }
        let bytes = learner.save();
        // Capacity 3 (selector >> 1 = 1): even with the stored CRC, odd with it recomputed.
        let mut even = vec![2u8];
        even.extend(&bytes);
        out.push(even);
        let mut odd = vec![3u8];
        odd.extend(&bytes[..bytes.len() - 4]);
        out.push(odd);
    }
    out
}

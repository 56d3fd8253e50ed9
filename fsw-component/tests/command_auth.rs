//! Command authorisation with the default `[commands]` policy: CAN source node-IDs and
//! anonymous transfers (bus core fed real Cyphal frames), the UDP command socket and packet
//! type (real sockets on 127.0.0.1), arm-then-execute, the RENDER rate limit and size bound,
//! and no acknowledgement storm for strangers.

mod component_support;

use component_support::*;
use fsw_component::config::ComponentConfig;
use fsw_component::inbound::{BusCore, CoreSettings, Outgoing};
use fsw_component::runtime::{build_learner, LearnerKind};
use fsw_component::worker::{CheckpointSettings, QueueLimits, Worker};
use interfaces::cyphal::{transfer_frames, MessageCanId, Mtu, Priority, TransferHeader};
use interfaces::messages::{
    encode, port, AckStatus, CameraFrame, CameraModel, Command, CommandAck, CommandKind,
    Distortion, ErrorCode, EventKind, FrameHeader, Mode, PixelFormat, PredictionSource,
    RenderRequest,
};
use std::time::Duration;

const GROUND_NODE: u8 = 1;

fn bus_core() -> (BusCore, Worker) {
    let config = ComponentConfig::default();
    let worker = Worker::start(
        build_learner(&config, LearnerKind::NearestKeyframe).unwrap(),
        QueueLimits {
            frames: 4,
            commands: 16,
            predictions: 8,
        },
        CheckpointSettings {
            path: temp_dir("cmdauth-core").join("checkpoint.bin"),
            period: None,
        },
        1,
        config.denormals().unwrap(),
        Duration::from_millis(config.training.round_deadline_ms),
    )
    .unwrap();
    let settings = CoreSettings {
        sync: config.sync_config().unwrap(),
        max_wait_us: 1_000_000,
        pending_capacity: 8,
        initial_mode: Mode::Train,
        camera: config.camera_intrinsics().unwrap(),
        time_guard: config.time_guard_config().unwrap(),
        commands: config.command_policy().unwrap(),
    };
    let core = BusCore::new(settings, std::sync::Arc::clone(&worker.shared)).unwrap();
    (core, worker)
}

fn command_bytes(sequence: u32, kind: CommandKind) -> Vec<u8> {
    let mut buf = [0u8; Command::MAX_ENCODED_LEN];
    encode(&Command { sequence, kind }, &mut buf)
        .unwrap()
        .to_vec()
}

/// Sends a command as a Cyphal/CAN FD transfer from `node` (None: anonymous).
fn can_command(
    core: &mut BusCore,
    node: Option<u8>,
    sequence: u32,
    kind: CommandKind,
    now_us: u64,
) {
    can_send(core, node, sequence, command_bytes(sequence, kind), now_us);
}

/// Sends command bytes (transfer-ID from `sequence`) from `node` (None: anonymous).
fn can_send(core: &mut BusCore, node: Option<u8>, sequence: u32, bytes: Vec<u8>, now_us: u64) {
    match node {
        Some(node) => {
            let header = TransferHeader {
                priority: Priority::Nominal,
                subject_id: port::COMMAND,
                source_node_id: node,
                transfer_id: u64::from(sequence),
            };
            for f in transfer_frames(&header, &bytes, Mtu::Fd).unwrap() {
                core.handle_can_frame(true, f.id, &f.data, now_us);
            }
        }
        None => {
            // Anonymous transfers are single-frame: payload, padding, tail byte.
            let id = MessageCanId {
                priority: Priority::Nominal,
                subject_id: port::COMMAND,
                source_node_id: None,
            }
            .to_raw_anonymous(77)
            .unwrap();
            let mut data = bytes.clone();
            data.resize(15, 0);
            data.push(0xE0 | (sequence % 32) as u8);
            core.handle_can_frame(true, id, &data, now_us);
        }
    }
}

fn acks(out: &[Outgoing]) -> Vec<CommandAck> {
    out.iter()
        .filter_map(|o| match o {
            Outgoing::Ack(a) => Some(*a),
            _ => None,
        })
        .collect()
}

fn error_events(out: &[Outgoing], code: ErrorCode) -> usize {
    out.iter()
        .filter(|o| {
            matches!(o, Outgoing::Event(e)
                if matches!(e.kind, EventKind::Error { code: c, .. } if c == code))
        })
        .count()
}

fn render_kind() -> CommandKind {
    CommandKind::Render(RenderRequest {
        q_camera_from_target: [1.0, 0.0, 0.0, 0.0],
        t_camera_from_target_m: [0.0, 0.0, 10.0],
        sun_target: [0.0, 0.6, 0.8],
    })
}

#[test]
fn can_commands_only_from_listed_nodes_and_never_anonymous() {
    let (mut core, worker) = bus_core();
    let t0 = 1_000_000_000;
    can_command(&mut core, Some(GROUND_NODE), 1, CommandKind::Noop, t0);
    let out = core.take_outgoing();
    assert_eq!(acks(&out).len(), 1);
    assert_eq!(acks(&out)[0].status, AckStatus::Ok);

    // Unlisted node and anonymous transfers, 50 each within one second: no acknowledgement,
    // every one counted, one event for the lot.
    for i in 0..50 {
        can_command(
            &mut core,
            Some(10),
            100 + i,
            CommandKind::Noop,
            t0 + u64::from(i),
        );
        can_command(
            &mut core,
            None,
            200 + i,
            CommandKind::SaveCheckpoint,
            t0 + 100 + u64::from(i),
        );
    }
    let out = core.take_outgoing();
    assert!(acks(&out).is_empty(), "{:?}", acks(&out));
    assert_eq!(error_events(&out, ErrorCode::CommandUnauthorised), 1);
    let c = core.counters();
    assert_eq!(c.bus.commands_unauthorised, 100);
    assert_eq!(c.bus.commands_accepted, 1);
    // The event after the rate-limit interval carries the count of those suppressed.
    can_command(&mut core, Some(10), 300, CommandKind::Noop, t0 + 1_000_000);
    let out = core.take_outgoing();
    assert!(out.iter().any(|o| matches!(o, Outgoing::Event(e) if e.kind
        == EventKind::Error { code: ErrorCode::CommandUnauthorised, detail: 100 })));
    worker.finish();
}

#[test]
fn destructive_commands_need_a_fresh_arm_from_the_same_source() {
    let (mut core, worker) = bus_core();
    let t0 = 1_000_000_000;
    can_command(&mut core, Some(GROUND_NODE), 1, CommandKind::ResetModel, t0);
    let out = core.take_outgoing();
    let refused = acks(&out);
    assert_eq!(refused.len(), 1);
    assert_eq!(refused[0].status, AckStatus::ExecutionError);
    assert_eq!(refused[0].detail, ErrorCode::CommandNotArmed.index() as u16);
    assert_eq!(error_events(&out, ErrorCode::CommandNotArmed), 1);

    // ARM, then the command 10 s later (the default arm time): executes, arm consumed.
    let arm = CommandKind::Arm(CommandKind::RESET_MODEL);
    can_command(&mut core, Some(GROUND_NODE), 2, arm, t0);
    assert_eq!(acks(&core.take_outgoing())[0].status, AckStatus::Ok);
    can_command(
        &mut core,
        Some(GROUND_NODE),
        3,
        CommandKind::ResetModel,
        t0 + 10_000_000,
    );
    assert!(
        acks(&core.take_outgoing()).is_empty(),
        "queued: the trainer acknowledges"
    );
    can_command(
        &mut core,
        Some(GROUND_NODE),
        4,
        CommandKind::ResetModel,
        t0 + 10_000_001,
    );
    assert_eq!(
        acks(&core.take_outgoing())[0].status,
        AckStatus::ExecutionError
    );

    // An expired arm, and an arm for another command, do not execute.
    can_command(&mut core, Some(GROUND_NODE), 5, arm, t0 + 20_000_000);
    can_command(
        &mut core,
        Some(GROUND_NODE),
        6,
        CommandKind::ResetModel,
        t0 + 30_000_001,
    );
    let arm_load = CommandKind::Arm(CommandKind::LOAD_CHECKPOINT);
    can_command(&mut core, Some(GROUND_NODE), 7, arm_load, t0 + 40_000_000);
    can_command(
        &mut core,
        Some(GROUND_NODE),
        8,
        CommandKind::ResetModel,
        t0 + 40_000_001,
    );
    let statuses: Vec<_> = acks(&core.take_outgoing())
        .iter()
        .map(|a| (a.sequence, a.status))
        .collect();
    assert_eq!(
        statuses,
        [
            (Some(5), AckStatus::Ok),
            (Some(6), AckStatus::ExecutionError),
            (Some(7), AckStatus::Ok),
            (Some(8), AckStatus::ExecutionError),
        ]
    );
    // ARM of a harmless command is refused as invalid.
    // (sequence 9, opcode 7 ARM, argument 0 NOOP: written by hand, the encoder refuses it).
    can_send(
        &mut core,
        Some(GROUND_NODE),
        9,
        vec![9, 7, 0],
        t0 + 50_000_000,
    );
    assert_eq!(
        acks(&core.take_outgoing())[0].status,
        AckStatus::ValidationError
    );
    let c = core.counters().bus;
    assert_eq!((c.commands_not_armed, c.commands_accepted), (4, 4));
    worker.finish();
}

#[test]
fn render_commands_are_rate_limited() {
    let (mut core, worker) = bus_core();
    let t0 = 1_000_000_000;
    for i in 0..6 {
        can_command(&mut core, Some(GROUND_NODE), i, render_kind(), t0);
    }
    let out = core.take_outgoing();
    let busy: Vec<_> = acks(&out)
        .iter()
        .map(|a| (a.sequence, a.status, a.detail))
        .collect();
    let detail = ErrorCode::CommandRateLimited.index() as u16;
    assert_eq!(
        busy,
        [
            (Some(4), AckStatus::Busy, detail),
            (Some(5), AckStatus::Busy, detail)
        ]
    );
    can_command(
        &mut core,
        Some(GROUND_NODE),
        6,
        render_kind(),
        t0 + 1_000_000,
    );
    assert!(
        acks(&core.take_outgoing()).is_empty(),
        "one token after 1 s"
    );
    let c = core.counters().bus;
    assert_eq!((c.commands_accepted, c.commands_rate_limited), (5, 2));
    worker.finish();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn udp_commands_only_as_telecommands_on_the_command_socket() {
    let dir = temp_dir("cmdauth-udp");
    let mut peer = Peer::new().await;
    let config = peer.config(dir.join("checkpoint.bin"));
    let handle = start_component(&config, LearnerKind::NearestKeyframe, None).await;
    // To the camera-frame socket, and as a telemetry packet to the command socket.
    peer.command(1, CommandKind::Noop, handle.frames_addr).await;
    let as_telemetry = peer.raw_packets(port::COMMAND, &command_bytes(2, CommandKind::Noop));
    peer.send_raw(&as_telemetry[0], handle.telemetry_addr).await;
    peer.command(3, CommandKind::Noop, handle.telemetry_addr)
        .await;
    assert_eq!(peer.wait_ack(3).await.status, AckStatus::Ok);
    tokio::time::sleep(Duration::from_millis(200)).await;
    assert!(peer.snapshot(|r| r.ack(1).is_none() && r.ack(2).is_none()));
    assert_eq!(handle.counters().bus.commands_unauthorised, 2);
    assert!(
        peer.wait_for(Duration::from_secs(3), |r| r.events.iter().any(
            |e| matches!(
                e.kind,
                EventKind::Error {
                    code: ErrorCode::CommandUnauthorised,
                    ..
                }
            )
        ))
        .await
    );
    // Health counts them as rejected.
    assert!(
        peer.wait_for(Duration::from_secs(3), |r| r
            .last_health()
            .is_some_and(|h| h.commands_rejected == 2 && h.commands_accepted == 1))
            .await
    );
    handle.shutdown().await;
    std::fs::remove_dir_all(&dir).unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn render_size_is_bounded_for_large_camera_frames() {
    let dir = temp_dir("cmdauth-render");
    let mut peer = Peer::new().await;
    let config = peer.config(dir.join("checkpoint.bin"));
    let handle = start_component(&config, LearnerKind::NearestKeyframe, None).await;
    for k in 0..2 {
        send_step(&mut peer, k, &handle).await;
    }
    // A 700 x 700 grey frame (490,000 pixels, above the 262,144 default bound), with its
    // own camera model (its size is not the configured camera's).
    let (width, height) = (700u16, 700u16);
    let pixels = vec![90u8; usize::from(width) * usize::from(height)];
    let frame = CameraFrame {
        header: FrameHeader {
            frame_id: 50,
            // Long after the telemetry: rejected as stale, so that no 490 kB prediction
            // floods this peer's socket; its decoded size still sets the RENDER size.
            time_us: 100_000_000,
            width,
            height,
            format: PixelFormat::Gray8,
        },
        mask: None,
        pixels: &pixels,
        camera: Some(CameraModel {
            fx_px: 700.0,
            fy_px: 700.0,
            cx_px: 350.0,
            cy_px: 350.0,
            distortion: Distortion::None,
        }),
    };
    let mut bytes = vec![0u8; pixels.len() + 64];
    let len = encode(&frame, &mut bytes).unwrap().len();
    bytes.truncate(len);
    for (i, d) in peer
        .raw_packets(port::CAMERA_FRAME, &bytes)
        .iter()
        .enumerate()
    {
        peer.send_raw(d, handle.frames_addr).await;
        if i % 32 == 31 {
            // Stay below the kernel's socket buffer.
            tokio::time::sleep(Duration::from_millis(2)).await;
        }
    }
    let deadline = std::time::Instant::now() + Duration::from_secs(5);
    while handle.counters().bus.frames_received < 3 {
        assert!(
            std::time::Instant::now() < deadline,
            "{:#?}",
            handle.counters()
        );
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    peer.command(7, render_kind(), handle.telemetry_addr).await;
    let source = PredictionSource::Command { sequence: 7 };
    assert!(
        peer.wait_for(Duration::from_secs(5), |r| r
            .predictions
            .iter()
            .any(|p| p.source == source))
            .await
    );
    let p = peer.snapshot(|r| {
        r.predictions
            .iter()
            .find(|p| p.source == source)
            .cloned()
            .unwrap()
    });
    assert_eq!((p.header.width, p.header.height), (350, 350));
    assert_eq!(p.header.format, PixelFormat::Gray8);
    handle.shutdown().await;
    std::fs::remove_dir_all(&dir).unwrap();
}

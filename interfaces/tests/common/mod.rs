//! Shared test fixtures: one valid instance of every catalogue message, encoded to bytes with
//! its port ID, and a deterministic byte generator (SplitMix64).
#![allow(dead_code)]

use interfaces::messages::{
    encode, AckStatus, CameraFrame, Command, CommandAck, CommandKind, ErrorCode, Event, EventKind,
    FrameHeader, HealthStatus, Message, Mode, PixelFormat, PredictionSource, RenderRequest,
    RenderedPrediction, SunVector, TargetPose,
};
use serde::Serialize;

pub struct SplitMix64(pub u64);

impl SplitMix64 {
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    pub fn bytes(&mut self, n: usize) -> Vec<u8> {
        (0..n).map(|_| self.next_u64() as u8).collect()
    }
}

pub fn sun_vector() -> SunVector {
    SunVector {
        time_us: 1_700_000_000_123_456,
        sun_body: [0.6, 0.0, -0.8],
        valid: true,
        eclipse: None,
    }
}

pub fn target_pose() -> TargetPose {
    TargetPose {
        time_us: 1_700_000_000_200_000,
        q_camera_from_target: [0.5, 0.5, -0.5, 0.5],
        t_camera_from_target_m: [0.25, -0.1, 30.0],
        position_sigma_m: 0.05,
        attitude_sigma_rad: 0.002,
        valid: true,
    }
}

pub fn header(width: u16, height: u16, format: PixelFormat) -> FrameHeader {
    FrameHeader {
        frame_id: 42,
        time_us: 1_700_000_000_300_000,
        width,
        height,
        format,
    }
}

pub fn render_request() -> RenderRequest {
    RenderRequest {
        q_camera_from_target: [1.0, 0.0, 0.0, 0.0],
        t_camera_from_target_m: [0.0, 0.0, 25.0],
        sun_target: [0.0, 0.6, 0.8],
    }
}

pub fn commands() -> Vec<Command> {
    let kinds = [
        CommandKind::Noop,
        CommandKind::ResetCounters,
        CommandKind::ResetModel,
        CommandKind::SaveCheckpoint,
        CommandKind::LoadCheckpoint,
        CommandKind::SetMode(Mode::Idle),
        CommandKind::SetMode(Mode::Train),
        CommandKind::SetMode(Mode::PredictOnly),
        CommandKind::Render(render_request()),
        CommandKind::Arm(CommandKind::RESET_MODEL),
        CommandKind::Arm(CommandKind::LOAD_CHECKPOINT),
    ];
    kinds
        .iter()
        .enumerate()
        .map(|(i, &kind)| Command {
            sequence: 1000 + i as u32,
            kind,
        })
        .collect()
}

pub fn health() -> HealthStatus {
    HealthStatus {
        time_us: 5_000_000,
        mode: Mode::Train,
        uptime_s: 3600,
        frames_received: 720,
        frames_used: 200,
        frames_dropped: 3,
        decode_errors: 1,
        crc_errors: 2,
        commands_accepted: 10,
        commands_rejected: 1,
        gaussians: 10_000,
        rounds: 55,
        last_round_duration_ms: Some(1234),
        last_loss: Some(0.0321),
        last_prediction_psnr_db: Some(27.5),
        window_fill: 10,
        window_capacity: 10,
        frame_queue_depth: 1,
        publish_queue_depth: 0,
        memory_bytes: 512 << 20,
    }
}

pub fn events() -> Vec<Event> {
    vec![
        Event {
            time_us: 1,
            kind: EventKind::ModeChanged {
                from: Mode::Idle,
                to: Mode::Train,
            },
        },
        Event {
            time_us: 2,
            kind: EventKind::Error {
                code: ErrorCode::TelemetryStale,
                detail: 7,
            },
        },
        Event {
            time_us: 3,
            kind: EventKind::CheckpointSaved { rounds: 10 },
        },
        Event {
            time_us: 4,
            kind: EventKind::ModelReset,
        },
        Event {
            time_us: 5,
            kind: EventKind::ModelInitialised {
                source: interfaces::messages::InitSource::Hull,
                gaussians: 1500,
            },
        },
    ]
}

fn encoded<M: Message + Serialize>(msg: &M) -> (u16, Vec<u8>) {
    let mut buf = vec![0u8; 1 << 16];
    let len = encode(msg, &mut buf).expect("valid fixture encodes").len();
    buf.truncate(len);
    (M::PORT_ID, buf)
}

/// (port ID, encoded bytes) of every fixture message; images are small (CAN FD sized) and
/// medium (several CCSDS packets).
pub fn all_encoded(rng: &mut SplitMix64) -> Vec<(u16, Vec<u8>)> {
    let mut out = vec![
        encoded(&sun_vector()),
        encoded(&SunVector {
            eclipse: Some(true),
            ..sun_vector()
        }),
        encoded(&target_pose()),
        encoded(&health()),
    ];
    for c in commands() {
        out.push(encoded(&c));
    }
    out.push(encoded(&CommandAck {
        sequence: Some(7),
        opcode: Some(6),
        status: AckStatus::Busy,
        detail: 0,
    }));
    for e in events() {
        out.push(encoded(&e));
    }
    let small_pixels = rng.bytes(8 * 6 * 3);
    let small_mask = rng.bytes(8 * 6);
    out.push(encoded(&CameraFrame {
        header: header(8, 6, PixelFormat::Rgb8),
        mask: Some(&small_mask),
        pixels: &small_pixels,
        camera: None,
    }));
    let gray = rng.bytes(64 * 48);
    out.push(encoded(&CameraFrame {
        header: header(64, 48, PixelFormat::Gray8),
        mask: None,
        pixels: &gray,
        camera: None,
    }));
    out.push(encoded(&CameraFrame {
        header: header(8, 6, PixelFormat::Rgb8),
        mask: Some(&small_mask),
        pixels: &small_pixels,
        camera: Some(interfaces::messages::CameraModel {
            fx_px: 9.0,
            fy_px: 9.5,
            cx_px: 4.0,
            cy_px: 3.25,
            distortion: interfaces::messages::Distortion::None,
        }),
    }));
    let predicted = rng.bytes(40 * 30 * 3);
    out.push(encoded(&RenderedPrediction {
        header: header(40, 30, PixelFormat::Rgb8),
        source: PredictionSource::ObservedFrame { frame_id: 42 },
        q_camera_from_target: [0.5, 0.5, -0.5, 0.5],
        t_camera_from_target_m: [0.25, -0.1, 30.0],
        sun_target: [0.0, 0.0, 1.0],
        psnr_db: Some(31.25),
        ssim: Some(0.93),
        pixels: &predicted,
    }));
    out
}

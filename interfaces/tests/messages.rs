//! Catalogue tests: every message round-trips through postcard, the codec refuses invalid
//! messages both ways, command failures map to the right acknowledgement status, and port IDs
//! are unique and fit an 11-bit APID.

mod common;

use common::*;
use interfaces::messages::{
    decode, decode_command, encode, encoded_len, port, AckStatus, CameraFrame, CameraModel,
    CodecError, Command, CommandAck, CommandKind, Distortion, Event, HealthStatus, Message,
    PixelFormat, PredictionSource, RenderedPrediction, SunVector, TargetPose, ValidationError,
};
use serde::{Deserialize, Serialize};

fn round_trip<'a, M>(msg: &M, buf: &'a mut [u8]) -> M
where
    M: Message + Serialize + Deserialize<'a> + PartialEq + core::fmt::Debug,
{
    let expected_len = encoded_len(msg).unwrap();
    let len = encode(msg, buf).unwrap().len();
    assert_eq!(len, expected_len);
    let back: M = decode(&buf[..len]).unwrap();
    assert_eq!(&back, msg);
    back
}

#[test]
fn every_message_round_trips() {
    let mut buf = vec![0u8; 1 << 16];
    round_trip(&sun_vector(), &mut buf);
    round_trip(&target_pose(), &mut buf);
    round_trip(&health(), &mut buf);
    for c in commands() {
        round_trip(&c, &mut buf);
        let len = encode(&c, &mut buf).unwrap().len();
        assert_eq!(decode_command(&buf[..len]).unwrap(), c);
    }
    for e in events() {
        round_trip(&e, &mut buf);
    }
    round_trip(
        &CommandAck {
            sequence: None,
            opcode: None,
            status: AckStatus::FormatError,
            detail: 3,
        },
        &mut buf,
    );
    let mut rng = SplitMix64(1);
    let pixels = rng.bytes(5 * 4 * 3);
    let mask = rng.bytes(5 * 4);
    let frame = CameraFrame {
        header: header(5, 4, PixelFormat::Rgb8),
        mask: Some(&mask),
        pixels: &pixels,
        camera: None,
    };
    let mut frame_buf = vec![0u8; 256];
    round_trip(&frame, &mut frame_buf);
    let len = encode(&frame, &mut frame_buf).unwrap().len();
    let back: CameraFrame = decode(&frame_buf[..len]).unwrap();
    // Borrowed, not copied: the pixels point into the receive buffer.
    assert!(frame_buf.as_ptr_range().contains(&back.pixels.as_ptr()));
    let prediction = RenderedPrediction {
        header: header(5, 4, PixelFormat::Gray8),
        source: PredictionSource::Command { sequence: 9 },
        q_camera_from_target: [1.0, 0.0, 0.0, 0.0],
        t_camera_from_target_m: [0.0, 0.0, 10.0],
        sun_target: [1.0, 0.0, 0.0],
        psnr_db: None,
        ssim: None,
        pixels: &pixels[..20],
    };
    let mut pred_buf = vec![0u8; 256];
    round_trip(&prediction, &mut pred_buf);
}

#[test]
fn image_bytes_are_written_as_one_length_prefixed_block() {
    let pixels = [1u8, 2, 3, 4];
    let frame = CameraFrame {
        header: header(2, 2, PixelFormat::Gray8),
        mask: None,
        pixels: &pixels,
        camera: None,
    };
    let mut buf = [0u8; 64];
    let bytes = encode(&frame, &mut buf).unwrap();
    // ... mask: None (0x00), then varint 4 and the raw pixels, at the very end.
    assert_eq!(&bytes[bytes.len() - 6..], &[0x00, 4, 1, 2, 3, 4]);
}

#[test]
fn fixed_layout_of_sun_vector() {
    // Pin the wire format: varint time, three little-endian f32, bool.
    let msg = SunVector {
        time_us: 300,
        sun_body: [1.0, 0.0, 0.0],
        valid: true,
        eclipse: None,
    };
    let mut buf = [0u8; 32];
    let bytes = encode(&msg, &mut buf).unwrap();
    let mut expected = vec![0xAC, 0x02];
    expected.extend(1.0f32.to_le_bytes());
    expected.extend(0.0f32.to_le_bytes());
    expected.extend(0.0f32.to_le_bytes());
    expected.push(1);
    assert_eq!(bytes, &expected[..]);
}

#[test]
fn invalid_messages_are_refused_on_encode_and_decode() {
    let mut buf = [0u8; 128];
    let mut sun = sun_vector();
    sun.sun_body = [f32::NAN, 0.0, 1.0];
    assert_eq!(
        encode(&sun, &mut buf),
        Err(CodecError::Invalid(ValidationError::NonFinite {
            field: "sun_body"
        }))
    );
    // An invalid-flagged sample is not checked: it carries no numbers to use.
    sun.valid = false;
    assert!(encode(&sun, &mut buf).is_ok());

    // Encode a valid pose, then corrupt the quaternion in the bytes: decode must refuse it.
    let pose = target_pose();
    let len = encode(&pose, &mut buf).unwrap().len();
    let q_offset = len - (4 * 4 + 3 * 4 + 4 + 4 + 1);
    buf[q_offset..q_offset + 4].copy_from_slice(&2.0f32.to_le_bytes());
    assert!(matches!(
        decode::<TargetPose>(&buf[..len]),
        Err(CodecError::Invalid(ValidationError::NotUnitNorm {
            field: "q_camera_from_target",
            ..
        }))
    ));

    let mut h = health();
    h.last_loss = Some(f32::INFINITY);
    assert!(matches!(encode(&h, &mut buf), Err(CodecError::Invalid(_))));
    h.last_loss = Some(0.1);
    h.window_fill = 11;
    assert!(matches!(encode(&h, &mut buf), Err(CodecError::Invalid(_))));

    let pixels = [0u8; 11];
    let frame = CameraFrame {
        header: header(2, 2, PixelFormat::Rgb8),
        mask: None,
        pixels: &pixels,
        camera: None,
    };
    assert_eq!(
        encode(&frame, &mut buf),
        Err(CodecError::Invalid(ValidationError::SizeMismatch {
            field: "pixels",
            expected: 12,
            actual: 11
        }))
    );
}

#[test]
fn truncation_trailing_bytes_and_small_buffers_are_errors() {
    let mut buf = [0u8; 256];
    let len = encode(&health(), &mut buf).unwrap().len();
    for cut in 0..len {
        assert!(decode::<HealthStatus>(&buf[..cut]).is_err(), "cut at {cut}");
    }
    // Trailing zeros are CAN FD padding: accepted. Anything else is not.
    assert!(decode::<HealthStatus>(&buf[..len + 5]).is_ok());
    buf[len + 2] = 1;
    assert_eq!(
        decode::<HealthStatus>(&buf[..len + 5]),
        Err(CodecError::TrailingBytes)
    );
    let mut tiny = [0u8; 10];
    assert_eq!(
        encode(&health(), &mut tiny),
        Err(CodecError::BufferTooSmall)
    );
}

#[test]
fn command_failures_map_to_ack_statuses() {
    let mut buf = [0u8; 128];
    // Unknown opcode 9 with sequence 77: varint 77, varint 9.
    let err = decode_command(&[77, 9]).unwrap_err();
    assert_eq!(err.status, AckStatus::InvalidOpcode);
    assert_eq!(err.ack().sequence, Some(77));
    assert_eq!(err.ack().opcode, Some(9));

    // SET_MODE with a mode index that does not exist: format error, sequence known.
    let err = decode_command(&[78, 5, 9]).unwrap_err();
    assert_eq!(err.status, AckStatus::FormatError);
    assert_eq!(err.sequence, Some(78));

    // Empty and truncated input: format error, nothing known.
    let err = decode_command(&[]).unwrap_err();
    assert_eq!((err.status, err.sequence), (AckStatus::FormatError, None));
    let err = decode_command(&[0x80]).unwrap_err();
    assert_eq!(err.status, AckStatus::FormatError);

    // RENDER with a non-unit Sun vector: validation error.
    let mut req = render_request();
    req.sun_target = [0.0, 0.0, 2.0];
    let bad = Command {
        sequence: 79,
        kind: CommandKind::Render(req),
    };
    // Encode refuses it, so build the bytes from a valid command and patch the Sun vector.
    let good = Command {
        sequence: 79,
        kind: CommandKind::Render(render_request()),
    };
    let len = encode(&good, &mut buf).unwrap().len();
    buf[len - 4..len].copy_from_slice(&2.0f32.to_le_bytes());
    let err = decode_command(&buf[..len]).unwrap_err();
    assert_eq!(err.status, AckStatus::ValidationError);
    assert_eq!(err.sequence, Some(79));
    assert!(matches!(
        err.validation,
        Some(ValidationError::NotUnitNorm {
            field: "sun_target",
            ..
        })
    ));
    assert!(encode(&bad, &mut buf).is_err());
}

#[test]
fn opcodes_are_the_encoded_variant_index() {
    let mut buf = [0u8; 128];
    for c in commands() {
        let bytes = encode(&c, &mut buf).unwrap();
        // sequence 1000.. is a two-byte varint; the opcode follows.
        assert_eq!(u32::from(bytes[2]), c.kind.opcode());
    }
    assert_eq!(
        CommandKind::Arm(CommandKind::RESET_MODEL).opcode() + 1,
        CommandKind::OPCODE_COUNT
    );
    assert_eq!(CommandKind::ResetModel.opcode(), CommandKind::RESET_MODEL);
    assert_eq!(
        CommandKind::LoadCheckpoint.opcode(),
        CommandKind::LOAD_CHECKPOINT
    );
    assert_eq!(
        CommandKind::Render(render_request()).opcode(),
        CommandKind::RENDER
    );
}

#[test]
fn arm_names_a_destructive_command_only() {
    let mut buf = [0u8; 64];
    for opcode in [CommandKind::RESET_MODEL, CommandKind::LOAD_CHECKPOINT] {
        let c = Command {
            sequence: 1,
            kind: CommandKind::Arm(opcode),
        };
        let bytes = encode(&c, &mut buf).unwrap();
        assert_eq!(decode_command(bytes).unwrap(), c);
    }
    // ARM of NOOP: sequence 1, opcode 7, argument 0.
    let refused = decode_command(&[1, 7, 0]).unwrap_err();
    assert_eq!(refused.status, AckStatus::ValidationError);
    assert_eq!((refused.sequence, refused.opcode), (Some(1), Some(7)));
}

#[test]
fn error_codes_table_matches_the_wire_values() {
    use interfaces::messages::ErrorCode;
    for (i, code) in ErrorCode::ALL.iter().enumerate() {
        assert_eq!(code.index(), i);
        let event = Event {
            time_us: 1,
            kind: interfaces::messages::EventKind::Error {
                code: *code,
                detail: 0,
            },
        };
        let mut buf = [0u8; 32];
        let bytes = encode(&event, &mut buf).unwrap();
        // time_us 1, kind 1 (Error), then the code's index.
        assert_eq!(usize::from(bytes[2]), i);
    }
    // The wire value after the last code is not a code.
    let unknown = [1u8, 1, ErrorCode::COUNT as u8, 0];
    assert!(decode::<Event>(&unknown).is_err());
}

#[test]
fn port_ids_are_unique_fit_an_apid_and_match_the_trait() {
    let ids = port::ALL;
    for (i, a) in ids.iter().enumerate() {
        assert!(*a < 2047, "APID 2047 is the idle packet");
        for b in &ids[i + 1..] {
            assert_ne!(a, b);
        }
    }
    let from_trait = [
        SunVector::PORT_ID,
        TargetPose::PORT_ID,
        CameraFrame::PORT_ID,
        RenderedPrediction::PORT_ID,
        Command::PORT_ID,
        CommandAck::PORT_ID,
        HealthStatus::PORT_ID,
        Event::PORT_ID,
    ];
    assert_eq!(from_trait, ids);
    assert_eq!(
        Command::CCSDS_PACKET_TYPE,
        interfaces::ccsds::PacketType::Telecommand
    );
    assert_eq!(
        HealthStatus::CCSDS_PACKET_TYPE,
        interfaces::ccsds::PacketType::Telemetry
    );
}

#[test]
fn documented_maximum_sizes_are_exact() {
    use interfaces::messages::{ErrorCode, EventKind, FrameHeader, Mode, RenderRequest};
    let sun = SunVector {
        time_us: u64::MAX,
        sun_body: [1.0, 0.0, 0.0],
        valid: true,
        eclipse: Some(true),
    };
    assert_eq!(encoded_len(&sun).unwrap(), SunVector::MAX_ENCODED_LEN);
    let mut pose = target_pose();
    pose.time_us = u64::MAX;
    assert_eq!(encoded_len(&pose).unwrap(), TargetPose::MAX_ENCODED_LEN);
    let render = Command {
        sequence: u32::MAX,
        kind: CommandKind::Render(RenderRequest {
            q_camera_from_target: [1.0, 0.0, 0.0, 0.0],
            t_camera_from_target_m: [0.0; 3],
            sun_target: [1.0, 0.0, 0.0],
        }),
    };
    assert_eq!(encoded_len(&render).unwrap(), Command::MAX_ENCODED_LEN);
    let ack = CommandAck {
        sequence: Some(u32::MAX),
        opcode: Some(u32::MAX),
        status: AckStatus::Busy,
        detail: u16::MAX,
    };
    assert_eq!(encoded_len(&ack).unwrap(), CommandAck::MAX_ENCODED_LEN);
    let h = HealthStatus {
        time_us: u64::MAX,
        mode: Mode::PredictOnly,
        uptime_s: u32::MAX,
        frames_received: u32::MAX,
        frames_used: u32::MAX,
        frames_dropped: u32::MAX,
        decode_errors: u32::MAX,
        crc_errors: u32::MAX,
        commands_accepted: u32::MAX,
        commands_rejected: u32::MAX,
        gaussians: u32::MAX,
        rounds: u32::MAX,
        last_round_duration_ms: Some(u32::MAX),
        last_loss: Some(1.0),
        last_prediction_psnr_db: Some(1.0),
        window_fill: 255,
        window_capacity: 255,
        frame_queue_depth: u16::MAX,
        publish_queue_depth: u16::MAX,
        memory_bytes: u64::MAX,
    };
    assert_eq!(encoded_len(&h).unwrap(), HealthStatus::MAX_ENCODED_LEN);
    let e = Event {
        time_us: u64::MAX,
        kind: EventKind::Error {
            code: ErrorCode::CameraMismatch,
            detail: u32::MAX,
        },
    };
    assert_eq!(encoded_len(&e).unwrap(), Event::MAX_ENCODED_LEN);
    let initialised = Event {
        time_us: u64::MAX,
        kind: EventKind::ModelInitialised {
            source: interfaces::messages::InitSource::RandomCarveFailed,
            gaussians: u32::MAX,
        },
    };
    assert_eq!(encoded_len(&initialised).unwrap(), Event::MAX_ENCODED_LEN);
    let header = FrameHeader {
        frame_id: u32::MAX,
        time_us: u64::MAX,
        width: u16::MAX,
        height: u16::MAX,
        format: PixelFormat::Gray8,
    };
    assert_eq!(encoded_len(&header).unwrap(), FrameHeader::MAX_ENCODED_LEN);
    let prediction = RenderedPrediction {
        header,
        source: PredictionSource::Command { sequence: u32::MAX },
        q_camera_from_target: [1.0, 0.0, 0.0, 0.0],
        t_camera_from_target_m: [0.0; 3],
        sun_target: [1.0, 0.0, 0.0],
        psnr_db: Some(1.0),
        ssim: Some(1.0),
        pixels: &[],
    };
    // One byte for the empty pixel string's length.
    assert_eq!(
        encoded_len(&prediction).unwrap(),
        RenderedPrediction::MAX_FIXED_ENCODED_LEN + 1
    );
}

fn camera_model() -> CameraModel {
    CameraModel {
        fx_px: 30.5,
        fy_px: 31.0,
        cx_px: 2.0,
        cy_px: 1.5,
        distortion: Distortion::None,
    }
}

#[test]
fn camera_frame_1_0_bytes_decode_with_no_camera_and_1_1_round_trips() {
    let pixels = [1u8, 2, 3, 4, 5, 6];
    let mask = [0u8, 255, 255, 0, 0, 0];
    let old = CameraFrame {
        header: header(3, 2, PixelFormat::Gray8),
        mask: Some(&mask),
        pixels: &pixels,
        camera: None,
    };
    // A 1.0 frame written by hand (header, mask, pixels): no trailing byte at all.
    let mut v10 = Vec::new();
    v10.extend(
        postcard::to_slice(&old.header, &mut [0u8; 32])
            .unwrap()
            .iter(),
    );
    v10.push(1);
    v10.push(6);
    v10.extend_from_slice(&mask);
    v10.push(6);
    v10.extend_from_slice(&pixels);
    let mut buf = [0u8; 128];
    // Without a camera the encoding is exactly 1.0's, so 1.0 receivers read it unchanged.
    assert_eq!(encode(&old, &mut buf).unwrap(), &v10[..]);
    assert_eq!(decode::<CameraFrame>(&v10).unwrap(), old);
    // CAN FD padding after a 1.0 frame reads as "no camera" too.
    let mut padded = v10.clone();
    padded.extend_from_slice(&[0, 0, 0]);
    assert_eq!(decode::<CameraFrame>(&padded).unwrap(), old);

    let new = CameraFrame {
        camera: Some(camera_model()),
        ..old
    };
    let bytes = encode(&new, &mut buf).unwrap().to_vec();
    assert_eq!(bytes.len(), v10.len() + 1 + CameraModel::ENCODED_LEN);
    assert_eq!(&bytes[..v10.len()], &v10[..], "1.1 only appends");
    assert_eq!(bytes[v10.len()], 1, "Option tag of the camera");
    assert_eq!(decode::<CameraFrame>(&bytes).unwrap(), new);
    // A camera cut short is malformed, never silently "no camera".
    for cut in v10.len() + 1..bytes.len() {
        assert_eq!(
            decode::<CameraFrame>(&bytes[..cut]),
            Err(CodecError::Format),
            "cut at {cut}"
        );
    }
    // A tag other than 0 or 1 is malformed.
    let mut bad_tag = v10.clone();
    bad_tag.push(2);
    assert_eq!(decode::<CameraFrame>(&bad_tag), Err(CodecError::Format));
}

#[test]
fn camera_models_are_validated() {
    let pixels = [0u8; 6];
    let mut buf = [0u8; 128];
    for (camera, field) in [
        (
            CameraModel {
                fx_px: 0.0,
                ..camera_model()
            },
            "camera focal length",
        ),
        (
            CameraModel {
                cx_px: 3.5,
                ..camera_model()
            },
            "camera principal point",
        ),
        (
            CameraModel {
                cy_px: -0.1,
                ..camera_model()
            },
            "camera principal point",
        ),
    ] {
        let frame = CameraFrame {
            header: header(3, 2, PixelFormat::Gray8),
            mask: None,
            pixels: &pixels,
            camera: Some(camera),
        };
        assert_eq!(
            encode(&frame, &mut buf),
            Err(CodecError::Invalid(ValidationError::OutOfRange { field }))
        );
    }
    let nan = CameraModel {
        fy_px: f32::NAN,
        ..camera_model()
    };
    assert_eq!(
        nan.check(3, 2),
        Err(ValidationError::NonFinite { field: "camera" })
    );
    // Decoding validates too: a NaN focal length written by hand is refused.
    let good = CameraFrame {
        header: header(3, 2, PixelFormat::Gray8),
        mask: None,
        pixels: &pixels,
        camera: Some(camera_model()),
    };
    let mut bytes = encode(&good, &mut buf).unwrap().to_vec();
    let at = bytes.len() - CameraModel::ENCODED_LEN;
    bytes[at..at + 4].copy_from_slice(&f32::NAN.to_le_bytes());
    assert!(matches!(
        decode::<CameraFrame>(&bytes),
        Err(CodecError::Invalid(ValidationError::NonFinite { .. }))
    ));
}

#[test]
fn sun_vector_eclipse_flag_is_appended() {
    let mut buf = [0u8; 64];
    let v10 = sun_vector();
    let old_bytes = encode(&v10, &mut buf).unwrap().to_vec();
    assert_eq!(old_bytes.len(), 10 + 12 + 1 - 2, "1.0 layout");
    assert_eq!(decode::<SunVector>(&old_bytes).unwrap().eclipse, None);
    for flag in [true, false] {
        let sun = SunVector {
            eclipse: Some(flag),
            ..v10
        };
        let bytes = encode(&sun, &mut buf).unwrap().to_vec();
        assert_eq!(&bytes[..old_bytes.len()], &old_bytes[..]);
        assert_eq!(&bytes[old_bytes.len()..], &[1, u8::from(flag)]);
        assert_eq!(decode::<SunVector>(&bytes).unwrap(), sun);
        // CAN FD padding after it is still fine.
        let mut padded = bytes.clone();
        padded.extend_from_slice(&[0; 4]);
        assert_eq!(decode::<SunVector>(&padded).unwrap(), sun);
    }
    let mut cut = old_bytes.clone();
    cut.push(1);
    assert_eq!(decode::<SunVector>(&cut), Err(CodecError::Format));
}

#[test]
fn error_code_count_is_the_number_of_codes() {
    use interfaces::messages::ErrorCode;
    // Receivers size per-code tables with COUNT: a code appended without updating it would
    // index past them. The wire value COUNT - 1 is the last code, COUNT is none.
    let last = u8::try_from(ErrorCode::COUNT - 1).unwrap();
    assert!(postcard::from_bytes::<ErrorCode>(&[last]).is_ok());
    assert!(postcard::from_bytes::<ErrorCode>(&[last + 1]).is_err());
}

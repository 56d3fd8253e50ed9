//! Bus logs from a generated dataset: read back with the component's log readers, every
//! message reassembled with the interfaces reassemblers and compared with telemetry.jsonl and
//! the PNGs (classic CAN and CAN FD); then replayed through `run_replay` in-process, where
//! every frame must be decoded, synchronised and used with no decode or protocol errors.

use fsw_component::config::ComponentConfig;
use fsw_component::logfmt::candump::{CanLogFrame, CanLogReader, MalformedLinePolicy};
use fsw_component::logfmt::udprec::UdpRecordingReader;
use fsw_component::runtime::{build_learner, run_replay, LearnerKind, ReplaySpeed};
use interfaces::ccsds::CcsdsReassembler;
use interfaces::cyphal::CanReassembler;
use interfaces::messages::{decode, port, CameraFrame, PixelFormat, SunVector, TargetPose};
use sim_harness::busfeed::{
    bus_log_paths, write_bus_logs, BusFeedError, BusFeedOptions, AOCS_NODE_ID, NAVIGATION_NODE_ID,
};
use sim_harness::dataset::{generate, GenerateOptions};
use sim_harness::scenario::Scenario;
use std::io::BufReader;
use std::path::{Path, PathBuf};

const FRAMES: u32 = 3;

fn temp_dir(name: &str) -> PathBuf {
    let dir =
        std::env::temp_dir().join(format!("sim-harness-busfeed-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

/// The quick scenario, 3 frames of 120x75.
fn tiny_dataset(name: &str) -> PathBuf {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../config/scenarios/quick.toml");
    let scenario = Scenario::load(&path)
        .unwrap()
        .with_overrides(Some(FRAMES), Some(16), Some(1))
        .unwrap();
    let dir = temp_dir(name);
    generate(&scenario, &dir, GenerateOptions::default(), &mut |_| {}).unwrap();
    dir
}

fn telemetry(dataset: &Path) -> Vec<serde_json::Value> {
    std::fs::read_to_string(dataset.join("telemetry.jsonl"))
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect()
}

fn f32s<const N: usize>(v: &serde_json::Value) -> [f32; N] {
    std::array::from_fn(|i| v[i].as_f64().unwrap() as f32)
}

fn assert_close<const N: usize>(got: [f32; N], want: [f32; N], what: &str) {
    for i in 0..N {
        // Unit vectors are renormalised in f64 before the cast: a few f32 ulps at most.
        assert!(
            (got[i] - want[i]).abs() <= 1e-6 * want[i].abs().max(1.0),
            "{what}[{i}]: {} vs {}",
            got[i],
            want[i]
        );
    }
}

#[test]
fn logs_decode_to_the_dataset_telemetry_and_images() {
    let dataset = tiny_dataset("decode");
    let lines = telemetry(&dataset);
    assert_eq!(lines.len(), FRAMES as usize);
    for fd in [true, false] {
        let out = dataset.join(if fd { "bus-fd" } else { "bus-classic" });
        let mut options = BusFeedOptions::from_config(&ComponentConfig::default());
        options.can_fd = fd;
        options.position_sigma_m = 0.05;
        let summary = write_bus_logs(&dataset, &out, &options, 42).unwrap();
        assert_eq!(summary.frames, u64::from(FRAMES));
        let [can_path, udp_path] = bus_log_paths(&out);

        // CAN: one pose transfer from navigation and one Sun transfer from the AOCS per line.
        let reader = BufReader::new(std::fs::File::open(&can_path).unwrap());
        let mut rx: CanReassembler<Vec<u8>, 4> = CanReassembler::new(vec![0; 4 * 256]);
        let (mut poses, mut suns) = (Vec::new(), Vec::new());
        let mut can_times = Vec::new();
        for record in CanLogReader::new(reader, MalformedLinePolicy::Report) {
            let record = record.unwrap();
            assert_eq!(record.interface, options.can_interface);
            let (id, data) = match record.frame {
                CanLogFrame::Fd { id, data, .. } if fd => (id, data),
                CanLogFrame::Classic { id, data, .. } if !fd => (id, data),
                other => panic!("unexpected frame kind {other:?} (fd = {fd})"),
            };
            assert!(data.len() <= if fd { 64 } else { 8 });
            can_times.push(record.timestamp_us);
            if let Some(t) = rx
                .push(id.raw(), data.as_slice(), record.timestamp_us)
                .unwrap()
            {
                match t.subject_id {
                    port::TARGET_POSE => {
                        assert_eq!(t.source_node_id, Some(NAVIGATION_NODE_ID));
                        poses.push((t.timestamp_us, decode::<TargetPose>(t.payload).unwrap()));
                    }
                    port::SUN_VECTOR => {
                        assert_eq!(t.source_node_id, Some(AOCS_NODE_ID));
                        suns.push((t.timestamp_us, decode::<SunVector>(t.payload).unwrap()));
                    }
                    other => panic!("unexpected subject {other}"),
                }
            }
        }
        assert!(
            can_times.windows(2).all(|w| w[0] < w[1]),
            "CAN times increase"
        );
        assert_eq!((poses.len(), suns.len()), (lines.len(), lines.len()));

        // UDP: one camera frame per line, after that line's telemetry and before the next.
        let reader = BufReader::new(std::fs::File::open(&udp_path).unwrap());
        let mut rx: CcsdsReassembler<Vec<u8>, 2> = CcsdsReassembler::new(vec![0; 2 << 20]);
        let mut frames = 0;
        let mut last_us = 0;
        for record in UdpRecordingReader::new(reader).unwrap() {
            let record = record.unwrap();
            assert_eq!(record.destination_port, options.frames_port);
            assert!(record.time_us > last_us || frames == 0 && last_us == 0);
            last_us = record.time_us;
            let Some(message) = rx.push(&record.payload, record.time_us).unwrap() else {
                continue;
            };
            assert_eq!(message.apid, port::CAMERA_FRAME);
            let k = frames;
            let line = &lines[k];
            let frame = decode::<CameraFrame>(message.payload).unwrap();
            let time_us = (line["time_s"].as_f64().unwrap() * 1e6).round() as u64;
            assert_eq!(
                frame.header.frame_id,
                line["index"].as_u64().unwrap() as u32
            );
            assert_eq!(frame.header.time_us, time_us);
            assert_eq!(frame.header.format, PixelFormat::Rgb8);
            let png = image::open(dataset.join(line["frame"].as_str().unwrap())).unwrap();
            assert_eq!(
                (
                    u32::from(frame.header.width),
                    u32::from(frame.header.height)
                ),
                (png.width(), png.height())
            );
            assert_eq!(frame.pixels, png.to_rgb8().as_raw().as_slice());
            let mask = image::open(dataset.join(line["mask"].as_str().unwrap())).unwrap();
            assert_eq!(frame.mask, Some(mask.to_luma8().as_raw().as_slice()));
            assert!(
                frame.mask.unwrap().iter().any(|&m| m != 0),
                "target in view"
            );

            // Telemetry for this frame: exact time, arrived before the frame's first packet,
            // and the previous frame's packets all arrived before it.
            let (pose_rx_us, pose) = poses[k];
            let (sun_rx_us, sun) = suns[k];
            assert!(pose_rx_us < message.timestamp_us && sun_rx_us < message.timestamp_us);
            if k + 1 < lines.len() {
                assert!(poses[k + 1].0 > last_us);
            }
            assert_eq!((pose.time_us, sun.time_us), (time_us, time_us));
            assert_close(
                pose.q_camera_from_target,
                f32s(&line["q_camera_from_target_wxyz"]),
                "q",
            );
            assert_eq!(
                pose.t_camera_from_target_m,
                f32s(&line["t_camera_from_target_m"])
            );
            assert_eq!(pose.position_sigma_m, 0.05);
            assert!(pose.valid && sun.valid);
            assert_close(sun.sun_body, f32s(&line["sun_servicer_body"]), "sun");
            frames += 1;
        }
        assert_eq!(frames, lines.len());
    }
    let _ = std::fs::remove_dir_all(&dataset);
}

#[test]
fn bad_datasets_and_options_are_clear_errors() {
    let dir = temp_dir("bad");
    std::fs::create_dir_all(&dir).unwrap();
    let options = BusFeedOptions::from_config(&ComponentConfig::default());
    let out = dir.join("bus");
    let err = write_bus_logs(&dir, &out, &options, 42).unwrap_err();
    assert!(matches!(err, BusFeedError::Io { .. }), "{err}");
    assert!(err.to_string().contains("telemetry.jsonl"), "{err}");

    let line = r#"{"index":0,"time_s":1.0,"frame":"frames/000000.png","mask":"","q_camera_from_target_wxyz":[1.0,0.0,0.0,0.0],"t_camera_from_target_m":[0.0,0.0,30.0],"sun_servicer_body":[0.0,0.0,1.0],"intrinsics":{"width":4,"height":2,"fx":4.0,"fy":4.0,"cx":2.0,"cy":1.0}}"#;
    let write = |text: &str| std::fs::write(dir.join("telemetry.jsonl"), text).unwrap();
    write(&line.replace("[0.0,0.0,1.0]", "[0.0,0.0,2.0]"));
    let err = write_bus_logs(&dir, &out, &options, 42).unwrap_err();
    assert!(
        err.to_string().contains("line 1") && err.to_string().contains("sun_servicer_body"),
        "{err}"
    );
    write(&line.replace("\"cx\":2.0", "\"cx\":5.0"));
    let err = write_bus_logs(&dir, &out, &options, 42).unwrap_err();
    assert!(
        err.to_string().contains("line 1") && err.to_string().contains("principal point"),
        "{err}"
    );
    write(&line.replace("\"time_s\":1.0", "\"time_s\":null"));
    assert!(write_bus_logs(&dir, &out, &options, 42)
        .unwrap_err()
        .to_string()
        .contains("time_s"));
    write(&format!("{line}\n{line}\n"));
    let err = write_bus_logs(&dir, &out, &options, 42).unwrap_err();
    assert!(
        err.to_string().contains("line 2") && err.to_string().contains("not after"),
        "{err}"
    );
    write(line);
    let err = write_bus_logs(&dir, &out, &options, 42).unwrap_err();
    assert!(
        matches!(err, BusFeedError::Image { .. }),
        "missing PNG: {err}"
    );
    let mut clash = options.clone();
    clash.aocs_node_id = 42;
    let err = write_bus_logs(&dir, &out, &clash, 42).unwrap_err();
    assert!(err.to_string().contains("component's own node-ID"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn replayed_logs_train_the_component() {
    let dataset = tiny_dataset("replay");
    let sinks: Vec<_> = (0..2)
        .map(|_| std::net::UdpSocket::bind("127.0.0.1:0").unwrap())
        .collect();
    let mut config = ComponentConfig::default();
    config.can.enabled = false;
    config.udp.frames_port = 0;
    config.udp.telemetry_port = 0;
    config.udp.health_to = sinks[0].local_addr().unwrap();
    config.udp.predictions_to = sinks[1].local_addr().unwrap();
    // A window of 2 fills with the tiny dataset, so training rounds run.
    config.training.window_size = 2;
    config.checkpoint.path = dataset.join("checkpoint.bin");
    config.checkpoint.period_s = 0;
    let out = dataset.join("bus");
    let options = BusFeedOptions::from_config(&config);
    let written = write_bus_logs(&dataset, &out, &options, config.node.node_id).unwrap();
    let learner = build_learner(&config, LearnerKind::NearestKeyframe).unwrap();
    let summary = run_replay(
        &config,
        learner,
        &bus_log_paths(&out),
        ReplaySpeed::AsFastAsPossible,
    )
    .await
    .unwrap();
    let n = u64::from(FRAMES);
    assert_eq!(summary.load.can_frames, written.can_frames);
    assert_eq!(summary.load.datagrams, written.frame_datagrams);
    assert_eq!(summary.load.skipped_lines, 0);
    let c = summary.counters;
    assert_eq!(c.bus.frames_received, n);
    assert_eq!(
        (
            c.bus.sun_decode_errors,
            c.bus.pose_decode_errors,
            c.bus.frame_decode_errors
        ),
        (0, 0, 0)
    );
    assert_eq!(c.bus.telemetry_out_of_order, 0);
    assert_eq!(c.can.transfers, 2 * n, "{:?}", c.can);
    assert_eq!(c.can.frames, written.can_frames);
    assert_eq!(c.udp.messages, n, "{:?}", c.udp);
    assert_eq!((c.sync.pose.stored_valid, c.sync.sun.stored_valid), (n, n));
    assert_eq!(c.sync.frames.synced, n, "{:?}", c.sync.frames);
    assert_eq!(summary.frames_used, n);
    assert!(summary.rounds > 0, "{summary:?}");
    let _ = std::fs::remove_dir_all(&dataset);
}

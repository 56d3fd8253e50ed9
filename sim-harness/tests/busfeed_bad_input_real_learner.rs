//! Bad input, floods and spoofed commands against the component with the real Sun-aware
//! learner (a small configuration), fed a ray-traced rendezvous over loopback UDP.
//!
//! The same nominal sequence is played twice into fresh components: once clean, once with
//! bad input between the nominal messages (garbage datagrams, far-future telemetry, a flood
//! of repeated telemetry, destructive commands from unauthorised sources). Checked: no
//! nominal frame is lost (each one synchronised, predicted and used), the bad input is
//! counted, the learner's predictions are bit-identical with and without it (so nothing of
//! it reached the model), and the model draws the target: its predictions of the frames
//! after the first rounds beat an all-black image on the target's own pixels by
//! `CLEAR_MARGIN_DB`.

use fsw_component::config::ComponentConfig;
use fsw_component::runtime::{build_learner, start, ComponentHandle, LearnerKind};
use interfaces::ccsds::{message_packets, CcsdsReassembler, PacketType};
use interfaces::messages::{
    decode, port, Command, CommandKind, PredictionSource, RenderedPrediction, SunVector, TargetPose,
};
use sim_harness::busfeed::{BusFeed, BusFeedOptions, FeedLine};
use sim_harness::dataset::{generate, GenerateOptions};
use sim_harness::experiment::ladder::CLEAR_MARGIN_DB;
use sim_harness::scenario::Scenario;
use std::collections::BTreeMap;
use std::net::{SocketAddr, UdpSocket};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

mod udp_step;
use udp_step::send_step;

const FRAMES: u32 = 16;
/// The first frames train nothing yet (the window fills at W = 4, then the hull start):
/// the model is judged on the predictions of the frames after these.
const JUDGED_FROM_FRAME: u32 = 8;
const WAIT: Duration = Duration::from_secs(60);

fn dataset() -> PathBuf {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../config/scenarios/quick.toml");
    let scenario = Scenario::load(&path)
        .unwrap()
        .with_overrides(Some(FRAMES), Some(24), Some(4))
        .unwrap();
    let dir = std::env::temp_dir().join(format!("sim-harness-badinput-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    generate(&scenario, &dir, GenerateOptions::default(), &mut |_| {}).unwrap();
    dir
}

fn config(dir: &Path, predictions: &UdpSocket, health: &UdpSocket) -> ComponentConfig {
    let mut config = ComponentConfig::default();
    config.can.enabled = false;
    config.udp.frames_port = 0;
    config.udp.telemetry_port = 0;
    config.udp.health_to = health.local_addr().unwrap();
    config.udp.predictions_to = predictions.local_addr().unwrap();
    config.training.window_size = 4;
    config.training.passes_per_round = 3;
    config.training.threads = 1;
    config.checkpoint.path = dir.join("checkpoint.bin");
    config.checkpoint.period_s = 0;
    config
}

/// Predictions of observed frames received on `socket` so far, by frame id (pixels).
fn drain_predictions(
    socket: &UdpSocket,
    rx: &mut CcsdsReassembler<Vec<u8>, 4>,
    out: &mut BTreeMap<u32, Vec<u8>>,
) {
    let mut buffer = vec![0u8; 2048];
    while let Ok((len, _)) = socket.recv_from(&mut buffer) {
        let Ok(Some(message)) = rx.push(&buffer[..len], 0) else {
            continue;
        };
        if message.apid != port::RENDERED_PREDICTION {
            continue;
        }
        let p = decode::<RenderedPrediction>(message.payload).expect("prediction decodes");
        if let PredictionSource::ObservedFrame { frame_id } = p.source {
            out.insert(frame_id, p.pixels.to_vec());
        }
    }
}

/// The spoofer's CCSDS packets for one message: its own sequence counts (far from the
/// nominal sender's, so they are not taken for duplicates of nominal packets).
struct Spoofer {
    socket: UdpSocket,
    next_count: u16,
}

impl Spoofer {
    fn send(&mut self, packet_type: PacketType, apid: u16, payload: &[u8], to: SocketAddr) {
        let packets = message_packets(packet_type, apid, payload, self.next_count, 1472).unwrap();
        for p in packets {
            self.socket.send_to(&p, to).unwrap();
            self.next_count = (self.next_count + 1) % 16384;
        }
    }
}

fn encoded<M: interfaces::messages::Message + serde::Serialize>(message: &M) -> Vec<u8> {
    let mut buffer = vec![0u8; 256];
    interfaces::messages::encode(message, &mut buffer)
        .unwrap()
        .to_vec()
}

/// Bad input between two nominal steps, in every form the component must survive.
fn bad_input(
    k: u32,
    spoofer: &mut Spoofer,
    handle: &ComponentHandle,
    line: &FeedLine,
    last_telemetry: &[Vec<u8>],
) {
    let (telemetry, frames) = (handle.telemetry_addr, handle.frames_addr);
    // Garbage of every length class, to both sockets.
    for (i, len) in [0usize, 1, 5, 6, 13, 200, 1472].into_iter().enumerate() {
        let bytes: Vec<u8> = (0..len)
            .map(|b| (b * 31 + i * 7 + k as usize) as u8)
            .collect();
        spoofer.socket.send_to(&bytes, telemetry).unwrap();
        spoofer.socket.send_to(&bytes, frames).unwrap();
    }
    // Far-future telemetry, valid and invalid: must never become the newest sample.
    let future_us = line.time_us + 365 * 86_400_000_000;
    let sun = SunVector {
        time_us: future_us,
        sun_body: line.sun_servicer_body,
        valid: k.is_multiple_of(2),
        eclipse: None,
    };
    let pose = TargetPose {
        time_us: future_us,
        q_camera_from_target: line.q_camera_from_target_wxyz,
        t_camera_from_target_m: line.t_camera_from_target_m,
        position_sigma_m: 0.01,
        attitude_sigma_rad: 0.001,
        valid: true,
    };
    spoofer.send(
        PacketType::Telemetry,
        port::SUN_VECTOR,
        &encoded(&sun),
        telemetry,
    );
    spoofer.send(
        PacketType::Telemetry,
        port::TARGET_POSE,
        &encoded(&pose),
        telemetry,
    );
    // A flood: the last nominal telemetry datagrams repeated 20 times.
    for _ in 0..20 {
        for d in last_telemetry {
            spoofer.socket.send_to(d, telemetry).unwrap();
        }
    }
    // Destructive commands from sources the default policy does not authorise: as
    // telemetry-type packets on the command socket, and as telecommands on the frame socket.
    let kinds = [
        CommandKind::Arm(CommandKind::RESET_MODEL),
        CommandKind::ResetModel,
        CommandKind::LoadCheckpoint,
    ];
    for (i, kind) in kinds.into_iter().enumerate() {
        let command = encoded(&Command {
            sequence: 1000 * k + i as u32,
            kind,
        });
        spoofer.send(PacketType::Telemetry, port::COMMAND, &command, telemetry);
        spoofer.send(PacketType::Telecommand, port::COMMAND, &command, frames);
    }
}

struct Run {
    predictions: BTreeMap<u32, Vec<u8>>,
    counters: fsw_component::inbound::CoreCounters,
    frames_used: u64,
}

async fn run(dataset: &Path, with_bad_input: bool) -> Run {
    let sinks: Vec<UdpSocket> = (0..2)
        .map(|_| UdpSocket::bind("127.0.0.1:0").unwrap())
        .collect();
    sinks[0]
        .set_read_timeout(Some(Duration::from_millis(20)))
        .unwrap();
    let config = config(dataset, &sinks[0], &sinks[1]);
    let learner = build_learner(&config, LearnerKind::SunAware).unwrap();
    let handle = start(&config, learner, None).await.unwrap();
    let options = BusFeedOptions::from_config(&config);
    let mut feed = BusFeed::open(dataset, options, config.node.node_id).unwrap();
    let sender = UdpSocket::bind("127.0.0.1:0").unwrap();
    let mut spoofer = Spoofer {
        socket: UdpSocket::bind("127.0.0.1:0").unwrap(),
        next_count: 9000,
    };
    let mut rx: CcsdsReassembler<Vec<u8>, 4> = CcsdsReassembler::new(vec![0; 4 << 20]);
    let mut predictions = BTreeMap::new();
    let mut last_telemetry: Vec<Vec<u8>> = Vec::new();
    for k in 0..feed.lines().len() {
        let step = feed.step(k).unwrap();
        send_step(&sender, &step, handle.telemetry_addr, handle.frames_addr).await;
        let id = step.line.index;
        let deadline = Instant::now() + WAIT;
        while !predictions.contains_key(&id) {
            assert!(Instant::now() < deadline, "frame {id} lost");
            drain_predictions(&sinks[0], &mut rx, &mut predictions);
            tokio::task::yield_now().await;
        }
        if with_bad_input {
            bad_input(id, &mut spoofer, &handle, &step.line, &last_telemetry);
        }
        last_telemetry = step.telemetry_datagrams.clone();
    }
    let n = feed.lines().len() as u64;
    let deadline = Instant::now() + WAIT;
    while handle.worker_snapshot().frames_processed < n {
        assert!(Instant::now() < deadline, "frames not processed");
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    let run = Run {
        predictions,
        counters: handle.counters(),
        frames_used: handle.worker_snapshot().frames_used,
    };
    handle.shutdown().await;
    run
}

fn load_rgb(path: &Path) -> Vec<u8> {
    image::open(path).unwrap().to_rgb8().into_raw()
}

fn load_mask(path: &Path) -> Vec<u8> {
    image::open(path).unwrap().to_luma8().into_raw()
}

/// Masked PSNR of `image` against `truth` (8-bit RGB), weights = mask / 255, dB.
fn masked_psnr_db(image: &[u8], truth: &[u8], mask: &[u8]) -> f64 {
    let (mut se, mut weight) = (0.0f64, 0.0f64);
    for (p, &m) in mask.iter().enumerate() {
        let w = f64::from(m) / 255.0;
        for c in 0..3 {
            let d = (f64::from(image[3 * p + c]) - f64::from(truth[3 * p + c])) / 255.0;
            se += w * d * d;
        }
        weight += 3.0 * w;
    }
    gs_core::loss::psnr_db_from_mse(se / weight)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_input_reaches_neither_the_real_learner_nor_costs_a_valid_message() {
    let dataset = dataset();
    let clean = run(&dataset, false).await;
    let attacked = run(&dataset, true).await;
    let n = u64::from(FRAMES);

    // No nominal frame lost: each synchronised, predicted and offered to the model.
    for r in [&clean, &attacked] {
        assert_eq!(r.predictions.len() as u64, n);
        assert_eq!(r.counters.bus.frames_received, n, "{:?}", r.counters.bus);
        assert_eq!(r.counters.sync.frames.synced, n, "{:?}", r.counters.sync);
    }
    assert_eq!(attacked.frames_used, clean.frames_used);
    // The bad input was seen and counted.
    let bus = &attacked.counters.bus;
    assert!(
        attacked.counters.udp.rejected_truncated + attacked.counters.udp.rejected_bad_version > 0,
        "{:?}",
        attacked.counters.udp
    );
    assert_eq!(bus.commands_unauthorised, 6 * n, "{bus:?}");
    assert_eq!(bus.commands_accepted, 0, "{bus:?}");
    assert!(bus.telemetry_time_out_of_bounds > 0, "{bus:?}");
    // Nothing of it reached the model: every prediction is bit-identical.
    assert_eq!(attacked.predictions, clean.predictions);

    // The model draws the target: after its first rounds it beats black on the target's
    // own pixels by the clear margin.
    let lines = sim_harness::busfeed::load_telemetry(&dataset).unwrap();
    let (mut model_db, mut black_db, mut judged) = (0.0, 0.0, 0);
    for line in lines.iter().filter(|l| l.index >= JUDGED_FROM_FRAME) {
        let Some(mask_path) = &line.mask_path else {
            panic!("the dataset has masks");
        };
        let mask = load_mask(mask_path);
        if mask.iter().all(|&m| m == 0) {
            continue;
        }
        let truth = load_rgb(&line.frame_path);
        let predicted = &clean.predictions[&line.index];
        model_db += masked_psnr_db(predicted, &truth, &mask);
        black_db += masked_psnr_db(&vec![0u8; truth.len()], &truth, &mask);
        judged += 1;
    }
    assert!(judged >= 4, "{judged} frames judged");
    let (model_db, black_db) = (model_db / judged as f64, black_db / judged as f64);
    eprintln!(
        "masked PSNR of the predictions of frames {JUDGED_FROM_FRAME}..{FRAMES}: model {model_db:.2} dB, black {black_db:.2} dB"
    );
    assert!(
        model_db > black_db + CLEAR_MARGIN_DB,
        "model {model_db:.2} dB vs black {black_db:.2} dB"
    );
    let _ = std::fs::remove_dir_all(&dataset);
}

//! End-to-end accuracy through the bus: the component (its runtime in-process, real UDP
//! sockets on loopback, the real Sun-aware learner) fed a short rendered rendezvous by the
//! simulator's bus feed ends with the same model, bit for bit, as gs-online's online trainer
//! run in-process on the same frames with the same settings, seed, thread count and
//! denormal mode; so it scores the same masked PSNR on the evaluation views.
//!
//! The reference takes the frames as the experiments (`table`) do: the scene rendered in
//! memory (`experiment::data`, byte-identical to the dataset's PNGs), images in [0, 1], masks
//! in {0, 1}. Its poses and Sun directions are the telemetry as the bus carries it (`f32`
//! on the wire, the simulator's telemetry being exact here: the scenario's sensor noise is
//! off), turned into a camera and a target-frame Sun with the ICD's conventions
//! (x_camera = q x_target + t; Sun from the servicer body through the camera mounting
//! into the camera, then into the target frame); the test first checks that these agree
//! with the renderer's own geometry to f32 rounding. It starts from the component's
//! configured start (random points, replaced by the visual hull carved when the window
//! first fills), as the component does.
//!
//! Compared bit for bit: every prediction the component published (rendered before
//! training on the frame), the trainer checkpoint (Gaussians, networks, optimiser, RNG)
//! and the online state (window, round counter, replay memory, counters) inside the
//! component's FSWSAL02 checkpoint, and the evaluation scores. A frame dropped or
//! reordered on the bus, or a camera, pose, Sun or mask convention that differs from the
//! reference, changes all of them.
//!
//! The same dataset as bus logs (`sim-harness buslogs`: telemetry as Cyphal/CAN FD transfers
//! in a candump log, frames in a UDP recording), with a SAVE_CHECKPOINT telecommand after
//! the last frame, replayed through the component (`fsw-component --replay`) writes the
//! same checkpoint file, byte for byte.

use fsw_component::config::ComponentConfig;
use fsw_component::hull_start;
use fsw_component::outbound::UdpFramer;
use fsw_component::recorder::{Recorder, CAN_FILE, UDP_FILE};
use fsw_component::runtime::{build_learner, run_replay, start, LearnerKind, ReplaySpeed};
use fsw_component::sunaware_learner::CHECKPOINT_MAGIC;
use glam::{DQuat, DVec3, Quat, Vec3};
use gs_core::fpmode;
use gs_core::sunaware::checkpoint;
use gs_core::Camera;
use gs_online::online::{Frame, Initialisation, OnlineConfig, OnlineTrainer};
use interfaces::ccsds::CcsdsReassembler;
use interfaces::messages::{
    decode, port, AckStatus, Command, CommandAck, CommandKind, PredictionSource,
    RenderedPrediction, SunVector, TargetPose,
};
use sim_harness::busfeed::{load_telemetry, write_bus_logs, BusFeed, BusFeedOptions};
use sim_harness::dataset::{generate, GenerateOptions};
use sim_harness::experiment::data::{render_scene, SceneData};
use sim_harness::experiment::evaluate::{camera_of, evaluate_model, intrinsics, sun_of};
use sim_harness::scenario::{NoiseConfig, Scenario};
use std::collections::BTreeMap;
use std::net::{SocketAddr, UdpSocket};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

mod udp_step;
use udp_step::send_step;

const FRAMES: u32 = 10;
const DOWNSAMPLE: u32 = 24;
const EVAL_VIEWS: u32 = 4;
const WAIT: Duration = Duration::from_secs(120);

fn scenario() -> Scenario {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../config/scenarios/quick.toml");
    let mut scenario = Scenario::load(&path)
        .unwrap()
        .with_overrides(Some(FRAMES), Some(DOWNSAMPLE), Some(EVAL_VIEWS))
        .unwrap();
    // Exact telemetry: the bus then differs from the renderer's geometry by f32 rounding
    // only, which the convention check below can bound tightly.
    scenario.noise = NoiseConfig::default();
    scenario
}

fn config(
    dir: &Path,
    scenario: &Scenario,
    predictions: SocketAddr,
    health: SocketAddr,
) -> ComponentConfig {
    let mut config = ComponentConfig::default();
    config.can.enabled = false;
    config.udp.frames_port = 0;
    config.udp.telemetry_port = 0;
    config.udp.health_to = health;
    config.udp.predictions_to = predictions;
    // The simulator's camera mounting (body from camera) as the component's camera from body.
    let [w, x, y, z] = scenario.camera.mounting_quaternion;
    config.camera.camera_from_body_wxyz = [w, -x, -y, -z];
    config.training.window_size = 4;
    config.training.passes_per_round = 3;
    config.training.threads = 1;
    config.model.initial_gaussians = 500;
    config.model.hull_resolution = 48;
    config.checkpoint.path = dir.join("checkpoint.bin");
    config.checkpoint.period_s = 0;
    config
}

/// What the component produced: predictions by frame id, and its checkpoint file.
struct BusRun {
    predictions: BTreeMap<u32, Vec<u8>>,
    checkpoint: Vec<u8>,
    /// Frames synchronised, and processed by the trainer thread.
    frames_synced: u64,
    frames_processed: u64,
}

fn drain(
    socket: &UdpSocket,
    rx: &mut CcsdsReassembler<Vec<u8>, 4>,
    run: &mut BusRun,
    acks: &mut Vec<CommandAck>,
) {
    let mut buffer = vec![0u8; 2048];
    while let Ok((len, _)) = socket.recv_from(&mut buffer) {
        let Ok(Some(message)) = rx.push(&buffer[..len], 0) else {
            continue;
        };
        match message.apid {
            port::RENDERED_PREDICTION => {
                let p: RenderedPrediction = decode(message.payload).expect("prediction decodes");
                if let PredictionSource::ObservedFrame { frame_id } = p.source {
                    run.predictions.insert(frame_id, p.pixels.to_vec());
                }
            }
            port::COMMAND_ACK => acks.push(decode(message.payload).expect("ack decodes")),
            _ => {}
        }
    }
}

/// Plays the dataset into a fresh component, one step after the previous frame's
/// prediction, then SAVE_CHECKPOINT (acknowledged after every frame was trained).
async fn run_component(dataset: &Path, config: &ComponentConfig, sinks: &[UdpSocket; 2]) -> BusRun {
    let learner = build_learner(config, LearnerKind::SunAware).unwrap();
    let handle = start(config, learner, None).await.unwrap();
    let mut feed = BusFeed::open(
        dataset,
        BusFeedOptions::from_config(config),
        config.node.node_id,
    )
    .unwrap();
    let sender = UdpSocket::bind("127.0.0.1:0").unwrap();
    let mut rx: CcsdsReassembler<Vec<u8>, 4> = CcsdsReassembler::new(vec![0; 4 << 20]);
    let mut acks = Vec::new();
    let mut run = BusRun {
        predictions: BTreeMap::new(),
        checkpoint: Vec::new(),
        frames_synced: 0,
        frames_processed: 0,
    };
    let wait = |what: String| {
        let deadline = Instant::now() + WAIT;
        move || assert!(Instant::now() < deadline, "timed out waiting for {what}")
    };
    for k in 0..feed.lines().len() {
        let step = feed.step(k).unwrap();
        send_step(&sender, &step, handle.telemetry_addr, handle.frames_addr).await;
        let id = step.line.index;
        let check = wait(format!("the prediction of frame {id}"));
        while !run.predictions.contains_key(&id) {
            check();
            for s in sinks {
                drain(s, &mut rx, &mut run, &mut acks);
            }
            tokio::task::yield_now().await;
        }
    }
    let mut framer = UdpFramer::default();
    let save = Command {
        sequence: 1,
        kind: CommandKind::SaveCheckpoint,
    };
    for d in framer.datagrams(&save).unwrap() {
        sender.send_to(&d, handle.telemetry_addr).unwrap();
    }
    let check = wait("the SAVE_CHECKPOINT acknowledgement".into());
    while !acks.iter().any(|a| a.sequence == Some(1)) {
        check();
        for s in sinks {
            drain(s, &mut rx, &mut run, &mut acks);
        }
        tokio::task::yield_now().await;
    }
    let ack = acks.iter().find(|a| a.sequence == Some(1)).unwrap();
    assert_eq!(ack.status, AckStatus::Ok, "{ack:?}");
    run.frames_synced = handle.counters().sync.frames.synced;
    run.frames_processed = handle.worker_snapshot().frames_processed;
    handle.shutdown().await;
    run.checkpoint = std::fs::read(&config.checkpoint.path).unwrap();
    run
}

/// The dataset as bus logs plus a SAVE_CHECKPOINT one second after the last frame,
/// replayed as fast as the trainer takes them; the checkpoint file it saved.
async fn run_replay_logs(dataset: &Path, config: &ComponentConfig, dir: &Path) -> Vec<u8> {
    let logs = dir.join("logs");
    let options = BusFeedOptions::from_config(config);
    let written = write_bus_logs(dataset, &logs, &options, config.node.node_id).unwrap();
    let save_dir = dir.join("save");
    let last_us = load_telemetry(dataset).unwrap().last().unwrap().time_us;
    {
        let mut recorder = Recorder::create(&save_dir, &options.can_interface).unwrap();
        let save = Command {
            sequence: 1,
            kind: CommandKind::SaveCheckpoint,
        };
        for d in UdpFramer::default().datagrams(&save).unwrap() {
            recorder.udp(last_us + 1_000_000, 15_300, config.udp.telemetry_port, &d);
        }
    }
    let mut config = config.clone();
    config.checkpoint.path = dir.join("checkpoint.bin");
    let learner = build_learner(&config, LearnerKind::SunAware).unwrap();
    let logs = [
        logs.join(CAN_FILE),
        logs.join(UDP_FILE),
        save_dir.join(UDP_FILE),
    ];
    let summary = run_replay(&config, learner, &logs, ReplaySpeed::AsFastAsPossible)
        .await
        .unwrap();
    assert_eq!(summary.counters.sync.frames.synced, u64::from(FRAMES));
    assert!(summary.load.can_frames > 0, "{written:?}");
    assert_eq!(summary.counters.bus.commands_accepted, 1);
    std::fs::read(&config.checkpoint.path).unwrap()
}

/// The camera and target-frame Sun of a bus step, by the ICD's conventions.
fn bus_geometry(
    scene: &SceneData,
    mounting_camera_from_body: DQuat,
    pose: &TargetPose,
    sun: &SunVector,
) -> (Camera, Vec3) {
    let [w, x, y, z] = pose.q_camera_from_target.map(f64::from);
    let q = DQuat::from_xyzw(x, y, z, w).normalize();
    let camera = Camera {
        intrinsics: intrinsics(&scene.intrinsics),
        rotation: Quat::from_xyzw(q.x as f32, q.y as f32, q.z as f32, q.w as f32),
        translation: DVec3::from_array(pose.t_camera_from_target_m.map(f64::from)).as_vec3(),
    };
    let sun_body = DVec3::from_array(sun.sun_body.map(f64::from));
    let sun_target = (q.inverse() * (mounting_camera_from_body * sun_body)).normalize();
    (camera, sun_target.as_vec3())
}

fn to_u8(v: f32) -> u8 {
    (v.clamp(0.0, 1.0) * 255.0).round() as u8
}

/// The reference: gs-online's trainer on the scene's frames, as the component is configured.
struct Reference {
    online: OnlineTrainer,
    predictions: BTreeMap<u32, Vec<u8>>,
    hull_carved: bool,
}

fn run_reference(dataset: &Path, scene: &SceneData, config: &ComponentConfig) -> Reference {
    let model = &config.model;
    // The component's own trainer settings (window, model, replay memory, rates).
    let online_config = OnlineConfig {
        // The component tests brightness only under a mask (`unlit_full_frame` off).
        unlit_full_frame: false,
        ..config.online_config().unwrap()
    };
    let backend = gs_core::engine::Backend::Cpu;
    let init = Initialisation::RandomSphere {
        count: model.initial_gaussians,
        centre: Vec3::ZERO,
        radius_m: model.target_radius_m,
        seed: model.seed,
    };
    let mut online =
        OnlineTrainer::new(online_config, &init, model.ball_scene_box().unwrap()).unwrap();
    online.trainer_mut().set_backend(&backend).unwrap();
    let [w, x, y, z] = config.camera.camera_from_body_wxyz;
    let mounting = DQuat::from_xyzw(x, y, z, w).normalize();
    // The same telemetry messages the bus feed sends.
    let mut feed = BusFeed::open(
        dataset,
        BusFeedOptions::from_config(config),
        config.node.node_id,
    )
    .unwrap();
    let mut predictions = BTreeMap::new();
    let mut hull_pending = true;
    let mut hull_carved = false;
    for (k, view) in scene.frames.iter().enumerate() {
        let step = feed.step(k).unwrap();
        assert_eq!(step.line.index, view.index);
        let (camera, sun_target) = bus_geometry(scene, mounting, &step.pose, &step.sun);
        // The bus conventions agree with the renderer's geometry to f32 rounding.
        let truth = camera_of(&scene.intrinsics, view);
        assert!(
            camera.rotation.angle_between(truth.rotation) < 1e-3
                && (camera.translation - truth.translation).length()
                    < 1e-4 * truth.translation.length(),
            "frame {k}: bus pose {camera:?}, rendered with {truth:?}"
        );
        assert!(
            (sun_target - sun_of(view)).length() < 1e-5,
            "frame {k}: Sun"
        );
        let rendered = online.predict(&camera, sun_target).unwrap();
        predictions.insert(
            view.index,
            rendered.image.iter().map(|&v| to_u8(v)).collect(),
        );
        online
            .offer(Frame {
                id: u64::from(view.index),
                time_s: step.line.time_us as f64 / 1e6,
                camera,
                sun_dir_target: sun_target,
                image: view.rgb_f32(),
                mask: Some(view.mask_f32()),
                eclipse: view.eclipse,
            })
            .unwrap();
        if hull_pending && online.round_due() {
            hull_pending = false;
            let keyframes: Vec<&Frame> = online
                .window()
                .keyframes()
                .iter()
                .map(|k| &k.payload)
                .collect();
            let start = hull_start::carve(&keyframes, model).expect("the hull carves");
            let init = Initialisation::SurfaceSamples {
                points: start.points,
                normals: None,
                colours: Some(start.colours),
            };
            online
                .restart_model(&init, start.scene_box, &backend)
                .unwrap();
            hull_carved = true;
        }
        online.run_round_if_due().unwrap();
    }
    Reference {
        online,
        predictions,
        hull_carved,
    }
}

/// The sections of a FSWSAL02 checkpoint: hull start pending, trainer bytes, online state.
fn sections(bytes: &[u8]) -> (u8, &[u8], &[u8]) {
    assert_eq!(&bytes[..8], CHECKPOINT_MAGIC);
    let word = |at: usize| u64::from_le_bytes(bytes[at..at + 8].try_into().unwrap()) as usize;
    let trainer_len = word(9);
    let trainer = &bytes[17..17 + trainer_len];
    let state_len = word(17 + trainer_len);
    let state_at = 25 + trainer_len;
    let state = &bytes[state_at..state_at + state_len];
    assert_eq!(
        state_at + state_len + 4,
        bytes.len(),
        "layout of {CHECKPOINT_MAGIC:?}"
    );
    (bytes[8], trainer, state)
}

fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("sim-harness-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_bus_trains_the_model_the_in_process_trainer_trains() {
    let scenario = scenario();
    let dataset = temp_dir("e2e-dataset");
    generate(&scenario, &dataset, GenerateOptions::default(), &mut |_| {}).unwrap();
    let scene = render_scene(&scenario, 16, &mut |_| {}).unwrap();
    assert_eq!(scene.frames.len() as u32, FRAMES);
    let out = temp_dir("e2e-component");
    let sinks = [0, 1].map(|_| {
        let s = UdpSocket::bind("127.0.0.1:0").unwrap();
        s.set_read_timeout(Some(Duration::from_millis(5))).unwrap();
        s
    });
    let config = config(
        &out,
        &scenario,
        sinks[0].local_addr().unwrap(),
        sinks[1].local_addr().unwrap(),
    );

    let started = Instant::now();
    let bus = run_component(&dataset, &config, &sinks).await;
    let bus_s = started.elapsed().as_secs_f64();
    // The reference on the component's trainer settings: one thread, its denormal mode.
    let mode = config.denormals().unwrap();
    let pool = fpmode::pool_builder(mode)
        .num_threads(config.training.threads)
        .build()
        .unwrap();
    let started = Instant::now();
    let reference = pool.install(|| {
        fpmode::set_for_current_thread(mode);
        run_reference(&dataset, &scene, &config)
    });
    let reference_s = started.elapsed().as_secs_f64();
    eprintln!("component over UDP {bus_s:.1} s, in-process reference {reference_s:.1} s");

    assert_eq!(bus.frames_synced, u64::from(FRAMES));
    assert_eq!(bus.frames_processed, u64::from(FRAMES));
    assert!(reference.hull_carved);
    assert!(
        reference.online.rounds() >= 3,
        "{} rounds",
        reference.online.rounds()
    );
    // Every prediction, rendered before training on its frame, is the reference's.
    assert_eq!(bus.predictions.len() as u32, FRAMES);
    for (id, pixels) in &reference.predictions {
        assert!(
            bus.predictions.get(id) == Some(pixels),
            "prediction of frame {id}"
        );
    }
    let (hull_pending, trainer, state) = sections(&bus.checkpoint);
    assert_eq!(hull_pending, 0, "the component carved its hull start");
    assert!(
        trainer == checkpoint::to_bytes(reference.online.trainer()).as_slice(),
        "the component's model differs from the in-process trainer's"
    );
    assert!(
        state == reference.online.state_bytes().as_slice(),
        "the component's window, rounds or counters differ from the in-process trainer's"
    );

    // Hence the same scores on the evaluation views.
    let component_model = checkpoint::from_bytes(trainer).unwrap();
    let (bus_eval, _) = evaluate_model(&component_model.model, &scene, 0).unwrap();
    let (reference_eval, _) = evaluate_model(&reference.online.trainer().model, &scene, 0).unwrap();
    eprintln!(
        "evaluation views: masked PSNR {:.3} dB (component) / {:.3} dB (in-process), PSNR {:.3} / {:.3} dB",
        bus_eval.masked_psnr_db, reference_eval.masked_psnr_db, bus_eval.psnr_db, reference_eval.psnr_db
    );
    assert!(bus_eval.masked_psnr_db.is_finite());
    assert_eq!(bus_eval, reference_eval);

    // The logged bus (telemetry on CAN FD) replayed: the same checkpoint file.
    let replay_dir = temp_dir("e2e-replay");
    let started = Instant::now();
    let replayed = run_replay_logs(&dataset, &config, &replay_dir).await;
    eprintln!(
        "replay of the bus logs {:.1} s",
        started.elapsed().as_secs_f64()
    );
    assert!(
        replayed == bus.checkpoint,
        "the replayed logs' checkpoint differs from the live bus run's"
    );
    for dir in [dataset, out, replay_dir] {
        std::fs::remove_dir_all(dir).unwrap();
    }
}

//! Exact resume through the whole component: the `fsw-component` binary with the real
//! Sun-aware learner, fed over loopback UDP, SIGKILLed after a checkpoint and restarted
//! from it (`[checkpoint] resume`), trains the same model, bit for bit, as one process that
//! ran every frame without stopping.
//!
//! Each process gets N (or M, or N + M) steps: pose and Sun telemetry stamped with the
//! frame's exposure time on the telemetry socket, then the 16x16 RGB frame (with mask and
//! its own camera model) on the frame socket; the next step waits for the frame's
//! prediction, so no frame can overtake another. SAVE_CHECKPOINT is acknowledged only after
//! every queued frame was trained (one FIFO for frames and commands), so the file then
//! holds the model of exactly the frames sent. The checkpoint (FSWSAL02: model, optimiser,
//! keyframe window, round counter, replay memory, counters) of the interrupted run must
//! equal the uninterrupted run's byte for byte, and so must the predictions the two
//! processes published for the last M frames.

use fsw_component::config::ComponentConfig;
use fsw_component::outbound::UdpFramer;
use fsw_component::sunaware_learner::CHECKPOINT_MAGIC;
use gs_core::Intrinsics;
use interfaces::ccsds::CcsdsReassembler;
use interfaces::messages::{
    decode, port, AckStatus, CameraFrame, CameraModel, Command, CommandAck, CommandKind,
    Distortion, FrameHeader, PixelFormat, PredictionSource, RenderedPrediction, SunVector,
    TargetPose,
};
use orbit_disc::{disc_frame, DiscFrame};
use std::collections::BTreeMap;
use std::io::{BufRead, BufReader};
use std::net::{SocketAddr, UdpSocket};
use std::path::{Path, PathBuf};
use std::process::{Child, Command as Process, Stdio};
use std::time::{Duration, Instant};

mod orbit_disc;

const SIDE: u16 = 16;
/// Frames before the kill, and after the restart.
const N: u32 = 6;
const M: u32 = 8;
const WAIT: Duration = Duration::from_secs(60);
const FIELD_OF_VIEW_RAD: f32 = 0.5;

fn intrinsics() -> Intrinsics {
    Intrinsics::from_fov_x(FIELD_OF_VIEW_RAD, u32::from(SIDE), u32::from(SIDE))
}

/// Exposure time of frame `k`: one second apart, from 1 s.
fn time_us(k: u32) -> u64 {
    u64::from(k + 1) * 1_000_000
}

/// Step `k`: telemetry and the frame's pixels and mask.
struct Step {
    pose: TargetPose,
    sun: SunVector,
    pixels: Vec<u8>,
    mask: Vec<u8>,
}

impl Step {
    fn frame(&self, k: u32) -> CameraFrame<'_> {
        let k_px = intrinsics();
        CameraFrame {
            header: FrameHeader {
                frame_id: k,
                time_us: time_us(k),
                width: SIDE,
                height: SIDE,
                format: PixelFormat::Rgb8,
            },
            mask: Some(&self.mask),
            pixels: &self.pixels,
            camera: Some(CameraModel {
                fx_px: k_px.fx,
                fy_px: k_px.fy,
                cx_px: k_px.cx,
                cy_px: k_px.cy,
                distortion: Distortion::None,
            }),
        }
    }
}

/// Step `k`: frame k of the disc orbit (`orbit_disc`); the Sun sent in the servicer body
/// frame (= camera frame: the configured mounting is the identity).
fn step(k: u32) -> Step {
    let DiscFrame {
        camera,
        sun_target,
        pixels,
        mask,
        ..
    } = disc_frame(k, SIDE, intrinsics());
    let q = camera.rotation;
    let sun_body = (q * sun_target).normalize();
    let pose = TargetPose {
        time_us: time_us(k),
        q_camera_from_target: [q.w, q.x, q.y, q.z],
        t_camera_from_target_m: camera.translation.to_array(),
        position_sigma_m: 0.01,
        attitude_sigma_rad: 0.001,
        valid: true,
    };
    let sun = SunVector {
        time_us: time_us(k),
        sun_body: sun_body.to_array(),
        valid: true,
        eclipse: Some(false),
    };
    Step {
        pose,
        sun,
        pixels,
        mask,
    }
}

/// A small model: the real learner with a hull start, W = 3, one trainer thread.
fn config(dir: &Path, health: SocketAddr, predictions: SocketAddr, resume: bool) -> String {
    let mut config = ComponentConfig::default();
    config.can.enabled = false;
    config.udp.frames_port = 0;
    config.udp.telemetry_port = 0;
    config.udp.health_to = health;
    config.udp.predictions_to = predictions;
    config.udp.receive_buffer_bytes = 0;
    config.camera.width_px = SIDE;
    config.camera.height_px = SIDE;
    let k = intrinsics();
    (config.camera.fx_px, config.camera.fy_px) = (k.fx, k.fy);
    (config.camera.cx_px, config.camera.cy_px) = (k.cx, k.cy);
    config.training.window_size = 3;
    config.training.min_view_angle_deg = 10.0;
    config.training.threads = 1;
    config.model.initial_gaussians = 60;
    config.model.hull_resolution = 16;
    config.model.target_radius_m = 2.0;
    config.checkpoint.path = dir.join("checkpoint.bin");
    config.checkpoint.period_s = 0;
    config.checkpoint.resume = resume;
    toml::to_string(&config).expect("the configuration serialises")
}

/// One `fsw-component` process and the test's ends of its sockets.
struct Component {
    child: Child,
    frames: SocketAddr,
    telemetry: SocketAddr,
}

impl Component {
    fn start(config_path: &Path) -> Self {
        let mut child = Process::new(env!("CARGO_BIN_EXE_fsw-component"))
            .args(["--config".as_ref(), config_path.as_os_str()])
            .stdout(Stdio::piped())
            .spawn()
            .expect("start fsw-component");
        // The binary prints its bound addresses once it listens.
        let mut line = String::new();
        BufReader::new(child.stdout.take().unwrap())
            .read_line(&mut line)
            .unwrap();
        let addr = |key: &str| -> SocketAddr {
            line.split_whitespace()
                .find_map(|w| w.strip_prefix(key))
                .unwrap_or_else(|| panic!("no {key} in {line:?}"))
                .parse()
                .unwrap()
        };
        Self {
            frames: addr("frames="),
            telemetry: addr("telemetry="),
            child,
        }
    }

    /// SIGKILL: no shutdown path runs.
    fn kill(mut self) {
        self.child.kill().unwrap();
        let status = self.child.wait().unwrap();
        assert!(!status.success(), "the component must have been killed");
    }
}

/// The test's side of the bus: one sender, the health and prediction sinks.
struct Bus {
    sender: UdpSocket,
    framer: UdpFramer,
    health: UdpSocket,
    predictions: UdpSocket,
    rx: CcsdsReassembler<Vec<u8>, 4>,
    acks: Vec<CommandAck>,
    /// Predictions of observed frames by frame id (pixels), this process's.
    predicted: BTreeMap<u32, Vec<u8>>,
    next_sequence: u32,
}

impl Bus {
    fn new() -> Self {
        let bind = || UdpSocket::bind("127.0.0.1:0").unwrap();
        let (health, predictions) = (bind(), bind());
        for s in [&health, &predictions] {
            s.set_read_timeout(Some(Duration::from_millis(5))).unwrap();
        }
        Self {
            sender: bind(),
            framer: UdpFramer::default(),
            health,
            predictions,
            rx: CcsdsReassembler::new(vec![0; 4 << 16]),
            acks: Vec::new(),
            predicted: BTreeMap::new(),
            next_sequence: 1,
        }
    }

    fn send<M: interfaces::messages::Message + serde::Serialize>(&mut self, m: &M, to: SocketAddr) {
        for d in self.framer.datagrams(m).unwrap() {
            self.sender.send_to(&d, to).unwrap();
        }
    }

    fn drain(&mut self) {
        let mut buffer = vec![0u8; 2048];
        for socket in [&self.health, &self.predictions] {
            while let Ok((len, _)) = socket.recv_from(&mut buffer) {
                let Ok(Some(message)) = self.rx.push(&buffer[..len], 0) else {
                    continue;
                };
                match message.apid {
                    port::COMMAND_ACK => self.acks.push(decode(message.payload).unwrap()),
                    port::RENDERED_PREDICTION => {
                        let p: RenderedPrediction = decode(message.payload).unwrap();
                        if let PredictionSource::ObservedFrame { frame_id } = p.source {
                            self.predicted.insert(frame_id, p.pixels.to_vec());
                        }
                    }
                    _ => {}
                }
            }
        }
    }

    fn wait(&mut self, what: &str, done: impl Fn(&Self) -> bool) {
        let deadline = Instant::now() + WAIT;
        while !done(self) {
            assert!(Instant::now() < deadline, "timed out waiting for {what}");
            self.drain();
        }
    }

    /// Steps `frames` into `component`, each after the previous one's prediction.
    fn feed(&mut self, component: &Component, frames: std::ops::Range<u32>) {
        for k in frames {
            let step = step(k);
            self.send(&step.pose, component.telemetry);
            self.send(&step.sun, component.telemetry);
            // Telemetry and frames use different sockets: give the telemetry a head start
            // (a frame that still overtakes it waits `sync.max_wait_ms` for it).
            std::thread::sleep(Duration::from_millis(20));
            self.send(&step.frame(k), component.frames);
            self.wait(&format!("the prediction of frame {k}"), |b| {
                b.predicted.contains_key(&k)
            });
        }
    }

    /// SAVE_CHECKPOINT, acknowledged OK (after every frame sent before it was trained).
    fn save(&mut self, component: &Component) {
        let sequence = self.next_sequence;
        self.next_sequence += 1;
        let command = Command {
            sequence,
            kind: CommandKind::SaveCheckpoint,
        };
        self.send(&command, component.telemetry);
        self.wait("the SAVE_CHECKPOINT acknowledgement", |b| {
            b.acks.iter().any(|a| a.sequence == Some(sequence))
        });
        let ack = self.acks.iter().find(|a| a.sequence == Some(sequence));
        assert_eq!(ack.unwrap().status, AckStatus::Ok, "{ack:?}");
    }
}

fn fresh_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("fsw-resume-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn write_config(dir: &Path, bus: &Bus, resume: bool) -> PathBuf {
    let path = dir.join(if resume { "resume.toml" } else { "start.toml" });
    let text = config(
        dir,
        bus.health.local_addr().unwrap(),
        bus.predictions.local_addr().unwrap(),
        resume,
    );
    std::fs::write(&path, text).unwrap();
    path
}

#[test]
fn a_component_killed_after_its_checkpoint_resumes_bit_for_bit() {
    // Uninterrupted: N + M frames in one process.
    let whole_dir = fresh_dir("whole");
    let mut whole_bus = Bus::new();
    let whole = Component::start(&write_config(&whole_dir, &whole_bus, false));
    whole_bus.feed(&whole, 0..N + M);
    whole_bus.save(&whole);
    whole.kill();
    let reference = std::fs::read(whole_dir.join("checkpoint.bin")).unwrap();
    assert_eq!(&reference[..8], CHECKPOINT_MAGIC);

    // Interrupted: N frames, checkpoint, SIGKILL; a new process resumes and gets M more.
    let split_dir = fresh_dir("split");
    let mut first_bus = Bus::new();
    let first = Component::start(&write_config(&split_dir, &first_bus, false));
    first_bus.feed(&first, 0..N);
    first_bus.save(&first);
    first.kill();
    let at_kill = std::fs::read(split_dir.join("checkpoint.bin")).unwrap();
    assert!(
        at_kill != reference,
        "N frames must not already give the final model"
    );
    let mut second_bus = Bus::new();
    let second = Component::start(&write_config(&split_dir, &second_bus, true));
    second_bus.feed(&second, N..N + M);
    second_bus.save(&second);
    second.kill();
    let resumed = std::fs::read(split_dir.join("checkpoint.bin")).unwrap();

    // The processes trained: the window and round counter moved on after the resume.
    assert!(resumed != at_kill, "the resumed process trained nothing");
    assert_eq!(resumed.len(), reference.len());
    assert!(
        resumed == reference,
        "the resumed component's checkpoint differs from the uninterrupted one's"
    );
    for k in N..N + M {
        assert_eq!(
            second_bus.predicted.get(&k),
            whole_bus.predicted.get(&k),
            "prediction of frame {k}"
        );
    }
    for dir in [whole_dir, split_dir] {
        std::fs::remove_dir_all(dir).unwrap();
    }
}

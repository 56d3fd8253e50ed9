//! Unit tests of the trainer thread: queues, checkpoints, denormal mode, supervision.

use super::*;
use crate::learner::PredictedImage;
use crate::nearest_learner::NearestKeyframeLearner;
use gs_online::keyframe::WindowConfig;

fn limits() -> QueueLimits {
    QueueLimits {
        frames: 2,
        commands: 1,
        predictions: 2,
    }
}

/// A worker over `learner` with checkpoints in `dir` (none periodic) and a 60 s round
/// deadline.
fn start_worker(
    learner: Box<dyn Learner>,
    dir: &std::path::Path,
    threads: usize,
    mode: DenormalMode,
) -> Worker {
    let checkpoints = CheckpointSettings {
        path: dir.join("ckpt.bin"),
        period: None,
    };
    Worker::start(
        learner,
        limits(),
        checkpoints,
        threads,
        mode,
        Duration::from_secs(60),
    )
    .unwrap()
}

#[test]
fn full_queues_drop_oldest_frames_and_refuse_commands() {
    let shared = WorkerShared {
        limits: limits(),
        queues: Mutex::new(Queues::default()),
        work_ready: Condvar::new(),
        snapshot: Mutex::new(WorkerSnapshot::default()),
        job_started: Mutex::new(None),
        round_deadline: Duration::from_secs(1),
        output_ready: tokio::sync::Notify::new(),
    };
    let job = |id| CommandJob {
        sequence: id,
        opcode: 2,
        command: ModelCommand::ResetModel,
    };
    assert!(shared.push_command(job(1)).is_ok());
    assert_eq!(shared.push_command(job(2)).unwrap_err().sequence, 2);
    for i in 0..3 {
        shared.publish_prediction(Prediction {
            header: FrameHeader {
                frame_id: i,
                time_us: 0,
                width: 1,
                height: 1,
                format: PixelFormat::Gray8,
            },
            source: PredictionSource::Command { sequence: i },
            q_camera_from_target: [1.0, 0.0, 0.0, 0.0],
            t_camera_from_target_m: [0.0; 3],
            sun_target: [0.0, 0.0, 1.0],
            psnr_db: None,
            ssim: None,
            pixels: vec![0],
        });
    }
    let ids: Vec<u32> = shared
        .take_predictions()
        .iter()
        .map(|p| p.header.frame_id)
        .collect();
    assert_eq!(ids, vec![1, 2], "the oldest prediction is the one dropped");
    assert_eq!(shared.depths().predictions_dropped, 1);
}

#[test]
fn finish_drains_queued_commands() {
    let learner = NearestKeyframeLearner::new(WindowConfig::default()).expect("default window");
    let dir = std::env::temp_dir().join(format!("fsw-worker-{}", std::process::id()));
    let worker = start_worker(Box::new(learner), &dir, 1, DenormalMode::FlushToZero);
    let shared = Arc::clone(&worker.shared);
    shared
        .push_command(CommandJob {
            sequence: 7,
            opcode: 3,
            command: ModelCommand::SaveCheckpoint,
        })
        .unwrap();
    worker.finish();
    let notices = shared.take_notices();
    assert!(notices.contains(&Notice::Ack(CommandAck {
        sequence: Some(7),
        opcode: Some(3),
        status: AckStatus::Ok,
        detail: 0
    })));
    assert!(dir.join("ckpt.bin").exists());
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The baseline learner, noting on `save` the denormal mode of the thread it runs on
/// and of every worker of the pool it runs in.
struct ModeProbe {
    inner: NearestKeyframeLearner,
    seen: Arc<Mutex<Vec<DenormalMode>>>,
}

impl Learner for ModeProbe {
    fn offer(&mut self, frame: &ObservedFrame) -> OfferResult {
        self.inner.offer(frame)
    }
    fn run_round_if_due(&mut self) -> Result<Option<RoundSummary>, LearnerError> {
        self.inner.run_round_if_due()
    }
    fn predict(&self, view: &ViewRequest) -> Result<PredictedImage, LearnerError> {
        self.inner.predict(view)
    }
    fn reset(&mut self) -> Result<(), LearnerError> {
        self.inner.reset()
    }
    fn save(&self) -> Vec<u8> {
        let mut seen = lock(&self.seen);
        seen.push(fpmode::current());
        seen.extend(rayon::broadcast(|_| fpmode::current()));
        self.inner.save()
    }
    fn load(&mut self, bytes: &[u8]) -> Result<(), LearnerError> {
        self.inner.load(bytes)
    }
    fn inspect(&self, bytes: &[u8]) -> Result<u64, LearnerError> {
        self.inner.inspect(bytes)
    }
    fn stats(&self) -> LearnerStats {
        self.inner.stats()
    }
}

#[test]
fn the_model_runs_in_the_configured_denormal_mode() {
    let dir = std::env::temp_dir().join(format!("fsw-worker-fp-{}", std::process::id()));
    for mode in [DenormalMode::Ieee, DenormalMode::FlushToZero] {
        let seen = Arc::new(Mutex::new(Vec::new()));
        let probe = ModeProbe {
            inner: NearestKeyframeLearner::new(WindowConfig::default()).expect("default window"),
            seen: Arc::clone(&seen),
        };
        let worker = start_worker(Box::new(probe), &dir, 2, mode);
        let save = CommandJob {
            sequence: 1,
            opcode: 3,
            command: ModelCommand::SaveCheckpoint,
        };
        worker.shared.push_command(save).unwrap();
        worker.finish();
        let seen = lock(&seen).clone();
        assert_eq!(seen.len(), 3, "the model's thread and both pool workers");
        if fpmode::is_supported() {
            assert!(seen.iter().all(|&m| m == mode), "{mode}: {seen:?}");
        }
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A learner that counts the frames offered to it as rounds and is slow to report its
/// events (the worker asks for them after every job, before it used to refresh the
/// learner's figures in the snapshot).
struct SlowReporter {
    offered: u32,
}

impl Learner for SlowReporter {
    fn offer(&mut self, _frame: &ObservedFrame) -> OfferResult {
        self.offered += 1;
        OfferResult::Added
    }
    fn run_round_if_due(&mut self) -> Result<Option<RoundSummary>, LearnerError> {
        Ok(None)
    }
    fn predict(&self, _view: &ViewRequest) -> Result<PredictedImage, LearnerError> {
        Err(LearnerError::NothingToRender)
    }
    fn reset(&mut self) -> Result<(), LearnerError> {
        self.offered = 0;
        Ok(())
    }
    fn save(&self) -> Vec<u8> {
        Vec::new()
    }
    fn load(&mut self, _bytes: &[u8]) -> Result<(), LearnerError> {
        Ok(())
    }
    fn inspect(&self, _bytes: &[u8]) -> Result<u64, LearnerError> {
        Ok(0)
    }
    fn stats(&self) -> LearnerStats {
        LearnerStats {
            rounds: self.offered,
            ..LearnerStats::default()
        }
    }
    fn take_events(&mut self) -> Vec<EventKind> {
        std::thread::sleep(Duration::from_millis(300));
        Vec::new()
    }
}

#[test]
fn a_processed_frame_and_the_learner_figures_it_changed_are_seen_together() {
    let dir = std::env::temp_dir().join(format!("fsw-worker-snap-{}", std::process::id()));
    let reporter = Box::new(SlowReporter { offered: 0 });
    let worker = start_worker(reporter, &dir, 1, DenormalMode::FlushToZero);
    let shared = Arc::clone(&worker.shared);
    let view = glam::DVec3::new(0.0, 0.0, -1.0);
    let frame = ObservedFrame {
        frame_id: 1,
        time_us: 1_000_000,
        width: 4,
        height: 2,
        format: PixelFormat::Rgb8,
        pixels: vec![100; 24],
        mask: None,
        camera: gs_core::Intrinsics::from_fov_x(0.6, 4, 2),
        telemetry: crate::sync::SyncedTelemetry {
            time_us: 1_000_000,
            camera_from_target: glam::DQuat::IDENTITY,
            target_in_camera_m: -view * 10.0,
            pose_quality: 1.0,
            sun_in_body: glam::DVec3::Z,
            sun_in_camera: glam::DVec3::Z,
            sun_in_target: glam::DVec3::Z,
            view_in_target: view,
            range_m: 10.0,
            eclipse: false,
        },
    };
    assert!(!shared.push_frame(FrameJob {
        frame,
        usage: FrameUse::PredictAndTrain,
    }));
    let deadline = Instant::now() + Duration::from_secs(10);
    let snapshot = loop {
        let s = *lock(&shared.snapshot);
        if s.frames_processed >= 1 {
            break s;
        }
        assert!(Instant::now() < deadline, "the frame was not processed");
        std::thread::sleep(Duration::from_millis(1));
    };
    assert_eq!(
        snapshot.learner.rounds, 1,
        "frames_processed moved before the learner's figures"
    );
    worker.finish();
    let _ = std::fs::remove_dir_all(&dir);
}

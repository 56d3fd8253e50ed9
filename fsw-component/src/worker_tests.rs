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
    let worker = Worker::start(
        Box::new(learner),
        limits(),
        CheckpointSettings {
            path: dir.join("ckpt.bin"),
            period: None,
        },
        1,
        DenormalMode::FlushToZero,
        Duration::from_secs(60),
    )
    .unwrap();
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
        let checkpoints = CheckpointSettings {
            path: dir.join("ckpt.bin"),
            period: None,
        };
        let worker = Worker::start(
            Box::new(probe),
            limits(),
            checkpoints,
            2,
            mode,
            Duration::from_secs(60),
        )
        .unwrap();
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

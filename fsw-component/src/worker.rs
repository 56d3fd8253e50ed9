//! The trainer thread and the bounded queues between it and the bus side.
//!
//! The bus side only ever takes the queue locks for a push or a snapshot (never held while
//! the model works), so a training round cannot stall receiving, commands or health.
//! Queues and their drop policies:
//! - frames in (synchronised frames): bounded, the oldest is dropped and counted when full;
//! - commands in (model commands: reset, save, load, render): bounded, a full queue refuses
//!   the command (the bus side acknowledges BUSY);
//! - predictions out: bounded, the oldest is dropped and counted when full;
//! - acknowledgements and events out: one per command or model event, so bounded by the
//!   command queue and the frame rate.
//!
//! Order: frames and model commands run in arrival order (one FIFO; the capacities are
//! counted per kind), so a SAVE_CHECKPOINT after a frame saves a model that has seen that
//! frame, live and on replay alike. For each frame the worker first
//! renders the prediction at the frame's pose and Sun (before training on it), then offers
//! the frame and runs a round if one is due; the rounds a sequence of frames triggers are
//! therefore a function of that sequence alone (replay equals live). The model's parallel
//! work runs on the worker's own rayon pool of `training.threads` threads, never on the
//! bus side's threads, and a fixed count keeps results bit-identical. The trainer thread
//! and every pool worker run in `training.denormals`' mode (`gs_core::fpmode`), set as
//! each starts: the bus side's threads keep IEEE arithmetic.
//!
//! Supervision: every job runs under `catch_unwind`. A panic becomes an `Internal` event
//! (`TRAINER_PANICKED`), a [`Notice::TrainerFault`] (the bus side leaves Train while the
//! learner restarts), an EXECUTION_ERROR ack for a command that was running, and a restart:
//! the learner is reset and loaded from the newest usable checkpoint, then
//! [`Notice::TrainerRestored`]. After `MAX_CONSECUTIVE_PANICS` panics with no job
//! completing in between, or a failed restart, the fault notice says the trainer gave up.
//! A watchdog (`WorkerShared::overdue_job`, polled by the bus side) reports a job that runs
//! past the round deadline once per job. Learner errors (a refused frame, a failed round,
//! non-finite steps) become events, never log lines.

use crate::learner::{
    Learner, LearnerError, LearnerStats, ObservedFrame, OfferResult, RoundSummary, ViewRequest,
};
use crate::model_store::{LoadOutcome, ModelStore, SaveOutcome};
use gs_core::fpmode::{self, DenormalMode};
use gs_online::imagemetrics;
use interfaces::messages::{
    event_detail, AckStatus, CommandAck, ErrorCode, EventKind, FrameHeader, PixelFormat,
    PredictionSource,
};
use std::collections::VecDeque;
use std::panic::{self, AssertUnwindSafe};
use std::path::PathBuf;
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// What to do with a synchronised frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FrameUse {
    /// Render the prediction, then train on the frame.
    PredictAndTrain,
    /// Render the prediction only.
    PredictOnly,
}

#[derive(Clone, Debug)]
pub struct FrameJob {
    pub frame: ObservedFrame,
    pub usage: FrameUse,
}

/// Commands that need the model.
#[derive(Clone, Debug)]
pub(crate) enum ModelCommand {
    ResetModel,
    SaveCheckpoint,
    LoadCheckpoint,
    Render(ViewRequest),
}

#[derive(Clone, Debug)]
pub(crate) struct CommandJob {
    pub sequence: u32,
    pub opcode: u32,
    pub command: ModelCommand,
}

/// A rendered prediction ready to publish (owned form of `RenderedPrediction`).
#[derive(Clone, Debug, PartialEq)]
pub struct Prediction {
    pub header: FrameHeader,
    pub source: PredictionSource,
    pub q_camera_from_target: [f32; 4],
    pub t_camera_from_target_m: [f32; 3],
    pub sun_target: [f32; 3],
    pub psnr_db: Option<f32>,
    pub ssim: Option<f32>,
    pub pixels: Vec<u8>,
}

/// Panics in a row (no job completing in between) after which the trainer gives up.
pub(crate) const MAX_CONSECUTIVE_PANICS: u32 = 3;

/// Acknowledgements, events and supervision notices from the worker.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Notice {
    Ack(CommandAck),
    Event(EventKind),
    /// The trainer panicked and its learner is being restarted; `gave_up` when it will not
    /// train again until commanded.
    TrainerFault {
        gave_up: bool,
    },
    /// The learner was restarted (from the newest usable checkpoint, or afresh).
    TrainerRestored,
}

/// Figures the worker publishes for health reports.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct WorkerSnapshot {
    pub learner: LearnerStats,
    pub frames_used: u64,
    pub frames_processed: u64,
    pub predictions_rendered: u64,
    pub predictions_unavailable: u64,
    pub last_round: Option<RoundSummary>,
    pub last_prediction_psnr_db: Option<f32>,
    pub checkpoints_saved: u64,
    /// Saves refused (fewer rounds than on disk, or bytes the model's reader refuses).
    pub checkpoints_refused: u64,
    /// Learner restarts after a panic.
    pub trainer_restarts: u64,
    /// Jobs that ran past the round deadline.
    pub deadline_misses: u64,
    /// True while the worker runs a job (a frame or a command).
    pub busy: bool,
}

#[derive(Default)]
struct Queues {
    /// Frames and commands in arrival order.
    jobs: VecDeque<Job>,
    frames: usize,
    commands: usize,
    predictions: VecDeque<Prediction>,
    notices: VecDeque<Notice>,
    frames_dropped: u64,
    predictions_dropped: u64,
    shutdown: bool,
}

/// Queue capacities.
#[derive(Clone, Copy, Debug)]
pub struct QueueLimits {
    pub frames: usize,
    pub commands: usize,
    pub predictions: usize,
}

/// State shared between the bus side and the worker thread.
pub struct WorkerShared {
    limits: QueueLimits,
    queues: Mutex<Queues>,
    work_ready: Condvar,
    snapshot: Mutex<WorkerSnapshot>,
    /// The running job's start, and whether the watchdog has reported it.
    job_started: Mutex<Option<(Instant, bool)>>,
    round_deadline: Duration,
    /// Wakes the bus side when predictions or notices are waiting.
    pub output_ready: tokio::sync::Notify,
}

fn lock<T>(mutex: &Mutex<T>) -> MutexGuard<'_, T> {
    // A panic elsewhere must not take the bus side down with it: keep using the data.
    mutex
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// Queue depths and drop counts, for health.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct QueueDepths {
    pub frames: usize,
    pub commands: usize,
    pub predictions: usize,
    pub frames_dropped: u64,
    pub predictions_dropped: u64,
}

impl WorkerShared {
    /// Empty queues with these limits. [`Worker::start`] builds one for its thread; the bus
    /// core alone (fuzzing, tests) can run on one that no thread drains, since every queue
    /// is bounded.
    pub fn new(limits: QueueLimits, learner: LearnerStats, round_deadline: Duration) -> Self {
        Self {
            limits,
            queues: Mutex::new(Queues::default()),
            work_ready: Condvar::new(),
            snapshot: Mutex::new(WorkerSnapshot {
                learner,
                ..WorkerSnapshot::default()
            }),
            job_started: Mutex::new(None),
            round_deadline,
            output_ready: tokio::sync::Notify::new(),
        }
    }

    /// Queues a frame; returns true when the oldest queued frame was dropped to make room.
    pub fn push_frame(&self, job: FrameJob) -> bool {
        let mut q = lock(&self.queues);
        let dropped = q.frames >= self.limits.frames;
        if dropped {
            if let Some(oldest) = q.jobs.iter().position(|j| matches!(j, Job::Frame(_))) {
                q.jobs.remove(oldest);
                q.frames -= 1;
            }
            q.frames_dropped += 1;
        }
        q.jobs.push_back(Job::Frame(job));
        q.frames += 1;
        drop(q);
        self.work_ready.notify_one();
        dropped
    }

    /// Queues a model command; `Err(job)` when the queue is full (acknowledge BUSY).
    pub(crate) fn push_command(&self, job: CommandJob) -> Result<(), CommandJob> {
        let mut q = lock(&self.queues);
        if q.commands >= self.limits.commands {
            return Err(job);
        }
        q.jobs.push_back(Job::Command(job));
        q.commands += 1;
        drop(q);
        self.work_ready.notify_one();
        Ok(())
    }

    pub fn has_room(&self) -> bool {
        let q = lock(&self.queues);
        q.frames < self.limits.frames && q.commands < self.limits.commands
    }

    /// True when nothing is queued and the worker is not running a job.
    pub(crate) fn is_idle(&self) -> bool {
        let q = lock(&self.queues);
        q.jobs.is_empty() && !lock(&self.snapshot).busy
    }

    pub fn take_predictions(&self) -> Vec<Prediction> {
        lock(&self.queues).predictions.drain(..).collect()
    }

    pub fn take_notices(&self) -> Vec<Notice> {
        lock(&self.queues).notices.drain(..).collect()
    }

    pub fn depths(&self) -> QueueDepths {
        let q = lock(&self.queues);
        QueueDepths {
            frames: q.frames,
            commands: q.commands,
            predictions: q.predictions.len(),
            frames_dropped: q.frames_dropped,
            predictions_dropped: q.predictions_dropped,
        }
    }

    pub fn snapshot(&self) -> WorkerSnapshot {
        *lock(&self.snapshot)
    }

    /// The watchdog: true once for a job that has run past the round deadline (the bus
    /// side polls it at least every housekeeping tick and sends the event).
    pub(crate) fn overdue_job(&self) -> bool {
        let mut started = lock(&self.job_started);
        match started.as_mut() {
            Some((at, reported)) if !*reported && at.elapsed() > self.round_deadline => {
                *reported = true;
                drop(started);
                lock(&self.snapshot).deadline_misses += 1;
                true
            }
            _ => false,
        }
    }

    /// RESET_COUNTERS: zero the worker-side counters (model figures stay).
    pub(crate) fn reset_counters(&self) {
        let mut q = lock(&self.queues);
        q.frames_dropped = 0;
        q.predictions_dropped = 0;
        drop(q);
        let mut s = lock(&self.snapshot);
        s.frames_used = 0;
        s.frames_processed = 0;
        s.predictions_rendered = 0;
        s.predictions_unavailable = 0;
        s.checkpoints_saved = 0;
    }

    fn publish_prediction(&self, prediction: Prediction) {
        let mut q = lock(&self.queues);
        if q.predictions.len() >= self.limits.predictions {
            q.predictions.pop_front();
            q.predictions_dropped += 1;
        }
        q.predictions.push_back(prediction);
        drop(q);
        self.output_ready.notify_one();
    }

    fn notice(&self, notice: Notice) {
        lock(&self.queues).notices.push_back(notice);
        self.output_ready.notify_one();
    }
}

/// Checkpoint settings of the worker (the slots are `path` and `path.prev`).
#[derive(Clone, Debug)]
pub struct CheckpointSettings {
    pub path: PathBuf,
    /// None: no periodic checkpoints.
    pub period: Option<Duration>,
}

/// The running trainer thread.
pub struct Worker {
    pub shared: Arc<WorkerShared>,
    thread: Option<JoinHandle<()>>,
}

enum Job {
    Command(CommandJob),
    Frame(FrameJob),
}

impl Worker {
    /// Starts the thread that owns `learner`; the model's parallel work runs on its own pool
    /// of `threads` threads (results are bit-identical for a given thread count and
    /// `denormals` mode, which the thread and the pool's workers set as they start). A job
    /// running longer than `round_deadline` is reported by `WorkerShared::overdue_job`.
    pub fn start(
        learner: Box<dyn Learner>,
        limits: QueueLimits,
        checkpoints: CheckpointSettings,
        threads: usize,
        denormals: DenormalMode,
        round_deadline: Duration,
    ) -> std::io::Result<Self> {
        let pool = fpmode::pool_builder(denormals)
            .num_threads(threads.max(1))
            .thread_name(|i| format!("trainer-{i}"))
            .build()
            .map_err(std::io::Error::other)?;
        let shared = Arc::new(WorkerShared::new(limits, learner.stats(), round_deadline));
        let thread_shared = Arc::clone(&shared);
        let thread = std::thread::Builder::new()
            .name("trainer".into())
            .spawn(move || {
                fpmode::set_for_current_thread(denormals);
                pool.install(|| run(learner, &thread_shared, &checkpoints));
            })?;
        Ok(Self {
            shared,
            thread: Some(thread),
        })
    }

    /// Lets the worker finish every queued job, then stops it.
    pub fn finish(mut self) {
        self.stop();
    }

    fn stop(&mut self) {
        lock(&self.shared.queues).shutdown = true;
        self.shared.work_ready.notify_all();
        if let Some(thread) = self.thread.take() {
            // A panicked worker already lost its model; nothing more to clean up.
            let _ = thread.join();
        }
    }
}

impl Drop for Worker {
    fn drop(&mut self) {
        self.stop();
    }
}

fn next_job(shared: &WorkerShared, wait: Duration) -> Option<Option<Job>> {
    let mut q = lock(&shared.queues);
    if q.jobs.is_empty() {
        if q.shutdown {
            return None;
        }
        q = shared
            .work_ready
            .wait_timeout(q, wait)
            .map_or_else(|poisoned| poisoned.into_inner().0, |(guard, _)| guard);
    }
    let job = q.jobs.pop_front();
    match &job {
        Some(Job::Frame(_)) => q.frames -= 1,
        Some(Job::Command(_)) => q.commands -= 1,
        None => {}
    }
    if job.is_some() {
        // Set while the queue lock is held, so `is_idle` never sees an empty queue and an
        // idle worker while a job is in flight.
        lock(&shared.snapshot).busy = true;
        *lock(&shared.job_started) = Some((Instant::now(), false));
    }
    Some(job)
}

fn run(mut learner: Box<dyn Learner>, shared: &WorkerShared, checkpoints: &CheckpointSettings) {
    let mut store = ModelStore::open(&checkpoints.path, learner.as_ref());
    let mut last_save = Instant::now();
    // The learner's own events (e.g. where its starting model came from), after every job.
    let report = |learner: &mut dyn Learner| {
        let events = panic::catch_unwind(AssertUnwindSafe(|| learner.take_events()));
        for kind in events.unwrap_or_default() {
            shared.notice(Notice::Event(kind));
        }
    };
    report(learner.as_mut());
    let mut consecutive_panics = 0;
    while let Some(job) = next_job(shared, Duration::from_millis(200)) {
        let running_command = match &job {
            Some(Job::Command(c)) => Some((c.sequence, c.opcode)),
            _ => None,
        };
        let ran_job = job.is_some();
        let outcome = panic::catch_unwind(AssertUnwindSafe(|| {
            match job {
                Some(Job::Command(c)) => run_command(learner.as_mut(), shared, &mut store, c),
                Some(Job::Frame(f)) => run_frame(learner.as_mut(), shared, f),
                None => {}
            }
            if let Some(period) = checkpoints.period {
                if last_save.elapsed() >= period {
                    last_save = Instant::now();
                    save(learner.as_ref(), shared, &mut store);
                }
            }
        }));
        match outcome {
            Ok(()) if ran_job => consecutive_panics = 0,
            Ok(()) => {}
            Err(_) => {
                consecutive_panics += 1;
                if let Some((sequence, opcode)) = running_command {
                    shared.notice(Notice::Ack(CommandAck {
                        sequence: Some(sequence),
                        opcode: Some(opcode),
                        status: AckStatus::ExecutionError,
                        detail: ErrorCode::Internal as u16,
                    }));
                }
                restart(&mut learner, &store, shared, consecutive_panics);
            }
        }
        report(learner.as_mut());
        let stats = panic::catch_unwind(AssertUnwindSafe(|| learner.stats())).unwrap_or_default();
        *lock(&shared.job_started) = None;
        let mut s = lock(&shared.snapshot);
        s.learner = stats;
        s.busy = false;
    }
}

/// After a panic: report it, reset the learner and load the newest usable checkpoint.
fn restart(
    learner: &mut Box<dyn Learner>,
    store: &ModelStore,
    shared: &WorkerShared,
    consecutive_panics: u32,
) {
    shared.notice(Notice::Event(EventKind::Error {
        code: ErrorCode::Internal,
        detail: event_detail::TRAINER_PANICKED,
    }));
    let mut gave_up = consecutive_panics >= MAX_CONSECUTIVE_PANICS;
    shared.notice(Notice::TrainerFault { gave_up });
    let restored = panic::catch_unwind(AssertUnwindSafe(|| {
        learner.reset()?;
        Ok::<_, LearnerError>(store.load_newest(learner.as_mut()))
    }));
    match restored {
        Ok(Ok(outcome)) => {
            let mut s = lock(&shared.snapshot);
            s.trainer_restarts += 1;
            s.last_round = None;
            s.last_prediction_psnr_db = None;
            drop(s);
            report_load(shared, outcome);
        }
        Ok(Err(_)) | Err(_) => gave_up = true,
    }
    if gave_up {
        shared.notice(Notice::Event(EventKind::Error {
            code: ErrorCode::Internal,
            detail: event_detail::TRAINER_GAVE_UP,
        }));
        shared.notice(Notice::TrainerFault { gave_up });
    } else {
        shared.notice(Notice::TrainerRestored);
    }
}

/// Events for a load: `CheckpointLoaded`, a `CheckpointLoadFailed` when the newest slot was
/// refused or none was usable, `ModelReset` when the model starts afresh.
pub(crate) fn load_events(outcome: LoadOutcome) -> Vec<EventKind> {
    let mut events = Vec::new();
    if let Some(detail) = outcome.failure_detail() {
        events.push(EventKind::Error {
            code: ErrorCode::CheckpointLoadFailed,
            detail,
        });
    }
    events.push(match outcome {
        LoadOutcome::Loaded { rounds, .. } => EventKind::CheckpointLoaded {
            rounds: u32::try_from(rounds).unwrap_or(u32::MAX),
        },
        LoadOutcome::Empty | LoadOutcome::Unusable => EventKind::ModelReset,
    });
    events
}

fn report_load(shared: &WorkerShared, outcome: LoadOutcome) {
    for kind in load_events(outcome) {
        shared.notice(Notice::Event(kind));
    }
}

fn save(learner: &dyn Learner, shared: &WorkerShared, store: &mut ModelStore) -> bool {
    let (code, detail) = match store.save(learner) {
        SaveOutcome::Saved { rounds } => {
            lock(&shared.snapshot).checkpoints_saved += 1;
            let rounds = u32::try_from(rounds).unwrap_or(u32::MAX);
            shared.notice(Notice::Event(EventKind::CheckpointSaved { rounds }));
            return true;
        }
        SaveOutcome::Refused { detail } => {
            lock(&shared.snapshot).checkpoints_refused += 1;
            (ErrorCode::CheckpointSaveFailed, detail)
        }
        SaveOutcome::Failed { detail } => (ErrorCode::CheckpointSaveFailed, detail),
    };
    shared.notice(Notice::Event(EventKind::Error { code, detail }));
    false
}

fn run_command(
    learner: &mut dyn Learner,
    shared: &WorkerShared,
    store: &mut ModelStore,
    job: CommandJob,
) {
    let ack = |status| {
        Notice::Ack(CommandAck {
            sequence: Some(job.sequence),
            opcode: Some(job.opcode),
            status,
            detail: 0,
        })
    };
    let status = match &job.command {
        ModelCommand::ResetModel => match learner.reset() {
            Ok(()) => {
                // The explicit command that may replace a trained model on disk.
                store.allow_replacing();
                let mut s = lock(&shared.snapshot);
                s.last_round = None;
                s.last_prediction_psnr_db = None;
                drop(s);
                shared.notice(Notice::Event(EventKind::ModelReset));
                AckStatus::Ok
            }
            Err(_) => {
                shared.notice(Notice::Event(EventKind::Error {
                    code: ErrorCode::Internal,
                    detail: event_detail::RESET_FAILED,
                }));
                AckStatus::ExecutionError
            }
        },
        ModelCommand::SaveCheckpoint => {
            if save(learner, shared, store) {
                AckStatus::Ok
            } else {
                AckStatus::ExecutionError
            }
        }
        ModelCommand::LoadCheckpoint => {
            let outcome = store.load_newest(learner);
            if let Some(detail) = outcome.failure_detail() {
                shared.notice(Notice::Event(EventKind::Error {
                    code: ErrorCode::CheckpointLoadFailed,
                    detail,
                }));
            }
            match outcome {
                LoadOutcome::Loaded { rounds, .. } => {
                    let rounds = u32::try_from(rounds).unwrap_or(u32::MAX);
                    shared.notice(Notice::Event(EventKind::CheckpointLoaded { rounds }));
                    AckStatus::Ok
                }
                LoadOutcome::Empty => {
                    shared.notice(Notice::Event(EventKind::Error {
                        code: ErrorCode::CheckpointLoadFailed,
                        detail: event_detail::LOAD_NOTHING_USABLE,
                    }));
                    AckStatus::ExecutionError
                }
                LoadOutcome::Unusable => AckStatus::ExecutionError,
            }
        }
        ModelCommand::Render(view) => match learner.predict(view) {
            Ok(image) => {
                shared.publish_prediction(prediction(
                    view,
                    PredictionSource::Command {
                        sequence: job.sequence,
                    },
                    0,
                    image,
                    None,
                ));
                lock(&shared.snapshot).predictions_rendered += 1;
                AckStatus::Ok
            }
            Err(error) => {
                render_failed(shared, &error);
                AckStatus::ExecutionError
            }
        },
    };
    shared.notice(ack(status));
}

fn internal_event(shared: &WorkerShared, detail: u32) {
    shared.notice(Notice::Event(EventKind::Error {
        code: ErrorCode::Internal,
        detail,
    }));
}

fn render_failed(shared: &WorkerShared, error: &LearnerError) {
    let detail = match error {
        LearnerError::NothingToRender => 0,
        LearnerError::BadRequest(_) => 1,
        LearnerError::BadCheckpoint(_) => 2,
        LearnerError::Training(_) => 3,
    };
    shared.notice(Notice::Event(EventKind::Error {
        code: ErrorCode::RenderFailed,
        detail,
    }));
}

fn to_f32<const N: usize>(values: [f64; N]) -> [f32; N] {
    values.map(|v| v as f32)
}

fn prediction(
    view: &ViewRequest,
    source: PredictionSource,
    time_us: u64,
    image: crate::learner::PredictedImage,
    metrics: Option<(f32, f32)>,
) -> Prediction {
    let q = view.camera_from_target.normalize();
    Prediction {
        header: FrameHeader {
            frame_id: match source {
                PredictionSource::ObservedFrame { frame_id } => frame_id,
                PredictionSource::Command { sequence } => sequence,
            },
            time_us,
            width: image.width,
            height: image.height,
            format: image.format,
        },
        source,
        q_camera_from_target: to_f32([q.w, q.x, q.y, q.z]),
        t_camera_from_target_m: to_f32(view.target_in_camera_m.to_array()),
        sun_target: to_f32(view.sun_in_target.normalize().to_array()),
        psnr_db: metrics.map(|m| m.0),
        ssim: metrics.map(|m| m.1),
        pixels: image.pixels,
    }
}

fn channels(format: PixelFormat) -> usize {
    format.bytes_per_pixel()
}

fn run_frame(learner: &mut dyn Learner, shared: &WorkerShared, job: FrameJob) {
    let frame = &job.frame;
    let t = &frame.telemetry;
    let view = ViewRequest {
        camera_from_target: t.camera_from_target,
        target_in_camera_m: t.target_in_camera_m,
        sun_in_target: t.sun_in_target,
        width: frame.width,
        height: frame.height,
        format: frame.format,
        intrinsics: frame.camera,
    };
    match learner.predict(&view) {
        Ok(image) => {
            let (w, h, c) = (
                usize::from(frame.width),
                usize::from(frame.height),
                channels(frame.format),
            );
            let metrics = imagemetrics::psnr_db(&image.pixels, &frame.pixels, w, h, c)
                .and_then(|p| {
                    Ok((
                        p,
                        imagemetrics::ssim(&image.pixels, &frame.pixels, w, h, c)?,
                    ))
                })
                .ok();
            let source = PredictionSource::ObservedFrame {
                frame_id: frame.frame_id,
            };
            shared.publish_prediction(prediction(&view, source, frame.time_us, image, metrics));
            let mut s = lock(&shared.snapshot);
            s.predictions_rendered += 1;
            if let Some((psnr, _)) = metrics {
                s.last_prediction_psnr_db = Some(psnr);
            }
        }
        Err(LearnerError::NothingToRender) => {
            lock(&shared.snapshot).predictions_unavailable += 1;
        }
        Err(error) => render_failed(shared, &error),
    }
    let mut used = false;
    let mut round = None;
    if job.usage == FrameUse::PredictAndTrain {
        let offered = learner.offer(frame);
        used = offered == OfferResult::Added;
        if offered == OfferResult::Refused {
            internal_event(shared, event_detail::FRAME_REFUSED_BY_MODEL);
        }
        let started = Instant::now();
        match learner.run_round_if_due() {
            // The worker times the round itself: the figure health reports is wall time.
            Ok(Some(r)) => {
                if r.skipped_steps > 0 {
                    shared.notice(Notice::Event(EventKind::Error {
                        code: ErrorCode::TrainingNonFinite,
                        detail: r.skipped_steps,
                    }));
                }
                round = Some(RoundSummary {
                    duration_ms: u32::try_from(started.elapsed().as_millis()).unwrap_or(u32::MAX),
                    ..r
                });
            }
            Ok(None) => {}
            Err(_) => internal_event(shared, event_detail::ROUND_FAILED),
        }
    }
    // The learner's figures change with the frame counters under one lock, so a reader that
    // sees the frame processed also sees the round it ran.
    let stats = learner.stats();
    let mut s = lock(&shared.snapshot);
    s.learner = stats;
    s.frames_processed += 1;
    s.frames_used += u64::from(used);
    if round.is_some() {
        s.last_round = round;
    }
}

#[cfg(test)]
#[path = "worker_tests.rs"]
mod tests;

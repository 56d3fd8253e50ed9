//! Synchronizer: pairs camera frames with pose and Sun telemetry interpolated to the frame time.
//!
//! Two bounded, time-ordered buffers hold the telemetry: target pose (camera-from-target
//! rotation + target origin in the camera frame, with a quality) and the AOCS Sun vector
//! (servicer body frame, with a validity flag). For a frame time t, the samples on both
//! sides of t are interpolated (quaternion slerp along the shorter arc, linear translation,
//! linear Sun vector renormalised), and the Sun is carried into the camera frame through
//! the camera mounting and into the target frame through the pose.
//!
//! Invariants:
//! - Buffers never exceed `buffer_capacity`; when full the oldest sample is dropped and counted.
//! - Sample times are strictly increasing: older or equal time tags are dropped and counted.
//! - Malformed samples (NaN/Inf, non-unit beyond tolerance, flagged invalid, low quality) are
//!   kept as *invalid markers*: a frame they bracket is rejected as invalid, and no NaN
//!   value is ever stored or returned.
//! - Every final answer for a frame is counted exactly once ([`SyncCounters::frames`]);
//!   [`SyncError::AwaitingTelemetry`] is not final and not counted.
//! - Eclipse (the ICD's rule): a Sun sample flagged `eclipse = Some(true)` is an eclipse
//!   sample, kept with its direction when the vector is valid and without one when not (it
//!   is then no invalid marker). A frame bracketed by an eclipse sample is an eclipse frame:
//!   with a direction from every bracketing sample it is synchronised with
//!   [`SyncedTelemetry::eclipse`] set (the learner skips it and counts it); otherwise it is
//!   the final [`SyncError::Eclipse`]. A sample without the flag (a 1.0 sender) or with
//!   `Some(false)` is sunlit: `valid = false` makes it an invalid marker as before.
//!
//! Times are integer microseconds on the spacecraft clock.

use glam::{DQuat, DVec3, DVec4};
use std::collections::VecDeque;
use std::fmt;

/// A target pose sample from relative navigation.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PoseSample {
    pub time_us: u64,
    /// Rotation taking target-body vectors to camera-frame vectors.
    pub camera_from_target: DQuat,
    /// Target body origin expressed in the camera frame, metres.
    pub target_in_camera_m: DVec3,
    /// Navigation quality in [0, 1], 1 best; below `min_pose_quality` the sample is invalid.
    pub quality: f64,
}

/// An AOCS Sun-vector sample.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SunSample {
    pub time_us: u64,
    /// Unit vector from the servicer towards the Sun, servicer body frame.
    pub sun_in_body: DVec3,
    /// The AOCS validity flag.
    pub valid: bool,
    /// The AOCS eclipse flag (`None`: not reported, treated as sunlit).
    pub eclipse: Option<bool>,
}

/// The two telemetry streams.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Stream {
    Pose,
    Sun,
}

/// Why a stored sample (or an interpolation of samples) is unusable.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum InvalidReason {
    /// The sender's validity flag was cleared.
    FlaggedInvalid,
    /// A component was NaN or infinite.
    NonFinite,
    /// The quaternion or Sun vector norm differs from 1 by more than the tolerance.
    NonUnit { norm: f64 },
    /// Pose quality below the configured minimum.
    LowQuality { quality: f64 },
    /// The two bracketing Sun vectors are (nearly) opposite: no meaningful interpolation.
    SunInterpolationDegenerate,
    /// The camera sits at the target origin: no view direction.
    ZeroRange,
}

/// Why a sample was dropped on arrival (it is not stored).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SampleDropped {
    /// Older than the newest buffered sample.
    OutOfOrder { time_us: u64, newest_time_us: u64 },
    /// Same time tag as the newest buffered sample.
    Duplicate { time_us: u64 },
}

/// How an accepted sample was stored.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum SampleStatus {
    Valid,
    /// Stored as an invalid marker: frames it brackets are rejected.
    Invalid(InvalidReason),
}

/// What is missing when a frame cannot be bracketed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MissingDetail {
    NoSamples,
    /// The frame is older than the oldest buffered sample.
    BeforeOldest {
        oldest_time_us: u64,
    },
    /// The sample before the frame is more than `max_gap_us` earlier.
    GapBefore {
        gap_us: u64,
    },
    /// The sample after the frame is more than `max_gap_us` later.
    GapAfter {
        gap_us: u64,
    },
    /// No sample after the frame yet, and the caller chose not to wait.
    NoSampleAfter {
        newest_time_us: u64,
    },
}

/// Why a frame got no telemetry.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum SyncError {
    /// Not final: the sample after the frame time has not arrived yet; retry later.
    AwaitingTelemetry { stream: Stream },
    Missing {
        stream: Stream,
        detail: MissingDetail,
    },
    /// The newest sample is more than `stale_after_us` older than the frame.
    Stale { stream: Stream, age_us: u64 },
    Invalid {
        stream: Stream,
        reason: InvalidReason,
    },
    /// An eclipse frame without a Sun direction (skipped on purpose, not an error).
    Eclipse,
}

impl SyncError {
    /// False only for [`SyncError::AwaitingTelemetry`].
    pub fn is_final(&self) -> bool {
        !matches!(self, Self::AwaitingTelemetry { .. })
    }
}

impl fmt::Display for SyncError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::AwaitingTelemetry { stream } => {
                write!(
                    f,
                    "{stream:?} telemetry after the frame time not received yet"
                )
            }
            Self::Missing { stream, detail } => {
                write!(f, "{stream:?} telemetry missing: {detail:?}")
            }
            Self::Stale { stream, age_us } => {
                write!(
                    f,
                    "{stream:?} telemetry stale: newest sample {age_us} us before the frame"
                )
            }
            Self::Invalid { stream, reason } => {
                write!(f, "{stream:?} telemetry invalid: {reason:?}")
            }
            Self::Eclipse => f.write_str("eclipse frame without a Sun direction"),
        }
    }
}

impl std::error::Error for SyncError {}

/// Whether a frame may wait for telemetry after its time tag.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum WaitPolicy {
    /// Answer [`SyncError::AwaitingTelemetry`] (uncounted) when the later sample is still due.
    MayWait,
    /// Final answer now: a missing later sample is [`MissingDetail::NoSampleAfter`].
    NoWait,
}

/// Synchronizer settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SyncConfig {
    /// Samples kept per stream.
    pub buffer_capacity: usize,
    /// Largest allowed distance from the frame time to the sample on either side.
    pub max_gap_us: u64,
    /// A frame later than the newest sample by more than this is rejected as stale.
    pub stale_after_us: u64,
    /// Allowed |norm - 1| of incoming quaternions and Sun vectors (then renormalised).
    pub unit_norm_tolerance: f64,
    /// Poses with a lower quality are invalid.
    pub min_pose_quality: f64,
    /// Camera mounting: rotation taking servicer-body vectors to camera-frame vectors.
    pub camera_from_body: DQuat,
}

impl Default for SyncConfig {
    fn default() -> Self {
        Self {
            buffer_capacity: 256,
            max_gap_us: 2_000_000,
            stale_after_us: 10_000_000,
            unit_norm_tolerance: 1e-3,
            min_pose_quality: 0.0,
            camera_from_body: DQuat::IDENTITY,
        }
    }
}

/// A refused [`SyncConfig`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum SyncConfigError {
    BufferTooSmall { capacity: usize },
    ZeroMaxGap,
    BadTolerance { tolerance: f64 },
    BadMinPoseQuality { quality: f64 },
    BadMounting { norm: f64 },
}

impl fmt::Display for SyncConfigError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::BufferTooSmall { capacity } => {
                write!(
                    f,
                    "telemetry buffer capacity {capacity} < 2 cannot bracket a frame"
                )
            }
            Self::ZeroMaxGap => write!(f, "max_gap_us must be positive"),
            Self::BadTolerance { tolerance } => {
                write!(f, "unit-norm tolerance {tolerance} is not in (0, 0.5)")
            }
            Self::BadMinPoseQuality { quality } => {
                write!(f, "minimum pose quality {quality} is not a finite number")
            }
            Self::BadMounting { norm } => write!(
                f,
                "camera mounting quaternion has norm {norm}, not a finite unit quaternion"
            ),
        }
    }
}

impl std::error::Error for SyncConfigError {}

impl SyncConfig {
    pub fn validate(&self) -> Result<(), SyncConfigError> {
        if self.buffer_capacity < 2 {
            return Err(SyncConfigError::BufferTooSmall {
                capacity: self.buffer_capacity,
            });
        }
        if self.max_gap_us == 0 {
            return Err(SyncConfigError::ZeroMaxGap);
        }
        let tolerance = self.unit_norm_tolerance;
        if !(tolerance > 0.0 && tolerance < 0.5) {
            return Err(SyncConfigError::BadTolerance { tolerance });
        }
        if !self.min_pose_quality.is_finite() {
            return Err(SyncConfigError::BadMinPoseQuality {
                quality: self.min_pose_quality,
            });
        }
        let norm = self.camera_from_body.length();
        if !self.camera_from_body.is_finite() || (norm - 1.0).abs() > tolerance {
            return Err(SyncConfigError::BadMounting { norm });
        }
        Ok(())
    }
}

/// Telemetry at a frame time, in every frame the pipeline needs.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SyncedTelemetry {
    pub time_us: u64,
    pub camera_from_target: DQuat,
    pub target_in_camera_m: DVec3,
    /// The lower quality of the bracketing samples.
    pub pose_quality: f64,
    /// Unit Sun vector in the servicer body, camera and target body frames.
    pub sun_in_body: DVec3,
    pub sun_in_camera: DVec3,
    pub sun_in_target: DVec3,
    /// Unit vector from the target origin to the camera, target body frame (the keyframe w).
    pub view_in_target: DVec3,
    /// Distance between camera and target origin, metres.
    pub range_m: f64,
    /// A bracketing Sun sample was flagged eclipse (the Sun vectors are still valid).
    pub eclipse: bool,
}

/// Per-stream sample counters.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct StreamCounters {
    pub stored_valid: u64,
    /// Stored as invalid markers (flag, NaN, non-unit, low quality).
    pub stored_invalid: u64,
    pub dropped_out_of_order: u64,
    pub dropped_duplicate: u64,
    /// Oldest samples dropped because the buffer was full.
    pub evicted_oldest: u64,
}

/// Final outcomes of frame synchronisation.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FrameCounters {
    pub synced: u64,
    pub rejected_missing: u64,
    pub rejected_stale: u64,
    pub rejected_invalid: u64,
    /// Eclipse frames without a Sun direction ([`SyncError::Eclipse`]).
    pub eclipse: u64,
}

/// Health counters of the synchronizer.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SyncCounters {
    pub pose: StreamCounters,
    pub sun: StreamCounters,
    pub frames: FrameCounters,
}

#[derive(Clone, Copy, Debug)]
struct PoseValue {
    camera_from_target: DQuat,
    target_in_camera_m: DVec3,
    quality: f64,
}

/// A usable Sun sample: `direction` is `None` only for eclipse samples.
#[derive(Clone, Copy, Debug)]
struct SunValue {
    direction: Option<DVec3>,
    eclipse: bool,
}

#[derive(Clone, Copy, Debug)]
struct Stored<T> {
    time_us: u64,
    value: Result<T, InvalidReason>,
}

/// The samples around a frame time.
enum Bracket<T> {
    Exact(T),
    Between { before: T, after: T, alpha: f64 },
}

/// Buffers telemetry and answers frame-time queries.
#[derive(Clone, Debug)]
pub struct Synchronizer {
    config: SyncConfig,
    camera_from_body: DQuat,
    poses: VecDeque<Stored<PoseValue>>,
    suns: VecDeque<Stored<SunValue>>,
    counters: SyncCounters,
}

impl Synchronizer {
    pub fn new(config: SyncConfig) -> Result<Self, SyncConfigError> {
        config.validate()?;
        Ok(Self {
            config,
            camera_from_body: config.camera_from_body.normalize(),
            poses: VecDeque::with_capacity(config.buffer_capacity),
            suns: VecDeque::with_capacity(config.buffer_capacity),
            counters: SyncCounters::default(),
        })
    }

    pub fn config(&self) -> &SyncConfig {
        &self.config
    }

    pub fn counters(&self) -> SyncCounters {
        self.counters
    }

    pub fn reset_counters(&mut self) {
        self.counters = SyncCounters::default();
    }

    /// Buffered samples (valid and invalid markers) per stream.
    pub fn buffered(&self, stream: Stream) -> usize {
        match stream {
            Stream::Pose => self.poses.len(),
            Stream::Sun => self.suns.len(),
        }
    }

    /// Drops all buffered telemetry (counters are kept).
    pub fn clear(&mut self) {
        self.poses.clear();
        self.suns.clear();
    }

    /// Drops one stream's buffered telemetry (after a clock jump; counters are kept).
    pub(crate) fn clear_stream(&mut self, stream: Stream) {
        match stream {
            Stream::Pose => self.poses.clear(),
            Stream::Sun => self.suns.clear(),
        }
    }

    pub fn push_pose(&mut self, sample: PoseSample) -> Result<SampleStatus, SampleDropped> {
        let value = self.check_pose(&sample);
        push_ordered(
            &mut self.poses,
            &mut self.counters.pose,
            self.config.buffer_capacity,
            sample.time_us,
            value,
        )
    }

    pub fn push_sun(&mut self, sample: SunSample) -> Result<SampleStatus, SampleDropped> {
        let value = self.check_sun(&sample);
        push_ordered(
            &mut self.suns,
            &mut self.counters.sun,
            self.config.buffer_capacity,
            sample.time_us,
            value,
        )
    }

    fn check_pose(&self, sample: &PoseSample) -> Result<PoseValue, InvalidReason> {
        let q = sample.camera_from_target;
        if !q.is_finite() || !sample.target_in_camera_m.is_finite() || !sample.quality.is_finite() {
            return Err(InvalidReason::NonFinite);
        }
        let norm = q.length();
        if (norm - 1.0).abs() > self.config.unit_norm_tolerance {
            return Err(InvalidReason::NonUnit { norm });
        }
        if sample.quality < self.config.min_pose_quality {
            return Err(InvalidReason::LowQuality {
                quality: sample.quality,
            });
        }
        Ok(PoseValue {
            camera_from_target: q / norm,
            target_in_camera_m: sample.target_in_camera_m,
            quality: sample.quality,
        })
    }

    fn check_sun(&self, sample: &SunSample) -> Result<SunValue, InvalidReason> {
        let direction = self.check_sun_direction(sample);
        if sample.eclipse == Some(true) {
            // In eclipse the direction is optional: without one the frame is skipped.
            return Ok(SunValue {
                direction: direction.ok(),
                eclipse: true,
            });
        }
        direction.map(|d| SunValue {
            direction: Some(d),
            eclipse: false,
        })
    }

    fn check_sun_direction(&self, sample: &SunSample) -> Result<DVec3, InvalidReason> {
        if !sample.valid {
            return Err(InvalidReason::FlaggedInvalid);
        }
        if !sample.sun_in_body.is_finite() {
            return Err(InvalidReason::NonFinite);
        }
        let norm = sample.sun_in_body.length();
        if (norm - 1.0).abs() > self.config.unit_norm_tolerance {
            return Err(InvalidReason::NonUnit { norm });
        }
        Ok(sample.sun_in_body / norm)
    }

    /// Telemetry interpolated to `frame_time_us`, or why there is none.
    ///
    /// Pose is checked before Sun; a final rejection of either stream wins over waiting.
    pub fn synchronize(
        &mut self,
        frame_time_us: u64,
        policy: WaitPolicy,
    ) -> Result<SyncedTelemetry, SyncError> {
        let result = self.resolve(frame_time_us, policy);
        let frames = &mut self.counters.frames;
        match &result {
            Ok(_) => frames.synced += 1,
            Err(SyncError::AwaitingTelemetry { .. }) => {}
            Err(SyncError::Missing { .. }) => frames.rejected_missing += 1,
            Err(SyncError::Stale { .. }) => frames.rejected_stale += 1,
            Err(SyncError::Invalid { .. }) => frames.rejected_invalid += 1,
            Err(SyncError::Eclipse) => frames.eclipse += 1,
        }
        result
    }

    fn resolve(&self, t: u64, policy: WaitPolicy) -> Result<SyncedTelemetry, SyncError> {
        let pose = bracket(&self.poses, t, Stream::Pose, &self.config, policy);
        let sun = bracket(&self.suns, t, Stream::Sun, &self.config, policy);
        let (pose, sun) = match (pose, sun) {
            (Ok(p), Ok(s)) => (p, s),
            (Err(e), _) if e.is_final() => return Err(e),
            (_, Err(e)) if e.is_final() => return Err(e),
            (Err(e), _) | (_, Err(e)) => return Err(e),
        };

        let (camera_from_target, target_in_camera_m, pose_quality) = match pose {
            Bracket::Exact(p) => (p.camera_from_target, p.target_in_camera_m, p.quality),
            Bracket::Between {
                before,
                after,
                alpha,
            } => (
                slerp_shortest(before.camera_from_target, after.camera_from_target, alpha),
                before
                    .target_in_camera_m
                    .lerp(after.target_in_camera_m, alpha),
                before.quality.min(after.quality),
            ),
        };
        let (sun, eclipse) = match sun {
            Bracket::Exact(s) => (s.direction.map(Bracket::Exact), s.eclipse),
            Bracket::Between {
                before,
                after,
                alpha,
            } => (
                before
                    .direction
                    .zip(after.direction)
                    .map(|(b, a)| Bracket::Between {
                        before: b,
                        after: a,
                        alpha,
                    }),
                before.eclipse || after.eclipse,
            ),
        };
        let Some(sun) = sun else {
            // Only eclipse samples lack a direction.
            return Err(SyncError::Eclipse);
        };
        let sun_in_body = match sun {
            Bracket::Exact(s) => s,
            Bracket::Between {
                before,
                after,
                alpha,
            } => {
                let mixed = before.lerp(after, alpha);
                // Opposite samples cancel; below this the direction is numerical noise.
                if mixed.length() < 1e-6 {
                    return Err(SyncError::Invalid {
                        stream: Stream::Sun,
                        reason: InvalidReason::SunInterpolationDegenerate,
                    });
                }
                mixed.normalize()
            }
        };

        let range_m = target_in_camera_m.length();
        if range_m <= 1e-9 {
            return Err(SyncError::Invalid {
                stream: Stream::Pose,
                reason: InvalidReason::ZeroRange,
            });
        }
        let target_from_camera = camera_from_target.conjugate();
        // Camera centre in the target frame is -R^T t; its direction is the view vector.
        let view_in_target = (-(target_from_camera * target_in_camera_m) / range_m).normalize();
        let sun_in_camera = (self.camera_from_body * sun_in_body).normalize();
        let sun_in_target = (target_from_camera * sun_in_camera).normalize();
        Ok(SyncedTelemetry {
            time_us: t,
            camera_from_target,
            target_in_camera_m,
            pose_quality,
            sun_in_body,
            sun_in_camera,
            sun_in_target,
            view_in_target,
            range_m,
            eclipse,
        })
    }
}

fn push_ordered<T>(
    buffer: &mut VecDeque<Stored<T>>,
    counters: &mut StreamCounters,
    capacity: usize,
    time_us: u64,
    value: Result<T, InvalidReason>,
) -> Result<SampleStatus, SampleDropped> {
    if let Some(newest) = buffer.back() {
        if time_us == newest.time_us {
            counters.dropped_duplicate += 1;
            return Err(SampleDropped::Duplicate { time_us });
        }
        if time_us < newest.time_us {
            counters.dropped_out_of_order += 1;
            return Err(SampleDropped::OutOfOrder {
                time_us,
                newest_time_us: newest.time_us,
            });
        }
    }
    if buffer.len() >= capacity {
        buffer.pop_front();
        counters.evicted_oldest += 1;
    }
    let status = match &value {
        Ok(_) => {
            counters.stored_valid += 1;
            SampleStatus::Valid
        }
        Err(reason) => {
            counters.stored_invalid += 1;
            SampleStatus::Invalid(*reason)
        }
    };
    buffer.push_back(Stored { time_us, value });
    Ok(status)
}

fn bracket<T: Copy>(
    buffer: &VecDeque<Stored<T>>,
    t: u64,
    stream: Stream,
    config: &SyncConfig,
    policy: WaitPolicy,
) -> Result<Bracket<T>, SyncError> {
    let usable = |s: &Stored<T>| {
        s.value
            .map_err(|reason| SyncError::Invalid { stream, reason })
    };
    let missing = |detail| SyncError::Missing { stream, detail };
    let (Some(oldest), Some(newest)) = (buffer.front(), buffer.back()) else {
        return Err(missing(MissingDetail::NoSamples));
    };
    let index = buffer.partition_point(|s| s.time_us < t);
    if let Some(exact) = buffer.get(index).filter(|s| s.time_us == t) {
        return usable(exact).map(Bracket::Exact);
    }
    if index == 0 {
        return Err(missing(MissingDetail::BeforeOldest {
            oldest_time_us: oldest.time_us,
        }));
    }
    if index == buffer.len() {
        let age_us = t - newest.time_us;
        if age_us > config.stale_after_us {
            return Err(SyncError::Stale { stream, age_us });
        }
        return Err(match policy {
            WaitPolicy::MayWait => SyncError::AwaitingTelemetry { stream },
            WaitPolicy::NoWait => missing(MissingDetail::NoSampleAfter {
                newest_time_us: newest.time_us,
            }),
        });
    }
    let before = &buffer[index - 1];
    let after = &buffer[index];
    let gap_before = t - before.time_us;
    let gap_after = after.time_us - t;
    if gap_before > config.max_gap_us {
        return Err(missing(MissingDetail::GapBefore { gap_us: gap_before }));
    }
    if gap_after > config.max_gap_us {
        return Err(missing(MissingDetail::GapAfter { gap_us: gap_after }));
    }
    let alpha = gap_before as f64 / (after.time_us - before.time_us) as f64;
    Ok(Bracket::Between {
        before: usable(before)?,
        after: usable(after)?,
        alpha,
    })
}

/// Spherical linear interpolation of unit quaternions along the shorter arc.
///
/// q and -q are the same rotation; flipping `end` into `start`'s hemisphere makes the
/// path the short one. The arc angle comes from atan2 of the chord lengths, which stays
/// accurate for tiny angles where acos(dot) loses half the digits; only when the angle
/// underflows does linear interpolation take over.
pub fn slerp_shortest(start: DQuat, end: DQuat, alpha: f64) -> DQuat {
    let a = DVec4::from(start);
    let mut b = DVec4::from(end);
    if a.dot(b) < 0.0 {
        b = -b;
    }
    let theta = 2.0 * (a - b).length().atan2((a + b).length());
    let sin_theta = theta.sin();
    let mixed = if sin_theta < 1e-300 {
        a * (1.0 - alpha) + b * alpha
    } else {
        a * (((1.0 - alpha) * theta).sin() / sin_theta) + b * ((alpha * theta).sin() / sin_theta)
    };
    DQuat::from_vec4(mixed.normalize())
}

#[cfg(test)]
mod tests;

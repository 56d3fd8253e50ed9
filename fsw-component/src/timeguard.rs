//! Time-tag guard: bounds telemetry time tags against the receive clock and recovers the
//! synchronizer from a clock jump.
//!
//! Telemetry carries spacecraft time; the component receives it on its own clock. The
//! offset between the two (`time_us - received_us`) is nearly constant for a healthy sender,
//! so a sample whose offset differs from the last accepted sample's by more than
//! `tolerance_us` is out of bounds: dropped and counted, never stored, so one far-future
//! time tag cannot become the newest sample and lock every later one out as out of order.
//!
//! A real clock jump (a backwards correction, or a first sample on a bad clock) makes every
//! later sample look wrong. `resync_after` consecutive rejected samples of one stream
//! (out of bounds or out of order) whose time tags increase and whose offsets agree with
//! each other within the tolerance are taken as the new clock: that stream's buffer is
//! cleared and the sample is stored. A stream therefore accepts samples again at most
//! `resync_after` samples after any jump or any single bad sample.
//!
//! Invariants: one guard per stream; every sample pushed through [`TimeTagGuard::push`]
//! gets exactly one [`Admission`]; duplicates (same time tag as the newest) neither extend
//! nor break a rejection streak, so a stuck sender cannot force resynchronisations.

use crate::sync::{PoseSample, SampleDropped, SampleStatus, Stream, SunSample, Synchronizer};
use std::fmt;

/// Guard settings (the same for both streams).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TimeGuardConfig {
    /// Largest change of `time_us - received_us` from the last accepted sample.
    pub tolerance_us: u64,
    /// Consecutive consistent rejections that are taken as a clock jump (at least 2).
    pub resync_after: u32,
}

impl Default for TimeGuardConfig {
    fn default() -> Self {
        Self {
            tolerance_us: 60_000_000,
            resync_after: 3,
        }
    }
}

/// A refused [`TimeGuardConfig`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TimeGuardConfigError {
    ZeroTolerance,
    ResyncTooEager { resync_after: u32 },
}

impl fmt::Display for TimeGuardConfigError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::ZeroTolerance => write!(f, "time-tag tolerance must be positive"),
            Self::ResyncTooEager { resync_after } => write!(
                f,
                "resynchronising after {resync_after} sample(s) would let a single bad \
                 time tag clear the buffer (at least 2)"
            ),
        }
    }
}

impl std::error::Error for TimeGuardConfigError {}

impl TimeGuardConfig {
    pub fn validate(&self) -> Result<(), TimeGuardConfigError> {
        if self.tolerance_us == 0 {
            return Err(TimeGuardConfigError::ZeroTolerance);
        }
        if self.resync_after < 2 {
            return Err(TimeGuardConfigError::ResyncTooEager {
                resync_after: self.resync_after,
            });
        }
        Ok(())
    }
}

/// A sample for one of the synchronizer's streams.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum TelemetrySample {
    Pose(PoseSample),
    Sun(SunSample),
}

impl TelemetrySample {
    pub fn time_us(&self) -> u64 {
        match self {
            Self::Pose(p) => p.time_us,
            Self::Sun(s) => s.time_us,
        }
    }

    pub fn stream(&self) -> Stream {
        match self {
            Self::Pose(_) => Stream::Pose,
            Self::Sun(_) => Stream::Sun,
        }
    }
}

/// What happened to a pushed sample.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Admission {
    Stored(SampleStatus),
    /// Dropped: its offset moved by `deviation_us` from the last accepted sample's.
    OutOfBounds {
        deviation_us: i128,
    },
    /// Dropped by the synchronizer (older than or as old as the newest sample).
    Dropped(SampleDropped),
    /// Taken as a clock jump: the stream's buffer was cleared, then the sample stored.
    Resynchronised(SampleStatus),
}

#[derive(Clone, Copy, Debug)]
struct Streak {
    count: u32,
    last_time_us: u64,
    last_offset_us: i128,
}

/// Per-stream state; see the module header.
#[derive(Clone, Debug)]
pub struct TimeTagGuard {
    config: TimeGuardConfig,
    accepted_offset_us: Option<i128>,
    streak: Option<Streak>,
}

fn offset_us(time_us: u64, received_us: u64) -> i128 {
    i128::from(time_us) - i128::from(received_us)
}

impl TimeTagGuard {
    pub fn new(config: TimeGuardConfig) -> Result<Self, TimeGuardConfigError> {
        config.validate()?;
        Ok(Self {
            config,
            accepted_offset_us: None,
            streak: None,
        })
    }

    /// Bounds `sample`'s time tag, stores it in `sync` when admitted, and resynchronises
    /// the stream after a clock jump.
    pub fn push(
        &mut self,
        sync: &mut Synchronizer,
        sample: TelemetrySample,
        received_us: u64,
    ) -> Admission {
        let offset = offset_us(sample.time_us(), received_us);
        let tolerance = i128::from(self.config.tolerance_us);
        let rejection = match self.accepted_offset_us {
            Some(accepted) if (offset - accepted).abs() > tolerance => Admission::OutOfBounds {
                deviation_us: offset - accepted,
            },
            _ => match store(sync, sample) {
                Ok(status) => {
                    self.accept(offset);
                    return Admission::Stored(status);
                }
                Err(dropped @ SampleDropped::Duplicate { .. }) => {
                    return Admission::Dropped(dropped)
                }
                Err(dropped) => Admission::Dropped(dropped),
            },
        };
        if !self.extend_streak(sample.time_us(), offset) {
            return rejection;
        }
        sync.clear_stream(sample.stream());
        match store(sync, sample) {
            Ok(status) => {
                self.accept(offset);
                Admission::Resynchronised(status)
            }
            // Unreachable with an empty buffer; reported as the drop it would be.
            Err(dropped) => Admission::Dropped(dropped),
        }
    }

    fn accept(&mut self, offset: i128) {
        self.accepted_offset_us = Some(offset);
        self.streak = None;
    }

    /// Counts a rejected sample; true when the streak now marks a clock jump.
    fn extend_streak(&mut self, time_us: u64, offset: i128) -> bool {
        let tolerance = i128::from(self.config.tolerance_us);
        let count = match self.streak {
            Some(s)
                if time_us > s.last_time_us && (offset - s.last_offset_us).abs() <= tolerance =>
            {
                s.count + 1
            }
            _ => 1,
        };
        self.streak = Some(Streak {
            count,
            last_time_us: time_us,
            last_offset_us: offset,
        });
        count >= self.config.resync_after
    }
}

fn store(sync: &mut Synchronizer, sample: TelemetrySample) -> Result<SampleStatus, SampleDropped> {
    match sample {
        TelemetrySample::Pose(p) => sync.push_pose(p),
        TelemetrySample::Sun(s) => sync.push_sun(s),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sync::SyncConfig;
    use glam::DVec3;

    fn sun(time_us: u64) -> TelemetrySample {
        TelemetrySample::Sun(SunSample {
            time_us,
            sun_in_body: DVec3::X,
            valid: true,
            eclipse: None,
        })
    }

    fn setup() -> (TimeTagGuard, Synchronizer) {
        let guard = TimeTagGuard::new(TimeGuardConfig {
            tolerance_us: 10_000,
            resync_after: 3,
        })
        .unwrap();
        (guard, Synchronizer::new(SyncConfig::default()).unwrap())
    }

    #[test]
    fn config_is_validated() {
        let bad = |tolerance_us, resync_after| {
            TimeGuardConfig {
                tolerance_us,
                resync_after,
            }
            .validate()
            .unwrap_err()
        };
        assert_eq!(bad(0, 3), TimeGuardConfigError::ZeroTolerance);
        assert_eq!(
            bad(1, 1),
            TimeGuardConfigError::ResyncTooEager { resync_after: 1 }
        );
    }

    #[test]
    fn a_far_future_sample_is_dropped_and_nominal_traffic_goes_on() {
        let (mut g, mut s) = setup();
        let base = 1_000_000_000;
        assert!(matches!(
            g.push(&mut s, sun(100), base),
            Admission::Stored(_)
        ));
        assert!(matches!(
            g.push(&mut s, sun(u64::MAX), base + 500),
            Admission::OutOfBounds { .. }
        ));
        for k in 1..10 {
            assert!(matches!(
                g.push(&mut s, sun(100 + k * 1_000), base + k * 1_000),
                Admission::Stored(_)
            ));
        }
        assert_eq!(s.buffered(Stream::Sun), 10);
    }

    #[test]
    fn a_backwards_step_resynchronises_after_three_consistent_samples() {
        let (mut g, mut s) = setup();
        let base = 1_000_000_000;
        for k in 0..5 {
            g.push(&mut s, sun(1_000_000 + k * 1_000), base + k * 1_000);
        }
        // Clock stepped back by 0.9 s: out of bounds (10 ms tolerance).
        let step = |k: u64| (1_000_000 + k * 1_000 - 900_000, base + k * 1_000);
        for k in 5..7 {
            let (t, r) = step(k);
            assert!(matches!(
                g.push(&mut s, sun(t), r),
                Admission::OutOfBounds { .. }
            ));
        }
        let (t, r) = step(7);
        assert!(matches!(
            g.push(&mut s, sun(t), r),
            Admission::Resynchronised(SampleStatus::Valid)
        ));
        assert_eq!(s.buffered(Stream::Sun), 1);
        let (t, r) = step(8);
        assert!(matches!(g.push(&mut s, sun(t), r), Admission::Stored(_)));
    }

    #[test]
    fn a_small_backwards_step_recovers_through_out_of_order_drops() {
        let (mut g, mut s) = setup();
        let base = 1_000_000_000;
        for k in 0..5 {
            g.push(&mut s, sun(1_000_000 + k * 1_000), base + k * 1_000);
        }
        // Stepped back by 3 ms: within the tolerance, but older than the newest sample.
        let step = |k: u64| (1_000_000 + k * 1_000 - 3_500, base + k * 1_000);
        for k in 5..7 {
            let (t, r) = step(k);
            assert!(matches!(
                g.push(&mut s, sun(t), r),
                Admission::Dropped(SampleDropped::OutOfOrder { .. })
            ));
        }
        let (t, r) = step(7);
        assert!(matches!(
            g.push(&mut s, sun(t), r),
            Admission::Resynchronised(_)
        ));
    }

    #[test]
    fn inconsistent_or_repeated_rejections_do_not_resynchronise() {
        let (mut g, mut s) = setup();
        let base = 1_000_000_000;
        g.push(&mut s, sun(5_000_000), base);
        // Random far-off time tags: each one starts a new streak.
        for (i, t) in [1u64, 900_000_000, 77, 3_000_000_000_000, 12]
            .into_iter()
            .enumerate()
        {
            let r = base + i as u64;
            assert!(!matches!(
                g.push(&mut s, sun(t), r),
                Admission::Resynchronised(_)
            ));
        }
        // The same stale sample repeated: not increasing, never a clock.
        for i in 0..5 {
            assert!(!matches!(
                g.push(&mut s, sun(1_000), base + 10 + i),
                Admission::Resynchronised(_)
            ));
        }
        // Duplicates of the newest are plain drops.
        assert_eq!(
            g.push(&mut s, sun(5_000_000), base + 20),
            Admission::Dropped(SampleDropped::Duplicate { time_us: 5_000_000 })
        );
        assert_eq!(s.buffered(Stream::Sun), 1);
    }
}

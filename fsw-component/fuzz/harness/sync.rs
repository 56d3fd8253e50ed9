//! Synchronizer harness: a configuration, then a program of pose pushes, Sun pushes, frame
//! queries and clears with arbitrary time tags (forward steps, backward jumps, raw 64-bit
//! times) and values (well-formed rotations and vectors, or raw f32 bits: NaN, Inf, huge).
//!
//! Asserted: buffers never exceed the capacity and hold exactly what was accepted; a push is
//! accepted iff its time tag is newer than the last accepted one (equal: duplicate, older:
//! out of order); every push and every final answer is counted exactly once; only
//! `MayWait` queries wait; a synced answer is finite, its rotations and directions are unit,
//! its range positive and its time the frame's.
//!
//! Record: `op(1) time(2 or 8) values...`; `op % 4` picks the operation, `(op >> 2) % 4`
//! how the time tag moves, `op & 0x10` raw f32 values instead of well-formed ones.

use super::Bytes;
use fsw_component::sync::{
    PoseSample, SampleDropped, SampleStatus, Stream, SunSample, SyncConfig, SyncError,
    SyncedTelemetry, Synchronizer, WaitPolicy,
};
use glam::{DQuat, DVec3};

pub fn run(input: &[u8]) {
    let mut b = Bytes::new(input);
    let config = SyncConfig {
        buffer_capacity: 2 + usize::from(b.u8() % 15),
        max_gap_us: 1 + u64::from(b.u16()) * 100,
        stale_after_us: u64::from(b.u16()) * 1000,
        unit_norm_tolerance: 1e-3,
        min_pose_quality: f64::from(b.u8()) / 255.0,
        camera_from_body: DQuat::from_rotation_z(f64::from(b.u8()) * 0.0246),
    };
    let capacity = config.buffer_capacity;
    let mut sync = Synchronizer::new(config).expect("the harness builds valid configurations");
    let mut clock_us = 0u64;
    let mut streams = [Tracked::default(); 2];
    let mut final_answers = 0u64;
    while !b.done() {
        let op = b.u8();
        let time_us = next_time(&mut b, op, &mut clock_us);
        let raw = op & 0x10 != 0;
        match op % 4 {
            0 => {
                let sample = PoseSample {
                    time_us,
                    camera_from_target: quaternion(&mut b, raw),
                    target_in_camera_m: vector(&mut b, raw) * f64::from(b.u8()),
                    quality: if raw {
                        f64::from(b.f32())
                    } else {
                        f64::from(b.u8()) / 255.0
                    },
                };
                let result = sync.push_pose(sample);
                streams[0].check_push(time_us, result, capacity);
            }
            1 => {
                let sample = SunSample {
                    time_us,
                    sun_in_body: vector(&mut b, raw),
                    valid: op & 0x20 == 0,
                    eclipse: (op & 0x40 != 0).then_some(op & 0x80 != 0),
                };
                let result = sync.push_sun(sample);
                streams[1].check_push(time_us, result, capacity);
            }
            2 => {
                let policy = if op & 0x20 == 0 {
                    WaitPolicy::MayWait
                } else {
                    WaitPolicy::NoWait
                };
                match sync.synchronize(time_us, policy) {
                    Ok(t) => {
                        check_synced(&t, time_us);
                        final_answers += 1;
                    }
                    Err(SyncError::AwaitingTelemetry { .. }) => {
                        assert_eq!(policy, WaitPolicy::MayWait, "NoWait never waits");
                    }
                    Err(e) => {
                        assert!(e.is_final());
                        final_answers += 1;
                    }
                }
            }
            _ => {
                sync.clear();
                for s in &mut streams {
                    *s = Tracked {
                        pushes: s.pushes,
                        ..Tracked::default()
                    };
                }
            }
        }
        assert_eq!(sync.buffered(Stream::Pose), streams[0].buffered);
        assert_eq!(sync.buffered(Stream::Sun), streams[1].buffered);
        assert!(sync.buffered(Stream::Pose) <= capacity);
        assert!(sync.buffered(Stream::Sun) <= capacity);
    }
    let c = sync.counters();
    for (counters, pushes) in [(c.pose, streams[0].pushes), (c.sun, streams[1].pushes)] {
        let accounted = counters.stored_valid
            + counters.stored_invalid
            + counters.dropped_out_of_order
            + counters.dropped_duplicate;
        assert_eq!(accounted, pushes, "{counters:?}");
        assert!(counters.evicted_oldest <= counters.stored_valid + counters.stored_invalid);
    }
    let f = c.frames;
    assert_eq!(
        f.synced + f.rejected_missing + f.rejected_stale + f.rejected_invalid,
        final_answers
    );
}

/// What the harness expects of one stream (pushes: in all; the rest: since the last clear).
#[derive(Clone, Copy, Default)]
struct Tracked {
    newest_time_us: Option<u64>,
    buffered: usize,
    pushes: u64,
}

impl Tracked {
    fn check_push(
        &mut self,
        time_us: u64,
        result: Result<SampleStatus, SampleDropped>,
        capacity: usize,
    ) {
        self.pushes += 1;
        match (self.newest_time_us, result) {
            (Some(newest), Err(SampleDropped::Duplicate { time_us: t })) => {
                assert_eq!((t, newest), (time_us, time_us));
            }
            (Some(newest), Err(SampleDropped::OutOfOrder { newest_time_us, .. })) => {
                assert!(time_us < newest && newest_time_us == newest);
            }
            (newest, Ok(_)) => {
                assert!(newest.is_none_or(|n| time_us > n), "accepted out of order");
                self.newest_time_us = Some(time_us);
                self.buffered = (self.buffered + 1).min(capacity);
            }
            (None, Err(e)) => panic!("{e:?} with an empty buffer"),
        }
    }
}

/// Forward steps (coarse or fine), backward jumps, or an arbitrary 64-bit time.
fn next_time(b: &mut Bytes, op: u8, clock_us: &mut u64) -> u64 {
    match (op >> 2) % 4 {
        0 => *clock_us = clock_us.saturating_add(u64::from(b.u16()) * 1000),
        1 => *clock_us = clock_us.saturating_add(u64::from(b.u16())),
        2 => *clock_us = clock_us.saturating_sub(u64::from(b.u16()) * 1000),
        _ => *clock_us = b.u64(),
    }
    *clock_us
}

fn quaternion(b: &mut Bytes, raw: bool) -> DQuat {
    if raw {
        let [w, x, y, z] = [b.f32(), b.f32(), b.f32(), b.f32()].map(f64::from);
        return DQuat::from_xyzw(x, y, z, w);
    }
    let q = DQuat::from_xyzw(
        f64::from(b.i8()),
        f64::from(b.i8()),
        f64::from(b.i8()),
        f64::from(b.i8()),
    );
    // The zero quaternion stays zero (a non-unit sample), anything else is made unit.
    if q.length() > 0.0 {
        q.normalize()
    } else {
        q
    }
}

fn vector(b: &mut Bytes, raw: bool) -> DVec3 {
    if raw {
        return DVec3::new(f64::from(b.f32()), f64::from(b.f32()), f64::from(b.f32()));
    }
    let v = DVec3::new(f64::from(b.i8()), f64::from(b.i8()), f64::from(b.i8()));
    if v.length() > 0.0 {
        v.normalize()
    } else {
        v
    }
}

fn check_synced(t: &SyncedTelemetry, frame_time_us: u64) {
    assert_eq!(t.time_us, frame_time_us);
    let unit = |v: DVec3| v.is_finite() && (v.length() - 1.0).abs() < 1e-9;
    assert!(
        t.camera_from_target.is_finite() && (t.camera_from_target.length() - 1.0).abs() < 1e-9,
        "{t:?}"
    );
    assert!(t.target_in_camera_m.is_finite(), "{t:?}");
    assert!(t.pose_quality.is_finite(), "{t:?}");
    for v in [
        t.sun_in_body,
        t.sun_in_camera,
        t.sun_in_target,
        t.view_in_target,
    ] {
        assert!(unit(v), "{t:?}");
    }
    assert!(t.range_m.is_finite() && t.range_m > 0.0, "{t:?}");
}

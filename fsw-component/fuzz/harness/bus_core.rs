//! Bus core harness: `BusCore` fed arbitrary UDP datagrams, CAN frames (command packets
//! included) and clock ticks, with no trainer thread (its bounded queues just fill).
//!
//! Input: `mode(1)` then records `op(1) dt(2) body`; `op % 3`: 0 a datagram
//! (`len(2) bytes`, len % 1500), 1 a CAN frame (`id(4) len(1) bytes`, len % 65, extended
//! unless `op & 4`), 2 a tick. The receive clock advances by `dt` x 10 us (x 1 s when
//! `op & 8`), so reassembly timeouts, frame waits and event rate limits all trigger.
//!
//! Asserted: no panic; every datagram and frame is counted by its reassembler; every
//! delivered message is counted exactly once by its disposition (decode error, stored or
//! dropped telemetry, received frame, accepted or rejected command); every received frame
//! is ignored, answered by the synchronizer, or pending; pending frames and worker queues
//! stay within their limits; one input yields at most one acknowledgement, one mode event
//! and one error event per error code. A RESET_COUNTERS command restarts the accounting.

use super::Bytes;
use fsw_component::cmdauth::UdpIngress;
use fsw_component::config::ComponentConfig;
use fsw_component::inbound::{BusCore, CoreCounters, CoreSettings, HealthContext, Outgoing};
use fsw_component::learner::LearnerStats;
use fsw_component::sync::SyncConfig;
use fsw_component::worker::{QueueLimits, WorkerShared};
use interfaces::messages::{AckStatus, CommandKind, ErrorCode, EventKind, Mode};
use std::sync::Arc;

const LIMITS: QueueLimits = QueueLimits {
    frames: 3,
    commands: 2,
    predictions: 2,
};
const PENDING_CAPACITY: usize = 4;
/// Error codes in the ICD (one rate-limited event each per input at most).
const ERROR_CODES: usize = ErrorCode::COUNT;

pub fn run(input: &[u8]) {
    let mut b = Bytes::new(input);
    let mode = match b.u8() % 3 {
        0 => Mode::Train,
        1 => Mode::PredictOnly,
        _ => Mode::Idle,
    };
    let worker = Arc::new(WorkerShared::new(
        LIMITS,
        LearnerStats::default(),
        std::time::Duration::from_secs(60),
    ));
    let config = ComponentConfig::default();
    let settings = CoreSettings {
        sync: SyncConfig::default(),
        max_wait_us: 500_000,
        pending_capacity: PENDING_CAPACITY,
        initial_mode: mode,
        camera: config.camera_intrinsics().expect("default camera"),
        time_guard: config.time_guard_config().expect("default guard"),
        commands: config.command_policy().expect("default policy"),
    };
    let mut core = BusCore::new(settings, Arc::clone(&worker)).expect("valid settings");
    let mut now_us = 1_000_000u64;
    let mut base = Tally::of(&core);
    while !b.done() {
        let op = b.u8();
        let dt = u64::from(b.u16());
        now_us = now_us.saturating_add(if op & 8 == 0 { dt * 10 } else { dt * 1_000_000 });
        let before = core.counters();
        match op % 3 {
            0 => {
                let len = usize::from(b.u16()) % 1500;
                let ingress = if op & 16 == 0 {
                    UdpIngress::Telemetry
                } else {
                    UdpIngress::Frames
                };
                core.handle_datagram(b.take(len), ingress, now_us);
            }
            1 => {
                let id = b.u32();
                let len = usize::from(b.u8()) % 65;
                core.handle_can_frame(op & 4 == 0, id, b.take(len), now_us);
            }
            _ => core.tick(now_us),
        }
        let out = core.take_outgoing();
        check_outgoing(&out);
        let reset = out.iter().any(|o| {
            matches!(o, Outgoing::Ack(a) if a.opcode == Some(CommandKind::ResetCounters.opcode())
                && a.status == AckStatus::Ok)
        });
        let now = Tally::of(&core);
        if reset {
            base = now;
        } else {
            let after = core.counters();
            let (datagrams, frames) = match op % 3 {
                0 => (1, 0),
                1 => (0, 1),
                _ => (0, 0),
            };
            assert_eq!(after.udp.datagrams, before.udp.datagrams + datagrams);
            assert_eq!(after.can.frames, before.can.frames + frames);
            assert_eq!(
                now.delivered - base.delivered,
                now.dispositions - base.dispositions,
                "messages unaccounted: {:?}",
                core.counters()
            );
            assert_eq!(
                now.frames_in - base.frames_in,
                now.frames_out - base.frames_out,
                "frames unaccounted: {:?}",
                core.counters()
            );
        }
        assert!(core.pending_frames() <= PENDING_CAPACITY);
        let depths = worker.depths();
        assert!(depths.frames <= LIMITS.frames && depths.commands <= LIMITS.commands);
    }
    let health = core.health(HealthContext::default());
    assert_eq!(health.mode, core.mode());
}

/// The two balances the core keeps (as running totals since the core was made).
#[derive(Clone, Copy)]
struct Tally {
    delivered: u64,
    dispositions: u64,
    frames_in: u64,
    frames_out: u64,
}

impl Tally {
    fn of(core: &BusCore) -> Self {
        let CoreCounters {
            bus,
            udp,
            can,
            sync,
        } = core.counters();
        let stored = |s: fsw_component::sync::StreamCounters| {
            s.stored_valid + s.stored_invalid + s.dropped_out_of_order + s.dropped_duplicate
        };
        let f = sync.frames;
        Self {
            delivered: udp.messages + can.transfers,
            dispositions: bus.sun_decode_errors
                + bus.pose_decode_errors
                + bus.frame_decode_errors
                + bus.frames_received
                + bus.commands_accepted
                + bus.commands_rejected
                + bus.commands_unauthorised
                // Dropped by the time-tag guard before the synchronizer sees them.
                + bus.telemetry_time_out_of_bounds
                // The synchronizer counts telemetry drops itself too: count it once there.
                + stored(sync.pose)
                + stored(sync.sun),
            frames_in: bus.frames_received,
            frames_out: bus.frames_ignored_idle
                + bus.frames_camera_mismatch
                + f.synced
                + f.eclipse
                + f.rejected_missing
                + f.rejected_stale
                + f.rejected_invalid
                + core.pending_frames() as u64,
        }
    }
}

fn check_outgoing(out: &[Outgoing]) {
    let acks = out.iter().filter(|o| matches!(o, Outgoing::Ack(_))).count();
    let modes = out
        .iter()
        .filter(
            |o| matches!(o, Outgoing::Event(e) if matches!(e.kind, EventKind::ModeChanged { .. })),
        )
        .count();
    assert!(acks <= 1 && modes <= 1, "{out:?}");
    let mut per_code = [0usize; ERROR_CODES];
    for o in out {
        if let Outgoing::Event(e) = o {
            if let EventKind::Error { code, .. } = e.kind {
                per_code[code as usize] += 1;
            }
        }
    }
    assert!(per_code.iter().all(|&n| n <= 1), "{out:?}");
}

//! Replay equivalence: a scenario fed live (and recorded) and the same scenario replayed from
//! its logs give the same model, byte for byte; so does the scenario with its telemetry and
//! commands on CAN (candump log) and its frames in a UDP recording.

mod component_support;

use component_support::*;
use fsw_component::logfmt::candump::{CanId, CanLogFrame, CanLogRecord, CanLogWriter, FrameData};
use fsw_component::logfmt::udprec::{UdpRecord, UdpRecordingWriter};
use fsw_component::outbound::{CanFramer, UdpFramer};
use fsw_component::runtime::{build_learner, run_replay, LearnerKind, ReplaySpeed};
use interfaces::messages::{AckStatus, Command, CommandKind};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

const STEPS: u32 = 8;

async fn replay_checkpoint(
    peer: &Peer,
    logs: &[PathBuf],
    checkpoint: &Path,
    speed: ReplaySpeed,
) -> (Vec<u8>, fsw_component::runtime::ReplaySummary) {
    let config = peer.config(checkpoint.to_path_buf());
    let summary = run_replay(
        &config,
        build_learner(&config, LearnerKind::NearestKeyframe).unwrap(),
        logs,
        speed,
    )
    .await
    .unwrap();
    (std::fs::read(checkpoint).unwrap(), summary)
}

/// The scenario written straight into logs: telemetry and commands as Cyphal/CAN classic
/// frames in a candump log, frames as CCSDS datagrams in a UDP recording.
fn write_mixed_logs(dir: &Path) -> Vec<PathBuf> {
    let can_path = dir.join("mixed.log");
    let udp_path = dir.join("mixed.rec");
    let mut can_log = CanLogWriter::new(std::fs::File::create(&can_path).unwrap());
    let mut udp_log = UdpRecordingWriter::new(std::fs::File::create(&udp_path).unwrap()).unwrap();
    let mut can = CanFramer::new(10, false);
    let mut udp = UdpFramer::default();
    let mut time_us = 1_700_000_000_000_000u64;
    let mut write_can = |frames: Vec<fsw_component::transport::RawCanFrame>, time_us: &mut u64| {
        for f in frames {
            *time_us += 100;
            can_log
                .write_record(&CanLogRecord {
                    timestamp_us: *time_us,
                    interface: "vcan0".into(),
                    frame: CanLogFrame::Classic {
                        id: CanId::Extended(f.id()),
                        data: FrameData::new(f.data()).unwrap(),
                        len8_dlc: None,
                    },
                    direction: None,
                })
                .unwrap();
        }
    };
    for k in 0..STEPS {
        if k == 0 {
            write_can(can.frames(&pose_at(0)).unwrap(), &mut time_us);
            write_can(can.frames(&sun_at(0)).unwrap(), &mut time_us);
        }
        let next = u64::from(k + 1) * 1_000_000;
        write_can(can.frames(&pose_at(next)).unwrap(), &mut time_us);
        write_can(can.frames(&sun_at(next)).unwrap(), &mut time_us);
        let pixels = frame_pixels(k);
        let frame = step_frame(k, &pixels);
        for d in udp.datagrams(&frame).unwrap() {
            time_us += 100;
            udp_log
                .write_record(&UdpRecord {
                    time_us,
                    source_port: 40000,
                    destination_port: 15001,
                    payload: d,
                })
                .unwrap();
        }
        time_us += 50_000;
    }
    let save = Command {
        sequence: 1,
        kind: CommandKind::SaveCheckpoint,
    };
    // Commands come from node 1, the default `[commands] can_source_nodes`; telemetry from 10.
    let mut ground = CanFramer::new(1, false);
    write_can(ground.frames(&save).unwrap(), &mut time_us);
    can_log.flush().unwrap();
    udp_log.flush().unwrap();
    vec![can_path, udp_path]
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn live_and_replayed_scenarios_give_the_same_model() {
    let dir = temp_dir("replay");
    let mut peer = Peer::new().await;
    let live_checkpoint = dir.join("live.bin");
    let config = peer.config(live_checkpoint.clone());
    let record = dir.join("record");
    let handle = start_component(&config, LearnerKind::NearestKeyframe, Some(record.clone())).await;
    let started = Instant::now();
    for k in 0..STEPS {
        send_step(&mut peer, k, &handle).await;
        // One frame at a time, as the real camera would: nothing is dropped from the queue.
        let deadline = Instant::now() + Duration::from_secs(5);
        while handle.worker_snapshot().frames_processed < u64::from(k + 1) {
            assert!(Instant::now() < deadline, "frame {k} not processed");
            tokio::time::sleep(Duration::from_millis(2)).await;
        }
    }
    peer.command(1, CommandKind::SaveCheckpoint, handle.telemetry_addr)
        .await;
    assert_eq!(peer.wait_ack(1).await.status, AckStatus::Ok);
    let live_duration = started.elapsed();
    handle.shutdown().await;
    let live = std::fs::read(&live_checkpoint).unwrap();

    let logs = vec![record.join("udp.rec"), record.join("can.log")];
    let (fast, summary) = replay_checkpoint(
        &peer,
        &logs,
        &dir.join("fast.bin"),
        ReplaySpeed::AsFastAsPossible,
    )
    .await;
    assert!(
        fast == live,
        "as-fast-as-possible replay differs from the live run"
    );
    assert_eq!(summary.counters.bus.frames_received, u64::from(STEPS));
    assert_eq!(summary.frames_used, u64::from(STEPS));
    assert_eq!(summary.rounds, 5);
    assert_eq!(summary.predictions_sent, u64::from(STEPS - 1));
    assert_eq!(summary.load.can_frames, 0);

    let replay_started = Instant::now();
    let (timed, _) = replay_checkpoint(
        &peer,
        &logs,
        &dir.join("timed.bin"),
        ReplaySpeed::Scaled(2.0),
    )
    .await;
    assert!(
        timed == live,
        "replay at original timing differs from the live run"
    );
    // Half the recorded span (less the live run's start-up before the first datagram).
    assert!(
        replay_started.elapsed() + Duration::from_millis(200) >= live_duration / 2 / 2,
        "replay at half speed-up ran too fast: {:?} vs live {:?}",
        replay_started.elapsed(),
        live_duration
    );

    let mixed = write_mixed_logs(&dir);
    let (from_can, summary) = replay_checkpoint(
        &peer,
        &mixed,
        &dir.join("mixed.bin"),
        ReplaySpeed::AsFastAsPossible,
    )
    .await;
    assert!(summary.load.can_frames > 0 && summary.counters.can.transfers > 0);
    assert_eq!(summary.counters.can.rejected_total(), 0, "{summary:#?}");
    assert!(
        from_can == live,
        "telemetry over CAN gives a different model than over UDP: {summary:#?}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

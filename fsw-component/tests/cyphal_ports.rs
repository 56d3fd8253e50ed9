//! Configured Cyphal port-IDs and telemetry source node-IDs carry traffic: a scenario with
//! its telemetry and commands on moved subject-IDs (candump log, from the configured AOCS
//! and navigation nodes) and its frames in a UDP recording is replayed through the
//! component's own engine. With the moved configuration every frame is trained on, the
//! decoys (telemetry on the ICD default subjects, a Sun vector from the navigation node) are
//! counted and dropped, and the command on the moved subject is executed; with the default
//! configuration the same logs train nothing (the telemetry is on subjects it does not take).

mod component_support;

use component_support::*;
use fsw_component::config::ComponentConfig;
use fsw_component::cyphal_config::SubjectIds;
use fsw_component::logfmt::candump::{CanId, CanLogFrame, CanLogRecord, CanLogWriter, FrameData};
use fsw_component::logfmt::udprec::{UdpRecord, UdpRecordingWriter};
use fsw_component::outbound::{CanFramer, UdpFramer};
use fsw_component::runtime::{build_learner, run_replay, LearnerKind, ReplaySpeed};
use fsw_component::transport::RawCanFrame;
use interfaces::messages::{Command, CommandKind};
use std::path::{Path, PathBuf};

const STEPS: u32 = 6;
const AOCS: u8 = 20;
const NAVIGATION: u8 = 21;

fn moved() -> SubjectIds {
    SubjectIds {
        sun_vector: 1100,
        target_pose: 1101,
        camera_frame: 1200,
        command: 1300,
        command_ack: 1301,
        health_status: 1400,
        event: 1401,
        rendered_prediction: 1402,
    }
}

/// Telemetry and a SAVE_CHECKPOINT on the moved subjects, decoys on the default ones.
fn write_logs(dir: &Path) -> (Vec<PathBuf>, u64, u64) {
    let can_path = dir.join("moved.log");
    let udp_path = dir.join("moved.rec");
    let mut can_log = CanLogWriter::new(std::fs::File::create(&can_path).unwrap());
    let mut udp_log = UdpRecordingWriter::new(std::fs::File::create(&udp_path).unwrap()).unwrap();
    let mut aocs = CanFramer::new(AOCS, false).with_subjects(moved());
    let mut navigation = CanFramer::new(NAVIGATION, false).with_subjects(moved());
    let mut decoy_default_subjects = CanFramer::new(NAVIGATION, false);
    let mut udp = UdpFramer::default();
    let mut time_us = 1_700_000_000_000_000u64;
    let mut write_can = |frames: Vec<RawCanFrame>, time_us: &mut u64| {
        for f in frames {
            *time_us += 100;
            let frame = CanLogFrame::Classic {
                id: CanId::Extended(f.id()),
                data: FrameData::new(f.data()).unwrap(),
                len8_dlc: None,
            };
            let record = CanLogRecord {
                timestamp_us: *time_us,
                interface: "vcan0".into(),
                frame,
                direction: None,
            };
            can_log.write_record(&record).unwrap();
        }
    };
    let mut wrong_source = 0;
    let mut decoy_frames = 0;
    for k in 0..STEPS {
        let times = if k == 0 {
            vec![0, 1_000_000]
        } else {
            vec![u64::from(k + 1) * 1_000_000]
        };
        for t in times {
            write_can(navigation.frames(&pose_at(t)).unwrap(), &mut time_us);
            write_can(aocs.frames(&sun_at(t)).unwrap(), &mut time_us);
            // Decoys: a pose on the ICD's subject (not taken), a Sun vector from navigation.
            let decoy = decoy_default_subjects.frames(&pose_at(t + 10)).unwrap();
            decoy_frames += decoy.len() as u64;
            write_can(decoy, &mut time_us);
            write_can(navigation.frames(&sun_at(t + 10)).unwrap(), &mut time_us);
            wrong_source += 1;
        }
        let pixels = frame_pixels(k);
        let frame = step_frame(k, &pixels);
        for d in udp.datagrams(&frame).unwrap() {
            time_us += 100;
            let record = UdpRecord {
                time_us,
                source_port: 40000,
                destination_port: 15001,
                payload: d,
            };
            udp_log.write_record(&record).unwrap();
        }
        time_us += 50_000;
    }
    let save = Command {
        sequence: 1,
        kind: CommandKind::SaveCheckpoint,
    };
    let mut ground = CanFramer::new(1, false).with_subjects(moved());
    write_can(ground.frames(&save).unwrap(), &mut time_us);
    can_log.flush().unwrap();
    udp_log.flush().unwrap();
    (vec![can_path, udp_path], wrong_source, decoy_frames)
}

async fn replay(
    config: &ComponentConfig,
    logs: &[PathBuf],
) -> fsw_component::runtime::ReplaySummary {
    run_replay(
        config,
        build_learner(config, LearnerKind::NearestKeyframe).unwrap(),
        logs,
        ReplaySpeed::AsFastAsPossible,
    )
    .await
    .unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn moved_port_ids_and_source_nodes_carry_the_scenario() {
    let dir = temp_dir("cyphal-ports");
    let peer = Peer::new().await;
    let (logs, wrong_source, decoy_frames) = write_logs(&dir);

    let checkpoint = dir.join("moved.bin");
    let mut config = peer.config(checkpoint.clone());
    config.cyphal.subjects = moved();
    config.cyphal.aocs_node_id = AOCS.into();
    config.cyphal.navigation_node_id = NAVIGATION.into();
    config.validate().unwrap();
    let summary = replay(&config, &logs).await;
    assert_eq!(summary.frames_used, u64::from(STEPS), "{summary:#?}");
    assert_eq!(summary.counters.bus.telemetry_wrong_source, wrong_source);
    assert_eq!(summary.counters.can.rejected_not_subscribed, decoy_frames);
    assert_eq!(summary.counters.bus.commands_accepted, 1);
    assert!(
        checkpoint.exists(),
        "SAVE_CHECKPOINT on the moved subject ran"
    );

    let default_checkpoint = dir.join("default.bin");
    let summary = replay(&peer.config(default_checkpoint.clone()), &logs).await;
    assert_eq!(
        summary.frames_used, 0,
        "no telemetry on the default subjects is used"
    );
    assert_eq!(summary.counters.bus.commands_accepted, 0);
    assert!(!default_checkpoint.exists());
    std::fs::remove_dir_all(&dir).unwrap();
}

//! `play` onto a live component started in-process on loopback UDP: every frame arrives,
//! synchronises with its telemetry and is used, with telemetry on the telemetry port or on
//! the frame port, paced at 100x scenario time or at full speed; a missing CAN interface and
//! bad speeds are clear errors.

use fsw_component::config::ComponentConfig;
use fsw_component::runtime::{build_learner, start, LearnerKind};
use sim_harness::busfeed::{play, BusFeedError, BusFeedOptions, PlaySpeed, PlayTargets};
use sim_harness::dataset::{generate, GenerateOptions};
use sim_harness::scenario::Scenario;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

const FRAMES: u32 = 3;

fn tiny_dataset(name: &str) -> PathBuf {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../config/scenarios/quick.toml");
    let scenario = Scenario::load(&path)
        .unwrap()
        .with_overrides(Some(FRAMES), Some(16), Some(1))
        .unwrap();
    let dir =
        std::env::temp_dir().join(format!("sim-harness-busplay-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    generate(&scenario, &dir, GenerateOptions::default(), &mut |_| {}).unwrap();
    dir
}

fn component_config(dir: &Path, sinks: &[std::net::UdpSocket]) -> ComponentConfig {
    let mut config = ComponentConfig::default();
    config.can.enabled = false;
    config.udp.frames_port = 0;
    config.udp.telemetry_port = 0;
    config.udp.health_to = sinks[0].local_addr().unwrap();
    config.udp.predictions_to = sinks[1].local_addr().unwrap();
    config.training.window_size = 2;
    config.checkpoint.path = dir.join("checkpoint.bin");
    config.checkpoint.period_s = 0;
    config
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn played_dataset_is_used_by_a_live_component() {
    let dataset = tiny_dataset("live");
    let sinks: Vec<_> = (0..2)
        .map(|_| std::net::UdpSocket::bind("127.0.0.1:0").unwrap())
        .collect();
    let config = component_config(&dataset, &sinks);
    let options = BusFeedOptions::from_config(&config);
    let n = u64::from(FRAMES);
    // Telemetry on its own port, then everything on the frame port.
    for separate_telemetry in [true, false] {
        let learner = build_learner(&config, LearnerKind::NearestKeyframe).unwrap();
        let component = start(&config, learner, None).await.unwrap();
        let targets = PlayTargets {
            frames_udp: component.frames_addr,
            telemetry_udp: separate_telemetry.then_some(component.telemetry_addr),
            can_interface: None,
        };
        // Scenario time at 100x: the 20 s between the first and last frame take 0.2 s.
        let speed = if separate_telemetry {
            PlaySpeed::Scaled(100.0)
        } else {
            PlaySpeed::Max
        };
        let started = Instant::now();
        let played = play(&dataset, &options, config.node.node_id, &targets, speed)
            .await
            .unwrap();
        if separate_telemetry {
            assert!(started.elapsed() >= Duration::from_millis(200));
        }
        assert_eq!((played.frames, played.can_frames), (n, 0));
        assert!(played.telemetry_datagrams >= 2 * n && played.frame_datagrams >= n);
        let deadline = Instant::now() + Duration::from_secs(20);
        while component.worker_snapshot().frames_processed < n && Instant::now() < deadline {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        let c = component.counters();
        let worker = component.worker_snapshot();
        assert_eq!(c.bus.frames_received, n, "{:?}", c.bus);
        assert_eq!(
            (
                c.bus.sun_decode_errors,
                c.bus.pose_decode_errors,
                c.bus.frame_decode_errors
            ),
            (0, 0, 0)
        );
        assert_eq!(c.udp.messages, 3 * n, "{:?}", c.udp);
        assert_eq!(c.sync.frames.synced, n, "{:?}", c.sync.frames);
        assert_eq!(worker.frames_used, n, "{worker:?}");
        component.shutdown().await;
    }
    let _ = std::fs::remove_dir_all(&dataset);
}

#[tokio::test]
async fn missing_can_interface_is_a_clear_error() {
    let dataset = tiny_dataset("nocan");
    let options = BusFeedOptions::from_config(&ComponentConfig::default());
    let targets = PlayTargets {
        frames_udp: "127.0.0.1:9".parse().unwrap(),
        telemetry_udp: None,
        can_interface: Some("nosuchcan7".into()),
    };
    let err = play(&dataset, &options, 42, &targets, PlaySpeed::Max)
        .await
        .unwrap_err();
    assert!(matches!(err, BusFeedError::Can { .. }), "{err}");
    assert!(err.to_string().contains("nosuchcan7"), "{err}");
    let _ = std::fs::remove_dir_all(&dataset);
}

#[test]
fn speeds_parse() {
    assert_eq!("max".parse::<PlaySpeed>(), Ok(PlaySpeed::Max));
    assert_eq!("2.5".parse::<PlaySpeed>(), Ok(PlaySpeed::Scaled(2.5)));
    for bad in ["0", "-1", "inf", "NaN", "fast"] {
        let err = bad.parse::<PlaySpeed>().unwrap_err();
        assert!(err.contains(bad), "{err}");
    }
}

//! The `fsw-component` binary's start-up checks of its environment: a compute variable it
//! cannot honour is a usage error (status 2, the variable named) before any socket opens.

use std::path::Path;
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

/// Runs the prepared command; a process still running after 30 s (it started instead of
/// refusing) is killed and fails the test.
fn output_within_30_s(mut command: Command) -> Output {
    let mut child = command
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let start = Instant::now();
    while child.try_wait().unwrap().is_none() {
        if start.elapsed() > Duration::from_secs(30) {
            child.kill().unwrap();
            panic!("fsw-component started instead of refusing its environment");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    child.wait_with_output().unwrap()
}

#[test]
fn a_bad_compute_environment_variable_is_a_usage_error() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    for (var, value) in [
        ("GS_F32_KERNEL", "sse9"),
        ("GS_BF16_KERNEL", "fp8"),
        ("GS_DENORMALS", "sometimes"),
    ] {
        let mut command = Command::new(env!("CARGO_BIN_EXE_fsw-component"));
        command
            .args(["--config", "config/component.toml"])
            .env(var, value)
            .current_dir(&root);
        let output = output_within_30_s(command);
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert_eq!(output.status.code(), Some(2), "{var}={value}: {stderr}");
        assert!(stderr.contains(var) && stderr.contains(value), "{stderr}");
    }
}

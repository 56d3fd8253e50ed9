//! kill -9 during checkpoint saves leaves a loadable checkpoint.
//!
//! The test re-runs its own binary as a child process that saves checkpoints in a loop
//! through [`checkpoint::save_rotating`] (16 MiB each, so a save spends milliseconds in
//! write and fsync), and SIGKILLs it at varied points of a save: while the temporary is
//! being written, and at random delays after. After every kill, the newest usable slot
//! must hold a complete checkpoint no older than the last one seen, and a stale temporary
//! must be removable.

use fsw_component::checkpoint;
use std::path::{Path, PathBuf};
use std::process::{Child, Command};
use std::time::{Duration, Instant};

const CHILD_DIR_ENV: &str = "FSW_CHECKPOINT_KILL_CHILD_DIR";
const PAYLOAD_BYTES: usize = 16 << 20;
const KILLS: u64 = 12;

/// Generation `g`'s checkpoint: magic, generation, a pattern, FNV-1a of all before.
fn checkpoint_bytes(generation: u64) -> Vec<u8> {
    let mut out = Vec::with_capacity(PAYLOAD_BYTES + 24);
    out.extend_from_slice(b"okKILL01");
    out.extend_from_slice(&generation.to_le_bytes());
    let mut x = generation.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    while out.len() < PAYLOAD_BYTES + 16 {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        out.extend_from_slice(&x.to_le_bytes());
    }
    let sum = fnv1a(&out);
    out.extend_from_slice(&sum.to_le_bytes());
    out
}

fn fnv1a(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325, |h, &b| {
        (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3)
    })
}

/// The generation of a complete, intact checkpoint; None for anything else.
fn generation_of(bytes: &[u8]) -> Option<u64> {
    if bytes.len() < 24 || !bytes.starts_with(b"okKILL01") {
        return None;
    }
    let (body, sum) = bytes.split_at(bytes.len() - 8);
    (fnv1a(body).to_le_bytes() == sum).then(|| u64::from_le_bytes(body[8..16].try_into().unwrap()))
}

/// The newest slot that verifies, as load does it.
fn newest_usable(path: &Path) -> Option<u64> {
    checkpoint::slots(path)
        .iter()
        .find_map(|slot| generation_of(&checkpoint::read(slot).ok()??))
}

/// The child: saves generations after the newest on disk until killed.
fn save_forever(dir: &Path) -> ! {
    let path = dir.join("model.bin");
    let mut generation = newest_usable(&path).unwrap_or(0);
    loop {
        generation += 1;
        let bytes = checkpoint_bytes(generation);
        checkpoint::save_rotating(&path, &bytes, |b| generation_of(b).is_some())
            .expect("save in the child");
    }
}

fn spawn_child(dir: &Path) -> Child {
    Command::new(std::env::current_exe().unwrap())
        .args([
            "kill_9_during_saves_leaves_a_loadable_checkpoint",
            "--exact",
            "--nocapture",
        ])
        .env(CHILD_DIR_ENV, dir)
        .spawn()
        .expect("spawn the saving child")
}

fn wait_until(what: &str, condition: impl Fn() -> bool) {
    let deadline = Instant::now() + Duration::from_secs(30);
    while !condition() {
        assert!(Instant::now() < deadline, "timed out waiting for {what}");
        std::thread::sleep(Duration::from_micros(200));
    }
}

#[test]
fn kill_9_during_saves_leaves_a_loadable_checkpoint() {
    if let Some(dir) = std::env::var_os(CHILD_DIR_ENV) {
        save_forever(&PathBuf::from(dir));
    }
    let dir = std::env::temp_dir().join(format!("fsw-ckpt-kill-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("model.bin");
    let temporary = checkpoint::temporary_path(&path);
    let mut newest_seen = 0;
    let mut mid_write_kills = 0;
    for kill in 0..KILLS {
        let mut child = spawn_child(&dir);
        // Odd kills: as soon as a temporary exists (mid-write or mid-fsync); even kills: a
        // varied delay after the first complete save of this child, anywhere in a save.
        if kill % 2 == 1 {
            wait_until("a temporary", || temporary.exists());
        } else {
            wait_until("a newer checkpoint", || {
                newest_usable(&path).is_some_and(|g| g > newest_seen)
            });
            std::thread::sleep(Duration::from_millis(3 + 7 * kill));
        }
        let writing = temporary.exists();
        child.kill().unwrap();
        let status = child.wait().unwrap();
        assert!(!status.success(), "the child must have been killed");
        mid_write_kills += u64::from(writing);
        // Kill 0 waited for a complete save, so from then on one must always load.
        let g = newest_usable(&path).unwrap_or_else(|| panic!("kill {kill}: nothing loads"));
        assert!(
            g >= newest_seen,
            "kill {kill}: generation {g} < {newest_seen}"
        );
        newest_seen = g;
        checkpoint::remove_stale_temporary(&path).unwrap();
        assert!(!temporary.exists());
    }
    assert!(newest_seen > 0, "no save ever completed");
    assert!(
        mid_write_kills >= KILLS / 2,
        "only {mid_write_kills} kills hit a save in progress"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

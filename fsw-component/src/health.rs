//! Health helpers: resident memory from `/proc/self/status` and the receive clock.
//!
//! The receive clock is Unix time in microseconds taken once at start, advanced by the
//! monotonic clock, so it never jumps backwards when the wall clock is stepped (reassembly
//! timeouts depend on it) and candump recordings carry plausible absolute time stamps.

use std::time::{Instant, SystemTime, UNIX_EPOCH};

/// Resident set size (`VmRSS`) in bytes; None where /proc is unavailable.
pub fn memory_bytes() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    parse_vm_rss_bytes(&status)
}

/// `VmRSS:   123456 kB` -> bytes.
pub(crate) fn parse_vm_rss_bytes(status: &str) -> Option<u64> {
    let line = status.lines().find(|l| l.starts_with("VmRSS:"))?;
    let mut fields = line["VmRSS:".len()..].split_whitespace();
    let value: u64 = fields.next()?.parse().ok()?;
    match fields.next() {
        Some("kB") => value.checked_mul(1024),
        _ => None,
    }
}

/// Monotonic microseconds anchored at the Unix time of start.
#[derive(Clone, Copy, Debug)]
pub struct ReceiveClock {
    start: Instant,
    start_unix_us: u64,
}

impl ReceiveClock {
    pub fn start() -> Self {
        let start_unix_us = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map_or(0, |d| u64::try_from(d.as_micros()).unwrap_or(u64::MAX));
        Self {
            start: Instant::now(),
            start_unix_us,
        }
    }

    pub fn now_us(&self) -> u64 {
        let elapsed = u64::try_from(self.start.elapsed().as_micros()).unwrap_or(u64::MAX);
        self.start_unix_us.saturating_add(elapsed)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn vm_rss_is_parsed_in_bytes() {
        let status = "Name:\tx\nVmPeak:\t  9000 kB\nVmRSS:\t    1234 kB\nThreads:\t3\n";
        assert_eq!(parse_vm_rss_bytes(status), Some(1234 * 1024));
        assert_eq!(parse_vm_rss_bytes("VmRSS: 12 MB\n"), None);
        assert_eq!(parse_vm_rss_bytes("Name: x\n"), None);
        assert!(memory_bytes().unwrap_or(1) > 0);
    }

    #[test]
    fn the_receive_clock_moves_forward() {
        let clock = ReceiveClock::start();
        let a = clock.now_us();
        std::thread::sleep(std::time::Duration::from_millis(2));
        assert!(clock.now_us() >= a + 2000);
        assert!(a > 1_600_000_000_000_000, "anchored at Unix time");
    }
}

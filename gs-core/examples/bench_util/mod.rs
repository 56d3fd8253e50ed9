//! What the benchmark examples (`step_bench`, `raster_bench`, `loss_bench`) measure besides
//! wall time: process CPU time, the resident-memory high-water mark, medians. Linux `/proc`
//! only; elsewhere the readings are NaN (printed as such), never an error.
//!
//! Included with `mod bench_util;` (a folder without `main.rs`, so cargo does not take it
//! for an example of its own). Not every example uses every function.
#![allow(dead_code)]

/// CPU time of every thread of this process so far, ms (from /proc/self/task/*/schedstat).
/// The benchmark machine may be shared, so CPU time is reported beside wall time.
pub fn process_cpu_ms() -> f64 {
    let Ok(tasks) = std::fs::read_dir("/proc/self/task") else {
        return f64::NAN;
    };
    let mut ns = 0u64;
    for t in tasks.flatten() {
        if let Ok(s) = std::fs::read_to_string(t.path().join("schedstat")) {
            ns += s
                .split_whitespace()
                .next()
                .and_then(|v| v.parse::<u64>().ok())
                .unwrap_or(0);
        }
    }
    ns as f64 / 1e6
}

/// Process resident-memory high-water mark, MB (NaN where /proc is unavailable).
pub fn peak_rss_mb() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1))
                .and_then(|kb| kb.parse::<f64>().ok())
        })
        .map_or(f64::NAN, |kb| kb / 1024.0)
}

/// Resets the high-water mark to the current RSS (Linux >= 4.0); false where it cannot.
pub fn reset_peak_rss() -> bool {
    std::fs::write("/proc/self/clear_refs", "5").is_ok()
}

/// The median (the upper one of an even count); NaN for no values.
pub fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    if v.is_empty() {
        f64::NAN
    } else {
        v[v.len() / 2]
    }
}

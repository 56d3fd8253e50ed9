//! One process-wide allocator setting for programs that run the training step in a loop
//! (the flight component, the simulator's jobs, the benchmarks). The library never calls
//! it itself: a library must not change a process's allocator; each binary opts in at
//! start-up.
//!
//! Why: a step allocates tens of MB of short-lived buffers (images, image gradients, tile
//! records, gradient sets). glibc serves every block above its mmap threshold (128 KiB,
//! raised dynamically only up to the largest block freed so far) with a fresh `mmap`, and
//! returns freed heap tops to the kernel beyond its trim threshold, so the same buffers are
//! page-faulted in again on every step. Measured on the 100K-Gaussian, 960x600 step: about
//! 8 % of the step's CPU time (docs/bench/step.md). With blocks up to 32 MiB served from the
//! heap and freed memory kept, the process's memory stays at its high-water mark (a few MB
//! above it, measured) instead of churning, which is also what a flight computer with a
//! fixed memory budget wants.
//!
//! Invariant: results are the same bits either way (only where memory comes from changes).

/// Blocks up to this size come from the heap instead of their own `mmap` (32 MiB, glibc's
/// largest accepted value on 64-bit targets: half its maximum heap size).
pub const MMAP_THRESHOLD_BYTES: usize = 32 << 20;
/// Freed memory at the top of the heap is kept up to this size instead of trimmed.
pub const TRIM_THRESHOLD_BYTES: usize = 1 << 30;

/// Whether [`retain_freed_memory`] applied the setting.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum HeapTuning {
    Applied,
    /// Not glibc (or glibc refused a value): the allocator's defaults stay.
    Unsupported,
}

/// Serves blocks up to [`MMAP_THRESHOLD_BYTES`] from the heap and keeps freed memory up to
/// [`TRIM_THRESHOLD_BYTES`] (glibc `mallopt`). Call once at start-up, before the threads
/// that train are started. Never fails: where unsupported it changes nothing and says so.
pub fn retain_freed_memory() -> HeapTuning {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        // SAFETY: mallopt only sets allocator parameters, which glibc guards with its own
        // lock; the values are within the documented ranges (checked by the return value).
        let mmap_ok = unsafe { libc::mallopt(libc::M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES as i32) };
        // SAFETY: as above.
        let trim_ok = unsafe { libc::mallopt(libc::M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES as i32) };
        if mmap_ok == 1 && trim_ok == 1 {
            return HeapTuning::Applied;
        }
    }
    HeapTuning::Unsupported
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn glibc_accepts_the_setting_and_memory_still_works() {
        let tuning = retain_freed_memory();
        if cfg!(all(target_os = "linux", target_env = "gnu")) {
            assert_eq!(tuning, HeapTuning::Applied);
        }
        // A block just under the threshold, freed and allocated again, holds what is
        // written to it (the allocator stays usable after the change).
        for round in 0..3u8 {
            let mut block = vec![round; MMAP_THRESHOLD_BYTES - 4096];
            block[12_345] = round.wrapping_add(1);
            assert_eq!(block[0], round);
            assert_eq!(block[12_345], round.wrapping_add(1));
        }
    }
}

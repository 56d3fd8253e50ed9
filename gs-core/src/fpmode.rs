//! The floating-point denormal mode of the threads that train: flush-to-zero (FTZ) and
//! denormals-are-zero (DAZ), set deliberately per thread by each binary at start-up. The
//! library never sets it by itself (like `gs_core::heap`): a library must not change the
//! arithmetic of a thread it does not own; the binaries opt in.
//!
//! Why: the networks' products and activations and Adam's moment updates can produce and
//! then consume subnormal floats (tiny gradients, squared-gradient moments decaying towards
//! zero). x86 cores handle those through a microcode assist costing on the order of a
//! hundred cycles per operation; with FTZ (MXCSR bit 15: subnormal results become 0) and
//! DAZ (bit 6: subnormal inputs read as 0) the same instructions run at full speed. A
//! previous engineer measured the training step at about 1.46x the CPU time without them on
//! this project's Intel Xeon (FTZ/DAZ set through a preload library). On aarch64 the FPCR
//! FZ bit (24) does both jobs for f32 and f64. On other targets nothing is changed:
//! [`is_supported`] says so and every thread reads as [`DenormalMode::Ieee`].
//!
//! The mode is per thread (a register of each core's state, saved and restored with the
//! thread), so it is set on the calling thread and on every worker of each rayon pool
//! that trains ([`pool_builder`], [`init_global_pool`]); new threads may inherit the
//! creator's setting, but the binaries do not rely on that.
//!
//! Invariants: for a fixed mode (and thread count) results stay deterministic, bit for bit
//! run to run; between the two modes results may differ in the last bits wherever a value
//! falls below f32::MIN_POSITIVE (1.2e-38), far below anything an image or a loss resolves.
//! Only bits 15 and 6 (x86) or bit 24 (aarch64) are touched; rounding mode and exception
//! masks stay as they were. Tests run with the platform's default (IEEE) unless they set it.
//!
//! The switch: `GS_DENORMALS=ftz|ieee` in the environment ([`mode_from_env`], read once at
//! start by each binary; default FTZ), and the flight component's `[training] denormals`.

use std::fmt;
use std::marker::PhantomData;
use std::str::FromStr;

/// The environment variable the binaries read at start ([`mode_from_env`]).
pub const ENV_VAR: &str = "GS_DENORMALS";

/// The "environment" part of the binaries' and benchmarks' `--help`.
pub const ENV_HELP: &str = "environment:
  GS_DENORMALS=ftz|ieee  denormal mode of every thread that computes
                         (default ftz: flush-to-zero and denormals-are-zero)
  GS_F32_KERNEL=avx512|avx2|gemm-crate
                         the networks' f32 product kernel (default: avx512 where
                         the CPU has it, else avx2; avx512 and avx2 give the same
                         bits, the gemm crate other ones)
  GS_BF16_KERNEL=amx|avx512bf16
                         the bf16 products' kernel when a configuration asks for
                         bf16 (default: amx where the CPU and Linux allow it, else
                         avx512bf16; they give different last bits)";

/// How a thread's floating-point unit treats subnormal (denormal) numbers.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum DenormalMode {
    /// Subnormal results become zero and subnormal inputs read as zero (x86 FTZ + DAZ,
    /// aarch64 FZ): fast, the default for the threads that train.
    #[default]
    FlushToZero,
    /// IEEE 754 gradual underflow, the platform's default.
    Ieee,
}

impl DenormalMode {
    /// The name the config file and the benchmarks' headers use.
    pub fn name(self) -> &'static str {
        match self {
            Self::FlushToZero => "flush-to-zero",
            Self::Ieee => "ieee",
        }
    }
}

impl fmt::Display for DenormalMode {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for DenormalMode {
    type Err = String;

    /// `flush-to-zero` (or `ftz`) and `ieee`, exactly; anything else is an error that
    /// names the accepted values.
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "flush-to-zero" | "ftz" => Ok(Self::FlushToZero),
            "ieee" => Ok(Self::Ieee),
            other => Err(format!(
                "denormal mode {other:?}: want \"flush-to-zero\" (or \"ftz\") or \"ieee\""
            )),
        }
    }
}

/// Whether this target can change the mode (x86_64, aarch64). Elsewhere every call here
/// is a no-op and [`current`] reads [`DenormalMode::Ieee`].
pub const fn is_supported() -> bool {
    cfg!(any(target_arch = "x86_64", target_arch = "aarch64"))
}

/// The calling thread's mode: [`DenormalMode::FlushToZero`] only when every flush bit is
/// set (on x86 both FTZ and DAZ; a lone FTZ set by foreign code reads as `Ieee`).
pub fn current() -> DenormalMode {
    if raw::flush_bits_set(raw::read()) {
        DenormalMode::FlushToZero
    } else {
        DenormalMode::Ieee
    }
}

/// Sets the calling thread's mode; returns the one it had (as [`current`] read it).
pub fn set_for_current_thread(mode: DenormalMode) -> DenormalMode {
    let before = raw::read();
    raw::write(raw::with_mode(before, mode));
    if raw::flush_bits_set(before) {
        DenormalMode::FlushToZero
    } else {
        DenormalMode::Ieee
    }
}

/// Sets a mode on the calling thread until dropped, then restores the whole register as it
/// was (bit for bit, so a partial setting made by foreign code survives too). Not `Send`:
/// the setting belongs to the thread that made it.
#[must_use = "the previous mode is restored when the guard is dropped"]
pub struct DenormalGuard {
    saved: raw::Register,
    _this_thread_only: PhantomData<*const ()>,
}

impl DenormalGuard {
    pub fn new(mode: DenormalMode) -> Self {
        let saved = raw::read();
        raw::write(raw::with_mode(saved, mode));
        Self {
            saved,
            _this_thread_only: PhantomData,
        }
    }
}

impl Drop for DenormalGuard {
    fn drop(&mut self) {
        raw::write(self.saved);
    }
}

/// A rayon pool builder whose worker threads set `mode` as they start. Add the thread count
/// and names to it; a later `start_handler` on it would replace this one.
pub fn pool_builder(mode: DenormalMode) -> rayon::ThreadPoolBuilder {
    rayon::ThreadPoolBuilder::new().start_handler(move |_| {
        set_for_current_thread(mode);
    })
}

/// For a program's start: sets `mode` on the calling thread and builds rayon's global pool
/// (`threads` workers, or rayon's default for `None`) with `mode` on every worker. Fails if
/// the global pool already exists (something used rayon first, or this ran twice).
pub fn init_global_pool(
    mode: DenormalMode,
    threads: Option<usize>,
) -> Result<(), rayon::ThreadPoolBuildError> {
    set_for_current_thread(mode);
    let mut builder = pool_builder(mode);
    if let Some(n) = threads {
        builder = builder.num_threads(n);
    }
    builder.build_global()
}

/// The mode `GS_DENORMALS` asks for: `None` when unset or empty, an error naming the
/// variable for any other value than those [`DenormalMode::from_str`] accepts.
pub fn mode_from_env() -> Result<Option<DenormalMode>, String> {
    match std::env::var(ENV_VAR) {
        Ok(v) if v.is_empty() => Ok(None),
        Ok(v) => v.parse().map(Some).map_err(|e| format!("{ENV_VAR}: {e}")),
        Err(std::env::VarError::NotPresent) => Ok(None),
        Err(std::env::VarError::NotUnicode(_)) => Err(format!("{ENV_VAR} is not UTF-8")),
    }
}

/// [`mode_from_env`] (default flush-to-zero) applied by [`init_global_pool`]: the one call
/// a binary or benchmark makes first thing in `main`. Returns the mode set. It also checks
/// `GS_F32_KERNEL` and `GS_BF16_KERNEL` ([`crate::nn::check_kernel_env`]), so that a
/// kernel name this CPU cannot run stops the program at start, not when its first network
/// is built.
pub fn init_from_env(threads: Option<usize>) -> Result<DenormalMode, String> {
    crate::nn::check_kernel_env().map_err(|e| e.to_string())?;
    let mode = mode_from_env()?.unwrap_or_default();
    init_global_pool(mode, threads).map_err(|e| format!("rayon global pool: {e}"))?;
    Ok(mode)
}

/// The control register itself, one implementation per architecture.
#[cfg(target_arch = "x86_64")]
mod raw {
    use super::DenormalMode;
    use std::arch::asm;

    pub type Register = u32;
    /// MXCSR bit 15, flush-to-zero (subnormal results), and bit 6, denormals-are-zero
    /// (subnormal inputs).
    const FLUSH: u32 = (1 << 15) | (1 << 6);

    pub fn read() -> Register {
        let mut mxcsr: u32 = 0;
        // SAFETY: stmxcsr stores the 4-byte MXCSR to the address given, which is a live,
        // aligned, writable u32 on this stack frame; SSE is part of the x86_64 baseline.
        // (Inline asm instead of `_mm_getcsr`, deprecated in favour of it.)
        unsafe {
            asm!("stmxcsr [{}]", in(reg) &raw mut mxcsr, options(nostack, preserves_flags));
        }
        mxcsr
    }

    pub fn write(mxcsr: Register) {
        // SAFETY: ldmxcsr loads 4 bytes from a live, aligned u32. Callers only pass a value
        // read from MXCSR with bits 15 and 6 changed; both are control bits every x86_64
        // processor implements (DAZ predates x86_64), so no reserved bit gets set (which
        // would fault).
        unsafe {
            asm!("ldmxcsr [{}]", in(reg) &raw const mxcsr, options(nostack, preserves_flags, readonly));
        }
    }

    pub fn flush_bits_set(mxcsr: Register) -> bool {
        mxcsr & FLUSH == FLUSH
    }

    pub fn with_mode(mxcsr: Register, mode: DenormalMode) -> Register {
        match mode {
            DenormalMode::FlushToZero => mxcsr | FLUSH,
            DenormalMode::Ieee => mxcsr & !FLUSH,
        }
    }
}

#[cfg(target_arch = "aarch64")]
mod raw {
    use super::DenormalMode;
    use std::arch::asm;

    pub type Register = u64;
    /// FPCR bit 24, FZ: subnormal inputs and results of f32/f64 operations become zero.
    const FLUSH: u64 = 1 << 24;

    pub fn read() -> Register {
        let fpcr: u64;
        // SAFETY: reading FPCR has no side effects and is allowed at EL0.
        unsafe {
            asm!("mrs {}, fpcr", out(reg) fpcr, options(nomem, nostack, preserves_flags));
        }
        fpcr
    }

    pub fn write(fpcr: Register) {
        // SAFETY: writing FPCR is allowed at EL0; callers only pass a value read from FPCR
        // with bit 24 (FZ, a defined control bit) changed.
        unsafe {
            asm!("msr fpcr, {}", in(reg) fpcr, options(nomem, nostack, preserves_flags));
        }
    }

    pub fn flush_bits_set(fpcr: Register) -> bool {
        fpcr & FLUSH == FLUSH
    }

    pub fn with_mode(fpcr: Register, mode: DenormalMode) -> Register {
        match mode {
            DenormalMode::FlushToZero => fpcr | FLUSH,
            DenormalMode::Ieee => fpcr & !FLUSH,
        }
    }
}

/// Other targets: nothing to set; every thread is IEEE.
#[cfg(not(any(target_arch = "x86_64", target_arch = "aarch64")))]
mod raw {
    use super::DenormalMode;

    pub type Register = ();

    pub fn read() -> Register {}

    pub fn write(_: Register) {}

    pub fn flush_bits_set(_: Register) -> bool {
        false
    }

    pub fn with_mode(_: Register, _: DenormalMode) -> Register {}
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::hint::black_box;

    /// f32::MIN_POSITIVE / 4, computed at run time: a subnormal result under IEEE.
    fn quarter_of_smallest_normal() -> f32 {
        black_box(f32::MIN_POSITIVE) * black_box(0.25)
    }

    /// Twice the smallest subnormal: reads the subnormal input (DAZ flushes it first).
    fn double_smallest_subnormal() -> f32 {
        black_box(f32::from_bits(1)) * black_box(2.0)
    }

    #[test]
    fn flush_to_zero_flushes_results_and_inputs_and_ieee_keeps_them() {
        let before = current();
        {
            let _ftz = DenormalGuard::new(DenormalMode::FlushToZero);
            if is_supported() {
                assert_eq!(current(), DenormalMode::FlushToZero);
                assert_eq!(quarter_of_smallest_normal(), 0.0);
                assert_eq!(double_smallest_subnormal(), 0.0);
            }
            {
                let _ieee = DenormalGuard::new(DenormalMode::Ieee);
                assert_eq!(current(), DenormalMode::Ieee);
                let q = quarter_of_smallest_normal();
                assert!(q > 0.0 && q.is_subnormal(), "{q:e}");
                assert_eq!(q, f32::MIN_POSITIVE / 4.0);
                assert_eq!(double_smallest_subnormal(), f32::from_bits(2));
            }
            if is_supported() {
                assert_eq!(current(), DenormalMode::FlushToZero, "inner guard restored");
            }
        }
        assert_eq!(current(), before, "outer guard restored the test thread");
    }

    #[test]
    fn set_returns_the_previous_mode() {
        let _restore = DenormalGuard::new(DenormalMode::Ieee);
        let first = set_for_current_thread(DenormalMode::FlushToZero);
        assert_eq!(first, DenormalMode::Ieee);
        let second = set_for_current_thread(DenormalMode::Ieee);
        let expected = if is_supported() {
            DenormalMode::FlushToZero
        } else {
            DenormalMode::Ieee
        };
        assert_eq!(second, expected);
    }

    #[test]
    fn pool_workers_start_in_the_pool_mode() {
        let before = current();
        for mode in [DenormalMode::FlushToZero, DenormalMode::Ieee] {
            let pool = pool_builder(mode).num_threads(3).build().unwrap();
            let seen: Vec<(DenormalMode, f32)> =
                pool.install(|| rayon::broadcast(|_| (current(), quarter_of_smallest_normal())));
            assert_eq!(seen.len(), 3);
            for (worker_mode, q) in seen {
                if is_supported() {
                    assert_eq!(worker_mode, mode);
                    assert_eq!(q == 0.0, mode == DenormalMode::FlushToZero, "{q:e}");
                } else {
                    assert_eq!(worker_mode, DenormalMode::Ieee);
                }
            }
        }
        assert_eq!(current(), before, "building pools left this thread alone");
    }

    #[test]
    fn names_parse_and_unknown_ones_are_clear_errors() {
        for mode in [DenormalMode::FlushToZero, DenormalMode::Ieee] {
            assert_eq!(mode.name().parse::<DenormalMode>(), Ok(mode));
        }
        assert_eq!("ftz".parse(), Ok(DenormalMode::FlushToZero));
        assert_eq!(DenormalMode::default(), DenormalMode::FlushToZero);
        let e = "FTZ".parse::<DenormalMode>().unwrap_err();
        assert!(e.contains("\"FTZ\"") && e.contains("ieee"), "{e}");
    }
}

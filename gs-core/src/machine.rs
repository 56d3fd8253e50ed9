//! What machine a measurement ran on, for the benchmarks' headers and JSON: the CPU model,
//! how many CPUs this process may use, the instruction-set extensions the fast paths pick
//! at run time (AVX2, AVX-512F, AVX-512 BF16, AMX-BF16 on x86_64), the calling thread's
//! denormal mode ([`crate::fpmode`]) and the networks' f32 and bf16 product kernels. A
//! timing without these cannot be compared with another.
//!
//! Reads `/proc/cpuinfo` on Linux; elsewhere the model falls back to the architecture's
//! name. Never fails.

use crate::fpmode;
use crate::nn::{Bf16Kernel, F32Kernel};

/// One line: CPU model, CPUs available, the extensions that matter, e.g.
/// `Intel(R) Xeon(R) Processor, 2 CPUs available, avx2 avx512f avx512bf16 amx-bf16`
/// (a missing extension is listed as `no-avx512bf16`).
pub fn cpu_description() -> String {
    let model = cpu_model().unwrap_or_else(|| std::env::consts::ARCH.to_string());
    // What this process may use (affinity, cgroup quota), not the machine's total.
    let cpus = std::thread::available_parallelism().map_or(0, std::num::NonZero::get);
    let features = isa_features();
    if features.is_empty() {
        format!("{model}, {cpus} CPUs available")
    } else {
        format!("{model}, {cpus} CPUs available, {features}")
    }
}

/// The benchmarks' header line: [`cpu_description`], the calling thread's denormal mode
/// (the binaries set the same mode on every training thread) and the networks' f32 and
/// bf16 product kernels (`GS_F32_KERNEL` / `GS_BF16_KERNEL`, else the CPU's default; an
/// invalid setting is shown as such, the network constructors report it as an error; a
/// CPU without bf16 kernels shows "none").
pub fn header_line() -> String {
    let kernel = F32Kernel::from_env().map_or_else(|e| e.to_string(), |k| k.name().to_string());
    let bf16 = match Bf16Kernel::forced_by_env() {
        Some(forced) => forced.map_or_else(|e| e.to_string(), |k| k.name().to_string()),
        None => Bf16Kernel::detect().map_or_else(|_| "none".to_string(), |k| k.name().to_string()),
    };
    format!(
        "cpu: {}; denormals: {}; f32 kernel: {kernel}; bf16 kernel: {bf16}",
        cpu_description(),
        fpmode::current()
    )
}

/// The first "model name" of /proc/cpuinfo (x86), or its "Hardware"/"CPU part" on arm.
fn cpu_model() -> Option<String> {
    let text = std::fs::read_to_string("/proc/cpuinfo").ok()?;
    ["model name", "Hardware", "CPU part"]
        .iter()
        .find_map(|key| {
            text.lines().find_map(|line| {
                let (k, v) = line.split_once(':')?;
                (k.trim() == *key && !v.trim().is_empty()).then(|| v.trim().to_string())
            })
        })
}

/// The run-time-detected extensions the rasterizer, the loss and the networks choose
/// their code by; empty off x86_64.
fn isa_features() -> String {
    #[cfg(target_arch = "x86_64")]
    {
        let found = [
            ("avx2", std::arch::is_x86_feature_detected!("avx2")),
            ("avx512f", std::arch::is_x86_feature_detected!("avx512f")),
            (
                "avx512bf16",
                std::arch::is_x86_feature_detected!("avx512bf16"),
            ),
            // Usable tiles: the CPU has them and Linux granted this process the state.
            ("amx-bf16", crate::nn::amx::AmxKernels::detect().is_ok()),
        ];
        found
            .iter()
            .map(|&(name, present)| {
                if present {
                    name.to_string()
                } else {
                    format!("no-{name}")
                }
            })
            .collect::<Vec<_>>()
            .join(" ")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        String::new()
    }
}

/// CPU time of this process so far (user + system, every thread), seconds; `None` where
/// the platform does not report it. Benchmarks and experiments report it beside wall time:
/// on a shared or throttled machine the two differ.
pub fn process_cpu_s() -> Option<f64> {
    #[cfg(target_os = "linux")]
    {
        // SAFETY: getrusage only writes the struct it is given; zeroed is a valid rusage.
        let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
        if unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut usage) } != 0 {
            return None;
        }
        let seconds = |t: libc::timeval| t.tv_sec as f64 + 1e-6 * t.tv_usec as f64;
        Some(seconds(usage.ru_utime) + seconds(usage.ru_stime))
    }
    #[cfg(not(target_os = "linux"))]
    None
}

/// For a test that needs something this machine may lack (a CPU extension, a GPU): prints
/// a visible `SKIPPED` notice naming `why` and the variable that forbids the skip, or
/// panics when `require_env` is set to `1` (a machine that must run the test: `tests/run.sh`
/// sets it where the CPU has the feature). The caller returns after it.
pub fn skip_unless_required(require_env: &str, why: &str) {
    if std::env::var(require_env).is_ok_and(|v| v == "1") {
        panic!("{require_env}=1 but this test cannot run here: {why}");
    }
    eprintln!("SKIPPED (set {require_env}=1 to fail instead): {why}");
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn description_names_the_cpu_count_and_the_extensions() {
        let d = cpu_description();
        assert!(d.contains(" CPUs available"), "{d}");
        assert!(!d.starts_with(','), "{d}");
        if cfg!(target_arch = "x86_64") {
            assert!(d.contains("avx512bf16") && d.contains("amx-bf16"), "{d}");
        }
        let line = header_line();
        assert!(
            line.starts_with("cpu: ")
                && line.contains("; denormals: ")
                && line.contains("; f32 kernel: ")
                && line.contains("; bf16 kernel: "),
            "{line}"
        );
    }

    #[test]
    fn a_skip_returns_unless_required_and_panics_when_required() {
        // Variable names used by no other test, so setting one races with nothing.
        skip_unless_required("GS_TEST_SKIP_NEVER_SET", "nothing");
        std::env::set_var("GS_TEST_SKIP_REQUIRED", "1");
        let required = std::panic::catch_unwind(|| {
            skip_unless_required("GS_TEST_SKIP_REQUIRED", "the feature is absent");
        });
        let message = required.expect_err("a required skip must panic");
        let text = message.downcast_ref::<String>().expect("formatted message");
        assert!(text.contains("the feature is absent"), "{text}");
    }
}

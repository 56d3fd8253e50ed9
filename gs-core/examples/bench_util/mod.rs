//! What the benchmark examples measure besides wall time: process CPU time, the
//! resident-memory high-water mark, medians (Linux `/proc` only; elsewhere the readings
//! are NaN, printed as such, never an error); and the setup several of them share:
//! `--help`, `--name VALUE` arguments, the denormal mode of their threads (`GS_DENORMALS`,
//! as the binaries do: [`init_threads`]), the machine fields of their JSON lines, the
//! random Gaussian cloud of the rasterizer benchmarks, the `main` of an example that
//! runs a `bench` module ([`bench_main!`]), and the machine's tuned GEMM rate measured
//! beside a benchmark (`reference.rs`).
//!
//! Included with `#[macro_use] mod bench_util;` (a folder without `main.rs`, so cargo
//! does not take it for an example of its own; gs-wgpu's examples include it by path). Not every example uses every item.
#![allow(dead_code, unused_macros)]

pub mod reference;

use gs_core::raster::GaussianView;
use gs_core::rng::SplitMix64;

/// The `main` of an example whose benchmark is `bench::run`: `--help` prints `$usage`,
/// then it sets the threads' denormal mode ([`init_threads`]) and runs the benchmark.
macro_rules! bench_main {
    ($name:literal, $usage:expr) => {
        fn main() {
            let args: Vec<String> = std::env::args().skip(1).collect();
            crate::bench_util::exit_if_help(&args, $usage);
            crate::bench_util::init_threads($name, None);
            bench::run();
        }
    };
}

/// With `--help` or `-h` among `args`: prints `usage` (and the environment every example
/// reads) on stdout and exits 0, before any work is done.
pub fn exit_if_help(args: &[String], usage: &str) {
    if args.iter().any(|a| a == "--help" || a == "-h") {
        println!("{}\n\n{}", usage.trim_end(), gs_core::fpmode::ENV_HELP);
        std::process::exit(0);
    }
}

/// Sets the denormal mode `GS_DENORMALS` asks for (default flush-to-zero) on this thread
/// and on every worker of rayon's global pool, which it builds with `threads` workers
/// (rayon's default for `None`), so a benchmark times the arithmetic the binaries run.
/// A bad value or an already built pool ends the process with status 2.
pub fn init_threads(name: &str, threads: Option<usize>) -> gs_core::fpmode::DenormalMode {
    gs_core::fpmode::init_from_env(threads).unwrap_or_else(|e| {
        eprintln!("{name}: {e}");
        std::process::exit(2);
    })
}

/// The value after `name` in `args` (None if absent).
pub fn arg_str<'a>(args: &'a [String], name: &str) -> Option<&'a str> {
    let i = args.iter().position(|a| a == name)?;
    args.get(i + 1).map(String::as_str)
}

/// The value after `name` in `args`, parsed as a count (None if absent or not a number).
pub fn arg(args: &[String], name: &str) -> Option<usize> {
    arg_str(args, name).and_then(|v| v.parse().ok())
}

/// `"cpu":"...","denormals":"..."`, to put into a JSON line: which machine and arithmetic
/// the numbers beside them come from (`gs_core::machine`).
pub fn json_machine_fields() -> String {
    format!(
        "\"cpu\":{},\"denormals\":\"{}\"",
        json_string(&gs_core::machine::cpu_description()),
        gs_core::fpmode::current()
    )
}

/// `text` as a JSON string literal, quotes included.
pub fn json_string(text: &str) -> String {
    let mut out = String::with_capacity(text.len() + 2);
    out.push('"');
    for c in text.chars() {
        match c {
            '"' => out.push_str("\\\""),
            '\\' => out.push_str("\\\\"),
            c if (c as u32) < 0x20 => out.push_str(&format!("\\u{:04x}", c as u32)),
            c => out.push(c),
        }
    }
    out.push('"');
    out
}

/// Gaussians as the rasterizer's parameter arrays, RGB channels.
pub struct Cloud {
    pub means: Vec<f32>,
    pub log_scales: Vec<f32>,
    pub rotations: Vec<f32>,
    pub opacity_logits: Vec<f32>,
    pub channels: Vec<f32>,
}

impl Cloud {
    /// Room for `n` Gaussians, none yet.
    pub fn with_capacity(n: usize) -> Self {
        Self {
            means: Vec::with_capacity(3 * n),
            log_scales: Vec::with_capacity(3 * n),
            rotations: Vec::with_capacity(4 * n),
            opacity_logits: Vec::with_capacity(n),
            channels: Vec::with_capacity(3 * n),
        }
    }

    pub fn view(&self) -> GaussianView<'_> {
        GaussianView {
            means: &self.means,
            log_scales: &self.log_scales,
            rotations: &self.rotations,
            opacity_logits: &self.opacity_logits,
            channels: &self.channels,
            n_channels: 3,
        }
    }
}

/// `n` Gaussians uniform in a 2 m ball at the origin, sized so neighbours overlap;
/// random rotations, opacities and colours.
pub fn random_cloud(n: usize, seed: u64) -> Cloud {
    let mut rng = SplitMix64::new(seed);
    let sigma = 2.0 * (4.0 / n as f32).sqrt().min(0.05);
    let mut c = Cloud::with_capacity(n);
    for _ in 0..n {
        let p = loop {
            let p = glam::Vec3::new(
                rng.uniform(-1.0, 1.0),
                rng.uniform(-1.0, 1.0),
                rng.uniform(-1.0, 1.0),
            );
            if p.length_squared() <= 1.0 {
                break p * 2.0;
            }
        };
        c.means.extend(p.to_array());
        for _ in 0..3 {
            c.log_scales.push((sigma * rng.uniform(0.3, 1.5)).ln());
        }
        for _ in 0..4 {
            c.rotations.push(rng.uniform(-1.0, 1.0));
        }
        c.opacity_logits.push(rng.uniform(-1.0, 3.0));
        for _ in 0..3 {
            c.channels.push(rng.uniform(0.0, 1.0));
        }
    }
    c
}

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

/// Median wall ms and mean process CPU ms per call of `f` over `runs` calls after one
/// warm-up call, and the warm-up's result.
pub fn time_calls<T>(runs: usize, mut f: impl FnMut() -> T) -> (f64, f64, T) {
    let out = f();
    let mut walls = Vec::with_capacity(runs);
    let cpu0 = process_cpu_ms();
    for _ in 0..runs {
        let t = std::time::Instant::now();
        std::hint::black_box(f());
        walls.push(t.elapsed().as_secs_f64() * 1e3);
    }
    let cpu = (process_cpu_ms() - cpu0) / runs as f64;
    (median(walls), cpu, out)
}

/// The median (the upper one of an even count); NaN for no values.
pub fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    if v.is_empty() {
        f64::NAN
    } else {
        v[v.len() / 2]
    }
}

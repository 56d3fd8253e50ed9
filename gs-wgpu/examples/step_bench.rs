//! Training-step benchmark of configuration (d) (issue 5): per-stage time of
//! [`SunAwareTrainer::step`], whole-step time, peak memory, and each network stage's distance
//! from its GEMM floor.
//!
//! Scene: `N` Gaussians filling a satellite-sized box (3 x 1.5 x 1.5 m) in front of the
//! camera (`--scene volume`, the default), or sampled on the box's faces (`--scene
//! surface`, closer to a trained model, where the front faces hide the back ones); random
//! but seeded scales, rotations and opacities; a seeded random target image, no mask.
//! The camera sees the box from a three-quarter view at 6 m (field of view 0.7 rad), the
//! Sun comes from the side.
//!
//! For every size x image: one warm-up step, then `--repeats` steps (default 5); medians of
//! every stage of [`StepTimings`], of the whole step and of the process CPU time per step
//! (all threads; the machine may be shared, so `cpu / threads` is what the wall time would
//! be with the cores to ourselves). Peak RSS is the process high-water mark over the
//! measured steps (reset through `/proc/self/clear_refs` before them; it includes the
//! model, its optimiser state and every buffer the step holds at once). Every size x image
//! (x setting) runs in its own child process, so memory the allocator kept from an
//! earlier configuration never counts.
//!
//! Network stages: FLOPs from the rows actually evaluated (the step's `visible`) times the
//! layer shapes (forward `2 k n` per row and layer; backward twice that: weight and input
//! gradients). The floor is this machine's time for the very same GEMMs (the network's
//! layer shapes, its own products): each layer's product on matrices of that shape, blocked
//! over `gs_core::nn::mlp::BLOCK_ROWS` rows in parallel as the MLP runs them. After the
//! measured steps, `--repeats` more steps each followed at once by one timing of the
//! floor; `ratio` is the median of those per-step `stage time / floor time` (a host whose
//! speed drifts between a stage and its floor would otherwise show up as distance from the
//! floor). The printed stage and floor ms are the medians of those paired repeats.
//!
//! `cargo run --release -p gs-wgpu --example step_bench -- [--json] [--sizes 10000,50000,100000]
//! [--images 480x300,960x600] [--threads N] [--repeats N] [--scene volume|surface]
//! [--set NAME=VALUE,...] [--ab SWITCH] [--backend cpu,wgpu] [--gpu-atomic] [--default-malloc]`
//!
//! `--backend cpu,wgpu` measures each configuration on each listed backend (default `cpu`;
//! `wgpu` needs a Vulkan adapter). On `wgpu` the trainer is
//! device-resident: the repeats run as one `step_many` batch and only the whole step is
//! timed, its stages from the device's timestamp queries where the adapter has them (no
//! CPU floors). On a software Vulkan driver (Mesa's lavapipe) the
//! wgpu rows are CPU timings of the GPU kernels, not GPU timings; the adapter is printed
//! with the results. The wgpu backend opens deterministic (`BackendKind::open`, as the
//! component does); `--gpu-atomic` uses the float-atomic backward instead.
//!
//! The process keeps freed memory as the component and the simulator do
//! (`gs_core::heap::retain_freed_memory`); `--default-malloc` keeps glibc's defaults. Its
//! threads run in the denormal mode the binaries train in (`GS_DENORMALS`, default
//! flush-to-zero; `gs_core::fpmode`), printed in the header with the CPU.
//!
//! `--set` changes settings of `SunAwareConfig` (defaults otherwise): the speed switches
//! (`NAME=on|off`), `mlp_precision=f32|bf16` and `appearance_hidden_width=N`; `--ab SWITCH`
//! measures every size and image twice in the same run, the switch off then on, so a
//! change's before/after sits side by side under the same machine load.
//!
//! Files: `step_bench/setup.rs` (scene and camera), `runs.rs` (one configuration's
//! measurement, in a child process), `floors.rs` (the GEMM floors); this one the CLI and
//! the report.
//!
//! Prints tables by default, one JSON object per line with `--json`. The targets
//! are printed beside the numbers with PASS/MISS: every network stage within 1.5x of its
//! floor, peak memory under 0.5 GB at 100K Gaussians, the step under 0.4 s at 100K
//! Gaussians and 960x600.

use std::time::Instant;

#[path = "../../gs-core/examples/bench_util/mod.rs"]
mod bench_util;
use bench_util::{
    arg_str, exit_if_help, json_machine_fields, median, peak_rss_mb, process_cpu_ms, reset_peak_rss,
};

/// The device engines of this bench: wgpu (gs-wgpu is this example's crate).
const ENGINES: gs_core::engine::DeviceEngines = gs_core::engine::DeviceEngines {
    wgpu: Some(gs_wgpu::open_engine),
};

use glam::{Quat, Vec3};
use gs_core::model::{GaussianModel, Param};
use gs_core::nn::mlp::BLOCK_ROWS;
use gs_core::nn::{MatmulPrecision, Mlp, Products, SceneBox};
use gs_core::rng::SplitMix64;
use gs_core::sunaware::{
    BackendKind, Observation, StepTimings, SunAwareConfig, SunAwareModel, SunAwareTrainer, Variant,
};
use gs_core::{Camera, Intrinsics};
use rayon::prelude::*;

const TARGET_MLP_RATIO: f64 = 1.5;
const TARGET_PEAK_MB: f64 = 500.0;
const TARGET_STEP_MS: f64 = 400.0;

#[derive(Clone, Copy, PartialEq)]
enum SceneKind {
    Volume,
    Surface,
}

struct NetStage {
    name: &'static str,
    rows: usize,
    gflop: f64,
    /// Medians over the paired repeats (see [`measure`]).
    stage_ms: f64,
    floor_ms: f64,
    /// Median over the repeats of each step's stage time over the floor timed right
    /// after that step (not the ratio of the medians).
    ratio: f64,
}

impl NetStage {
    fn ratio(&self) -> f64 {
        self.ratio
    }

    fn gemm_gflops(&self) -> f64 {
        self.gflop / (self.floor_ms * 1e-3)
    }
}

struct Measured {
    label: String,
    gaussians: usize,
    width: u32,
    height: u32,
    /// Gaussians that survived culling, and rows the networks evaluated (medians).
    visible: usize,
    rows: usize,
    stages: StepTimings,
    /// Median of each step's time outside the named stages (not the difference of the
    /// medians, which can come out negative).
    other_ms: f64,
    cpu_ms: f64,
    peak_rss_mb: f64,
    nets: Vec<NetStage>,
    /// Precision of the networks' products (and of their floor).
    precision: MatmulPrecision,
}

fn print_step(m: &Measured, json: bool, scene_name: &str, threads: usize, repeats: usize) {
    let s = &m.stages;
    if json {
        let stages: Vec<String> = s
            .stages()
            .iter()
            .map(|(name, ms)| format!("\"{name}_ms\":{ms:.3}"))
            .collect();
        println!(
            "{{\"kind\":\"step\",{},\"settings\":\"{}\",\"scene\":\"{scene_name}\",\"gaussians\":{},\"width\":{},\"height\":{},\"threads\":{threads},\"repeats\":{repeats},\"visible\":{},\"rows\":{},{},\"other_ms\":{:.3},\"step_ms\":{:.3},\"cpu_ms\":{:.3},\"peak_rss_mb\":{:.1}}}",
            json_machine_fields(), m.label, m.gaussians, m.width, m.height, m.visible, m.rows, stages.join(","),
            m.other_ms, s.total_ms, m.cpu_ms, m.peak_rss_mb
        );
        for net in &m.nets {
            println!(
                "{{\"kind\":\"mlp_stage\",\"settings\":\"{}\",\"gaussians\":{},\"width\":{},\"height\":{},\"stage\":\"{}\",\"precision\":\"{}\",\"rows\":{},\"gflop\":{:.4},\"stage_ms\":{:.3},\"floor_ms\":{:.3},\"gemm_gflops\":{:.2},\"ratio\":{:.3}}}",
                m.label, m.gaussians, m.width, m.height, net.name, precision_name(m.precision), net.rows, net.gflop,
                net.stage_ms, net.floor_ms, net.gemm_gflops(), net.ratio()
            );
        }
    } else {
        println!(
            "{:>7} {:>8} {:>7} {:>7} | {:>6.1} {:>6.1} {:>6.1} {:>6.1} {:>7.1} {:>6.1} {:>7.1} {:>6.1} {:>7.1} {:>7.1} {:>7.1} {:>6.1} {:>6.1} {:>6.1} | {:>7.1} {:>7.1} {:>7.0} | {}",
            m.gaussians,
            format!("{}x{}", m.width, m.height),
            m.visible,
            m.rows,
            s.project_ms,
            s.sort_bin_ms,
            s.contribution_ms,
            s.shadow_pass_ms,
            s.phi_forward_ms,
            s.psi_forward_ms,
            s.blend_forward_ms,
            s.loss_ms,
            s.blend_backward_ms,
            s.project_backward_ms,
            s.phi_backward_ms,
            s.psi_backward_ms,
            s.optimizer_ms,
            m.other_ms,
            s.total_ms,
            m.cpu_ms,
            m.peak_rss_mb,
            m.label
        );
    }
}

fn parse_list<T>(text: &str, parse: impl Fn(&str) -> Option<T>) -> Result<Vec<T>, String> {
    text.split(',')
        .map(|s| parse(s.trim()).ok_or_else(|| format!("cannot parse {s:?}")))
        .collect()
}

fn precision_name(p: MatmulPrecision) -> &'static str {
    match p {
        MatmulPrecision::F32 => "f32",
        MatmulPrecision::Bf16 => "bf16",
    }
}

fn pass_miss(ok: bool) -> &'static str {
    if ok {
        "PASS"
    } else {
        "MISS"
    }
}

const USAGE: &str = "\
usage: cargo run --release -p gs-wgpu --example step_bench -- [FLAGS]

  --json                 one JSON object per line instead of the tables
  --sizes N,...          Gaussian counts (default 10000,50000,100000)
  --images WxH,...       image sizes (default 480x300,960x600)
  --threads N            rayon threads (default: rayon's, one per CPU)
  --repeats N            measured steps after one warm-up (default 5)
  --scene KIND           volume (default) or surface
  --set NAME=VALUE,...   SunAwareConfig settings: speed switches (on|off),
                         mlp_precision=f32|bf16, appearance_hidden_width=N
  --ab SWITCH            every size and image twice, the switch off then on
  --backend B,...        cpu (default) and/or wgpu
  --gpu-atomic           on wgpu: the float-atomic backward instead of the deterministic one
  --default-malloc       keep glibc's allocator defaults
  --child-variant I      internal: measure one configuration in this process
  -h, --help             this text";

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    exit_if_help(&args, USAGE);
    // As the component and the simulator run the step (gs_core::heap); `--default-malloc`
    // keeps glibc's defaults, to measure what the setting buys. Children inherit the flag.
    if !args.iter().any(|a| a == "--default-malloc") {
        gs_core::heap::retain_freed_memory();
    }
    if let Err(e) = run(&args) {
        eprintln!("step_bench: {e}");
        std::process::exit(2);
    }
}

fn run(args: &[String]) -> Result<(), String> {
    let json = args.iter().any(|a| a == "--json");
    let sizes = match arg_str(args, "--sizes") {
        Some(v) => parse_list(v, |s| s.parse::<usize>().ok().filter(|&n| n > 0))?,
        None => vec![10_000, 50_000, 100_000],
    };
    let images = match arg_str(args, "--images") {
        Some(v) => parse_list(v, |s| {
            let (w, h) = s.split_once('x')?;
            Some((w.parse::<u32>().ok()?, h.parse::<u32>().ok()?)).filter(|&(w, h)| w > 0 && h > 0)
        })?,
        None => vec![(480, 300), (960, 600)],
    };
    let repeats = match arg_str(args, "--repeats") {
        Some(v) => v
            .parse::<usize>()
            .ok()
            .filter(|&r| r > 0)
            .ok_or("--repeats needs a positive integer")?,
        None => 5,
    };
    let kind = match arg_str(args, "--scene").unwrap_or("volume") {
        "volume" => SceneKind::Volume,
        "surface" => SceneKind::Surface,
        other => return Err(format!("--scene {other:?}: expected volume or surface")),
    };
    let threads = match arg_str(args, "--threads") {
        Some(v) => Some(
            v.parse::<usize>()
                .ok()
                .filter(|&t| t > 0)
                .ok_or("--threads needs a positive integer")?,
        ),
        None => None,
    };
    // The denormal mode the binaries train with (GS_DENORMALS, inherited by the children).
    gs_core::fpmode::init_from_env(threads)?;
    let threads = rayon::current_num_threads();
    let mut config = SunAwareConfig::for_variant(Variant::D);
    if let Some(v) = arg_str(args, "--set") {
        for item in v.split(',') {
            let (name, value) = item
                .split_once('=')
                .ok_or_else(|| format!("--set {item:?}: expected NAME=VALUE"))?;
            set_value(&mut config, name, value)?;
        }
    }
    // Each measured configuration: a label and its settings. With `--ab NAME` every size
    // and image runs with the switch off, then on (the rest as set), in the same run.
    let mut settings = vec![("as set".to_string(), config.clone())];
    if let Some(name) = arg_str(args, "--ab") {
        let mut off = config.clone();
        set_switch(&mut off, name, false)?;
        let mut on = config.clone();
        set_switch(&mut on, name, true)?;
        settings = vec![(format!("{name}=off"), off), (format!("{name}=on"), on)];
    }
    let backends = match arg_str(args, "--backend") {
        Some(v) => parse_list(v, |s| s.parse::<BackendKind>().ok())?,
        None => vec![BackendKind::Cpu],
    };
    for b in &backends {
        b.check_compiled_in(&ENGINES).map_err(|e| e.to_string())?;
    }
    // Every setting on every backend; the backend joins the label when there is a choice.
    let mut variants = Vec::new();
    for (label, config) in &settings {
        for &b in &backends {
            let label = if backends.len() > 1 || b != BackendKind::Cpu {
                format!("{label} backend={b}")
            } else {
                label.clone()
            };
            variants.push((label, config.clone(), b));
        }
    }
    let main_label = variants[variants.len() - 1].0.clone();
    let scene_name = if kind == SceneKind::Volume {
        "volume"
    } else {
        "surface"
    };

    if json {
        eprintln!("{}", gs_core::machine::header_line());
    } else {
        println!("{}", gs_core::machine::header_line());
        println!(
            "step_bench: configuration d, {scene_name} scene, {threads} threads, median of {repeats} steps after one warm-up (ms)"
        );
        if backends.contains(&BackendKind::Wgpu) {
            println!(
                "backend=wgpu: device-resident (every stage on the GPU, one submission per step; stages are device \
                 timestamps, `other` the host's recording and waiting), or with --hybrid the rasterizer, shadow pass and network products on the GPU and the rest on \
                 the host; adapter on stderr; on a software Vulkan driver (lavapipe) these are CPU timings, not GPU \
                 timings"
            );
        }
        println!(
            "{:>7} {:>8} {:>7} {:>7} | {:>6} {:>6} {:>6} {:>6} {:>7} {:>6} {:>7} {:>6} {:>7} {:>7} {:>7} {:>6} {:>6} {:>6} | {:>7} {:>7} {:>7} | settings",
            "gauss", "image", "visible", "rows", "proj", "sort", "contr", "shadow", "phi-f", "psi-f",
            "blend-f", "loss", "blend-b", "proj-b", "phi-b", "psi-b", "optim", "other", "step",
            "cpu", "rss MB"
        );
    }
    if let Some(v) = arg_str(args, "--child-variant") {
        // One configuration in this (fresh) process: its peak RSS is its own.
        let i = v
            .parse::<usize>()
            .ok()
            .filter(|&i| i < variants.len())
            .ok_or("bad --child-variant")?;
        let (label, config, backend) = &variants[i];
        let m = measure(sizes[0], images[0], kind, repeats, config, *backend, label)?;
        println!("MEASURED {}", m.to_line());
        return Ok(());
    }
    let mut results = Vec::new();
    for &n in &sizes {
        for &image in &images {
            for (i, (label, _, _)) in variants.iter().enumerate() {
                let m = measure_in_child(args, n, image, i, label)?;
                print_step(&m, json, scene_name, threads, repeats);
                results.push(m);
            }
        }
    }

    if !json {
        println!();
        println!("network stages against the GEMM floor (same shapes, same run, the networks' own precision; target ratio <= {TARGET_MLP_RATIO})");
        println!(
            "{:>7} {:>8} {:>13} {:>5} {:>7} {:>7} {:>8} {:>8} {:>7} {:>6} {:>5} settings",
            "gauss",
            "image",
            "stage",
            "prec",
            "rows",
            "GFLOP",
            "stage ms",
            "floor ms",
            "GFLOP/s",
            "ratio",
            ""
        );
        for m in &results {
            for net in &m.nets {
                println!(
                    "{:>7} {:>8} {:>13} {:>5} {:>7} {:>7.2} {:>8.1} {:>8.1} {:>7.1} {:>6.2} {:>5} {}",
                    m.gaussians,
                    format!("{}x{}", m.width, m.height),
                    net.name,
                    precision_name(m.precision),
                    net.rows,
                    net.gflop,
                    net.stage_ms,
                    net.floor_ms,
                    net.gemm_gflops(),
                    net.ratio(),
                    pass_miss(net.ratio() <= TARGET_MLP_RATIO),
                    m.label
                );
            }
        }
        println!();
        println!("targets (issue 5)");
    }
    // The targets, for the configurations this run measured.
    let mut targets: Vec<(String, f64, f64, bool)> = Vec::new();
    // Targets apply to the last settings measured (the "on" side of `--ab`).
    let main: Vec<&Measured> = results.iter().filter(|m| m.label == main_label).collect();
    let worst = main
        .iter()
        .flat_map(|m| m.nets.iter())
        .map(NetStage::ratio)
        .fold(f64::NAN, f64::max);
    if !worst.is_nan() {
        targets.push((
            "worst network stage / GEMM floor".into(),
            worst,
            TARGET_MLP_RATIO,
            worst <= TARGET_MLP_RATIO,
        ));
    }
    for m in main.iter().filter(|m| m.gaussians == 100_000) {
        targets.push((
            format!("peak RSS MB, 100K at {}x{}", m.width, m.height),
            m.peak_rss_mb,
            TARGET_PEAK_MB,
            m.peak_rss_mb < TARGET_PEAK_MB,
        ));
        if (m.width, m.height) == (960, 600) {
            targets.push((
                "step ms, 100K at 960x600".into(),
                m.stages.total_ms,
                TARGET_STEP_MS,
                m.stages.total_ms < TARGET_STEP_MS,
            ));
        }
    }
    for (what, value, limit, ok) in &targets {
        if json {
            println!(
                "{{\"kind\":\"target\",\"what\":\"{what}\",\"value\":{value:.3},\"limit\":{limit},\"pass\":{ok}}}"
            );
        } else {
            println!(
                "{:>40} {:>9.2} (target {:>6}) {}",
                what,
                value,
                if what.starts_with("worst") {
                    format!("<= {limit}")
                } else {
                    format!("< {limit}")
                },
                pass_miss(*ok)
            );
        }
    }
    Ok(())
}

use floors::paired_floors;
use runs::{measure, measure_in_child, set_switch, set_value};
use setup::{camera, scene, BOX_HALF_M};

#[path = "step_bench/floors.rs"]
mod floors;
#[path = "step_bench/runs.rs"]
mod runs;
#[path = "step_bench/setup.rs"]
mod setup;

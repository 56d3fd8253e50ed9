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

const BOX_HALF_M: [f32; 3] = [1.5, 0.75, 0.75];
const TARGET_MLP_RATIO: f64 = 1.5;
const TARGET_PEAK_MB: f64 = 500.0;
const TARGET_STEP_MS: f64 = 400.0;

#[derive(Clone, Copy, PartialEq)]
enum SceneKind {
    Volume,
    Surface,
}

/// A point of the scene and the rotation that orients its Gaussian.
fn scene_point(kind: SceneKind, rng: &mut SplitMix64) -> (Vec3, Quat) {
    let h = Vec3::from_array(BOX_HALF_M);
    let inside = Vec3::new(
        rng.uniform(-h.x, h.x),
        rng.uniform(-h.y, h.y),
        rng.uniform(-h.z, h.z),
    );
    match kind {
        SceneKind::Volume => {
            let q = Quat::from_xyzw(rng.normal(), rng.normal(), rng.normal(), rng.normal());
            (inside, q.normalize())
        }
        SceneKind::Surface => {
            // Pick a face by area, put the point on it, lay the Gaussian flat on it.
            let areas = [h.y * h.z, h.x * h.z, h.x * h.y];
            let total: f32 = areas.iter().sum();
            let mut pick = rng.uniform(0.0, total);
            let mut axis = 0;
            while axis < 2 && pick >= areas[axis] {
                pick -= areas[axis];
                axis += 1;
            }
            let mut p = inside;
            p[axis] = if rng.next_f32() < 0.5 {
                -h[axis]
            } else {
                h[axis]
            };
            let mut normal = Vec3::ZERO;
            normal[axis] = 1.0;
            let base = Quat::from_rotation_arc(Vec3::Z, normal);
            let spin = Quat::from_rotation_z(rng.uniform(0.0, std::f32::consts::TAU));
            (p, (base * spin).normalize())
        }
    }
}

/// `n` Gaussians of the configuration-(d) layout, seeded.
fn scene(n: usize, kind: SceneKind, config: &SunAwareConfig, seed: u64) -> GaussianModel {
    let mut rng = SplitMix64::new(seed);
    let h = Vec3::from_array(BOX_HALF_M);
    let spacing = match kind {
        SceneKind::Volume => (8.0 * h.x * h.y * h.z / n as f32).cbrt(),
        SceneKind::Surface => {
            let area = 8.0 * (h.y * h.z + h.x * h.z + h.x * h.y);
            (area / n as f32).sqrt()
        }
    };
    let mut g = GaussianModel::new(config.layout()).expect("layout");
    g.params.push_zeros(n);
    for i in 0..n {
        let (p, q) = scene_point(kind, &mut rng);
        let s = spacing * rng.uniform(0.4, 0.9);
        let log_scale = match kind {
            SceneKind::Volume => [
                s.ln(),
                (s * rng.uniform(0.5, 1.0)).ln(),
                (s * rng.uniform(0.5, 1.0)).ln(),
            ],
            SceneKind::Surface => [s.ln(), (s * rng.uniform(0.5, 1.0)).ln(), (0.1 * s).ln()],
        };
        let p_ = &mut g.params;
        p_.row_mut(Param::Mean, i).copy_from_slice(&p.to_array());
        p_.row_mut(Param::LogScale, i).copy_from_slice(&log_scale);
        p_.row_mut(Param::Rotation, i)
            .copy_from_slice(&[q.w, q.x, q.y, q.z]);
        p_.row_mut(Param::OpacityLogit, i)[0] = rng.uniform(-1.0, 2.5);
    }
    g
}

fn camera(width: u32, height: u32) -> Camera {
    let dir = Vec3::new(0.6, -0.7, 0.4).normalize();
    Camera::look_at(
        Intrinsics::from_fov_x(0.7, width, height),
        dir * 6.0,
        Vec3::ZERO,
        Vec3::Z,
    )
}

fn seconds_ms(f: impl FnOnce()) -> f64 {
    let t0 = Instant::now();
    f();
    t0.elapsed().as_secs_f64() * 1e3
}

/// Operands of one layer's products over `rows` rows, `k -> n` widths.
struct LayerOperands {
    rows: usize,
    k: usize,
    n: usize,
    x: Vec<f32>,
    w: Vec<f32>,
    dz: Vec<f32>,
    y: Vec<f32>,
    dx: Vec<f32>,
}

impl LayerOperands {
    fn new(rows: usize, k: usize, n: usize, rng: &mut SplitMix64) -> Self {
        let mut fill = |len: usize| (0..len).map(|_| rng.uniform(-1.0, 1.0)).collect();
        Self {
            rows,
            k,
            n,
            x: fill(rows * k),
            w: fill(k * n),
            dz: fill(rows * n),
            y: vec![0.0; rows * n],
            dx: vec![0.0; rows * k],
        }
    }

    /// `Y = X W`, blocked over `BLOCK_ROWS` rows in parallel as the MLP runs it.
    fn forward(&mut self, products: Products) {
        let (k, n) = (self.k, self.n);
        let (x, w) = (&self.x, &self.w);
        self.y
            .par_chunks_mut(BLOCK_ROWS * n)
            .enumerate()
            .for_each(|(b, out)| {
                let r = out.len() / n;
                let s = b * BLOCK_ROWS;
                products.matmul(&x[s * k..(s + r) * k], w, out, r, k, n, false);
            });
    }

    /// `dW = X^T dZ` (per-block partials summed in block order) and `dX = dZ W^T`.
    fn backward(&mut self, products: Products) {
        let (rows, k, n) = (self.rows, self.k, self.n);
        let (x, w, dz) = (&self.x, &self.w, &self.dz);
        let partials: Vec<Vec<f32>> = (0..rows.div_ceil(BLOCK_ROWS))
            .into_par_iter()
            .map(|b| {
                let s = b * BLOCK_ROWS;
                let r = BLOCK_ROWS.min(rows - s);
                let mut p = vec![0.0f32; k * n];
                products.matmul_at_b(
                    &x[s * k..(s + r) * k],
                    &dz[s * n..(s + r) * n],
                    &mut p,
                    r,
                    k,
                    n,
                    false,
                );
                p
            })
            .collect();
        let mut dw = vec![0.0f32; k * n];
        for p in &partials {
            for (a, b) in dw.iter_mut().zip(p) {
                *a += b;
            }
        }
        std::hint::black_box(&dw);
        self.dx
            .par_chunks_mut(BLOCK_ROWS * k)
            .enumerate()
            .for_each(|(b, out)| {
                let r = out.len() / k;
                let s = b * BLOCK_ROWS;
                products.matmul_a_bt(&dz[s * n..(s + r) * n], w, out, r, n, k, false);
            });
    }
}

/// The GEMMs of one network over `rows` rows (its layer shapes, its own products), built
/// once and timed right after each measured step, so a stage and its floor are measured
/// seconds apart under the same machine state.
struct FloorOperands {
    products: Products,
    layers: Vec<LayerOperands>,
}

impl FloorOperands {
    fn new(mlp: &Mlp, rows: usize) -> Self {
        let mut rng = SplitMix64::new(99);
        let mut layers: Vec<LayerOperands> = if rows == 0 {
            Vec::new()
        } else {
            mlp.widths()
                .windows(2)
                .map(|p| LayerOperands::new(rows, p[0], p[1], &mut rng))
                .collect()
        };
        // One untimed pass: first-touch page faults are not GEMM time.
        for l in &mut layers {
            l.forward(mlp.products());
            l.backward(mlp.products());
        }
        Self {
            products: mlp.products(),
            layers,
        }
    }

    /// One forward and one backward of every layer: (forward ms, backward ms).
    fn time_once(&mut self) -> (f64, f64) {
        let products = self.products;
        let fwd = self
            .layers
            .iter_mut()
            .map(|l| seconds_ms(|| l.forward(products)))
            .sum();
        let bwd = self
            .layers
            .iter_mut()
            .map(|l| seconds_ms(|| l.backward(products)))
            .sum();
        (fwd, bwd)
    }
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

/// The networks' stages against their GEMM floors, paired: after the measured steps (so
/// the floors' operands do not count in the peak memory), `repeats` more steps, each
/// followed at once by one timing of the same GEMMs on `rows` rows. Each stage's ratio is
/// the median of its per-step ratios, so a change in the machine's speed between the
/// steps and the floors (a shared host) does not pass for distance from the floor.
fn paired_floors(
    trainer: &mut SunAwareTrainer,
    obs: &Observation,
    rows: usize,
    repeats: usize,
) -> Result<Vec<NetStage>, String> {
    let model = &trainer.model;
    let phi = &model
        .appearance
        .as_ref()
        .ok_or("configuration d has Phi")?
        .mlp;
    let psi = &model.shadow.as_ref().ok_or("configuration d has Psi")?.mlp;
    let gflop = |mlp: &Mlp| (rows * mlp.flops_per_row_forward()) as f64 / 1e9;
    let (phi_gflop, psi_gflop) = (gflop(phi), gflop(psi));
    let mut floors = [FloorOperands::new(phi, rows), FloorOperands::new(psi, rows)];
    // [phi_f, phi_b, psi_f, psi_b]: (stage ms, floor ms) per repeat.
    let mut pairs: [Vec<(f64, f64)>; 4] = Default::default();
    for r in 0..repeats {
        let stats = trainer
            .step(obs, r as f32 / repeats as f32)
            .map_err(|e| format!("step: {e}"))?;
        let t = &stats.timings;
        let (phi_f, phi_b) = floors[0].time_once();
        let (psi_f, psi_b) = floors[1].time_once();
        pairs[0].push((t.phi_forward_ms, phi_f));
        pairs[1].push((t.phi_backward_ms, phi_b));
        pairs[2].push((t.psi_forward_ms, psi_f));
        pairs[3].push((t.psi_backward_ms, psi_b));
    }
    let names = ["phi_forward", "phi_backward", "psi_forward", "psi_backward"];
    let gflops = [phi_gflop, 2.0 * phi_gflop, psi_gflop, 2.0 * psi_gflop];
    Ok(names
        .iter()
        .zip(gflops)
        .zip(&pairs)
        .map(|((&name, gflop), p)| NetStage {
            name,
            rows,
            gflop,
            stage_ms: median(p.iter().map(|&(s, _)| s).collect()),
            floor_ms: median(p.iter().map(|&(_, f)| f).collect()),
            ratio: median(p.iter().map(|&(s, f)| s / f).collect()),
        })
        .collect())
}

fn measure(
    n: usize,
    (width, height): (u32, u32),
    kind: SceneKind,
    repeats: usize,
    config: &SunAwareConfig,
    backend: BackendKind,
    label: &str,
) -> Result<Measured, String> {
    let gaussians = scene(n, kind, config, 7);
    let h = BOX_HALF_M;
    let scene_box = SceneBox::new([-h[0], -h[1], -h[2]], h).expect("box");
    let model = SunAwareModel::new(gaussians, scene_box, config.clone())
        .map_err(|e| format!("model: {e}"))?;
    let mut trainer = SunAwareTrainer::new(model);
    // The float-atomic backward (last bits vary run to run) with --gpu-atomic; the
    // component's default is the deterministic one.
    let deterministic = !std::env::args().any(|a| a == "--gpu-atomic");
    let opened = backend
        .open(&ENGINES, deterministic)
        .map_err(|e| e.to_string())?;
    if let Some(adapter) = opened.describe() {
        eprintln!("step_bench: backend wgpu on {adapter}");
    }
    trainer
        .set_backend(&opened)
        .map_err(|e| format!("backend {backend}: {e}"))?;
    let resident = trainer.is_device_resident();
    let cam = camera(width, height);
    let mut rng = SplitMix64::new(11);
    let target: Vec<f32> = (0..width as usize * height as usize * 3)
        .map(|_| rng.next_f32())
        .collect();
    let obs = Observation {
        camera: cam,
        sun_dir: Vec3::new(0.3, 0.5, 0.8).normalize(),
        image: &target,
        mask: None,
    };
    let warm = trainer.step(&obs, 0.0).expect("warm-up step");
    assert!(!warm.skipped, "warm-up step was skipped (non-finite)");
    reset_peak_rss();
    let mut all = Vec::new();
    let mut cpu = Vec::new();
    let mut visible = Vec::new();
    let mut rows = Vec::new();
    if resident {
        // Device-resident: the repeats run as one batch (state uploaded once, downloaded
        // once, as a training round runs); each step's time is its own recording and wait,
        // its stages the device's timestamps (zeros without timestamp queries).
        let batch: Vec<(Observation, f32)> = (0..repeats)
            .map(|r| (obs, r as f32 / repeats as f32))
            .collect();
        let c0 = process_cpu_ms();
        let steps = trainer.step_many(&batch).expect("steps");
        let per_step = (process_cpu_ms() - c0) / repeats.max(1) as f64;
        for stats in steps {
            cpu.push(per_step);
            assert!(!stats.skipped, "step was skipped (non-finite)");
            visible.push(stats.visible as f64);
            rows.push(stats.network_rows as f64);
            all.push(stats.timings);
        }
    }
    for r in 0..if resident { 0 } else { repeats } {
        let c0 = process_cpu_ms();
        let stats = trainer.step(&obs, r as f32 / repeats as f32).expect("step");
        cpu.push(process_cpu_ms() - c0);
        assert!(!stats.skipped, "step was skipped (non-finite)");
        visible.push(stats.visible as f64);
        rows.push(stats.network_rows as f64);
        all.push(stats.timings);
    }
    let peak = peak_rss_mb();
    let med = |f: fn(&StepTimings) -> f64| median(all.iter().map(f).collect());
    let stages = StepTimings {
        project_ms: med(|t| t.project_ms),
        sort_bin_ms: med(|t| t.sort_bin_ms),
        contribution_ms: med(|t| t.contribution_ms),
        shadow_pass_ms: med(|t| t.shadow_pass_ms),
        phi_forward_ms: med(|t| t.phi_forward_ms),
        psi_forward_ms: med(|t| t.psi_forward_ms),
        blend_forward_ms: med(|t| t.blend_forward_ms),
        loss_ms: med(|t| t.loss_ms),
        blend_backward_ms: med(|t| t.blend_backward_ms),
        project_backward_ms: med(|t| t.project_backward_ms),
        phi_backward_ms: med(|t| t.phi_backward_ms),
        psi_backward_ms: med(|t| t.psi_backward_ms),
        optimizer_ms: med(|t| t.optimizer_ms),
        total_ms: med(|t| t.total_ms),
    };
    let rows = median(rows) as usize;
    // The floors are CPU GEMMs: no meaning next to a device-resident step's stages.
    let nets = if resident {
        Vec::new()
    } else {
        paired_floors(&mut trainer, &obs, rows, repeats)?
    };
    Ok(Measured {
        label: label.to_string(),
        gaussians: n,
        width,
        height,
        visible: median(visible) as usize,
        rows,
        stages,
        other_ms: median(all.iter().map(StepTimings::other_ms).collect()),
        cpu_ms: median(cpu),
        peak_rss_mb: peak,
        nets,
        precision: config.mlp_precision,
    })
}

/// The speed switches of [`SunAwareConfig`] this bench can set by name. `mlp_precision`
/// counts as a switch: off is f32, on is bf16.
fn set_switch(config: &mut SunAwareConfig, name: &str, on: bool) -> Result<(), String> {
    match name {
        "skip_noncontributing_in_mlp" => config.skip_noncontributing_in_mlp = on,
        "mlp_recompute_activations" => config.mlp_recompute_activations = on,
        "reuse_step_buffers" => config.reuse_step_buffers = on,
        "mlp_precision" => {
            config.mlp_precision = if on {
                MatmulPrecision::Bf16
            } else {
                MatmulPrecision::F32
            }
        }
        _ => return Err(format!("unknown switch {name:?}")),
    }
    Ok(())
}

/// One `--set NAME=VALUE`: a switch (on/off/true/false), `mlp_precision=f32|bf16`, or
/// `appearance_hidden_width=N`.
fn set_value(config: &mut SunAwareConfig, name: &str, value: &str) -> Result<(), String> {
    let bad = || format!("--set {name}={value}: bad value");
    match (name, value) {
        ("mlp_precision", "f32") => set_switch(config, name, false),
        ("mlp_precision", "bf16") => set_switch(config, name, true),
        ("appearance_hidden_width", v) => {
            config.appearance_hidden_width = v.parse().map_err(|_| bad())?;
            Ok(())
        }
        (_, "on" | "true") => set_switch(config, name, true),
        (_, "off" | "false") => set_switch(config, name, false),
        _ => Err(bad()),
    }
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

/// Runs one configuration in a child process (this executable with `--child-variant`), so
/// memory the allocator kept from an earlier configuration does not count in its peak.
fn measure_in_child(
    args: &[String],
    n: usize,
    (width, height): (u32, u32),
    variant: usize,
    label: &str,
) -> Result<Measured, String> {
    let mut child_args: Vec<String> = Vec::new();
    let mut i = 0;
    while i < args.len() {
        if args[i] == "--sizes" || args[i] == "--images" || args[i] == "--json" {
            i += if args[i] == "--json" { 1 } else { 2 };
            continue;
        }
        child_args.push(args[i].clone());
        i += 1;
    }
    child_args.extend([
        "--sizes".to_string(),
        n.to_string(),
        "--images".to_string(),
        format!("{width}x{height}"),
        "--child-variant".to_string(),
        variant.to_string(),
    ]);
    let exe = std::env::current_exe().map_err(|e| format!("own executable: {e}"))?;
    let out = std::process::Command::new(exe)
        .args(&child_args)
        .stderr(std::process::Stdio::inherit())
        .output()
        .map_err(|e| format!("child process: {e}"))?;
    if !out.status.success() {
        return Err(format!(
            "child for {n} at {width}x{height} failed: {}",
            out.status
        ));
    }
    let text = String::from_utf8_lossy(&out.stdout);
    let line = text
        .lines()
        .find_map(|l| l.strip_prefix("MEASURED "))
        .ok_or("child printed no result")?;
    Measured::from_line(line, label)
}

impl Measured {
    const NET_NAMES: [&'static str; 4] =
        ["phi_forward", "phi_backward", "psi_forward", "psi_backward"];

    /// Whitespace-separated numbers (the child's report to the parent).
    fn to_line(&self) -> String {
        let mut v: Vec<String> = vec![
            self.gaussians.to_string(),
            self.width.to_string(),
            self.height.to_string(),
            self.visible.to_string(),
            self.rows.to_string(),
        ];
        v.extend(self.stages.stages().iter().map(|(_, ms)| format!("{ms:e}")));
        for x in [
            self.stages.total_ms,
            self.other_ms,
            self.cpu_ms,
            self.peak_rss_mb,
        ] {
            v.push(format!("{x:e}"));
        }
        for net in &self.nets {
            v.push(net.rows.to_string());
            for x in [net.gflop, net.stage_ms, net.floor_ms, net.ratio] {
                v.push(format!("{x:e}"));
            }
        }
        v.push(u8::from(self.precision == MatmulPrecision::Bf16).to_string());
        v.join(" ")
    }

    fn from_line(line: &str, label: &str) -> Result<Self, String> {
        let f: Vec<f64> = line
            .split_whitespace()
            .map(|s| {
                s.parse::<f64>()
                    .map_err(|e| format!("child result {s:?}: {e}"))
            })
            .collect::<Result<_, _>>()?;
        // The network floors are absent for a device-resident run.
        let with_nets = f.len() == 5 + 13 + 4 + 4 * 5 + 1;
        if !with_nets && f.len() != 5 + 13 + 4 + 1 {
            return Err(format!("child result has {} numbers", f.len()));
        }
        let st = &f[5..18];
        let stages = StepTimings {
            project_ms: st[0],
            sort_bin_ms: st[1],
            contribution_ms: st[2],
            shadow_pass_ms: st[3],
            phi_forward_ms: st[4],
            psi_forward_ms: st[5],
            blend_forward_ms: st[6],
            loss_ms: st[7],
            blend_backward_ms: st[8],
            project_backward_ms: st[9],
            phi_backward_ms: st[10],
            psi_backward_ms: st[11],
            optimizer_ms: st[12],
            total_ms: f[18],
        };
        let named = if with_nets { &Self::NET_NAMES[..] } else { &[] };
        let nets = named
            .iter()
            .enumerate()
            .map(|(k, &name)| {
                let o = 22 + 5 * k;
                NetStage {
                    name,
                    rows: f[o] as usize,
                    gflop: f[o + 1],
                    stage_ms: f[o + 2],
                    floor_ms: f[o + 3],
                    ratio: f[o + 4],
                }
            })
            .collect();
        Ok(Self {
            label: label.to_string(),
            gaussians: f[0] as usize,
            width: f[1] as u32,
            height: f[2] as u32,
            visible: f[3] as usize,
            rows: f[4] as usize,
            stages,
            other_ms: f[19],
            cpu_ms: f[20],
            peak_rss_mb: f[21],
            nets,
            precision: if f[f.len() - 1] == 1.0 {
                MatmulPrecision::Bf16
            } else {
                MatmulPrecision::F32
            },
        })
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

//! CPU vs wgpu rasterizer times (feature `wgpu`): forward and backward medians on a
//! random cloud of Gaussians in front of the camera, for 10K, 50K and 100K Gaussians.
//!
//! `cargo run --release -p gs-core --features wgpu --example gpu_bench -- [--runs N]
//! [--width W --height H] [--gaussians N] [--cas] [--reduce] [--deterministic] [--train]`
//! (`--cas`: force the compare-and-swap gradient accumulation; `--reduce`: per-tile
//! workgroup reductions; `--deterministic`: the fixed-order backward; `--train`: also
//! time `train::Trainer` steps (SH colour, render, loss, backward, Adam) per backend, as
//! steps per second; on wgpu the device-resident path, `gpu::ResidentModel`)
//!
//! On Mesa's software Vulkan driver (lavapipe) the "wgpu" column measures a CPU
//! emulation of a GPU, not a GPU: compare columns only on a machine with a real one.
//! `wgpu prj` is the part of `wgpu fwd` up to the entry-count readback (upload,
//! projection, prefix sum). Times are wall-clock medians after one warm-up; `cpu s` is
//! this process's CPU time (user + system) over the whole configuration, which on a
//! shared machine says how much of the wall time was ours.

use std::time::Instant;

mod bench_util;
use bench_util::{arg, exit_if_help, init_threads, random_cloud, Cloud};

use glam::Vec3;
use gs_core::gpu::{GpuContext, GpuOptions, GpuRasterizer};
use gs_core::raster::{render, render_backward, PixelGrads, RasterSettings};
use gs_core::rng::SplitMix64;
use gs_core::sh::rgb_to_sh_dc;
use gs_core::train::{Backend, TrainConfig, TrainView, Trainer};
use gs_core::{Camera, GaussianModel, Intrinsics, ModelLayout, Param};

/// The cloud as a degree-0 SH model (colours as the DC terms).
fn cloud_model(c: &Cloud) -> GaussianModel {
    let n = c.opacity_logits.len();
    let mut m = GaussianModel::new(ModelLayout::sh(0)).expect("degree 0");
    m.params.push_zeros(n);
    m.params.get_mut(Param::Mean).copy_from_slice(&c.means);
    m.params
        .get_mut(Param::LogScale)
        .copy_from_slice(&c.log_scales);
    m.params
        .get_mut(Param::Rotation)
        .copy_from_slice(&c.rotations);
    m.params
        .get_mut(Param::OpacityLogit)
        .copy_from_slice(&c.opacity_logits);
    for (dc, rgb) in m.params.get_mut(Param::ShDc).iter_mut().zip(&c.channels) {
        *dc = rgb_to_sh_dc(*rgb);
    }
    m
}

/// Medians of `runs` training steps after one warm-up, on a grey target.
struct StepTimes {
    wall_ms: f64,
    forward_ms: f64,
    loss_ms: f64,
    backward_ms: f64,
    /// This process's CPU time per step (all threads), ms.
    cpu_ms: f64,
}

fn step_times(model: &GaussianModel, camera: &Camera, backend: Backend, runs: usize) -> StepTimes {
    let config = TrainConfig {
        densify_until_iter: 0,
        opacity_reset_interval: 0,
        ..TrainConfig::default()
    };
    let mut trainer = Trainer::new(model.clone(), &config, 3.0)
        .expect("trainer")
        .with_backend(backend)
        .expect("backend");
    let view = TrainView {
        camera: *camera,
        image: vec![0.5; camera.intrinsics.pixel_count() * 3],
        mask: None,
    };
    let (mut wall, mut fwd, mut loss, mut bwd) = (vec![], vec![], vec![], vec![]);
    let mut cpu0 = 0.0;
    for r in 0..=runs {
        if r == 1 {
            cpu0 = gs_core::machine::process_cpu_s().unwrap_or(f64::NAN);
        }
        let t = Instant::now();
        let st = trainer.step(&view, 0).expect("step");
        if r > 0 {
            wall.push(t.elapsed().as_secs_f64() * 1e3);
            fwd.push(st.forward_ms);
            loss.push(st.loss_ms);
            bwd.push(st.backward_ms);
        }
    }
    let cpu_ms = (gs_core::machine::process_cpu_s().unwrap_or(f64::NAN) - cpu0) * 1e3 / runs as f64;
    StepTimes {
        wall_ms: median(wall),
        forward_ms: median(fwd),
        loss_ms: median(loss),
        backward_ms: median(bwd),
        cpu_ms,
    }
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

const USAGE: &str = "\
usage: cargo run --release -p gs-core --features wgpu --example gpu_bench -- [FLAGS]

  --runs N         timed runs per size after one warm-up (default 5)
  --width W        image width in pixels (default 960)
  --height H       image height in pixels (default 600)
  --gaussians N    one cloud size instead of 10000, 50000, 100000
  --cas            force the compare-and-swap gradient accumulation
  --reduce         per-tile workgroup reductions in the backward
  --deterministic  the fixed-order backward
  --train          also time training steps per backend (steps per second)
  -h, --help       this text";

fn main() {
    let args: Vec<String> = std::env::args().collect();
    exit_if_help(&args, USAGE);
    init_threads("gpu_bench", None);
    let runs = arg(&args, "--runs").unwrap_or(5).max(1);
    let width = arg(&args, "--width").unwrap_or(960) as u32;
    let height = arg(&args, "--height").unwrap_or(600) as u32;
    let sizes = match arg(&args, "--gaussians") {
        Some(n) => vec![n],
        None => vec![10_000, 50_000, 100_000],
    };
    let options = GpuOptions {
        force_cas_atomics: args.iter().any(|a| a == "--cas"),
        workgroup_reduction: args.iter().any(|a| a == "--reduce"),
        deterministic: args.iter().any(|a| a == "--deterministic"),
    };
    let ctx = match GpuContext::with_options(options) {
        Ok(c) => c,
        Err(e) => {
            eprintln!("{e}");
            std::process::exit(1);
        }
    };
    println!("{}", gs_core::machine::header_line());
    println!("adapter: {}", ctx.describe());
    println!(
        "image {width}x{height}, {runs} runs (median ms), rayon threads {}",
        rayon::current_num_threads()
    );
    let train = args.iter().any(|a| a == "--train");
    let gpu = std::sync::Arc::new(GpuRasterizer::new(ctx).expect("pipelines"));
    let camera = Camera::look_at(
        Intrinsics::from_fov_x(0.9, width, height),
        Vec3::new(0.0, -5.0, 1.0),
        Vec3::ZERO,
        Vec3::Z,
    );
    let settings = RasterSettings::default();
    println!(
        "{:>8} {:>9} | {:>9} {:>9} | {:>9} {:>9} {:>9} {:>10} | {:>7}",
        "gauss",
        "entries",
        "cpu fwd",
        "cpu bwd",
        "wgpu prj",
        "wgpu fwd",
        "wgpu bwd",
        "wgpu f+b",
        "cpu s"
    );
    for n in sizes {
        let c = random_cloud(n, 1);
        let view = c.view();
        let px = (width * height) as usize;
        let mut rng = SplitMix64::new(2);
        let d_color: Vec<f32> = (0..px * 3).map(|_| rng.uniform(-1.0, 1.0)).collect();
        let pg = PixelGrads {
            d_color: &d_color,
            d_alpha: None,
            d_depth: None,
        };
        let cpu0 = gs_core::machine::process_cpu_s().unwrap_or(f64::NAN);
        let (mut cf, mut cb, mut gf, mut gb, mut gp) = (vec![], vec![], vec![], vec![], vec![]);
        let mut entries = 0;
        for r in 0..=runs {
            let t = Instant::now();
            let f = render(&camera, &view, &settings).unwrap();
            let t_f = t.elapsed().as_secs_f64() * 1e3;
            let t = Instant::now();
            render_backward(&camera, &view, &settings, &f, &pg).unwrap();
            let t_b = t.elapsed().as_secs_f64() * 1e3;
            let t = Instant::now();
            let g = gpu.render(&camera, &view, &settings).unwrap();
            let g_f = t.elapsed().as_secs_f64() * 1e3;
            let t = Instant::now();
            gpu.render_backward(&camera, &settings, &g, &pg).unwrap();
            let g_b = t.elapsed().as_secs_f64() * 1e3;
            entries = g.tile_entries;
            if r > 0 {
                cf.push(t_f);
                cb.push(t_b);
                gf.push(g_f);
                gb.push(g_b);
                gp.push(g.timings.project_scan_ms);
            }
        }
        let (gfm, gbm) = (median(gf), median(gb));
        println!(
            "{:>8} {:>9} | {:>9.1} {:>9.1} | {:>9.1} {:>9.1} {:>9.1} {:>10.1} | {:>7.1}",
            n,
            entries,
            median(cf),
            median(cb),
            median(gp),
            gfm,
            gbm,
            gfm + gbm,
            gs_core::machine::process_cpu_s().unwrap_or(f64::NAN) - cpu0
        );
        if train {
            let model = cloud_model(&c);
            for (name, backend) in [
                ("cpu", Backend::Cpu),
                ("wgpu resident", Backend::Wgpu(gpu.clone())),
            ] {
                let t = step_times(&model, &camera, backend, runs);
                println!(
                    "{n:>8} training step, {name}: {:.1} ms = {:.2} steps/s (forward {:.1}, \
                     loss {:.1}, backward + Adam {:.1}); process CPU {:.1} ms/step",
                    t.wall_ms,
                    1e3 / t.wall_ms,
                    t.forward_ms,
                    t.loss_ms,
                    t.backward_ms,
                    t.cpu_ms
                );
            }
        }
    }
}

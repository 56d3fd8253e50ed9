//! CPU vs wgpu rasterizer times: forward and backward medians on a
//! random cloud of Gaussians in front of the camera, for 10K, 50K and 100K Gaussians.
//!
//! `cargo run --release -p gs-wgpu --example gpu_bench -- [--runs N]
//! [--width W --height H] [--gaussians N] [--cas] [--reduce] [--deterministic]`
//! (`--cas`: force the compare-and-swap gradient accumulation; `--reduce`: per-tile
//! workgroup reductions; `--deterministic`: the fixed-order backward). Whole training
//! steps per backend: `step_bench --backend cpu,wgpu`.
//!
//! On Mesa's software Vulkan driver (lavapipe) the "wgpu" column measures a CPU
//! emulation of a GPU, not a GPU: compare columns only on a machine with a real one.
//! `wgpu prj` is the part of `wgpu fwd` up to the entry-count readback (upload,
//! projection, prefix sum). Times are wall-clock medians after one warm-up; `cpu s` is
//! this process's CPU time (user + system) over the whole configuration, which on a
//! shared machine says how much of the wall time was ours.

use std::time::Instant;

#[path = "../../gs-core/examples/bench_util/mod.rs"]
mod bench_util;
use bench_util::{arg, exit_if_help, init_threads, random_cloud};

use glam::Vec3;
use gs_core::raster::{render, render_backward, PixelGrads, RasterSettings};
use gs_core::rng::SplitMix64;
use gs_core::{Camera, Intrinsics};
use gs_wgpu::{GpuContext, GpuOptions, GpuRasterizer};

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

const USAGE: &str = "\
usage: cargo run --release -p gs-wgpu --example gpu_bench -- [FLAGS]

  --runs N         timed runs per size after one warm-up (default 5)
  --width W        image width in pixels (default 960)
  --height H       image height in pixels (default 600)
  --gaussians N    one cloud size instead of 10000, 50000, 100000
  --cas            force the compare-and-swap gradient accumulation
  --reduce         per-tile workgroup reductions in the backward
  --deterministic  the fixed-order backward
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
    }
}

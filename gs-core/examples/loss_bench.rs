//! Micro-benchmark of two training-step stages (issue 5): the photometric loss
//! (`gs_core::loss::photometric_loss`, L1 + SSIM value and image gradient) and the shadow
//! pass (`gs_core::sunaware::sun_visibility::sun_visibility`, split into its light splats, the
//! receivers' axis sigmas and `visibility_from_splats`).
//!
//! Inputs match `step_bench`'s configuration (d) at the given size: a seeded random target
//! image and a rendered image near it (target + uniform noise, so the SSIM map is neither
//! 1 nor 0), and for the shadow pass `N` Gaussians filling a 3 x 1.5 x 1.5 m box seen
//! from 6 m with the Sun from the side (the same draws as `step_bench --scene volume`).
//!
//! Per stage: one warm-up call, then `--repeats` calls (default 9); medians of the wall
//! time and of the process CPU time (all threads, from `/proc/self/task/*/schedstat`),
//! ms. On a shared machine the CPU time is the steadier number.
//!
//! `cargo run --release -p gs-core --example loss_bench -- [--image 960x600]
//! [--gaussians 100000] [--threads N] [--repeats N] [--only loss|shadow] [--mask] [--no-reference]`
//! (`--no-reference`: skip the f64 SSIM printed beside the loss, e.g. under a profiler)

use std::time::Instant;

mod bench_util;
use bench_util::{arg_str, exit_if_help, init_threads, median, process_cpu_ms};

use glam::{Quat, Vec3};
use gs_core::loss::{photometric_loss, ssim, ImageShape};
use gs_core::model::{GaussianModel, Param};
use gs_core::nn::SceneBox;
use gs_core::rng::SplitMix64;
use gs_core::sunaware::sun_visibility::{
    light_axis_sigmas_m, light_camera, light_splats, sun_visibility, visibility_from_splats,
    RECEIVER_EXTENT_SIGMAS,
};
use gs_core::sunaware::SunAwareConfig;

const BOX_HALF_M: [f32; 3] = [1.5, 0.75, 0.75];

/// `n` Gaussians filling the box (step_bench's volume scene, same seed and draws).
fn scene(n: usize, config: &SunAwareConfig, seed: u64) -> GaussianModel {
    let mut rng = SplitMix64::new(seed);
    let h = Vec3::from_array(BOX_HALF_M);
    let spacing = (8.0 * h.x * h.y * h.z / n as f32).cbrt();
    let mut g = GaussianModel::new(config.layout()).expect("layout");
    g.params.push_zeros(n);
    for i in 0..n {
        let p = Vec3::new(
            rng.uniform(-h.x, h.x),
            rng.uniform(-h.y, h.y),
            rng.uniform(-h.z, h.z),
        );
        let q = Quat::from_xyzw(rng.normal(), rng.normal(), rng.normal(), rng.normal()).normalize();
        let s = spacing * rng.uniform(0.4, 0.9);
        let log_scale = [
            s.ln(),
            (s * rng.uniform(0.5, 1.0)).ln(),
            (s * rng.uniform(0.5, 1.0)).ln(),
        ];
        let p_ = &mut g.params;
        p_.row_mut(Param::Mean, i).copy_from_slice(&p.to_array());
        p_.row_mut(Param::LogScale, i).copy_from_slice(&log_scale);
        p_.row_mut(Param::Rotation, i)
            .copy_from_slice(&[q.w, q.x, q.y, q.z]);
        p_.row_mut(Param::OpacityLogit, i)[0] = rng.uniform(-1.0, 2.5);
    }
    g
}

/// Median wall and CPU ms of `repeats` calls of `f` after one warm-up.
fn time(repeats: usize, mut f: impl FnMut()) -> (f64, f64) {
    f();
    let (mut wall, mut cpu) = (Vec::new(), Vec::new());
    for _ in 0..repeats {
        let c0 = process_cpu_ms();
        let t0 = Instant::now();
        f();
        wall.push(t0.elapsed().as_secs_f64() * 1e3);
        cpu.push(process_cpu_ms() - c0);
    }
    (median(wall), median(cpu))
}

const USAGE: &str = "\
usage: cargo run --release -p gs-core --example loss_bench -- [FLAGS]

  --image WxH      image size of the loss (default 960x600)
  --gaussians N    Gaussians of the shadow pass (default 100000)
  --threads N      rayon threads (default 2)
  --repeats N      timed calls per stage after one warm-up (default 9)
  --only STAGE     loss or shadow: one stage only
  --mask           a loss mask (half the image weighted 0.5)
  --no-reference   skip the f64 SSIM printed beside the loss
  -h, --help       this text";

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    exit_if_help(&args, USAGE);
    let (w, h) = arg_str(&args, "--image")
        .and_then(|s| s.split_once('x'))
        .and_then(|(a, b)| Some((a.parse::<usize>().ok()?, b.parse::<usize>().ok()?)))
        .unwrap_or((960, 600));
    let n: usize = arg_str(&args, "--gaussians")
        .and_then(|s| s.parse().ok())
        .unwrap_or(100_000);
    let threads: usize = arg_str(&args, "--threads")
        .and_then(|s| s.parse().ok())
        .unwrap_or(2);
    let repeats: usize = arg_str(&args, "--repeats")
        .and_then(|s| s.parse().ok())
        .unwrap_or(9)
        .max(1);
    let only = arg_str(&args, "--only");
    let masked = args.iter().any(|a| a == "--mask");
    init_threads("loss_bench", Some(threads));
    println!("{}", gs_core::machine::header_line());
    println!("loss_bench: {threads} threads, median of {repeats} calls after one warm-up (ms)");
    println!("{:>28} {:>9} {:>9}", "stage", "wall", "cpu");
    let row = |name: &str, (wall, cpu): (f64, f64)| println!("{name:>28} {wall:>9.2} {cpu:>9.2}");

    if only.is_none() || only == Some("loss") {
        let shape = ImageShape::new(w, h, 3);
        let mut rng = SplitMix64::new(11);
        let target: Vec<f32> = (0..shape.values()).map(|_| rng.next_f32()).collect();
        let rendered: Vec<f32> = target
            .iter()
            .map(|&t| (t + rng.uniform(-0.2, 0.2)).clamp(0.0, 1.0))
            .collect();
        let mask: Option<Vec<f32>> = masked.then(|| {
            (0..shape.pixels())
                .map(|p| if (p % w) < w / 2 { 1.0 } else { 0.5 })
                .collect()
        });
        let mut checksum = 0.0f64;
        let t = time(repeats, || {
            let out =
                photometric_loss(&rendered, &target, mask.as_deref(), shape, 0.2).expect("loss");
            checksum += out.loss as f64 + out.d_rendered[shape.values() / 2] as f64;
        });
        row(&format!("loss {w}x{h}"), t);
        let out = photometric_loss(&rendered, &target, mask.as_deref(), shape, 0.2).unwrap();
        // The metric runs the same window in f64: the reference for the f32 value (no mask).
        let ssim64 = if args.iter().any(|a| a == "--no-reference") {
            f32::NAN
        } else {
            ssim(&rendered, &target, shape).expect("ssim")
        };
        println!(
            "{:>28} loss {:.9} ssim {:.9} (f64 metric {ssim64:.9}) |grad|_1 {:.9e} (checksum {checksum:.6})",
            "",
            out.loss,
            out.ssim,
            out.d_rendered.iter().map(|g| g.abs() as f64).sum::<f64>()
        );
    }

    if only.is_none() || only == Some("shadow") {
        let config = SunAwareConfig::default();
        let gaussians = scene(n, &config, 7);
        let hb = BOX_HALF_M;
        let scene_box = SceneBox::new([-hb[0], -hb[1], -hb[2]], hb).expect("box");
        let sun = Vec3::new(0.3, 0.5, 0.8).normalize();
        let eye = Vec3::new(0.6, -0.7, 0.4).normalize() * 6.0;
        let lc = &config.light;
        let near = config.near_m;
        let light = light_camera(sun, eye, &scene_box, lc).expect("light camera");
        let mut vis = Vec::new();
        let t = time(repeats, || {
            vis = sun_visibility(&gaussians, sun, eye, &scene_box, lc, near).expect("shadow");
        });
        row(&format!("shadow {n}"), t);
        let mut splats = Vec::new();
        row(
            "  light_splats",
            time(repeats, || {
                splats = light_splats(&gaussians, &light, near).expect("splats");
            }),
        );
        let mut margin = Vec::new();
        row(
            "  light_axis_sigmas_m",
            time(repeats, || {
                margin = light_axis_sigmas_m(&gaussians, &light)
                    .iter()
                    .map(|s| s * RECEIVER_EXTENT_SIGMAS)
                    .collect();
            }),
        );
        let mut v2 = Vec::new();
        row(
            "  visibility_from_splats",
            time(repeats, || {
                v2 = visibility_from_splats(
                    &splats,
                    lc.resolution_px,
                    lc.footprint_radius_px,
                    light.depth_bias_m,
                    &margin,
                );
            }),
        );
        assert!(vis.iter().zip(&v2).all(|(a, b)| a.to_bits() == b.to_bits()));
        let bits: u64 = vis.iter().fold(0u64, |h, v| {
            (h ^ v.to_bits() as u64).wrapping_mul(0x100000001b3)
        });
        println!(
            "{:>28} mean V {:.9}, hash {bits:016x}",
            "",
            vis.iter().map(|&v| v as f64).sum::<f64>() / vis.len() as f64
        );
    }
}

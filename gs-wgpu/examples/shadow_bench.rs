//! Shadow-pass times: the host path the GPU shadow pass had before it
//! moved to the device (light splats and receiver margins on the CPU, then
//! `GpuSunVisibility::visibility_from_splats`: upload, count readback, sort and walk) against the
//! device path (`GpuSunVisibility::sun_visibility`: the geometry uploaded, splats and margins by
//! a kernel, count readback; and `sun_visibility_packed` with a sort capacity: no
//! mid-pass readback), and the CPU's `sunaware::sun_visibility::sun_visibility`, per light
//! projection.
//!
//! `cargo run --release -p gs-wgpu --example shadow_bench -- [--runs N]
//! [--gaussians N] [--side PX]`
//!
//! Wall-clock medians after one warm-up, and this process's CPU time per call (all
//! threads, the software driver's included), which on a shared machine says how much of
//! the wall time was ours. On Mesa's software Vulkan driver (lavapipe) the GPU columns
//! measure a CPU emulation of a GPU.

#[macro_use]
#[path = "../../gs-core/examples/bench_util/mod.rs"]
mod bench_util;

const USAGE: &str = "\
usage: cargo run --release -p gs-wgpu --example shadow_bench -- [FLAGS]

  --runs N        timed calls per path after one warm-up (default 10)
  --gaussians N   Gaussians of the test model (default 10000)
  --side PX       light image side in pixels (default 256)
  -h, --help      this text";

bench_main!("shadow_bench", USAGE);

mod bench {
    use std::sync::Arc;

    use glam::Vec3;
    use gs_core::nn::SceneBox;
    use gs_core::rng::SplitMix64;
    use gs_core::sunaware::config::{LightConfig, LightProjection};
    use gs_core::sunaware::sun_visibility;
    use gs_core::{GaussianModel, ModelLayout, Param};
    use gs_wgpu::{GpuContext, GpuRasterizer, GpuSunVisibility, SunLight};

    use super::bench_util::{arg, time_calls};

    const NEAR_M: f32 = 0.01;

    /// Flat Gaussians on the faces of a cube (60%) and anywhere in the box (40%), as in
    /// tests/gpu_shadow.rs, with the Sun-aware layout's extra groups.
    fn model(n: usize) -> GaussianModel {
        let layout = ModelLayout {
            sh_degree: 3,
            feature_dim: 72,
            shadow_latent_dim: 6,
            normal_dim: 0,
        };
        let mut model = GaussianModel::new(layout).expect("layout");
        model.params.push_zeros(n);
        let mut rng = SplitMix64::new(5);
        for i in 0..n {
            let mut mean = [
                rng.uniform_symmetric(0.95),
                rng.uniform_symmetric(0.95),
                rng.uniform_symmetric(0.95),
            ];
            if i % 5 < 3 {
                for m in &mut mean {
                    *m *= 0.5 / 0.95;
                }
                mean[rng.below(3)] = if rng.next_f32() < 0.5 { -0.5 } else { 0.5 };
            }
            let log_scale = [
                rng.uniform(0.01, 0.05).ln(),
                rng.uniform(0.01, 0.04).ln(),
                rng.uniform(0.002, 0.01).ln(),
            ];
            let q = [
                rng.uniform_symmetric(1.0),
                rng.uniform_symmetric(1.0),
                rng.uniform_symmetric(1.0),
                rng.uniform_symmetric(1.0),
            ];
            let p = &mut model.params;
            p.row_mut(Param::Mean, i).copy_from_slice(&mean);
            p.row_mut(Param::LogScale, i).copy_from_slice(&log_scale);
            p.row_mut(Param::Rotation, i).copy_from_slice(&q);
            p.row_mut(Param::OpacityLogit, i)[0] = rng.uniform(-1.0, 4.0);
        }
        model
    }

    pub fn run() {
        let args: Vec<String> = std::env::args().collect();
        let runs = arg(&args, "--runs").unwrap_or(10).max(1);
        let n = arg(&args, "--gaussians").unwrap_or(10_000);
        let side = arg(&args, "--side").unwrap_or(256) as u32;
        let ctx = GpuContext::new().expect("a Vulkan adapter");
        println!("{}", gs_core::machine::header_line());
        println!("GPU: {}", ctx.describe());
        let shadow = GpuSunVisibility::new(Arc::new(GpuRasterizer::new(ctx).expect("rasterizer")))
            .expect("shadow pipelines");
        let model = model(n);
        let scene_box = SceneBox::new([-1.0; 3], [1.0; 3]).expect("box");
        let sun = Vec3::new(0.3, -0.5, 0.8).normalize();
        let centre = Vec3::new(0.0, -4.0, 1.0);
        println!("{n} Gaussians, light image {side} px, {runs} runs: median wall ms / process CPU ms per call");
        println!(
            "{:<13} {:>17} {:>17} {:>17} {:>17}  max |dV| vs CPU",
            "projection", "cpu", "old host path", "device, readback", "device, capacity"
        );
        for projection in [LightProjection::Perspective, LightProjection::Orthographic] {
            let config = LightConfig {
                projection,
                resolution_px: side,
                ..LightConfig::default()
            };
            let cpu = time_calls(runs, || {
                sun_visibility::sun_visibility(&model, sun, centre, &scene_box, &config, NEAR_M)
                    .expect("cpu")
            });
            let old = time_calls(runs, || {
                let lc =
                    sun_visibility::light_camera(sun, centre, &scene_box, &config).expect("light");
                let splats = sun_visibility::light_splats(&model, &lc, NEAR_M).expect("splats");
                let margin: Vec<f32> = sun_visibility::light_axis_sigmas_m(&model, &lc)
                    .iter()
                    .map(|s| s * sun_visibility::RECEIVER_EXTENT_SIGMAS)
                    .collect();
                shadow
                    .visibility_from_splats(
                        &splats,
                        side,
                        config.footprint_radius_px,
                        lc.depth_bias_m,
                        &margin,
                    )
                    .expect("old path")
            });
            let light = SunLight {
                sun_dir: sun,
                camera_centre: centre,
                scene_box: &scene_box,
                config: &config,
                near_m: NEAR_M,
            };
            let device = time_calls(runs, || {
                shadow.sun_visibility(&model, &light).expect("device")
            });
            let packed = |capacity| shadow.sun_visibility_packed(&model.params, &light, capacity);
            let entries = packed(None).expect("count").tile_entries;
            let capacity = time_calls(runs, || {
                let r = packed(Some(entries)).expect("capacity");
                assert_eq!(r.flags, 0, "capacity overflow");
                r.visibility
            });
            let worst = |v: &[f32]| {
                v.iter()
                    .zip(&cpu.2)
                    .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()))
            };
            let cell = |t: &(f64, f64, Vec<f32>)| format!("{:.1} / {:.1}", t.0, t.1);
            println!(
                "{:<13} {:>17} {:>17} {:>17} {:>17}  {:.1e} {:.1e} {:.1e}",
                format!("{projection:?}"),
                cell(&cpu),
                cell(&old),
                cell(&device),
                cell(&capacity),
                worst(&old.2),
                worst(&device.2),
                worst(&capacity.2),
            );
        }
    }
}

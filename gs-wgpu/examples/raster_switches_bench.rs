//! What the rasterizer's switches cost or save on the wgpu backend:
//! forward (`GpuRasterizer::render`), backward (`render_backward`) and the contribution
//! pass (`GpuRasterizer::contributing`) with every tile blended, with a checkerboard
//! `blend_tiles` selection (half the tiles), with no tile blended (what is left is the
//! projection, sort, uploads and readbacks: subtracted from the others it gives the
//! blend's and the contribution walk's own cost), and with early termination off.
//!
//! `cargo run --release -p gs-wgpu --example raster_switches_bench --
//! [--runs N] [--gaussians N] [--width W --height H]`
//!
//! Wall-clock medians after one warm-up, and this process's CPU time per call (all
//! threads, the software driver's included), which on a shared machine says how much of
//! the wall time was ours. On Mesa's software Vulkan driver (lavapipe) the kernels run on
//! the CPU, so the CPU time is the device's work too.

#[macro_use]
#[path = "../../gs-core/examples/bench_util/mod.rs"]
mod bench_util;

const USAGE: &str = "\
usage: cargo run --release -p gs-wgpu --example raster_switches_bench -- [FLAGS]

  --runs N        timed calls per pass after one warm-up (default 5)
  --gaussians N   Gaussians in the random cloud (default 20000)
  --width W       image width in pixels (default 480)
  --height H      image height in pixels (default 300)
  -h, --help      this text";

bench_main!("raster_switches_bench", USAGE);

mod bench {

    use glam::Vec3;
    use gs_core::raster::bin::{TileGrid, TileSelection};
    use gs_core::raster::{PixelGrads, RasterSettings};
    use gs_core::rng::SplitMix64;
    use gs_core::{Camera, Intrinsics};
    use gs_wgpu::{GpuContext, GpuRasterizer};

    use super::bench_util::{arg, random_cloud, time_calls};

    /// Tiles whose `(tx + ty) % 2` is `parity`, or none.
    fn selection(w: u32, h: u32, parity: Option<u32>) -> TileSelection {
        let grid = TileGrid::new(w, h);
        let mut mask = vec![0.0f32; (w * h) as usize];
        if let Some(parity) = parity {
            for t in 0..grid.n_tiles() as u32 {
                if (t % grid.tiles_x + t / grid.tiles_x) % 2 == parity {
                    let r = grid.tile_rect(t as usize);
                    mask[(r.y0 * w + r.x0) as usize] = 1.0;
                }
            }
        }
        TileSelection::from_mask(&mask, w, h, 0).expect("mask of the image's size")
    }

    pub fn run() {
        let args: Vec<String> = std::env::args().collect();
        let runs = arg(&args, "--runs").unwrap_or(5).max(1);
        let n = arg(&args, "--gaussians").unwrap_or(20_000);
        let width = arg(&args, "--width").unwrap_or(480) as u32;
        let height = arg(&args, "--height").unwrap_or(300) as u32;
        let ctx = GpuContext::new().expect("a Vulkan adapter");
        println!("{}", gs_core::machine::header_line());
        println!("GPU: {}", ctx.describe());
        let gpu = GpuRasterizer::new(ctx).expect("rasterizer");
        let c = random_cloud(n, 7);
        let camera = Camera::look_at(
            Intrinsics::from_fov_x(0.9, width, height),
            Vec3::new(0.0, 0.0, -5.0),
            Vec3::ZERO,
            Vec3::Y,
        );
        let mut rng = SplitMix64::new(11);
        let px = (width * height) as usize;
        let d_color: Vec<f32> = (0..3 * px).map(|_| rng.uniform(-1.0, 1.0)).collect();
        let d_alpha: Vec<f32> = (0..px).map(|_| rng.uniform(-1.0, 1.0)).collect();
        let grads = PixelGrads {
            d_color: &d_color,
            d_alpha: Some(&d_alpha),
            d_depth: None,
        };
        let base = RasterSettings::default();
        let configs = [
            ("all tiles", base.clone()),
            (
                "half the tiles",
                RasterSettings {
                    blend_tiles: Some(selection(width, height, Some(0))),
                    ..base.clone()
                },
            ),
            (
                "no tile",
                RasterSettings {
                    blend_tiles: Some(selection(width, height, None)),
                    ..base.clone()
                },
            ),
            (
                "early term. off",
                RasterSettings {
                    early_termination: false,
                    ..base.clone()
                },
            ),
        ];
        println!(
            "{n} Gaussians at {width}x{height}, {runs} runs: median wall ms / process CPU ms \
             per call"
        );
        println!(
            "{:<16} {:>17} {:>17} {:>17}",
            "tiles", "forward", "backward", "contributing"
        );
        let mut rows = Vec::new();
        for (name, settings) in &configs {
            let (fwd_wall, fwd_cpu, out) = time_calls(runs, || {
                gpu.render(&camera, &c.view(), settings).expect("render")
            });
            let fwd = (fwd_wall, fwd_cpu);
            let (bwd_wall, bwd_cpu, _) = time_calls(runs, || {
                gpu.render_backward(&camera, settings, &out, &grads)
                    .expect("backward")
            });
            let bwd = (bwd_wall, bwd_cpu);
            let (contrib_wall, contrib_cpu, _) = time_calls(runs, || {
                gpu.contributing(&camera, &c.view(), settings)
                    .expect("contributing")
            });
            let contrib = (contrib_wall, contrib_cpu);
            let cell = |(w, c): (f64, f64)| format!("{w:8.1} /{c:8.1}");
            println!(
                "{name:<16} {:>17} {:>17} {:>17}",
                cell(fwd),
                cell(bwd),
                cell(contrib)
            );
            rows.push([fwd, bwd, contrib]);
        }
        // Each pass's own cost: the run minus the run that blends no tile (process CPU);
        // `pass` 0 forward, 1 backward, 2 contribution walk.
        let own = |config: usize, pass: usize| rows[config][pass].1 - rows[2][pass].1;
        let (blend_all, blend_half) = (own(0, 0), own(1, 0));
        let (back_all, back_half) = (own(0, 1), own(1, 1));
        let (walk_all, walk_half) = (own(0, 2), own(1, 2));
        println!(
            "own CPU ms (minus the no-tile run): blend {blend_all:.1} all / {blend_half:.1} half, \
             backward blend {back_all:.1} / {back_half:.1}, contribution walk {walk_all:.1} / \
             {walk_half:.1} ({:.0}% of the forward blend)",
            100.0 * walk_all / blend_all
        );
    }
}

//! Ray-tracer benchmark: for each built-in target prints the triangle count, BVH build time and
//! the median time per 960x600 frame (SPEED intrinsics downsampled by 2) over several viewpoints:
//! framed (whole craft in view) at 1 and 4 samples per pixel, and close (0.4 times the range,
//! the craft fills the frame) at 1 sample. With `--png DIR` it also writes frames of every
//! target under a few Sun directions (and one eclipse frame with Earth fill) to look at.
//!
//! Run: `cargo run --release -p sim-harness --example render_bench [-- --png DIR [--png-range 0.5]]`
//!
//! The header names the CPU and the threads' denormal mode (`GS_DENORMALS`, default
//! flush-to-zero, as the simulator binary sets it: `gs_core::fpmode`).

use glam::Vec3;
use sim_harness::raytrace::{
    camera_pose_looking_at, render_frame, EarthFill, Frame, FrameRequest, PinholeCamera, Scene,
    DEFAULT_EXPOSURE,
};
use sim_harness::target::{builtin_target, BuiltinTarget};
use std::path::{Path, PathBuf};
use std::time::Instant;

const REPEATS: usize = 3;

fn camera() -> PinholeCamera {
    PinholeCamera {
        fx: 3003.41 / 2.0,
        fy: 3003.41 / 2.0,
        cx: 480.0,
        cy: 300.0,
        width: 960,
        height: 600,
    }
}

fn request(eye: Vec3, sun: Vec3, samples_per_pixel: u32) -> FrameRequest {
    let (rotation, translation) =
        camera_pose_looking_at(eye, Vec3::ZERO, Vec3::Z).expect("eye is off the z axis");
    FrameRequest {
        camera: camera(),
        camera_from_target_rotation: rotation,
        camera_from_target_translation_m: translation,
        sun_dir_target: sun.normalize(),
        sun_lit: true,
        earth_albedo: None,
        samples_per_pixel,
        exposure: DEFAULT_EXPOSURE,
        seed: 1,
    }
}

/// Viewing directions (unit) around the target.
fn view_directions() -> [Vec3; 3] {
    [
        Vec3::new(1.0, -1.2, 0.6).normalize(),
        Vec3::new(-1.0, -0.4, 0.3).normalize(),
        Vec3::new(0.3, 1.0, -0.5).normalize(),
    ]
}

fn write_png(frame: &Frame, path: &Path) {
    let image = image::RgbImage::from_raw(frame.width, frame.height, frame.rgb8.clone())
        .expect("buffer size matches the frame");
    if let Err(e) = image.save(path) {
        eprintln!("cannot write {}: {e}", path.display());
    }
}

fn median_ms(mut samples: Vec<f64>) -> f64 {
    samples.sort_by(f64::total_cmp);
    samples[samples.len() / 2]
}

const USAGE: &str = "\
usage: cargo run --release -p sim-harness --example render_bench -- [FLAGS]

  --png DIR        also write frames of every target under a few Sun directions to DIR
  --png-range F    distance of those frames as a fraction of the framing range (default 1)
  -h, --help       this text";

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if args.iter().any(|a| a == "--help" || a == "-h") {
        println!("{USAGE}\n\n{}", gs_core::fpmode::ENV_HELP);
        return;
    }
    if let Err(e) = gs_core::fpmode::init_from_env(None) {
        eprintln!("render_bench: {e}");
        std::process::exit(2);
    }
    let png_dir = args
        .iter()
        .position(|a| a == "--png")
        .and_then(|i| args.get(i + 1))
        .map(PathBuf::from);
    // Distance of the PNG views as a fraction of the framing range (below 1 zooms in).
    let png_range_factor: f32 = args
        .iter()
        .position(|a| a == "--png-range")
        .and_then(|i| args.get(i + 1))
        .and_then(|v| v.parse().ok())
        .filter(|f: &f32| f.is_finite() && *f > 0.0)
        .unwrap_or(1.0);
    if let Some(dir) = &png_dir {
        if let Err(e) = std::fs::create_dir_all(dir) {
            eprintln!("cannot create {}: {e}", dir.display());
            std::process::exit(1);
        }
    }
    println!("{}", gs_core::machine::header_line());
    println!("threads: {}", rayon::current_num_threads());
    println!(
        "{:<10} {:>10} {:>10} {:>8} {:>14} {:>14} {:>16}",
        "target",
        "triangles",
        "radius_m",
        "bvh_ms",
        "frame_1spp_ms",
        "frame_4spp_ms",
        "close_1spp_ms"
    );
    for kind in BuiltinTarget::ALL {
        let mesh = builtin_target(kind);
        let triangles = mesh.triangle_count();
        let radius_m = mesh.bounding_radius_m();
        let start = Instant::now();
        let scene = Scene::new(mesh);
        let bvh_ms = start.elapsed().as_secs_f64() * 1e3;
        // Distance so the bounding sphere fills ~90% of the image height.
        let half_fov_y = (camera().cy / camera().fy).atan();
        let range_m = radius_m / 0.9 / half_fov_y.tan();
        let sun = Vec3::new(0.6, -0.3, 0.75).normalize();
        // Framed (whole craft in view) at 1 and 4 samples, and close (craft fills the frame).
        let mut timings = [Vec::new(), Vec::new(), Vec::new()];
        for (slot, spp, range_factor) in [(0, 1, 1.0), (1, 4, 1.0), (2, 1, 0.4)] {
            for _ in 0..REPEATS {
                for dir in view_directions() {
                    let req = request(dir * range_m * range_factor, sun, spp);
                    let start = Instant::now();
                    let frame = render_frame(&scene, &req);
                    timings[slot].push(start.elapsed().as_secs_f64() * 1e3);
                    std::hint::black_box(&frame);
                }
            }
        }
        let [t1, t4, t_close] = timings.map(median_ms);
        println!(
            "{:<10} {:>10} {:>10.2} {:>8.1} {:>14.1} {:>14.1} {:>16.1}",
            kind.name(),
            triangles,
            radius_m,
            bvh_ms,
            t1,
            t4,
            t_close
        );
        if let Some(dir) = &png_dir {
            let suns = [
                ("sun_front", Vec3::new(1.0, -1.0, 0.5)),
                ("sun_side", Vec3::new(-0.2, -1.0, -0.1)),
                ("sun_top", Vec3::new(0.1, 0.2, 1.0)),
                ("sun_back", Vec3::new(-1.0, 0.8, -0.3)),
            ];
            for (view_index, view) in view_directions().into_iter().enumerate() {
                for (sun_name, sun) in suns {
                    let eye = view * range_m * png_range_factor;
                    let frame = render_frame(&scene, &request(eye, sun, 4));
                    let name = format!("{}_view{view_index}_{sun_name}.png", kind.name());
                    write_png(&frame, &dir.join(name));
                }
            }
            let eye = view_directions()[0] * range_m * png_range_factor;
            let mut eclipse = request(eye, sun, 4);
            eclipse.sun_lit = false;
            eclipse.earth_albedo = Some(EarthFill {
                dir_target: Vec3::new(0.2, -1.0, -0.6).normalize(),
                strength: 0.3,
            });
            let frame = render_frame(&scene, &eclipse);
            write_png(
                &frame,
                &dir.join(format!("{}_eclipse_fill.png", kind.name())),
            );
        }
    }
}

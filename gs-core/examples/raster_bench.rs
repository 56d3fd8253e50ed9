//! Rasterizer benchmark: forward and backward time on an object-like scene.
//!
//! The scene is a satellite-sized body (a 1.2 x 1.2 x 1.6 m box bus with two 2.6 x 1.1 m
//! solar panels) covered by flat Gaussians sampled uniformly by area, seen from a
//! three-quarter view at the distance where the rendered alpha exceeds 0.5 on about a
//! third of the pixels. For 10K, 50K, 100K Gaussians at 480x300 and 960x600 it reports
//! median forward and backward times (over `--runs`, default 7, after one warm-up), the
//! per-stage split and the peak resident memory.
//!
//! `cargo run --release -p gs-core --example raster_bench -- [--json] [--runs N] [--quick]
//! [--gaussians N] [--width 480|960]`
//! prints a human table on stdout; with `--json` the table goes to stderr and stdout
//! carries one JSON object per configuration. `cpu` is the CPU time of forward + backward
//! summed over all threads: on a shared machine, `cpu / threads` is what the wall time
//! would be with the cores to ourselves (assuming perfect parallel scaling).

use std::time::Instant;

mod bench_util;
use bench_util::{
    arg, exit_if_help, init_threads, json_machine_fields, median, peak_rss_mb, process_cpu_ms,
    Cloud,
};

use glam::{Quat, Vec3};
use gs_core::raster::{
    render, render_backward_with, render_with, PixelGrads, RasterSettings, RasterWorkspace,
};
use gs_core::rng::SplitMix64;
use gs_core::{Camera, Intrinsics};

/// A flat rectangle: centre, two half-edge vectors, and a base colour.
struct Face {
    centre: Vec3,
    half_u: Vec3,
    half_v: Vec3,
    colour: [f32; 3],
}

impl Face {
    fn area(&self) -> f32 {
        4.0 * self.half_u.length() * self.half_v.length()
    }
}

fn satellite_faces() -> Vec<Face> {
    let mut faces = Vec::new();
    let half = Vec3::new(0.6, 0.6, 0.8);
    let gold = [0.8, 0.6, 0.2];
    for axis in 0..3 {
        for sign in [-1.0f32, 1.0] {
            let mut n = Vec3::ZERO;
            n[axis] = sign * half[axis];
            let (a, b) = ((axis + 1) % 3, (axis + 2) % 3);
            let mut u = Vec3::ZERO;
            u[a] = half[a];
            let mut v = Vec3::ZERO;
            v[b] = half[b];
            faces.push(Face {
                centre: n,
                half_u: u,
                half_v: v,
                colour: gold,
            });
        }
    }
    for sign in [-1.0f32, 1.0] {
        // Panels on +-x, both sides of each (front blue cells, back grey).
        for (offset, colour) in [(0.005f32, [0.1, 0.15, 0.5]), (-0.005, [0.5, 0.5, 0.5])] {
            faces.push(Face {
                centre: Vec3::new(sign * (0.6 + 0.2 + 1.3), offset, 0.0),
                half_u: Vec3::new(1.3, 0.0, 0.0),
                half_v: Vec3::new(0.0, 0.0, 0.55),
                colour,
            });
        }
    }
    faces
}

fn satellite_scene(n: usize, seed: u64) -> Cloud {
    let faces = satellite_faces();
    let total_area: f32 = faces.iter().map(Face::area).sum();
    let mut rng = SplitMix64::new(seed);
    // Tangent sigma so that neighbours overlap (mean spacing sqrt(area / n)).
    let spacing = (total_area / n as f32).sqrt();
    let mut s = Cloud::with_capacity(n);
    for _ in 0..n {
        let mut pick = rng.uniform(0.0, total_area);
        let mut face = &faces[0];
        for f in &faces {
            face = f;
            if pick < f.area() {
                break;
            }
            pick -= f.area();
        }
        let p = face.centre
            + face.half_u * rng.uniform(-1.0, 1.0)
            + face.half_v * rng.uniform(-1.0, 1.0);
        s.means.extend(p.to_array());
        let tangent = spacing * rng.uniform(0.5, 1.0);
        s.log_scales.extend([
            tangent.ln(),
            (tangent * rng.uniform(0.4, 1.0)).ln(),
            (0.1 * tangent).ln(),
        ]);
        // Local x, y along the face, z along the normal, spun randomly about the normal.
        let basis = Quat::from_mat3(&glam::Mat3::from_cols(
            face.half_u.normalize(),
            face.half_v.normalize(),
            face.half_u.cross(face.half_v).normalize(),
        ));
        let q = basis * Quat::from_rotation_z(rng.uniform(0.0, std::f32::consts::TAU));
        s.rotations.extend([q.w, q.x, q.y, q.z]);
        s.opacity_logits.push(rng.uniform(0.5, 3.0));
        for c in face.colour {
            s.channels
                .push((c + rng.uniform(-0.1, 0.1)).clamp(0.0, 1.0));
        }
    }
    s
}

fn camera_at(distance_m: f32, width: u32, height: u32) -> Camera {
    let dir = Vec3::new(0.6, -0.7, 0.4).normalize();
    Camera::look_at(
        Intrinsics::from_fov_x(0.7, width, height),
        dir * distance_m,
        Vec3::ZERO,
        Vec3::Z,
    )
}

fn coverage(scene: &Cloud, cam: &Camera) -> f32 {
    let out = render(cam, &scene.view(), &RasterSettings::default()).expect("render");
    out.alpha.iter().filter(|&&a| a > 0.5).count() as f32 / out.alpha.len() as f32
}

/// Distance at which about a third of the pixels are covered (bisection on a coarse render).
fn calibrate_distance() -> f32 {
    let scene = satellite_scene(20_000, 1);
    let (mut near, mut far) = (3.0f32, 60.0f32);
    for _ in 0..14 {
        let mid = 0.5 * (near + far);
        if coverage(&scene, &camera_at(mid, 240, 150)) > 1.0 / 3.0 {
            near = mid;
        } else {
            far = mid;
        }
    }
    0.5 * (near + far)
}

struct Row {
    gaussians: usize,
    width: u32,
    height: u32,
    visible: usize,
    tile_entries_per_gaussian: f64,
    coverage: f32,
    forward_ms: f64,
    backward_ms: f64,
    project_ms: f64,
    sort_bin_ms: f64,
    blend_ms: f64,
    backward_blend_ms: f64,
    backward_reduce_project_ms: f64,
    cpu_ms: f64,
}

fn bench(n: usize, width: u32, height: u32, distance_m: f32, runs: usize) -> Row {
    let scene = satellite_scene(n, 7);
    let cam = camera_at(distance_m, width, height);
    let settings = RasterSettings::default();
    // A fixed, dense pixel gradient (as from an L1 loss against a flat grey target).
    let d_color: Vec<f32> = (0..width as usize * height as usize * 3)
        .map(|i| if i % 7 < 3 { 1.0 } else { -1.0 } / (width * height) as f32)
        .collect();
    let mut cpu = Vec::new();
    let mut fwd = Vec::new();
    let mut bwd = Vec::new();
    let (mut proj, mut sort, mut blend, mut bblend, mut bred) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let mut visible = 0;
    let mut cov = 0.0;
    // Scratch memory reused across iterations, as a training loop does.
    let mut workspace = RasterWorkspace::default();
    for run in 0..=runs {
        let cpu0 = process_cpu_ms();
        let t0 = Instant::now();
        let out = render_with(&mut workspace, &cam, &scene.view(), &settings).expect("render");
        let forward_ms = t0.elapsed().as_secs_f64() * 1e3;
        let t1 = Instant::now();
        let grads = render_backward_with(
            &mut workspace,
            &cam,
            &scene.view(),
            &settings,
            &out,
            &PixelGrads {
                d_color: &d_color,
                d_alpha: None,
                d_depth: None,
            },
        )
        .expect("backward");
        let backward_ms = t1.elapsed().as_secs_f64() * 1e3;
        std::hint::black_box(&grads);
        let cpu_ms = process_cpu_ms() - cpu0;
        if run == 0 {
            visible = out.visible.iter().filter(|&&v| v).count();
            cov = out.alpha.iter().filter(|&&a| a > 0.5).count() as f32 / out.alpha.len() as f32;
            continue; // warm-up
        }
        cpu.push(cpu_ms);
        fwd.push(forward_ms);
        bwd.push(backward_ms);
        proj.push(out.timings.project_ms);
        sort.push(out.timings.sort_bin_ms);
        blend.push(out.timings.blend_ms);
        bblend.push(grads.timings.blend_ms);
        bred.push(grads.timings.reduce_project_ms);
    }
    let out = render(&cam, &scene.view(), &settings).expect("render");
    let entries = out.tile_entry_count();
    Row {
        gaussians: n,
        width,
        height,
        visible,
        tile_entries_per_gaussian: entries as f64 / visible.max(1) as f64,
        coverage: cov,
        forward_ms: median(fwd.clone()),
        backward_ms: median(bwd.clone()),
        project_ms: median(proj.clone()),
        sort_bin_ms: median(sort.clone()),
        blend_ms: median(blend.clone()),
        backward_blend_ms: median(bblend.clone()),
        backward_reduce_project_ms: median(bred.clone()),
        cpu_ms: median(cpu.clone()),
    }
}

const USAGE: &str = "\
usage: cargo run --release -p gs-core --example raster_bench -- [FLAGS]

  --json          one JSON object per configuration on stdout, the table on stderr
  --runs N        timed runs per configuration after one warm-up (default 7)
  --quick         10K Gaussians at 480x300 only
  --gaussians N   one size instead of 10000, 50000, 100000
  --width W       keep the resolution of this width (480 or 960)
  -h, --help      this text";

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    exit_if_help(&args, USAGE);
    init_threads("raster_bench", None);
    let json = args.iter().any(|a| a == "--json");
    let quick = args.iter().any(|a| a == "--quick");
    let runs = arg(&args, "--runs").unwrap_or(7).max(1);
    let threads = rayon::current_num_threads();
    let distance_m = calibrate_distance();
    let mut sizes: Vec<usize> = if quick {
        vec![10_000]
    } else {
        vec![10_000, 50_000, 100_000]
    };
    let mut resolutions: Vec<(u32, u32)> = if quick {
        vec![(480, 300)]
    } else {
        vec![(480, 300), (960, 600)]
    };
    if let Some(n) = arg(&args, "--gaussians") {
        sizes = vec![n];
    }
    if let Some(w) = arg(&args, "--width") {
        resolutions.retain(|r| r.0 as usize == w);
    }

    let mut table = format!("{}\n", gs_core::machine::header_line());
    table += &format!(
        "raster_bench: satellite scene at {distance_m:.2} m, {threads} threads, median of {runs} runs (ms)\n"
    );
    table += &format!(
        "{:>8} {:>9} {:>7} {:>5} {:>6} | {:>8} {:>8} {:>8} | {:>7} {:>7} {:>7} | {:>8} {:>8} {:>7} | {:>7}\n",
        "gauss", "image", "visible", "cover", "tiles/g", "forward", "backward", "total",
        "project", "sort", "blend", "bwd-blnd", "bwd-red", "cpu", "rss MB"
    );
    for &n in &sizes {
        for &(w, h) in &resolutions {
            let r = bench(n, w, h, distance_m, runs);
            let rss = peak_rss_mb();
            table += &format!(
                "{:>8} {:>9} {:>7} {:>5.2} {:>6.2} | {:>8.1} {:>8.1} {:>8.1} | {:>7.1} {:>7.1} {:>7.1} | {:>8.1} {:>8.1} {:>7.1} | {:>7.0}\n",
                r.gaussians,
                format!("{}x{}", r.width, r.height),
                r.visible,
                r.coverage,
                r.tile_entries_per_gaussian,
                r.forward_ms,
                r.backward_ms,
                r.forward_ms + r.backward_ms,
                r.project_ms,
                r.sort_bin_ms,
                r.blend_ms,
                r.backward_blend_ms,
                r.backward_reduce_project_ms,
                r.cpu_ms,
                rss
            );
            if json {
                println!(
                    "{{\"gaussians\":{},\"width\":{},\"height\":{},\"threads\":{},{},\"forward_ms\":{:.3},\"backward_ms\":{:.3},\"peak_rss_mb\":{:.1},\"visible\":{},\"coverage\":{:.3},\"tile_entries_per_gaussian\":{:.3},\"project_ms\":{:.3},\"sort_bin_ms\":{:.3},\"blend_ms\":{:.3},\"backward_blend_ms\":{:.3},\"backward_reduce_project_ms\":{:.3},\"cpu_ms\":{:.3},\"runs\":{}}}",
                    r.gaussians, r.width, r.height, threads, json_machine_fields(), r.forward_ms, r.backward_ms, rss,
                    r.visible, r.coverage, r.tile_entries_per_gaussian, r.project_ms, r.sort_bin_ms,
                    r.blend_ms, r.backward_blend_ms, r.backward_reduce_project_ms, r.cpu_ms, runs
                );
            }
        }
    }
    if json {
        eprint!("{table}");
    } else {
        print!("{table}");
    }
}

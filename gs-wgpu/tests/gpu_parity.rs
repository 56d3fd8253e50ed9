//! Parity of the wgpu backend with the CPU path: forward images and every gradient of the
//! rasterizer, and the shadow pass, on random scenes. This file holds the scenes, the
//! forward and gradient checks and the input errors; `gpu_parity/` the shadow pass
//! (`light.rs`), the sort (`sort.rs`) and the rasterizer's switches (`switches.rs`).
//!
//! Without an adapter the tests print a skip notice, unless `GS_REQUIRE_GPU=1` (set by
//! CI), where a missing adapter fails every test with the reason.
//!
//! Scenes are 2,000 Gaussians at 128x96 (a few seconds on Mesa's software driver on
//! two cores): a cloud in front of the camera with random sizes from sub-pixel to a
//! tenth of the view, random rotations, opacities from 0.05 up past the 0.99 clamp,
//! some Gaussians behind the near plane, off-screen, or with the Jacobian clamp active.

use glam::Vec3;
use gs_core::raster::bin::{bin_tiles, PixelRect, TileGrid, TileSelection};
use gs_core::raster::blend::{tile_contributions, AlphaMode, Splat, ENTRY_BLENDS};
use gs_core::raster::{
    camera_frame, depth_order, prepare_view, project_splats_with, render, render_backward,
    GaussianGrads, GaussianView, PixelGrads, RasterSettings, RenderOutput,
};
use gs_core::rng::SplitMix64;
use gs_core::{Camera, Intrinsics};
use gs_wgpu::{context_or_skip, GpuContext, GpuOptions, GpuRasterizer, GpuRenderOutput};

/// A context, or None (with a notice) when there is no adapter and GS_REQUIRE_GPU is
/// not 1.
fn context(options: GpuOptions) -> Option<GpuContext> {
    context_or_skip(options)
}

struct Scene {
    camera: Camera,
    settings: RasterSettings,
    means: Vec<f32>,
    log_scales: Vec<f32>,
    rotations: Vec<f32>,
    opacity_logits: Vec<f32>,
    channels: Vec<f32>,
    n_channels: usize,
}

impl Scene {
    fn view(&self) -> GaussianView<'_> {
        GaussianView {
            means: &self.means,
            log_scales: &self.log_scales,
            rotations: &self.rotations,
            opacity_logits: &self.opacity_logits,
            channels: &self.channels,
            n_channels: self.n_channels,
        }
    }
}

/// `n` Gaussians seen by a 128x96 camera (fov_x 1 rad, Jacobian clamp at x/z = 0.71).
fn random_scene(seed: u64, n: usize, n_channels: usize, smooth: bool) -> Scene {
    let mut rng = SplitMix64::new(seed);
    let k = Intrinsics::from_fov_x(1.0, 128, 96);
    let camera = Camera::look_at(
        k,
        Vec3::new(0.3, -0.4, -4.0),
        Vec3::new(0.0, 0.1, 0.0),
        Vec3::new(0.1, 1.0, 0.0),
    );
    let mut s = Scene {
        camera,
        settings: RasterSettings {
            near_m: 0.2,
            background: (0..n_channels).map(|_| rng.uniform(0.0, 1.0)).collect(),
            smooth_cutoff: smooth,
            ..RasterSettings::default()
        },
        means: Vec::with_capacity(3 * n),
        log_scales: Vec::with_capacity(3 * n),
        rotations: Vec::with_capacity(4 * n),
        opacity_logits: Vec::with_capacity(n),
        channels: Vec::with_capacity(n * n_channels),
        n_channels,
    };
    for i in 0..n {
        // Camera-frame centre: mostly inside the view, some beyond its edges (clamp),
        // a few behind the near plane.
        let z = if i % 97 == 0 {
            rng.uniform(-1.0, 0.19)
        } else {
            rng.uniform(1.5, 7.0)
        };
        let spread = if i % 13 == 0 { 1.1 } else { 0.5 };
        let c = Vec3::new(
            rng.uniform(-spread, spread) * z.abs(),
            rng.uniform(-spread, spread) * 0.75 * z.abs(),
            z,
        );
        let world = camera.rotation.conjugate() * (c - camera.translation);
        s.means.extend(world.to_array());
        for _ in 0..3 {
            s.log_scales.push(rng.uniform(-4.5, -1.8));
        }
        for _ in 0..4 {
            s.rotations.push(rng.uniform(-1.0, 1.0));
        }
        s.opacity_logits.push(rng.uniform(-3.0, 5.0));
        for _ in 0..n_channels {
            s.channels.push(rng.uniform(0.0, 1.0));
        }
    }
    s
}

fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

fn count_above(a: &[f32], b: &[f32], tol: f32) -> usize {
    a.iter()
        .zip(b)
        .filter(|(x, y)| (*x - *y).abs() > tol)
        .count()
}

#[test]
fn context_reports_adapter() {
    let Some(ctx) = context(GpuOptions::default()) else {
        return;
    };
    assert!(!ctx.adapter_name().is_empty());
    assert_eq!(ctx.backend(), "Vulkan");
    let forced = GpuContext::with_options(GpuOptions {
        force_cas_atomics: true,
        ..GpuOptions::default()
    })
    .expect("a second context on the same adapter");
    assert!(!forced.uses_float32_atomics());
    assert_eq!(forced.has_float32_atomics(), ctx.has_float32_atomics());
}

/// Forward images against the CPU.
///
/// Tolerances: colour and alpha within 2e-5 (depth within 2e-5 of the largest depth)
/// for all but 0.1% of values, and every value within 1e-2 (depth 1e-2 x the largest
/// depth). Why: both paths run the same f32 formulas, but the GPU may fuse multiplies
/// and adds and its exp/log/sqrt differ by an ulp or two, so a pixel's sum of a few
/// dozen terms differs by ~1e-6. Rarely a difference moves a splat's alpha across the
/// 1/255 cutoff (or T across the 1e-4 stop) at a pixel; that changes the pixel by at
/// most about 2/255 of the largest value, hence the 1e-2 cap.
fn forward_parity(seed: u64, n_channels: usize, smooth: bool) {
    let Some(ctx) = context(GpuOptions::default()) else {
        return;
    };
    let gpu = GpuRasterizer::new(ctx).unwrap();
    let scene = random_scene(seed, 2000, n_channels, smooth);
    let (cpu, _) = compare_forward(&gpu, &scene, &format!("seed {seed}"));
    // The scene is not trivial: most of the image is covered, some Gaussians are culled.
    let px = cpu.alpha.len();
    assert!(cpu.alpha.iter().filter(|&&a| a > 0.5).count() > px / 4);
    assert!(cpu.visible.iter().any(|v| !v));
}

/// `scene` rendered on both paths and compared with [`forward_parity`]'s tolerances;
/// returns both renders.
fn compare_forward(
    gpu: &GpuRasterizer,
    scene: &Scene,
    label: &str,
) -> (RenderOutput, GpuRenderOutput) {
    let (n_channels, smooth) = (scene.n_channels, scene.settings.smooth_cutoff);
    let cpu = render(&scene.camera, &scene.view(), &scene.settings).unwrap();
    let out = gpu
        .render(&scene.camera, &scene.view(), &scene.settings)
        .unwrap();
    assert_eq!(out.tile_entries, cpu.tile_entry_count());
    assert_eq!(out.visible, cpu.visible);
    let max_depth = cpu.depth.iter().fold(0.0f32, |m, v| m.max(*v));
    for (name, g, c, scale) in [
        ("colour", &out.color, &cpu.color, 1.0),
        ("alpha", &out.alpha, &cpu.alpha, 1.0),
        ("depth", &out.depth, &cpu.depth, max_depth),
    ] {
        let worst = max_abs_diff(g, c);
        let n_off = count_above(g, c, 2e-5 * scale);
        eprintln!(
            "{label} nc {n_channels} smooth {smooth}: {name} max |gpu - cpu| {worst:.2e} \
             ({n_off} of {} above {:.1e})",
            c.len(),
            2e-5 * scale
        );
        assert!(worst <= 1e-2 * scale, "{name}: {worst}");
        assert!(n_off * 1000 <= c.len(), "{name}: {n_off} values off");
    }
    // Radii are sqrt(2 ln(o / cutoff) lambda_max) of pixel-sized values: 1e-3 px is
    // ~1e-4 relative, far above the ulp-level differences of the inputs.
    let radius_err = max_abs_diff(&out.radii_px, &cpu.radii_px);
    assert!(radius_err < 1e-3, "radius {radius_err}");
    // The forward is deterministic: the same call gives the same bits.
    let again = gpu
        .render(&scene.camera, &scene.view(), &scene.settings)
        .unwrap();
    assert!(again.color == out.color && again.alpha == out.alpha && again.depth == out.depth);
    (cpu, out)
}

#[test]
fn forward_matches_cpu_rgb() {
    forward_parity(11, 3, false);
}

#[test]
fn forward_matches_cpu_smooth_four_channels() {
    forward_parity(12, 4, true);
}

fn pixel_grads(scene: &Scene, seed: u64) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    let mut rng = SplitMix64::new(seed);
    let px = scene.camera.intrinsics.pixel_count();
    let mut draw = |n: usize, s: f32| (0..n).map(|_| rng.uniform(-s, s)).collect::<Vec<f32>>();
    (
        draw(px * scene.n_channels, 1.0),
        draw(px, 1.0),
        draw(px, 0.3),
    )
}

/// Gradients against the CPU backward, for a linear loss of colour, alpha and depth.
///
/// Tolerance per value: |gpu - cpu| <= 1e-4 G + 1e-3 |cpu|, G the largest |cpu| value of
/// that group (means, log-scales, rotations, opacities, channels, NDC mean gradient).
/// Why: a gradient is a sum over every pixel a Gaussian touches (hundreds of terms of
/// both signs); the GPU adds them in a different order (tree within a tile, atomics
/// across tiles) and rounds the per-pixel terms slightly differently, so small sums that
/// cancel carry errors relative to the large terms, ~1e-6 G. In hard mode a pixel can
/// cross the 1/255 cutoff (see the forward test): up to 0.1% of values may then exceed
/// the tolerance, each still within 5e-2 G.
fn grads_parity(seed: u64, n_channels: usize, smooth: bool, options: GpuOptions) {
    let Some(ctx) = context(options) else {
        return;
    };
    let gpu = GpuRasterizer::new(ctx).unwrap();
    let scene = random_scene(seed, 2000, n_channels, smooth);
    compare_grads(&gpu, &scene, seed, options);
}

/// `scene`'s gradients on both paths for random pixel gradients (from `seed`), compared
/// with [`grads_parity`]'s tolerances; returns both.
fn compare_grads(
    gpu: &GpuRasterizer,
    scene: &Scene,
    seed: u64,
    options: GpuOptions,
) -> (GaussianGrads, GaussianGrads) {
    let smooth = scene.settings.smooth_cutoff;
    let (dc, da, dd) = pixel_grads(scene, seed ^ 0x5EED);
    let pg = PixelGrads {
        d_color: &dc,
        d_alpha: Some(&da),
        d_depth: Some(&dd),
    };
    let cpu_f = render(&scene.camera, &scene.view(), &scene.settings).unwrap();
    let cpu = render_backward(&scene.camera, &scene.view(), &scene.settings, &cpu_f, &pg).unwrap();
    let gpu_f = gpu
        .render(&scene.camera, &scene.view(), &scene.settings)
        .unwrap();
    let g = gpu
        .render_backward(&scene.camera, &scene.settings, &gpu_f, &pg)
        .unwrap();
    assert_eq!(g.dropped_nonfinite, 0);
    assert_eq!(cpu.dropped_nonfinite, 0);
    if options.deterministic {
        let again = gpu
            .render_backward(&scene.camera, &scene.settings, &gpu_f, &pg)
            .unwrap();
        let bits = |g: &GaussianGrads| -> Vec<u32> {
            [
                &g.d_means,
                &g.d_log_scales,
                &g.d_rotations,
                &g.d_opacity_logits,
                &g.d_channels,
                &g.mean2d_grad_ndc,
            ]
            .iter()
            .flat_map(|v| v.iter().map(|x| x.to_bits()))
            .collect()
        };
        assert!(bits(&g) == bits(&again), "deterministic backward differs");
    }
    let allowed_off = if smooth { 0.0 } else { 1e-3 };
    let groups: [(&str, &[f32], &[f32]); 6] = [
        ("means", &cpu.d_means, &g.d_means),
        ("log_scales", &cpu.d_log_scales, &g.d_log_scales),
        ("rotations", &cpu.d_rotations, &g.d_rotations),
        ("opacity", &cpu.d_opacity_logits, &g.d_opacity_logits),
        ("channels", &cpu.d_channels, &g.d_channels),
        ("ndc", &cpu.mean2d_grad_ndc, &g.mean2d_grad_ndc),
    ];
    for (name, c, x) in groups {
        let big = c.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        assert!(big > 0.0, "{name}: all zero");
        let mut worst = 0.0f32;
        let mut n_off = 0usize;
        for (a, b) in c.iter().zip(x) {
            let err = (a - b).abs();
            let tol = 1e-4 * big + 1e-3 * a.abs();
            worst = worst.max(err / tol);
            if err > tol {
                n_off += 1;
                assert!(err <= 5e-2 * big, "{name}: cpu {a} gpu {b}");
            }
        }
        eprintln!(
            "seed {seed} smooth {smooth}: {name}: max |cpu| {big:.3e}, worst error / tolerance \
             {worst:.3}, {n_off} of {} beyond",
            c.len()
        );
        assert!(
            n_off as f64 <= allowed_off * c.len() as f64,
            "{name}: {n_off} of {} values beyond tolerance",
            c.len()
        );
    }
    (cpu, g)
}

#[test]
fn gradients_match_cpu_smooth() {
    grads_parity(21, 3, true, GpuOptions::default());
}

#[test]
fn gradients_match_cpu_hard() {
    grads_parity(22, 3, false, GpuOptions::default());
}

/// The compare-and-swap accumulation, forced even where f32 atomics exist.
#[test]
fn gradients_match_cpu_cas_fallback() {
    grads_parity(
        23,
        4,
        true,
        GpuOptions {
            force_cas_atomics: true,
            ..GpuOptions::default()
        },
    );
}

/// The per-tile workgroup reduction variant of the backward (one atomic add per key and
/// value instead of one per pixel).
#[test]
fn gradients_match_cpu_workgroup_reduction() {
    grads_parity(
        24,
        3,
        false,
        GpuOptions {
            workgroup_reduction: true,
            ..GpuOptions::default()
        },
    );
}

/// Deterministic mode: same parity, and two backward passes give the same bits.
#[test]
fn gradients_match_cpu_deterministic() {
    grads_parity(
        25,
        3,
        false,
        GpuOptions {
            deterministic: true,
            ..GpuOptions::default()
        },
    );
}

#[test]
fn bad_inputs_are_errors() {
    let Some(ctx) = context(GpuOptions::default()) else {
        return;
    };
    let gpu = GpuRasterizer::new(ctx).unwrap();
    let scene = random_scene(5, 50, 3, false);
    let mut view = scene.view();
    view.means = &scene.means[..3];
    assert!(gpu.render(&scene.camera, &view, &scene.settings).is_err());
    let mut camera = scene.camera;
    camera.intrinsics.fx = f32::NAN;
    assert!(gpu.render(&camera, &scene.view(), &scene.settings).is_err());
    let wide = vec![0.5f32; 50 * 9];
    let mut view = scene.view();
    view.channels = &wide;
    view.n_channels = 9;
    assert!(gpu
        .render(&scene.camera, &view, &RasterSettings::default())
        .is_err());
    // No Gaussians: the background, no tile entries.
    let empty = GaussianView {
        means: &[],
        log_scales: &[],
        rotations: &[],
        opacity_logits: &[],
        channels: &[],
        n_channels: 3,
    };
    let out = gpu.render(&scene.camera, &empty, &scene.settings).unwrap();
    assert_eq!(out.tile_entries, 0);
    assert!(out.alpha.iter().all(|&a| a == 0.0));
    for px in out.color.chunks_exact(3) {
        assert_eq!(px, &scene.settings.background[..]);
    }
    let out = gpu
        .render(&scene.camera, &scene.view(), &scene.settings)
        .unwrap();
    let px = scene.camera.intrinsics.pixel_count();
    let mut d_color = vec![0.0f32; px * 3];
    d_color[7] = f32::INFINITY;
    let pg = PixelGrads {
        d_color: &d_color,
        d_alpha: None,
        d_depth: None,
    };
    assert!(gpu
        .render_backward(&scene.camera, &scene.settings, &out, &pg)
        .is_err());
}

#[path = "gpu_parity/light.rs"]
mod light;
#[path = "gpu_parity/sort.rs"]
mod sort;
#[path = "gpu_parity/switches.rs"]
mod switches;

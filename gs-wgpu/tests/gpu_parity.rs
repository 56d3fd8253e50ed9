//! Parity of the wgpu backend with the CPU path: forward images and every gradient of the
//! rasterizer, and the shadow pass, on random scenes.
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

/// The GPU shadow pass against `sunaware::sun_visibility::visibility_from_splats`, on splats of a
/// random scene in a 128x128 light image with random receiver margins.
///
/// Tolerance: |V_gpu - V_cpu| <= 1e-4 for all but 0.5% of the Gaussians, and <= 2e-2 for
/// all. Why: V is a ratio of sums over a Gaussian's footprint pixels (f32 on the GPU,
/// f64 across tiles on the CPU; exp differs by an ulp), ~1e-6 apart; where rounding moves
/// an occluder's alpha across 1/255 at a pixel, that pixel's T changes by 0.4% and the
/// receiver's V by at most that.
#[test]
fn shadow_visibility_matches_cpu() {
    use gs_core::raster::blend::AlphaMode;
    use gs_core::raster::{camera_frame, project_splats};
    use gs_core::sunaware::sun_visibility::visibility_from_splats;
    use gs_wgpu::GpuSunVisibility;
    use std::sync::Arc;

    let Some(ctx) = context(GpuOptions::default()) else {
        return;
    };
    let shadow = GpuSunVisibility::new(Arc::new(GpuRasterizer::new(ctx).unwrap())).unwrap();
    let mut scene = random_scene(31, 2000, 3, false);
    scene.camera.intrinsics = Intrinsics::from_fov_x(1.0, 128, 128);
    let frame = camera_frame(&scene.camera, 0.2).unwrap();
    let splats =
        project_splats(&frame, &scene.view(), AlphaMode { smooth: false }, 128, 128).splats;
    let mut rng = SplitMix64::new(32);
    let margins: Vec<f32> = (0..splats.len()).map(|_| rng.uniform(0.0, 0.3)).collect();
    for (radius, bias, margin) in [(2.0, 0.01, &margins[..]), (3.5, 0.05, &[][..])] {
        let cpu = visibility_from_splats(&splats, 128, radius, bias, margin);
        let gpu = shadow
            .visibility_from_splats(&splats, 128, radius, bias, margin)
            .unwrap();
        let worst = max_abs_diff(&gpu, &cpu);
        let n_off = count_above(&gpu, &cpu, 1e-4);
        let shadowed = cpu.iter().filter(|&&v| v < 0.5).count();
        let lit = cpu.iter().filter(|&&v| v > 0.9).count();
        eprintln!(
            "shadow r {radius} bias {bias}: max |dV| {worst:.2e}, {n_off} of {} above 1e-4 \
             ({shadowed} with V < 0.5, {lit} with V > 0.9)",
            cpu.len()
        );
        // The pass is not trivial: both shadowed and lit Gaussians.
        assert!(shadowed > 100 && lit > 100);
        assert!(worst <= 2e-2, "max |dV| {worst}");
        assert!(n_off * 200 <= cpu.len(), "{n_off} Gaussians off");
    }
}

/// `GpuSunVisibility::sun_visibility` against `sunaware::sun_visibility::sun_visibility` for a model, a
/// Sun direction and both light projections (same tolerance as the splat-level test).
#[test]
fn sun_visibility_matches_cpu() {
    use gs_core::init::random_in_sphere;
    use gs_core::nn::SceneBox;
    use gs_core::sunaware::config::{LightConfig, LightProjection};
    use gs_core::sunaware::sun_visibility::sun_visibility;
    use gs_core::ModelLayout;
    use gs_wgpu::GpuSunVisibility;
    use std::sync::Arc;

    let Some(ctx) = context(GpuOptions::default()) else {
        return;
    };
    let shadow = GpuSunVisibility::new(Arc::new(GpuRasterizer::new(ctx).unwrap())).unwrap();
    let model = random_in_sphere(1500, Vec3::ZERO, 1.0, ModelLayout::sh(0), 9)
        .unwrap()
        .model;
    let scene_box = SceneBox::new([-1.0; 3], [1.0; 3]).unwrap();
    let sun = Vec3::new(0.3, -0.5, 0.8).normalize();
    let camera_centre = Vec3::new(0.0, -6.0, 1.0);
    for projection in [LightProjection::Perspective, LightProjection::Orthographic] {
        let config = LightConfig {
            projection,
            ..LightConfig::default()
        };
        let cpu = sun_visibility(&model, sun, camera_centre, &scene_box, &config, 0.01).unwrap();
        let gpu = shadow
            .sun_visibility(&model, sun, camera_centre, &scene_box, &config, 0.01)
            .unwrap();
        let worst = max_abs_diff(&gpu, &cpu);
        let n_off = count_above(&gpu, &cpu, 1e-4);
        let shadowed = cpu.iter().filter(|&&v| v < 0.5).count();
        eprintln!(
            "{projection:?}: max |dV| {worst:.2e}, {n_off} of {} above 1e-4, {shadowed} with V < 0.5",
            cpu.len()
        );
        assert!(shadowed > 50);
        assert!(worst <= 2e-2, "max |dV| {worst}");
        assert!(n_off * 200 <= cpu.len(), "{n_off} Gaussians off");
    }
}

/// Random sort keys: tiles below `n_tiles` and order bits from a handful of values (so
/// many keys tie on both), word 2 random (not ascending, so only a stable sort keeps the
/// given order among ties), word 3 the key's position.
fn sort_keys_input(seed: u64, len: usize, n_tiles: u32) -> Vec<[u32; 4]> {
    let mut rng = SplitMix64::new(seed);
    let orders: Vec<u32> = (0..7).map(|_| rng.next_u64() as u32).collect();
    (0..len)
        .map(|i| {
            let r = rng.next_u64();
            let tile = ((r >> 8) % n_tiles as u64) as u32;
            // Mostly shared values (top bit set and clear among them), some all-random.
            let order = if r & 7 == 0 {
                (r >> 32) as u32
            } else {
                orders[((r >> 3) % 7) as usize]
            };
            [tile, order, rng.next_u64() as u32, i as u32]
        })
        .collect()
}

#[test]
fn radix_sort_matches_a_stable_cpu_sort() {
    let Some(ctx) = context(GpuOptions::default()) else {
        return;
    };
    let raster = GpuRasterizer::new(ctx).unwrap();
    // (buffer length, live keys on the device, tiles): empty, single, block edges (4096
    // keys per workgroup), capacity above the count, 0 tile bits (an even pass count:
    // 8), 9 and 12 tile bits (11 passes: the copy back), 13 (12 passes).
    let cases = [
        (0, 0, 5),
        (1, 1, 5),
        (1, 0, 5),
        (700, 700, 1),
        (4096, 4095, 300),
        (4097, 4097, 4096),
        (10007, 6001, 4096),
        (50001, 50001, 5000),
        (70000, 65537, 300),
    ];
    for (k, &(len, live, n_tiles)) in cases.iter().enumerate() {
        let keys = sort_keys_input(100 + k as u64, len, n_tiles);
        let mut expected = keys[..live].to_vec();
        expected.sort_by_key(|key| (key[0], key[1]));
        expected.extend_from_slice(&keys[live..]);
        let got = raster.sort_keys(&keys, live, n_tiles).unwrap();
        assert_eq!(got.len(), len);
        let first_bad = got.iter().zip(&expected).position(|(a, b)| a != b);
        assert!(
            first_bad.is_none(),
            "len {len}, live {live}, {n_tiles} tiles: first difference at {first_bad:?}"
        );
    }
    let mut keys = sort_keys_input(7, 10, 3);
    assert!(raster.sort_keys(&keys, 11, 3).is_err(), "live > length");
    keys[9][0] = 3;
    assert!(raster.sort_keys(&keys, 10, 3).is_err(), "tile >= n_tiles");
    // Past the live keys a tile word is not read.
    assert!(raster.sort_keys(&keys, 9, 3).is_ok());
}

/// `RasterSettings::early_termination = false` (every pixel blends its whole list, down
/// to T = 1.2e-38): images and gradients against the CPU with the tolerances above, on a
/// scene where the switch changes many pixels.
#[test]
fn early_termination_off_matches_cpu() {
    let Some(ctx) = context(GpuOptions::default()) else {
        return;
    };
    let gpu = GpuRasterizer::new(ctx).unwrap();
    let mut scene = random_scene(31, 2000, 3, false);
    let stopped = render(&scene.camera, &scene.view(), &scene.settings).unwrap();
    scene.settings.early_termination = false;
    let (cpu, out) = compare_forward(&gpu, &scene, "early termination off");
    // The switch matters here: with the stop a pixel keeps T >= 1e-4, without it the
    // alpha of a pixel that stopped grows by about that much.
    let changed = count_above(&cpu.alpha, &stopped.alpha, 2e-5);
    eprintln!(
        "{changed} of {} pixels change by more than 2e-5 (at most {:.2e})",
        cpu.alpha.len(),
        max_abs_diff(&cpu.alpha, &stopped.alpha)
    );
    assert!(changed > 100, "{changed} pixels changed");
    assert!(count_above(&out.alpha, &stopped.alpha, 2e-5) >= changed / 2);
    compare_grads(&gpu, &scene, 31, GpuOptions::default());
}

/// Seeded tile selection over `scene`'s image: about half the tiles, from a mask.
fn holed_selection(scene: &Scene, seed: u64) -> TileSelection {
    let (w, h) = (
        scene.camera.intrinsics.width,
        scene.camera.intrinsics.height,
    );
    let grid = TileGrid::new(w, h);
    let mut rng = SplitMix64::new(seed);
    let mut mask = vec![0.0f32; (w * h) as usize];
    for t in 0..grid.n_tiles() {
        if rng.next_u64() & 1 == 0 {
            let r = grid.tile_rect(t);
            mask[(r.y0 * w + r.x0) as usize] = 1.0;
        }
    }
    let selection = TileSelection::from_mask(&mask, w, h, 0).unwrap();
    let active = selection.active_count();
    assert!(
        active > 0 && active < grid.n_tiles(),
        "{active} tiles active"
    );
    selection
}

/// `RasterSettings::blend_tiles` with holes: skipped tiles' pixels are the CPU's bits
/// exactly (background, alpha 0, depth 0); active tiles are the GPU's own full render,
/// bit for bit, and match the CPU with the tolerances above; gradients match the CPU's
/// (which get nothing from skipped tiles) on both backward kernels.
#[test]
fn blend_tiles_match_cpu() {
    let Some(ctx) = context(GpuOptions::default()) else {
        return;
    };
    let gpu = GpuRasterizer::new(ctx).unwrap();
    let mut scene = random_scene(32, 2000, 3, false);
    let full = gpu
        .render(&scene.camera, &scene.view(), &scene.settings)
        .unwrap();
    let selection = holed_selection(&scene, 32);
    scene.settings.blend_tiles = Some(selection.clone());
    let (cpu, out) = compare_forward(&gpu, &scene, "blend_tiles");
    let grid = TileGrid::new(out.width, out.height);
    let (w, nc) = (out.width as usize, out.n_channels);
    let mut skipped_covered = 0;
    for t in 0..grid.n_tiles() {
        let r = grid.tile_rect(t);
        for y in r.y0 as usize..r.y1 as usize {
            for x in r.x0 as usize..r.x1 as usize {
                let p = y * w + x;
                let colour = |o: &[f32]| -> Vec<u32> {
                    o[p * nc..p * nc + nc].iter().map(|v| v.to_bits()).collect()
                };
                if selection.is_active(t) {
                    assert_eq!(colour(&out.color), colour(&full.color), "pixel {x},{y}");
                    assert_eq!(out.alpha[p].to_bits(), full.alpha[p].to_bits());
                    assert_eq!(out.depth[p].to_bits(), full.depth[p].to_bits());
                } else {
                    assert_eq!(colour(&out.color), colour(&cpu.color), "pixel {x},{y}");
                    let bg: Vec<u32> = scene
                        .settings
                        .background
                        .iter()
                        .map(|v| v.to_bits())
                        .collect();
                    assert_eq!(colour(&out.color), bg);
                    assert_eq!(out.alpha[p].to_bits(), 0.0f32.to_bits());
                    assert_eq!(out.depth[p].to_bits(), 0.0f32.to_bits());
                    assert_eq!(cpu.alpha[p].to_bits(), 0.0f32.to_bits());
                    assert_eq!(cpu.depth[p].to_bits(), 0.0f32.to_bits());
                    skipped_covered += usize::from(full.alpha[p] > 0.5);
                }
            }
        }
    }
    // The skip hides real content.
    assert!(
        skipped_covered > 100,
        "{skipped_covered} covered pixels skipped"
    );
    let (_, g) = compare_grads(&gpu, &scene, 32, GpuOptions::default());
    // Gaussians seen only in skipped tiles get no gradient at all.
    let full_grads = {
        let full_settings = RasterSettings {
            blend_tiles: None,
            ..scene.settings.clone()
        };
        let (dc, da, dd) = pixel_grads(&scene, 32 ^ 0x5EED);
        let pg = PixelGrads {
            d_color: &dc,
            d_alpha: Some(&da),
            d_depth: Some(&dd),
        };
        let f = gpu
            .render(&scene.camera, &scene.view(), &full_settings)
            .unwrap();
        gpu.render_backward(&scene.camera, &full_settings, &f, &pg)
            .unwrap()
    };
    let silenced = (0..scene.opacity_logits.len())
        .filter(|&i| g.d_opacity_logits[i] == 0.0 && full_grads.d_opacity_logits[i] != 0.0)
        .count();
    assert!(silenced > 20, "{silenced} Gaussians lost their gradient");
    // The workgroup-reduction kernel (and the gather) skip the same tiles.
    let Some(det) = context(GpuOptions {
        deterministic: true,
        ..GpuOptions::default()
    }) else {
        return;
    };
    compare_grads(
        &GpuRasterizer::new(det).unwrap(),
        &scene,
        32,
        GpuOptions {
            deterministic: true,
            ..GpuOptions::default()
        },
    );
}

/// Per Gaussian: blended into a pixel of an active tile of `selection`, from the CPU's own
/// projection, depth order, bins and alpha-only tile walk (what
/// `PreparedView::contributing` computes, tile by tile).
fn cpu_contributing_in(scene: &Scene, selection: Option<&TileSelection>) -> Vec<bool> {
    let s = &scene.settings;
    let (w, h) = (
        scene.camera.intrinsics.width,
        scene.camera.intrinsics.height,
    );
    let frame = camera_frame(&scene.camera, s.near_m).unwrap();
    let mode = AlphaMode {
        smooth: s.smooth_cutoff,
    };
    let bare = GaussianView {
        channels: &[],
        n_channels: 0,
        ..scene.view()
    };
    let projected = project_splats_with(&frame, &bare, mode, w, h, s.cull_outside_frustum);
    let gaussian_of_rank = depth_order(&projected.splats);
    let splats: Vec<Splat> = gaussian_of_rank
        .iter()
        .filter_map(|&g| projected.splats[g as usize])
        .collect();
    let rects: Vec<PixelRect> = splats.iter().map(|s| s.rect).collect();
    let grid = TileGrid::new(w, h);
    let bins = bin_tiles(&grid, &rects);
    let mut out = vec![false; bare.len()];
    for t in 0..grid.n_tiles() {
        if selection.is_some_and(|sel| !sel.is_active(t)) {
            continue;
        }
        let list = &bins.tile_ranks[bins.tile_offsets[t]..bins.tile_offsets[t + 1]];
        let mut flags = vec![0u8; list.len()];
        tile_contributions(
            &grid.tile_rect(t),
            list,
            &splats,
            mode,
            s.early_termination,
            &mut flags,
        );
        for (&f, &rank) in flags.iter().zip(list) {
            if f & ENTRY_BLENDS != 0 {
                out[gaussian_of_rank[rank as usize] as usize] = true;
            }
        }
    }
    out
}

/// The device's contribution pass against the CPU's `PreparedView::contributing` on
/// random views (camera positions and scenes), with early termination on and off and in
/// smooth mode, and against the CPU's tile walk restricted to a selection's tiles.
/// Exact equality: the pass evaluates alpha and the transmittance with the blend's
/// operations, which agree with the CPU's on these scenes bit for bit (a fused multiply-add
/// or an ulp in exp could move an alpha across 1/255 or a T across the stop and so flip a
/// Gaussian seen in one pixel only; none does here, and the test would show it).
#[test]
fn contribution_flags_match_cpu() {
    let Some(ctx) = context(GpuOptions::default()) else {
        return;
    };
    let gpu = GpuRasterizer::new(ctx).unwrap();
    for seed in 0..4u64 {
        // Dense, so that many projected Gaussians hide behind others.
        let mut scene = random_scene(40 + seed, 8000, 3, seed == 3);
        let mut rng = SplitMix64::new(seed);
        let eye = Vec3::new(
            rng.uniform(-1.5, 1.5),
            rng.uniform(-1.0, 1.0),
            rng.uniform(-4.5, -3.0),
        );
        scene.camera = Camera::look_at(
            scene.camera.intrinsics,
            eye,
            Vec3::new(rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3), 0.0),
            Vec3::new(0.0, 1.0, 0.0),
        );
        scene.settings.early_termination = seed != 1;
        let view = scene.view();
        let prepared = prepare_view(&scene.camera, &view, &scene.settings).unwrap();
        let cpu = prepared.contributing();
        let survived = prepared.survived();
        let n_cpu = cpu.iter().filter(|&&c| c).count();
        let n_survived = survived.iter().filter(|&&c| c).count();
        eprintln!("view {seed}: {n_cpu} of {n_survived} projected Gaussians contribute");
        assert!(
            n_cpu > 100 && n_cpu + 20 < n_survived,
            "{n_cpu} of {n_survived}"
        );
        // The reference walk is the CPU's own pass where no tile is left out.
        assert_eq!(cpu_contributing_in(&scene, None), cpu);
        let got = gpu
            .contributing(&scene.camera, &view, &scene.settings)
            .unwrap();
        let differ: Vec<usize> = (0..cpu.len()).filter(|&g| got[g] != cpu[g]).collect();
        assert!(
            differ.is_empty(),
            "view {seed}: Gaussians {differ:?} differ"
        );

        let selection = holed_selection(&scene, seed);
        scene.settings.blend_tiles = Some(selection.clone());
        let expected = cpu_contributing_in(&scene, Some(&selection));
        let n_expected = expected.iter().filter(|&&c| c).count();
        assert!(
            n_expected > 50 && n_expected < n_cpu,
            "{n_expected} of {n_cpu}"
        );
        let got = gpu
            .contributing(&scene.camera, &scene.view(), &scene.settings)
            .unwrap();
        let differ: Vec<usize> = (0..cpu.len()).filter(|&g| got[g] != expected[g]).collect();
        assert!(
            differ.is_empty(),
            "view {seed}, tiles: Gaussians {differ:?} differ"
        );
    }
}

/// The switches' inputs are checked as on the CPU: a tile selection built for another
/// image size is an error (render and contribution pass), and an empty model has no
/// contribution flags.
#[test]
fn switch_inputs_are_checked() {
    let Some(ctx) = context(GpuOptions::default()) else {
        return;
    };
    let gpu = GpuRasterizer::new(ctx).unwrap();
    let mut scene = random_scene(33, 50, 3, false);
    let (w, h) = (
        scene.camera.intrinsics.width,
        scene.camera.intrinsics.height,
    );
    let wrong = TileSelection::from_mask(&vec![1.0; (w * 2 * h) as usize], w * 2, h, 0).unwrap();
    scene.settings.blend_tiles = Some(wrong);
    assert!(render(&scene.camera, &scene.view(), &scene.settings).is_err());
    assert!(gpu
        .render(&scene.camera, &scene.view(), &scene.settings)
        .is_err());
    assert!(gpu
        .contributing(&scene.camera, &scene.view(), &scene.settings)
        .is_err());
    scene.settings.blend_tiles = None;
    let empty = GaussianView {
        means: &[],
        log_scales: &[],
        rotations: &[],
        opacity_logits: &[],
        channels: &[],
        n_channels: 3,
    };
    let flags = gpu
        .contributing(&scene.camera, &empty, &scene.settings)
        .unwrap();
    assert!(flags.is_empty());
}

/// What the contribution flags promise the device-resident step: the blend and its
/// backward never read the channels of a Gaussian without a flag. With 1e30 in those
/// channels (any use would overflow), the image and every gradient are the same bits
/// (deterministic backward), with and without a tile selection; the flagged channels'
/// gradients are zero for the others.
#[test]
fn unflagged_channels_are_never_read() {
    let options = GpuOptions {
        deterministic: true,
        ..GpuOptions::default()
    };
    let Some(ctx) = context(options) else {
        return;
    };
    let gpu = GpuRasterizer::new(ctx).unwrap();
    let mut scene = random_scene(34, 5000, 3, false);
    for with_tiles in [false, true] {
        if with_tiles {
            scene.settings.blend_tiles = Some(holed_selection(&scene, 34));
        }
        let flags = gpu
            .contributing(&scene.camera, &scene.view(), &scene.settings)
            .unwrap();
        let hidden = flags.iter().filter(|&&f| !f).count();
        assert!(hidden > 500, "{hidden} Gaussians without a flag");
        let mut poisoned = Scene {
            channels: scene.channels.clone(),
            means: scene.means.clone(),
            log_scales: scene.log_scales.clone(),
            rotations: scene.rotations.clone(),
            opacity_logits: scene.opacity_logits.clone(),
            camera: scene.camera,
            settings: scene.settings.clone(),
            n_channels: scene.n_channels,
        };
        for (g, &f) in flags.iter().enumerate() {
            if !f {
                poisoned.channels[3 * g..3 * g + 3].fill(1e30);
            }
        }
        let (dc, da, dd) = pixel_grads(&scene, 34);
        let pg = PixelGrads {
            d_color: &dc,
            d_alpha: Some(&da),
            d_depth: Some(&dd),
        };
        let run = |s: &Scene| {
            let f = gpu.render(&s.camera, &s.view(), &s.settings).unwrap();
            let g = gpu
                .render_backward(&s.camera, &s.settings, &f, &pg)
                .unwrap();
            (f, g)
        };
        let (f0, g0) = run(&scene);
        let (f1, g1) = run(&poisoned);
        let bits = |v: &[f32]| -> Vec<u32> { v.iter().map(|x| x.to_bits()).collect() };
        assert_eq!(bits(&f0.color), bits(&f1.color), "tiles {with_tiles}");
        assert_eq!(bits(&f0.alpha), bits(&f1.alpha));
        assert_eq!(bits(&f0.depth), bits(&f1.depth));
        for (a, b) in [
            (&g0.d_means, &g1.d_means),
            (&g0.d_log_scales, &g1.d_log_scales),
            (&g0.d_rotations, &g1.d_rotations),
            (&g0.d_opacity_logits, &g1.d_opacity_logits),
            (&g0.d_channels, &g1.d_channels),
            (&g0.mean2d_grad_ndc, &g1.mean2d_grad_ndc),
        ] {
            assert_eq!(bits(a), bits(b), "tiles {with_tiles}");
        }
        for (g, &f) in flags.iter().enumerate() {
            if !f {
                assert!(g0.d_channels[3 * g..3 * g + 3].iter().all(|&v| v == 0.0));
            }
        }
    }
}

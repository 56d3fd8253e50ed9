//! The Sun-aware trainer on the wgpu backend against the CPU backend.
//!
//! The model's forward on the device (the camera pass's rasterizer and the shadow pass on
//! the GPU, the networks on the host): the image, the shadow image and the visible lists
//! against the CPU, the shadow pass through the model, and a device render refusing a
//! backward (training on the device is device-resident).
//!
//! Device-resident path (the default on wgpu, `gs_wgpu::resident_sunaware`): one step's
//! gradients (read as Adam's first moments) per group against the CPU step (a, b, d; the
//! learned-normal shading, Phi's local-frame inputs, and `colour_space = "linear"` in a,
//! b and d), short training runs of a, b, c and d (d also with the learned normal and
//! with the local inputs, c also linear) through `step_many` reaching the CPU's PSNR
//! within 0.1 dB,
//! a batch giving the same bits as single steps, a refused step changing nothing, and a
//! sort overflow redone.
//!
//! Without an adapter the tests print a skip notice, unless `GS_REQUIRE_GPU=1` (CI), where
//! a missing adapter fails. Scenes are small (about 1,000 Gaussians, 96x64 images) so that
//! Mesa's software driver runs them in seconds.

use std::sync::Arc;

use glam::Vec3;
use gs_core::engine::Backend;
use gs_core::init::from_points;
use gs_core::rng::SplitMix64;
use gs_core::sunaware::checkpoint;
use gs_core::sunaware::synthetic::{orbit_camera, sun_direction, SyntheticScene};
use gs_core::sunaware::{
    AppearanceInputs, ColourSpace, LightConfig, Observation, Shading, SunAwareConfig,
    SunAwareModel, SunAwareTrainer, Variant,
};
use gs_core::{Camera, Param};
use gs_wgpu::{context_or_skip, GpuContext, GpuOptions, GpuRasterizer, WgpuEngine};

fn gpu_backend() -> Option<Backend> {
    let ctx = context_or_skip(GpuOptions::default())?;
    Some(
        WgpuEngine::new(Arc::new(GpuRasterizer::new(ctx).unwrap()))
            .unwrap()
            .into_backend(),
    )
}

/// Camera, Sun vector, image and mask of one observation.
type View = (Camera, Vec3, Vec<f32>, Vec<f32>);

/// The synthetic plate-and-ball scene (24x24 plate + 400 ball Gaussians = 976), a model
/// of `variant` initialised from jittered surface samples, and `count` observations
/// (orbit cameras at 96x64 with Suns at varying azimuth).
fn setup(variant: Variant, count: usize) -> (SunAwareModel, Vec<View>) {
    setup_with_width(
        variant,
        count,
        SunAwareConfig::default().appearance_hidden_width,
    )
}

/// [`setup`] with Phi's hidden layers `appearance_hidden_width` wide.
fn setup_with_width(
    variant: Variant,
    count: usize,
    appearance_hidden_width: usize,
) -> (SunAwareModel, Vec<View>) {
    setup_shaded(variant, count, appearance_hidden_width, Shading::None)
}

/// [`setup_with_width`] with `shading` (the model's layout carries the learned normal
/// group under `lambert_learned`, started by the model from the Gaussians' shapes).
fn setup_shaded(
    variant: Variant,
    count: usize,
    appearance_hidden_width: usize,
    shading: Shading,
) -> (SunAwareModel, Vec<View>) {
    setup_inputs(
        variant,
        count,
        appearance_hidden_width,
        shading,
        AppearanceInputs::Paper,
    )
}

/// [`setup_shaded`] with Phi's `appearance_inputs` (the local ones need `lambert_learned`).
fn setup_inputs(
    variant: Variant,
    count: usize,
    appearance_hidden_width: usize,
    shading: Shading,
    appearance_inputs: AppearanceInputs,
) -> (SunAwareModel, Vec<View>) {
    let scene = SyntheticScene::plate_and_ball(24, 400).unwrap();
    let config = SunAwareConfig {
        light: LightConfig {
            resolution_px: 96,
            ..LightConfig::default()
        },
        appearance_hidden_width,
        shading,
        appearance_inputs,
        ..SunAwareConfig::for_variant(variant)
    };
    let (points, _, colours) = scene.surface_samples(0.02, 5);
    let init = from_points(&points, Some(&colours), config.layout()).unwrap();
    let model = SunAwareModel::new(init.model, scene.scene_box, config).unwrap();
    let obs = (0..count)
        .map(|i| {
            let camera = orbit_camera(i, count, 2.4, 0.6, 96, 64);
            let sun = sun_direction(0.3 + 0.7 * i as f32, 0.8);
            let (image, mask) = scene.render(&camera, sun).unwrap();
            (camera, sun, image, mask)
        })
        .collect();
    (model, obs)
}

/// `cpu` and `gpu` agree: every value within `1e-4 max|cpu| + 1e-3 |cpu|`, except at most
/// `allowed_off` of them, which stay within `5e-2 max|cpu|`. The same tolerance as the
/// rasterizer's own parity test (f32 atomics sum in another order; `exp` differs by an
/// ulp; a pixel where rounding moves an alpha across 1/255 changes a little more).
fn assert_close(name: &str, cpu: &[f32], gpu: &[f32], allowed_off: f64) {
    assert_eq!(cpu.len(), gpu.len(), "{name}: lengths");
    let big = cpu.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    assert!(big > 0.0, "{name}: all zero");
    let mut worst = 0.0f32;
    let mut n_off = 0usize;
    for (a, b) in cpu.iter().zip(gpu) {
        assert!(b.is_finite(), "{name}: non-finite GPU value");
        let err = (a - b).abs();
        let tol = 1e-4 * big + 1e-3 * a.abs();
        worst = worst.max(err / tol);
        if err > tol {
            n_off += 1;
            assert!(
                err <= 5e-2 * big,
                "{name}: cpu {a} gpu {b} (max |cpu| {big})"
            );
        }
    }
    eprintln!(
        "{name}: max |cpu| {big:.3e}, worst error / tolerance {worst:.3}, {n_off} of {} beyond",
        cpu.len()
    );
    assert!(
        n_off as f64 <= allowed_off * cpu.len() as f64,
        "{name}: {n_off} of {} values beyond tolerance",
        cpu.len()
    );
}

/// One configuration-d forward on both backends, with the shadow pass's `V` held at the
/// CPU's values (the GPU's `V` is compared on its own below), so the difference is the
/// rasterizer's alone; the device render refuses a backward with a clear error (the
/// device-resident step's gradients are compared in `resident_step_parity`).
#[test]
fn sunaware_forward_matches_cpu() {
    let Some(backend) = gpu_backend() else {
        return;
    };
    let (mut cpu_model, obs) = setup(Variant::D, 2);
    randomise_shapes(&mut cpu_model, 4);
    let mut gpu_model = cpu_model.clone();
    gpu_model.set_backend(&backend).unwrap();
    assert!(matches!(gpu_model.backend(), Backend::Device(_)));
    assert!(matches!(cpu_model.backend(), Backend::Cpu));
    let (camera, sun, _, _) = &obs[0];
    let settings = cpu_model.raster_settings(false);
    let vis = cpu_model.sun_visibility(camera, *sun).unwrap();
    let cpu_pass = cpu_model
        .forward_for_step(camera, *sun, 0, &settings, Some(&vis))
        .unwrap();
    let gpu_pass = gpu_model
        .forward_for_step(camera, *sun, 0, &settings, Some(&vis))
        .unwrap();
    assert_eq!(cpu_pass.visible_list, gpu_pass.visible_list);
    assert_eq!(cpu_pass.network_list, gpu_pass.network_list);
    assert!(cpu_pass.visible_list.len() > 500, "too few visible");
    assert_close("image", &cpu_pass.image, &gpu_pass.image, 1e-3);
    assert_close(
        "shadow image",
        &cpu_pass.shadow_image,
        &gpu_pass.shadow_image,
        1e-3,
    );
    let d_image = vec![0.5f32; cpu_pass.image.len()];
    cpu_model.backward(&cpu_pass, &d_image).unwrap();
    let err = gpu_model
        .backward(&gpu_pass, &d_image)
        .unwrap_err()
        .to_string();
    assert!(err.contains("device-resident"), "{err}");
}

/// `SunAwareModel::sun_visibility` on the GPU backend against the CPU: within 1e-4 for
/// all but 0.5% of the Gaussians and within 2e-2 for all (the tolerance of
/// `gpu_parity::sun_visibility_matches_cpu`; V is data to the model, never differentiated).
#[test]
fn sunaware_visibility_matches_cpu() {
    let Some(backend) = gpu_backend() else {
        return;
    };
    let (cpu_model, obs) = setup(Variant::C, 3);
    let mut gpu_model = cpu_model.clone();
    gpu_model.set_backend(&backend).unwrap();
    for (camera, sun, _, _) in &obs {
        let c = cpu_model.sun_visibility(camera, *sun).unwrap();
        let g = gpu_model.sun_visibility(camera, *sun).unwrap();
        let shadowed = c.iter().filter(|&&v| v < 0.5).count();
        assert!(
            shadowed > 0,
            "no Gaussian in shadow: the test would be weak"
        );
        let off = c
            .iter()
            .zip(&g)
            .filter(|(a, b)| (*a - *b).abs() > 1e-4)
            .count();
        let worst = c
            .iter()
            .zip(&g)
            .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
        eprintln!(
            "V: {shadowed} shadowed, {off} of {} beyond 1e-4, worst {worst:.2e}",
            c.len()
        );
        assert!(off as f64 <= 5e-3 * c.len() as f64, "{off} beyond 1e-4");
        assert!(worst <= 2e-2, "worst |dV| {worst}");
    }
}

/// A context whose backward sums are bit-identical from run to run.
fn deterministic_backend() -> Option<Backend> {
    gpu_backend()?;
    let ctx = GpuContext::with_options(GpuOptions {
        deterministic: true,
        ..GpuOptions::default()
    })
    .unwrap();
    Some(
        WgpuEngine::new(Arc::new(GpuRasterizer::new(ctx).unwrap()))
            .unwrap()
            .into_backend(),
    )
}

fn observations(obs: &[View]) -> Vec<Observation<'_>> {
    obs.iter()
        .map(|(camera, sun, image, mask)| Observation {
            camera: *camera,
            sun_dir: *sun,
            image,
            mask: Some(mask),
        })
        .collect()
}

/// Random rotations and anisotropic scales (the initial Gaussians are isotropic, whose
/// rotation gradients vanish and whose isotropic-loss gradient is a tie).
fn randomise_shapes(model: &mut SunAwareModel, seed: u64) {
    let mut rng = SplitMix64::new(seed);
    let n = model.len();
    let params = &mut model.gaussians.params;
    for i in 0..n {
        let q: Vec<f32> = (0..4).map(|_| rng.normal()).collect();
        let norm = q.iter().map(|v| v * v).sum::<f32>().sqrt();
        for (r, v) in params.row_mut(Param::Rotation, i).iter_mut().zip(&q) {
            *r = v / norm;
        }
        for s in params.row_mut(Param::LogScale, i) {
            *s += rng.uniform(-0.5, 0.5);
        }
    }
}

/// Phi's first-layer weights on the local columns `[n.s, n.v, n.h]` times `factor`. At
/// their initial size the local inputs' share of the mean gradient is below the
/// rasterizer's tolerance (a device step that left it out passed the step test); scaled
/// up, it counts.
fn amplify_local_inputs(model: &mut SunAwareModel, factor: f32) {
    let net = model.appearance.as_mut().expect("Phi");
    let (start, hidden) = (net.local_start(), net.hidden_width());
    let w0 = net.mlp.weight_range(0).start;
    for w in &mut net.mlp.params_mut()[w0 + start * hidden..w0 + (start + 3) * hidden] {
        *w *= factor;
    }
}

/// [`amplify_local_inputs`]' factor in the step and training tests.
const LOCAL_GAIN: f32 = 30.0;

/// One device-resident step against one CPU step from the same trainer. Adam's first
/// moment after a first step is `(1 - b1) g` (the same f32 product on both), so the
/// moments compare the gradients of every group and both networks, here with the
/// device's own visible list and shadow pass (`V` within 1e-4 of the CPU's for all but
/// 0.5%, see above). Tolerance: the rasterizer's gradient tolerance of
/// `sunaware_step_gradients_match_cpu`, all but 0.2% of the values (the shadow pass's
/// differences reach Psi's inputs). The loss parts agree to f32 rounding of their sums.
fn resident_step_parity(variant: Variant) {
    resident_step_parity_with(variant, 1.0, Shading::None);
}

/// [`resident_step_parity`] with a shadow gain and a shading; under `lambert_learned` the
/// Normal group's moments are compared too.
fn resident_step_parity_with(variant: Variant, shadow_gain: f32, shading: Shading) {
    resident_step_parity_inputs(variant, shadow_gain, shading, AppearanceInputs::Paper);
}

/// [`resident_step_parity_with`] with Phi's `appearance_inputs`.
fn resident_step_parity_inputs(
    variant: Variant,
    shadow_gain: f32,
    shading: Shading,
    inputs: AppearanceInputs,
) {
    resident_step_parity_space(variant, shadow_gain, shading, inputs, ColourSpace::Srgb);
}

/// [`resident_step_parity_inputs`] with the model's `colour_space`.
fn resident_step_parity_space(
    variant: Variant,
    shadow_gain: f32,
    shading: Shading,
    inputs: AppearanceInputs,
    colour_space: ColourSpace,
) {
    let Some(backend) = gpu_backend() else {
        return;
    };
    let (mut start, obs) = setup_inputs(variant, 2, 64, shading, inputs);
    randomise_shapes(&mut start, 4);
    if inputs != AppearanceInputs::Paper {
        amplify_local_inputs(&mut start, LOCAL_GAIN);
    }
    start.config.shadow_gain = shadow_gain;
    start.config.colour_space = colour_space;
    let observations = observations(&obs);
    let mut cpu = SunAwareTrainer::new(start.clone());
    let mut gpu = SunAwareTrainer::new(start);
    gpu.set_backend(&backend).unwrap();
    assert!(gpu.is_device_resident());
    let c = cpu.step(&observations[0], 0.0).unwrap();
    let g = gpu.step(&observations[0], 0.0).unwrap();
    assert!(!c.skipped && !g.skipped);
    eprintln!(
        "loss cpu {} gpu {}; l1 {} {}; ssim {} {}; iso {} {}; visible {} {}",
        c.loss, g.loss, c.l1, g.l1, c.ssim, g.ssim, c.iso, g.iso, c.visible, g.visible
    );
    for (what, a, b) in [
        ("loss", c.loss, g.loss),
        ("l1", c.l1, g.l1),
        ("ssim", c.ssim, g.ssim),
        ("iso", c.iso, g.iso),
    ] {
        assert!(
            (a - b).abs() <= 1e-4 * a.abs().max(1e-3),
            "{what}: cpu {a} gpu {b}"
        );
    }
    assert_eq!(c.visible, g.visible, "visible lists differ in size");
    // The device's network list honours the masked-tile skip, the CPU's does not (its
    // extra rows get zero gradient): at most the CPU's rows.
    eprintln!("network rows cpu {} gpu {}", c.network_rows, g.network_rows);
    assert!(g.network_rows > 0 && g.network_rows <= c.network_rows);
    assert_eq!(gpu.steps, 1);
    assert_eq!(gpu.adam.step, 1);
    let groups: &[Param] = if variant == Variant::A {
        // SH degree 0 at the first step: the higher coefficients get no gradient.
        &[
            Param::Mean,
            Param::LogScale,
            Param::Rotation,
            Param::OpacityLogit,
            Param::ShDc,
        ]
    } else if variant == Variant::B {
        &[
            Param::Mean,
            Param::LogScale,
            Param::Rotation,
            Param::OpacityLogit,
            Param::Feature,
        ]
    } else {
        &[
            Param::Mean,
            Param::LogScale,
            Param::Rotation,
            Param::OpacityLogit,
            Param::Feature,
            Param::ShadowLatent,
        ]
    };
    let mut groups = groups.to_vec();
    if shading == Shading::LambertLearned {
        groups.push(Param::Normal);
    }
    for p in groups {
        assert_close(p.name(), cpu.adam.m.get(p), gpu.adam.m.get(p), 2e-3);
    }
    if variant != Variant::A {
        assert_eq!(gpu.appearance_adam.step, 1);
        assert_close(
            "Phi moments",
            &cpu.appearance_adam.m,
            &gpu.appearance_adam.m,
            2e-3,
        );
    }
    if variant.uses_shadow() {
        assert_eq!(gpu.shadow_adam.step, 1);
        assert_close("Psi moments", &cpu.shadow_adam.m, &gpu.shadow_adam.m, 2e-3);
    }
    assert_eq!(
        cpu.densify_stats.visible_count, gpu.densify_stats.visible_count,
        "densification visibility counts"
    );
    assert_close(
        "densify grad accum",
        &cpu.densify_stats.grad_accum,
        &gpu.densify_stats.grad_accum,
        2e-3,
    );
}

#[test]
fn resident_step_d_matches_the_cpu_step() {
    resident_step_parity(Variant::D);
}

/// `shadow_gain` scales `V Psi` on the device as on the CPU (the demo's preset uses 2).
#[test]
fn resident_step_d_with_shadow_gain_2_matches_the_cpu_step() {
    resident_step_parity_with(Variant::D, 2.0, Shading::None);
}

/// The learned-normal Lambertian factor on Phi's colour (`shading = "lambert_learned"`):
/// the shaded channels, Phi's output gradient and the normal's own gradient (its Adam
/// moments) as on the CPU, with the demo's shadow gain.
#[test]
fn resident_step_d_with_lambert_learned_matches_the_cpu_step() {
    resident_step_parity_with(Variant::D, 2.0, Shading::LambertLearned);
}

#[test]
fn resident_step_b_with_lambert_learned_matches_the_cpu_step() {
    resident_step_parity_with(Variant::B, 1.0, Shading::LambertLearned);
}

/// Phi's local-frame inputs `[n.s, n.v, n.h]` (the demo's model: `lambert_learned`,
/// `appearance_inputs = "local"`, shadow gain 2): their gradient reaches the normals'
/// and the means' moments as on the CPU.
#[test]
fn resident_step_d_with_local_inputs_matches_the_cpu_step() {
    resident_step_parity_inputs(
        Variant::D,
        2.0,
        Shading::LambertLearned,
        AppearanceInputs::Local,
    );
}

/// `"local_no_sun"`: Phi sees the Sun through the local inputs only (zero Sun code).
#[test]
fn resident_step_b_with_local_no_sun_matches_the_cpu_step() {
    resident_step_parity_inputs(
        Variant::B,
        1.0,
        Shading::LambertLearned,
        AppearanceInputs::LocalNoSun,
    );
}

/// `colour_space = "linear"` (c-d): the per-pixel sRGB encoding of `RGB * S` and its
/// slope in the backward, with the demo's model (learned normal, local inputs, shadow
/// gain 2).
#[test]
fn resident_step_d_linear_matches_the_cpu_step() {
    resident_step_parity_space(
        Variant::D,
        2.0,
        Shading::LambertLearned,
        AppearanceInputs::Local,
        ColourSpace::Linear,
    );
}

/// `colour_space = "linear"` without S (a-b): the device encodes the colour buffer into
/// its own image and sends the slope-scaled gradient to the rasterizer.
#[test]
fn resident_step_b_linear_matches_the_cpu_step() {
    resident_step_parity_space(
        Variant::B,
        1.0,
        Shading::None,
        AppearanceInputs::Paper,
        ColourSpace::Linear,
    );
}

#[test]
fn resident_step_b_matches_the_cpu_step() {
    resident_step_parity(Variant::B);
}

#[test]
fn resident_step_a_matches_the_cpu_step() {
    resident_step_parity(Variant::A);
}

/// With the non-contributing skip on and the masked-tile skip off, the device's network
/// batch is the CPU's (`PreparedView::contributing`, from the device's alpha-only walk),
/// smaller than the visible list on a view where Gaussians hide each other; with the skip
/// off it is the visible list.
///
/// Up to the Gaussians at a cut: the device computes the opacity's sigmoid and the scales
/// with WGSL's `exp` (3 + 2|x| ULP) and the projection and the conic with its division
/// (2.5 ULP), where the CPU rounds correctly, so a Gaussian whose alpha lies near the
/// 1/255 cut, or a pixel whose transmittance lies near the 1e-4 stop (`1 - alpha` of these
/// nearly opaque Gaussians is 400 times more sensitive than alpha), may fall on the other
/// side. The device's count must lie between the CPU's counts with every alpha scaled by
/// `1 -/+ ALPHA_REL_ERR` (opacity logits moved by `ALPHA_REL_ERR / (1 - sigmoid)`), an
/// estimate of the device's alpha error (about 3e-5 to 6e-5 through exp, the projection
/// and the conic, doubled). The CPU's counts at 10 and 100 times that are printed beside
/// them. On lavapipe every count is the CPU's. An NVIDIA H200 counted 839 rows on the
/// second view against the CPU's 838 at `1 -/+ 1e-4` (839 at `1 - 1e-3`): it fails there,
/// and why its alpha differs by more than the estimate is open (docs/gpu.md).
#[test]
fn resident_network_rows_are_the_cpu_contributing_gaussians() {
    const ALPHA_REL_ERR: f32 = 1e-4;
    const LOGIT: f32 = 6.0;
    let Some(backend) = gpu_backend() else {
        return;
    };
    let (mut start, obs) = setup_with_width(Variant::D, 3, 32);
    start.config.skip_masked_background_tiles = false;
    // Large, nearly opaque Gaussians: the front ones stop the pixels (T < 1e-4), so the
    // ones behind are never read.
    for s in start.gaussians.params.get_mut(Param::LogScale) {
        *s += 1.0;
    }
    let logit_step = ALPHA_REL_ERR / (1.0 - 1.0 / (1.0 + (-LOGIT).exp()));
    let with_logit = |logit: f32| {
        let mut m = start.clone();
        m.gaussians.params.get_mut(Param::OpacityLogit).fill(logit);
        m
    };
    let observations = observations(&obs);
    for skip in [true, false] {
        let trainer = |logit: f32| {
            let mut model = with_logit(logit);
            model.config.skip_noncontributing_in_mlp = skip;
            SunAwareTrainer::new(model)
        };
        let mut cpu = trainer(LOGIT);
        let mut cpu_bracket = [trainer(LOGIT - logit_step), trainer(LOGIT + logit_step)];
        // Wider brackets, printed only: how far a device's alpha is from the CPU's.
        let mut wider = [10.0f32, 100.0]
            .map(|f| [-1.0f32, 1.0].map(|sign| trainer(LOGIT + sign * f * logit_step)));
        let mut gpu = trainer(LOGIT);
        gpu.set_backend(&backend).unwrap();
        for o in &observations {
            let c = cpu.step(o, 0.0).unwrap();
            let g = gpu.step(o, 0.0).unwrap();
            let bracket = cpu_bracket
                .each_mut()
                .map(|t| t.step(o, 0.0).unwrap().network_rows);
            let wider_rows = wider
                .each_mut()
                .map(|p| p.each_mut().map(|t| t.step(o, 0.0).unwrap().network_rows));
            eprintln!("CPU rows at alpha -/+ 1e-3 and 1e-2: {wider_rows:?}");
            let (lo, hi) = (
                bracket.iter().copied().fold(c.network_rows, usize::min),
                bracket.iter().copied().fold(c.network_rows, usize::max),
            );
            eprintln!(
                "skip {skip}: visible {} / {}, network rows {} / {} (CPU at alpha -/+ \
                 {ALPHA_REL_ERR:e}: {bracket:?})",
                c.visible, g.visible, c.network_rows, g.network_rows
            );
            assert_eq!(c.visible, g.visible);
            assert!(
                (lo..=hi).contains(&g.network_rows),
                "device rows {} outside the CPU's {lo}..={hi}",
                g.network_rows
            );
            if skip {
                assert!(g.network_rows < g.visible, "the skip skipped nothing");
            } else {
                assert_eq!(g.network_rows, g.visible);
            }
        }
    }
}

/// `steps` steps over 6 views on the CPU (one `step` each) and device-resident (through
/// `step_many` in batches of 12, as the component's rounds run), densification between
/// two batches on both; both scored on the CPU: within 0.1 dB.
fn resident_training_parity(variant: Variant, steps: usize) {
    resident_training_parity_with(variant, steps, Shading::None);
}

fn resident_training_parity_with(variant: Variant, steps: usize, shading: Shading) {
    resident_training_parity_inputs(variant, steps, shading, AppearanceInputs::Paper);
}

fn resident_training_parity_inputs(
    variant: Variant,
    steps: usize,
    shading: Shading,
    inputs: AppearanceInputs,
) {
    resident_training_parity_space(variant, steps, shading, inputs, ColourSpace::Srgb);
}

/// [`resident_training_parity_inputs`] with the model's `colour_space`.
fn resident_training_parity_space(
    variant: Variant,
    steps: usize,
    shading: Shading,
    inputs: AppearanceInputs,
    colour_space: ColourSpace,
) {
    let Some(backend) = gpu_backend() else {
        return;
    };
    let (mut start, obs) = setup_inputs(variant, 6, 32, shading, inputs);
    start.config.colour_space = colour_space;
    if inputs != AppearanceInputs::Paper {
        amplify_local_inputs(&mut start, LOCAL_GAIN);
    }
    // Densification between the second and third batch must change the model.
    start.config.densify_from_step = 0;
    start.config.densify.grad_threshold = 1e-5;
    let observations = observations(&obs);
    let score = |model: &SunAwareModel| -> f32 {
        let mut m = model.clone();
        m.set_backend(&Backend::Cpu).unwrap();
        let total: f32 = observations
            .iter()
            .map(|o| m.evaluate(o, true).unwrap().psnr_db)
            .sum();
        total / observations.len() as f32
    };
    let batches: Vec<Vec<(Observation, f32)>> = (0..steps)
        .map(|s| {
            (
                observations[s % observations.len()],
                s as f32 / steps as f32,
            )
        })
        .collect::<Vec<_>>()
        .chunks(12)
        .map(<[(Observation<'_>, f32)]>::to_vec)
        .collect();
    let run = |backend: &Backend| -> (SunAwareTrainer, f64) {
        let mut trainer = SunAwareTrainer::new(start.clone());
        trainer.set_backend(backend).unwrap();
        let t = std::time::Instant::now();
        for (b, batch) in batches.iter().enumerate() {
            let stats = trainer.step_many(batch).unwrap();
            assert_eq!(stats.len(), batch.len());
            assert!(
                stats.iter().all(|s| !s.skipped),
                "batch {b}: a step skipped"
            );
            if b == 1 {
                let report = trainer.densify_and_prune().unwrap();
                assert!(
                    report.cloned + report.split > 0,
                    "densification added nothing"
                );
            }
        }
        (trainer, t.elapsed().as_secs_f64())
    };
    let (cpu, cpu_s) = run(&Backend::Cpu);
    let (gpu, gpu_s) = run(&backend);
    assert!(gpu.is_device_resident());
    assert_eq!(gpu.skipped_nonfinite, 0);
    assert_eq!(gpu.steps, steps as u64);
    let (p0, pc, pg) = (score(&start), score(&cpu.model), score(&gpu.model));
    eprintln!(
        "resident configuration {variant}, shading {shading}, inputs {inputs}, colour space \
         {colour_space}: {steps} steps, PSNR start {p0:.3} dB, cpu \
         {pc:.3} dB ({cpu_s:.1} s), wgpu resident {pg:.3} dB ({gpu_s:.1} s; software \
         driver), Gaussians cpu {} wgpu {}",
        cpu.model.len(),
        gpu.model.len()
    );
    assert!(pc > p0 + 1.0, "the run did not learn: {p0} -> {pc}");
    assert!((pc - pg).abs() <= 0.1, "cpu {pc} dB vs wgpu {pg} dB");
}

#[test]
fn resident_training_d_reaches_the_same_psnr() {
    resident_training_parity(Variant::D, 48);
}

/// Learned normals through batches, Adam at their own rate and densification (which
/// copies the normal group) on the device as on the CPU.
#[test]
fn resident_training_d_with_lambert_learned_reaches_the_same_psnr() {
    resident_training_parity_with(Variant::D, 48, Shading::LambertLearned);
}

/// The demo's model (local-frame inputs on the learned normal) through batches and
/// densification on the device as on the CPU.
#[test]
fn resident_training_d_with_local_inputs_reaches_the_same_psnr() {
    resident_training_parity_inputs(
        Variant::D,
        36,
        Shading::LambertLearned,
        AppearanceInputs::Local,
    );
}

/// `colour_space = "linear"` through batches and densification. 72 steps: the linear
/// model starts nearer the targets (14.6 dB; configuration c in sRGB 10.6 dB), and 48
/// steps gained 0.98 dB, under the 1 dB that shows a run learned.
#[test]
fn resident_training_d_linear_reaches_the_same_psnr() {
    resident_training_parity_space(
        Variant::D,
        72,
        Shading::None,
        AppearanceInputs::Paper,
        ColourSpace::Linear,
    );
}

#[test]
fn resident_training_c_reaches_the_same_psnr() {
    resident_training_parity(Variant::C, 36);
}

#[test]
fn resident_training_b_reaches_the_same_psnr() {
    resident_training_parity(Variant::B, 36);
}

#[test]
fn resident_training_a_reaches_the_same_psnr() {
    resident_training_parity(Variant::A, 36);
}

/// A batch of steps gives the same bits as the same steps one at a time (each a batch of
/// one: upload, step, download): the host round trip loses nothing. Configuration d on a
/// deterministic context (the light pass sums in fixed point, so it is bit-stable too).
#[test]
fn a_resident_batch_gives_the_same_bits_as_single_steps() {
    let Some(backend) = deterministic_backend() else {
        return;
    };
    let (start, obs) = setup_with_width(Variant::D, 4, 32);
    let observations = observations(&obs);
    let batch: Vec<(Observation, f32)> = (0..8)
        .map(|s| (observations[s % 4], s as f32 / 8.0))
        .collect();
    let mut whole = SunAwareTrainer::new(start.clone());
    whole.set_backend(&backend).unwrap();
    let mut single = whole.clone();
    let a = whole.step_many(&batch).unwrap();
    let b: Vec<_> = batch
        .iter()
        .map(|(o, p)| single.step(o, *p).unwrap())
        .collect();
    for (x, y) in a.iter().zip(&b) {
        assert_eq!(x.loss.to_bits(), y.loss.to_bits(), "losses differ");
    }
    assert!(whole == single, "batched and single-step trainers differ");
    assert!(whole.model != start, "nothing trained");
}

/// A NaN feature makes Phi's input non-finite: the device refuses the step, counts it and
/// changes nothing (bit for bit); the CPU step rejects the same trainer with an error.
#[test]
fn a_refused_resident_step_changes_nothing() {
    let Some(backend) = gpu_backend() else {
        return;
    };
    let (mut start, obs) = setup_with_width(Variant::D, 1, 32);
    start.gaussians.params.get_mut(Param::Feature)[5] = f32::NAN;
    let observations = observations(&obs);
    let mut cpu = SunAwareTrainer::new(start.clone());
    assert!(cpu.step(&observations[0], 0.0).is_err());
    let mut gpu = SunAwareTrainer::new(start);
    gpu.set_backend(&backend).unwrap();
    let before = checkpoint::to_bytes(&gpu);
    let stats = gpu.step(&observations[0], 0.0).unwrap();
    assert!(stats.skipped);
    assert_eq!(gpu.skipped_nonfinite, 1);
    assert_eq!(gpu.steps, 0);
    gpu.skipped_nonfinite = 0;
    assert_eq!(
        checkpoint::to_bytes(&gpu),
        before,
        "a refused step changed the state"
    );
}

/// A far view sizes the sorts; a near view then outgrows them: the device refuses the
/// step, and it is redone at the exact counts. With all rates 0 nothing moves, so the
/// near step after the far one gives the loss of a near step on a fresh trainer, bit for
/// bit (deterministic context, configuration b).
#[test]
fn a_resident_sort_overflow_is_redone() {
    let Some(backend) = deterministic_backend() else {
        return;
    };
    let (mut start, obs) = setup_with_width(Variant::B, 1, 32);
    let lr = &mut start.config.lr;
    (lr.position_init, lr.position_final) = (0.0, 0.0);
    (lr.sh_dc, lr.sh_rest, lr.opacity, lr.scale) = (0.0, 0.0, 0.0, 0.0);
    (lr.rotation, lr.feature, lr.shadow_latent) = (0.0, 0.0, 0.0);
    (lr.appearance_mlp, lr.shadow_mlp) = (0.0, 0.0);
    let sun = obs[0].1;
    // 300x200 px (247 tiles): from far every Gaussian touches one tile, from near many.
    let (width, height) = (300, 200);
    let far = orbit_camera(0, 1, 20.0, 0.6, width, height);
    let near = orbit_camera(0, 1, 1.2, 0.6, width, height);
    let image = vec![0.5f32; (width * height * 3) as usize];
    let view = |camera: Camera| Observation {
        camera,
        sun_dir: sun,
        image: &image,
        mask: None,
    };
    let mut a = SunAwareTrainer::new(start.clone());
    a.set_backend(&backend).unwrap();
    let mut b = a.clone();
    let far_stats = a.step(&view(far), 0.0).unwrap();
    let a_near = a.step(&view(near), 0.0).unwrap();
    let b_near = b.step(&view(near), 0.0).unwrap();
    eprintln!(
        "far: {} visible; near: {} visible, loss {} (after far) vs {} (fresh)",
        far_stats.visible, a_near.visible, a_near.loss, b_near.loss
    );
    assert!(!a_near.skipped && !b_near.skipped);
    assert_eq!(far_stats.device_sort_retries, 0);
    assert_eq!(
        a_near.device_sort_retries, 1,
        "the near step did not outgrow the sort"
    );
    assert_eq!(b_near.device_sort_retries, 0);
    assert_eq!(a_near.loss.to_bits(), b_near.loss.to_bits());
    assert_eq!(a_near.visible, b_near.visible);
}

#[test]
fn learned_normal_and_local_inputs_are_supported_and_lambert_refused_by_name() {
    let Some(backend) = gpu_backend() else {
        return;
    };
    let (mut model, _) = setup(Variant::D, 1);
    model.config.shadow_gain = 2.0;
    model.set_backend(&backend).unwrap();
    // The learned normal runs on the device; the shortest-axis normal is CPU-only, and
    // the refusal names the setting and its value.
    let (mut learned, _) = setup_shaded(Variant::B, 1, 32, Shading::LambertLearned);
    learned.set_backend(&backend).unwrap();
    let (mut shaded, _) = setup(Variant::B, 1);
    shaded.config.shading = Shading::Lambert;
    let err = shaded.set_backend(&backend).unwrap_err().to_string();
    assert!(
        err.contains("shading") && err.contains("\"lambert\""),
        "{err}"
    );
    assert!(matches!(shaded.backend(), Backend::Cpu));
    // Phi's local-frame inputs run on the device.
    for inputs in [AppearanceInputs::Local, AppearanceInputs::LocalNoSun] {
        let (mut local, _) = setup_inputs(Variant::B, 1, 32, Shading::LambertLearned, inputs);
        local.set_backend(&backend).unwrap();
        assert!(!matches!(local.backend(), Backend::Cpu), "{inputs}");
    }
}

//! The kernels of the device-resident Sun-aware step against the CPU: the Gaussians' Adam
//! kernel alone against `optim.rs` on random inputs (through `gs_wgpu::GpuAdam`, the
//! step's optimiser kernels run from the host), the loss kernels against `gs_core::loss`,
//! and a sort overflow redone without applying anything (configuration (a) through
//! `SunAwareResident`). The resident step as a whole is compared step for step and run
//! for run in `gpu_sunaware.rs`.
//!
//! Without an adapter the tests print a skip notice, unless `GS_REQUIRE_GPU=1` (CI), where
//! a missing adapter fails. Scenes are small (a few hundred Gaussians, 64x64 images) so the
//! file runs in seconds on Mesa's software driver.

use std::sync::Arc;

use glam::Vec3;
use gs_core::densify::DensifyStats;
use gs_core::init::random_in_sphere;
use gs_core::optim::Adam;
use gs_core::rng::SplitMix64;
use gs_core::{Camera, Intrinsics, ModelLayout, Param, ParamSet};
use gs_wgpu::{context_or_skip, GpuAdam, GpuContext, GpuOptions, GpuRasterizer};

/// A rasterizer, or None (with a notice) when there is no adapter and GS_REQUIRE_GPU is
/// not 1.
fn gpu() -> Option<Arc<GpuRasterizer>> {
    gpu_with(GpuOptions::default())
}

/// [`gpu`] with the given options.
fn gpu_with(options: GpuOptions) -> Option<Arc<GpuRasterizer>> {
    let ctx = context_or_skip(options)?;
    Some(Arc::new(GpuRasterizer::new(ctx).unwrap()))
}

/// Random values spanning magnitudes 1e-20 to 1e3, both signs.
fn random_set(dims_of: ModelLayout, n: usize, rng: &mut SplitMix64, scale: f32) -> ParamSet {
    let mut set = ParamSet::new(dims_of.dims());
    set.push_zeros(n);
    for p in Param::ALL {
        for v in set.get_mut(p) {
            let magnitude = 10f32.powf(rng.uniform(-20.0, 3.0));
            *v = scale * magnitude * if rng.next_f32() < 0.5 { -1.0 } else { 1.0 };
        }
    }
    set
}

/// The Adam kernel against `optim::Adam::step` for three steps on random parameters and
/// gradients (every group, including the feature, latent and learned-normal groups, one
/// frozen group).
///
/// Tolerance (f32 rounding, WGSL's accuracy rules, section 15.7.4.1): per step the kernel
/// computes the same operations in the same order, `dx = (s m) / (sqrt(v) c + eps)`. The
/// CPU rounds each correctly (5 x 0.5 eps of `dx`, eps = f32::EPSILON); the device may
/// fuse `a * b + c` and its `sqrt` (inherited from `1.0 / inverseSqrt`) and division are
/// within 4.5 and 2.5 ULP (8.5 eps; lavapipe rounds both correctly, an H200 does not):
/// 11 eps of `|dx|` from the step's own operations. The moments' bounds below,
/// `|m_gpu - m_cpu| <= 8 eps (|m| + 0.1 sum|g|)` and `|v_gpu - v_cpu| <= 8 eps (|v| +
/// 0.001 sum g^2)` (the updates `b m + (1 - b) g` fused or not), move `dx` by their
/// relative size (`dx` is proportional to `m`) and by half of `v`'s. Each side rounds
/// `x - dx` once (1 eps of `|x|`). `|x_gpu - x_cpu|` is bounded by the sum of these over
/// the steps, with each step's `m`, `v`, sums and change `dx` (the CPU's). Frozen
/// groups and refused steps are compared bit for bit.
#[test]
fn adam_kernel_matches_optim_rs() {
    let Some(gpu) = gpu() else {
        return;
    };
    let layout = ModelLayout {
        sh_degree: 1,
        feature_dim: 2,
        shadow_latent_dim: 1,
        // The learned shading normal: the ninth group, at its own rate.
        normal_dim: 3,
    };
    let n = 700;
    let mut rng = SplitMix64::new(21);
    let mut params = random_set(layout, n, &mut rng, 1.0);
    let mut adam = Adam::new(&params);
    let kernels = GpuAdam::new(gpu.context()).unwrap();
    // The device's state, carried from step to step through the host (exact copies).
    let (mut got, mut got_adam) = (params.clone(), adam.clone());
    let mut rates = [0.0f32; Param::COUNT];
    for (k, r) in rates.iter_mut().enumerate() {
        *r = 10f32.powf(-1.0 - k as f32 * 0.5);
    }
    rates[Param::ShRest.index()] = 0.0;
    let eps = f32::EPSILON;
    let mut tol_x = params.zeros_like();
    let mut sum_g = params.zeros_like();
    let mut sum_g2 = params.zeros_like();
    for _ in 0..3 {
        let grads = random_set(layout, n, &mut rng, 1e-2);
        let before = params.clone();
        adam.step(&mut params, &grads, &rates).unwrap();
        assert!(kernels
            .step(&mut got, &mut got_adam, &grads, &rates)
            .unwrap());
        for p in Param::ALL {
            for i in 0..params.get(p).len() {
                let g = grads.get(p)[i];
                sum_g.get_mut(p)[i] += g.abs();
                sum_g2.get_mut(p)[i] += g * g;
                // This step's share of x's bound (see the doc comment): its rounding of
                // x - dx, and dx's relative error from its own operations and from the
                // moments' bounds at this step (dx is m / (sqrt(v) c + eps)).
                let (x, dx) = (params.get(p)[i], params.get(p)[i] - before.get(p)[i]);
                let (m, v) = (adam.m.get(p)[i].abs(), adam.v.get(p)[i].abs());
                let mut share = eps * x.abs();
                if dx != 0.0 {
                    let m_rel = 8.0 * eps * (1.0 + 0.1 * sum_g.get(p)[i] / m);
                    let v_rel =
                        8.0 * eps * (1.0 + 0.001 * sum_g2.get(p)[i] / v.max(f32::MIN_POSITIVE));
                    share += dx.abs() * (11.0 * eps + m_rel + v_rel / 2.0);
                }
                tol_x.get_mut(p)[i] += share;
            }
        }
    }
    assert_eq!(got_adam.step, 3);
    let mut worst = 0.0f32;
    for p in Param::ALL {
        let frozen = rates[p.index()] == 0.0;
        for i in 0..params.get(p).len() {
            let (x, m, v) = (params.get(p)[i], adam.m.get(p)[i], adam.v.get(p)[i]);
            let (gx, gm, gv) = (got.get(p)[i], got_adam.m.get(p)[i], got_adam.v.get(p)[i]);
            if frozen {
                assert_eq!(
                    (gx.to_bits(), gm.to_bits(), gv.to_bits()),
                    (x.to_bits(), m.to_bits(), v.to_bits()),
                    "frozen group {} changed at {i}",
                    p.name()
                );
                continue;
            }
            let tol_x = tol_x.get(p)[i];
            let tol_m = 8.0 * eps * (m.abs() + 0.1 * sum_g.get(p)[i]);
            let tol_v = 8.0 * eps * (v.abs() + 0.001 * sum_g2.get(p)[i]);
            assert!(
                (gx - x).abs() <= tol_x,
                "{} x[{i}]: gpu {gx} cpu {x}",
                p.name()
            );
            assert!(
                (gm - m).abs() <= tol_m,
                "{} m[{i}]: gpu {gm} cpu {m}",
                p.name()
            );
            assert!(
                (gv - v).abs() <= tol_v,
                "{} v[{i}]: gpu {gv} cpu {v}",
                p.name()
            );
            if tol_x > 0.0 {
                worst = worst.max((gx - x).abs() / tol_x);
            }
        }
    }
    eprintln!("worst parameter error / tolerance: {worst:.3}");

    // A non-finite gradient refuses the step: nothing changes on the device.
    let mut bad = random_set(layout, n, &mut rng, 1e-2);
    bad.get_mut(Param::Rotation)[17] = f32::NAN;
    let (mut again, mut again_adam) = (got.clone(), got_adam.clone());
    assert!(!kernels
        .step(&mut again, &mut again_adam, &bad, &rates)
        .unwrap());
    assert_eq!(again, got);
    assert_eq!(again_adam, got_adam);
}

/// The loss kernels against loss.rs `photometric_loss` on random 37x29 and 130x70 images (values in
/// [0, 1], a quarter of them equal to the target so the L1 sign's zero is exercised), with
/// and without a soft mask, at lambda 0.2 and 1.
///
/// Tolerance: SSIM sums over up to 121 taps twice and the totals over every pixel in
/// another order; in f32 that is ~1e-6 relative on the totals (asserted: `1e-5` of the
/// value plus `1e-6`) and on each gradient value `1e-3 |g| + 1e-4 max|g|` (the SSIM
/// derivative's terms cancel, so the relative error of small values is larger).
#[test]
fn loss_kernels_match_the_cpu_loss() {
    use gs_core::loss::ImageShape;
    use gs_wgpu::GpuLoss;
    let Some(gpu) = gpu() else {
        return;
    };
    let ctx = gpu.context();
    let kernels = GpuLoss::new(ctx, 3).unwrap();
    // 130x70 spans three chunks of the totals' first stage (4,096 pixels each).
    for (width, height) in [(37, 29), (130, 70)] {
        check_loss_kernels(&kernels, ctx, ImageShape::new(width, height, 3));
    }
    let shape = ImageShape::new(37, 29, 3);
    let mut rng = SplitMix64::new(12);
    let target: Vec<f32> = (0..shape.values()).map(|_| rng.next_f32()).collect();
    // A non-finite render is refused, as the trainer refuses it on the CPU.
    let mut bad = target.clone();
    bad[40] = f32::INFINITY;
    assert!(kernels
        .evaluate(ctx, &bad, &target, None, shape, 0.2)
        .unwrap()
        .is_none());
}

/// One shape of [`loss_kernels_match_the_cpu_loss`]: three mask/lambda cases.
fn check_loss_kernels(
    kernels: &gs_wgpu::GpuLoss,
    ctx: &GpuContext,
    shape: gs_core::loss::ImageShape,
) {
    use gs_core::loss::photometric_loss;
    let mut rng = SplitMix64::new(12);
    let target: Vec<f32> = (0..shape.values()).map(|_| rng.next_f32()).collect();
    let rendered: Vec<f32> = target
        .iter()
        .map(|&t| {
            if rng.next_f32() < 0.25 {
                t
            } else {
                rng.next_f32()
            }
        })
        .collect();
    let mask: Vec<f32> = (0..shape.pixels())
        .map(|_| (rng.next_f32() * 1.5).min(1.0))
        .collect();
    for (mask, lambda) in [(None, 0.2), (Some(&mask[..]), 0.2), (Some(&mask[..]), 1.0)] {
        let cpu = photometric_loss(&rendered, &target, mask, shape, lambda).unwrap();
        let got = kernels
            .evaluate(ctx, &rendered, &target, mask, shape, lambda)
            .unwrap()
            .expect("finite");
        for (what, a, b) in [
            ("loss", cpu.loss, got.loss),
            ("l1", cpu.l1, got.l1),
            ("ssim", cpu.ssim, got.ssim),
        ] {
            assert!(
                (a - b).abs() <= 1e-5 * a.abs() + 1e-6,
                "{what}: cpu {a} gpu {b} (mask {}, lambda {lambda}, {shape:?})",
                mask.is_some()
            );
        }
        let max_g = cpu.d_rendered.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        for (i, (a, b)) in cpu.d_rendered.iter().zip(&got.d_rendered).enumerate() {
            assert!(
                (a - b).abs() <= 1e-3 * a.abs() + 1e-4 * max_g,
                "d_rendered[{i}]: cpu {a} gpu {b} (mask {}, lambda {lambda}, {shape:?})",
                mask.is_some()
            );
        }
    }
}

/// The resident step sizes its sort from the recent steps' entry counts (no mid-step
/// readback). A view with many more (tile, Gaussian) pairs than the last overflows that
/// capacity: the attempt must change nothing and be redone. Configuration (a) (SH colour
/// on the device, no networks). Model A steps on a far view with all learning
/// rates 0 (its parameters stay the start's; its statistics are then reset to the start's,
/// so both models meet the near view in the same state) and then on a near one
/// (overflow, redone); model B steps on the near view first (sized at its first step). The
/// forward is deterministic, so both near steps must give the same loss bits, entry count,
/// visibility counts and radii, and A must have counted two Adam steps, not three.
#[test]
fn a_sort_overflow_is_redone_without_applying_anything() {
    use gs_core::nn::SceneBox;
    use gs_core::sunaware::trainer::FlatAdam;
    use gs_core::sunaware::{SunAwareConfig, SunAwareModel, Variant};
    use gs_wgpu::resident_sunaware::{SunAwareResident, SunAwareStepInput, SunAwareStepReport};
    use gs_wgpu::{GpuMlp, GpuSunVisibility};
    let Some(gpu) = gpu() else {
        return;
    };
    let config = SunAwareConfig {
        sh_degree: 0,
        background: [0.0; 3],
        lambda_dssim: 0.2,
        ..SunAwareConfig::for_variant(Variant::A)
    };
    let gaussians = random_in_sphere(400, Vec3::ZERO, 1.0, config.layout(), 5)
        .unwrap()
        .model;
    let scene_box = SceneBox::new([-1.5; 3], [1.5; 3]).unwrap();
    let start = SunAwareModel::new(gaussians, scene_box, config).unwrap();
    let params = &start.gaussians.params;
    let k = Intrinsics::from_fov_x(45f32.to_radians(), 128, 128);
    let far = Camera::look_at(k, Vec3::new(12.0, 0.0, 0.0), Vec3::ZERO, Vec3::Z);
    let near = Camera::look_at(k, Vec3::new(2.5, 0.0, 0.0), Vec3::ZERO, Vec3::Z);
    let target = vec![0.3f32; 128 * 128 * 3];
    let frozen = [0.0f32; Param::COUNT];
    let mut rates = [0.0f32; Param::COUNT];
    rates[Param::OpacityLogit.index()] = 0.025;
    rates[Param::ShDc.index()] = 2.5e-3;
    let adam = Adam::new(params);
    let stats = DensifyStats::new(start.gaussians.len());
    let no_network = FlatAdam::new(0);
    let ctx = gpu.context().clone();
    let shadow = Arc::new(GpuSunVisibility::new(gpu.clone()).unwrap());
    let networks = Arc::new(GpuMlp::new(ctx).unwrap());
    let new_model = || {
        let mut m = SunAwareResident::new(gpu.clone(), shadow.clone(), networks.clone()).unwrap();
        m.upload(&start, &adam, &no_network, &no_network, &stats)
            .unwrap();
        m
    };
    let step = |m: &mut SunAwareResident, camera: &Camera, rates: &[f32; Param::COUNT]| {
        m.step(
            &start,
            &SunAwareStepInput {
                camera,
                sun_dir: Vec3::Z,
                target: &target,
                mask: None,
                rates,
                sh_degree: 0,
                appearance_lr: 0.0,
                shadow_lr: 0.0,
            },
        )
        .unwrap()
    };
    let download = |m: &SunAwareResident| {
        let mut model = start.clone();
        let mut adam = Adam::new(params);
        let mut stats = DensifyStats::new(start.gaussians.len());
        let (mut phi, mut psi) = (FlatAdam::new(0), FlatAdam::new(0));
        m.download(&mut model, &mut adam, &mut phi, &mut psi, &mut stats)
            .unwrap();
        (model, adam, stats)
    };
    let (mut a, mut b) = (new_model(), new_model());
    let a_far: SunAwareStepReport = step(&mut a, &far, &frozen);
    let (after_far, adam_far, _) = download(&a);
    assert!(
        after_far == start,
        "a step with all rates 0 moved the model"
    );
    a.upload(&after_far, &adam_far, &no_network, &no_network, &stats)
        .unwrap();
    let a_near = step(&mut a, &near, &rates);
    let b_near = step(&mut b, &near, &rates);
    eprintln!(
        "tile entries: far {}, near {}",
        a_far.tile_entries, a_near.tile_entries
    );
    assert_eq!(a_far.sort_retries, 0);
    assert_eq!(a_near.sort_retries, 1, "the near view did not overflow");
    assert_eq!(b_near.sort_retries, 0);
    for r in [&a_far, &a_near, &b_near] {
        assert!(!r.refused, "{r:?}");
    }
    assert_eq!(a_near.tile_entries, b_near.tile_entries);
    assert_eq!(a_near.loss.to_bits(), b_near.loss.to_bits());
    let ((_, adam_a, stats_a), (_, adam_b, stats_b)) = (download(&a), download(&b));
    assert_eq!(
        (adam_a.step, adam_b.step),
        (2, 1),
        "an overflowed attempt was applied"
    );
    assert_eq!(stats_a.visible_count, stats_b.visible_count);
    assert_eq!(stats_a.max_radius_px, stats_b.max_radius_px);
    assert!(stats_a.visible_count.contains(&1));
}

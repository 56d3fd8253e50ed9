//! Unit tests of the Sun-aware model's forward and backward: buffer reuse, recomputed
//! activations and the skip of non-contributing Gaussians change no image and no
//! gradient beyond float summation order.

use super::*;
use crate::init::from_points;
use crate::sunaware::config::{LightConfig, Variant};
use crate::sunaware::synthetic::sun_direction;
use crate::Intrinsics;

/// A configuration-(d) model of `n` fairly opaque Gaussians filling a box, so the
/// front ones hide many behind them.
fn dense_model(n: usize, skip: bool) -> SunAwareModel {
    let config = SunAwareConfig {
        light: LightConfig {
            resolution_px: 48,
            ..LightConfig::default()
        },
        skip_noncontributing_in_mlp: skip,
        ..SunAwareConfig::for_variant(Variant::D)
    };
    let mut rng = SplitMix64::new(21);
    let points: Vec<Vec3> = (0..n)
        .map(|_| {
            Vec3::new(
                rng.uniform(-0.6, 0.6),
                rng.uniform(-0.4, 0.4),
                rng.uniform(-0.4, 0.4),
            )
        })
        .collect();
    let mut init = from_points(&points, None, config.layout()).unwrap().model;
    init.params.get_mut(Param::OpacityLogit).fill(2.5);
    let scene_box = SceneBox::new([-0.6, -0.4, -0.4], [0.6, 0.4, 0.4]).unwrap();
    SunAwareModel::new(init, scene_box, config).unwrap()
}

fn camera() -> Camera {
    Camera::look_at(
        Intrinsics::from_fov_x(0.8, 64, 48),
        Vec3::new(1.2, -2.2, 0.9),
        Vec3::ZERO,
        Vec3::Z,
    )
}

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

/// `a` and `b` agree to float summation-order noise: every difference within 1e-5 of
/// the largest magnitude of the group (f32 sums of a few thousand terms reassociated).
fn assert_close(what: &str, a: &[f32], b: &[f32]) {
    assert_eq!(a.len(), b.len(), "{what}");
    let scale = a.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    assert!(scale > 0.0, "{what} is all zeros: nothing compared");
    for (i, (x, y)) in a.iter().zip(b).enumerate() {
        assert!(
            (x - y).abs() <= 1e-5 * scale,
            "{what}[{i}]: {x} vs {y} (scale {scale})"
        );
    }
}

fn camera_sized(width: u32, height: u32, eye: Vec3) -> Camera {
    Camera::look_at(
        Intrinsics::from_fov_x(0.8, width, height),
        eye,
        Vec3::ZERO,
        Vec3::Z,
    )
}

#[test]
fn reused_step_buffers_give_the_same_bits_as_fresh_ones() {
    for recompute in [false, true] {
        let mut warm = dense_model(700, true);
        warm.config.mlp_recompute_activations = recompute;
        warm.config.reuse_step_buffers = true;
        let settings = warm.raster_settings(false);
        // Large, small, large again (leftovers of a bigger call sit in the buffers),
        // and different views, so the network batches change size too.
        let views = [
            (80, 60, Vec3::new(1.2, -2.2, 0.9)),
            (24, 20, Vec3::new(-2.0, 0.5, 1.5)),
            (64, 48, Vec3::new(0.3, 2.4, -0.8)),
            (80, 60, Vec3::new(2.5, 0.2, 0.1)),
        ];
        for (i, &(w, h, eye)) in views.iter().enumerate() {
            let cam = camera_sized(w, h, eye);
            let sun = sun_direction(0.3 + i as f32, 0.4);
            // A clone starts with empty buffers: the fresh reference.
            let fresh = warm.clone();
            let a = warm
                .forward_for_step(&cam, sun, 0, &settings, None)
                .unwrap();
            let b = fresh
                .forward_for_step(&cam, sun, 0, &settings, None)
                .unwrap();
            assert_eq!(bits(&a.image), bits(&b.image), "view {i}");
            assert_eq!(a.network_list, b.network_list);
            let d_image: Vec<f32> = (0..a.image.len())
                .map(|k| ((k * 31 + i) % 7) as f32 / 7.0 - 0.4)
                .collect();
            let ga = warm.backward(&a, &d_image).unwrap();
            let gb = fresh.backward(&b, &d_image).unwrap();
            for p in Param::ALL {
                assert_eq!(
                    bits(ga.params.get(p)),
                    bits(gb.params.get(p)),
                    "{}",
                    p.name()
                );
            }
            assert_eq!(bits(&ga.appearance), bits(&gb.appearance));
            assert_eq!(bits(&ga.shadow), bits(&gb.shadow));
            warm.recycle(a);
        }
    }
}

#[test]
fn recomputed_network_activations_give_the_same_gradient_bits() {
    let cached = dense_model(500, true);
    let mut recompute = cached.clone();
    recompute.config.mlp_recompute_activations = true;
    let settings = cached.raster_settings(false);
    let sun = sun_direction(1.1, 0.6);
    let a = cached.forward(&camera(), sun, 0, &settings, None).unwrap();
    let b = recompute
        .forward(&camera(), sun, 0, &settings, None)
        .unwrap();
    assert_eq!(bits(&a.image), bits(&b.image));
    // Recompute keeps no hidden activations.
    let tape = |p: &FramePass| {
        p.phi.as_ref().unwrap().forward.tape_len() + p.psi.as_ref().unwrap().tape_len()
    };
    assert!(tape(&a) > 0);
    assert_eq!(tape(&b), 0);
    let d_image: Vec<f32> = (0..a.image.len())
        .map(|i| ((i * 104729) % 11) as f32 / 11.0 - 0.5)
        .collect();
    let ga = cached.backward(&a, &d_image).unwrap();
    let gb = recompute.backward(&b, &d_image).unwrap();
    for p in Param::ALL {
        assert_eq!(
            bits(ga.params.get(p)),
            bits(gb.params.get(p)),
            "{}",
            p.name()
        );
    }
    assert_eq!(bits(&ga.appearance), bits(&gb.appearance));
    assert_eq!(bits(&ga.shadow), bits(&gb.shadow));
    assert!(ga.appearance.iter().any(|&v| v != 0.0));
}

#[test]
fn skipping_non_contributing_gaussians_changes_no_image_and_no_gradient() {
    let full = dense_model(1200, false);
    let skip = dense_model(1200, true);
    assert_eq!(full.gaussians, skip.gaussians);
    let settings = full.raster_settings(false);
    let sun = sun_direction(0.7, 0.5);
    let a = full
        .forward_for_step(&camera(), sun, 0, &settings, None)
        .unwrap();
    let b = skip
        .forward_for_step(&camera(), sun, 0, &settings, None)
        .unwrap();
    // The plain forward never skips: complete per-Gaussian outputs.
    let plain = skip.forward(&camera(), sun, 0, &settings, None).unwrap();
    assert_eq!(plain.network_list, plain.visible_list);
    assert_eq!(bits(&plain.image), bits(&b.image));
    assert_eq!(a.visible_list, b.visible_list);
    assert_eq!(a.network_list, a.visible_list);
    // The skip must actually drop rows here, or this test shows nothing.
    assert!(
        b.network_list.len() + 100 < a.network_list.len(),
        "{} of {} rows kept",
        b.network_list.len(),
        a.network_list.len()
    );
    assert!(b.network_list.len() > 100);
    assert_eq!(bits(&a.image), bits(&b.image));
    assert_eq!(bits(&a.rgb), bits(&b.rgb));
    assert_eq!(bits(&a.shadow_image), bits(&b.shadow_image));
    assert_eq!(bits(&a.alpha), bits(&b.alpha));
    for &g in &b.network_list {
        let g = g as usize;
        assert_eq!(
            a.refined_visibility[g].to_bits(),
            b.refined_visibility[g].to_bits()
        );
    }

    let d_image: Vec<f32> = (0..a.image.len())
        .map(|i| ((i * 7919) % 17) as f32 / 17.0 - 0.45)
        .collect();
    let ga = full.backward(&a, &d_image).unwrap();
    let gb = skip.backward(&b, &d_image).unwrap();
    // Rasterizer-only groups: the same bits.
    for p in [Param::LogScale, Param::Rotation, Param::OpacityLogit] {
        assert_eq!(
            bits(ga.params.get(p)),
            bits(gb.params.get(p)),
            "{}",
            p.name()
        );
    }
    assert_eq!(bits(&ga.mean2d_grad_ndc), bits(&gb.mean2d_grad_ndc));
    // Through the networks: batches of different sizes sum in a different order.
    for p in [Param::Mean, Param::Feature, Param::ShadowLatent] {
        assert_close(p.name(), ga.params.get(p), gb.params.get(p));
    }
    assert_close("Phi weights", &ga.appearance, &gb.appearance);
    assert_close("Psi weights", &ga.shadow, &gb.shadow);
    // Skipped Gaussians get exactly nothing through the networks.
    let kept: std::collections::HashSet<u32> = b.network_list.iter().copied().collect();
    for &g in a.visible_list.iter().filter(|g| !kept.contains(g)) {
        let g = g as usize;
        let f = &gb.params.get(Param::Feature)[72 * g..72 * g + 72];
        assert!(f.iter().all(|&v| v == 0.0));
        assert!(ga.params.get(Param::Feature)[72 * g..72 * g + 72]
            .iter()
            .all(|&v| v == 0.0));
    }
}

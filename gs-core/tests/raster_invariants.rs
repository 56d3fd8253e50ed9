//! Rasterizer invariants, closed-form renders, error reporting and numerical stress.
//!
//! - an empty model renders exactly the background;
//! - culled Gaussians (NaN/Inf values, zero quaternion, behind the near plane, fully
//!   transparent, off-screen) change nothing, bit for bit, and get zero gradients;
//! - results are bit-identical across runs and across thread counts;
//! - single Gaussians on the optical axis match the closed-form EWA footprint;
//! - bad inputs give errors, never panics;
//! - extreme scales, opacities and positions (camera inside the cloud) stay finite.

mod common;

use common::{backward, pixel_weights, Gaussians};
use glam::{Quat, Vec3};
use gs_core::raster::{
    render, render_backward, GaussianGrads, PixelGrads, RasterError, RasterSettings, RenderOutput,
};
use gs_core::rng::SplitMix64;
use gs_core::{Camera, Intrinsics};

fn camera(width: u32, height: u32) -> Camera {
    Camera::look_at(
        Intrinsics::from_fov_x(0.9, width, height),
        Vec3::new(0.5, -4.0, 1.0),
        Vec3::ZERO,
        Vec3::Z,
    )
}

fn pixel_grads_for(out: &RenderOutput, seed: u64) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    let px = out.width as usize * out.height as usize;
    pixel_weights(&mut SplitMix64::new(seed), px, out.n_channels)
}

fn render_and_backward(
    cam: &Camera,
    g: &Gaussians,
    settings: &RasterSettings,
) -> (RenderOutput, GaussianGrads) {
    let out = render(cam, &g.view(), settings).unwrap();
    let grads = backward(cam, g, settings, &out, &pixel_grads_for(&out, 5));
    (out, grads)
}

fn all_finite(v: &[f32]) -> bool {
    v.iter().all(|x| x.is_finite())
}

fn assert_grads_finite(g: &GaussianGrads) {
    for (name, v) in [
        ("d_means", &g.d_means),
        ("d_log_scales", &g.d_log_scales),
        ("d_rotations", &g.d_rotations),
        ("d_opacity_logits", &g.d_opacity_logits),
        ("d_channels", &g.d_channels),
        ("mean2d_grad_ndc", &g.mean2d_grad_ndc),
    ] {
        assert!(all_finite(v), "{name} has non-finite values");
    }
}

#[test]
fn empty_model_renders_the_background() {
    let cam = camera(40, 23);
    let g = Gaussians::new(3);
    let settings = RasterSettings {
        background: vec![0.1, 0.5, 0.9],
        ..Default::default()
    };
    let (out, grads) = render_and_backward(&cam, &g, &settings);
    assert_eq!(out.color.len(), 40 * 23 * 3);
    for px in out.color.chunks(3) {
        assert_eq!(px, &[0.1, 0.5, 0.9]);
    }
    assert!(out.alpha.iter().all(|&a| a == 0.0));
    assert!(out.depth.iter().all(|&d| d == 0.0));
    assert!(grads.d_means.is_empty() && grads.d_channels.is_empty());
    // Default background is zero in every channel.
    let out = render(&cam, &g.view(), &RasterSettings::default()).unwrap();
    assert!(out.color.iter().all(|&c| c == 0.0));
}

#[test]
fn culled_gaussians_change_nothing() {
    let cam = camera(70, 50);
    let mut rng = SplitMix64::new(3);
    let base = Gaussians::random_cloud(&mut rng, 60, 3, Vec3::ZERO, 0.8);
    let settings = RasterSettings {
        background: vec![0.2, 0.3, 0.4],
        ..Default::default()
    };
    let (out_base, grads_base) = render_and_backward(&cam, &base, &settings);
    assert!(out_base.visible.iter().filter(|&&v| v).count() > 50);

    let mut bad = Gaussians::new(3);
    let ok_s = [-2.0; 3];
    let ok_q = [1.0, 0.0, 0.0, 0.0];
    let ok_c = [0.5; 3];
    bad.push([f32::NAN, 0.0, 0.0], ok_s, ok_q, 2.0, &ok_c);
    bad.push([0.0, f32::INFINITY, 0.0], ok_s, ok_q, 2.0, &ok_c);
    bad.push([0.0; 3], [f32::NAN, -2.0, -2.0], ok_q, 2.0, &ok_c);
    bad.push([0.0; 3], [200.0, -2.0, -2.0], ok_q, 2.0, &ok_c); // exp overflows to Inf
    bad.push([0.0; 3], ok_s, [0.0, 0.0, 0.0, 0.0], 2.0, &ok_c);
    bad.push([0.0; 3], ok_s, [0.0, 5e-4, 0.0, 5e-4], 2.0, &ok_c); // |q|^2 = 5e-7
    bad.push([0.0; 3], ok_s, [f32::NAN, 0.0, 0.0, 1.0], 2.0, &ok_c);
    bad.push([0.0; 3], ok_s, ok_q, f32::NAN, &ok_c);
    bad.push([0.0; 3], ok_s, ok_q, -40.0, &ok_c); // opacity 4e-18
    bad.push([0.0; 3], ok_s, ok_q, 2.0, &[f32::NAN, 0.0, 0.0]);
    bad.push([0.0; 3], ok_s, ok_q, 2.0, &[0.0, f32::NEG_INFINITY, 0.0]);
    bad.push([0.5, -4.0, 1.0], ok_s, ok_q, 2.0, &ok_c); // at the camera centre
    bad.push([1.0, -8.0, 2.0], ok_s, ok_q, 2.0, &ok_c); // behind the camera
    bad.push([60.0, 0.0, 0.0], ok_s, ok_q, 2.0, &ok_c); // far off-screen

    let mut mixed = base.clone();
    let mut bad_positions = Vec::new();
    for k in 0..bad.len() {
        let at = (k * 7 + 3) % (mixed.len() + 1);
        mixed.insert_from(at, &bad, k);
        for p in bad_positions.iter_mut() {
            if *p >= at {
                *p += 1;
            }
        }
        bad_positions.push(at);
    }
    let (out_mixed, grads_mixed) = render_and_backward(&cam, &mixed, &settings);
    assert_eq!(out_mixed.color, out_base.color);
    assert_eq!(out_mixed.alpha, out_base.alpha);
    assert_eq!(out_mixed.depth, out_base.depth);
    assert_eq!(grads_mixed.dropped_nonfinite, 0);
    assert_grads_finite(&grads_mixed);

    let mut base_idx = 0;
    for i in 0..mixed.len() {
        if bad_positions.contains(&i) {
            assert!(!out_mixed.visible[i], "bad Gaussian at {i} visible");
            assert_eq!(out_mixed.radii_px[i], 0.0);
            assert_eq!(grads_mixed.d_means[3 * i..3 * i + 3], [0.0; 3]);
            assert_eq!(grads_mixed.d_log_scales[3 * i..3 * i + 3], [0.0; 3]);
            assert_eq!(grads_mixed.d_rotations[4 * i..4 * i + 4], [0.0; 4]);
            assert_eq!(grads_mixed.d_opacity_logits[i], 0.0);
            assert_eq!(grads_mixed.d_channels[3 * i..3 * i + 3], [0.0; 3]);
            assert_eq!(grads_mixed.mean2d_grad_ndc[i], 0.0);
        } else {
            let b = base_idx;
            assert_eq!(out_mixed.visible[i], out_base.visible[b]);
            assert_eq!(out_mixed.radii_px[i], out_base.radii_px[b]);
            assert_eq!(
                grads_mixed.d_means[3 * i..3 * i + 3],
                grads_base.d_means[3 * b..3 * b + 3]
            );
            assert_eq!(
                grads_mixed.d_rotations[4 * i..4 * i + 4],
                grads_base.d_rotations[4 * b..4 * b + 4]
            );
            assert_eq!(
                grads_mixed.d_opacity_logits[i],
                grads_base.d_opacity_logits[b]
            );
            assert_eq!(
                grads_mixed.d_channels[3 * i..3 * i + 3],
                grads_base.d_channels[3 * b..3 * b + 3]
            );
            base_idx += 1;
        }
    }
}

#[test]
fn results_are_bit_identical_across_runs_and_thread_counts() {
    let cam = camera(150, 100);
    let mut rng = SplitMix64::new(11);
    let g = Gaussians::random_cloud(&mut rng, 3000, 4, Vec3::ZERO, 1.0);
    let settings = RasterSettings::default();
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| render_and_backward(&cam, &g, &settings))
    };
    let (out_a, grads_a) = run(2);
    let (out_b, grads_b) = run(2);
    let (out_c, grads_c) = run(3);
    let (out_d, grads_d) = run(1);
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    for (out, grads) in [(&out_b, &grads_b), (&out_c, &grads_c), (&out_d, &grads_d)] {
        assert_eq!(bits(&out.color), bits(&out_a.color));
        assert_eq!(bits(&out.alpha), bits(&out_a.alpha));
        assert_eq!(bits(&out.depth), bits(&out_a.depth));
        assert_eq!(bits(&out.radii_px), bits(&out_a.radii_px));
        assert_eq!(bits(&grads.d_means), bits(&grads_a.d_means));
        assert_eq!(bits(&grads.d_log_scales), bits(&grads_a.d_log_scales));
        assert_eq!(bits(&grads.d_rotations), bits(&grads_a.d_rotations));
        assert_eq!(
            bits(&grads.d_opacity_logits),
            bits(&grads_a.d_opacity_logits)
        );
        assert_eq!(bits(&grads.d_channels), bits(&grads_a.d_channels));
        assert_eq!(bits(&grads.mean2d_grad_ndc), bits(&grads_a.mean2d_grad_ndc));
    }
    // The scene is not trivial: many pixels covered, many gradients non-zero.
    assert!(out_a.alpha.iter().filter(|&&a| a > 0.5).count() > 2000);
    assert!(grads_a.d_means.iter().filter(|&&d| d != 0.0).count() > 3000);
}

/// A camera at the origin looking along +z with the principal point on a pixel centre,
/// so a Gaussian on the optical axis has `J = diag(f/z, f/z)` and a 2D covariance of
/// `(f/z)^2 R2 diag(sx^2, sy^2) R2^T + 0.3 I` (R2 its rotation about the axis).
fn axis_camera(width: u32, height: u32, f: f32) -> Camera {
    Camera {
        intrinsics: Intrinsics {
            fx: f,
            fy: f,
            cx: width as f32 / 2.0 + 0.5,
            cy: height as f32 / 2.0 + 0.5,
            width,
            height,
        },
        rotation: Quat::IDENTITY,
        translation: Vec3::ZERO,
    }
}

#[test]
fn single_gaussians_match_the_closed_form_footprint() {
    let (w, h, f) = (64u32, 48u32, 80.0f32);
    let cam = axis_camera(w, h, f);
    let z = 5.0f32;
    let bg = [0.2f32, 0.6];
    let colour = [0.9f32, 0.3];
    let settings = RasterSettings {
        background: bg.to_vec(),
        ..Default::default()
    };
    // (scale x, scale y, rotation angle about the optical axis, opacity)
    for (sx, sy, theta, opacity) in [(0.2f32, 0.2f32, 0.0f32, 0.8f32), (0.35, 0.08, 0.6, 0.5)] {
        let mut g = Gaussians::new(2);
        let q = Quat::from_rotation_z(theta);
        let logit = (opacity / (1.0 - opacity)).ln();
        g.push(
            [0.0, 0.0, z],
            [sx.ln(), sy.ln(), (0.05f32).ln()],
            [q.w, q.x, q.y, q.z],
            logit,
            &colour,
        );
        let out = render(&cam, &g.view(), &settings).unwrap();
        // Closed-form 2D covariance and its inverse.
        let k = f / z;
        let (c, s) = (theta.cos(), theta.sin());
        let (vx, vy) = ((k * sx).powi(2), (k * sy).powi(2));
        let sxx = c * c * vx + s * s * vy + 0.3;
        let sxy = c * s * (vx - vy);
        let syy = s * s * vx + c * c * vy + 0.3;
        let det = sxx * syy - sxy * sxy;
        let (mean_x, mean_y) = (w as f32 / 2.0 + 0.5, h as f32 / 2.0 + 0.5);
        let mut covered = 0;
        for y in 0..h {
            for x in 0..w {
                let dx = x as f32 + 0.5 - mean_x;
                let dy = y as f32 + 0.5 - mean_y;
                let maha = (syy * dx * dx - 2.0 * sxy * dx * dy + sxx * dy * dy) / det;
                let a = (opacity * (-0.5 * maha).exp()).min(0.99);
                let a = if a < 1.0 / 255.0 { 0.0 } else { a };
                let p = (y * w + x) as usize;
                let tol = 2e-6 + 2e-5 * a;
                assert!(
                    (out.alpha[p] - a).abs() < tol,
                    "alpha at ({x},{y}): {} vs {a}",
                    out.alpha[p]
                );
                assert!((out.depth[p] - a * z).abs() < tol * z);
                for ch in 0..2 {
                    let expect = a * colour[ch] + (1.0 - a) * bg[ch];
                    assert!(
                        (out.color[p * 2 + ch] - expect).abs() < tol,
                        "colour at ({x},{y})"
                    );
                }
                if a > 0.0 {
                    covered += 1;
                }
            }
        }
        // Peak at the pixel holding the mean is the opacity itself.
        let centre = ((h / 2) * w + w / 2) as usize;
        assert!((out.alpha[centre] - opacity).abs() < 1e-6);
        assert!(covered > 30);
        // Radius: the opacity-aware extent sqrt(2 ln(255 o) lambda_max).
        let mid = 0.5 * (sxx + syy);
        let lambda = mid + (mid * mid - det).sqrt();
        let radius = (2.0 * (255.0 * opacity).ln() * lambda).sqrt();
        assert!((out.radii_px[0] - radius).abs() < 1e-3 * radius);
    }
}

#[test]
fn bad_inputs_are_errors_not_panics() {
    let cam = camera(32, 32);
    let mut rng = SplitMix64::new(1);
    let g = Gaussians::random_cloud(&mut rng, 10, 3, Vec3::ZERO, 0.5);
    let s = RasterSettings::default();
    let mut short = g.clone();
    short.means.pop();
    assert!(matches!(
        render(&cam, &short.view(), &s),
        Err(RasterError::Length { .. })
    ));
    let mut short = g.clone();
    short.channels.pop();
    assert!(matches!(
        render(&cam, &short.view(), &s),
        Err(RasterError::Length { .. })
    ));
    let mut short = g.clone();
    short.rotations.push(1.0);
    assert!(matches!(
        render(&cam, &short.view(), &s),
        Err(RasterError::Length { .. })
    ));

    let mut zero = cam;
    zero.intrinsics.width = 0;
    assert!(matches!(
        render(&zero, &g.view(), &s),
        Err(RasterError::EmptyImage { .. })
    ));
    let mut nan_cam = cam;
    nan_cam.translation.x = f32::NAN;
    assert!(matches!(
        render(&nan_cam, &g.view(), &s),
        Err(RasterError::InvalidCamera(_))
    ));
    let mut neg_f = cam;
    neg_f.intrinsics.fx = -1.0;
    assert!(matches!(
        render(&neg_f, &g.view(), &s),
        Err(RasterError::InvalidCamera(_))
    ));
    let bad_bg = RasterSettings {
        background: vec![0.0; 2],
        ..Default::default()
    };
    assert!(matches!(
        render(&cam, &g.view(), &bad_bg),
        Err(RasterError::Length { .. })
    ));
    let bad_near = RasterSettings {
        near_m: 0.0,
        ..Default::default()
    };
    assert!(matches!(
        render(&cam, &g.view(), &bad_near),
        Err(RasterError::InvalidSettings(_))
    ));

    let out = render(&cam, &g.view(), &s).unwrap();
    let (mut c, a, d) = pixel_grads_for(&out, 2);
    let pg = |c: &[f32]| -> Result<_, RasterError> {
        render_backward(
            &cam,
            &g.view(),
            &s,
            &out,
            &PixelGrads {
                d_color: c,
                d_alpha: Some(&a),
                d_depth: Some(&d),
            },
        )
    };
    assert!(matches!(pg(&c[1..]), Err(RasterError::Length { .. })));
    c[17] = f32::NAN;
    assert!(matches!(pg(&c), Err(RasterError::NonFiniteGradient(_))));
    c[17] = 0.0;
    assert!(pg(&c).is_ok());
    // Backward with other parameters than the forward used.
    let mut moved = g.clone();
    for m in moved.means.iter_mut() {
        *m += 0.01;
    }
    let res = render_backward(
        &cam,
        &moved.view(),
        &s,
        &out,
        &PixelGrads {
            d_color: &c,
            d_alpha: None,
            d_depth: None,
        },
    );
    assert!(matches!(res, Err(RasterError::ForwardMismatch(_))));
    let other_cam = camera(32, 32);
    let mut other_cam2 = other_cam;
    other_cam2.translation.z += 0.1;
    let res = render_backward(
        &other_cam2,
        &g.view(),
        &s,
        &out,
        &PixelGrads {
            d_color: &c,
            d_alpha: None,
            d_depth: None,
        },
    );
    assert!(matches!(res, Err(RasterError::ForwardMismatch(_))));
}

/// Scales 1e-6..1e3, opacity logits +-40, Gaussians on and behind the near plane, and
/// the camera inside the cloud: everything stays finite and nothing panics.
#[test]
fn extreme_inputs_stay_finite() {
    let mut rng = SplitMix64::new(77);
    let k = Intrinsics::from_fov_x(1.2, 160, 100);
    let eye = Vec3::new(0.1, 0.2, -0.1);
    let cam = Camera::look_at(k, eye, Vec3::new(1.0, 0.5, 0.3), Vec3::Z);
    let settings = RasterSettings {
        background: vec![0.3; 3],
        ..Default::default()
    };
    let mut g = Gaussians::new(3);
    let forward = (cam.rotation.conjugate() * Vec3::Z).normalize();
    for i in 0..4000 {
        let mean = match i % 5 {
            // Inside a cloud around the camera.
            0 | 1 => {
                eye + Vec3::new(
                    rng.uniform(-3.0, 3.0),
                    rng.uniform(-3.0, 3.0),
                    rng.uniform(-3.0, 3.0),
                )
            }
            // On the near plane (camera z within a hair of 0.01 either side).
            2 => {
                eye + forward * (0.01 + rng.uniform(-1e-4, 1e-4))
                    + Vec3::new(rng.uniform(-0.01, 0.01), rng.uniform(-0.01, 0.01), 0.0)
            }
            // Just in front of the camera.
            3 => eye + forward * rng.uniform(0.011, 0.2),
            // Behind the camera.
            _ => eye - forward * rng.uniform(0.0, 2.0),
        };
        let log_s = [(); 3].map(|_| rng.uniform((1e-6f32).ln(), (1e3f32).ln()));
        let q = [(); 4].map(|_| rng.uniform(-1.0, 1.0));
        let logit = match i % 3 {
            0 => 40.0,
            1 => -40.0,
            _ => rng.uniform(-10.0, 10.0),
        };
        let ch = [(); 3].map(|_| rng.uniform(-2.0, 2.0));
        g.push(mean.to_array(), log_s, q, logit, &ch);
    }
    for smooth in [false, true] {
        let settings = RasterSettings {
            smooth_cutoff: smooth,
            ..settings.clone()
        };
        let (out, grads) = render_and_backward(&cam, &g, &settings);
        assert!(all_finite(&out.color) && all_finite(&out.alpha) && all_finite(&out.depth));
        assert!(all_finite(&out.radii_px));
        assert!(out.alpha.iter().all(|&a| (0.0..=1.0).contains(&a)));
        assert_grads_finite(&grads);
        let visible = out.visible.iter().filter(|&&v| v).count();
        assert!(visible > 500, "only {visible} visible");
        println!(
            "smooth {smooth}: visible {visible}, dropped non-finite {}",
            grads.dropped_nonfinite
        );
    }
}

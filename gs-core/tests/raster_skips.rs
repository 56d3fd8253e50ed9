//! The rasterizer's three switchable skips, each checked against running without it:
//!
//! - `cull_outside_frustum` (the early, conservative frustum test) changes no bit of the
//!   image, the per-Gaussian outputs or any gradient, on scenes full of Gaussians just
//!   outside the image (some of which still reach into it);
//! - `early_termination` off blends past T < 1e-4: the image moves by at most the stopped
//!   pixel's residual transmittance times the largest |channel - background| (the bound in
//!   `RasterSettings::early_termination`), pixels do move, and the backward stays finite
//!   (its exactness against finite differences is checked tile by tile in `raster/blend/tests.rs`);
//! - `blend_tiles` from a foreground mask (the Sun-aware step's
//!   `skip_masked_background_tiles`): with the masked photometric loss, the loss, its
//!   pixel gradient and every Gaussian gradient are the same bits as with every tile
//!   blended, and so is the rendered image on the tiles kept; a reach smaller than the
//!   SSIM window's half width does change the gradients (so the comparison can fail).

mod common;

use common::{assert_bits_eq, assert_same_grads, backward, bits, pixel_weights, Gaussians};
use glam::Vec3;
use gs_core::camera::{Camera, Intrinsics};
use gs_core::init::{inverse_sigmoid, SplitMix64};
use gs_core::loss::{photometric_loss, ImageShape, SSIM_WINDOW};
use gs_core::model::{GaussianModel, Param};
use gs_core::nn::SceneBox;
use gs_core::raster::bin::{TileGrid, TileSelection, TILE_PX};
use gs_core::raster::blend::AlphaMode;
use gs_core::raster::project::footprint_certainly_misses;
use gs_core::raster::{
    camera_frame, project_splats_with, render, render_backward, GaussianGrads, PixelGrads,
    RasterSettings, RenderOutput,
};
use gs_core::sunaware::trainer::loss_and_grads;
use gs_core::sunaware::{Observation, SunAwareConfig, SunAwareModel, Variant};

const NC: usize = 3;

/// Opacity logits of the skip scenes: U(-1, 4).
fn random_logit(rng: &mut SplitMix64) -> f32 {
    rng.uniform(-1.0, 4.0)
}

/// 96x64 pixels (6x4 tiles), fov_x 1 rad.
fn camera() -> Camera {
    let k = Intrinsics::from_fov_x(1.0, 96, 64);
    Camera::look_at(
        k,
        Vec3::new(0.3, -0.2, -5.0),
        Vec3::ZERO,
        Vec3::new(0.0, 1.0, 0.0),
    )
}

fn settings(rng: &mut SplitMix64) -> RasterSettings {
    RasterSettings {
        near_m: 0.2,
        background: (0..NC).map(|_| rng.uniform(0.0, 1.0)).collect(),
        ..RasterSettings::default()
    }
}

/// A dense cluster in view, Gaussians scattered up to three image widths around it (many
/// outside the frustum, small and large), some straddling the edges, some behind the
/// near plane and behind the camera.
fn scene(seed: u64, camera: &Camera) -> Gaussians {
    let mut rng = SplitMix64::new(seed);
    let mut g = Gaussians::new(NC);
    // tan(fov_x / 2) = 0.546; the image spans |x/z| < 0.546, |y/z| < 0.364.
    for _ in 0..400 {
        let z = rng.uniform(3.0, 7.0);
        let c = Vec3::new(rng.uniform(-0.45, 0.45) * z, rng.uniform(-0.3, 0.3) * z, z);
        let sigma = rng.uniform(0.03, 0.25);
        g.push_in_camera(&mut rng, camera, c, sigma, random_logit);
    }
    for _ in 0..600 {
        let z = rng.uniform(0.5, 20.0);
        let c = Vec3::new(rng.uniform(-2.0, 2.0) * z, rng.uniform(-1.5, 1.5) * z, z);
        let sigma = if rng.uniform(0.0, 1.0) < 0.3 {
            rng.uniform(0.3, 2.0)
        } else {
            rng.uniform(0.02, 0.2)
        };
        g.push_in_camera(&mut rng, camera, c, sigma, random_logit);
    }
    for _ in 0..50 {
        let z = rng.uniform(-3.0, 0.19);
        let c = Vec3::new(rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0), z);
        g.push_in_camera(&mut rng, camera, c, 0.3, random_logit);
    }
    g
}

fn render_and_backward(
    camera: &Camera,
    g: &Gaussians,
    settings: &RasterSettings,
    weights: &(Vec<f32>, Vec<f32>, Vec<f32>),
) -> (RenderOutput, GaussianGrads) {
    let out = render(camera, &g.view(), settings).unwrap();
    let grads = backward(camera, g, settings, &out, weights);
    (out, grads)
}

#[test]
fn frustum_cull_changes_no_bit() {
    let cam = camera();
    let k = cam.intrinsics;
    for seed in [1u64, 2, 3] {
        let g = scene(seed, &cam);
        let mut rng = SplitMix64::new(seed ^ 0x77);
        let on = settings(&mut rng);
        let off = RasterSettings {
            cull_outside_frustum: false,
            ..on.clone()
        };
        // The early test really fires, and some Gaussians centred outside the image still
        // reach into it (so a plain centre-in-frustum test would have changed the image).
        let frame = camera_frame(&cam, on.near_m).unwrap();
        let cutoff = AlphaMode { smooth: false }.cutoff();
        let n = g.opacity_logits.len();
        let flagged = (0..n)
            .filter(|&i| {
                footprint_certainly_misses(&frame, &g.params(i), cutoff, k.width, k.height)
            })
            .count();
        assert!(flagged > 200, "seed {seed}: only {flagged} culled early");
        let weights = pixel_weights(&mut rng, (k.width * k.height) as usize, NC);
        let (out_on, grads_on) = render_and_backward(&cam, &g, &on, &weights);
        let (out_off, grads_off) = render_and_backward(&cam, &g, &off, &weights);
        let outside_but_visible = (0..n)
            .filter(|&i| {
                let m = Vec3::from_slice(&g.means[3 * i..3 * i + 3]);
                let c = cam.rotation * m + cam.translation;
                let (u, v) = (k.fx * c.x / c.z + k.cx, k.fy * c.y / c.z + k.cy);
                c.z > 0.2
                    && (u < 0.0 || v < 0.0 || u > k.width as f32 || v > k.height as f32)
                    && out_off.visible[i]
            })
            .count();
        assert!(
            outside_but_visible > 5,
            "seed {seed}: {outside_but_visible}"
        );
        assert_bits_eq(&out_on.color, &out_off.color, "values");
        assert_bits_eq(&out_on.alpha, &out_off.alpha, "values");
        assert_bits_eq(&out_on.depth, &out_off.depth, "values");
        assert_bits_eq(&out_on.radii_px, &out_off.radii_px, "values");
        assert_eq!(out_on.visible, out_off.visible);
        assert_same_grads(&grads_on, &grads_off, "frustum cull");
        // Projection alone, without the blend: the same survivors either way.
        let proj_on = project_splats_with(
            &frame,
            &g.view(),
            AlphaMode { smooth: false },
            k.width,
            k.height,
            true,
        );
        let proj_off = project_splats_with(
            &frame,
            &g.view(),
            AlphaMode { smooth: false },
            k.width,
            k.height,
            false,
        );
        for i in 0..n {
            assert_eq!(proj_on.splats[i].is_some(), proj_off.splats[i].is_some());
        }
        assert_bits_eq(&proj_on.radii_px, &proj_off.radii_px, "values");
    }
}

/// Thousands of Gaussians of every size placed around the image border at every depth:
/// whatever the early test flags, the full projection drops too.
#[test]
fn early_frustum_test_is_conservative() {
    let cam = camera();
    let k = cam.intrinsics;
    let frame = camera_frame(&cam, 0.2).unwrap();
    let cutoff = AlphaMode { smooth: false }.cutoff();
    let mut rng = SplitMix64::new(11);
    let mut g = Gaussians::new(NC);
    for _ in 0..20_000 {
        let z = rng.uniform(0.2, 30.0);
        // Centres within +-20 % of the image border, in x or in y.
        let (bx, by) = if rng.uniform(0.0, 1.0) < 0.5 {
            (
                0.546
                    * if rng.uniform(0.0, 1.0) < 0.5 {
                        -1.0
                    } else {
                        1.0
                    },
                rng.uniform(-0.45, 0.45),
            )
        } else {
            (
                rng.uniform(-0.65, 0.65),
                0.364
                    * if rng.uniform(0.0, 1.0) < 0.5 {
                        -1.0
                    } else {
                        1.0
                    },
            )
        };
        let c = Vec3::new(
            (bx * rng.uniform(0.8, 1.2)) * z,
            (by * rng.uniform(0.8, 1.2)) * z,
            z,
        );
        let sigma = 10f32.powf(rng.uniform(-3.0, 0.5));
        g.push_in_camera(&mut rng, &cam, c, sigma, random_logit);
    }
    let n = g.opacity_logits.len();
    let full = project_splats_with(
        &frame,
        &g.view(),
        AlphaMode { smooth: false },
        k.width,
        k.height,
        false,
    );
    let mut flagged = 0;
    let mut survivors = 0;
    for i in 0..n {
        let misses = footprint_certainly_misses(&frame, &g.params(i), cutoff, k.width, k.height);
        flagged += usize::from(misses);
        survivors += usize::from(full.splats[i].is_some());
        assert!(
            !(misses && full.splats[i].is_some()),
            "Gaussian {i} flagged but its footprint reaches the image"
        );
    }
    assert!(
        flagged > 2_000 && survivors > 2_000,
        "{flagged} / {survivors}"
    );
}

/// Dense, opaque stacks: many pixels stop early with early termination on.
fn dense_scene(camera: &Camera) -> Gaussians {
    let mut rng = SplitMix64::new(5);
    let mut g = Gaussians::new(NC);
    for _ in 0..1500 {
        let z = rng.uniform(3.0, 6.0);
        let c = Vec3::new(rng.uniform(-0.3, 0.3) * z, rng.uniform(-0.2, 0.2) * z, z);
        let sigma = rng.uniform(0.1, 0.4);
        g.push_in_camera(&mut rng, camera, c, sigma, random_logit);
    }
    g
}

#[test]
fn early_termination_off_moves_pixels_within_the_bound() {
    let cam = camera();
    let k = cam.intrinsics;
    let g = dense_scene(&cam);
    let mut rng = SplitMix64::new(8);
    let on = settings(&mut rng);
    let off = RasterSettings {
        early_termination: false,
        ..on.clone()
    };
    let weights = pixel_weights(&mut rng, (k.width * k.height) as usize, NC);
    let (out_on, _) = render_and_backward(&cam, &g, &on, &weights);
    let (out_off, grads_off) = render_and_backward(&cam, &g, &off, &weights);
    // Largest |channel - background| over every Gaussian and channel.
    let max_dev = g
        .channels
        .chunks(NC)
        .flat_map(|c| c.iter().zip(&on.background).map(|(a, b)| (a - b).abs()))
        .fold(0.0f32, f32::max);
    let mut stopped = 0;
    let mut moved = 0;
    for p in 0..(k.width * k.height) as usize {
        let t_on = 1.0 - out_on.alpha[p];
        let t_off = 1.0 - out_off.alpha[p];
        // The pixel keeps blending: less light gets through. 1e-6 covers `1 - alpha`.
        assert!(t_off <= t_on + 1e-6, "pixel {p}: T {t_on} -> {t_off}");
        if t_on < 1e-2 {
            stopped += 1;
        }
        for c in 0..NC {
            let d = (out_on.color[p * NC + c] - out_off.color[p * NC + c]).abs();
            // T_on is below 0.01 wherever blending stopped (T (1 - alpha) < 1e-4 with
            // alpha <= 0.99); 1e-5 covers the rounding of the two sums.
            assert!(
                d <= t_on * max_dev + 1e-5,
                "pixel {p} channel {c}: {d} > {t_on} * {max_dev}"
            );
            assert!(d <= 1e-2 * max_dev + 1e-5);
            moved += usize::from(d > 1e-6);
        }
    }
    assert!(stopped > 500, "only {stopped} pixels stopped early");
    assert!(moved > 100, "only {moved} channel values moved");
    assert!(grads_off.d_means.iter().all(|v| v.is_finite()));
    assert_eq!(grads_off.dropped_nonfinite, 0);
}

/// Mask: a disc of radius 11 px centred at (42.5, 24.5) px in the 96x64 image: it covers
/// tile columns 2..=3 and rows 0..=2, and its 5 px SSIM rim reaches into column 1.
fn disc_mask(k: &Intrinsics) -> Vec<f32> {
    let (w, h) = (k.width as usize, k.height as usize);
    let mut mask = vec![0.0f32; w * h];
    for y in 0..h {
        for x in 0..w {
            let (dx, dy) = (x as f32 - 42.5, y as f32 - 24.5);
            if dx * dx + dy * dy < 121.0 {
                mask[y * w + x] = 1.0;
            }
        }
    }
    mask
}

/// Masked photometric loss (lambda 0.2), its pixel gradient and the Gaussian gradients.
fn masked_loss_and_grads(
    cam: &Camera,
    g: &Gaussians,
    settings: &RasterSettings,
    target: &[f32],
    mask: &[f32],
) -> (RenderOutput, f32, Vec<f32>, GaussianGrads) {
    let k = cam.intrinsics;
    let shape = ImageShape::new(k.width as usize, k.height as usize, NC);
    let out = render(cam, &g.view(), settings).unwrap();
    let loss = photometric_loss(&out.color, target, Some(mask), shape, 0.2).unwrap();
    let grads = render_backward(
        cam,
        &g.view(),
        settings,
        &out,
        &PixelGrads {
            d_color: &loss.d_rendered,
            d_alpha: None,
            d_depth: None,
        },
    )
    .unwrap();
    (out, loss.loss, loss.d_rendered, grads)
}

#[test]
fn masked_background_tiles_change_no_gradient_bit() {
    let cam = camera();
    let k = cam.intrinsics;
    let g = dense_scene(&cam);
    let mut rng = SplitMix64::new(9);
    let all = settings(&mut rng);
    let target: Vec<f32> = (0..(k.width * k.height) as usize * NC)
        .map(|_| rng.uniform(0.0, 1.0))
        .collect();
    let mask = disc_mask(&k);
    let reach = (SSIM_WINDOW / 2) as u32;
    let selection = TileSelection::from_mask(&mask, k.width, k.height, reach).unwrap();
    // Tiles 1..4 x 0..3 of 6x4 hold the disc and its 5 px rim: a third of them is skipped.
    assert_eq!(selection.n_tiles(), 24);
    assert!(
        selection.active_count() <= 16,
        "{}",
        selection.active_count()
    );
    let skip = RasterSettings {
        blend_tiles: Some(selection.clone()),
        ..all.clone()
    };
    let (out_all, loss_all, d_all, grads_all) =
        masked_loss_and_grads(&cam, &g, &all, &target, &mask);
    let (out_skip, loss_skip, d_skip, grads_skip) =
        masked_loss_and_grads(&cam, &g, &skip, &target, &mask);
    assert_eq!(loss_all.to_bits(), loss_skip.to_bits());
    // The loss gradient is zero off the kept tiles (its sign may follow the rendered
    // value there: -0 or +0), and the same bits on them.
    let grid = TileGrid::new(k.width, k.height);
    for t in 0..grid.n_tiles() {
        let r = grid.tile_rect(t);
        for y in r.y0..r.y1 {
            for x in r.x0..r.x1 {
                let p = (y * k.width + x) as usize * NC;
                let (a, b) = (&d_all[p..p + NC], &d_skip[p..p + NC]);
                if selection.is_active(t) {
                    assert_bits_eq(a, b, "d_rendered on a kept tile");
                } else {
                    assert!(a.iter().chain(b).all(|&v| v == 0.0), "({x}, {y})");
                }
            }
        }
    }
    assert_same_grads(&grads_all, &grads_skip, "masked background tiles");
    assert!(grads_all.d_means.iter().any(|&v| v != 0.0));
    // The image is the same on every kept tile (the mask and the SSIM rim included), and
    // the skipped tiles hold the background.
    let mut skipped_pixels = 0;
    for t in 0..grid.n_tiles() {
        let r = grid.tile_rect(t);
        for y in r.y0..r.y1 {
            for x in r.x0..r.x1 {
                let p = (y * k.width + x) as usize;
                let (a, b) = (
                    &out_all.color[p * NC..][..NC],
                    &out_skip.color[p * NC..][..NC],
                );
                if selection.is_active(t) {
                    assert_bits_eq(a, b, "pixel ({x}, {y})");
                    assert_eq!(out_all.alpha[p].to_bits(), out_skip.alpha[p].to_bits());
                } else {
                    assert_bits_eq(b, &all.background, "values");
                    assert_eq!(out_skip.alpha[p], 0.0);
                    assert!(mask[p] == 0.0);
                    skipped_pixels += 1;
                    // The skip mattered: this tile had content.
                }
            }
        }
    }
    assert!(skipped_pixels >= 8 * (TILE_PX * TILE_PX) as usize);
    assert!(out_all.alpha.iter().filter(|&&a| a > 0.5).count() > 3000);

    // Control: a reach below the SSIM window's half width drops pixels the SSIM reads, and
    // the gradients do change, so the comparison above can fail.
    let short = RasterSettings {
        blend_tiles: Some(TileSelection::from_mask(&mask, k.width, k.height, 0).unwrap()),
        ..all.clone()
    };
    assert_eq!(short.blend_tiles.as_ref().unwrap().active_count(), 6);
    let (_, loss_short, _, grads_short) = masked_loss_and_grads(&cam, &g, &short, &target, &mask);
    assert!(
        loss_short.to_bits() != loss_all.to_bits()
            || bits(&grads_short.d_means) != bits(&grads_all.d_means)
    );
}

#[test]
fn tile_selection_of_another_size_is_an_error() {
    let cam = camera();
    let g = scene(1, &cam);
    let mask = vec![1.0f32; 50 * 40];
    let settings = RasterSettings {
        blend_tiles: Some(TileSelection::from_mask(&mask, 50, 40, 0).unwrap()),
        ..RasterSettings::default()
    };
    let err = render(&cam, &g.view(), &settings).unwrap_err();
    assert!(err.to_string().contains("blend_tiles"), "{err}");
}

/// The Sun-aware step (configuration d: Phi, Psi, the shadow pass) with a masked
/// observation: `skip_masked_background_tiles` on and off give the same loss and the same
/// bits in every gradient (Gaussian groups and both networks).
#[test]
fn sunaware_step_with_mask_is_bit_identical_with_the_tile_skip() {
    let k = Intrinsics::from_fov_x(0.6, 96, 64);
    let cam = Camera::look_at(k, Vec3::new(2.2, -1.5, 1.2), Vec3::ZERO, Vec3::Z);
    let sun = Vec3::new(0.3, 0.8, 0.5).normalize();
    let model_for = |skip: bool| {
        let config = SunAwareConfig {
            encoding_frequencies: 2,
            skip_masked_background_tiles: skip,
            ..SunAwareConfig::for_variant(Variant::D)
        };
        let mut g = GaussianModel::new(config.layout()).unwrap();
        let n = 300;
        g.params.push_zeros(n);
        let mut rng = SplitMix64::new(17);
        for i in 0..n {
            let p = &mut g.params;
            let m = [(); 3].map(|_| (rng.next_f32() - 0.5) * 1.2);
            p.row_mut(Param::Mean, i).copy_from_slice(&m);
            for s in p.row_mut(Param::LogScale, i) {
                *s = (0.03 + 0.06 * rng.next_f32()).ln();
            }
            let q = [1.0, rng.next_f32() - 0.5, rng.next_f32() - 0.5, 0.2];
            p.row_mut(Param::Rotation, i).copy_from_slice(&q);
            p.row_mut(Param::OpacityLogit, i)[0] = inverse_sigmoid(0.3 + 0.6 * rng.next_f32());
            for c in p.row_mut(Param::ShDc, i) {
                *c = rng.next_f32() - 0.5;
            }
        }
        let scene_box = SceneBox::new([-0.7; 3], [0.7; 3]).unwrap();
        SunAwareModel::new(g, scene_box, config).unwrap()
    };
    let mut rng = SplitMix64::new(23);
    let image: Vec<f32> = (0..(k.width * k.height) as usize * 3)
        .map(|_| rng.next_f32())
        .collect();
    let mask = disc_mask(&k);
    let obs = Observation {
        camera: cam,
        sun_dir: sun,
        image: &image,
        mask: Some(&mask),
    };
    let mut results = Vec::new();
    for skip in [false, true] {
        let model = model_for(skip);
        let settings = model.raster_settings(false);
        let (parts, pass, grads, _) = loss_and_grads(&model, &obs, 0, &settings, None).unwrap();
        results.push((parts, pass.image, grads.expect("finite step")));
    }
    let (a, b) = (&results[0], &results[1]);
    assert_eq!(a.0.total.to_bits(), b.0.total.to_bits());
    assert_eq!(a.0.ssim.to_bits(), b.0.ssim.to_bits());
    for p in Param::ALL {
        assert_bits_eq(a.2.params.get(p), b.2.params.get(p), p.name());
    }
    assert!(a.2.params.get(Param::Mean).iter().any(|&v| v != 0.0));
    assert_bits_eq(&a.2.appearance, &b.2.appearance, "values");
    assert_bits_eq(&a.2.shadow, &b.2.shadow, "values");
    assert_bits_eq(&a.2.mean2d_grad_ndc, &b.2.mean2d_grad_ndc, "values");
    // The image differs only off the mask's tiles: on the mask it is the same.
    for (px, &m) in mask.iter().enumerate() {
        if m > 0.0 {
            assert_bits_eq(&a.1[px * 3..px * 3 + 3], &b.1[px * 3..px * 3 + 3], "values");
        }
    }
    assert_ne!(bits(&a.1), bits(&b.1), "no tile was skipped");
}

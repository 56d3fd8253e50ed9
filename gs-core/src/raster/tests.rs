//! Tests of the rasterizer's internals: the prepared path against the plain render, the
//! compacted lists, the backward reduction against a serial sum, thread-count
//! independence and the untiling copy.

use super::backward::{write_records, REDUCE_BLOCK};
use super::bin::{TileGrid, TILE_PIXELS, TILE_PX};
use super::blend::{AlphaMode, REC_CHANNELS, REC_CONIC, REC_DEPTH, REC_OPACITY};
use super::project::{self, ProjectedGrad};
use super::untile::{untile, TileMajor};
use super::*;
use crate::camera::Camera;
use crate::rng::SplitMix64;
use crate::Intrinsics;
use glam::Vec3;

/// Geometry of `n` random Gaussians, dense enough that many are hidden.
struct Scene {
    means: Vec<f32>,
    log_scales: Vec<f32>,
    rotations: Vec<f32>,
    opacity_logits: Vec<f32>,
}

impl Scene {
    fn random(seed: u64, n: usize) -> Self {
        let mut rng = SplitMix64::new(seed);
        let mut u = |lo, hi, count: usize| (0..count).map(|_| rng.uniform(lo, hi)).collect();
        Self {
            means: u(-1.0, 1.0, 3 * n),
            log_scales: u(-3.0, -1.6, 3 * n),
            rotations: u(-1.0, 1.0, 4 * n),
            opacity_logits: u(-1.0, 5.0, n),
        }
    }

    fn view<'a>(&'a self, channels: &'a [f32], n_channels: usize) -> GaussianView<'a> {
        GaussianView {
            means: &self.means,
            log_scales: &self.log_scales,
            rotations: &self.rotations,
            opacity_logits: &self.opacity_logits,
            channels,
            n_channels,
        }
    }
}

fn camera() -> Camera {
    Camera::look_at(
        Intrinsics::from_fov_x(0.9, 72, 56),
        Vec3::new(0.5, -4.0, 1.0),
        Vec3::ZERO,
        Vec3::Z,
    )
}

fn settings() -> RasterSettings {
    RasterSettings {
        background: vec![0.2, 0.1, 0.0, 1.0],
        ..RasterSettings::default()
    }
}

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

fn backward(scene: &Scene, channels: &[f32], out: &RenderOutput) -> GaussianGrads {
    let d_color: Vec<f32> = (0..out.color.len())
        .map(|i| ((i * 7919) % 13) as f32 / 13.0 - 0.4)
        .collect();
    let d_alpha: Vec<f32> = (0..out.alpha.len()).map(|i| (i % 5) as f32 * 0.1).collect();
    render_backward(
        &camera(),
        &scene.view(channels, 4),
        &settings(),
        out,
        &PixelGrads {
            d_color: &d_color,
            d_alpha: Some(&d_alpha),
            d_depth: None,
        },
    )
    .unwrap()
}

fn assert_same_grads(a: &GaussianGrads, b: &GaussianGrads) {
    assert_eq!(bits(&a.d_means), bits(&b.d_means));
    assert_eq!(bits(&a.d_log_scales), bits(&b.d_log_scales));
    assert_eq!(bits(&a.d_rotations), bits(&b.d_rotations));
    assert_eq!(bits(&a.d_opacity_logits), bits(&b.d_opacity_logits));
    assert_eq!(bits(&a.d_channels), bits(&b.d_channels));
    assert_eq!(bits(&a.mean2d_grad_ndc), bits(&b.mean2d_grad_ndc));
}

#[test]
fn prepared_render_is_the_plain_render_bit_for_bit() {
    let n = 900;
    let scene = Scene::random(3, n);
    let mut rng = SplitMix64::new(4);
    let channels: Vec<f32> = (0..4 * n).map(|_| rng.uniform(0.0, 1.0)).collect();
    let plain = render(&camera(), &scene.view(&channels, 4), &settings()).unwrap();
    let prepared = prepare_view(&camera(), &scene.view(&[], 0), &settings()).unwrap();
    assert_eq!(prepared.survived(), plain.visible);
    assert_eq!(prepared.tile_entry_count(), plain.tile_entry_count());
    let mut ws = RasterWorkspace::default();
    let out = render_prepared(&mut ws, prepared, &channels, 4).unwrap();
    assert_eq!(bits(&out.color), bits(&plain.color));
    assert_eq!(bits(&out.alpha), bits(&plain.alpha));
    assert_eq!(bits(&out.depth), bits(&plain.depth));
    assert_eq!(bits(&out.radii_px), bits(&plain.radii_px));
    assert_same_grads(
        &backward(&scene, &channels, &out),
        &backward(&scene, &channels, &plain),
    );
}

#[test]
fn channels_of_non_contributing_gaussians_are_never_read() {
    let n = 1500;
    let scene = Scene::random(5, n);
    let mut rng = SplitMix64::new(6);
    let channels: Vec<f32> = (0..4 * n).map(|_| rng.uniform(0.0, 1.0)).collect();
    let prepared = prepare_view(&camera(), &scene.view(&[], 0), &settings()).unwrap();
    let survived = prepared.survived();
    let contributing = prepared.contributing();
    let n_survived = survived.iter().filter(|&&v| v).count();
    let n_contributing = contributing.iter().filter(|&&v| v).count();
    // The scene must exercise both sides: hidden Gaussians and blended ones.
    assert!(n_contributing > 100, "{n_contributing} contribute");
    assert!(
        n_contributing + 100 < n_survived,
        "{n_contributing} of {n_survived} contribute: too few hidden to test"
    );
    for (c, s) in contributing.iter().zip(&survived) {
        assert!(!c || *s, "a culled Gaussian contributes");
    }
    // Garbage (finite) channels wherever the blend should not look.
    let mut garbage = channels.clone();
    for (g, &c) in contributing.iter().enumerate() {
        if !c {
            for (k, v) in garbage[4 * g..4 * g + 4].iter_mut().enumerate() {
                *v = 1e3 * (k as f32 + 1.0) - g as f32;
            }
        }
    }
    let clean = render(&camera(), &scene.view(&channels, 4), &settings()).unwrap();
    let dirty = render(&camera(), &scene.view(&garbage, 4), &settings()).unwrap();
    assert_eq!(bits(&dirty.color), bits(&clean.color));
    assert_eq!(bits(&dirty.alpha), bits(&clean.alpha));
    let g_clean = backward(&scene, &channels, &clean);
    let g_dirty = backward(&scene, &garbage, &dirty);
    assert_same_grads(&g_clean, &g_dirty);
    // ... and they get no channel gradient, while every contributing one is read: a
    // change of its channels changes the image.
    for (g, &c) in contributing.iter().enumerate() {
        if !c {
            assert!(g_clean.d_channels[4 * g..4 * g + 4]
                .iter()
                .all(|&v| v == 0.0));
        }
    }
    for g in (0..n).filter(|&g| contributing[g]).step_by(37) {
        let mut bumped = channels.clone();
        bumped[4 * g] += 0.5;
        let out = render(&camera(), &scene.view(&bumped, 4), &settings()).unwrap();
        assert_ne!(bits(&out.color), bits(&clean.color), "Gaussian {g} unread");
    }
}

/// The backward reduction as it was written first: serial, in rank order, each
/// rank's records summed in tile order into a buffer starting at +0.0, then pushed
/// through the projection backward and scattered to the Gaussians.
fn serial_reduction(
    scene: &Scene,
    channels: &[f32],
    out: &RenderOutput,
    d_color: &[f32],
    d_alpha: &[f32],
) -> GaussianGrads {
    let st = &out.state;
    let nc = 4;
    let stride = REC_CHANNELS + nc;
    let gaussians = scene.view(channels, nc);
    let frame = camera_frame(&camera(), settings().near_m).unwrap();
    let mode = AlphaMode { smooth: false };
    let mut records = vec![f32::NAN; st.bins.tile_ranks.len() * stride];
    let view = blend::PixelGradsView {
        width: out.width as usize,
        d_color,
        d_alpha: Some(d_alpha),
        d_depth: None,
    };
    write_records(st, mode, nc, &view, &mut records);
    let n = gaussians.len();
    let mut g_out = GaussianGrads {
        d_means: vec![0.0; 3 * n],
        d_log_scales: vec![0.0; 3 * n],
        d_rotations: vec![0.0; 4 * n],
        d_opacity_logits: vec![0.0; n],
        d_channels: vec![0.0; nc * n],
        mean2d_grad_ndc: vec![0.0; n],
        ..GaussianGrads::default()
    };
    let (half_w, half_h) = (0.5 * out.width as f32, 0.5 * out.height as f32);
    for (rank, &g) in st.gaussian_of_rank.iter().enumerate() {
        let g = g as usize;
        let mut sum = vec![0.0f32; stride];
        let bins = &st.bins;
        for &e in &bins.entry_of_rank[bins.rank_offsets[rank]..bins.rank_offsets[rank + 1]] {
            let rec = &records[e as usize * stride..(e as usize + 1) * stride];
            for (s, r) in sum.iter_mut().zip(rec) {
                *s += r;
            }
        }
        let p = project::project_forward(&frame, &gaussians.params(g), mode.cutoff()).unwrap();
        let d = ProjectedGrad {
            d_mean_px: [sum[0], sum[1]],
            d_conic: [sum[REC_CONIC], sum[REC_CONIC + 1], sum[REC_CONIC + 2]],
            d_opacity: sum[REC_OPACITY],
            d_depth: sum[REC_DEPTH],
        };
        let pg = project::project_backward(&frame, &p, &d);
        let ndc = (sum[0] * half_w).hypot(sum[1] * half_h);
        let d_ch = &sum[REC_CHANNELS..];
        if !(pg.is_finite() && d_ch.iter().all(|v| v.is_finite()) && ndc.is_finite()) {
            g_out.dropped_nonfinite += 1;
            continue;
        }
        g_out.d_means[3 * g..3 * g + 3].copy_from_slice(&pg.d_mean);
        g_out.d_log_scales[3 * g..3 * g + 3].copy_from_slice(&pg.d_log_scale);
        g_out.d_rotations[4 * g..4 * g + 4].copy_from_slice(&pg.d_rotation);
        g_out.d_opacity_logits[g] = pg.d_opacity_logit;
        g_out.d_channels[nc * g..nc * g + nc].copy_from_slice(d_ch);
        g_out.mean2d_grad_ndc[g] = ndc;
    }
    g_out
}

/// The blocked, parallel reduction gives the serial one's bits, on the full lists and
/// on the compacted ones, with culled Gaussians and more than one block.
#[test]
fn backward_reduction_is_the_serial_rank_order_sum() {
    let n = 2 * REDUCE_BLOCK + 77;
    let mut scene = Scene::random(11, n);
    // Every ninth Gaussian far off to the side: culled, no rank.
    for g in (0..n).step_by(9) {
        scene.means[3 * g] = 40.0;
    }
    let mut rng = SplitMix64::new(12);
    let channels: Vec<f32> = (0..4 * n).map(|_| rng.uniform(0.0, 1.0)).collect();
    let plain = render(&camera(), &scene.view(&channels, 4), &settings()).unwrap();
    let prepared = prepare_view(&camera(), &scene.view(&[], 0), &settings()).unwrap();
    prepared.contributing();
    let compacted =
        render_prepared(&mut RasterWorkspace::default(), prepared, &channels, 4).unwrap();
    assert!(compacted.blended_entry_count() < plain.blended_entry_count());
    let n_culled = plain.visible.iter().filter(|&&v| !v).count();
    assert!(n_culled > 0 && n_culled < n / 2, "{n_culled} culled");
    for out in [&plain, &compacted] {
        let d_color: Vec<f32> = (0..out.color.len())
            .map(|i| ((i * 7919) % 13) as f32 / 13.0 - 0.4)
            .collect();
        let d_alpha: Vec<f32> = (0..out.alpha.len()).map(|i| (i % 5) as f32 * 0.1).collect();
        let expected = serial_reduction(&scene, &channels, out, &d_color, &d_alpha);
        let got = backward(&scene, &channels, out);
        assert_same_grads(&got, &expected);
        assert_eq!(got.dropped_nonfinite, expected.dropped_nonfinite);
        let nonzero = got.d_means.iter().filter(|&&v| v != 0.0).count();
        assert!(nonzero > n, "only {nonzero} non-zero mean gradients");
    }
}

/// Images and gradients are the same bits with 1, 2 and 3 worker threads.
#[test]
fn results_do_not_depend_on_the_thread_count() {
    let n = 1200;
    let scene = Scene::random(13, n);
    let mut rng = SplitMix64::new(14);
    let channels: Vec<f32> = (0..4 * n).map(|_| rng.uniform(0.0, 1.0)).collect();
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let prepared = prepare_view(&camera(), &scene.view(&[], 0), &settings()).unwrap();
            prepared.contributing();
            let out =
                render_prepared(&mut RasterWorkspace::default(), prepared, &channels, 4).unwrap();
            let grads = backward(&scene, &channels, &out);
            (out, grads)
        })
    };
    let (out1, grads1) = run(1);
    for threads in [2, 3] {
        let (out, grads) = run(threads);
        assert_eq!(bits(&out.color), bits(&out1.color), "{threads} threads");
        assert_eq!(bits(&out.alpha), bits(&out1.alpha), "{threads} threads");
        assert_eq!(bits(&out.depth), bits(&out1.depth), "{threads} threads");
        assert_same_grads(&grads, &grads1);
    }
}

/// The band-wise copy puts every tile-major value at its pixel, ragged edge tiles and
/// zero channels included.
#[test]
fn untile_puts_each_tile_pixel_at_its_image_pixel() {
    for (w, h, nc) in [(37u32, 21u32, 3usize), (32, 16, 1), (5, 40, 0)] {
        let grid = TileGrid::new(w, h);
        let color_chunk = TILE_PIXELS * nc.max(1);
        let n_tiles = grid.n_tiles();
        let value = |i: usize| i as f32 * 0.25 + 1.0;
        let color: Vec<f32> = (0..n_tiles * color_chunk).map(value).collect();
        let depth: Vec<f32> = (0..n_tiles * TILE_PIXELS).map(|i| -value(i)).collect();
        let trans: Vec<f32> = (0..n_tiles * TILE_PIXELS).map(|i| 1.0 / value(i)).collect();
        let (wu, hu) = (w as usize, h as usize);
        let mut img_color = vec![f32::NAN; wu * hu * nc];
        let mut img_alpha = vec![f32::NAN; wu * hu];
        let mut img_depth = vec![f32::NAN; wu * hu];
        untile(
            &grid,
            nc,
            TileMajor {
                color: &color,
                color_chunk,
                depth: &depth,
                transmittance: &trans,
            },
            &mut img_color,
            &mut img_alpha,
            &mut img_depth,
        );
        let tile_px = TILE_PX as usize;
        for y in 0..hu {
            for x in 0..wu {
                let t = (y / tile_px) * grid.tiles_x as usize + x / tile_px;
                let p = (y % tile_px) * tile_px + x % tile_px;
                let q = t * TILE_PIXELS + p;
                let at = y * wu + x;
                assert_eq!(img_alpha[at].to_bits(), (1.0 - trans[q]).to_bits());
                assert_eq!(img_depth[at].to_bits(), depth[q].to_bits());
                for c in 0..nc {
                    let src = color[t * color_chunk + p * nc + c];
                    assert_eq!(img_color[at * nc + c].to_bits(), src.to_bits());
                }
            }
        }
    }
}

#[test]
fn prepared_render_rejects_bad_channels() {
    let n = 200;
    let scene = Scene::random(7, n);
    let prepare = || prepare_view(&camera(), &scene.view(&[], 0), &settings()).unwrap();
    let mut ws = RasterWorkspace::default();
    let short = vec![0.5f32; 4 * n - 1];
    assert!(matches!(
        render_prepared(&mut ws, prepare(), &short, 4),
        Err(RasterError::Length { .. })
    ));
    let prepared = prepare();
    let g = prepared.survived().iter().position(|&v| v).unwrap();
    let mut channels = vec![0.5f32; 4 * n];
    channels[4 * g + 2] = f32::NAN;
    assert_eq!(
        render_prepared(&mut ws, prepared, &channels, 4).unwrap_err(),
        RasterError::NonFiniteChannel { gaussian: g }
    );
    // Background of the wrong length is still an error.
    let three = vec![0.5f32; 3 * n];
    assert!(matches!(
        render_prepared(&mut ws, prepare(), &three, 3),
        Err(RasterError::Length { .. })
    ));
}

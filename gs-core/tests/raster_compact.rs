//! The compacted tile lists (`PreparedView::contributing` keeps, per tile, only the
//! entries that are blended into or stop some pixel of that tile; `render_prepared` and
//! the backward then walk those) against the full lists of `render_with`:
//!
//! - the image, alpha, depth, radii and visible set are the same bits;
//! - every gradient group (means, scales, rotations, opacities, channels, the NDC mean
//!   gradient, the dropped count) is the same bits, with colour, alpha and depth losses;
//! - on scenes where most entries change nothing (faint Gaussians below the 1/255 cutoff
//!   at every pixel centre, Gaussians hidden behind an opaque wall), so the compacted
//!   lists are much shorter; with early termination on and off, smooth mode, a
//!   background, and a tile selection (`blend_tiles`).

use glam::Vec3;
use gs_core::camera::{Camera, Intrinsics};
use gs_core::init::SplitMix64;
use gs_core::raster::bin::TileSelection;
use gs_core::raster::{
    prepare_view, render_backward, render_prepared, render_with, GaussianGrads, GaussianView,
    PixelGrads, RasterSettings, RasterWorkspace, RenderOutput,
};

const NC: usize = 3;
const WIDTH: u32 = 96;
const HEIGHT: u32 = 80;

#[derive(Clone, Default)]
struct Gaussians {
    means: Vec<f32>,
    log_scales: Vec<f32>,
    rotations: Vec<f32>,
    opacity_logits: Vec<f32>,
    channels: Vec<f32>,
}

impl Gaussians {
    fn view(&self) -> GaussianView<'_> {
        GaussianView {
            means: &self.means,
            log_scales: &self.log_scales,
            rotations: &self.rotations,
            opacity_logits: &self.opacity_logits,
            channels: &self.channels,
            n_channels: NC,
        }
    }

    /// Adds a Gaussian with its centre given in the camera frame.
    fn push(
        &mut self,
        rng: &mut SplitMix64,
        camera: &Camera,
        centre_cam: Vec3,
        sigma_m: f32,
        opacity_logit: f32,
    ) {
        let world = camera.rotation.conjugate() * (centre_cam - camera.translation);
        self.means.extend(world.to_array());
        for _ in 0..3 {
            self.log_scales.push((sigma_m * rng.uniform(0.5, 1.5)).ln());
        }
        for _ in 0..4 {
            self.rotations.push(rng.uniform(-1.0, 1.0));
        }
        self.opacity_logits.push(opacity_logit);
        for _ in 0..NC {
            self.channels.push(rng.uniform(0.0, 1.0));
        }
    }
}

fn camera() -> Camera {
    let k = Intrinsics::from_fov_x(1.0, WIDTH, HEIGHT);
    Camera::look_at(
        k,
        Vec3::new(0.2, -0.1, -5.0),
        Vec3::ZERO,
        Vec3::new(0.0, 1.0, 0.0),
    )
}

/// A dense cluster (many Gaussians behind others), an opaque wall in front of the left
/// half (everything behind it hidden once the pixels stop), and faint Gaussians (opacity
/// about 0.5 %, so their alpha passes 1/255 near the centre only, or nowhere when tiny).
fn scene(seed: u64, camera: &Camera) -> Gaussians {
    let mut rng = SplitMix64::new(seed);
    let mut g = Gaussians::default();
    // tan(fov_x / 2) = 0.546; the image spans |x/z| < 0.546, |y/z| < 0.455.
    for _ in 0..900 {
        let z = rng.uniform(4.0, 7.0);
        let c = Vec3::new(rng.uniform(-0.5, 0.5) * z, rng.uniform(-0.4, 0.4) * z, z);
        let sigma = rng.uniform(0.03, 0.3);
        let logit = rng.uniform(-1.0, 4.0);
        g.push(&mut rng, camera, c, sigma, logit);
    }
    for _ in 0..150 {
        let z = rng.uniform(2.5, 3.0);
        let c = Vec3::new(rng.uniform(-1.4, 0.0), rng.uniform(-1.2, 1.2), z);
        g.push(&mut rng, camera, c, 0.25, 6.0);
    }
    for _ in 0..600 {
        let z = rng.uniform(1.5, 8.0);
        let c = Vec3::new(rng.uniform(-0.5, 0.5) * z, rng.uniform(-0.4, 0.4) * z, z);
        let sigma = if rng.uniform(0.0, 1.0) < 0.5 {
            rng.uniform(0.002, 0.01)
        } else {
            rng.uniform(0.05, 0.3)
        };
        let logit = rng.uniform(-5.6, -5.0);
        g.push(&mut rng, camera, c, sigma, logit);
    }
    g
}

fn pixel_weights(rng: &mut SplitMix64, pixels: usize) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    let mut draw = |n: usize| -> Vec<f32> { (0..n).map(|_| rng.uniform(-1.0, 1.0)).collect() };
    (draw(pixels * NC), draw(pixels), draw(pixels))
}

/// Same bits everywhere; the message names the first difference only.
fn assert_bits_eq(a: &[f32], b: &[f32], what: &str) {
    assert_eq!(a.len(), b.len(), "{what}: lengths");
    if let Some(i) = (0..a.len()).find(|&i| a[i].to_bits() != b[i].to_bits()) {
        panic!("{what}: first difference at {i}: {} vs {}", a[i], b[i]);
    }
}

fn assert_same_render(a: &RenderOutput, b: &RenderOutput, what: &str) {
    assert_bits_eq(&a.color, &b.color, &format!("{what}: color"));
    assert_bits_eq(&a.alpha, &b.alpha, &format!("{what}: alpha"));
    assert_bits_eq(&a.depth, &b.depth, &format!("{what}: depth"));
    assert_bits_eq(&a.radii_px, &b.radii_px, &format!("{what}: radii"));
    assert_eq!(a.visible, b.visible, "{what}: visible");
    assert_eq!(
        a.tile_entry_count(),
        b.tile_entry_count(),
        "{what}: entries"
    );
}

fn assert_same_grads(a: &GaussianGrads, b: &GaussianGrads, what: &str) {
    assert_bits_eq(&a.d_means, &b.d_means, &format!("{what}: d_means"));
    assert_bits_eq(
        &a.d_log_scales,
        &b.d_log_scales,
        &format!("{what}: d_log_scales"),
    );
    assert_bits_eq(&a.d_rotations, &b.d_rotations, &format!("{what}: d_rot"));
    assert_bits_eq(
        &a.d_opacity_logits,
        &b.d_opacity_logits,
        &format!("{what}: d_opacity_logits"),
    );
    assert_bits_eq(&a.d_channels, &b.d_channels, &format!("{what}: d_channels"));
    assert_bits_eq(
        &a.mean2d_grad_ndc,
        &b.mean2d_grad_ndc,
        &format!("{what}: mean2d_grad_ndc"),
    );
    assert_eq!(a.dropped_nonfinite, b.dropped_nonfinite, "{what}: dropped");
}

fn backward(
    camera: &Camera,
    g: &Gaussians,
    settings: &RasterSettings,
    out: &RenderOutput,
    weights: &(Vec<f32>, Vec<f32>, Vec<f32>),
) -> GaussianGrads {
    render_backward(
        camera,
        &g.view(),
        settings,
        out,
        &PixelGrads {
            d_color: &weights.0,
            d_alpha: Some(&weights.1),
            d_depth: Some(&weights.2),
        },
    )
    .unwrap()
}

/// Left half of the image as the mask, for a tile selection.
fn left_half_selection() -> TileSelection {
    let mask: Vec<f32> = (0..WIDTH * HEIGHT)
        .map(|i| if i % WIDTH < WIDTH / 2 { 1.0 } else { 0.0 })
        .collect();
    TileSelection::from_mask(&mask, WIDTH, HEIGHT, 5).unwrap()
}

#[test]
fn compacted_lists_give_the_same_image_and_gradients() {
    let cam = camera();
    let pixels = (WIDTH * HEIGHT) as usize;
    for seed in [11u64, 12] {
        let g = scene(seed, &cam);
        let mut rng = SplitMix64::new(seed ^ 0x5a5a);
        let weights = pixel_weights(&mut rng, pixels);
        let background: Vec<f32> = (0..NC).map(|_| rng.uniform(0.0, 1.0)).collect();
        for early_termination in [true, false] {
            for smooth_cutoff in [false, true] {
                for blend_tiles in [None, Some(left_half_selection())] {
                    let settings = RasterSettings {
                        near_m: 0.2,
                        background: background.clone(),
                        smooth_cutoff,
                        early_termination,
                        blend_tiles: blend_tiles.clone(),
                        ..RasterSettings::default()
                    };
                    let what = format!(
                        "seed {seed}, early termination {early_termination}, smooth \
                         {smooth_cutoff}, tile selection {}",
                        blend_tiles.is_some()
                    );
                    let full =
                        render_with(&mut RasterWorkspace::default(), &cam, &g.view(), &settings)
                            .unwrap();
                    let full_grads = backward(&cam, &g, &settings, &full, &weights);
                    assert_eq!(full.blended_entry_count(), full.tile_entry_count());

                    let prepared = prepare_view(&cam, &g.view(), &settings).unwrap();
                    let contributing = prepared.contributing();
                    // A second call gives the same set (the lists are built once).
                    assert_eq!(prepared.contributing(), contributing, "{what}");
                    let compact =
                        render_prepared(&mut RasterWorkspace::default(), prepared, &g.channels, NC)
                            .unwrap();
                    let compact_grads = backward(&cam, &g, &settings, &compact, &weights);

                    assert_same_render(&full, &compact, &what);
                    assert_same_grads(&full_grads, &compact_grads, &what);
                    // The comparison means something only when many entries were dropped
                    // (hard mode; smooth mode never stops a pixel but still drops the
                    // entries below the cutoff everywhere).
                    let (all, kept) = (compact.tile_entry_count(), compact.blended_entry_count());
                    let limit = if smooth_cutoff || !early_termination {
                        0.9
                    } else {
                        0.6
                    };
                    assert!(
                        (kept as f64) < limit * all as f64,
                        "{what}: {kept} of {all} entries kept"
                    );
                    // Gaussians that are not contributing get exactly zero gradients.
                    let n = contributing.len();
                    let silent = (0..n).filter(|&i| !contributing[i]).collect::<Vec<_>>();
                    if !smooth_cutoff {
                        assert!(silent.len() > n / 10, "{what}: {} silent", silent.len());
                    }
                    for &i in &silent {
                        assert!(
                            compact_grads.d_channels[i * NC..i * NC + NC]
                                .iter()
                                .all(|&v| v == 0.0),
                            "{what}: Gaussian {i}"
                        );
                    }
                }
            }
        }
    }
}

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

mod common;

use common::{assert_bits_eq, assert_same_grads, backward, pixel_weights, Gaussians};
use glam::Vec3;
use gs_core::camera::{Camera, Intrinsics};
use gs_core::init::SplitMix64;
use gs_core::raster::bin::TileSelection;
use gs_core::raster::{
    prepare_view, render_prepared, render_with, RasterSettings, RasterWorkspace, RenderOutput,
};

const NC: usize = 3;
const WIDTH: u32 = 96;
const HEIGHT: u32 = 80;

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
    let mut g = Gaussians::new(NC);
    // tan(fov_x / 2) = 0.546; the image spans |x/z| < 0.546, |y/z| < 0.455.
    for _ in 0..900 {
        let z = rng.uniform(4.0, 7.0);
        let c = Vec3::new(rng.uniform(-0.5, 0.5) * z, rng.uniform(-0.4, 0.4) * z, z);
        let sigma = rng.uniform(0.03, 0.3);
        let logit = rng.uniform(-1.0, 4.0);
        g.push_in_camera(&mut rng, camera, c, sigma, |_| logit);
    }
    for _ in 0..150 {
        let z = rng.uniform(2.5, 3.0);
        let c = Vec3::new(rng.uniform(-1.4, 0.0), rng.uniform(-1.2, 1.2), z);
        g.push_in_camera(&mut rng, camera, c, 0.25, |_| 6.0);
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
        g.push_in_camera(&mut rng, camera, c, sigma, |_| logit);
    }
    g
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
        let weights = pixel_weights(&mut rng, pixels, NC);
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

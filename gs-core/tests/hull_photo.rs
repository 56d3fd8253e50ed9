//! Photo-consistent hull points (`carve_photo_consistent`) on a textured square plate seen
//! from a narrow cone of views, the geometry that makes a visual hull fat: the silhouettes
//! leave a thick slab around the plate, and only the colours tell where in it the plate is.
//! Images are rendered by casting each pixel centre's ray onto the plate (as the simulator
//! renders); checked: the photo-consistent points concentrate on the plate where volume
//! points spread through the slab, a wide weight falls back to the volume's spread, every
//! point projects onto the foreground in every view that sees it, the draw is seeded and
//! independent of the thread count, and bad input is an error. The silhouette-only start
//! (`HullSampling::Silhouette`) at low resolution: it removes the carving's margin around
//! the plate's edges, and equals `carve_silhouette_consistent`.

use glam::Vec3;
use gs_core::camera::{Camera, Intrinsics};
use gs_core::hull::{
    carve, carve_photo_consistent, carve_silhouette_consistent, ColourView, HullError, HullGrid,
    HullOptions, HullPoints, HullSampling, HullView, PhotoOptions, SILHOUETTE_SAMPLES_PER_VOXEL,
};

const SIZE_PX: u32 = 128;
/// Low-resolution images for the silhouette test: a pixel covers two voxels, as on the
/// simulated targets (160x100 images, voxels of half a pixel), so the carving's one-pixel
/// margin is several voxels wide.
const SMALL_SIZE_PX: u32 = 32;
const FOV_X_RAD: f32 = 0.9;
const DISTANCE_M: f32 = 4.0;
/// The plate: |x|, |y| <= PLATE_HALF_M in the plane z = 0.
const PLATE_HALF_M: f32 = 1.0;
/// Texture cells along each side of the plate.
const CELLS: i32 = 8;
/// Half-angle of the cone of view directions around +z.
const CONE_DEG: f32 = 20.0;
const GRID_HALF_M: f32 = 1.2;
const RESOLUTION: u32 = 40;
const POINTS: usize = 1500;

/// Four well separated colours, one per cell by a fixed hash of the cell's indices (a
/// two-colour checkerboard would let points off the plate match by parity).
fn texture(x: f32, y: f32) -> [f32; 3] {
    const PALETTE: [[f32; 3]; 4] = [
        [0.9, 0.1, 0.1],
        [0.1, 0.8, 0.2],
        [0.15, 0.2, 0.9],
        [0.9, 0.9, 0.2],
    ];
    let cell = |v: f32| ((v + PLATE_HALF_M) / (2.0 * PLATE_HALF_M) * CELLS as f32).floor() as i32;
    let (i, j) = (cell(x).clamp(0, CELLS - 1), cell(y).clamp(0, CELLS - 1));
    let hash = (i.wrapping_mul(73_856_093) ^ j.wrapping_mul(19_349_663)).unsigned_abs();
    PALETTE[(hash % 4) as usize]
}

struct View {
    camera: Camera,
    rgb: Vec<f32>,
    mask: Vec<u8>,
}

/// A camera `CONE_DEG` off +z at azimuth `azimuth_deg`, looking at the plate's centre.
fn camera_at(azimuth_deg: f32) -> Camera {
    camera_of_size(azimuth_deg, SIZE_PX)
}

fn camera_of_size(azimuth_deg: f32, size_px: u32) -> Camera {
    let (tilt, azimuth) = (CONE_DEG.to_radians(), azimuth_deg.to_radians());
    let dir = Vec3::new(
        tilt.sin() * azimuth.cos(),
        tilt.sin() * azimuth.sin(),
        tilt.cos(),
    );
    Camera::look_at(
        Intrinsics::from_fov_x(FOV_X_RAD, size_px, size_px),
        dir * DISTANCE_M,
        Vec3::ZERO,
        Vec3::Y,
    )
}

/// Ray-cast image of the plate: its texture where a pixel centre's ray meets it, black
/// background elsewhere.
fn render(camera: Camera) -> View {
    let k = camera.intrinsics;
    let mut rgb = vec![0.0f32; 3 * k.pixel_count()];
    let mut mask = vec![0u8; k.pixel_count()];
    let origin = camera.position();
    for y in 0..k.height {
        for x in 0..k.width {
            let d_cam = Vec3::new(
                (x as f32 + 0.5 - k.cx) / k.fx,
                (y as f32 + 0.5 - k.cy) / k.fy,
                1.0,
            );
            let d = camera.rotation.conjugate() * d_cam;
            let t = -origin.z / d.z;
            let hit = origin + d * t;
            if t > 0.0 && hit.x.abs() <= PLATE_HALF_M && hit.y.abs() <= PLATE_HALF_M {
                let i = (y * k.width + x) as usize;
                mask[i] = 255;
                rgb[3 * i..3 * i + 3].copy_from_slice(&texture(hit.x, hit.y));
            }
        }
    }
    View { camera, rgb, mask }
}

fn plate_views(count: usize) -> Vec<View> {
    (0..count)
        .map(|k| render(camera_at(360.0 * k as f32 / count as f32)))
        .collect()
}

fn colour_views(views: &[View]) -> Vec<ColourView<'_>> {
    views
        .iter()
        .map(|v| ColourView {
            camera: v.camera,
            rgb: &v.rgb,
            mask: &v.mask,
        })
        .collect()
}

fn grid() -> HullGrid {
    HullGrid::around_sphere(Vec3::ZERO, GRID_HALF_M, RESOLUTION)
}

fn options() -> HullOptions {
    HullOptions {
        point_count: POINTS,
        margin_px: 1,
        min_views: 1,
        seed: 7,
        sampling: HullSampling::Volume,
    }
}

fn photo(spread_width: f32) -> PhotoOptions {
    PhotoOptions {
        samples_per_voxel: 4,
        spread_width,
    }
}

/// Mean |z| and the fraction of points within two voxels of the plate's plane.
fn depth_summary(hull: &HullPoints) -> (f32, f32) {
    let n = hull.points.len() as f32;
    let mean = hull.points.iter().map(|p| p.z.abs()).sum::<f32>() / n;
    let near = hull
        .points
        .iter()
        .filter(|p| p.z.abs() <= 2.0 * hull.voxel_m)
        .count() as f32;
    (mean, near / n)
}

#[test]
fn photo_consistent_points_concentrate_on_the_plate_where_volume_points_fill_the_slab() {
    let views = plate_views(6);
    let hull_views: Vec<HullView> = views
        .iter()
        .map(|v| HullView {
            camera: v.camera,
            mask: &v.mask,
        })
        .collect();
    let volume = carve(&hull_views, grid(), options()).unwrap();
    let (volume_mean, volume_near) = depth_summary(&volume);
    // The narrow cone leaves a slab: volume points spread far above and below the plate.
    assert!(volume_mean > 0.3, "volume mean |z| {volume_mean}");
    assert!(volume_near < 0.25, "volume near fraction {volume_near}");

    let (sharp, stats) =
        carve_photo_consistent(&colour_views(&views), grid(), options(), photo(0.25)).unwrap();
    assert_eq!(sharp.points.len(), POINTS);
    assert_eq!(sharp.occupied, volume.occupied);
    assert_eq!(stats.candidates, 4 * volume.occupied);
    assert_eq!(stats.unscored, 0);
    assert!(stats.median_spread > 0.05, "{stats:?}");
    let (sharp_mean, sharp_near) = depth_summary(&sharp);
    assert!(
        sharp_mean < 0.3 * volume_mean,
        "photo mean |z| {sharp_mean} against volume {volume_mean}"
    );
    assert!(sharp_near > 0.6, "photo near fraction {sharp_near}");

    // A weight much wider than the spreads keeps no colour evidence: the points fill the
    // slab again (the silhouette test alone cannot find the plate's depth here).
    let (flat, _) =
        carve_photo_consistent(&colour_views(&views), grid(), options(), photo(1e3)).unwrap();
    let (flat_mean, flat_near) = depth_summary(&flat);
    assert!(
        flat_mean > 0.7 * volume_mean,
        "flat mean |z| {flat_mean} against volume {volume_mean}"
    );
    assert!(flat_near < 0.3, "flat near fraction {flat_near}");
}

/// Bilinear foreground at a point: used to check that points project onto the plate.
fn foreground_at(view: &View, p: Vec3) -> Option<f32> {
    let c = view.camera.world_to_camera(p);
    if c.z <= 0.0 {
        return None;
    }
    let (u, v) = view.camera.camera_to_pixel(c);
    let (x, y) = (u - 0.5, v - 0.5);
    let k = view.camera.intrinsics;
    if !(x >= 0.0 && y >= 0.0 && x <= (k.width - 1) as f32 && y <= (k.height - 1) as f32) {
        return None;
    }
    let (x0, y0) = (x.floor() as u32, y.floor() as u32);
    let (x1, y1) = ((x0 + 1).min(k.width - 1), (y0 + 1).min(k.height - 1));
    let (fx, fy) = (x - x0 as f32, y - y0 as f32);
    let m = |px: u32, py: u32| (view.mask[(py * k.width + px) as usize] >= 128) as u8 as f32;
    Some(
        m(x0, y0) * (1.0 - fx) * (1.0 - fy)
            + m(x1, y0) * fx * (1.0 - fy)
            + m(x0, y1) * (1.0 - fx) * fy
            + m(x1, y1) * fx * fy,
    )
}

#[test]
fn points_lie_on_the_silhouette_in_every_view_and_the_draw_is_seeded() {
    let views = plate_views(5);
    let run = |threads: usize, opts: HullOptions| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| {
                carve_photo_consistent(&colour_views(&views), grid(), opts, photo(0.5)).unwrap()
            })
    };
    let (one, stats) = run(1, options());
    assert_eq!((one.clone(), stats), run(3, options()));
    // The carving's one-pixel margin keeps voxels whose points fall off the plate; those
    // candidates are dropped, and every kept point is on the plate in every view.
    assert!(stats.off_silhouette > 0, "{stats:?}");
    for p in &one.points {
        for view in &views {
            if let Some(fg) = foreground_at(view, *p) {
                assert!(fg >= 0.5, "{p} on background ({fg}) in a view");
            }
        }
        assert!(p.x.abs() <= PLATE_HALF_M + 0.2 && p.y.abs() <= PLATE_HALF_M + 0.2);
    }
    for (p, n) in one.points.iter().zip(&one.normals) {
        assert!(p.is_finite() && (n.length() - 1.0).abs() < 1e-4);
    }
    let (other, _) = run(
        2,
        HullOptions {
            seed: 8,
            ..options()
        },
    );
    assert_ne!(one.points, other.points);
    // Asking for more points than candidates returns every on-silhouette candidate.
    let (all, all_stats) = run(
        2,
        HullOptions {
            point_count: usize::MAX,
            ..options()
        },
    );
    assert_eq!(
        all.points.len(),
        all_stats.candidates - all_stats.off_silhouette
    );
}

#[test]
fn bad_input_is_an_error() {
    let views = plate_views(3);
    let mut colour = colour_views(&views);
    assert_eq!(
        carve_photo_consistent(&[], grid(), options(), photo(0.5)).unwrap_err(),
        HullError::NoViews
    );
    let short = vec![0.0f32; 10];
    colour[1].rgb = &short;
    assert!(matches!(
        carve_photo_consistent(&colour, grid(), options(), photo(0.5)),
        Err(HullError::MaskSize { view: 1, .. })
    ));
    let colour = colour_views(&views);
    assert_eq!(
        carve_photo_consistent(
            &colour,
            grid(),
            HullOptions {
                point_count: 0,
                ..options()
            },
            photo(0.5)
        )
        .unwrap_err(),
        HullError::ZeroPointCount
    );
    // Empty masks carve everything away.
    let empty = vec![0u8; views[0].mask.len()];
    let blank: Vec<ColourView> = colour
        .iter()
        .map(|v| ColourView { mask: &empty, ..*v })
        .collect();
    assert!(matches!(
        carve_photo_consistent(&blank, grid(), options(), photo(0.5)),
        Err(HullError::NothingLeft { .. })
    ));
}

#[test]
fn silhouette_points_drop_the_carving_margin_around_the_plate() {
    let views: Vec<View> = (0..6)
        .map(|k| render(camera_of_size(60.0 * k as f32, SMALL_SIZE_PX)))
        .collect();
    let hull_views: Vec<HullView> = views
        .iter()
        .map(|v| HullView {
            camera: v.camera,
            mask: &v.mask,
        })
        .collect();
    let pixel_m = DISTANCE_M / views[0].camera.intrinsics.fx;
    let volume = carve(&hull_views, grid(), options()).unwrap();
    assert!(
        volume.voxel_m < 0.6 * pixel_m,
        "{} {pixel_m}",
        volume.voxel_m
    );
    let silhouette = carve(
        &hull_views,
        grid(),
        HullOptions {
            sampling: HullSampling::Silhouette,
            ..options()
        },
    )
    .unwrap();
    let (direct, stats) =
        carve_silhouette_consistent(&hull_views, grid(), options(), SILHOUETTE_SAMPLES_PER_VOXEL)
            .unwrap();
    assert_eq!(silhouette, direct);
    assert_eq!(silhouette.points.len(), POINTS);
    assert_eq!(stats.median_spread, 0.0);
    assert!(stats.off_silhouette > 0);
    // Beyond the plate's edge by more than half a pixel: the margin.
    let edge_m = PLATE_HALF_M + 0.5 * pixel_m;
    let beyond = |hull: &HullPoints| {
        hull.points
            .iter()
            .filter(|p| p.x.abs().max(p.y.abs()) > edge_m)
            .count() as f32
            / hull.points.len() as f32
    };
    let (volume_beyond, silhouette_beyond) = (beyond(&volume), beyond(&silhouette));
    assert!(
        volume_beyond > 0.05,
        "volume: {volume_beyond} beyond the edge"
    );
    assert!(
        silhouette_beyond < 0.01,
        "silhouette: {silhouette_beyond} beyond the edge"
    );
    for p in &silhouette.points {
        for view in &views {
            if let Some(fg) = foreground_at(view, *p) {
                assert!(fg >= 0.5, "{p} on background ({fg}) in a view");
            }
        }
    }
}

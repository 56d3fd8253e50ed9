//! Visual hull carving against analytic shapes: a sphere and a cube rendered into masks by
//! casting each pixel centre's ray (as the simulator renders its masks), carved, and the
//! surface points checked against the true visual hull (the intersection of the silhouette
//! cones) with bounds derived from the voxel size and the pixel size; plus abstaining views,
//! determinism across thread counts, colour sampling and bad input.

use glam::Vec3;
use gs_core::camera::{Camera, Intrinsics};
use gs_core::hull::{
    carve, sample_colours, CarvedVolume, ColourView, HullError, HullGrid, HullOptions, HullPoints,
    HullSampling, HullView,
};

const SIZE_PX: u32 = 64;
const FOV_X_RAD: f32 = 1.3;
const DISTANCE_M: f32 = 4.0;

fn intrinsics() -> Intrinsics {
    Intrinsics::from_fov_x(FOV_X_RAD, SIZE_PX, SIZE_PX)
}

/// A camera at `DISTANCE_M` along `dir` looking at the origin.
fn camera_towards_origin(dir: Vec3) -> Camera {
    let eye = dir.normalize() * DISTANCE_M;
    let up = if dir.normalize().dot(Vec3::Z).abs() > 0.9 {
        Vec3::Y
    } else {
        Vec3::Z
    };
    Camera::look_at(intrinsics(), eye, Vec3::ZERO, up)
}

/// World-frame ray (origin, unit direction) through the centre of pixel (x, y).
fn pixel_ray(camera: &Camera, x: u32, y: u32) -> (Vec3, Vec3) {
    let k = camera.intrinsics;
    let d_cam = Vec3::new(
        (x as f32 + 0.5 - k.cx) / k.fx,
        (y as f32 + 0.5 - k.cy) / k.fy,
        1.0,
    );
    let d = (camera.rotation.conjugate() * d_cam).normalize();
    (camera.position(), d)
}

fn render_mask(camera: &Camera, hit: impl Fn(Vec3, Vec3) -> bool) -> Vec<u8> {
    let k = camera.intrinsics;
    let mut mask = vec![0u8; k.pixel_count()];
    for y in 0..k.height {
        for x in 0..k.width {
            let (o, d) = pixel_ray(camera, x, y);
            if hit(o, d) {
                mask[(y * k.width + x) as usize] = 255;
            }
        }
    }
    mask
}

fn ray_hits_sphere(o: Vec3, d: Vec3, radius: f32) -> bool {
    let t = -o.dot(d);
    t > 0.0 && (o + d * t).length_squared() <= radius * radius
}

fn ray_hits_cube(o: Vec3, d: Vec3, half: f32) -> bool {
    let (mut t0, mut t1) = (0.0f32, f32::INFINITY);
    for axis in 0..3 {
        if d[axis].abs() < 1e-12 {
            if o[axis].abs() > half {
                return false;
            }
            continue;
        }
        let a = (-half - o[axis]) / d[axis];
        let b = (half - o[axis]) / d[axis];
        t0 = t0.max(a.min(b));
        t1 = t1.min(a.max(b));
    }
    t0 <= t1
}

fn directions(count: usize) -> Vec<Vec3> {
    let all = [
        Vec3::X,
        Vec3::Y,
        Vec3::Z,
        -Vec3::X,
        -Vec3::Y,
        -Vec3::Z,
        Vec3::new(1.0, 1.0, 1.0),
        Vec3::new(-1.0, 1.0, -1.0),
    ];
    all[..count].to_vec()
}

struct Scene {
    cameras: Vec<Camera>,
    masks: Vec<Vec<u8>>,
}

impl Scene {
    fn views(&self) -> Vec<HullView<'_>> {
        self.cameras
            .iter()
            .zip(&self.masks)
            .map(|(c, m)| HullView {
                camera: *c,
                mask: m,
            })
            .collect()
    }
}

fn sphere_scene(view_count: usize, radius: f32) -> Scene {
    let cameras: Vec<Camera> = directions(view_count)
        .into_iter()
        .map(camera_towards_origin)
        .collect();
    let masks = cameras
        .iter()
        .map(|c| render_mask(c, |o, d| ray_hits_sphere(o, d, radius)))
        .collect();
    Scene { cameras, masks }
}

const RADIUS_M: f32 = 1.0;
const GRID_HALF_M: f32 = 1.2;
const RESOLUTION: u32 = 48;

fn options(point_count: usize) -> HullOptions {
    HullOptions {
        point_count,
        margin_px: 1,
        min_views: 1,
        seed: 7,
        sampling: HullSampling::Shell,
    }
}

fn grid() -> HullGrid {
    HullGrid::around_sphere(Vec3::ZERO, GRID_HALF_M, RESOLUTION)
}

/// Angular slack of a surface point's cone test, radians: the voxel's half-diagonal seen
/// from the camera (the point is the voxel centre, the evidence anywhere in the voxel) plus
/// the footprint margin and the sampled mask (a foreground pixel centre lies in the
/// silhouette, the pixel reaches half a pixel further, the footprint rectangle rounds out to
/// whole pixels: (margin + 1) pixels per image axis, sqrt(2) of that diagonally); one pixel
/// subtends at most 1/f radians.
fn angular_slack_rad(point: Vec3, camera: &Camera, voxel_m: f32, margin_px: u32) -> f32 {
    let half_diagonal = 0.5 * 3f32.sqrt() * voxel_m;
    let range = (point - camera.position()).length();
    let voxel = (half_diagonal / (range - half_diagonal)).atan();
    let pixels = (margin_px as f32 + 1.0) * 2f32.sqrt() / camera.intrinsics.fx;
    voxel + pixels
}

fn check_sphere_hull(hull: &HullPoints, scene: &Scene) {
    let h = hull.voxel_m;
    assert!(hull.points.len() > 100, "{}", hull.points.len());
    assert_eq!(hull.points.len(), hull.normals.len());
    let half_angle = (RADIUS_M / DISTANCE_M).asin();
    let mut mean_cos = 0.0f64;
    for (p, n) in hull.points.iter().zip(&hull.normals) {
        // The hull contains the sphere: a surface voxel has an empty neighbour, which
        // (carving being conservative) lies wholly outside the sphere, one voxel away.
        assert!(
            p.length() > RADIUS_M - h,
            "{p} is {} inside the sphere",
            RADIUS_M - p.length()
        );
        // ... and lies within every view's silhouette cone, up to the voxel and pixel slack.
        for cam in &scene.cameras {
            let to_centre = -cam.position();
            let angle = (*p - cam.position()).angle_between(to_centre);
            let slack = angular_slack_rad(*p, cam, h, 1);
            assert!(
                angle <= half_angle + slack,
                "{p}: {angle} rad off the axis of the camera at {}, cone {half_angle} + {slack}",
                cam.position()
            );
        }
        assert!((n.length() - 1.0).abs() < 1e-5);
        // A convex body around the origin: the outward normal has a positive radial part.
        let cos = n.dot(p.normalize());
        assert!(cos > 0.0, "normal {n} at {p} points inward");
        mean_cos += cos as f64;
    }
    mean_cos /= hull.points.len() as f64;
    assert!(mean_cos > 0.8, "mean radial cosine {mean_cos}");
}

/// Radius of the true visual hull (the intersection of the silhouette cones, clipped to the
/// grid) along `dir`, by bisection: the intersection of convex sets around the origin is
/// star-shaped from it.
fn true_hull_radius(dir: Vec3, cameras: &[Camera]) -> f32 {
    let half_angle = (RADIUS_M / DISTANCE_M).asin();
    let inside = |p: Vec3| {
        p.abs().max_element() <= GRID_HALF_M
            && cameras
                .iter()
                .all(|c| (p - c.position()).angle_between(-c.position()) <= half_angle)
    };
    let (mut lo, mut hi) = (0.0f32, 3.0 * GRID_HALF_M);
    for _ in 0..40 {
        let mid = 0.5 * (lo + hi);
        if inside(dir * mid) {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    lo
}

#[test]
fn sphere_from_three_and_six_views_is_bounded_by_its_cones() {
    let mut max_radius = Vec::new();
    let mut occupied = Vec::new();
    for view_count in [3, 6] {
        let scene = sphere_scene(view_count, RADIUS_M);
        let hull = carve(&scene.views(), grid(), options(usize::MAX)).unwrap();
        check_sphere_hull(&hull, &scene);
        let radius = hull
            .points
            .iter()
            .map(|p| p.length())
            .fold(0.0f32, f32::max);
        // The carved hull contains the true one, so it reaches at least as far (less half
        // a voxel diagonal: points are voxel centres) in every sampled direction.
        let golden = std::f32::consts::PI * (3.0 - 5f32.sqrt());
        let true_max = (0..2000)
            .map(|i| {
                let z = 1.0 - 2.0 * (i as f32 + 0.5) / 2000.0;
                let r = (1.0 - z * z).sqrt();
                let phi = golden * i as f32;
                true_hull_radius(Vec3::new(r * phi.cos(), r * phi.sin(), z), &scene.cameras)
            })
            .fold(0.0f32, f32::max);
        assert!(
            radius >= true_max - 0.5 * 3f32.sqrt() * hull.voxel_m,
            "{view_count} views: carved hull reaches {radius}, the true one {true_max}"
        );
        max_radius.push(radius);
        occupied.push(hull.occupied);
    }
    // More views carve more: the six-view hull is inside the three-view one.
    assert!(occupied[1] < occupied[0], "{occupied:?}");
    assert!(max_radius[1] < max_radius[0], "{max_radius:?}");
}

#[test]
fn cube_hull_contains_the_cube_and_stays_in_its_silhouettes() {
    let half = 0.8f32;
    let cameras: Vec<Camera> = directions(6)
        .into_iter()
        .map(camera_towards_origin)
        .collect();
    let masks: Vec<Vec<u8>> = cameras
        .iter()
        .map(|c| render_mask(c, |o, d| ray_hits_cube(o, d, half)))
        .collect();
    let scene = Scene { cameras, masks };
    let hull = carve(&scene.views(), grid(), options(usize::MAX)).unwrap();
    let h = hull.voxel_m;
    let mut axis_aligned_normals = 0;
    for (p, n) in hull.points.iter().zip(&hull.normals) {
        assert!(p.abs().max_element() > half - h, "{p} inside the cube");
        for cam in &scene.cameras {
            // The silhouette of a face-on cube is the bounding rectangle of its corners.
            let (mut lo, mut hi) = ([f32::MAX; 2], [f32::MIN; 2]);
            for c in 0..8 {
                let corner = Vec3::new(
                    if c & 1 == 0 { -half } else { half },
                    if c & 2 == 0 { -half } else { half },
                    if c & 4 == 0 { -half } else { half },
                );
                let (u, v) = cam.camera_to_pixel(cam.world_to_camera(corner));
                lo = [lo[0].min(u), lo[1].min(v)];
                hi = [hi[0].max(u), hi[1].max(v)];
            }
            let depth = cam.world_to_camera(*p).z;
            let half_diagonal = 0.5 * 3f32.sqrt() * h;
            let slack_px = cam.intrinsics.fx * half_diagonal / (depth - half_diagonal) + 2.0;
            let (u, v) = cam.camera_to_pixel(cam.world_to_camera(*p));
            assert!(
                u >= lo[0] - slack_px
                    && u <= hi[0] + slack_px
                    && v >= lo[1] - slack_px
                    && v <= hi[1] + slack_px,
                "{p} projects to ({u}, {v}), outside {lo:?}..{hi:?} + {slack_px}"
            );
        }
        assert!(n.dot(*p) > 0.0, "normal {n} at {p} points inward");
        // Away from the hull's edges (where two coordinates are within two voxels), the
        // normal points along the axis and side of the point's largest coordinate: the
        // hull of a cube from its six face-on views is the cube with shallow roofs on its
        // faces (each side view's pyramid widens behind its near face by a / (d - a)).
        let mut order = [0usize, 1, 2];
        order.sort_by(|&i, &j| p[j].abs().total_cmp(&p[i].abs()));
        if p[order[0]].abs() - p[order[1]].abs() >= 2.0 * h {
            let axis = order[0];
            let normal_axis = (0..3)
                .max_by(|&i, &j| n[i].abs().total_cmp(&n[j].abs()))
                .unwrap();
            assert_eq!(normal_axis, axis, "normal {n} at {p}");
            assert_eq!(n[axis].signum(), p[axis].signum(), "normal {n} at {p}");
            axis_aligned_normals += 1;
        }
    }
    // The faces are most of the surface.
    assert!(
        axis_aligned_normals * 2 > hull.points.len(),
        "{axis_aligned_normals} of {}",
        hull.points.len()
    );
}

#[test]
fn views_that_do_not_see_the_box_remove_nothing() {
    let scene = sphere_scene(3, RADIUS_M);
    let reference = carve(&scene.views(), grid(), options(usize::MAX)).unwrap();
    // Looking away from the box (it is behind the camera), and looking past it (it is
    // outside the image): both masks are empty, so a vote would carve everything.
    let away = Camera::look_at(intrinsics(), Vec3::X * 4.0, Vec3::X * 10.0, Vec3::Z);
    let past = Camera::look_at(
        intrinsics(),
        Vec3::Y * 4.0,
        Vec3::new(20.0, 4.0, 0.0),
        Vec3::Z,
    );
    let empty = vec![0u8; intrinsics().pixel_count()];
    let mut views = scene.views();
    views.push(HullView {
        camera: away,
        mask: &empty,
    });
    views.push(HullView {
        camera: past,
        mask: &empty,
    });
    let with_blind = carve(&views, grid(), options(usize::MAX)).unwrap();
    assert_eq!(with_blind, reference);
    // A view that does see the box with an empty mask carves everything: a clear error.
    let seeing = HullView {
        camera: scene.cameras[0],
        mask: &empty,
    };
    assert!(matches!(
        carve(&[seeing], grid(), options(10)),
        Err(HullError::NothingLeft { .. })
    ));
}

#[test]
fn results_do_not_depend_on_the_thread_count_and_subsampling_is_a_seeded_subset() {
    let scene = sphere_scene(4, RADIUS_M);
    let run = |threads: usize, opts: HullOptions| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| carve(&scene.views(), grid(), opts).unwrap())
    };
    let one = run(1, options(800));
    let three = run(3, options(800));
    assert_eq!(one, three);
    assert_eq!(one.points.len(), 800);
    let all = run(3, options(usize::MAX));
    assert_eq!(all.points.len(), all.surface);
    assert_eq!(one.surface, all.surface);
    // The subsample is a subset of the full surface, same normals, in the same order.
    let mut k = 0;
    for (p, n) in one.points.iter().zip(&one.normals) {
        while all.points[k] != *p {
            k += 1;
        }
        assert_eq!(all.normals[k], *n);
    }
    let other_seed = run(
        2,
        HullOptions {
            seed: 8,
            ..options(800)
        },
    );
    assert_ne!(other_seed.points, one.points);
}

#[test]
fn colours_come_from_the_most_frontal_view() {
    let scene = sphere_scene(6, RADIUS_M);
    let hull = carve(&scene.views(), grid(), options(2000)).unwrap();
    // Each view paints a flat colour of its own: view i has red = i / 10.
    let images: Vec<Vec<f32>> = (0..6)
        .map(|i| {
            [i as f32 / 10.0, 0.5, 0.25]
                .repeat(intrinsics().pixel_count())
                .clone()
        })
        .collect();
    let views: Vec<ColourView> = (0..6)
        .map(|i| ColourView {
            camera: scene.cameras[i],
            rgb: &images[i],
            mask: &scene.masks[i],
        })
        .collect();
    let (colours, missing) = sample_colours(&hull.points, &hull.normals, &views, [0.5; 3]);
    assert_eq!(missing, 0);
    for ((p, n), c) in hull.points.iter().zip(&hull.normals).zip(&colours) {
        // Views where the point lands on the target's mask compete; the hull bulges past
        // the sphere, so a hull point can fall outside some silhouettes.
        let cosines: Vec<f32> = scene
            .cameras
            .iter()
            .zip(&scene.masks)
            .map(|(cam, mask)| {
                let (u, v) = cam.camera_to_pixel(cam.world_to_camera(*p));
                let pixel = v as usize * SIZE_PX as usize + u as usize;
                if mask[pixel] >= 128 {
                    n.dot((cam.position() - *p).normalize())
                } else {
                    f32::NEG_INFINITY
                }
            })
            .collect();
        // The first of equally frontal views wins, as in the sampler.
        let best = (1..6).fold(0, |b, i| if cosines[i] > cosines[b] { i } else { b });
        assert_eq!(c[0], best as f32 / 10.0, "{p} {n} {cosines:?}");
    }
    // A point outside every silhouette (off each cone by 0.3-0.55 rad) gets the fallback,
    // counted.
    let (c, missing) = sample_colours(&[Vec3::splat(1.2)], &[Vec3::Z], &views, [0.5; 3]);
    assert_eq!((c, missing), (vec![[0.5; 3]], 1));
}

#[test]
fn bad_input_is_a_clear_error() {
    let scene = sphere_scene(3, RADIUS_M);
    let views = scene.views();
    assert_eq!(
        carve(&[], grid(), options(10)).unwrap_err(),
        HullError::NoViews
    );
    let short = vec![255u8; 10];
    let bad_mask = HullView {
        camera: scene.cameras[1],
        mask: &short,
    };
    let err = carve(&[views[0], bad_mask], grid(), options(10)).unwrap_err();
    assert_eq!(
        err,
        HullError::MaskSize {
            view: 1,
            expected: (SIZE_PX * SIZE_PX) as usize,
            got: 10
        }
    );
    assert!(err.to_string().contains("view 1"));
    let zero = HullGrid {
        voxels_along_longest: 0,
        ..grid()
    };
    assert_eq!(
        carve(&views, zero, options(10)).unwrap_err(),
        HullError::ZeroResolution
    );
    for (min_m, max_m) in [
        (Vec3::ONE, Vec3::ZERO),
        (Vec3::new(f32::NAN, 0.0, 0.0), Vec3::ONE),
        (Vec3::ZERO, Vec3::new(1.0, 1.0, 0.0)),
    ] {
        let g = HullGrid {
            min_m,
            max_m,
            voxels_along_longest: 8,
        };
        assert!(matches!(
            carve(&views, g, options(10)),
            Err(HullError::InvalidBox { .. })
        ));
    }
    let huge = HullGrid {
        voxels_along_longest: 100_000,
        ..grid()
    };
    assert!(matches!(
        carve(&views, huge, options(10)),
        Err(HullError::TooManyVoxels { .. })
    ));
    assert_eq!(
        carve(&views, grid(), options(0)).unwrap_err(),
        HullError::ZeroPointCount
    );
    let mut broken = scene.cameras[0];
    broken.translation.x = f32::NAN;
    let err = carve(
        &[HullView {
            camera: broken,
            mask: &scene.masks[0],
        }],
        grid(),
        options(10),
    )
    .unwrap_err();
    assert_eq!(err, HullError::BadCamera { view: 0 });
}

/// Carving one view at a time into a [`CarvedVolume`] is the one-shot carve where voxels no
/// view votes on survive (`min_views: 0`), in either order.
#[test]
fn carving_view_by_view_equals_one_shot_carving_in_any_order() {
    let scene = sphere_scene(6, RADIUS_M);
    let one_shot = carve(
        &scene.views(),
        grid(),
        HullOptions {
            min_views: 0,
            ..options(usize::MAX)
        },
    )
    .unwrap();
    let mut forward = CarvedVolume::new(grid()).unwrap();
    let total = forward.occupied();
    let mut removed = 0;
    for view in scene.views() {
        removed += forward.carve(&view, 1).unwrap();
    }
    assert_eq!(forward.views(), 6);
    assert_eq!(forward.occupancy(), &one_shot.occupancy[..]);
    assert_eq!(forward.occupied(), one_shot.occupied);
    assert_eq!(total - removed, one_shot.occupied);
    let mut backward = CarvedVolume::new(grid()).unwrap();
    for view in scene.views().iter().rev() {
        backward.carve(view, 1).unwrap();
    }
    assert_eq!(backward.occupancy(), forward.occupancy());
    // Carving again with a view already used removes nothing.
    assert_eq!(forward.carve(&scene.views()[2], 1).unwrap(), 0);
}

/// A thin plate (|x| <= 0.05 m, |y|, |z| <= 0.5 m) seen only from near +x carves to a thick
/// slab; one view from the side removes the phantom slab and nothing of the plate.
#[test]
fn a_side_view_carves_away_the_phantom_volume_and_never_the_object() {
    let half = Vec3::new(0.05, 0.5, 0.5);
    let hits_plate = |o: Vec3, d: Vec3| ray_hits_cube(o / half, d / half, 1.0);
    let front: Vec<Camera> = [
        Vec3::new(1.0, 0.2, 0.0),
        Vec3::new(1.0, -0.2, 0.1),
        Vec3::new(1.0, 0.0, -0.2),
    ]
    .into_iter()
    .map(camera_towards_origin)
    .collect();
    let side = camera_towards_origin(Vec3::Y);
    let front_masks: Vec<Vec<u8>> = front.iter().map(|c| render_mask(c, hits_plate)).collect();
    let side_mask = render_mask(&side, hits_plate);
    let mut volume = CarvedVolume::new(grid()).unwrap();
    for (camera, mask) in front.iter().zip(&front_masks) {
        volume
            .carve(
                &HullView {
                    camera: *camera,
                    mask,
                },
                1,
            )
            .unwrap();
    }
    let voxel_m = volume.voxel_m();
    // Points on the plate's faces, edges included.
    let mut on_plate = Vec::new();
    for i in 0..=20 {
        for j in 0..=20 {
            let (u, v) = (i as f32 / 10.0 - 1.0, j as f32 / 10.0 - 1.0);
            on_plate.push(Vec3::new(1.0, u, v) * half);
            on_plate.push(Vec3::new(-1.0, u, v) * half);
            on_plate.push(Vec3::new(u, 1.0, v) * half);
            on_plate.push(Vec3::new(u, v, 1.0) * half);
        }
    }
    // In front of and behind the plate, along x: inside the three front views' cones.
    let phantom = [Vec3::new(0.3, 0.0, 0.0), Vec3::new(-0.3, 0.1, 0.1)];
    for p in phantom {
        assert!(volume.contains(p, 0), "{p} carved by the front views alone");
    }
    let before = volume.occupied();
    volume
        .carve(
            &HullView {
                camera: side,
                mask: &side_mask,
            },
            1,
        )
        .unwrap();
    assert!(
        volume.occupied() < before / 2,
        "{} of {before}",
        volume.occupied()
    );
    for p in &on_plate {
        assert!(volume.contains(*p, 0), "plate point {p} carved");
    }
    for p in phantom {
        assert!(!volume.contains(p, 1), "{p} survives the side view");
    }
    // Every occupied voxel is within the side view's silhouette up to voxel and pixel
    // slack: its centre lies within |x| <= 0.05 m plus the slack (the side camera looks
    // along -y, so x is an image axis at range about DISTANCE_M - y).
    let dims = volume.dims();
    let grid_min = Vec3::splat(-GRID_HALF_M);
    for (i, &o) in volume.occupancy().iter().enumerate() {
        if o == 0 {
            continue;
        }
        let (x, y, z) = (
            i % dims[0],
            (i / dims[0]) % dims[1],
            i / (dims[0] * dims[1]),
        );
        let centre = grid_min + (Vec3::new(x as f32, y as f32, z as f32) + 0.5) * voxel_m;
        let slack = angular_slack_rad(centre, &side, voxel_m, 1);
        let range = DISTANCE_M - centre.y;
        let bound = (half.x / (DISTANCE_M - half.y)).atan() + slack;
        assert!(
            (centre.x / range).atan().abs() <= bound + 1e-4,
            "voxel at {centre} outside the side silhouette"
        );
    }
}

#[test]
fn contains_is_false_outside_the_grid_and_for_non_finite_points() {
    let mut volume = CarvedVolume::new(grid()).unwrap();
    assert!(volume.contains(Vec3::ZERO, 0));
    assert!(!volume.contains(Vec3::splat(GRID_HALF_M + 0.5), 0));
    assert!(!volume.contains(Vec3::new(f32::NAN, 0.0, 0.0), 1));
    assert!(!volume.contains(Vec3::splat(f32::INFINITY), 1));
    // A bad view is an error and changes nothing.
    let scene = sphere_scene(1, RADIUS_M);
    let short = [0u8; 10];
    let err = volume.carve(
        &HullView {
            camera: scene.cameras[0],
            mask: &short,
        },
        1,
    );
    assert!(matches!(err, Err(HullError::MaskSize { .. })));
    assert_eq!(volume.occupied(), volume.occupancy().len());
    assert_eq!(volume.views(), 0);
    // Dilation reaches exactly the requested number of voxels.
    volume.carve(&scene.views()[0], 1).unwrap();
    let h = volume.voxel_m();
    let outside = Vec3::new(0.0, 0.0, RADIUS_M + 4.5 * h);
    let nearest_occupied = (0..40)
        .map(|k| outside - Vec3::Z * (k as f32 * 0.25 * h))
        .find(|p| volume.contains(*p, 0))
        .unwrap();
    let gap_voxels = ((outside.z - nearest_occupied.z) / h).floor() as u32;
    assert!(gap_voxels >= 1);
    assert!(!volume.contains(outside, gap_voxels.saturating_sub(1)));
    assert!(volume.contains(outside, gap_voxels + 1));
}

/// Volume sampling: points lie in occupied voxels (anywhere inside them, not only at the
/// centres), reach deep inside the hull, and are seeded and thread-count independent.
#[test]
fn volume_sampling_fills_the_hull() {
    let scene = sphere_scene(6, RADIUS_M);
    let volume_options = HullOptions {
        sampling: HullSampling::Volume,
        ..options(3000)
    };
    let run = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| carve(&scene.views(), grid(), volume_options).unwrap())
    };
    let hull = run(1);
    assert_eq!(hull, run(3));
    assert_eq!(hull.points.len(), 3000);
    let mut volume = CarvedVolume::new(grid()).unwrap();
    for view in scene.views() {
        volume.carve(&view, 1).unwrap();
    }
    let h = hull.voxel_m;
    let mut off_centre = 0;
    let mut deep = 0;
    for p in &hull.points {
        assert!(volume.contains(*p, 0), "{p} outside the carved voxels");
        let cell = (*p + Vec3::splat(GRID_HALF_M)) / h;
        let from_centre = cell - cell.floor() - Vec3::splat(0.5);
        if from_centre.abs().max_element() > 0.1 {
            off_centre += 1;
        }
        if p.length() < 0.5 * RADIUS_M {
            deep += 1;
        }
    }
    // Uniform over the hull (at least the unit ball): about 1/8 of the points lie within
    // half the radius, and nearly all points sit away from their voxel's centre.
    assert!(deep > 3000 / 16, "{deep} points deep inside");
    assert!(
        off_centre > 2500,
        "{off_centre} points off their voxel centre"
    );
    let shell = carve(&scene.views(), grid(), options(3000)).unwrap();
    assert!(shell.points.iter().all(|p| p.length() > RADIUS_M - h));
    let other = carve(
        &scene.views(),
        grid(),
        HullOptions {
            seed: 99,
            ..volume_options
        },
    )
    .unwrap();
    assert_ne!(other.points, hull.points);
}

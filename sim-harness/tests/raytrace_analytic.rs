//! The ray tracer against analytic cases: a lit plane's radiance against the BRDF formula written
//! out by hand, a floating box's shadow outline and area on a plate, darkness in eclipse, a
//! rotated box's silhouette and depth, determinism across runs and thread counts.

use glam::{Quat, Vec3};
use sim_harness::raytrace::{
    camera_pose_looking_at, linear_to_srgb8, render_frame, render_radiance, try_render_frame,
    EarthFill, FrameRequest, PinholeCamera, Scene, SUN_IRRADIANCE,
};
use sim_harness::target::{builtin_target, BuiltinTarget, Material, MeshBuilder, TargetMesh};
use std::f32::consts::PI;

fn camera(width: u32, height: u32, f: f32) -> PinholeCamera {
    PinholeCamera {
        fx: f,
        fy: f,
        cx: width as f32 / 2.0,
        cy: height as f32 / 2.0,
        width,
        height,
    }
}

fn request(camera: PinholeCamera, eye: Vec3, look_at: Vec3, up: Vec3, sun: Vec3) -> FrameRequest {
    let (rotation, translation) = camera_pose_looking_at(eye, look_at, up).unwrap();
    FrameRequest {
        camera,
        camera_from_target_rotation: rotation,
        camera_from_target_translation_m: translation,
        sun_dir_target: sun.normalize(),
        sun_lit: true,
        earth_albedo: None,
        samples_per_pixel: 1,
        exposure: 1.0,
        seed: 9,
    }
}

/// Origin and (camera-z-normalised) direction of the ray through a pixel centre, target frame,
/// computed from the request independently of the renderer.
fn pixel_ray(req: &FrameRequest, x: u32, y: u32) -> (Vec3, Vec3) {
    let c = &req.camera;
    let d_cam = Vec3::new(
        (x as f32 + 0.5 - c.cx) / c.fx,
        (y as f32 + 0.5 - c.cy) / c.fy,
        1.0,
    );
    let r_inv = req.camera_from_target_rotation.conjugate();
    (r_inv * -req.camera_from_target_translation_m, r_inv * d_cam)
}

/// A square plate in z = 0, `half_m` on a side, facing +z.
fn plate(builder: &mut MeshBuilder, half_m: f32, material: u16) {
    builder.quad_grid(
        Vec3::new(-half_m, -half_m, 0.0),
        Vec3::new(2.0 * half_m, 0.0, 0.0),
        Vec3::new(0.0, 2.0 * half_m, 0.0),
        1,
        1,
        material,
    );
}

/// Ray-box slab test for an axis-aligned box: entry distance if hit with t > 0.
fn ray_box(origin: Vec3, dir: Vec3, lo: Vec3, hi: Vec3) -> Option<f32> {
    let (mut near, mut far) = (0.0f32, f32::INFINITY);
    for a in 0..3 {
        if dir[a].abs() < 1e-12 {
            if origin[a] < lo[a] || origin[a] > hi[a] {
                return None;
            }
            continue;
        }
        let t1 = (lo[a] - origin[a]) / dir[a];
        let t2 = (hi[a] - origin[a]) / dir[a];
        near = near.max(t1.min(t2));
        far = far.min(t1.max(t2));
    }
    (near <= far).then_some(near)
}

/// The BRDF of the module documentation, evaluated term by term for unit n, l, v.
fn brdf_by_hand(base: Vec3, metallic: f32, roughness: f32, n: Vec3, l: Vec3, v: Vec3) -> Vec3 {
    let alpha = roughness * roughness;
    let a2 = alpha * alpha;
    let h = (l + v).normalize();
    let (nl, nv, nh, vh) = (n.dot(l), n.dot(v), n.dot(h), v.dot(h));
    let d = a2 / (PI * (nh * nh * (a2 - 1.0) + 1.0).powi(2));
    let g1 = |x: f32| 2.0 * x / (x + (a2 + (1.0 - a2) * x * x).sqrt());
    let f0 = Vec3::splat(0.04) * (1.0 - metallic) + base * metallic;
    let fresnel = f0 + (Vec3::ONE - f0) * (1.0 - vh).powi(5);
    base * (1.0 - metallic) / PI + fresnel * (d * g1(nv) * g1(nl) / (4.0 * nl * nv))
}

#[test]
fn lit_plane_radiance_equals_the_brdf_formula() {
    let materials = [
        Material {
            name: "test_dielectric".into(),
            base_color_linear: [0.7, 0.5, 0.3],
            metallic: 0.0,
            roughness: 0.4,
            ..Material::default_grey()
        },
        Material {
            name: "test_metal".into(),
            base_color_linear: [0.95, 0.64, 0.26],
            metallic: 1.0,
            roughness: 0.3,
            ..Material::default_grey()
        },
    ];
    for material in materials {
        let (base, metallic, roughness) = (
            Vec3::from_array(material.base_color_linear),
            material.metallic,
            material.roughness,
        );
        let mut b = MeshBuilder::new();
        let m = b.material(material);
        plate(&mut b, 20.0, m);
        let scene = Scene::new(b.build().unwrap());
        let sun = Vec3::new(-0.3, 0.5, 0.8).normalize();
        let req = request(
            camera(160, 100, 120.0),
            Vec3::new(1.5, -2.0, 4.0),
            Vec3::new(0.3, 0.2, 0.0),
            Vec3::Z,
            sun,
        );
        let radiance = render_radiance(&scene, &req).unwrap();
        let frame = render_frame(&scene, &req);
        let mut checked = 0;
        let mut max_rel_err = 0.0f32;
        for y in 0..req.camera.height {
            for x in 0..req.camera.width {
                let i = (y * req.camera.width + x) as usize;
                let (o, d) = pixel_ray(&req, x, y);
                let s = -o.z / d.z;
                if s <= 0.0 || (o + d * s).abs().max_element() > 20.01 {
                    assert_eq!(radiance.mask[i], 0);
                    continue;
                }
                if (o + d * s).abs().max_element() > 19.99 {
                    continue; // too close to the plate's edge to call
                }
                assert_eq!(radiance.mask[i], 255);
                // Depth = camera z = s (the direction has unit camera z).
                assert!(
                    (radiance.depth_m[i] - s).abs() < 1e-4 * s,
                    "{} vs {s}",
                    radiance.depth_m[i]
                );
                let v = -d.normalize();
                let expected = brdf_by_hand(base, metallic, roughness, Vec3::Z, sun, v)
                    * (SUN_IRRADIANCE * sun.z);
                let got = Vec3::from_array(radiance.radiance_rgb[i]);
                let rel = ((got - expected).abs() / expected.max(Vec3::splat(1e-3))).max_element();
                max_rel_err = max_rel_err.max(rel);
                for c in 0..3 {
                    assert_eq!(frame.rgb8[3 * i + c], linear_to_srgb8(got[c]));
                }
                checked += 1;
            }
        }
        assert!(checked > 10_000, "{checked}");
        assert!(max_rel_err < 2e-4, "max relative error {max_rel_err}");
    }
}

#[test]
fn white_plate_facing_the_sun_has_radiance_equal_to_its_diffuse_albedo_plus_specular() {
    // Normalisation check: Sun straight above, camera far off-specular: radiance ~ albedo.
    let mut b = MeshBuilder::new();
    let m = b.material(Material {
        roughness: 1.0,
        ..Material::white_paint()
    });
    plate(&mut b, 5.0, m);
    let scene = Scene::new(b.build().unwrap());
    let req = request(
        camera(64, 64, 400.0),
        Vec3::new(0.0, -6.0, 3.0),
        Vec3::ZERO,
        Vec3::Z,
        Vec3::Z,
    );
    let radiance = render_radiance(&scene, &req).unwrap();
    let centre = radiance.radiance_rgb[32 * 64 + 32];
    // Diffuse part is exactly the albedo 0.8; the rough specular adds a few percent.
    assert!(centre[0] > 0.8 && centre[0] < 0.86, "{centre:?}");
}

#[test]
fn plane_lit_from_behind_or_below_is_black() {
    let mut b = MeshBuilder::new();
    let m = b.material(Material::white_paint());
    plate(&mut b, 5.0, m);
    let scene = Scene::new(b.build().unwrap());
    let req = request(
        camera(64, 64, 60.0),
        Vec3::new(0.5, -1.0, 3.0),
        Vec3::ZERO,
        Vec3::Z,
        Vec3::new(0.2, 0.3, -1.0),
    );
    let frame = render_frame(&scene, &req);
    assert!(frame.mask.iter().filter(|&&m| m == 255).count() > 1000);
    assert!(frame.rgb8.iter().all(|&c| c == 0));
}

#[test]
fn floating_box_shadow_outline_and_area_match_geometry() {
    let (lo, hi) = (Vec3::new(-0.5, -0.5, 2.5), Vec3::new(0.5, 0.5, 3.5));
    let mut b = MeshBuilder::new();
    let paint = b.material(Material::white_paint());
    plate(&mut b, 6.0, paint);
    b.simple_box((lo + hi) / 2.0, (hi - lo) / 2.0, 0.25, paint);
    let scene = Scene::new(b.build().unwrap());
    let sun = Vec3::new(0.8, 0.3, 1.0).normalize();
    let (size, range_m) = (400u32, 25.0f32);
    let focal = size as f32 * range_m / 12.0;
    let req = request(
        camera(size, size, focal),
        Vec3::new(0.0, 0.0, range_m),
        Vec3::ZERO,
        Vec3::Y,
        sun,
    );
    let radiance = render_radiance(&scene, &req).unwrap();
    let in_shadow = |p: Vec3| ray_box(p, sun, lo, hi).is_some();
    let (mut shadow_pixels, mut boundary_pixels, mut mismatches) = (0, 0, 0);
    for y in 0..size {
        for x in 0..size {
            let i = (y * size + x) as usize;
            let (o, d) = pixel_ray(&req, x, y);
            let s = -o.z / d.z;
            let p = o + d * s;
            if p.x.abs() > 5.9 || p.y.abs() > 5.9 || ray_box(o, d, lo, hi).is_some() {
                continue; // off the plate or the box hides the plate here
            }
            assert!((radiance.depth_m[i] - s).abs() < 1e-4 * s);
            let expected = in_shadow(p);
            let eps = 1e-3;
            let near_edge = [Vec3::X, -Vec3::X, Vec3::Y, -Vec3::Y]
                .iter()
                .any(|&e| in_shadow(p + e * eps) != expected);
            if near_edge {
                boundary_pixels += 1;
                continue;
            }
            let rendered_dark = radiance.radiance_rgb[i] == [0.0; 3];
            if rendered_dark != expected {
                mismatches += 1;
            }
            if expected {
                shadow_pixels += 1;
            }
        }
    }
    assert_eq!(
        mismatches, 0,
        "{mismatches} pixels disagree with the shadow geometry"
    );
    assert!(boundary_pixels < 20, "{boundary_pixels}");
    // Shadow of a unit cube cast along unit L onto z = 0: (|Lx| + |Ly| + |Lz|) / |Lz| m^2.
    let expected_area = (sun.x.abs() + sun.y.abs() + sun.z.abs()) / sun.z.abs();
    let pixel_area = (range_m / focal).powi(2);
    let area = shadow_pixels as f32 * pixel_area;
    assert!(
        (area / expected_area - 1.0).abs() < 0.02,
        "{area} vs {expected_area}"
    );
}

fn overview_request(scene: &Scene) -> FrameRequest {
    let r = scene.mesh().bounding_radius_m();
    request(
        camera(240, 150, 375.0),
        Vec3::new(1.0, -0.8, 0.5).normalize() * 5.0 * r,
        Vec3::ZERO,
        Vec3::Z,
        Vec3::new(0.6, -0.3, 0.75),
    )
}

#[test]
fn eclipse_is_exactly_dark_without_fill_and_dim_with_it() {
    let scene = Scene::new(builtin_target(BuiltinTarget::Rosetta));
    let lit_req = overview_request(&scene);
    let lit = render_frame(&scene, &lit_req);
    let mut eclipse_req = lit_req;
    eclipse_req.sun_lit = false;
    eclipse_req.sun_dir_target = Vec3::NAN; // ignored in eclipse
    eclipse_req.samples_per_pixel = 4;
    let dark = try_render_frame(&scene, &eclipse_req).unwrap();
    assert_eq!(dark.mask, lit.mask, "the target is still there");
    assert!(dark.mask.contains(&255));
    assert!(dark.rgb8.iter().all(|&c| c == 0));
    let dark_radiance = render_radiance(&scene, &eclipse_req).unwrap();
    assert!(dark_radiance.radiance_rgb.iter().all(|p| *p == [0.0; 3]));

    let earth = Vec3::new(0.2, -1.0, -0.6).normalize();
    eclipse_req.earth_albedo = Some(EarthFill {
        dir_target: earth,
        strength: 0.3,
    });
    let filled = render_radiance(&scene, &eclipse_req).unwrap();
    let lit_radiance = render_radiance(&scene, &lit_req).unwrap();
    let lit_pixels = filled.radiance_rgb.iter().filter(|p| p[0] > 0.0).count();
    assert!(lit_pixels > 100, "{lit_pixels}");
    // Background stays black away from the silhouette (edge pixels are partly covered by the
    // jittered samples).
    let (w, h) = (filled.width as usize, filled.height as usize);
    let mut background_checked = 0;
    for y in 1..h - 1 {
        for x in 1..w - 1 {
            let far_from_target =
                (y - 1..=y + 1).all(|yy| (x - 1..=x + 1).all(|xx| filled.mask[yy * w + xx] == 0));
            if far_from_target {
                assert_eq!(filled.radiance_rgb[y * w + x], [0.0; 3]);
                background_checked += 1;
            }
        }
    }
    assert!(background_checked > w * h / 2);
    // Fill at 0.3 of the Sun's irradiance: total light well below the sunlit frame's.
    let total = |f: &[[f32; 3]]| f.iter().map(|p| p[0] as f64).sum::<f64>();
    assert!(total(&filled.radiance_rgb) < 0.6 * total(&lit_radiance.radiance_rgb));
}

#[test]
fn rotated_box_mask_matches_projected_silhouette_and_depth_matches_geometry() {
    let rotation = Quat::from_euler(glam::EulerRot::XYZ, 0.4, -0.7, 0.25);
    let half = Vec3::new(1.0, 0.6, 0.4);
    let mut b = MeshBuilder::new();
    let m = b.material(Material::white_paint());
    b.oriented_box(Vec3::ZERO, half, rotation, 0.3, [m; 6]);
    let scene = Scene::new(b.build().unwrap());
    let req = request(
        camera(320, 240, 300.0),
        Vec3::new(3.0, -7.0, 2.0),
        Vec3::new(0.1, 0.0, -0.1),
        Vec3::Z,
        Vec3::Z,
    );
    let frame = render_frame(&scene, &req);
    // Project the 8 corners and take their convex hull (gift wrapping).
    let c = &req.camera;
    let corners: Vec<(f32, f32)> = (0..8)
        .map(|k| {
            let s = Vec3::new(
                if k & 1 == 0 { -1.0 } else { 1.0 },
                if k & 2 == 0 { -1.0 } else { 1.0 },
                if k & 4 == 0 { -1.0 } else { 1.0 },
            );
            let p = req.camera_from_target_rotation * (rotation * (half * s))
                + req.camera_from_target_translation_m;
            (c.fx * p.x / p.z + c.cx, c.fy * p.y / p.z + c.cy)
        })
        .collect();
    let hull = convex_hull(&corners);
    let (mut inside, mut ambiguous, mut mismatches) = (0, 0, 0);
    for y in 0..c.height {
        for x in 0..c.width {
            let i = (y * c.width + x) as usize;
            let p = (x as f32 + 0.5, y as f32 + 0.5);
            let distance = signed_distance_inside(&hull, p);
            if distance.abs() < 1e-3 {
                ambiguous += 1;
                continue;
            }
            let expected = distance > 0.0;
            inside += expected as usize;
            if (frame.mask[i] == 255) != expected {
                mismatches += 1;
            }
            // Depth against an analytic ray-box intersection in the box frame.
            let (o, d) = pixel_ray(&req, x, y);
            let inv = rotation.conjugate();
            let hit = ray_box(inv * o, inv * d, -half, half);
            match hit {
                Some(t) => assert!(
                    (frame.depth_m[i] - t).abs() < 1e-4 * t,
                    "{} vs {t}",
                    frame.depth_m[i]
                ),
                None => assert_eq!(frame.depth_m[i], f32::INFINITY),
            }
        }
    }
    assert_eq!(mismatches, 0);
    assert!(ambiguous < 5);
    assert!(inside > 2000, "{inside}");
}

/// Counter-clockwise (in image coordinates with y down: clockwise on screen) convex hull.
fn convex_hull(points: &[(f32, f32)]) -> Vec<(f32, f32)> {
    let mut pts = points.to_vec();
    pts.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.total_cmp(&b.1)));
    let cross = |o: (f32, f32), a: (f32, f32), b: (f32, f32)| {
        (a.0 - o.0) * (b.1 - o.1) - (a.1 - o.1) * (b.0 - o.0)
    };
    let mut hull: Vec<(f32, f32)> = Vec::new();
    for pass in 0..2 {
        let start = hull.len();
        let iter: Box<dyn Iterator<Item = &(f32, f32)>> = if pass == 0 {
            Box::new(pts.iter())
        } else {
            Box::new(pts.iter().rev())
        };
        for &p in iter {
            while hull.len() >= start + 2
                && cross(hull[hull.len() - 2], hull[hull.len() - 1], p) <= 0.0
            {
                hull.pop();
            }
            hull.push(p);
        }
        hull.pop();
    }
    hull
}

/// Distance from p to the hull boundary, positive inside (hull in counter-clockwise order
/// by the `cross > 0` convention of `convex_hull`).
fn signed_distance_inside(hull: &[(f32, f32)], p: (f32, f32)) -> f32 {
    let mut distance = f32::INFINITY;
    for k in 0..hull.len() {
        let a = hull[k];
        let b = hull[(k + 1) % hull.len()];
        let (ex, ey) = (b.0 - a.0, b.1 - a.1);
        let len = (ex * ex + ey * ey).sqrt();
        let side = (ex * (p.1 - a.1) - ey * (p.0 - a.0)) / len;
        distance = distance.min(side);
    }
    distance
}

#[test]
fn same_request_gives_identical_bytes_across_runs_and_thread_counts() {
    let scene = Scene::new(builtin_target(BuiltinTarget::Cassini));
    let mut req = overview_request(&scene);
    req.samples_per_pixel = 3;
    req.earth_albedo = Some(EarthFill {
        dir_target: Vec3::new(0.0, 0.6, -0.8),
        strength: 0.3,
    });
    let a = render_frame(&scene, &req);
    let b = render_frame(&scene, &req);
    assert_eq!(a, b);
    let single = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap()
        .install(|| render_frame(&scene, &req));
    let triple = rayon::ThreadPoolBuilder::new()
        .num_threads(3)
        .build()
        .unwrap()
        .install(|| render_frame(&scene, &req));
    assert_eq!(a.rgb8, single.rgb8);
    assert_eq!(a.rgb8, triple.rgb8);
    assert_eq!(a.depth_m, single.depth_m);
    assert!(a.rgb8.iter().any(|&c| c > 0));
    // The seed drives the anti-aliasing jitter: another seed changes edge pixels, not the mask.
    let mut other = req;
    other.seed += 1;
    let c = render_frame(&scene, &other);
    assert_ne!(a.rgb8, c.rgb8);
    assert_eq!(a.mask, c.mask);
}

#[test]
fn invalid_requests_are_errors_and_render_black() {
    let scene = Scene::new(
        TargetMesh::new(
            vec![Vec3::ZERO, Vec3::X, Vec3::Y],
            vec![[0, 1, 2]],
            vec![0],
            vec![Material::default_grey()],
        )
        .unwrap(),
    );
    let good = request(
        camera(8, 8, 10.0),
        Vec3::new(0.0, 0.0, 5.0),
        Vec3::ZERO,
        Vec3::Y,
        Vec3::Z,
    );
    assert!(try_render_frame(&scene, &good).is_ok());
    let mut cases = Vec::new();
    let mut r = good;
    r.camera.width = 0;
    cases.push((r, "image size"));
    let mut r = good;
    r.camera.fx = f32::NAN;
    cases.push((r, "focal"));
    let mut r = good;
    r.camera_from_target_rotation = Quat::from_xyzw(0.0, 0.0, 0.0, 2.0);
    cases.push((r, "unit quaternion"));
    let mut r = good;
    r.camera_from_target_translation_m = Vec3::new(0.0, f32::INFINITY, 0.0);
    cases.push((r, "translation"));
    let mut r = good;
    r.sun_dir_target = Vec3::new(0.0, 0.0, 2.0);
    cases.push((r, "Sun direction"));
    let mut r = good;
    r.samples_per_pixel = 0;
    cases.push((r, "samples per pixel"));
    let mut r = good;
    r.exposure = -1.0;
    cases.push((r, "exposure"));
    let mut r = good;
    r.earth_albedo = Some(EarthFill {
        dir_target: Vec3::Z,
        strength: f32::NAN,
    });
    cases.push((r, "Earth fill"));
    for (req, needle) in cases {
        let err = try_render_frame(&scene, &req).unwrap_err();
        assert!(err.to_string().contains(needle), "{err} lacks {needle:?}");
        let frame = render_frame(&scene, &req);
        assert!(frame.rgb8.iter().all(|&c| c == 0));
        assert!(frame.mask.iter().all(|&m| m == 0));
        assert!(frame.depth_m.iter().all(|d| *d == f32::INFINITY));
    }
}

#[test]
fn edge_pixels_average_their_coverage() {
    // A plate whose edge x = 3 mm cuts pixel column 32 (x in [0, 10 mm]) at 30%: with several
    // jittered samples that column's radiance is ~0.7 of its fully covered neighbour's.
    let mut b = MeshBuilder::new();
    let m = b.material(Material {
        roughness: 1.0,
        ..Material::white_paint()
    });
    b.quad_grid(
        Vec3::new(0.003, -10.0, 0.0),
        Vec3::new(10.0, 0.0, 0.0),
        Vec3::new(0.0, 20.0, 0.0),
        1,
        1,
        m,
    );
    let scene = Scene::new(b.build().unwrap());
    let (width, height) = (64u32, 256u32);
    for (spp, tolerance) in [(16u32, 0.03f32), (5, 0.05)] {
        let mut req = request(
            PinholeCamera {
                fx: 1000.0,
                fy: 1000.0,
                cx: 32.0,
                cy: 128.0,
                width,
                height,
            },
            Vec3::new(0.0, 0.0, 10.0),
            Vec3::ZERO,
            Vec3::Y,
            Vec3::new(0.2, 0.1, 1.0),
        );
        req.samples_per_pixel = spp;
        let radiance = render_radiance(&scene, &req).unwrap();
        let mut ratio_sum = 0.0;
        for y in 0..height as usize {
            let row = &radiance.radiance_rgb[y * width as usize..];
            assert_eq!(row[31], [0.0; 3], "column 31 lies entirely off the plate");
            ratio_sum += row[32][0] / row[33][0];
            // The centre ray of column 32 (x = 5 mm) hits the plate.
            assert_eq!(radiance.mask[y * width as usize + 32], 255);
        }
        let mean = ratio_sum / height as f32;
        assert!((mean - 0.7).abs() < tolerance, "spp {spp}: {mean}");
    }
}

/// A latitude-longitude sphere (outward winding) of the given radius.
fn uv_sphere(radius_m: f32, rings: u32, segments: u32) -> TargetMesh {
    let mut vertices = Vec::new();
    for r in 0..=rings {
        let theta = PI * r as f32 / rings as f32;
        for s in 0..segments {
            let phi = 2.0 * PI * s as f32 / segments as f32;
            vertices.push(
                Vec3::new(
                    theta.sin() * phi.cos(),
                    theta.sin() * phi.sin(),
                    theta.cos(),
                ) * radius_m,
            );
        }
    }
    let mut triangles = Vec::new();
    for r in 0..rings {
        for s in 0..segments {
            let s1 = (s + 1) % segments;
            let a = r * segments + s;
            let b = r * segments + s1;
            let c = (r + 1) * segments + s1;
            let d = (r + 1) * segments + s;
            if r > 0 {
                triangles.push([a, d, b]);
            }
            if r + 1 < rings {
                triangles.push([b, d, c]);
            }
        }
    }
    let n = triangles.len();
    TargetMesh::new(
        vertices,
        triangles,
        vec![0; n],
        vec![Material::white_paint()],
    )
    .unwrap()
}

#[test]
fn convex_sphere_has_no_shadow_acne_and_a_clean_terminator() {
    // On a convex body nothing casts a shadow: every point facing the Sun must be lit (no
    // self-intersection of shadow rays), every point facing away must be black.
    let radius_m = 2.0;
    let scene = Scene::new(uv_sphere(radius_m, 96, 192));
    let sun = Vec3::new(0.9, -0.2, 0.4).normalize();
    let req = request(
        camera(200, 200, 400.0),
        Vec3::new(0.5, -9.0, 2.0),
        Vec3::ZERO,
        Vec3::Z,
        sun,
    );
    let radiance = render_radiance(&scene, &req).unwrap();
    let (mut lit_checked, mut dark_checked) = (0, 0);
    for y in 0..200 {
        for x in 0..200 {
            let i = (y * 200 + x) as usize;
            if radiance.mask[i] == 0 {
                continue;
            }
            let (o, d) = pixel_ray(&req, x, y);
            let p = o + d * radiance.depth_m[i];
            // The facets deviate from the sphere by < 0.1 degree-scale; stay 3 degrees away.
            let cos_sun = p.normalize().dot(sun);
            if cos_sun > 0.05 {
                assert!(
                    radiance.radiance_rgb[i][0] > 0.0,
                    "acne at pixel ({x}, {y})"
                );
                lit_checked += 1;
            } else if cos_sun < -0.05 {
                assert_eq!(radiance.radiance_rgb[i], [0.0; 3]);
                dark_checked += 1;
            }
        }
    }
    assert!(
        lit_checked > 2000 && dark_checked > 2000,
        "{lit_checked} {dark_checked}"
    );
}

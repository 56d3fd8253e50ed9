//! The shadow pass on analytic cases, for both light projections: a small Gaussian behind
//! two big opaque ones (seen from the Sun) is dark, the front one is lit, and moving the Sun
//! sideways lights the small one again. Also: the pass is deterministic and V is in [0, 1].

use glam::Vec3;
use gs_core::init::inverse_sigmoid;
use gs_core::model::{GaussianModel, ModelLayout, Param};
use gs_core::nn::SceneBox;
use gs_core::sunaware::sun_visibility::{
    light_camera, light_splats, sun_visibility, sun_visibility_with_margin, RECEIVER_EXTENT_SIGMAS,
};
use gs_core::sunaware::{LightConfig, LightProjection};

/// Gaussian 0: small, at the origin. 1 and 2: big, opaque, on the Sun side along `sun`.
fn blockers(sun: Vec3) -> GaussianModel {
    let mut g = GaussianModel::new(ModelLayout::sh(0)).unwrap();
    g.params.push_zeros(3);
    // The blockers are further apart along the Sun than their own extents (2 sigma each),
    // so the front one is in front of the rear one rather than beside it.
    let rows = [
        (Vec3::ZERO, 0.02f32, 0.9f32),
        (sun * 0.8, 0.15, 0.999),
        (sun * 0.35, 0.15, 0.999),
    ];
    for (i, (m, s, o)) in rows.iter().enumerate() {
        let p = &mut g.params;
        p.row_mut(Param::Mean, i).copy_from_slice(&m.to_array());
        p.row_mut(Param::LogScale, i).fill(s.ln());
        p.row_mut(Param::Rotation, i)
            .copy_from_slice(&[1.0, 0.0, 0.0, 0.0]);
        p.row_mut(Param::OpacityLogit, i)[0] = inverse_sigmoid(*o);
    }
    g
}

fn config(projection: LightProjection) -> LightConfig {
    LightConfig {
        projection,
        resolution_px: 128,
        ..LightConfig::default()
    }
}

fn scene_box() -> SceneBox {
    SceneBox::new([-1.0; 3], [1.0; 3]).unwrap()
}

fn camera_centre() -> Vec3 {
    Vec3::new(3.0, -1.0, 0.5)
}

#[test]
fn occluded_gaussian_is_dark_and_front_one_is_lit() {
    for projection in [LightProjection::Perspective, LightProjection::Orthographic] {
        let sun = Vec3::new(0.2, 0.5, 0.8).normalize();
        let g = blockers(sun);
        let v = sun_visibility(
            &g,
            sun,
            camera_centre(),
            &scene_box(),
            &config(projection),
            0.01,
        )
        .unwrap();
        // Two blockers of alpha <= 0.99 at the centre leave T <= 1e-4: counted as 0.
        assert!(
            v[0] < 0.02,
            "{projection:?}: small Gaussian behind blockers has V = {}",
            v[0]
        );
        assert!(
            v[1] > 0.97,
            "{projection:?}: nothing in front of the front blocker, V = {}",
            v[1]
        );
        // The rear blocker sits behind the front one: mostly dark, lit only at its rim
        // (its footprint average includes pixels the front one covers less).
        assert!(v[2] < 0.2, "{projection:?}: rear blocker V = {}", v[2]);
        assert!(v.iter().all(|x| (0.0..=1.0).contains(x)));
    }
}

#[test]
fn sun_from_the_side_lights_the_small_gaussian() {
    for projection in [LightProjection::Perspective, LightProjection::Orthographic] {
        // Blockers placed for one Sun; the Sun then comes from a perpendicular direction.
        let g = blockers(Vec3::Z);
        let v = sun_visibility(
            &g,
            Vec3::X,
            camera_centre(),
            &scene_box(),
            &config(projection),
            0.01,
        )
        .unwrap();
        assert!(v[0] > 0.97, "{projection:?}: V = {}", v[0]);
        let v = sun_visibility(
            &g,
            Vec3::Z,
            camera_centre(),
            &scene_box(),
            &config(projection),
            0.01,
        )
        .unwrap();
        assert!(v[0] < 0.02, "{projection:?}: V = {}", v[0]);
    }
}

#[test]
fn a_single_half_transparent_blocker_passes_its_transmittance() {
    // One blocker of opacity 0.5, much wider than the small Gaussian's footprint: the small
    // one sees T = 1 - 0.5 exp(-d^2/2s^2) ~ 0.5 averaged over its 2 px footprint.
    for projection in [LightProjection::Perspective, LightProjection::Orthographic] {
        let mut g = blockers(Vec3::Z);
        g.params.retain(&[true, true, false]).unwrap();
        g.params.row_mut(Param::OpacityLogit, 1)[0] = inverse_sigmoid(0.5);
        g.params.row_mut(Param::LogScale, 1).fill(0.4f32.ln());
        let v = sun_visibility(
            &g,
            Vec3::Z,
            camera_centre(),
            &scene_box(),
            &config(projection),
            0.01,
        )
        .unwrap();
        assert!((v[0] - 0.5).abs() < 0.03, "{projection:?}: V = {}", v[0]);
    }
}

#[test]
fn orthographic_keeps_sizes_and_perspective_shrinks_with_distance() {
    // Two equal Gaussians at different distances from the light: orthographic splats are
    // the same size, perspective ones are not.
    let mut g = blockers(Vec3::Z);
    g.params
        .row_mut(Param::Mean, 0)
        .copy_from_slice(&[0.3, 0.0, -0.5]);
    g.params.row_mut(Param::LogScale, 0).fill(0.15f32.ln());
    let sizes = |projection| {
        let light =
            light_camera(Vec3::Z, camera_centre(), &scene_box(), &config(projection)).unwrap();
        let splats = light_splats(&g, &light, 0.01).unwrap();
        // Conic a = 1 / sigma_x^2 for an isotropic splat.
        let s0 = splats[0].unwrap().conic[0];
        let s1 = splats[1].unwrap().conic[0];
        s0 / s1
    };
    let ortho = sizes(LightProjection::Orthographic);
    let persp = sizes(LightProjection::Perspective);
    assert!(
        (ortho - 1.0).abs() < 1e-3,
        "orthographic size ratio {ortho}"
    );
    assert!(
        persp > 1.2,
        "perspective: the farther one must look smaller, ratio {persp}"
    );
}

#[test]
fn shadow_pass_is_deterministic() {
    let sun = Vec3::new(0.2, 0.5, 0.8).normalize();
    let g = blockers(sun);
    let a = sun_visibility(
        &g,
        sun,
        camera_centre(),
        &scene_box(),
        &config(LightProjection::Perspective),
        0.01,
    )
    .unwrap();
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    let b = pool.install(|| {
        sun_visibility(
            &g,
            sun,
            camera_centre(),
            &scene_box(),
            &config(LightProjection::Perspective),
            0.01,
        )
        .unwrap()
    });
    assert_eq!(
        a.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
        b.iter().map(|v| v.to_bits()).collect::<Vec<_>>()
    );
    assert!(sun_visibility(
        &g,
        Vec3::ZERO,
        camera_centre(),
        &scene_box(),
        &LightConfig::default(),
        0.01
    )
    .is_err());
}

/// A ball of surface Gaussians (Fibonacci points on a 0.5 m sphere, isotropic, sigma = the
/// point spacing, opacity 0.95: what surface-sample initialisation makes) under a plate of
/// Gaussians that covers the half-space x < 0 at z = 1. Returns the model, the ball's
/// centres and outward normals (the first `ball` Gaussians) and the plate's height.
fn ball_under_half_plate() -> (GaussianModel, Vec<(Vec3, Vec3)>, f32) {
    let ball = 600;
    let radius = 0.5f32;
    let spacing = (4.0 * std::f32::consts::PI * radius * radius / ball as f32).sqrt();
    let golden = std::f32::consts::PI * (3.0 - 5f32.sqrt());
    let mut rows: Vec<(Vec3, f32, f32)> = Vec::new();
    let mut surface = Vec::new();
    for k in 0..ball {
        let z = 1.0 - 2.0 * (k as f32 + 0.5) / ball as f32;
        let r = (1.0 - z * z).sqrt();
        let phi = golden * k as f32;
        let n = Vec3::new(r * phi.cos(), r * phi.sin(), z);
        rows.push((n * radius, spacing, 0.95));
        surface.push((n * radius, n));
    }
    let plate_z = 1.0f32;
    let step = 0.05f32;
    for i in 0..30 {
        for j in 0..50 {
            let p = Vec3::new(-1.45 + step * i as f32, -1.25 + step * j as f32, plate_z);
            rows.push((p, step, 0.99));
        }
    }
    let mut g = GaussianModel::new(ModelLayout::sh(0)).unwrap();
    g.params.push_zeros(rows.len());
    for (i, (m, s, o)) in rows.iter().enumerate() {
        let p = &mut g.params;
        p.row_mut(Param::Mean, i).copy_from_slice(&m.to_array());
        p.row_mut(Param::LogScale, i).fill(s.ln());
        p.row_mut(Param::Rotation, i)
            .copy_from_slice(&[1.0, 0.0, 0.0, 0.0]);
        p.row_mut(Param::OpacityLogit, i)[0] = inverse_sigmoid(*o);
    }
    (g, surface, plate_z)
}

#[test]
fn lit_side_of_a_ball_is_lit_and_the_plate_shadow_is_dark() {
    // The Sun 20 degrees off the plate's normal. Ground truth per ball Gaussian: lit when its
    // surface faces the Sun (the ball itself blocks the far side) and the ray to the Sun
    // passes the plate's edge (x = -0.05 .. the plate's rim) with a margin; shadowed when
    // the ray hits the plate well inside, or the surface faces well away from the Sun.
    let sun = Vec3::new(0.3, 0.2, 1.0).normalize();
    let (g, surface, plate_z) = ball_under_half_plate();
    for projection in [LightProjection::Perspective, LightProjection::Orthographic] {
        let v = sun_visibility(
            &g,
            sun,
            camera_centre() * 2.0,
            &SceneBox::new([-1.5; 3], [1.5; 3]).unwrap(),
            &config(projection),
            0.01,
        )
        .unwrap();
        let (mut lit, mut dark) = (Vec::new(), Vec::new());
        for (i, &(p, n)) in surface.iter().enumerate() {
            let facing = n.dot(sun);
            let at_plate = p + sun * ((plate_z - p.z) / sun.z);
            if facing > 0.3 && at_plate.x > 0.1 {
                lit.push(v[i]);
            } else if facing < -0.3 || (facing > 0.3 && at_plate.x < -0.25) {
                dark.push(v[i]);
            }
        }
        assert!(
            lit.len() > 100 && dark.len() > 200,
            "{} {}",
            lit.len(),
            dark.len()
        );
        let mean = |x: &[f32]| x.iter().sum::<f32>() / x.len() as f32;
        // Neighbours on the curved surface must not shadow each other ("acne").
        assert!(
            mean(&lit) > 0.9,
            "{projection:?}: lit Gaussians have mean V = {}",
            mean(&lit)
        );
        let lit_below_half = lit.iter().filter(|&&x| x < 0.5).count();
        assert!(
            lit_below_half * 20 <= lit.len(),
            "{projection:?}: {lit_below_half} of {} lit Gaussians have V < 0.5",
            lit.len()
        );
        assert!(
            mean(&dark) < 0.05,
            "{projection:?}: shadowed Gaussians have mean V = {}",
            mean(&dark)
        );
    }
}

#[test]
fn fixed_bias_alone_lets_a_lit_surface_shadow_itself() {
    // The same scene with the receiver-extent margin switched off: the defect the margin
    // fixes (a lit, curved surface of overlapping Gaussians darkens itself).
    let sun = Vec3::new(0.3, 0.2, 1.0).normalize();
    let (g, surface, plate_z) = ball_under_half_plate();
    let scene_box = SceneBox::new([-1.5; 3], [1.5; 3]).unwrap();
    let cfg = config(LightProjection::Orthographic);
    let lit_mean = |extent_sigmas: f32| {
        let v = sun_visibility_with_margin(
            &g,
            sun,
            camera_centre() * 2.0,
            &scene_box,
            &cfg,
            0.01,
            extent_sigmas,
        )
        .unwrap();
        let lit: Vec<f32> = surface
            .iter()
            .enumerate()
            .filter(|(_, &(p, n))| {
                let at_plate = p + sun * ((plate_z - p.z) / sun.z);
                n.dot(sun) > 0.3 && at_plate.x > 0.1
            })
            .map(|(i, _)| v[i])
            .collect();
        lit.iter().sum::<f32>() / lit.len() as f32
    };
    let without = lit_mean(0.0);
    let with = lit_mean(RECEIVER_EXTENT_SIGMAS);
    assert!(without < 0.7, "fixed bias alone: lit mean V = {without}");
    assert!(with > without + 0.2, "{with} vs {without}");
    assert!(
        sun_visibility_with_margin(&g, sun, camera_centre(), &scene_box, &cfg, 0.01, f32::NAN)
            .is_err()
    );
}

//! The shadow pass on analytic cases, for both light projections: a small Gaussian behind
//! two big opaque ones (seen from the Sun) is dark, the front one is lit, and moving the Sun
//! sideways lights the small one again. Also: the pass is deterministic and V is in [0, 1].

use glam::Vec3;
use gs_core::init::inverse_sigmoid;
use gs_core::model::{GaussianModel, ModelLayout, Param};
use gs_core::nn::SceneBox;
use gs_core::sunaware::light::{light_camera, light_splats, sun_visibility};
use gs_core::sunaware::{LightConfig, LightProjection};

/// Gaussian 0: small, at the origin. 1 and 2: big, opaque, on the Sun side along `sun`.
fn blockers(sun: Vec3) -> GaussianModel {
    let mut g = GaussianModel::new(ModelLayout::sh(0)).unwrap();
    g.params.push_zeros(3);
    let rows = [
        (Vec3::ZERO, 0.02f32, 0.9f32),
        (sun * 0.6, 0.2, 0.999),
        (sun * 0.35, 0.2, 0.999),
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
    g.params.row_mut(Param::LogScale, 0).fill(0.2f32.ln());
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

//! The benchmark's scene: `N` seeded Gaussians in (or on the faces of) a satellite-sized
//! box, and the three-quarter camera at 6 m that sees it.

use super::*;

/// Half extents of the satellite-sized box the Gaussians fill, m.
pub(super) const BOX_HALF_M: [f32; 3] = [1.5, 0.75, 0.75];

/// A point of the scene and the rotation that orients its Gaussian.
fn scene_point(kind: SceneKind, rng: &mut SplitMix64) -> (Vec3, Quat) {
    let h = Vec3::from_array(BOX_HALF_M);
    let inside = Vec3::new(
        rng.uniform(-h.x, h.x),
        rng.uniform(-h.y, h.y),
        rng.uniform(-h.z, h.z),
    );
    match kind {
        SceneKind::Volume => {
            let q = Quat::from_xyzw(rng.normal(), rng.normal(), rng.normal(), rng.normal());
            (inside, q.normalize())
        }
        SceneKind::Surface => {
            // Pick a face by area, put the point on it, lay the Gaussian flat on it.
            let areas = [h.y * h.z, h.x * h.z, h.x * h.y];
            let total: f32 = areas.iter().sum();
            let mut pick = rng.uniform(0.0, total);
            let mut axis = 0;
            while axis < 2 && pick >= areas[axis] {
                pick -= areas[axis];
                axis += 1;
            }
            let mut p = inside;
            p[axis] = if rng.next_f32() < 0.5 {
                -h[axis]
            } else {
                h[axis]
            };
            let mut normal = Vec3::ZERO;
            normal[axis] = 1.0;
            let base = Quat::from_rotation_arc(Vec3::Z, normal);
            let spin = Quat::from_rotation_z(rng.uniform(0.0, std::f32::consts::TAU));
            (p, (base * spin).normalize())
        }
    }
}

/// `n` Gaussians of the configuration-(d) layout, seeded.
pub(super) fn scene(
    n: usize,
    kind: SceneKind,
    config: &SunAwareConfig,
    seed: u64,
) -> GaussianModel {
    let mut rng = SplitMix64::new(seed);
    let h = Vec3::from_array(BOX_HALF_M);
    let spacing = match kind {
        SceneKind::Volume => (8.0 * h.x * h.y * h.z / n as f32).cbrt(),
        SceneKind::Surface => {
            let area = 8.0 * (h.y * h.z + h.x * h.z + h.x * h.y);
            (area / n as f32).sqrt()
        }
    };
    let mut g = GaussianModel::new(config.layout()).expect("layout");
    g.params.push_zeros(n);
    for i in 0..n {
        let (p, q) = scene_point(kind, &mut rng);
        let s = spacing * rng.uniform(0.4, 0.9);
        let log_scale = match kind {
            SceneKind::Volume => [
                s.ln(),
                (s * rng.uniform(0.5, 1.0)).ln(),
                (s * rng.uniform(0.5, 1.0)).ln(),
            ],
            SceneKind::Surface => [s.ln(), (s * rng.uniform(0.5, 1.0)).ln(), (0.1 * s).ln()],
        };
        let p_ = &mut g.params;
        p_.row_mut(Param::Mean, i).copy_from_slice(&p.to_array());
        p_.row_mut(Param::LogScale, i).copy_from_slice(&log_scale);
        p_.row_mut(Param::Rotation, i)
            .copy_from_slice(&[q.w, q.x, q.y, q.z]);
        p_.row_mut(Param::OpacityLogit, i)[0] = rng.uniform(-1.0, 2.5);
    }
    g
}

pub(super) fn camera(width: u32, height: u32) -> Camera {
    let dir = Vec3::new(0.6, -0.7, 0.4).normalize();
    Camera::look_at(
        Intrinsics::from_fov_x(0.7, width, height),
        dir * 6.0,
        Vec3::ZERO,
        Vec3::Z,
    )
}

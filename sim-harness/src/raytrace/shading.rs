//! Physically based shading: Lambertian diffuse plus a GGX microfacet specular lobe with the
//! separable Smith shadowing-masking term and Schlick's Fresnel, in the metallic-roughness
//! parameterisation; and the procedural surface details (MLI crinkle normals, solar-cell grid).
//!
//! BRDF (all vectors unit, n.l > 0, n.v > 0, h = normalize(l + v), alpha = roughness^2):
//!   f = (1 - metallic) * base / pi + D(h) * G1(v) * G1(l) * F(v.h) / (4 (n.l) (n.v))
//!   D = alpha^2 / (pi ((n.h)^2 (alpha^2 - 1) + 1)^2)
//!   G1(x) = 2 (n.x) / ((n.x) + sqrt(alpha^2 + (1 - alpha^2) (n.x)^2))
//!   F = F0 + (1 - F0) (1 - v.h)^5,  F0 = mix(0.04, base, metallic)
//! Invariants: outputs are finite and non-negative for unit inputs; evaluation is a pure
//! function of its arguments (deterministic).

use crate::target::Material;
use glam::Vec3;
use gs_core::rng::mix64;
use std::f32::consts::PI;

/// Reflectance at normal incidence of the dielectrics we model (index of refraction ~1.5).
pub(crate) const DIELECTRIC_F0: f32 = 0.04;

/// Material parameters at one surface point, after procedural detail.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct SurfacePoint {
    pub base_color: Vec3,
    pub metallic: f32,
    pub roughness: f32,
    /// Shading normal (unit), on the viewer's side.
    pub normal: Vec3,
}

/// GGX normal distribution D(h).
pub(crate) fn ggx_distribution(n_dot_h: f32, alpha: f32) -> f32 {
    let a2 = alpha * alpha;
    let d = n_dot_h * n_dot_h * (a2 - 1.0) + 1.0;
    a2 / (PI * d * d)
}

/// Smith G1 for GGX.
pub(crate) fn smith_g1(n_dot_x: f32, alpha: f32) -> f32 {
    let a2 = alpha * alpha;
    2.0 * n_dot_x / (n_dot_x + (a2 + (1.0 - a2) * n_dot_x * n_dot_x).sqrt())
}

/// Schlick's Fresnel approximation.
pub(crate) fn schlick_fresnel(f0: Vec3, v_dot_h: f32) -> Vec3 {
    let m = (1.0 - v_dot_h).clamp(0.0, 1.0);
    let m5 = (m * m) * (m * m) * m;
    f0 + (Vec3::ONE - f0) * m5
}

/// The BRDF value f(l, v) (per steradian), zero when either direction is below the surface.
pub(crate) fn brdf(point: &SurfacePoint, to_light: Vec3, to_viewer: Vec3) -> Vec3 {
    let n = point.normal;
    let n_dot_l = n.dot(to_light);
    let n_dot_v = n.dot(to_viewer);
    if n_dot_l <= 0.0 || n_dot_v <= 0.0 {
        return Vec3::ZERO;
    }
    let h = (to_light + to_viewer).normalize_or_zero();
    if h == Vec3::ZERO {
        return Vec3::ZERO;
    }
    let alpha = point.roughness * point.roughness;
    let n_dot_h = n.dot(h).max(0.0);
    let v_dot_h = to_viewer.dot(h).max(0.0);
    let f0 = Vec3::splat(DIELECTRIC_F0).lerp(point.base_color, point.metallic);
    let specular = schlick_fresnel(f0, v_dot_h)
        * (ggx_distribution(n_dot_h, alpha) * smith_g1(n_dot_v, alpha) * smith_g1(n_dot_l, alpha)
            / (4.0 * n_dot_l * n_dot_v));
    let diffuse = point.base_color * ((1.0 - point.metallic) / PI);
    diffuse + specular
}

/// The material at `position_m` with geometric normal `geometric_normal` (unit, facing the
/// viewer): applies the crinkle perturbation and the solar-cell grid.
pub(crate) fn surface_point(
    material: &Material,
    position_m: Vec3,
    geometric_normal: Vec3,
) -> SurfacePoint {
    let mut point = SurfacePoint {
        base_color: Vec3::from_array(material.base_color_linear),
        metallic: material.metallic,
        roughness: material.roughness,
        normal: geometric_normal,
    };
    if material.crinkle_amplitude > 0.0 {
        point.normal = crinkled_normal(
            geometric_normal,
            position_m / material.crinkle_scale_m,
            material.crinkle_amplitude,
        );
    }
    if material.cell_pitch_m > 0.0
        && on_cell_grid_line(position_m, geometric_normal, material.cell_pitch_m)
    {
        // Silver interconnects / gaps between cells.
        point.base_color = Vec3::splat(0.55);
        point.metallic = 0.9;
        point.roughness = 0.35;
    }
    point
}

/// Whether the point lies on the interconnect grid of a solar panel: lines of width ~6% of the
/// pitch along the two coordinate axes most parallel to the surface.
fn on_cell_grid_line(position_m: Vec3, normal: Vec3, pitch_m: f32) -> bool {
    let a = normal.abs();
    let (u, v) = if a.x >= a.y && a.x >= a.z {
        (position_m.y, position_m.z)
    } else if a.y >= a.z {
        (position_m.x, position_m.z)
    } else {
        (position_m.x, position_m.y)
    };
    let line_fraction = 0.03;
    let near_line = |c: f32| {
        let f = (c / pitch_m).rem_euclid(1.0);
        f < line_fraction || f > 1.0 - line_fraction
    };
    // Cells are twice as long as wide, like real string layouts.
    near_line(u) || near_line(v * 2.0)
}

/// Normal tilted by a smooth pseudo-random tangent field (two octaves of value noise): the
/// crinkles of multi-layer insulation. Stays within 90 degrees of `normal`.
fn crinkled_normal(normal: Vec3, p: Vec3, amplitude: f32) -> Vec3 {
    let field = noise_vector(p) + noise_vector(p * 2.7 + Vec3::splat(17.0)) * 0.5;
    let tangential = field - normal * field.dot(normal);
    (normal + tangential * amplitude).normalize_or(normal)
}

/// Three independent value-noise channels in [-1, 1].
fn noise_vector(p: Vec3) -> Vec3 {
    Vec3::new(
        value_noise(p, 0x51),
        value_noise(p, 0xA3),
        value_noise(p, 0xF7),
    )
}

/// Smoothly interpolated lattice noise in [-1, 1], hashed from integer cell coordinates.
fn value_noise(p: Vec3, channel: u64) -> f32 {
    let cell = p.floor();
    let f = p - cell;
    let smooth = f * f * (Vec3::splat(3.0) - 2.0 * f);
    let (ix, iy, iz) = (cell.x as i64, cell.y as i64, cell.z as i64);
    let corner = |dx: i64, dy: i64, dz: i64| {
        let key = ((ix + dx) as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
            ^ ((iy + dy) as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F)
            ^ ((iz + dz) as u64).wrapping_mul(0x1656_67B1_9E37_79F9)
            ^ channel;
        (mix64(key) >> 40) as f32 * (2.0 / (1u64 << 24) as f32) - 1.0
    };
    let lerp = |a: f32, b: f32, t: f32| a + (b - a) * t;
    let x00 = lerp(corner(0, 0, 0), corner(1, 0, 0), smooth.x);
    let x10 = lerp(corner(0, 1, 0), corner(1, 1, 0), smooth.x);
    let x01 = lerp(corner(0, 0, 1), corner(1, 0, 1), smooth.x);
    let x11 = lerp(corner(0, 1, 1), corner(1, 1, 1), smooth.x);
    lerp(lerp(x00, x10, smooth.y), lerp(x01, x11, smooth.y), smooth.z)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn point(metallic: f32, roughness: f32) -> SurfacePoint {
        SurfacePoint {
            base_color: Vec3::new(0.8, 0.5, 0.2),
            metallic,
            roughness,
            normal: Vec3::Z,
        }
    }

    /// Directional-hemispherical reflectance by midpoint quadrature over the hemisphere.
    fn albedo(p: &SurfacePoint, to_viewer: Vec3) -> Vec3 {
        let (n_theta, n_phi) = (400, 400);
        let mut sum = Vec3::ZERO;
        for i in 0..n_theta {
            let theta = (i as f32 + 0.5) / n_theta as f32 * PI / 2.0;
            for j in 0..n_phi {
                let phi = (j as f32 + 0.5) / n_phi as f32 * 2.0 * PI;
                let l = Vec3::new(
                    theta.sin() * phi.cos(),
                    theta.sin() * phi.sin(),
                    theta.cos(),
                );
                let d_omega = theta.sin() * (PI / 2.0 / n_theta as f32) * (2.0 * PI / n_phi as f32);
                sum += brdf(p, l, to_viewer) * l.z * d_omega;
            }
        }
        sum
    }

    #[test]
    fn brdf_is_reciprocal_and_energy_bounded() {
        let v = Vec3::new(0.3, -0.2, 0.9).normalize();
        let l = Vec3::new(-0.5, 0.4, 0.6).normalize();
        for (m, r) in [(0.0, 0.3), (1.0, 0.25), (0.5, 0.8)] {
            let p = point(m, r);
            let a = brdf(&p, l, v);
            let b = brdf(&p, v, l);
            assert!((a - b).abs().max_element() < 1e-5 * a.max_element().max(1.0));
            let reflectance = albedo(&p, v);
            assert!(reflectance.max_element() < 1.0 + 1e-3, "{reflectance:?}");
            assert!(reflectance.min_element() > 0.0);
        }
        // A Lambertian-only surface (roughness 1, dielectric) reflects about its albedo.
        let lambert = albedo(&point(0.0, 1.0), Vec3::Z);
        assert!((lambert.x - 0.8).abs() < 0.08, "{lambert:?}");
        assert_eq!(brdf(&point(0.0, 0.5), -Vec3::Z, v), Vec3::ZERO);
    }

    #[test]
    fn ggx_distribution_is_normalised() {
        // Integral of D(h) (n.h) over the hemisphere is 1.
        for alpha in [0.1f32, 0.4, 0.9] {
            let n = 20_000;
            let sum: f32 = (0..n)
                .map(|i| {
                    let theta = (i as f32 + 0.5) / n as f32 * PI / 2.0;
                    ggx_distribution(theta.cos(), alpha)
                        * theta.cos()
                        * theta.sin()
                        * (PI / 2.0 / n as f32)
                        * 2.0
                        * PI
                })
                .sum();
            assert!((sum - 1.0).abs() < 2e-3, "alpha {alpha}: {sum}");
        }
    }

    #[test]
    fn crinkles_perturb_but_stay_in_hemisphere_and_are_deterministic() {
        let mli = Material::gold_mli();
        let mut max_tilt = 0.0f32;
        for i in 0..500 {
            let p = Vec3::new(i as f32 * 0.013, (i as f32 * 0.7).sin(), 0.25);
            let a = surface_point(&mli, p, Vec3::Z);
            assert_eq!(a, surface_point(&mli, p, Vec3::Z));
            assert!((a.normal.length() - 1.0).abs() < 1e-5);
            assert!(a.normal.z > 0.0);
            max_tilt = max_tilt.max(a.normal.z.acos());
        }
        assert!(max_tilt > 0.15, "{max_tilt}");
        let paint = surface_point(&Material::white_paint(), Vec3::ONE, Vec3::Z);
        assert_eq!(paint.normal, Vec3::Z);
    }
}

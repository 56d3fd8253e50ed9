//! The three procedural targets, after the paper's (Cassini, Rosetta, a Starlink-like satellite).
//! Dimensions are plausible metres; the body-frame origin sits near the middle of each craft so
//! that a camera aimed at the origin frames it. Tessellation is chosen so each mesh has tens of
//! thousands of triangles (curved parts finely, flat parts subdivided for even sampling).
//!
//! Invariant: deterministic (no randomness), valid by construction.

use super::{Material, MeshBuilder, TargetMesh};
use glam::{Quat, Vec3};
use std::f32::consts::{FRAC_PI_2, TAU};

fn finish(builder: MeshBuilder) -> TargetMesh {
    builder
        .build()
        .expect("procedural meshes are valid by construction")
}

/// Cassini-like: tall bus (propulsion cylinder + electronics ring), ~4 m high-gain dish on top
/// with a subreflector on struts, a magnetometer boom, three finned RTGs, a probe, twin engines.
pub fn cassini() -> TargetMesh {
    let mut b = MeshBuilder::new();
    let gold = b.material(Material::gold_mli());
    let silver = b.material(Material::silver_mli());
    let white = b.material(Material::white_paint());
    let alu = b.material(Material::aluminium());
    let dark = b.material(Material::dark_grey());

    // Propulsion module (gold MLI) and electronics bus (12-sided, aluminium).
    b.frustum(
        Vec3::new(0.0, 0.0, -2.0),
        Vec3::new(0.0, 0.0, 1.0),
        0.75,
        0.75,
        96,
        24,
        true,
        gold,
    );
    b.frustum(
        Vec3::new(0.0, 0.0, 1.0),
        Vec3::new(0.0, 0.0, 1.6),
        1.1,
        1.1,
        12,
        4,
        true,
        alu,
    );
    // High-gain antenna: 4 m dish, focal length R^2 / (4 depth) = 1.82 m.
    let (dish_radius, dish_depth, dish_vertex_z) = (2.0, 0.55, 1.75);
    b.frustum(
        Vec3::new(0.0, 0.0, 1.6),
        Vec3::new(0.0, 0.0, 1.8),
        0.5,
        0.5,
        32,
        1,
        false,
        alu,
    );
    b.dish(
        Vec3::new(0.0, 0.0, dish_vertex_z),
        Vec3::Z,
        dish_radius,
        dish_depth,
        0.06,
        40,
        160,
        white,
        white,
    );
    let focus_z = dish_vertex_z + dish_radius * dish_radius / (4.0 * dish_depth);
    b.dish(
        Vec3::new(0.0, 0.0, focus_z + 0.08),
        -Vec3::Z,
        0.3,
        0.06,
        0.03,
        6,
        48,
        white,
        alu,
    );
    for k in 0..3 {
        let angle = TAU * k as f32 / 3.0 + 0.5;
        let foot_radius = 1.3;
        let foot = Vec3::new(
            foot_radius * angle.cos(),
            foot_radius * angle.sin(),
            dish_vertex_z + dish_depth * (foot_radius / dish_radius).powi(2),
        );
        b.frustum(
            foot,
            Vec3::new(0.0, 0.0, focus_z + 0.05),
            0.025,
            0.025,
            8,
            1,
            false,
            alu,
        );
    }
    // Magnetometer boom along +x from the electronics bus, with a sensor canister.
    b.frustum(
        Vec3::new(1.05, 0.0, 1.3),
        Vec3::new(6.0, 0.0, 1.3),
        0.05,
        0.05,
        12,
        8,
        false,
        silver,
    );
    b.frustum(
        Vec3::new(6.0, 0.0, 1.3),
        Vec3::new(6.35, 0.0, 1.3),
        0.12,
        0.12,
        24,
        1,
        true,
        white,
    );
    // Three RTGs on struts below the bus, tilted outward, each with eight radial fins.
    for k in 0..3 {
        let angle = TAU * k as f32 / 3.0 + 1.1;
        let radial = Vec3::new(angle.cos(), angle.sin(), 0.0);
        let base = radial * 1.05 + Vec3::new(0.0, 0.0, -1.2);
        let axis = (radial * 0.4 - Vec3::Z).normalize();
        let top = base + axis * 1.1;
        b.frustum(
            radial * 0.7 + Vec3::new(0.0, 0.0, -1.2),
            base,
            0.04,
            0.04,
            8,
            1,
            false,
            alu,
        );
        b.frustum(base, top, 0.2, 0.2, 48, 6, true, dark);
        let centre = (base + top) * 0.5;
        let fin_rotation = Quat::from_rotation_arc(Vec3::Z, axis);
        for f in 0..8 {
            let fin_angle = TAU * f as f32 / 8.0;
            let out = fin_rotation * Vec3::new(fin_angle.cos(), fin_angle.sin(), 0.0);
            let rotation = fin_rotation * Quat::from_rotation_z(fin_angle);
            b.oriented_box(
                centre + out * 0.3,
                Vec3::new(0.1, 0.008, 0.5),
                rotation,
                0.1,
                [dark; 6],
            );
        }
    }
    // Probe (conical heat shield with gold MLI back cover) on the -y side.
    b.frustum(
        Vec3::new(0.0, -0.8, -0.6),
        Vec3::new(0.0, -1.3, -0.6),
        1.3,
        0.4,
        96,
        8,
        true,
        gold,
    );
    // Twin main engines below the propulsion module (open nozzles).
    for x in [-0.35f32, 0.35] {
        b.frustum(
            Vec3::new(x, 0.0, -2.0),
            Vec3::new(x, 0.0, -2.15),
            0.08,
            0.08,
            24,
            1,
            false,
            alu,
        );
        b.frustum(
            Vec3::new(x, 0.0, -2.15),
            Vec3::new(x, 0.0, -2.9),
            0.1,
            0.32,
            48,
            6,
            false,
            dark,
        );
    }
    // Shift so the origin is near the middle of the stack (z from -2.9 to ~3.7).
    recentered(b, Vec3::new(0.0, 0.0, -0.4))
}

/// Rosetta-like: a 2.8 x 2.1 x 2.0 m box bus and two ~14 m solar wings of five panels each,
/// a 2.2 m steerable high-gain dish and a lander on the opposite face.
pub fn rosetta() -> TargetMesh {
    let mut b = MeshBuilder::new();
    let gold = b.material(Material::gold_mli());
    let silver = b.material(Material::silver_mli());
    let white = b.material(Material::white_paint());
    let alu = b.material(Material::aluminium());
    let cells = b.material(Material::solar_cell());
    let dark = b.material(Material::dark_grey());

    let bus_half = Vec3::new(1.4, 1.05, 1.0);
    // Faces: +x, -x, +y, -y, +z, -z.
    b.oriented_box(
        Vec3::ZERO,
        bus_half,
        Quat::IDENTITY,
        0.1,
        [gold, gold, silver, silver, white, gold],
    );
    // Solar wings along +y and -y: a yoke then five 2.25 x 2.74 m panels, cells facing +x.
    let (panel_len, panel_width, gap, yoke) = (2.25, 2.74, 0.06, 0.7);
    for side in [1.0f32, -1.0] {
        let root = bus_half.y + yoke;
        b.frustum(
            Vec3::new(0.0, side * bus_half.y, 0.0),
            Vec3::new(0.0, side * root, 0.0),
            0.05,
            0.05,
            16,
            2,
            true,
            alu,
        );
        for p in 0..5 {
            let centre_y = side * (root + panel_len / 2.0 + p as f32 * (panel_len + gap));
            b.oriented_box(
                Vec3::new(0.0, centre_y, 0.0),
                Vec3::new(0.02, panel_len / 2.0, panel_width / 2.0),
                Quat::IDENTITY,
                0.1,
                [cells, dark, dark, dark, dark, dark],
            );
        }
    }
    // High-gain antenna on a short mast on +x, tilted 30 degrees towards +z.
    let hga_axis = Quat::from_rotation_y(-FRAC_PI_2 / 3.0) * Vec3::X;
    b.frustum(
        Vec3::new(bus_half.x, 0.0, 0.3),
        Vec3::new(bus_half.x + 0.45, 0.0, 0.3),
        0.06,
        0.06,
        16,
        1,
        false,
        alu,
    );
    b.dish(
        Vec3::new(bus_half.x + 0.5, 0.0, 0.3),
        hga_axis,
        1.1,
        0.3,
        0.04,
        24,
        96,
        white,
        white,
    );
    // Lander (gold box with three legs) on -x.
    let lander_centre = Vec3::new(-bus_half.x - 0.45, 0.0, -0.2);
    b.simple_box(lander_centre, Vec3::new(0.45, 0.5, 0.4), 0.1, gold);
    for k in 0..3 {
        let angle = TAU * k as f32 / 3.0;
        let foot = lander_centre + Vec3::new(-0.9, 0.7 * angle.cos(), 0.7 * angle.sin());
        b.frustum(
            lander_centre + Vec3::new(-0.45, 0.0, 0.0),
            foot,
            0.03,
            0.03,
            8,
            1,
            false,
            alu,
        );
    }
    // Navigation cameras / star trackers on +z.
    for x in [-0.8f32, 0.8] {
        b.frustum(
            Vec3::new(x, 0.5, bus_half.z),
            Vec3::new(x, 0.5, bus_half.z + 0.35),
            0.1,
            0.12,
            24,
            1,
            true,
            dark,
        );
    }
    recentered(b, Vec3::ZERO)
}

/// Starlink-like: a flat 3.2 x 1.6 x 0.24 m bus with phased-array antennas underneath and a
/// single 10 x 2.8 m solar array on a short boom, stowed flat along +x.
pub fn starlink() -> TargetMesh {
    let mut b = MeshBuilder::new();
    let silver = b.material(Material::silver_mli());
    let white = b.material(Material::white_paint());
    let alu = b.material(Material::aluminium());
    let cells = b.material(Material::solar_cell());
    let dark = b.material(Material::dark_grey());

    let bus_half = Vec3::new(1.6, 0.8, 0.12);
    b.oriented_box(
        Vec3::ZERO,
        bus_half,
        Quat::IDENTITY,
        0.08,
        [alu, alu, alu, alu, silver, alu],
    );
    // Four phased-array antenna tiles and two parabolic backhaul antennas underneath.
    for (x, y) in [(-0.8f32, -0.4f32), (-0.8, 0.4), (0.8, -0.4), (0.8, 0.4)] {
        b.simple_box(
            Vec3::new(x, y, -bus_half.z - 0.02),
            Vec3::new(0.7, 0.33, 0.02),
            0.05,
            white,
        );
    }
    for x in [-0.2f32, 0.2] {
        b.dish(
            Vec3::new(x, 0.0, -bus_half.z - 0.04),
            -Vec3::Z,
            0.15,
            0.05,
            0.01,
            8,
            32,
            white,
            alu,
        );
    }
    // Hall thruster at -x.
    b.frustum(
        Vec3::new(-bus_half.x, 0.0, 0.0),
        Vec3::new(-bus_half.x - 0.15, 0.0, 0.0),
        0.07,
        0.09,
        24,
        1,
        false,
        dark,
    );
    // Boom from the +x edge and the array, tilted 20 degrees about x, cells facing +z (up).
    let boom_end = Vec3::new(bus_half.x + 0.6, 0.0, 0.35);
    b.frustum(
        Vec3::new(bus_half.x, 0.0, 0.0),
        boom_end,
        0.05,
        0.05,
        12,
        2,
        true,
        alu,
    );
    let (array_len, array_width) = (10.0, 2.8);
    let tilt = Quat::from_rotation_x(20f32.to_radians());
    let array_centre = boom_end + Vec3::new(array_len / 2.0, 0.0, 0.0);
    b.oriented_box(
        array_centre,
        Vec3::new(array_len / 2.0, array_width / 2.0, 0.015),
        tilt,
        0.07,
        [dark, dark, dark, dark, cells, dark],
    );
    // Stiffening spar along the back of the array.
    let spar_offset = tilt * Vec3::new(0.0, 0.0, -0.06);
    b.frustum(
        boom_end + spar_offset,
        boom_end + spar_offset + Vec3::new(array_len, 0.0, 0.0),
        0.04,
        0.04,
        12,
        20,
        true,
        alu,
    );
    // Body origin halfway along the whole craft.
    recentered(
        b,
        Vec3::new(-(bus_half.x + 0.6 + array_len - bus_half.x) / 2.0, 0.0, 0.0),
    )
}

/// Builds the mesh translated by `offset`.
fn recentered(b: MeshBuilder, offset: Vec3) -> TargetMesh {
    let mut moved = MeshBuilder::new();
    moved.append_transformed(&b, Quat::IDENTITY, offset);
    finish(moved)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn targets_have_tens_of_thousands_of_triangles_and_plausible_size() {
        for (mesh, min_radius, max_radius) in [
            (cassini(), 3.0, 8.0),
            (rosetta(), 10.0, 15.0),
            (starlink(), 4.0, 8.0),
        ] {
            let n = mesh.triangle_count();
            assert!((20_000..150_000).contains(&n), "{n}");
            let r = mesh.bounding_radius_m();
            assert!((min_radius..max_radius).contains(&r), "{r}");
        }
    }
}

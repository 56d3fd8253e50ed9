//! The procedural targets: size and tessellation as specified, the expected materials, a
//! deterministic build, and surface sampling that is uniform by area on a real target.

use sim_harness::target::{builtin_target, triangle_area_m2, BuiltinTarget};

#[test]
fn targets_are_deterministic_large_meshes_with_their_materials() {
    let expected_materials: [(BuiltinTarget, &[&str]); 3] = [
        (
            BuiltinTarget::Cassini,
            &["gold_mli", "white_paint", "aluminium", "dark_grey"],
        ),
        (
            BuiltinTarget::Rosetta,
            &["gold_mli", "solar_cell", "white_paint", "silver_mli"],
        ),
        (
            BuiltinTarget::Starlink,
            &["solar_cell", "aluminium", "white_paint"],
        ),
    ];
    for (kind, materials) in expected_materials {
        let mesh = builtin_target(kind);
        assert!(
            (20_000..200_000).contains(&mesh.triangle_count()),
            "{kind}: {}",
            mesh.triangle_count()
        );
        let radius = mesh.bounding_radius_m();
        assert!((2.0..16.0).contains(&radius), "{kind}: {radius}");
        for name in materials {
            assert!(
                mesh.materials().iter().any(|m| m.name == *name),
                "{kind} lacks {name}"
            );
        }
        let again = builtin_target(kind);
        assert_eq!(mesh.vertices_m(), again.vertices_m());
        assert_eq!(mesh.triangles(), again.triangles());
    }
}

#[test]
fn surface_samples_are_uniform_by_area_on_starlink() {
    let mesh = builtin_target(BuiltinTarget::Starlink);
    let n = 10_000;
    let samples = mesh.sample_surface(n, 42);
    assert_eq!(samples.len(), n);
    assert_eq!(samples, mesh.sample_surface(n, 42));
    let radius = mesh.bounding_radius_m();
    for s in &samples {
        assert!(s.position_m.is_finite() && s.position_m.length() <= radius + 1e-4);
        assert!((s.normal.length() - 1.0).abs() < 1e-4);
    }
    // The fraction of samples on solar cells matches the cells' share of the area.
    let cell_material = mesh
        .materials()
        .iter()
        .position(|m| m.name == "solar_cell")
        .unwrap() as u16;
    let cell_area: f64 = (0..mesh.triangle_count())
        .filter(|&t| mesh.material_of_triangle()[t] == cell_material)
        .map(|t| triangle_area_m2(mesh.triangle_corners_m(t)) as f64)
        .sum();
    let p = cell_area / mesh.surface_area_m2();
    let on_cells = samples
        .iter()
        .filter(|s| mesh.material_of_triangle()[s.triangle_index as usize] == cell_material)
        .count() as f64
        / n as f64;
    let sigma = (p * (1.0 - p) / n as f64).sqrt();
    assert!((on_cells - p).abs() < 4.0 * sigma, "{on_cells} vs {p}");
    assert!(p > 0.2 && p < 0.6, "{p}");
}

//! Tests of scenario loading, validation and the automatic relative orbit.

use super::*;

#[test]
fn empty_file_is_the_paper_setup() {
    let s = Scenario::from_toml_str("", Path::new(".")).unwrap();
    assert_eq!(s.frame_count(), 5764);
    let period = s.chief_elements().period_s();
    assert!((period - 5764.0).abs() < 1.0, "period {period}");
    let cam = s.camera_intrinsics();
    assert_eq!((cam.width, cam.height), (960, 600));
    assert!((cam.fx - 1501.705).abs() < 1e-9 && cam.cx == 480.0 && cam.cy == 300.0);
    assert_eq!(
        s.target_source().unwrap(),
        TargetSource::Builtin(BuiltinTarget::Cassini)
    );
    assert_eq!(s.attitude.tumble_rate_deg_s, 2.0);
}

#[test]
fn unknown_fields_and_bad_values_are_named() {
    let err = Scenario::from_toml_str("[camera]\nfocal_lenght_px = 3.0\n", Path::new("."))
        .unwrap_err()
        .to_string();
    assert!(err.contains("focal_lenght_px"), "{err}");
    let err = Scenario::from_toml_str("[target]\nbuiltin = \"hubble\"\n", Path::new("."))
        .unwrap_err()
        .to_string();
    assert!(err.contains("hubble"), "{err}");
    let err = Scenario::from_toml_str("[sequence]\ncadence_s = -1.0\n", Path::new("."))
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("sequence.cadence_s") && err.contains("-1"),
        "{err}"
    );
    let err = Scenario::from_toml_str("[chief_orbit]\ninclination_deg = 0.0\n", Path::new("."))
        .unwrap_err()
        .to_string();
    assert!(err.contains("inclination_deg"), "{err}");
    let err = Scenario::from_toml_str("epoch = 2024-03-20T12:00:00\n", Path::new("."))
        .unwrap_err()
        .to_string();
    assert!(err.contains("epoch") && err.contains("UTC"), "{err}");
    let err = Scenario::from_toml_str(
        "[attitude]\ninitial_quaternion = [1.0, 1.0, 0.0, 0.0]\n",
        Path::new("."),
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("unit quaternion"), "{err}");
    let err = Scenario::from_toml_str(
        "[target]\nbuiltin = \"rosetta\"\nobj = \"x.obj\"\n",
        Path::new("."),
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("not both"), "{err}");
    let err = Scenario::from_toml_str("[camera]\ndownsample = 0\n", Path::new("."))
        .unwrap_err()
        .to_string();
    assert!(err.contains("camera.downsample"), "{err}");
}

#[test]
fn overrides_shorten_and_downsample() {
    let s = Scenario::from_toml_str("", Path::new("."))
        .unwrap()
        .with_overrides(Some(12), Some(8), Some(3))
        .unwrap();
    assert_eq!(s.frame_count(), 12);
    assert_eq!(s.sequence.eval_views, 3);
    let cam = s.camera_intrinsics();
    assert_eq!((cam.width, cam.height), (240, 150));
    assert!((cam.fx - 3003.41 / 8.0).abs() < 1e-9);
    assert!(Scenario::default()
        .with_overrides(None, Some(1000), None)
        .is_err());
}

#[test]
fn automatic_relative_orbit_frames_the_target_and_is_safe() {
    let s = Scenario::default();
    let radius_m = 6.0;
    let geometry = s.geometry(TargetSize::sphere(radius_m)).unwrap();
    let a = s.chief_orbit.semi_major_axis_km * 1000.0;
    let min_rn = geometry.roe.min_radial_normal_separation_m(a);
    let half_fov = s.camera_intrinsics().min_half_fov_rad();
    // At the closest approach (radial-normal minimum, zero along-track) the bounding sphere
    // just fits the smaller field of view.
    assert!(((radius_m / min_rn).atan() - half_fov).abs() < 1e-9);
    let ranges: Vec<f64> = (0..1200)
        .map(|i| geometry.servicer_rtn_m(i as f64 * 5.0).length())
        .collect();
    let closest = ranges.iter().copied().fold(f64::INFINITY, f64::min);
    let farthest = ranges.iter().copied().fold(0.0, f64::max);
    assert!(
        (closest - min_rn).abs() < 0.05 && farthest < 2.25 * min_rn,
        "{closest} {farthest}"
    );
}

#[test]
fn automatic_relative_orbit_starts_on_the_sunlit_side() {
    for raan_deg in [0.0, 60.0, 150.0, 240.0, 330.0] {
        let mut s = Scenario::default();
        s.chief_orbit.raan_deg = raan_deg;
        let geometry = s.geometry(TargetSize::sphere(3.0)).unwrap();
        let phase_deg = geometry.at(0.0).phase_angle_rad.to_degrees();
        assert!(
            phase_deg < 90.0,
            "RAAN {raan_deg}: starts {phase_deg} deg from the Sun"
        );
        // A configured orbit is used as given, even when backlit.
        let roe_m = geometry
            .roe
            .scaled_m(s.chief_orbit.semi_major_axis_km * 1000.0);
        s.relative_orbit = Some(RelativeOrbitConfig {
            dey_m: -roe_m[3],
            diy_m: -roe_m[5],
            ..RelativeOrbitConfig::default()
        });
        let mirrored = s.geometry(TargetSize::sphere(3.0)).unwrap();
        let mirrored_deg = mirrored.at(0.0).phase_angle_rad.to_degrees();
        assert!(
            (mirrored_deg - (180.0 - phase_deg)).abs() < 0.5,
            "{mirrored_deg}"
        );
    }
}

#[test]
fn a_relative_orbit_through_the_target_is_rejected() {
    // e/i-separated by 3 m: the servicer flies 3..6.7 m from the centre of a 5 m target.
    let s = Scenario::from_toml_str(
        "[relative_orbit]\ndey_m = 3.0\ndiy_m = 3.0\n",
        Path::new("."),
    )
    .unwrap();
    let err = s.geometry(TargetSize::sphere(5.0)).unwrap_err().to_string();
    assert!(
        err.contains("relative_orbit") && err.contains("3.00 m"),
        "{err}"
    );
    // The same orbit is fine around a 1 m target; only the bounding radius matters here.
    let long_boom = TargetSize {
        bounding_radius_m: 5.0,
        framing_radius_m: 1.0,
    };
    assert!(s.geometry(long_boom).is_err());
    assert!(s.geometry(TargetSize::sphere(1.0)).is_ok());
}

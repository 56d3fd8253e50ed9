//! `Scenario::validate`: every number finite and in its range, quaternions unit, the epoch
//! a full UTC date-time; the error names the offending field.

use glam::{DQuat, DVec3};

use super::{invalid, Scenario, ScenarioError};

fn check_finite(field: &str, value: f64) -> Result<(), ScenarioError> {
    if value.is_finite() {
        Ok(())
    } else {
        Err(invalid(field, format!("{value} is not a finite number")))
    }
}

fn check_range(field: &str, value: f64, lo: f64, hi: f64) -> Result<(), ScenarioError> {
    check_finite(field, value)?;
    if value < lo || value > hi {
        return Err(invalid(field, format!("{value} is outside [{lo}, {hi}]")));
    }
    Ok(())
}

pub(super) fn unit_quaternion(field: &str, wxyz: [f64; 4]) -> Result<DQuat, ScenarioError> {
    let q = DQuat::from_xyzw(wxyz[1], wxyz[2], wxyz[3], wxyz[0]);
    if !q.is_finite() || (q.length() - 1.0).abs() > 1e-3 {
        return Err(invalid(
            field,
            format!(
                "{wxyz:?} is not a unit quaternion [w, x, y, z] (norm {})",
                q.length()
            ),
        ));
    }
    Ok(q.normalize())
}

impl Scenario {
    /// Checks every value's range; see the module header.
    pub fn validate(&self) -> Result<(), ScenarioError> {
        self.utc_epoch()?;
        let o = &self.chief_orbit;
        let earth_radius_km = crate::orbit::EARTH_RADIUS_M / 1000.0;
        check_range(
            "chief_orbit.semi_major_axis_km",
            o.semi_major_axis_km,
            earth_radius_km + 150.0,
            50_000.0,
        )?;
        check_range("chief_orbit.eccentricity", o.eccentricity, 0.0, 0.01)?;
        if o.semi_major_axis_km * (1.0 - o.eccentricity) < earth_radius_km + 150.0 {
            return Err(invalid(
                "chief_orbit.eccentricity",
                "perigee below 150 km altitude",
            ));
        }
        // The y component of the relative inclination vector divides by sin(i).
        check_range("chief_orbit.inclination_deg", o.inclination_deg, 1.0, 179.0)?;
        check_finite("chief_orbit.raan_deg", o.raan_deg)?;
        check_finite("chief_orbit.arg_perigee_deg", o.arg_perigee_deg)?;
        check_finite("chief_orbit.mean_anomaly_deg", o.mean_anomaly_deg)?;
        if let Some(r) = &self.relative_orbit {
            let names = ["da_m", "dl_m", "dex_m", "dey_m", "dix_m", "diy_m"];
            let values = [r.da_m, r.dl_m, r.dex_m, r.dey_m, r.dix_m, r.diy_m];
            for (name, value) in names.iter().zip(values) {
                // The linear map's error grows as separation^2 / a: 10 km gives ~10 m.
                check_range(
                    &format!("relative_orbit.{name}"),
                    value,
                    -10_000.0,
                    10_000.0,
                )?;
            }
        }
        let a = &self.attitude;
        unit_quaternion("attitude.initial_quaternion", a.initial_quaternion)?;
        let axis = DVec3::from_array(a.tumble_axis);
        if !axis.is_finite() || axis.length() < 1e-9 {
            return Err(invalid(
                "attitude.tumble_axis",
                format!("{:?} is not a usable axis", a.tumble_axis),
            ));
        }
        check_range(
            "attitude.tumble_rate_deg_s",
            a.tumble_rate_deg_s,
            -180.0,
            180.0,
        )?;
        let c = &self.camera;
        check_range("camera.focal_length_px", c.focal_length_px, 1.0, 1e6)?;
        for (field, value) in [
            ("camera.width_px", c.width_px),
            ("camera.height_px", c.height_px),
        ] {
            if !(8..=crate::raytrace::MAX_IMAGE_SIDE).contains(&value) {
                return Err(invalid(
                    field,
                    format!(
                        "{value} is outside [8, {}]",
                        crate::raytrace::MAX_IMAGE_SIDE
                    ),
                ));
            }
        }
        if c.downsample == 0 || c.width_px / c.downsample < 8 || c.height_px / c.downsample < 8 {
            return Err(invalid(
                "camera.downsample",
                format!(
                    "{} must be >= 1 and leave an image of at least 8x8 pixels",
                    c.downsample
                ),
            ));
        }
        if let Some([cx, cy]) = c.principal_point_px {
            check_range("camera.principal_point_px[0]", cx, 0.0, c.width_px as f64)?;
            check_range("camera.principal_point_px[1]", cy, 0.0, c.height_px as f64)?;
        }
        unit_quaternion("camera.mounting_quaternion", c.mounting_quaternion)?;
        self.target_source()?;
        if !(1..=10_000_000).contains(&self.target.surface_points) {
            return Err(invalid(
                "target.surface_points",
                format!("{} is outside [1, 10000000]", self.target.surface_points),
            ));
        }
        let s = &self.sequence;
        check_range("sequence.cadence_s", s.cadence_s, 0.001, 86_400.0)?;
        check_range("sequence.orbits", s.orbits, 0.0, 1000.0)?;
        if let Some(frames) = s.frames {
            if !(1..=10_000_000).contains(&frames) {
                return Err(invalid(
                    "sequence.frames",
                    format!("{frames} is outside [1, 10000000]"),
                ));
            }
        } else if self.frame_count() == 0 {
            return Err(invalid(
                "sequence.orbits",
                "the duration is shorter than one cadence: no frames",
            ));
        }
        if s.eval_views > 100_000 {
            return Err(invalid(
                "sequence.eval_views",
                format!("{} is above 100000", s.eval_views),
            ));
        }
        let r = &self.render;
        if !(1..=crate::raytrace::MAX_SAMPLES_PER_PIXEL).contains(&r.samples_per_pixel) {
            return Err(invalid(
                "render.samples_per_pixel",
                format!(
                    "{} is outside [1, {}]",
                    r.samples_per_pixel,
                    crate::raytrace::MAX_SAMPLES_PER_PIXEL
                ),
            ));
        }
        check_range("render.exposure", r.exposure, 0.0, 1e6)?;
        check_range("render.earth_albedo", r.earth_albedo, 0.0, 1.0)?;
        check_range(
            "render.eclipse_below_sun_fraction",
            r.eclipse_below_sun_fraction,
            0.0,
            1.0,
        )?;
        let n = &self.noise;
        check_range("noise.sun_bias_deg", n.sun_bias_deg, 0.0, 45.0)?;
        check_range("noise.sun_jitter_deg", n.sun_jitter_deg, 0.0, 45.0)?;
        check_range("noise.attitude_bias_deg", n.attitude_bias_deg, 0.0, 45.0)?;
        check_range(
            "noise.attitude_jitter_deg",
            n.attitude_jitter_deg,
            0.0,
            45.0,
        )?;
        check_range("noise.position_bias_m", n.position_bias_m, 0.0, 1000.0)?;
        check_range("noise.position_jitter_m", n.position_jitter_m, 0.0, 1000.0)?;
        Ok(())
    }
}

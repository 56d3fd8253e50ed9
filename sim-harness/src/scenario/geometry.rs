//! The scenario's relative orbit (configured, or the automatic passively safe e/i-separated
//! one sized to the target) and its full rendezvous geometry for a target's size.
//!
//! Invariant: `geometry` fails rather than bring the servicer within 1.5 bounding radii of
//! the target's centre.

use glam::DVec3;

use super::validate::unit_quaternion;
use super::{invalid, Scenario, ScenarioError};
use crate::orbit::{RendezvousGeometry, Roe, TumbleAttitude};

/// Closest-approach range of the automatic e/i-separated orbit is chosen so a sphere of the
/// target's framing radius (see `TargetSize`) spans this fraction of the smaller half field of
/// view: 1.0 = it just fits the frame height. The range then grows to 2.24 times that.
pub const AUTO_FILL_OF_HALF_FOV: f64 = 1.0;
/// The automatic orbit's relative e and i vectors point along +y or -y (phase +-90 deg: radial
/// and normal motion in quadrature, the largest along-track offset at the ascending node);
/// of the two, the one that starts with the servicer on the sunlit side is used.
const AUTO_EI_PHASES_RAD: [f64; 2] = [std::f64::consts::FRAC_PI_2, -std::f64::consts::FRAC_PI_2];

impl Scenario {
    /// The relative orbit: the configured one, or the automatic e/i-separated one (at e/i phase
    /// `auto_phase_rad`) whose closest approach lets a sphere of the target's framing radius
    /// fill `AUTO_FILL_OF_HALF_FOV` of the smaller half field of view.
    pub(crate) fn roe(&self, target: TargetSize, auto_phase_rad: f64) -> Roe {
        let a = self.chief_orbit.semi_major_axis_km * 1000.0;
        match &self.relative_orbit {
            Some(r) => Roe::from_scaled_m([r.da_m, r.dl_m, r.dex_m, r.dey_m, r.dix_m, r.diy_m], a),
            None => {
                let half_fov = self.camera_intrinsics().min_half_fov_rad();
                let separation_m =
                    target.framing_radius_m / (AUTO_FILL_OF_HALF_FOV * half_fov).tan();
                Roe::e_i_separated(separation_m, auto_phase_rad, a)
            }
        }
    }

    /// All geometry of the scenario for a target of the given size. Fails when the servicer
    /// would come closer than 1.5 bounding radii to the target's centre.
    pub fn geometry(&self, target: TargetSize) -> Result<RendezvousGeometry, ScenarioError> {
        let a = &self.attitude;
        let axis = DVec3::from_array(a.tumble_axis).normalize();
        let geometry = RendezvousGeometry {
            epoch: self.utc_epoch()?,
            chief: self.chief_elements(),
            roe: self.roe(target, AUTO_EI_PHASES_RAD[0]),
            target_attitude: TumbleAttitude {
                q_inertial_from_body_at_epoch: unit_quaternion(
                    "attitude.initial_quaternion",
                    a.initial_quaternion,
                )?,
                axis_body: axis,
                rate_rad_s: a.tumble_rate_deg_s.to_radians(),
            },
            q_body_from_camera: unit_quaternion(
                "camera.mounting_quaternion",
                self.camera.mounting_quaternion,
            )?,
            earth_albedo_strength: self.render.earth_albedo,
            eclipse_below_sun_fraction: self.render.eclipse_below_sun_fraction,
        };
        // Automatic orbit: start on the sunlit side (smaller Sun phase angle at the first frame),
        // so short runs do not begin with a backlit target.
        let geometry = if self.relative_orbit.is_none() {
            let flipped = RendezvousGeometry {
                roe: self.roe(target, AUTO_EI_PHASES_RAD[1]),
                ..geometry
            };
            if flipped.at(0.0).phase_angle_rad < geometry.at(0.0).phase_angle_rad {
                flipped
            } else {
                geometry
            }
        } else {
            geometry
        };
        // The relative orbit is periodic up to the along-track drift: check one orbit and the
        // whole run, sampled finely enough (at most 0.5 deg of orbit between samples).
        let duration_s =
            (self.frame_count() as f64 * self.sequence.cadence_s).max(geometry.chief.period_s());
        let samples = ((duration_s / geometry.chief.period_s()) * 720.0)
            .ceil()
            .min(1e6) as u32;
        let closest_m = (0..=samples)
            .map(|i| {
                geometry
                    .servicer_rtn_m(duration_s * i as f64 / samples as f64)
                    .length()
            })
            .fold(f64::INFINITY, f64::min);
        let keep_out_m = 1.5 * target.bounding_radius_m;
        if closest_m < keep_out_m {
            return Err(invalid(
                "relative_orbit",
                format!(
                    "the servicer comes within {closest_m:.2} m of the target centre, inside 1.5 x \
                     its bounding radius ({:.2} m)",
                    target.bounding_radius_m
                ),
            ));
        }
        Ok(geometry)
    }
}

/// Size of the target mesh, for sizing and checking the relative orbit.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TargetSize {
    /// Largest vertex distance from the body origin, metres.
    pub bounding_radius_m: f64,
    /// Radius holding most of the surface (the dataset uses the 90th percentile of the surface
    /// samples' distances): thin booms do not shrink the target in the frame.
    pub framing_radius_m: f64,
}

impl TargetSize {
    /// A target whose surface fills its bounding sphere.
    pub fn sphere(radius_m: f64) -> TargetSize {
        TargetSize {
            bounding_radius_m: radius_m,
            framing_radius_m: radius_m,
        }
    }
}

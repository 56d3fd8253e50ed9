//! Navigation telemetry the component consumes: the Sun direction from the AOCS and the
//! target's relative pose from relative navigation. Time tags are spacecraft time in
//! microseconds since the mission epoch. A message whose `valid` flag is false carries no
//! usable numbers and is not checked beyond its encoding; consumers must test `valid`.
//! `SunVector` 1.1 appends the AOCS's eclipse flag (left off the wire when not reported, so
//! such a message is byte-identical to 1.0).

use super::validate::{check_finite, check_non_negative, check_unit_norm, ValidationError};
use super::{appended, port, Direction, Message, Version};
use serde::{Deserialize, Serialize};

/// Sun direction from the AOCS.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SunVector {
    pub time_us: u64,
    /// Unit vector from the servicer towards the Sun, servicer body frame.
    pub sun_body: [f32; 3],
    /// False when the AOCS has no Sun solution (sensor blind, eclipse flag, fault).
    pub valid: bool,
    /// 1.1: `Some(true)` when the servicer and target are in the Earth's shadow, `Some(false)`
    /// when sunlit, `None` when not reported (every 1.0 message). The eclipse rule the
    /// component applies is in the ICD (interfaces/README.md).
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "appended::deserialize"
    )]
    pub eclipse: Option<bool>,
}

impl SunVector {
    /// Largest possible encoding, bytes (varints at their widest, the eclipse flag present).
    pub const MAX_ENCODED_LEN: usize = 25;
}

impl Message for SunVector {
    const PORT_ID: u16 = port::SUN_VECTOR;
    const VERSION: Version = Version { major: 1, minor: 1 };
    const NAME: &'static str = "SunVector";
    const DIRECTION: Direction = Direction::ToComponent;

    fn validate(&self) -> Result<(), ValidationError> {
        if self.valid {
            check_unit_norm("sun_body", &self.sun_body)?;
        }
        Ok(())
    }
}

/// Relative pose of the target from relative navigation.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct TargetPose {
    pub time_us: u64,
    /// Unit quaternion [w, x, y, z] rotating target-body vectors into the camera frame.
    pub q_camera_from_target: [f32; 4],
    /// Target body origin in the camera frame, metres (camera frame: +z along the boresight).
    pub t_camera_from_target_m: [f32; 3],
    /// 1-sigma position uncertainty, metres.
    pub position_sigma_m: f32,
    /// 1-sigma attitude uncertainty, radians.
    pub attitude_sigma_rad: f32,
    pub valid: bool,
}

impl TargetPose {
    /// Largest possible encoding, bytes.
    pub const MAX_ENCODED_LEN: usize = 47;
}

impl Message for TargetPose {
    const PORT_ID: u16 = port::TARGET_POSE;
    const VERSION: Version = Version { major: 1, minor: 0 };
    const NAME: &'static str = "TargetPose";
    const DIRECTION: Direction = Direction::ToComponent;

    fn validate(&self) -> Result<(), ValidationError> {
        if self.valid {
            check_unit_norm("q_camera_from_target", &self.q_camera_from_target)?;
            check_finite("t_camera_from_target_m", &self.t_camera_from_target_m)?;
            check_non_negative("position_sigma_m", self.position_sigma_m)?;
            check_non_negative("attitude_sigma_rad", self.attitude_sigma_rad)?;
        }
        Ok(())
    }
}

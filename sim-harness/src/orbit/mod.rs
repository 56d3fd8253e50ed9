//! Relative orbit (ROE), two-body reference propagation, Sun ephemeris, Earth shadow, target attitude.
//!
//! All orbit quantities are f64 SI units (metres, seconds, radians) in the Earth-centred inertial
//! frame EME2000 ("ECI") unless a name says otherwise. Conversion to f32 happens only at the
//! renderer boundary, after positions have been made relative (tens of metres), so no precision
//! is lost.

pub mod attitude;
pub mod kepler;
pub mod roe;
pub mod sequence;
pub mod shadow;
pub mod sun;
pub mod time;

pub use attitude::{look_at_camera_from_inertial, TumbleAttitude};
pub use kepler::{KeplerElements, OrbitState, RtnFrame};
pub use roe::Roe;
pub use sequence::{FrameGeometry, RendezvousGeometry};
pub use shadow::sun_visible_fraction;
pub use sun::sun_position_eci_m;
pub use time::UtcEpoch;

/// Earth's gravitational parameter (EGM2008 / WGS-84 value), m^3/s^2.
pub const EARTH_MU_M3_S2: f64 = 3.986_004_418e14;
/// Earth's equatorial radius (Montenbruck & Gill), metres.
pub const EARTH_RADIUS_M: f64 = 6_378_136.3;
/// Solar radius used by the conical shadow model (Montenbruck & Gill), metres.
pub const SUN_RADIUS_M: f64 = 696_000_000.0;
/// Astronomical unit, metres.
pub const AU_M: f64 = 149_597_870_700.0;

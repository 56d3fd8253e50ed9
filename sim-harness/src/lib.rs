//! sim-harness: rendezvous scenario simulator with ray-traced ground truth.

pub mod busfeed;
pub mod dataset;
pub mod experiment;
pub mod orbit;
pub mod raytrace;
pub mod scenario;
pub mod target;

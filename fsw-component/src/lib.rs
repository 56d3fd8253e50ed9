//! The flight component: keyframe window, synchronizer, training scheduler and transports.

pub mod config;
pub mod keyframe;
pub mod logfmt;
pub mod sync;
pub mod transport;

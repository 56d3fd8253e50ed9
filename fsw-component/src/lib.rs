//! The flight component: keyframe window, synchronizer, training scheduler and transports.

pub mod config;
pub mod keyframe;
pub mod logfmt;
pub mod online;
pub mod sync;
pub mod transport;
pub mod checkpoint;
pub mod imagemetrics;
pub mod learner;
pub mod nearest_learner;
pub mod worker;
pub mod bus;
pub mod core;
pub mod health;
pub mod recorder;
pub mod replay;
pub mod runtime;
pub mod sunaware_learner;

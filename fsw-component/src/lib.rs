//! The flight component: keyframe window, synchronizer, training scheduler and transports.

pub mod bus;
pub mod checkpoint;
pub mod cmdauth;
pub mod config;
pub mod core;
pub mod health;
pub mod imagemetrics;
pub mod keyframe;
pub mod learner;
pub mod logfmt;
pub mod nearest_learner;
pub mod online;
pub mod recorder;
pub mod replay;
pub mod runtime;
pub mod sunaware_learner;
pub mod sync;
pub mod timeguard;
pub mod transport;
pub mod worker;

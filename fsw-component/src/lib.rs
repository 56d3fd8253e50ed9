//! The flight component: transports, synchronizer, training scheduler, publishers, commands
//! and checkpoints around the online trainer of `gs-online`.

pub mod camera;
pub mod checkpoint;
pub mod cmdauth;
pub mod config;
pub mod cyphal_config;
pub mod engines;
pub mod health;
pub mod hull_start;
pub mod inbound;
pub mod learner;
pub mod logfmt;
pub mod model_store;
pub mod nearest_learner;
pub mod node;
pub mod outbound;
pub mod recorder;
pub mod registers;
pub mod replay;
pub mod runtime;
pub mod sunaware_learner;
pub mod sync;
pub mod timeguard;
pub mod transport;
pub mod worker;

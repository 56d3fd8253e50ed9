//! The online training procedure of the paper, independent of any bus or runtime.
//!
//! Data flow: frames (image, mask, camera, Sun vector) -> [`online::OnlineTrainer::offer`]
//! (validation, skips, the [`keyframe`] window rule) -> training rounds on the window (and
//! an optional replay memory) in `gs-core` -> renders scored by [`imagemetrics`].
//! Depends only on `gs-core`: the flight component (`fsw-component`, tokio and SocketCAN)
//! and the simulator (`sim-harness`) both drive it, so experiments run the flight code.

pub mod imagemetrics;
pub mod keyframe;
pub mod online;
pub mod resume;

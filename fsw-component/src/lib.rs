//! The flight component: keyframe window, synchronizer, training scheduler and transports.

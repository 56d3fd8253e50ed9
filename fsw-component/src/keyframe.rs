//! Keyframe window of the paper: add on view change, keep the two newest, evict the most redundant.

//! Adam with per-group learning rates and the 3DGS exponential schedule.

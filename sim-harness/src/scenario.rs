//! Scenario files (TOML): orbit, attitude, camera, target, cadence, noise.

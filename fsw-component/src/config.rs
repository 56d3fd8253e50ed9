//! Component configuration (config/component.toml).

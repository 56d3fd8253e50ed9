//! The device engines this build has: the one place the component names a backend crate
//! (cargo feature `wgpu`: crate gs-wgpu). The simulator uses the same list (its feature
//! `wgpu` turns on this crate's). A backend the build lacks is an error naming the
//! feature when it is checked or opened (`BackendKind::check_compiled_in`, `open`).

use gs_core::engine::DeviceEngines;

/// The engines compiled in ([`gs_core::sunaware::BackendKind::open`] takes them).
pub fn device_engines() -> DeviceEngines {
    DeviceEngines {
        #[cfg(feature = "wgpu")]
        wgpu: Some(gs_wgpu::open_engine),
        #[cfg(not(feature = "wgpu"))]
        wgpu: None,
    }
}

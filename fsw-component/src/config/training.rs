//! `[training]` of the component configuration: the trainer's settings and the model keys
//! beyond the model's form (the light camera, the replay memory, the learning rates), and
//! the online trainer's configuration they give ([`ComponentConfig::online_config`]).
//!
//! The defaults are the `sim-harness demo` preset's model and trainer
//! (config/presets/demo.toml); the window and timing keys follow the paper's cadence
//! instead (config/component.toml lists the differences).
//! Invariants: every value is checked when the file loads, the error naming its key.

use super::{invalid, ComponentConfig, ConfigError};
use crate::sunaware_learner::SunAwareSettings;
use gs_core::fpmode::DenormalMode;
use gs_core::sunaware::RateOverrides;
use gs_online::keyframe::WindowConfig;
use gs_online::online::OnlineConfig;
use serde::{Deserialize, Serialize};

/// Largest `training.replay_capacity`: the memory holds whole frames (1.2 GB for 32 at the
/// SPEED camera's 1920x1200), so a typo must not ask for thousands.
pub(crate) const MAX_REPLAY_CAPACITY: usize = 1024;
/// Largest `training.replay_steps_per_round`: a round must still end within minutes.
pub(crate) const MAX_REPLAY_STEPS_PER_ROUND: usize = 1000;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TrainingConfig {
    /// Model configuration of the paper's Table I: "a" (3DGS), "b" (+ appearance MLP),
    /// "c" (+ shadow splatting) or "d" (+ isotropic loss).
    pub variant: String,
    /// Passes over the keyframe window per training round (the paper: 1). More passes
    /// train each keyframe more often at the same frame rate, and make a round longer.
    pub passes_per_round: u32,
    /// Keyframe window size W.
    pub window_size: usize,
    /// A frame becomes a keyframe when its view moved more than this, degrees.
    pub min_view_angle_deg: f64,
    /// Worker threads of the trainer (fixed for bit-identical results).
    pub threads: usize,
    /// Where training runs: "cpu" (default) or "wgpu" (needs the cargo feature `wgpu` and a
    /// Vulkan adapter; either missing stops the start with an error, never a silent
    /// fallback). On "wgpu" a round's steps run device-resident (docs/gpu.md).
    pub backend: String,
    /// On "wgpu": bit-identical results run to run (default `true`, so a replay of the
    /// same telemetry gives the same model), or `false` for the float-atomic backward,
    /// faster where the device's atomics are, whose last bits vary from run to run.
    pub gpu_deterministic: bool,
    /// Width of the appearance network's (Phi's) hidden layers. Default 64, the demo's
    /// (docs/results/accuracy.md section 6: against 128, +0.21 dB on new Sun directions and
    /// -0.10 dB on held-out frames over three seeds, in 0.74x the training time).
    pub appearance_hidden_width: usize,
    /// Positional-encoding frequencies of the Sun and view directions. Default 2, the
    /// recommended preset's (the paper's 4 scored lower in the sweep at the same cost).
    pub encoding_frequencies: usize,
    /// The networks' matrix products: "f32" (default) or "bf16" (AMX-BF16 or AVX-512 BF16
    /// only; a CPU with neither fails validation).
    pub mlp_precision: String,
    /// Colour times `k_a + (1 - k_a) max(0, n.s)`: "lambert_learned" (default: a learned
    /// normal n per Gaussian, the demo's model), "none" (the paper) or "lambert" (the
    /// shortest scale axis; CPU only). Configuration (a) has no Phi colour and stays plain.
    pub shading: String,
    /// What Phi reads beyond the feature: "local" (default: and `[n.s, n.v, n.h]` of the
    /// learned normal; needs `shading = "lambert_learned"`; both backends), "paper" or
    /// "local_no_sun". With `shading = "lambert_learned"` and "local" the demo scored
    /// +1.0 dB on held-out frames and +2.0 dB on new Sun directions (docs/results/accuracy.md).
    pub appearance_inputs: String,
    /// What the model's colours and blend are: "linear" (default, the demo's: linear
    /// radiance, each rendered pixel sRGB-encoded as a camera does; configurations b-d) or
    /// "srgb" (the paper's form); both backends.
    pub colour_space: String,
    /// `V' = shadow_gain * V * Psi` in configurations (c)-(d), 0.5 to 8 (default 2, the
    /// demo's; the paper's form is 1).
    pub shadow_gain: f32,
    /// Side of the shadow pass's light image, pixels, 8 to 8192 (default 96, the demo's:
    /// `SunAwareConfig::light.resolution_px`; gs-core's own default is 256).
    pub light_resolution_px: u32,
    /// Evicted keyframes kept for replay, 0 to `MAX_REPLAY_CAPACITY` (default 32, the
    /// demo's; 0: none, the paper). Memory: one frame's image and mask each, `H * W * 16`
    /// bytes (37 MB at 1920x1200: 1.2 GB for 32).
    pub replay_capacity: usize,
    /// Training steps per round on frames drawn from the replay memory, after the window's
    /// steps, 0 to `MAX_REPLAY_STEPS_PER_ROUND` (default 6, the demo's).
    pub replay_steps_per_round: usize,
    /// Learning rates replacing gs-core's defaults (`[training.rates]`, gs-core's
    /// [`RateOverrides`], the table the simulator's presets read as `[rates]`); default the
    /// demo's `sh_dc = 0.01, feature = 0.01, opacity = 0.05` (4x and 2x the 3DGS rates).
    /// A file's table replaces these key by key: the rates it does not name keep them.
    #[serde(deserialize_with = "rates_over_the_defaults")]
    pub rates: RateOverrides,
    /// A trainer job (a frame with its training round, or a command) running longer than
    /// this is reported with an `Internal` event (`ROUND_DEADLINE_MISSED`), once per job,
    /// within the 50 ms housekeeping tick. 100 ms to one hour.
    pub round_deadline_ms: u64,
    /// Subnormal floats on the trainer's threads: "flush-to-zero" (default; x86 FTZ + DAZ,
    /// aarch64 FZ; with "ieee" the step took about 1.46x the CPU time on an Intel Xeon) or
    /// "ieee" (gradual underflow). Deterministic either way; the two differ in the last
    /// bits. `GS_DENORMALS` overrides it in the binary (`gs_core::fpmode`).
    pub denormals: String,
}

impl Default for TrainingConfig {
    fn default() -> Self {
        let window = WindowConfig::default();
        Self {
            variant: "d".to_string(),
            passes_per_round: 1,
            window_size: window.capacity,
            min_view_angle_deg: window.min_view_angle_deg,
            threads: 2,
            backend: "cpu".to_string(),
            gpu_deterministic: true,
            appearance_hidden_width: 64,
            encoding_frequencies: 2,
            mlp_precision: "f32".to_string(),
            // The model docs/results/accuracy.md measured best (the demo preset's).
            shading: "lambert_learned".to_string(),
            appearance_inputs: "local".to_string(),
            colour_space: "linear".to_string(),
            shadow_gain: 2.0,
            // The demo's light camera, replay memory and rates (config/presets/demo.toml,
            // measured in docs/results/accuracy.md); `demo_preset_keys_are_the_defaults`
            // in config/tests.rs compares them with that file.
            light_resolution_px: 96,
            replay_capacity: 32,
            replay_steps_per_round: 6,
            rates: default_rates(),
            round_deadline_ms: 60_000,
            denormals: DenormalMode::default().name().to_string(),
        }
    }
}

/// The demo's `[rates]`, the default `[training.rates]`.
fn default_rates() -> RateOverrides {
    RateOverrides {
        sh_dc: Some(0.01),
        feature: Some(0.01),
        opacity: Some(0.05),
        ..RateOverrides::default()
    }
}

/// A file's `[training.rates]` over the default table, so naming one rate keeps the
/// demo's others (as every other key of the file: only what differs is written).
fn rates_over_the_defaults<'de, D: serde::Deserializer<'de>>(
    d: D,
) -> Result<RateOverrides, D::Error> {
    Ok(RateOverrides::deserialize(d)?.or(default_rates()))
}

impl ComponentConfig {
    /// The online trainer's configuration: the window, passes, replay memory and the model
    /// ([`Self::model_config`]: its keys, light camera and rates), over the settings the
    /// adapter starts from (`SunAwareSettings::with_window`). What the binary trains with.
    pub fn online_config(&self) -> Result<OnlineConfig, ConfigError> {
        let t = &self.training;
        if t.replay_capacity > MAX_REPLAY_CAPACITY {
            return Err(invalid(
                "training.replay_capacity",
                format!("{} is above {MAX_REPLAY_CAPACITY}", t.replay_capacity),
            ));
        }
        if t.replay_steps_per_round > MAX_REPLAY_STEPS_PER_ROUND {
            return Err(invalid(
                "training.replay_steps_per_round",
                format!(
                    "{} is above {MAX_REPLAY_STEPS_PER_ROUND}",
                    t.replay_steps_per_round
                ),
            ));
        }
        let mut online = SunAwareSettings::with_window(self.window_config()?).online;
        online.passes_per_round = t.passes_per_round;
        online.replay_capacity = t.replay_capacity;
        online.replay_steps_per_round = t.replay_steps_per_round;
        online.model = self.model_config()?;
        Ok(online)
    }
}

//! Tests of `config` (a child module, so they reach its private items).

use super::*;
use gs_core::sunaware::{AppearanceInputs, ColourSpace, RateOverrides, Shading};

fn parse(text: &str) -> Result<ComponentConfig, ConfigError> {
    ComponentConfig::from_toml_str(text, Path::new("test.toml"))
}

fn invalid_key(text: &str) -> &'static str {
    match parse(text) {
        Err(ConfigError::Invalid { key, .. }) => key,
        other => panic!("expected an invalid key for {text:?}, got {other:?}"),
    }
}

#[test]
fn empty_file_gives_the_defaults() {
    let config = parse("").unwrap();
    assert_eq!(config, ComponentConfig::default());
    assert_eq!(config.window_config().unwrap(), WindowConfig::default());
    assert_eq!(config.sync_config().unwrap(), SyncConfig::default());
}

#[test]
fn defaults_round_trip_through_toml() {
    let text = ComponentConfig::default().to_toml_string();
    assert_eq!(parse(&text).unwrap(), ComponentConfig::default());
}

#[test]
fn unknown_keys_and_wrong_types_are_parse_errors() {
    for text in [
        "[node]\nnode_idd = 3\n",
        "[nodes]\nnode_id = 3\n",
        "[node]\nnode_id = \"three\"\n",
        "[node]\nnode_id = 300\n",
        "[udp]\nbind_ip = \"localhost\"\n",
        "[camera]\ncamera_from_body_wxyz = [1.0, 0.0, 0.0]\n",
    ] {
        match parse(text) {
            Err(ConfigError::Parse { message, .. }) => {
                assert!(!message.is_empty(), "{text:?}");
            }
            other => panic!("expected a parse error for {text:?}, got {other:?}"),
        }
    }
    let message = parse("[node]\nnode_idd = 3\n").unwrap_err().to_string();
    assert!(message.contains("node_idd"), "{message}");
}

#[test]
fn training_backend_is_validated_against_the_build() {
    let config = parse("[training]\nbackend = \"cpu\"\n").unwrap();
    assert_eq!(config.backend().unwrap(), BackendKind::Cpu);
    assert_eq!(
        invalid_key("[training]\nbackend = \"cuda\"\n"),
        "training.backend"
    );
    // Phi's local inputs (the default) run there too: see
    // `wgpu_with_local_inputs_is_accepted_and_lambert_refused_at_load`.
    let wgpu = parse("[training]\nbackend = \"wgpu\"\nappearance_inputs = \"paper\"\n");
    if cfg!(feature = "wgpu") {
        assert_eq!(wgpu.unwrap().backend().unwrap(), BackendKind::Wgpu);
    } else {
        let message = wgpu.unwrap_err().to_string();
        assert!(
            message.contains("training.backend") && message.contains("feature `wgpu`"),
            "{message}"
        );
    }
}

/// The default model is the demo's, measured best (docs/results/accuracy.md): the
/// learned-normal shading, Phi's local-frame inputs and V' = 2 V Psi.
#[test]
fn the_default_model_is_the_demos() {
    let model = ComponentConfig::default().model_config().unwrap();
    assert_eq!(model.shading, Shading::LambertLearned);
    assert_eq!(model.appearance_inputs, AppearanceInputs::Local);
    assert_eq!(model.shadow_gain, 2.0);
    assert_eq!(
        model.layout().normal_dim,
        3,
        "the learned normal is a parameter"
    );
    // The paper's model stays one file away.
    let paper =
        parse("[training]\nshading = \"none\"\nappearance_inputs = \"paper\"\nshadow_gain = 1.0\n")
            .unwrap()
            .model_config()
            .unwrap();
    assert_eq!(
        (paper.shading, paper.appearance_inputs, paper.shadow_gain),
        (Shading::None, AppearanceInputs::Paper, 1.0)
    );
    // Configuration (a) has no Phi colour to shade: the defaults leave it plain.
    let a = parse("[training]\nvariant = \"a\"\n")
        .unwrap()
        .model_config()
        .unwrap();
    assert_eq!(
        (a.shading, a.appearance_inputs, a.layout().normal_dim),
        (Shading::None, AppearanceInputs::Paper, 0)
    );
}

/// wgpu runs Phi's local-frame inputs (the default) with the learned-normal shading, in
/// either colour space: such a file passes the model rule when it loads (then needs the
/// build's feature); the shortest-axis `shading = "lambert"` is still refused at load,
/// naming the backend and the setting, in every build.
#[test]
fn wgpu_with_local_inputs_is_accepted_and_lambert_refused_at_load() {
    for (inputs, want) in [
        ("", AppearanceInputs::Local),
        ("appearance_inputs = \"local\"\n", AppearanceInputs::Local),
        (
            "appearance_inputs = \"local_no_sun\"\n",
            AppearanceInputs::LocalNoSun,
        ),
    ] {
        let text = format!("[training]\nbackend = \"wgpu\"\n{inputs}");
        let loaded = parse(&text);
        if cfg!(feature = "wgpu") {
            let model = loaded.unwrap().model_config().unwrap();
            assert_eq!(model.appearance_inputs, want, "{text:?}");
            assert_eq!(model.shading, Shading::LambertLearned, "{text:?}");
        } else {
            // Refused for the build only, not for the model.
            let message = loaded.unwrap_err().to_string();
            assert!(
                message.contains("training.backend")
                    && message.contains("feature `wgpu`")
                    && !message.contains("appearance_inputs"),
                "{text:?}: {message}"
            );
        }
    }
    let lambert =
        "[training]\nbackend = \"wgpu\"\nappearance_inputs = \"paper\"\nshading = \"lambert\"\n";
    let message = parse(lambert).unwrap_err().to_string();
    assert!(
        message.contains("training.backend") && message.contains("\"lambert\""),
        "{message}"
    );
    // What the device runs passes the model rule (then needs the build's feature), the
    // linear colour space included.
    let runs = parse(
        "[training]\nbackend = \"wgpu\"\nappearance_inputs = \"paper\"\nshadow_gain = 2.0\n\
         colour_space = \"linear\"\n",
    );
    match runs {
        Ok(config) => {
            let model = config.model_config().unwrap();
            assert_eq!(
                (model.shading, model.colour_space),
                (Shading::LambertLearned, ColourSpace::Linear)
            );
        }
        Err(e) => assert!(e.to_string().contains("feature `wgpu`"), "{e}"),
    }
    // The CPU runs every model.
    assert!(parse(
        "[training]\nbackend = \"cpu\"\nshading = \"lambert\"\nappearance_inputs = \"paper\"\n"
    )
    .is_ok());
}

#[test]
fn validation_names_the_key() {
    assert_eq!(invalid_key("[node]\nnode_id = 128\n"), "node.node_id");
    assert_eq!(invalid_key("[can]\ninterface = \"\"\n"), "can.interface");
    for bad in ["prediction_max_bytes = 0", "prediction_max_bytes = 65537"] {
        assert_eq!(
            invalid_key(&format!("[can]\n{bad}\n")),
            "can.prediction_max_bytes"
        );
    }
    // The prediction subject is one of [cyphal.subjects]: above 6143 (the heartbeat's
    // 7509 included) and subjects of other ports (health, pose) are refused there.
    for subject in [8192, 7509, 400, 101] {
        match parse(&format!(
            "[cyphal.subjects]\nrendered_prediction = {subject}\n"
        )) {
            Err(ConfigError::Cyphal(e)) => {
                assert_eq!(e.key, "cyphal.subjects.rendered_prediction", "{subject}");
            }
            other => panic!("subject {subject}: expected a refusal, got {other:?}"),
        }
    }
    let moved = parse("[cyphal.subjects]\nrendered_prediction = 6000\n").unwrap();
    assert_eq!(moved.cyphal.subjects.rendered_prediction, 6000);
    assert_eq!(
        invalid_key("[can]\ninterface = \"a_very_long_ifname0\"\n"),
        "can.interface"
    );
    assert_eq!(
        invalid_key("[can]\nenabled = false\n[udp]\nenabled = false\n"),
        "can.enabled"
    );
    assert_eq!(
        invalid_key("[udp]\nframes_port = 9000\ntelemetry_port = 9000\n"),
        "udp.telemetry_port"
    );
    assert_eq!(
        invalid_key("[udp]\npredictions_to = \"0.0.0.0:9000\"\n"),
        "udp.predictions_to"
    );
    assert_eq!(
        invalid_key("[udp]\nhealth_to = \"127.0.0.1:0\"\n"),
        "udp.health_to"
    );
    assert_eq!(
        invalid_key("[camera]\ncamera_from_body_wxyz = [1.0, 1.0, 0.0, 0.0]\n"),
        "camera.camera_from_body_wxyz"
    );
    assert_eq!(
        invalid_key("[camera]\ncamera_from_body_wxyz = [nan, 0.0, 0.0, 0.0]\n"),
        "camera.camera_from_body_wxyz"
    );
    assert_eq!(
        invalid_key("[sync]\nbuffer_capacity = 1\n"),
        "sync.buffer_capacity"
    );
    assert_eq!(invalid_key("[sync]\nmax_gap_ms = 0\n"), "sync.max_gap_ms");
    assert_eq!(
        invalid_key("[sync]\ntime_tag_tolerance_ms = 0\n"),
        "sync.time_tag_tolerance_ms"
    );
    assert_eq!(
        invalid_key("[sync]\nresync_after_samples = 1\n"),
        "sync.resync_after_samples"
    );
    assert_eq!(
        invalid_key("[commands]\ncan_source_nodes = [1, 128]\n"),
        "commands.can_source_nodes"
    );
    assert_eq!(
        invalid_key("[commands]\narm_timeout_ms = 0\n"),
        "commands.arm_timeout_ms"
    );
    assert_eq!(
        invalid_key("[sync]\nunit_norm_tolerance = 0.0\n"),
        "sync.unit_norm_tolerance"
    );
    assert_eq!(
        invalid_key("[sync]\nmax_wait_ms = 20000\n"),
        "sync.max_wait_ms"
    );
    assert_eq!(
        invalid_key("[training]\nwindow_size = 1\n"),
        "training.window_size"
    );
    assert_eq!(
        invalid_key("[training]\nmin_view_angle_deg = -5.0\n"),
        "training.min_view_angle_deg"
    );
    assert_eq!(
        invalid_key("[training]\nvariant = \"e\"\n"),
        "training.variant"
    );
    assert_eq!(invalid_key("[training]\nthreads = 0\n"), "training.threads");
    assert_eq!(
        invalid_key("[training]\nappearance_hidden_width = 0\n"),
        "training.appearance_hidden_width"
    );
    assert_eq!(
        invalid_key("[training]\nencoding_frequencies = 0\n"),
        "training.encoding_frequencies"
    );
    assert_eq!(
        invalid_key("[training]\nmlp_precision = \"f16\"\n"),
        "training.mlp_precision"
    );
    for (text, key) in [
        ("shading = \"phong\"", "training.shading"),
        ("shadow_gain = 0.0", "training.shadow_gain"),
        ("shadow_gain = nan", "training.shadow_gain"),
        ("colour_space = \"gamma\"", "training.colour_space"),
        (
            "appearance_inputs = \"global\"",
            "training.appearance_inputs",
        ),
        // The local inputs read the learned normal: without it the inputs are refused.
        ("shading = \"none\"", "training.appearance_inputs"),
        // (a) has no Phi: the shading keys are still parsed.
        ("variant = \"a\"\nshading = \"phong\"", "training.shading"),
    ] {
        assert_eq!(invalid_key(&format!("[training]\n{text}\n")), key, "{text}");
    }
    assert_eq!(
        invalid_key("[training]\npasses_per_round = 0\n"),
        "training.passes_per_round"
    );
    assert_eq!(
        invalid_key("[training]\nround_deadline_ms = 99\n"),
        "training.round_deadline_ms"
    );
    assert_eq!(
        invalid_key("[training]\ndenormals = \"fast\"\n"),
        "training.denormals"
    );
    assert_eq!(
        invalid_key("[checkpoint]\npath = \"\"\n"),
        "checkpoint.path"
    );
    assert_eq!(
        invalid_key("[checkpoint]\npath = \"out/..\"\n"),
        "checkpoint.path"
    );
    assert_eq!(invalid_key("[queues]\ncommands = 0\n"), "queues.commands");
    for (text, key) in [
        ("[camera]\nwidth_px = 0\n", "camera.width_px"),
        ("[camera]\nfy_px = -1.0\n", "camera.fy_px"),
        ("[camera]\ncx_px = 1921.0\n", "camera.cx_px"),
        ("[camera]\ncy_px = nan\n", "camera.cy_px"),
        ("[camera]\ndistortion = \"brown\"\n", "camera.distortion"),
        ("[model]\ninit = \"surface\"\n", "model.init"),
        ("[model]\nhull_resolution = 1000\n", "model.hull_resolution"),
    ] {
        assert_eq!(invalid_key(text), key, "{text}");
    }
    let message = parse("[node]\nnode_id = 128\n").unwrap_err().to_string();
    assert_eq!(
        message,
        "config key `node.node_id`: 128 is above the Cyphal maximum 127"
    );
}

#[test]
fn training_denormals_parse_and_name_the_values() {
    assert_eq!(
        ComponentConfig::default().denormals().unwrap(),
        DenormalMode::FlushToZero
    );
    let ieee = parse("[training]\ndenormals = \"ieee\"\n").unwrap();
    assert_eq!(ieee.denormals().unwrap(), DenormalMode::Ieee);
    let message = parse("[training]\ndenormals = \"FTZ\"\n")
        .unwrap_err()
        .to_string();
    assert!(
        message.contains("training.denormals")
            && message.contains("\"FTZ\"")
            && message.contains("flush-to-zero")
            && message.contains("ieee"),
        "{message}"
    );
}

#[test]
fn mounting_rotates_as_documented() {
    // 90 degrees about camera-body z: body x maps to camera y.
    let half = std::f64::consts::FRAC_1_SQRT_2;
    let config = parse(&format!(
        "[camera]\ncamera_from_body_wxyz = [{half}, 0.0, 0.0, {half}]\n"
    ))
    .unwrap();
    let q = config.camera_from_body().unwrap();
    assert!((q * glam::DVec3::X - glam::DVec3::Y).length() < 1e-12);
    assert_eq!(config.sync_config().unwrap().camera_from_body, q);
}

#[test]
fn committed_component_toml_parses_and_validates() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../config/component.toml");
    let config = ComponentConfig::load(&path).unwrap_or_else(|e| panic!("{e}"));
    // The committed file documents the defaults: it must state them exactly.
    assert_eq!(config, ComponentConfig::default());
}

#[test]
fn missing_file_is_a_read_error() {
    let e = ComponentConfig::load(Path::new("/nonexistent/component.toml")).unwrap_err();
    assert!(matches!(e, ConfigError::Read { .. }));
    assert!(e.to_string().contains("/nonexistent/component.toml"));
}

/// The demo preset's file (config/presets/demo.toml) as a TOML table: the component's
/// default model and trainer are read against it, not against a second copy of its numbers
/// (sim-harness, which parses presets, depends on this crate).
fn demo_preset() -> toml::Table {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../config/presets/demo.toml");
    toml::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

/// The default `[training]` sets every model key and trainer setting the demo preset sets
/// under the same name, to the demo's value; its rates are the demo's `[rates]` (the same
/// gs-core table), and they reach the online trainer's configuration.
#[test]
fn demo_preset_keys_are_the_defaults() {
    let demo = demo_preset();
    let training = toml::Table::try_from(TrainingConfig::default()).unwrap();
    for key in [
        "shading",
        "appearance_inputs",
        "colour_space",
        "shadow_gain",
        "appearance_hidden_width",
        "encoding_frequencies",
        "light_resolution_px",
        "replay_capacity",
        "replay_steps_per_round",
    ] {
        assert_eq!(training.get(key), demo.get(key), "training.{key}");
    }
    let demo_rates: RateOverrides = demo["rates"].clone().try_into().unwrap();
    let config = ComponentConfig::default();
    assert_eq!(config.training.rates, demo_rates);
    let online = config.online_config().unwrap();
    assert_eq!(
        online.model.lr,
        demo_rates.applied_to(SunAwareConfig::default().lr)
    );
    assert_eq!(
        (
            online.replay_capacity,
            online.replay_steps_per_round,
            online.model.light.resolution_px
        ),
        (
            demo["replay_capacity"].as_integer().unwrap() as usize,
            demo["replay_steps_per_round"].as_integer().unwrap() as usize,
            demo["light_resolution_px"].as_integer().unwrap() as u32
        )
    );
}

/// The rates, replay memory and light camera a file sets reach the online trainer's
/// configuration (what `runtime::build_learner` gives the learner); unnamed rates keep
/// the defaults.
#[test]
fn training_keys_reach_the_online_config() {
    let online = parse(
        "[training]\nreplay_capacity = 5\nreplay_steps_per_round = 2\n\
         light_resolution_px = 64\npasses_per_round = 3\n[training.rates]\nnormal = 0.004\n",
    )
    .unwrap()
    .online_config()
    .unwrap();
    let demo = TrainingConfig::default().rates;
    assert_eq!(
        (
            online.replay_capacity,
            online.replay_steps_per_round,
            online.passes_per_round
        ),
        (5, 2, 3)
    );
    assert_eq!(online.model.light.resolution_px, 64);
    assert_eq!(
        online.model.lr,
        RateOverrides {
            normal: Some(0.004),
            ..demo
        }
        .applied_to(SunAwareConfig::default().lr),
        "a [training.rates] table replaces the default rates key by key"
    );
    assert!(
        !online.unlit_full_frame,
        "the adapter's own setting is kept"
    );
}

#[test]
fn bad_training_keys_name_the_key() {
    for (text, key) in [
        (
            "[training]\nreplay_capacity = 1025\n",
            "training.replay_capacity",
        ),
        (
            "[training]\nreplay_steps_per_round = 1001\n",
            "training.replay_steps_per_round",
        ),
        (
            "[training]\nlight_resolution_px = 4\n",
            "training.light_resolution_px",
        ),
        ("[training.rates]\nopacity = -0.05\n", "training.rates"),
        ("[training.rates]\nfeature = nan\n", "training.rates"),
        ("[training.rates]\nsh_dc = inf\n", "training.rates"),
    ] {
        assert_eq!(invalid_key(text), key, "{text}");
    }
    let message = parse("[training.rates]\nopacity = -0.05\n")
        .unwrap_err()
        .to_string();
    assert!(message.contains("rates.opacity"), "{message}");
    // Unknown rate names and wrong types are parse errors naming the key.
    for (text, named) in [
        ("[training.rates]\nopacityy = 0.1\n", "opacityy"),
        ("[training.rates]\nopacity = \"high\"\n", "opacity"),
        ("[training]\nreplay_capacity = -1\n", "replay_capacity"),
    ] {
        match parse(text) {
            Err(ConfigError::Parse { message, .. }) => {
                assert!(message.contains(named), "{text:?}: {message}");
            }
            other => panic!("expected a parse error for {text:?}, got {other:?}"),
        }
    }
}

/// Checkpoints store the model (its rates and light camera among it) and the replay
/// capacity: a resume with other values is refused naming them; the replay steps per
/// round are not stored, so changing them resumes.
#[test]
fn a_resume_with_other_rates_replay_or_light_camera_is_refused() {
    use crate::runtime::{build_learner, LearnerKind};
    const SMALL: &str = "[model]\ninit = \"random\"\ninitial_gaussians = 40\n";
    let learner = |training: &str| {
        build_learner(
            &parse(&format!("{SMALL}{training}")).unwrap(),
            LearnerKind::SunAware,
        )
        .unwrap()
    };
    let saved = learner("").save();
    for (training, named) in [
        ("[training]\nreplay_capacity = 0\n", "replay capacity 32"),
        ("[training]\nlight_resolution_px = 64\n", "light"),
        ("[training.rates]\nopacity = 0.04\n", "lr"),
    ] {
        let error = learner(training).load(&saved).unwrap_err().to_string();
        assert!(
            error.contains("on_config_mismatch") && error.contains(named),
            "{training}: {error}"
        );
    }
    learner("[training]\nreplay_steps_per_round = 2\n")
        .load(&saved)
        .unwrap();
}

//! The accuracy ladder on small ray-traced sequences, trained online with the demo's preset
//! (`config/presets/demo.toml`) on a smaller image: the model must beat an all-black frame on
//! the target's own pixels (masked PSNR) by a clear margin.
//!
//! - L0 on a static target (the Sun fixed in the body frame, the camera going once around
//!   it), configuration (a): the frames it trained on must fit. The code before the accuracy
//!   work stayed below black here (the Earth-albedo fill lit the bus from a direction the
//!   model is never told, the 2-sample ground truth was noise-limited, and the 3DGS rates
//!   were made for 30K steps, not a few hundred).
//! - L1 on the tumbling target, configuration (d): frames of the same rendezvous that
//!   training never received.

use sim_harness::experiment::data::{render_scene, SceneData};
use sim_harness::experiment::demo::{DEMO_PRESET, DEMO_SCENARIO};
use sim_harness::experiment::evaluate::EvalSummary;
use sim_harness::experiment::preset::Preset;
use sim_harness::experiment::runner::{run_config, RunOutcome};
use sim_harness::scenario::Scenario;

use gs_core::sunaware::Variant;

/// The demo's scenario under `preset` (the demo's, changed by the caller), the target
/// tumbling at `tumble_rate_deg_s`.
fn scene_for(preset: &Preset, tumble_rate_deg_s: f64) -> SceneData {
    let scenario =
        Scenario::from_toml_str(DEMO_SCENARIO, std::path::Path::new(".")).expect("scenario");
    let mut scenario = preset.apply(&scenario).expect("preset applies");
    scenario.attitude.tumble_rate_deg_s = tumble_rate_deg_s;
    render_scene(&scenario, preset.init_points as usize, &mut |_| {}).expect("render")
}

fn demo_preset() -> Preset {
    let mut preset = Preset::from_toml_str(DEMO_PRESET, "demo").expect("preset");
    preset.eval_views = 4;
    preset
}

fn report(o: &RunOutcome) -> String {
    sim_harness::experiment::ladder::ladder_line("test", o)
}

/// Fails unless the model beats the all-black frame on a rung by `min_db` (masked PSNR).
fn assert_margin(rung: &str, model: &EvalSummary, black: &EvalSummary, min_db: f64) {
    let margin_db = model.masked_psnr_db - black.masked_psnr_db;
    assert!(
        margin_db >= min_db,
        "{rung} only {margin_db:.2} dB over black (at least {min_db} dB expected)"
    );
}

#[test]
fn static_target_training_frames_fit_well_above_black() {
    // The demo's 160x100 sequence; 12 rounds per window change: about 1,200 steps.
    let mut preset = demo_preset();
    preset.rounds_per_window_change = 12;
    let scene = scene_for(&preset, 0.0);
    let (o, _) = run_config(&scene, &preset, Variant::A, 0, &mut |_| {}).expect("run");
    eprintln!("{}", report(&o));
    // Measured in release: +6.2 dB (window), +6.4 dB (seen), +6.6 dB (held-out). The same
    // settings with the old ground truth and rates scored below black.
    assert_margin("L0 window", &o.window_fit, &o.black_window, 4.0);
    assert_margin("L0 seen", &o.seen, &o.black_seen, 4.0);
}

#[test]
fn held_out_trajectory_frames_beat_black_in_configuration_d() {
    // 80x50 pixels, a smaller model: about a minute.
    let mut preset = demo_preset();
    preset.downsample = 24;
    preset.orbits = 1.0;
    preset.init_points = 800;
    preset.max_gaussians = 1500;
    preset.appearance_hidden_width = 64;
    preset.light_resolution_px = 64;
    assert!(preset.holdout_every > 0, "the demo preset withholds frames");
    let scene = scene_for(&preset, 2.0);
    let (o, _) = run_config(&scene, &preset, Variant::D, 0, &mut |_| {}).expect("run");
    eprintln!("{}", report(&o));
    assert!(o.held_out.views > 0);
    // Measured with the linear blend (Intel Xeon): +6.35 dB (19.33 against 12.98 dB), L0
    // seen +10.2 dB; with the sRGB blend before it +3.4 dB and +8.9 dB.
    assert_margin("L1 held-out", &o.held_out, &o.black_held_out, 5.0);
    assert_margin("L0 seen", &o.seen, &o.black_seen, 8.0);
}

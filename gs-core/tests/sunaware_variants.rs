//! Configurations a-d on the synthetic Sun-lit scene with self-shadowing, scored on
//! held-out views with new cameras and Sun directions: with the Sun moving, the model that
//! knows the Sun and splats shadows (c) clearly beats SH colour (a) after a short run.
//! The full a-d table is the example `sunaware_variants` (same frames, same training loop,
//! `tests/common/variants.rs`).

#[path = "common/variants.rs"]
mod variants;
use gs_core::sunaware::synthetic::SyntheticScene;
use gs_core::sunaware::{LightProjection, Variant};
use variants::{make_frames, run};

#[test]
fn sun_and_shadow_aware_model_beats_sh_under_a_moving_sun() {
    let scene = SyntheticScene::plate_and_ball(12, 60).unwrap();
    let train = make_frames(&scene, 40, 0.0, 40, 30);
    let test = make_frames(&scene, 4, 0.37, 40, 30);
    let p = LightProjection::Perspective;
    let a = run(&scene, &train, &test, Variant::A, p, 300);
    let c = run(&scene, &train, &test, Variant::C, p, 300);
    eprintln!("a {:.2} dB, c {:.2} dB", a.0, c.0);
    assert!(c.0 > a.0 + 1.0, "PSNR(c) {:.2} vs PSNR(a) {:.2}", c.0, a.0);
}

//! Configurations a-d (and both light projections for c and d) trained for the same number
//! of steps on the synthetic Sun-lit scene with self-shadowing (64x48, 40 training views, 6
//! held-out views with new cameras and Sun directions); prints a Markdown table of held-out
//! PSNR, SSIM, Gaussian count and ms per step. The paper's ordering is PSNR(b) > PSNR(a)
//! and PSNR(c) >= PSNR(b). About a minute per 800 steps and row on a 2-core machine.
//!
//! `cargo run --release -p gs-core --example sunaware_variants -- [--steps N]`

mod bench_util;
#[path = "../tests/common/variants.rs"]
mod variants;

use bench_util::{arg, exit_if_help, init_threads};
use gs_core::sunaware::synthetic::SyntheticScene;
use gs_core::sunaware::{LightProjection, Variant};
use variants::{make_frames, run};

const USAGE: &str = "sunaware_variants: configurations a-d on the synthetic Sun-lit scene
usage: sunaware_variants [--steps N]
  --steps N   training steps per configuration (default 800)";

fn main() {
    let args: Vec<String> = std::env::args().collect();
    exit_if_help(&args, USAGE);
    init_threads("sunaware_variants", None);
    let steps = arg(&args, "--steps").unwrap_or(800).max(1);
    let scene = SyntheticScene::plate_and_ball(16, 100).expect("built-in scene");
    let train = make_frames(&scene, 40, 0.0, 64, 48);
    let test = make_frames(&scene, 6, 0.37, 64, 48);
    println!("{}", gs_core::machine::header_line());
    println!("synthetic plate + ball, 64x48, 40 training views, 6 held-out views, {steps} steps");
    println!("| config | light | PSNR (dB) | SSIM | Gaussians | ms/step |");
    println!("|---|---|---|---|---|---|");
    let rows = [
        (Variant::A, LightProjection::Perspective),
        (Variant::B, LightProjection::Perspective),
        (Variant::C, LightProjection::Perspective),
        (Variant::C, LightProjection::Orthographic),
        (Variant::D, LightProjection::Perspective),
        (Variant::D, LightProjection::Orthographic),
    ];
    for (v, p) in rows {
        let (psnr, ssim, n, ms) = run(&scene, &train, &test, v, p, steps);
        let light = if v.uses_shadow() {
            format!("{p:?}")
        } else {
            "-".into()
        };
        println!("| {v} | {light} | {psnr:.2} | {ssim:.4} | {n} | {ms:.1} |");
    }
}

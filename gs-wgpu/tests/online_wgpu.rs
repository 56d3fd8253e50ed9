//! The online trainer (gs-online) on the wgpu backend: its rounds run as
//! device-resident batches (`SunAwareTrainer::step_many`: one upload and one download per
//! round, densification between rounds on the host copy). The same short synthetic
//! sequence as `online_sequence.rs`, trained on the CPU and on the device, must reach the
//! same held-out PSNR within 0.1 dB, with nothing skipped and the same rounds and
//! densifications.
//!
//! Without an adapter the test prints a skip notice, unless `GS_REQUIRE_GPU=1` (CI), where
//! a missing adapter fails.

use gs_core::sunaware::synthetic::SyntheticScene;
use gs_core::sunaware::{LightConfig, SunAwareConfig, Variant};
use gs_online::keyframe::WindowConfig;
use gs_online::online::{Initialisation, OnlineConfig, OnlineTrainer};
use gs_wgpu::{context_or_skip, GpuOptions, GpuRasterizer, WgpuEngine};
use std::sync::Arc;

#[path = "../../gs-online/tests/online_support/mod.rs"]
mod online_support;
use online_support::{frame, held_out_psnr};

#[test]
fn online_rounds_on_the_device_match_the_cpu() {
    // The same adapter policy as the other GPU tests; the backend is what
    // `gs_wgpu::open_engine(true)` builds (deterministic options).
    let options = GpuOptions {
        deterministic: true,
        ..GpuOptions::default()
    };
    let Some(ctx) = context_or_skip(options) else {
        return;
    };
    let backend = WgpuEngine::new(Arc::new(GpuRasterizer::new(ctx).unwrap()))
        .unwrap()
        .into_backend();
    let scene = SyntheticScene::plate_and_ball(12, 60).unwrap();
    let (points, normals, colours) = scene.surface_samples(0.02, 11);
    let init = Initialisation::SurfaceSamples {
        points,
        normals: Some(normals),
        colours: Some(colours),
    };
    let config = OnlineConfig {
        window: WindowConfig {
            capacity: 6,
            ..WindowConfig::default()
        },
        model: SunAwareConfig {
            light: LightConfig {
                resolution_px: 96,
                ..LightConfig::default()
            },
            // Narrow Phi: the software driver runs the products on the CPU.
            appearance_hidden_width: 32,
            ..SunAwareConfig::for_variant(Variant::D)
        },
        densify_every_rounds: 5,
        passes_per_round: 2,
        ..OnlineConfig::default()
    };
    let run = |device: bool| {
        let mut t = OnlineTrainer::new(config.clone(), &init, scene.scene_box).unwrap();
        if device {
            t.trainer_mut().set_backend(&backend).unwrap();
            assert!(t.trainer().is_device_resident());
        }
        let start = std::time::Instant::now();
        let (mut rounds, mut densified) = (0, 0);
        for id in 0..20 {
            t.offer(frame(&scene, id, false)).unwrap();
            if let Some(r) = t.run_round_if_due().unwrap() {
                assert!(r.mean_loss.is_finite(), "round {}", r.rounds);
                assert_eq!(r.skipped_steps, 0);
                rounds += 1;
                densified += usize::from(r.densified.is_some());
            }
        }
        let psnr = held_out_psnr(&t, &scene);
        let gaussians = t.trainer().model.len();
        (
            psnr,
            rounds,
            densified,
            gaussians,
            start.elapsed().as_secs_f64(),
        )
    };
    let cpu = run(false);
    let gpu = run(true);
    eprintln!(
        "held-out PSNR cpu {:.3} dB ({} rounds, {} densified, {} Gaussians, {:.1} s), \
         wgpu {:.3} dB ({} rounds, {} densified, {} Gaussians, {:.1} s; software driver)",
        cpu.0, cpu.1, cpu.2, cpu.3, cpu.4, gpu.0, gpu.1, gpu.2, gpu.3, gpu.4
    );
    assert_eq!((cpu.1, cpu.2), (gpu.1, gpu.2), "rounds and densifications");
    assert_eq!(cpu.1, 15);
    assert!(
        (cpu.0 - gpu.0).abs() <= 0.1,
        "cpu {} dB vs wgpu {} dB",
        cpu.0,
        gpu.0
    );
}

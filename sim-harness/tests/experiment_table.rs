//! The results table's writers (CSV header and row format, Markdown layout) and a tiny
//! end-to-end `table` job and demo: every file written, metrics finite, rows as expected.

use sim_harness::experiment::demo::run_demo_with;
use sim_harness::experiment::ladder::{Ladder, Rung, CSV_COLUMNS as LADDER_COLUMNS};
use sim_harness::experiment::preset::Preset;
use sim_harness::experiment::table::{to_csv, to_markdown, ResultRow, CSV_HEADER};
use sim_harness::experiment::table_job::{run_table, TableJob};
use sim_harness::scenario::Scenario;
use std::path::{Path, PathBuf};

/// A row whose evaluation views score `masked_psnr` / `masked_ssim` on the target's pixels
/// against an all-black 10 dB; full frame 10 dB higher; the other rungs without frames.
fn row(target: &str, config: &str, masked_psnr: f64, masked_ssim: f64) -> ResultRow {
    let eval = Rung {
        views: 4,
        masked_psnr_db: masked_psnr,
        masked_ssim,
        psnr_db: masked_psnr + 10.0,
        black_masked_psnr_db: 10.0,
        black_psnr_db: 20.0,
    };
    ResultRow {
        target: target.into(),
        config: config.into(),
        ssim: 0.99,
        psnr: masked_psnr + 10.0,
        gaussians: 42_700,
        train_s: 12.34,
        step_ms: 5.67,
        ladder: Ladder {
            eval: Some(eval),
            ..Ladder::default()
        },
    }
}

#[test]
fn csv_has_the_exact_header_and_one_line_per_row() {
    let rows = [
        row("cassini", "a", 16.514, 0.58712),
        row("rosetta", "d", 25.27, 0.9905),
    ];
    let csv = to_csv(&rows);
    let lines: Vec<&str> = csv.lines().collect();
    assert_eq!(
        lines[0],
        format!("target,config,ssim,psnr,gaussians,train_s,step_ms,{LADDER_COLUMNS}")
    );
    assert_eq!(lines[0], CSV_HEADER);
    assert_eq!(
        lines[1],
        "cassini,a,0.9900,26.51,42700,12.3,5.7,NaN,NaN,NaN,NaN,NaN,NaN,16.514,10.000,NaN,NaN,0.5871"
    );
    assert_eq!(lines[2].split(',').count(), CSV_HEADER.split(',').count());
    assert_eq!(lines.len(), 3);
    // A name with a comma is quoted, so the column count stays the same.
    let odd = to_csv(&[row("my,target", "b", 1.0, 0.5)]);
    assert!(odd.lines().nth(1).unwrap().starts_with("\"my,target\",b,"));
}

#[test]
fn markdown_is_laid_out_like_table_one_with_the_target_pixels_first() {
    let rows = [
        row("cassini", "a", 16.51, 0.5871),
        row("cassini", "b", 20.63, 0.6894),
        row("starlink", "a", 15.05, 0.5539),
        row("starlink", "b", 11.00, 0.5600),
    ];
    let md = to_markdown(&rows);
    let lines: Vec<&str> = md.lines().collect();
    assert_eq!(
        lines[2],
        "| Config. | Cassini masked SSIM↑ | Cassini masked PSNR↑ (black) | Cassini full PSNR | Cassini \\|G\\| | Starlink masked SSIM↑ | Starlink masked PSNR↑ (black) | Starlink full PSNR | Starlink \\|G\\| |"
    );
    assert_eq!(lines[3], "|---|---:|---:|---:|---:|---:|---:|---:|---:|");
    // Best per target in bold, per metric; within 3 dB of black said in words.
    assert_eq!(
        lines[4],
        "| (a) 3DGS | 0.5871 | 16.51 (10.00) | 26.51 | 42.7K | 0.5539 | **15.05** (10.00) | 25.05 | 42.7K |"
    );
    assert_eq!(
        lines[5],
        "| (b) + Illum. | **0.6894** | **20.63** (10.00) | 30.63 | 42.7K | **0.5600** | 11.00 (10.00) **< 3 dB over black** | 21.00 | 42.7K |"
    );
    assert!(
        md.contains("| Cassini (a) 3DGS | - | - | - | 16.51 (10.00) | - |"),
        "{md}"
    );
    assert!(md.contains(
        "| Config. | Cassini train s | Cassini step ms | Starlink train s | Starlink step ms |"
    ));
    assert!(md.contains("| (a) 3DGS | 12.3 | 5.7 | 12.3 | 5.7 |"));
    // A missing cell prints dashes instead of shifting the columns.
    let md = to_markdown(&rows[..3]);
    assert!(
        md.contains(
            "| (b) + Illum. | **0.6894** | **20.63** (10.00) | 30.63 | 42.7K | - | - | - | - |"
        ),
        "{md}"
    );
}

fn quick_scenario() -> Scenario {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../config/scenarios/quick.toml");
    Scenario::load(&path).unwrap()
}

fn tiny_preset(configs: &[&str]) -> Preset {
    Preset {
        name: "tiny".into(),
        downsample: 40,
        cadence_s: 10.0,
        frames: Some(7),
        eval_views: 2,
        figure_views: 2,
        samples_per_pixel: 1,
        window: 3,
        init_points: 300,
        max_gaussians: 600,
        light_resolution_px: 32,
        densify_every_rounds: 2,
        configs: configs.iter().map(ToString::to_string).collect(),
        ..Preset::default()
    }
}

fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("sim-harness-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

#[test]
fn tiny_table_job_writes_every_file_with_finite_metrics() {
    let out = scratch("table");
    let job = TableJob {
        preset: tiny_preset(&["a", "d"]),
        scenarios: vec![quick_scenario()],
        out_dir: out.clone(),
        keep_data: false,
    };
    let result = run_table(&job, &mut |_| {}).unwrap();
    assert_eq!(result.rows.len(), 2);
    for (r, config) in result.rows.iter().zip(["a", "d"]) {
        assert_eq!((r.target.as_str(), r.config.as_str()), ("quick", config));
        assert!(r.psnr.is_finite() && r.psnr > 5.0, "{r:?}");
        assert!(r.ssim.is_finite() && r.ssim > 0.0 && r.ssim <= 1.0, "{r:?}");
        assert!(
            r.gaussians > 0 && r.train_s > 0.0 && r.step_ms > 0.0,
            "{r:?}"
        );
    }
    for run in &result.runs {
        // 7 frames with the tumble turning the view 20 deg each: all keyframes, W = 3, so
        // a round after each frame from the third on.
        assert_eq!(run.rounds, 5, "{}", run.config);
        assert_eq!(run.steps + run.skipped_nonfinite_steps, 15);
        assert_eq!(run.eval.views, 2);
    }
    let csv = std::fs::read_to_string(out.join("table.csv")).unwrap();
    assert_eq!(csv.lines().count(), 3);
    assert!(csv.starts_with(&format!("{CSV_HEADER}\n")));
    // Every rung of the ladder that has frames is a number in the CSV (no held-out frames
    // and maybe no covered views in this tiny preset: those are NaN).
    let fields: Vec<&str> = csv.lines().nth(1).unwrap().split(',').collect();
    for name in [
        "l0_window_masked_psnr",
        "l0_seen_masked_psnr",
        "l2_eval_masked_psnr",
    ] {
        let i = CSV_HEADER.split(',').position(|c| c == name).unwrap();
        assert!(
            fields[i].parse::<f64>().unwrap().is_finite(),
            "{name}: {}",
            fields[i]
        );
    }
    let md = std::fs::read_to_string(out.join("table.md")).unwrap();
    assert!(md.contains("(a) 3DGS") && md.contains("(d) + Isotropic Loss"));
    assert!(md.contains("Accuracy ladder"), "{md}");
    let figure = image::open(out.join("figure.png")).unwrap();
    // Two rows (evaluation views) of three columns (truth, a, d), each cell at least 200 px.
    assert!(figure.width() >= 3 * 200 && figure.height() >= 2 * 100);
    let runs: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("runs.json")).unwrap()).unwrap();
    assert_eq!(runs.as_array().unwrap().len(), 2);

    // A second run in the same folder reads the rendered scene from the cache and gives
    // bit-identical numbers.
    let again = run_table(&job, &mut |_| {}).unwrap();
    assert_eq!(again.render_s, 0.0);
    for (a, b) in result.rows.iter().zip(&again.rows) {
        assert_eq!((a.psnr, a.ssim, a.gaussians), (b.psnr, b.ssim, b.gaussians));
    }
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn tiny_demo_writes_every_file() {
    let out = scratch("demo");
    let preset = tiny_preset(&["d"]);
    let scenario = preset.apply(&quick_scenario()).unwrap();
    let summary = run_demo_with(&scenario, &preset, &out, &mut |_| {}).unwrap();
    assert!(summary.run.eval.psnr_db.is_finite());
    for file in [
        "renders.png",
        "loss_curve.csv",
        "loss_curve.png",
        "metrics.json",
        "model.ply",
        "checkpoint.bin",
    ] {
        let meta = std::fs::metadata(out.join(file)).unwrap_or_else(|e| panic!("{file}: {e}"));
        assert!(meta.len() > 0, "{file} is empty");
    }
    let curve = std::fs::read_to_string(out.join("loss_curve.csv")).unwrap();
    assert_eq!(curve.lines().count(), 1 + summary.run.rounds as usize);
    for line in curve.lines().skip(1) {
        let loss: f64 = line.split(',').nth(2).unwrap().parse().unwrap();
        assert!(loss.is_finite() && loss > 0.0, "{line}");
    }
    // The checkpoint restores the trained model exactly.
    let restored = gs_core::sunaware::checkpoint::load_file(out.join("checkpoint.bin")).unwrap();
    assert_eq!(restored.model.len(), summary.run.gaussians);
    let _ = std::fs::remove_dir_all(&out);
}

/// The simulator's images, poses and Sun vectors agree with gs-core's conventions: with
/// repeated rounds on two fixed frames, configuration (a) fits them far beyond an all-black
/// image, and the fit is to the images as they are (a vertically flipped copy scores low).
#[test]
fn online_trainer_fits_simulator_frames() {
    use gs_core::loss::{psnr, ImageShape};
    use gs_core::sunaware::Variant;
    use gs_online::online::OnlineTrainer;
    use sim_harness::experiment::data::render_scene;
    use sim_harness::experiment::evaluate::{camera_of, sun_of};
    use sim_harness::experiment::runner::{
        initialisation, online_config, scene_box, training_frame,
    };

    let preset = Preset {
        downsample: 24,
        frames: Some(2),
        eval_views: 1,
        samples_per_pixel: 1,
        window: 2,
        init_points: 1500,
        ..tiny_preset(&["a"])
    };
    let scenario = preset.apply(&quick_scenario()).unwrap();
    let scene = render_scene(&scenario, 1500, &mut |_| {}).unwrap();
    let k = scene.intrinsics;
    let (w, h) = (k.width as usize, k.height as usize);
    let shape = ImageShape::new(w, h, 3);
    let mut config = online_config(&preset, Variant::A).unwrap();
    config.require_window_change = false;
    let mut trainer = OnlineTrainer::new(
        config,
        &initialisation(&scene, &preset),
        scene_box(&scene).unwrap(),
    )
    .unwrap();
    for i in 0..2 {
        trainer.offer(training_frame(&scene, i)).unwrap();
    }
    for _ in 0..60 {
        assert!(trainer.run_round_if_due().unwrap().is_some());
    }
    for view in &scene.frames {
        let truth = view.rgb_f32();
        let render = trainer
            .predict(&camera_of(&k, view), sun_of(view))
            .unwrap()
            .image;
        let mut flipped = truth.clone();
        for y in 0..h {
            let src = &truth[3 * (h - 1 - y) * w..3 * (h - y) * w];
            flipped[3 * y * w..3 * (y + 1) * w].copy_from_slice(src);
        }
        let fit = psnr(&render, &truth, shape).unwrap();
        let black = psnr(&vec![0.0; truth.len()], &truth, shape).unwrap();
        let to_flipped = psnr(&render, &flipped, shape).unwrap();
        assert!(
            fit > black + 8.0,
            "frame {}: {fit} dB vs black {black} dB",
            view.index
        );
        assert!(
            fit > to_flipped + 8.0,
            "frame {}: {fit} dB vs flipped {to_flipped} dB",
            view.index
        );
    }
}

#[test]
fn rounds_per_window_change_multiplies_the_rounds() {
    let out = scratch("rounds");
    let preset = Preset {
        rounds_per_window_change: 3,
        eval_every_rounds: 5,
        ..tiny_preset(&["a"])
    };
    let job = TableJob {
        preset,
        scenarios: vec![quick_scenario()],
        out_dir: out.clone(),
        keep_data: false,
    };
    let result = run_table(&job, &mut |_| {}).unwrap();
    // Five window changes with a full window (as in the tiny table), three rounds each.
    assert_eq!(result.runs[0].rounds, 15);
    assert_eq!(result.runs[0].curve.len(), 15);
    // Evaluated during training at rounds 5, 10 and 15; the last equals the final evaluation.
    let evals = &result.runs[0].eval_curve;
    assert_eq!(
        evals.iter().map(|e| e.round).collect::<Vec<_>>(),
        [5, 10, 15]
    );
    assert_eq!(evals[2].psnr_db, result.runs[0].eval.psnr_db);
    let _ = std::fs::remove_dir_all(&out);
}

//! The run-time-against-error instruments: the Pareto front on hand-made points, the CSV
//! schema, command-line errors, and tiny end-to-end `pareto`, `skips` and window-ablation
//! runs on the quick scenario (rows, files, determinism, what each skip switches).

use sim_harness::experiment::ablation::{run_window_ablation, WindowJob};
use sim_harness::experiment::ladder::{Ladder, Rung};
use sim_harness::experiment::pareto::{
    from_csv, pareto_front, run_pareto, select_settings, to_csv, Knob, ParetoJob, Setting,
    SweepRow, CSV_HEADER,
};
use sim_harness::experiment::preset::Preset;
use sim_harness::experiment::skips::{run_skips, switchable_skips, SkipsJob};
use sim_harness::scenario::Scenario;
use std::path::{Path, PathBuf};
use std::process::Command;

#[test]
fn front_excludes_dominated_points_and_keeps_ties() {
    let points = [
        (10.0, 20.0),          // 0: front
        (20.0, 25.0),          // 1: front
        (15.0, 19.0),          // 2: dominated by 0 (slower, worse)
        (30.0, 25.0),          // 3: dominated by 1 (slower, same PSNR)
        (10.0, 20.0),          // 4: tie with 0: neither dominates, both on the front
        (5.0, f64::NAN),       // 5: not finite: never on the front, dominates nothing
        (40.0, 24.0),          // 6: dominated by 1
        (10.0, 18.0),          // 7: dominated by 0 (same time, worse PSNR)
        (50.0, 30.0),          // 8: front (best PSNR)
        (f64::INFINITY, 40.0), // 9: not finite
    ];
    assert_eq!(
        pareto_front(&points),
        vec![true, true, false, false, true, false, false, false, true, false]
    );
    assert_eq!(pareto_front(&[(1.0, 1.0)]), vec![true]);
    assert!(pareto_front(&[]).is_empty());
}

fn row(setting: &str, cpu_s: f64, psnr: f64) -> SweepRow {
    SweepRow {
        setting: setting.into(),
        target: "cassini".into(),
        config: "d".into(),
        downsample: 16,
        width: 120,
        height: 75,
        max_gaussians: 3000,
        init_points: 1500,
        feature_dim: 72,
        encoding_frequencies: 4,
        window: 6,
        rounds_per_window_change: 2,
        passes_per_round: 1,
        skip_eclipse: true,
        skip_unlit: false,
        skip_unchanged_window: true,
        frames: 96,
        rounds: 140,
        steps: 840,
        train_s: 62.71,
        train_cpu_s: cpu_s,
        step_ms: 74.66,
        psnr_db: psnr,
        ssim: 0.82391,
        masked_psnr_db: 10.1234,
        black_psnr_db: 19.55,
        gaussians: 3000,
        peak_rss_mb: 74.44,
        ladder: Ladder {
            eval: Some(Rung {
                views: 24,
                masked_psnr_db: 10.1234,
                masked_ssim: 0.25,
                psnr_db: psnr,
                black_masked_psnr_db: 9.5,
                black_psnr_db: 19.55,
            }),
            ..Ladder::default()
        },
    }
}

#[test]
fn csv_has_the_exact_header_and_one_full_line_per_row() {
    let csv = to_csv(&[row("base", 28.2, 19.15), row("a,b", 10.0, 18.0)], &[true]);
    let lines: Vec<&str> = csv.lines().collect();
    assert_eq!(lines[0], CSV_HEADER);
    assert_eq!(
        lines[0],
        "setting,target,config,downsample,width,height,max_gaussians,init_points,feature_dim,\
         encoding_frequencies,window,rounds_per_window_change,passes_per_round,skip_eclipse,\
         skip_unlit,skip_unchanged_window,frames,rounds,steps,train_s,train_cpu_s,step_ms,\
         psnr_db,ssim,masked_psnr_db,black_psnr_db,gaussians,peak_rss_mb,pareto,\
         l0_window_masked_psnr,l0_window_black_masked_psnr,l0_seen_masked_psnr,\
         l0_seen_black_masked_psnr,l1_held_out_masked_psnr,l1_held_out_black_masked_psnr,\
         l2_eval_masked_psnr,l2_eval_black_masked_psnr,l2_covered_masked_psnr,\
         l2_covered_black_masked_psnr,l2_eval_masked_ssim"
    );
    assert_eq!(
        lines[1],
        "base,cassini,d,16,120,75,3000,1500,72,4,6,2,1,true,false,true,96,140,840,62.71,28.20,\
         74.66,19.150,0.8239,10.123,19.550,3000,74.4,true,NaN,NaN,NaN,NaN,NaN,NaN,10.123,\
         9.500,NaN,NaN,0.2500"
    );
    // A comma in a name cannot shift the columns; a missing front flag is false.
    let columns = CSV_HEADER.split(',').count();
    assert!(lines[2].starts_with("a;b,"));
    assert!(lines[2].contains(",false,NaN,"));
    assert!(lines.iter().all(|l| l.split(',').count() == columns));
    assert_eq!(lines.len(), 3);
}

#[test]
fn csv_reads_back_and_bad_csv_is_a_clear_error() {
    let mut a = row("base", 28.2, 19.15);
    a.ssim = 0.8239;
    a.masked_psnr_db = 10.125;
    a.peak_rss_mb = 74.5;
    let mut b = a.clone();
    b.setting = "w4".into();
    b.window = 4;
    b.skip_unlit = true;
    let text = to_csv(&[a.clone(), b.clone()], &[true, false]);
    let back = from_csv(&text).unwrap();
    // Everything the CSV holds comes back: writing the rows read gives the same text (the
    // ladder's empty rungs are NaN, so the rows themselves cannot compare equal).
    assert_eq!(to_csv(&back, &[true, false]), text);
    assert_eq!((back[1].window, back[1].skip_unlit), (4, true));
    assert_eq!(back[0].ladder.eval.unwrap().black_masked_psnr_db, 9.5);
    assert_eq!(back[0].ladder.window, None);
    // A CSV written before the ladder's columns still reads, with an empty ladder.
    let old_header = CSV_HEADER.split(",pareto,").next().unwrap().to_string() + ",pareto";
    let old_line = text
        .lines()
        .nth(1)
        .unwrap()
        .split(",true,NaN")
        .next()
        .unwrap()
        .to_string()
        + ",true";
    let old = from_csv(&format!("{old_header}\n{old_line}\n")).unwrap();
    assert_eq!(old[0].masked_psnr_db, 10.125);
    assert_eq!(old[0].ladder, Ladder::default());
    let e = from_csv("setting,target\n").unwrap_err().to_string();
    assert!(e.contains("header"), "{e}");
    let short = format!("{CSV_HEADER}\nbase,cassini,d\n");
    let e = from_csv(&short).unwrap_err().to_string();
    assert!(e.contains("line 2") && e.contains("3 fields"), "{e}");
    let bad = text.replacen(",true,false,true,", ",yes,false,true,", 1);
    let e = from_csv(&bad).unwrap_err().to_string();
    assert!(e.contains("line 2") && e.contains("skip_eclipse"), "{e}");
}

#[test]
fn unknown_setting_names_are_errors_listing_the_known_ones() {
    let e = select_settings(&["base".into(), "nosuch".into()])
        .unwrap_err()
        .to_string();
    assert!(e.contains("nosuch") && e.contains("cap1500"), "{e}");
    let two = select_settings(&["w4".into(), "base".into()]).unwrap();
    assert_eq!(
        two.iter().map(|s| s.name.as_str()).collect::<Vec<_>>(),
        ["w4", "base"]
    );
    assert!(select_settings(&[]).unwrap().len() > 15);
    // Optional settings can be named too.
    assert_eq!(
        select_settings(&["eclipse-off".into()]).unwrap()[0].name,
        "eclipse-off"
    );
}

fn cli(args: &[&str]) -> (i32, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_sim-harness"))
        .args(args)
        .output()
        .unwrap();
    (
        out.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn command_line_errors_are_clear_and_fail_before_any_run() {
    let out = scratch("cli");
    let dir = out.to_str().unwrap();
    let (code, err) = cli(&["pareto"]);
    assert_ne!(code, 0);
    assert!(err.contains("--out"), "{err}");
    let (code, err) = cli(&["pareto", "--out", dir, "--target", "jupiter"]);
    assert_eq!(code, 1);
    assert!(err.contains("unknown target \"jupiter\""), "{err}");
    let (code, err) = cli(&[
        "pareto",
        "--out",
        dir,
        "--target",
        "cassini",
        "--scenario",
        "x.toml",
    ]);
    assert_ne!(code, 0);
    assert!(err.contains("cannot be used with"), "{err}");
    let (code, err) = cli(&["pareto", "--out", dir, "--settings", "base,nosuch"]);
    assert_eq!(code, 1);
    assert!(err.contains("unknown setting \"nosuch\""), "{err}");
    let (code, err) = cli(&["skips", "--out", dir, "--preset", "no-such-preset"]);
    assert_eq!(code, 1);
    assert!(err.contains("no-such-preset"), "{err}");
    let (code, err) = cli(&["ablation-window", "--out", dir, "--windows", "5,1"]);
    assert_eq!(code, 1);
    assert!(err.contains("window 1"), "{err}");
    let (code, err) = cli(&["ablation-window", "--out", dir, "--windows", "5,x"]);
    assert_ne!(code, 0);
    assert!(err.contains("'x'") || err.contains("invalid"), "{err}");
    // Nothing ran: no output was written.
    assert!(!out.join("pareto.csv").exists() && !out.join("window.csv").exists());
}

fn quick_scenario() -> Scenario {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../config/scenarios/quick.toml");
    Scenario::load(&path).unwrap()
}

fn tiny_preset() -> Preset {
    Preset {
        name: "tiny".into(),
        downsample: 40,
        cadence_s: 10.0,
        frames: Some(7),
        eval_views: 2,
        figure_views: 1,
        samples_per_pixel: 1,
        window: 3,
        init_points: 300,
        max_gaussians: 600,
        light_resolution_px: 32,
        densify_every_rounds: 2,
        configs: vec!["d".into()],
        ..Preset::default()
    }
}

fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("sim-harness-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

#[test]
fn tiny_pareto_run_writes_rows_and_plot_and_repeats_bit_for_bit() {
    let out = scratch("pareto");
    let job = ParetoJob {
        base: tiny_preset(),
        scenario: quick_scenario(),
        settings: vec![
            Setting::new("base", &[]),
            Setting::new(
                "small",
                &[
                    Knob::MaxGaussians(400),
                    Knob::Config(gs_core::sunaware::Variant::A),
                ],
            ),
        ],
        out_dir: out.clone(),
    };
    let (rows, front) = run_pareto(&job, &mut |_| {}).unwrap();
    assert_eq!(rows.len(), 2);
    assert_eq!(front.len(), 2);
    assert!(
        front.iter().any(|&f| f),
        "some point is always on the front"
    );
    assert_eq!(
        (rows[0].config.as_str(), rows[1].config.as_str()),
        ("d", "a")
    );
    assert_eq!((rows[0].max_gaussians, rows[1].max_gaussians), (600, 400));
    assert_eq!(rows[1].init_points, 200);
    for r in &rows {
        assert!(r.psnr_db.is_finite() && r.psnr_db > 5.0, "{r:?}");
        assert!(r.ssim > 0.0 && r.ssim <= 1.0, "{r:?}");
        assert!(
            r.train_s > 0.0 && r.train_cpu_s > 0.0 && r.step_ms > 0.0,
            "{r:?}"
        );
        assert!(r.peak_rss_mb.is_finite() && r.peak_rss_mb > 1.0, "{r:?}");
        // 7 frames, all keyframes, W = 3: a round after each frame from the third on.
        assert_eq!((r.rounds, r.steps), (5, 15), "{r:?}");
        assert!(r.gaussians <= r.max_gaussians);
    }
    let csv = std::fs::read_to_string(out.join("pareto.csv")).unwrap();
    let lines: Vec<&str> = csv.lines().collect();
    assert_eq!(lines.len(), 3);
    assert_eq!(lines[0], CSV_HEADER);
    assert!(lines[1].starts_with("base,quick,d,40,"));
    assert!(lines[2].starts_with("small,quick,a,40,"));
    let png = image::open(out.join("pareto.png")).unwrap();
    assert_eq!((png.width(), png.height()), (960, 600));
    let md = std::fs::read_to_string(out.join("pareto.md")).unwrap();
    // The sweep table (header and two rows), then the ladder table (the same).
    assert_eq!(
        md.lines().filter(|l| l.starts_with("| ")).count(),
        6,
        "{md}"
    );
    assert!(
        md.contains("small** (a) |") || md.contains("| small (a) |"),
        "{md}"
    );
    assert!(md.contains("| **"), "front rows are bold: {md}");
    // Same seed, same metrics (times differ).
    let (again, _) = run_pareto(&job, &mut |_| {}).unwrap();
    for (a, b) in rows.iter().zip(&again) {
        assert_eq!(
            (a.psnr_db, a.ssim, a.masked_psnr_db, a.gaussians, a.steps),
            (b.psnr_db, b.ssim, b.masked_psnr_db, b.gaussians, b.steps)
        );
    }
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn tiny_skips_table_switches_one_skip_per_run() {
    let out = scratch("skips");
    // The tumble turns the view ~20 deg between frames: with a 30 deg keyframe rule some
    // frames leave the window unchanged.
    let base = Preset {
        frames: Some(10),
        min_view_angle_deg: 30.0,
        ..tiny_preset()
    };
    let job = SkipsJob {
        base,
        scenario: quick_scenario(),
        skips: switchable_skips(),
        out_dir: out.clone(),
    };
    let rows = run_skips(&job, &mut |_| {}).unwrap();
    let names: Vec<&str> = rows.iter().map(|r| r.spec.name.as_str()).collect();
    assert_eq!(
        names,
        [
            "eclipse",
            "unlit",
            "unchanged-window",
            "noncontributing-mlp",
            "frustum-cull",
            "early-termination",
            "masked-background-tiles"
        ]
    );
    // Defaults: the unlit skip off, the others on.
    let on: Vec<bool> = rows.iter().map(|r| r.default_on).collect();
    assert_eq!(on, [true, false, true, true, true, true, true]);
    // The base run is reused: eclipse "with" and unlit "without" are the same run.
    assert_eq!(rows[0].with, rows[1].without);
    assert!(rows[0].with.skip_eclipse && !rows[0].without.skip_eclipse);
    assert!(rows[1].with.skip_unlit && !rows[1].without.skip_unlit);
    // Without the unchanged-window skip a round follows every frame once the window is
    // full, also the frames the keyframe rule turned away: more rounds, more steps.
    let u = &rows[2];
    assert!(!u.without.skip_unchanged_window);
    assert!(u.without.rounds > u.with.rounds, "{u:?}");
    assert_eq!(u.without.steps, 3 * u.without.rounds);
    for r in &rows {
        assert!(r.saved_cpu_s().is_finite() && r.psnr_cost_db().is_finite());
    }
    // The network skip changes no image: the blend never reads the skipped Gaussians, so
    // only the networks' summation order differs, which over this short run moves the
    // metrics by far less than the 0.05 dB bound (over hundreds of steps the two paths
    // drift apart by tenths of a dB: docs/runtime-vs-error.md).
    let m = &rows[3];
    assert_eq!(m.with.steps, m.without.steps);
    assert!(m.psnr_cost_db().abs() < 0.05, "{m:?}");
    // The frustum cull and the background-tile skip change no image and no gradient, so
    // the runs with and without them train the same model to the bit.
    for r in [&rows[4], &rows[6]] {
        assert_eq!(
            (r.with.psnr_db, r.with.ssim, r.with.gaussians, r.with.steps),
            (
                r.without.psnr_db,
                r.without.ssim,
                r.without.gaussians,
                r.without.steps
            ),
            "{}",
            r.spec.name
        );
    }
    // The background-tile row trains masked on both sides (its own two runs), so it
    // differs from the full-frame base.
    assert_ne!(rows[6].with.psnr_db, rows[0].with.psnr_db);
    let csv = std::fs::read_to_string(out.join("skips.csv")).unwrap();
    assert_eq!(csv.lines().count(), 8);
    // The nine runs (base, one per context-free skip, two for the background tiles) in the
    // sweep's schema, readable back.
    let runs = std::fs::read_to_string(out.join("skips-runs.csv")).unwrap();
    let runs = from_csv(&runs).unwrap();
    assert_eq!(runs.len(), 9);
    assert_eq!(runs[7].setting, "masked-background-tiles-on");
    assert_eq!(runs[0].setting, "base");
    assert_eq!(runs[0].psnr_db, (rows[0].with.psnr_db * 1e3).round() / 1e3);
    let md = std::fs::read_to_string(out.join("skips.md")).unwrap();
    assert!(md.contains("| eclipse | on |") && md.contains("Not switchable"));
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn tiny_window_ablation_writes_one_row_per_window() {
    let out = scratch("window");
    let job = WindowJob {
        base: tiny_preset(),
        scenarios: vec![quick_scenario()],
        windows: vec![2, 4],
        out_dir: out.clone(),
    };
    let rows = run_window_ablation(&job, &mut |_| {}).unwrap();
    assert_eq!(rows.iter().map(|r| r.window).collect::<Vec<_>>(), [2, 4]);
    // 7 keyframes: W = 2 trains 6 rounds of 2 steps, W = 4 trains 4 rounds of 4.
    assert_eq!((rows[0].rounds, rows[0].steps), (6, 12));
    assert_eq!((rows[1].rounds, rows[1].steps), (4, 16));
    let csv = std::fs::read_to_string(out.join("window.csv")).unwrap();
    assert_eq!(csv.lines().count(), 3);
    assert!(csv.lines().nth(2).unwrap().starts_with("w4,quick,d,"));
    let md = std::fs::read_to_string(out.join("window.md")).unwrap();
    assert!(
        md.starts_with("| W | Quick masked PSNR dB (black) |"),
        "{md}"
    );
    let png = image::open(out.join("window.png")).unwrap();
    assert_eq!((png.width(), png.height()), (900, 1040));
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn window_plot_draws_each_targets_all_black_floor() {
    use sim_harness::experiment::ablation::window_plot;
    let mut rows = Vec::new();
    for (target, w) in [
        ("cassini", 5),
        ("cassini", 10),
        ("rosetta", 5),
        ("rosetta", 10),
    ] {
        let mut r = row(&format!("w{w}"), 10.0, 20.0);
        r.target = target.into();
        r.window = w;
        rows.push(r);
    }
    let count = |canvas: &sim_harness::dataset::plots::Canvas| {
        canvas
            .rgb8
            .chunks(3)
            .filter(|p| p[0] != p[1] || p[1] != p[2])
            .count()
    };
    let with_floors = count(&window_plot(&rows));
    // Without a black score there is no floor to draw: fewer coloured pixels.
    for r in &mut rows {
        r.ladder.eval.as_mut().unwrap().black_masked_psnr_db = f64::NAN;
    }
    let without = count(&window_plot(&rows));
    assert!(
        with_floors > without,
        "{with_floors} coloured pixels with floors, {without} without"
    );
}

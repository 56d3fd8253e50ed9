//! The initialisation ablation on a tiny scene: the hull's keyframes are the ones the online
//! window would take, the hull is far closer to the true surface than random points, its
//! colours come from the images (or grey), and the job writes every file with finite metrics.

use glam::Vec3;
use gs_online::online::Initialisation;
use sim_harness::experiment::ablation_init::{
    first_keyframes, hull_initialisation, mean_nearest_distance, merge_runs, parse_init,
    run_init_ablation, write_hull_figure, InitAblationJob, CSV_HEADER,
};
use sim_harness::experiment::data::{render_scene, SceneData};
use sim_harness::experiment::preset::{InitKind, Preset};
use sim_harness::scenario::Scenario;
use std::path::Path;

fn quick_scenario() -> Scenario {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../config/scenarios/quick.toml");
    Scenario::load(&path).unwrap()
}

fn tiny_preset() -> Preset {
    Preset {
        name: "tiny".into(),
        downsample: 20,
        cadence_s: 10.0,
        frames: Some(8),
        eval_views: 2,
        figure_views: 1,
        samples_per_pixel: 1,
        window: 3,
        init_points: 300,
        max_gaussians: 600,
        light_resolution_px: 32,
        densify_every_rounds: 2,
        hull_resolution: 40,
        configs: vec!["d".into()],
        ..Preset::default()
    }
}

fn tiny_scene(preset: &Preset) -> SceneData {
    let scenario = preset.apply(&quick_scenario()).unwrap();
    render_scene(&scenario, preset.init_points as usize, &mut |_| {}).unwrap()
}

#[test]
fn hull_starts_from_the_windows_first_keyframes_and_hugs_the_target() {
    let preset = tiny_preset();
    let mut scene = tiny_scene(&preset);
    // Mark a frame as eclipsed and repeat one view: neither may be carved from.
    scene.frames[1].eclipse = true;
    let repeated = scene.frames[2].clone();
    scene.frames[3] = repeated;
    scene.frames[3].index = 3;
    let picked = first_keyframes(&scene, 3, preset.min_view_angle_deg).unwrap();
    assert_eq!(picked, vec![0, 2, 4]);
    for pair in picked.windows(2) {
        let a = scene.frames[pair[0]].view_dir_target();
        let b = scene.frames[pair[1]].view_dir_target();
        assert!(a.angle_between(b).to_degrees() >= preset.min_view_angle_deg);
    }
    // Fewer frames than asked: all usable ones (8 frames less the eclipsed and repeated).
    assert_eq!(
        first_keyframes(&scene, 50, preset.min_view_angle_deg).unwrap(),
        vec![0, 2, 4, 5, 6, 7]
    );

    // K = 0: the window's size (3 here).
    let (_, report) = hull_initialisation(&scene, &preset).unwrap();
    assert_eq!(report.frames, vec![0, 2, 4]);
    let six = Preset {
        hull_views: 6,
        ..preset.clone()
    };
    let (init, report) = hull_initialisation(&scene, &six).unwrap();
    assert_eq!(report.frames, vec![0, 2, 4, 5, 6, 7]);
    let Initialisation::SurfaceSamples {
        points, colours, ..
    } = init
    else {
        panic!("a hull initialises from points");
    };
    assert_eq!(points.len(), report.points);
    assert!(points.len() <= preset.init_points as usize && points.len() > 100);
    let r = scene.bounding_radius_m;
    assert!(points
        .iter()
        .all(|p| p.is_finite() && p.abs().max_element() <= r));
    let colours = colours.unwrap();
    assert!(colours
        .iter()
        .all(|c| c.iter().all(|v| (0.0..=1.0).contains(v))));
    // Sampled colours vary (the target is not one flat grey).
    assert!(colours.iter().any(|c| (c[0] - 0.5).abs() > 0.1));
    // Much closer to the true surface than points spread over the bounding ball (six
    // views of 96x60 pixels: about 0.36 of the distance).
    let random: Vec<Vec3> = (0..points.len())
        .map(|i| {
            let t = (i as f32 + 0.5) / points.len() as f32;
            let (z, phi) = (1.0 - 2.0 * t, 2.399_963 * i as f32);
            let s = (1.0 - z * z).sqrt();
            Vec3::new(s * phi.cos(), s * phi.sin(), z) * r * t.cbrt()
        })
        .collect();
    let spread = mean_nearest_distance(&random, &scene);
    assert!(
        report.mean_distance_to_surface_m < 0.5 * spread,
        "hull {} m, ball {spread} m",
        report.mean_distance_to_surface_m
    );
    // Same inputs, same hull.
    let (_, again) = hull_initialisation(&scene, &six).unwrap();
    assert_eq!(
        (again.points, again.occupied_voxels, again.frames),
        (report.points, report.occupied_voxels, report.frames)
    );

    let grey = Preset {
        hull_grey_colours: true,
        ..preset.clone()
    };
    let (init, _) = hull_initialisation(&scene, &grey).unwrap();
    let Initialisation::SurfaceSamples { colours, .. } = init else {
        panic!("a hull initialises from points");
    };
    assert!(colours.unwrap().iter().all(|c| *c == [0.5; 3]));
}

#[test]
fn presets_name_the_hull_and_bad_values_are_errors() {
    let p = Preset::from_toml_str("init = \"hull\"\nhull_views = 8\nhull_resolution = 64", "t")
        .unwrap();
    assert_eq!(
        (p.init, p.hull_views, p.hull_resolution),
        (InitKind::Hull, 8, 64)
    );
    let e = Preset::from_toml_str("hull_resolution = 4", "t")
        .unwrap_err()
        .to_string();
    assert!(e.contains("hull_resolution"), "{e}");
    assert!(parse_init("hull-grey").unwrap() == (InitKind::Hull, true));
    assert!(parse_init("sfm").unwrap_err().to_string().contains("sfm"));
}

#[test]
fn tiny_ablation_writes_every_file_with_finite_metrics() {
    let out = std::env::temp_dir().join(format!("sim-harness-init-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let job = InitAblationJob {
        preset: Preset {
            eval_every_rounds: 2,
            ..tiny_preset()
        },
        scenarios: vec![quick_scenario()],
        inits: ["surface", "random", "hull"].map(String::from).to_vec(),
        out_dir: out.clone(),
    };
    let result = run_init_ablation(&job, &mut |_| {}).unwrap();
    assert_eq!(result.runs.len(), 3);
    for (run, init) in result.runs.iter().zip(["surface", "random", "hull"]) {
        assert_eq!(run.init, init);
        assert_eq!(run.run.config, "d");
        assert!(run.run.eval.psnr_db.is_finite() && run.run.eval.psnr_db > 5.0);
        assert!(run.run.rounds > 0 && !run.run.curve.is_empty());
        assert!(!run.run.eval_curve.is_empty());
        assert!(run.initial_gaussians > 0 && run.cpu_s.is_finite() && run.cpu_s >= 0.0);
        assert_eq!(run.hull.is_some(), init == "hull");
    }
    assert_eq!(result.runs[1].initial_gaussians, 300);
    let csv = std::fs::read_to_string(out.join("init.csv")).unwrap();
    assert!(csv.starts_with(&format!("{CSV_HEADER}\n")));
    assert_eq!(csv.lines().count(), 4);
    let columns = CSV_HEADER.split(',').count();
    assert!(
        csv.lines().all(|l| l.split(',').count() == columns),
        "{csv}"
    );
    let md = std::fs::read_to_string(out.join("init.md")).unwrap();
    assert!(md.contains("| Quick | hull |"), "{md}");
    // The ladder of every run, and each start paired against surface samples on every rung
    // (the same views for both starts: a number, never `-`, on L0 and L2).
    assert!(md.contains("Accuracy ladder"), "{md}");
    assert!(md.contains("| Quick hull |"), "{md}");
    for init in ["random", "hull"] {
        let row = md
            .lines()
            .find(|l| l.starts_with(&format!("| Quick | {init} − surface |")))
            .unwrap_or_else(|| panic!("no paired row for {init}: {md}"));
        let cells: Vec<&str> = row.split('|').map(str::trim).collect();
        assert!(cells[3].contains('±') && cells[6].contains('±'), "{row}");
    }
    // Every row of a table has as many cells as its header (pipes in text are escaped).
    let cells = |line: &str| line.replace("\\|", "").matches('|').count();
    for table in md.split("\n\n").filter(|t| t.starts_with('|')) {
        let header = cells(table.lines().next().unwrap());
        assert!(table.lines().all(|l| cells(l) == header), "{table}");
    }
    assert!(md.contains("Visual hulls"));
    // runs.json reads back: merged on its own it rewrites the same tables; merged twice,
    // every run appears twice (and the merge refuses a file that is not a runs.json).
    let merged_dir = out.join("merged");
    let runs_json = out.join("runs.json");
    let merged = merge_runs(std::slice::from_ref(&runs_json), &merged_dir).unwrap();
    assert_eq!(merged.len(), 3);
    assert_eq!(
        std::fs::read_to_string(merged_dir.join("init.md")).unwrap(),
        md
    );
    assert_eq!(
        std::fs::read_to_string(merged_dir.join("init.csv")).unwrap(),
        csv
    );
    let twice = merge_runs(&[runs_json.clone(), runs_json], &merged_dir).unwrap();
    assert_eq!(twice.len(), 6);
    assert!(image::open(merged_dir.join("init.png")).is_ok());
    let err = merge_runs(&[out.join("init.csv")], &merged_dir).unwrap_err();
    assert!(err.to_string().contains("init.csv"), "{err}");
    let curves = std::fs::read_to_string(out.join("init_curves.csv")).unwrap();
    let rounds: usize = result.runs.iter().map(|r| r.run.curve.len()).sum();
    assert_eq!(curves.lines().count(), rounds + 1);
    let png = image::open(out.join("init.png")).unwrap();
    assert!(png.width() >= 400 && png.height() >= 500);
    // hull.png: one row of four panels (model and hull, two projections each), with the
    // points drawn over the dark panel background.
    let reports = write_hull_figure(&job, &mut |_| {}).unwrap();
    assert_eq!(reports.len(), 1);
    let (figure, trained) = (&reports[0].1, result.runs[2].hull.as_ref().unwrap());
    assert_eq!(
        (&figure.frames, figure.points, figure.occupied_voxels),
        (&trained.frames, trained.points, trained.occupied_voxels)
    );
    let hull_png = image::open(out.join("hull.png")).unwrap().to_rgb8();
    assert!(hull_png.width() >= 4 * 220);
    let background = image::Rgb([35u8, 35, 45]);
    let white = image::Rgb([255u8, 255, 255]);
    let drawn = hull_png
        .pixels()
        .filter(|p| **p != background && **p != white)
        .count();
    assert!(drawn > 1000, "{drawn}");
    let _ = std::fs::remove_dir_all(&out);
}

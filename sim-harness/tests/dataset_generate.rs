//! End-to-end dataset generation: exact output layout, byte-identical reruns, telemetry
//! consistent with the images, eclipse frames dark, clear errors from the command line.

use sim_harness::dataset::{generate, GenerateOptions};
use sim_harness::scenario::Scenario;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("sim-harness-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

fn small(text: &str) -> Scenario {
    Scenario::from_toml_str(text, Path::new("."))
        .unwrap()
        .with_overrides(Some(5), Some(16), Some(3))
        .unwrap()
}

/// Every file under `root` (relative path -> bytes).
fn read_tree(root: &Path) -> BTreeMap<String, Vec<u8>> {
    let mut out = BTreeMap::new();
    let mut stack = vec![root.to_path_buf()];
    while let Some(dir) = stack.pop() {
        for entry in std::fs::read_dir(&dir).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                stack.push(path);
            } else {
                let rel = path
                    .strip_prefix(root)
                    .unwrap()
                    .to_string_lossy()
                    .replace('\\', "/");
                out.insert(rel, std::fs::read(&path).unwrap());
            }
        }
    }
    out
}

fn telemetry(root: &Path) -> Vec<serde_json::Value> {
    std::fs::read_to_string(root.join("telemetry.jsonl"))
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect()
}

fn vec3(v: &serde_json::Value) -> [f64; 3] {
    [0, 1, 2].map(|i| v[i].as_f64().unwrap())
}

fn npy_f32(bytes: &[u8]) -> Vec<f32> {
    let header_len = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
    bytes[10 + header_len..]
        .chunks(4)
        .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
        .collect()
}

const QUICK: &str = "seed = 3\n[target]\nsurface_points = 300\n[sequence]\ncadence_s = 20.0\n\
                     [render]\nsamples_per_pixel = 1\n[noise]\nsun_jitter_deg = 0.5\nposition_bias_m = 0.2\n";

#[test]
fn same_scenario_gives_byte_identical_output_with_the_documented_layout() {
    let scenario = small(QUICK);
    let (a, b) = (temp_dir("det-a"), temp_dir("det-b"));
    let summary = generate(&scenario, &a, GenerateOptions::default(), &mut |_| {}).unwrap();
    // The second run on a single thread: the thread count must not change a byte.
    let one_thread = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    one_thread
        .install(|| generate(&scenario, &b, GenerateOptions::default(), &mut |_| {}))
        .unwrap();
    let (tree_a, tree_b) = (read_tree(&a), read_tree(&b));
    let mut expected: Vec<String> = [
        "points.ply",
        "telemetry.jsonl",
        "contact_sheet.png",
        "trajectory.png",
        "eval/telemetry.jsonl",
    ]
    .iter()
    .map(ToString::to_string)
    .collect();
    for (prefix, count) in [("", 5), ("eval/", 3)] {
        for i in 0..count {
            expected.push(format!("{prefix}frames/{i:06}.png"));
            expected.push(format!("{prefix}masks/{i:06}.png"));
            expected.push(format!("{prefix}depth/{i:06}.npy"));
        }
    }
    expected.sort();
    assert_eq!(tree_a.keys().cloned().collect::<Vec<_>>(), expected);
    for (name, bytes) in &tree_a {
        assert!(tree_b[name] == *bytes, "{name} differs between two runs");
    }
    assert_eq!(summary.frames, 5);
    assert_eq!(summary.surface_points, 300);
    // A different seed changes the noise, the eval views and the surface samples.
    let c = temp_dir("det-c");
    let other_seed = Scenario {
        seed: 4,
        ..scenario.clone()
    };
    generate(&other_seed, &c, GenerateOptions::default(), &mut |_| {}).unwrap();
    let tree_c = read_tree(&c);
    for name in ["telemetry.jsonl", "points.ply", "eval/frames/000000.png"] {
        assert!(tree_c[name] != tree_a[name], "{name} ignores the seed");
    }
    // Images come from the truth: without noise the frames are the same, the telemetry not.
    let d = temp_dir("det-d");
    let no_noise = Scenario {
        noise: Default::default(),
        ..scenario.clone()
    };
    generate(&no_noise, &d, GenerateOptions::default(), &mut |_| {}).unwrap();
    let tree_d = read_tree(&d);
    assert!(tree_d["frames/000002.png"] == tree_a["frames/000002.png"]);
    assert!(tree_d["telemetry.jsonl"] != tree_a["telemetry.jsonl"]);
    // Refuses to write into a non-empty folder unless asked to.
    let err = generate(&scenario, &a, GenerateOptions::default(), &mut |_| {}).unwrap_err();
    assert!(err.to_string().contains("not empty"), "{err}");
    for dir in [a, b, c, d] {
        std::fs::remove_dir_all(dir).unwrap();
    }
}

#[test]
fn telemetry_pose_depth_and_mask_agree() {
    let scenario = small("[target]\nsurface_points = 100\n[render]\nsamples_per_pixel = 1\n");
    let out = temp_dir("tele");
    let summary = generate(&scenario, &out, GenerateOptions::default(), &mut |_| {}).unwrap();
    let lines = telemetry(&out);
    assert_eq!(lines.len(), 5);
    for (i, line) in lines.iter().enumerate() {
        assert_eq!(line["index"].as_u64().unwrap(), i as u64);
        assert_eq!(line["time_s"].as_f64().unwrap(), 5.0 * i as f64);
        // No noise configured: the reported values are the truth.
        assert_eq!(
            line["q_camera_from_target_wxyz"],
            line["truth"]["q_camera_from_target_wxyz"]
        );
        assert_eq!(line["sun_target_body"], line["truth"]["sun_target_body"]);
        let t = vec3(&line["t_camera_from_target_m"]);
        let range = line["truth"]["range_m"].as_f64().unwrap();
        assert!(t[0].abs() < 1e-9 && t[1].abs() < 1e-9 && (t[2] - range).abs() < 1e-9);
        let sun = vec3(&line["sun_target_body"]);
        assert!(((sun[0] * sun[0] + sun[1] * sun[1] + sun[2] * sun[2]).sqrt() - 1.0).abs() < 1e-12);
        let intr = &line["intrinsics"];
        let (w, h) = (
            intr["width"].as_u64().unwrap() as usize,
            intr["height"].as_u64().unwrap() as usize,
        );
        assert_eq!((w, h), (120, 75));
        let mask = image::open(out.join(line["mask"].as_str().unwrap()))
            .unwrap()
            .to_luma8();
        let depth = npy_f32(&std::fs::read(out.join(line["depth"].as_str().unwrap())).unwrap());
        assert_eq!(depth.len(), w * h);
        let mut hits = 0;
        for (k, d) in depth.iter().enumerate() {
            let m = mask.as_raw()[k];
            if m == 255 {
                hits += 1;
                // Every hit lies within the bounding sphere around the target at `range`.
                let r = summary.target_bounding_radius_m as f32;
                assert!(
                    *d > range as f32 - r - 1e-3 && *d < range as f32 + r + 1e-3,
                    "depth {d}"
                );
            } else {
                assert_eq!(m, 0);
                assert!(d.is_infinite());
            }
        }
        assert!(
            hits > 20,
            "the target is in view (frame {i}: {hits} pixels)"
        );
    }
    std::fs::remove_dir_all(out).unwrap();
}

#[test]
fn eclipse_frames_are_flagged_and_dark() {
    // beta ~ 0 at the March equinox and the chief starting at the anti-Sun point: umbra.
    let scenario = small("[chief_orbit]\nraan_deg = 0.0\nmean_anomaly_deg = 180.0\n[render]\nsamples_per_pixel = 1\n");
    let out = temp_dir("eclipse");
    let summary = generate(&scenario, &out, GenerateOptions::default(), &mut |_| {}).unwrap();
    assert_eq!(summary.eclipse_frames, 5);
    for line in telemetry(&out) {
        assert!(line["eclipse"].as_bool().unwrap());
        assert_eq!(line["truth"]["sun_visible_fraction"].as_f64().unwrap(), 0.0);
        let frame = image::open(out.join(line["frame"].as_str().unwrap()))
            .unwrap()
            .to_rgb8();
        assert!(
            frame.as_raw().iter().all(|&v| v == 0),
            "no light leaks into an eclipse frame"
        );
        let mask = image::open(out.join(line["mask"].as_str().unwrap()))
            .unwrap()
            .to_luma8();
        assert!(mask.as_raw().contains(&255), "the target is still there");
    }
    // Evaluation views are always sunlit and not black.
    let eval_frame = image::open(out.join("eval/frames/000000.png"))
        .unwrap()
        .to_rgb8();
    assert!(eval_frame.as_raw().iter().any(|&v| v > 0));
    std::fs::remove_dir_all(out).unwrap();
}

#[test]
fn shipped_scenarios_load_with_the_paper_defaults() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../config/scenarios");
    for name in ["cassini", "rosetta", "starlink"] {
        let s = Scenario::load(&dir.join(format!("{name}.toml"))).unwrap();
        assert_eq!(s.name, name);
        assert_eq!(s.frame_count(), 5764);
        assert_eq!(s.sequence.eval_views, 100);
        // The file spells out the defaults: it equals the built-in default but for the target.
        let mut expected = Scenario {
            name: name.to_string(),
            base_dir: s.base_dir.clone(),
            ..Scenario::default()
        };
        expected.target.builtin = s.target.builtin;
        assert_eq!(s, expected);
    }
    let quick = Scenario::load(&dir.join("quick.toml")).unwrap();
    assert_eq!(quick.frame_count(), 24);
}

#[test]
fn command_line_reports_bad_files_clearly() {
    let dir = temp_dir("cli");
    std::fs::create_dir_all(&dir).unwrap();
    let bad = dir.join("bad.toml");
    std::fs::write(&bad, "[camera]\ndownsample = 2\nfocal_length = 10.0\n").unwrap();
    let output = std::process::Command::new(env!("CARGO_BIN_EXE_sim-harness"))
        .args(["generate", "--scenario"])
        .arg(&bad)
        .arg("--out")
        .arg(dir.join("out"))
        .output()
        .unwrap();
    assert_eq!(output.status.code(), Some(1));
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        stderr.contains("bad.toml") && stderr.contains("focal_length"),
        "{stderr}"
    );
    let output = std::process::Command::new(env!("CARGO_BIN_EXE_sim-harness"))
        .args([
            "generate",
            "--scenario",
            "config/scenarios/quick.toml",
            "--frames",
            "0",
            "--out",
        ])
        .arg(dir.join("out"))
        .current_dir(Path::new(env!("CARGO_MANIFEST_DIR")).join(".."))
        .output()
        .unwrap();
    assert_eq!(output.status.code(), Some(1));
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(stderr.contains("sequence.frames"), "{stderr}");
    assert!(!dir.join("out").exists(), "nothing written on error");
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn obj_targets_load_relative_to_the_scenario_file() {
    let dir = temp_dir("obj");
    std::fs::create_dir_all(dir.join("models")).unwrap();
    // A 2 m cube centred on the body origin.
    let mut obj = String::new();
    for z in [-1.0, 1.0] {
        for y in [-1.0, 1.0] {
            for x in [-1.0, 1.0] {
                obj.push_str(&format!("v {x} {y} {z}\n"));
            }
        }
    }
    for f in [
        "1 3 4 2", "5 6 8 7", "1 2 6 5", "3 7 8 4", "1 5 7 3", "2 4 8 6",
    ] {
        obj.push_str(&format!("f {f}\n"));
    }
    std::fs::write(dir.join("models/cube.obj"), obj).unwrap();
    let scenario_path = dir.join("cube.toml");
    std::fs::write(
        &scenario_path,
        "[target]\nobj = \"models/cube.obj\"\nsurface_points = 50\n[sequence]\nframes = 2\neval_views = 1\n\
         [camera]\ndownsample = 16\n[render]\nsamples_per_pixel = 1\n",
    )
    .unwrap();
    let scenario = Scenario::load(&scenario_path).unwrap();
    assert_eq!(scenario.name, "cube");
    let summary = generate(
        &scenario,
        &dir.join("out"),
        GenerateOptions::default(),
        &mut |_| {},
    )
    .unwrap();
    assert_eq!(summary.target_triangles, 12);
    assert!((summary.target_bounding_radius_m - 3f64.sqrt()).abs() < 1e-6);
    let mask = image::open(dir.join("out/masks/000000.png"))
        .unwrap()
        .to_luma8();
    assert!(mask.as_raw().contains(&255));
    // A missing mesh is an error naming the file.
    std::fs::write(&scenario_path, "[target]\nobj = \"models/missing.obj\"\n").unwrap();
    let err = generate(
        &Scenario::load(&scenario_path).unwrap(),
        &dir.join("out2"),
        GenerateOptions::default(),
        &mut |_| {},
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("missing.obj"), "{err}");
    std::fs::remove_dir_all(dir).unwrap();
}

/// A bad `GS_F32_KERNEL`, `GS_BF16_KERNEL` or `GS_DENORMALS` stops the binary at start with a usage error
/// (status 2) naming the variable, before any work (no output directory).
#[test]
fn a_bad_compute_environment_variable_stops_the_start() {
    let dir = std::env::temp_dir().join(format!("gs_bad_env_{}", std::process::id()));
    for (var, value) in [
        ("GS_F32_KERNEL", "sse9"),
        ("GS_BF16_KERNEL", "fp8"),
        ("GS_DENORMALS", "sometimes"),
    ] {
        let output = std::process::Command::new(env!("CARGO_BIN_EXE_sim-harness"))
            .args([
                "generate",
                "--scenario",
                "config/scenarios/quick.toml",
                "--out",
            ])
            .arg(&dir)
            .env(var, value)
            .current_dir(Path::new(env!("CARGO_MANIFEST_DIR")).join(".."))
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert_eq!(output.status.code(), Some(2), "{var}={value}: {stderr}");
        assert!(stderr.contains(var) && stderr.contains(value), "{stderr}");
        assert!(!dir.exists(), "{var}={value}: nothing written");
    }
}

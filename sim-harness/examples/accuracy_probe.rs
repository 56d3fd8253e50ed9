//! The accuracy work's measuring tool, on the demo's scenario and preset (with overrides):
//! - default: the offline reference, the same model trained on all lit frames at once (a
//!   random frame per step, one long schedule, densifying in the first half), masked PSNR on
//!   those frames as it goes: what the representation can fit without the online procedure;
//! - `--online 1`: the online procedure (`experiment::runner::run_config`), its ladder line,
//!   then each evaluation view (L2) and each held-out frame (L1) with its distance to the
//!   nearest trained Sun and viewpoint, then the error of the held-out frames (L1) and of
//!   the final window (L0) split by the material each pixel's centre ray hits, then the
//!   Sun and view sweeps: model and ray-traced truth of the window's frames with only the
//!   Sun, then only the camera, moved;
//! - `--noise-ref SPP`: the ground truth's own Monte Carlo noise, masked PSNR of the frames
//!   at the preset's samples per pixel against the same frames at SPP (the ceiling any model
//!   scored against that ground truth meets).
//!
//! `docs/results/accuracy.md` shows what it measured.

const USAGE: &str = "accuracy_probe: the accuracy ladder's measurements on the demo scenario

usage: cargo run --release -p sim-harness --example accuracy_probe -- [options]
  --scenario PATH      a scenario file instead of the demo's (the demo's preset still applies)
  --config a|b|c|d     configuration (default a)
  --tumble DEG_S       target tumble rate (default: the scenario's; 0: a static target)
  --spp N              ray-tracing samples per pixel (default: the preset's)
  --earth F            Earth-albedo fill (default: the preset's)
  --extra TOML         preset lines added to the demo preset's top-level keys, before
                       its tables such as [rates] (\\n for new lines); a key the
                       preset already sets is replaced
  --rates TOML         lines added to the demo preset's [rates] table ('normal = 0.01');
                       a rate the preset already sets is replaced
  --max-gaussians N    densification cap
  --steps N            offline steps (default 3000)
  --densify-every N    offline: densify every N steps in the first half (default 100)
  --masked 1           offline: masked loss
  --png PATH           offline: truth | render for four training frames; online: per
                       held-out frame, nearest trained frame | truth | render
  --png-eval 1         offline: the figure shows evaluation views instead
  --online 1           run the online procedure instead (--rounds R, --window W)
  --noise-ref SPP      measure the ground truth's noise against SPP samples per pixel";

use gs_core::loss::psnr_db_from_mse;
use gs_core::sunaware::trainer::Observation;
use gs_core::sunaware::Variant;
use sim_harness::experiment::data::render_scene;
use sim_harness::experiment::demo::DEMO_PRESET;
use sim_harness::experiment::evaluate::{
    black_baseline, camera_of, evaluate_views, frame_request_of, nearest_angle_deg, sun_of,
};
use sim_harness::experiment::preset::Preset;
use sim_harness::experiment::runner::{online_config, scene_box, try_initialisation};
use sim_harness::raytrace::material_ids;
use sim_harness::scenario::Scenario;

/// The target's material names, in `raytrace::material_ids` index order.
fn material_names(rt: &sim_harness::raytrace::Scene) -> Vec<String> {
    rt.mesh()
        .materials()
        .iter()
        .map(|m| m.name.clone())
        .collect()
}

/// Squared error (summed over channels, images clamped to [0, 1]) of the model and of an
/// all-black render over the target pixels of one material, and the model's summed signed
/// error (render - truth).
#[derive(Clone, Copy, Default)]
struct MaterialError {
    pixels: u64,
    model_se: f64,
    black_se: f64,
    model_bias: f64,
    /// Sum of the render's accumulated opacity: below 1 where the model leaves holes.
    alpha_sum: f64,
}

/// Prints, for `views` pooled, each material's target pixels, its share of the model's masked
/// squared error, its PSNR and the all-black PSNR over its pixels only, and the model's mean
/// signed error there in 8-bit levels (negative: drawn too dark) and its mean opacity.
fn print_material_split(
    rung: &str,
    rt: &sim_harness::raytrace::Scene,
    model: &gs_core::sunaware::SunAwareModel,
    k: &sim_harness::experiment::data::SceneIntrinsics,
    views: &[&sim_harness::experiment::data::ViewData],
) -> Result<(), Box<dyn std::error::Error>> {
    let mut names = material_names(rt);
    // Masked pixels whose centre ray hits nothing (none expected: the mask is that hit).
    names.push("(no centre hit)".into());
    let mut split = vec![MaterialError::default(); names.len()];
    for view in views {
        let ids = material_ids(rt, &frame_request_of(k, view))?;
        let rendered = model.render(&camera_of(k, view), sun_of(view))?;
        let render = rendered.image;
        let truth = view.rgb_f32();
        for (p, (&m, id)) in view.mask_f32().iter().zip(&ids).enumerate() {
            if m <= 0.0 {
                continue;
            }
            let e = &mut split[id.map_or(names.len() - 1, usize::from)];
            e.pixels += 1;
            e.alpha_sum += rendered.alpha[p] as f64;
            for c in 3 * p..3 * p + 3 {
                let t = truth[c].clamp(0.0, 1.0) as f64;
                let d = render[c].clamp(0.0, 1.0) as f64 - t;
                e.model_se += d * d;
                e.black_se += t * t;
                e.model_bias += d;
            }
        }
    }
    let all = split
        .iter()
        .fold(MaterialError::default(), |a, e| MaterialError {
            pixels: a.pixels + e.pixels,
            model_se: a.model_se + e.model_se,
            black_se: a.black_se + e.black_se,
            model_bias: a.model_bias + e.model_bias,
            alpha_sum: a.alpha_sum + e.alpha_sum,
        });
    let psnr = |se: f64, pixels: u64| psnr_db_from_mse(se / (3 * pixels.max(1)) as f64);
    eprintln!(
        "{rung}, {} frames pooled, by material (centre-ray hit):\n| material | pixels | share of pixels | share of squared error | PSNR | all-black PSNR | mean render - truth | mean alpha |\n|---|---:|---:|---:|---:|---:|---:|---:|",
        views.len()
    );
    for (name, e) in names.iter().zip(&split).chain([(&"all".to_string(), &all)]) {
        if e.pixels == 0 {
            continue;
        }
        eprintln!(
            "| {name} | {} | {:.1} % | {:.1} % | {:.2} dB | {:.2} dB | {:+.1} /255 | {:.3} |",
            e.pixels,
            100.0 * e.pixels as f64 / all.pixels.max(1) as f64,
            100.0 * e.model_se / all.model_se,
            psnr(e.model_se, e.pixels),
            psnr(e.black_se, e.pixels),
            255.0 * e.model_bias / (3 * e.pixels) as f64,
            e.alpha_sum / e.pixels as f64
        );
    }
    Ok(())
}

/// Signed offsets of the Sun and view sweeps, degrees.
const SWEEP_OFFSETS_DEG: [f64; 9] = [-20.0, -10.0, -5.0, -2.0, 0.0, 2.0, 5.0, 10.0, 20.0];

/// Sun or view sweep: held-out frames are drawn too dark while the window's are not, so this
/// moves only the Sun (`move_view` false: rotated about Sun x view direction, positive towards
/// the camera, i.e. a smaller phase angle; camera unchanged) or only the camera (`move_view`
/// true: orbiting the target's origin, Sun fixed in the body frame) away from each of
/// `views`' own, and prints, pooled, each material's mean 8-bit level in the ray-traced truth
/// (the frame's dataset request, so moved) and in the model's render, and the masked PSNR of
/// all target pixels: whether the model's brightness falls off faster than the truth's.
fn print_sweep(
    move_view: bool,
    rung: &str,
    scenario: &Scenario,
    rt: &sim_harness::raytrace::Scene,
    model: &gs_core::sunaware::SunAwareModel,
    k: &sim_harness::experiment::data::SceneIntrinsics,
    views: &[&sim_harness::experiment::data::ViewData],
) -> Result<(), Box<dyn std::error::Error>> {
    let names = material_names(rt);
    // Per offset: per material (truth sum, render sum, channel values), and all target
    // pixels' squared error and channel values.
    let mut sums =
        vec![(vec![(0.0f64, 0.0f64, 0u64); names.len()], 0.0f64, 0u64); SWEEP_OFFSETS_DEG.len()];
    let mut zero_offset_identical = true;
    for view in views {
        let request =
            sim_harness::experiment::data::sequence_frame_request(scenario, rt.mesh(), view.index)?;
        let sun = view.sun_dir_target;
        let axis = sun
            .cross(view.view_dir_target())
            .try_normalize()
            .unwrap_or_else(|| sun.any_orthonormal_vector());
        // View mode: the camera orbits the target's origin about the part of the Sun
        // perpendicular to the view, so the phase angle stays (to first order) and the Sun
        // stays fixed in the body frame.
        let view_axis = view
            .view_dir_target()
            .cross(axis)
            .try_normalize()
            .unwrap_or(axis);
        for (deg, (per_material, se, n)) in SWEEP_OFFSETS_DEG.iter().zip(&mut sums) {
            let turn = glam::DQuat::from_axis_angle(
                if move_view { view_axis } else { axis },
                deg.to_radians(),
            );
            let mut moved_view = (*view).clone();
            let mut moved = sun.as_vec3();
            if move_view {
                moved_view.q_camera_from_target = view.q_camera_from_target * turn;
            } else {
                moved = (turn * sun).as_vec3();
            }
            let ids = material_ids(rt, &frame_request_of(k, &moved_view))?;
            let camera = camera_of(k, &moved_view);
            let truth = sim_harness::raytrace::try_render_frame(
                rt,
                &sim_harness::raytrace::FrameRequest {
                    sun_dir_target: moved.normalize(),
                    camera_from_target_rotation: camera.rotation,
                    ..request
                },
            )?
            .rgb8;
            zero_offset_identical &= *deg != 0.0 || truth == view.rgb8;
            let render = model.render(&camera, moved.normalize())?.image;
            for (p, id) in ids.iter().enumerate() {
                let Some(id) = id else { continue };
                let e = &mut per_material[usize::from(*id)];
                for c in 3 * p..3 * p + 3 {
                    let t = truth[c] as f64 / 255.0;
                    let r = render[c].clamp(0.0, 1.0) as f64;
                    *e = (e.0 + 255.0 * t, e.1 + 255.0 * r, e.2 + 1);
                    *se += (r - t) * (r - t);
                    *n += 1;
                }
            }
        }
    }
    let (what, positive) = if move_view {
        (
            "view",
            "the camera turned about the Sun's part across the view",
        )
    } else {
        ("Sun", "towards the camera")
    };
    eprintln!(
        "{rung}, {} frames pooled, {what} sweep (offset > 0: {positive}; offset 0 truth identical to the stored frames: {zero_offset_identical}), mean 8-bit level truth / render by material (centre-ray hit):",
        views.len(),
    );
    let header: String = names.iter().map(|m| format!(" {m} |")).collect();
    let rule: String = names.iter().map(|_| "---:|").collect();
    eprintln!("| {what} offset |{header} masked PSNR |\n|---:|{rule}---:|");
    for (deg, (per_material, se, n)) in SWEEP_OFFSETS_DEG.iter().zip(&sums) {
        let levels: String = per_material
            .iter()
            .map(|(t, r, c)| {
                let c = (*c).max(1) as f64;
                format!(" {:.1} / {:.1} |", t / c, r / c)
            })
            .collect();
        let psnr = psnr_db_from_mse(se / (*n).max(1) as f64);
        eprintln!("| {deg:+.0} deg |{levels} {psnr:.2} dB |");
    }
    Ok(())
}

/// Writes `rows` of equally sized sRGB panels (`w x h` each) side by side, rows stacked,
/// upscaled 3x (nearest neighbour) as a PNG.
fn write_panels(
    path: &str,
    w: usize,
    h: usize,
    rows: &[Vec<Vec<u8>>],
) -> Result<(), Box<dyn std::error::Error>> {
    let cols = rows.iter().map(Vec::len).max().unwrap_or(0);
    let mut out = vec![0u8; 3 * (cols * w) * (h * rows.len())];
    for (r, panels) in rows.iter().enumerate() {
        for (c, panel) in panels.iter().enumerate() {
            for y in 0..h {
                let dst = 3 * ((r * h + y) * cols * w + c * w);
                out[dst..dst + 3 * w].copy_from_slice(&panel[3 * y * w..3 * (y + 1) * w]);
            }
        }
    }
    let up = sim_harness::experiment::figure::upscale_rgb(
        (cols * w) as u32,
        (h * rows.len()) as u32,
        &out,
        3,
    );
    sim_harness::dataset::files::write_png_rgb(
        std::path::Path::new(path),
        (3 * cols * w) as u32,
        (3 * h * rows.len()) as u32,
        &up,
    )?;
    Ok(())
}

fn arg(name: &str) -> Option<String> {
    let args: Vec<String> = std::env::args().collect();
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1).cloned())
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    if std::env::args().any(|a| a == "--help" || a == "-h") {
        println!("{USAGE}\n\n{}", gs_core::fpmode::ENV_HELP);
        return Ok(());
    }
    gs_core::heap::retain_freed_memory();
    gs_core::fpmode::init_from_env(None)?;
    let steps: u64 = arg("--steps").map_or(Ok(3000), |s| s.parse())?;
    let variant: Variant = arg("--config").unwrap_or("a".into()).parse()?;
    let masked = arg("--masked").is_some_and(|s| s == "1");
    let extra = arg("--extra").unwrap_or_default().replace("\\n", "\n");
    // Top-level keys must come before the preset's first table, or TOML files them in it.
    let tables_at = DEMO_PRESET.find("\n[").unwrap_or(DEMO_PRESET.len());
    let (top, tables) = DEMO_PRESET.split_at(tables_at);
    // A key set in `--extra` or `--rates` replaces the demo preset's line for it (TOML
    // forbids repeats).
    let key_of = |line: &str| line.split('=').next().map(|k| k.trim().to_string());
    let keys_in = |text: &str| -> Vec<String> {
        text.lines()
            .filter(|l| l.contains('='))
            .filter_map(key_of)
            .collect()
    };
    let without = |text: &str, keys: &[String]| -> String {
        text.lines()
            .filter(|l| !(l.contains('=') && key_of(l).is_some_and(|k| keys.contains(&k))))
            .map(|l| format!("{l}\n"))
            .collect()
    };
    let top = without(top, &keys_in(&extra));
    // The demo preset's last table is [rates]: lines after it land there.
    let rates = arg("--rates").unwrap_or_default().replace("\\n", "\n");
    let tables = without(tables, &keys_in(&rates));
    let mut preset =
        Preset::from_toml_str(&format!("{top}\n{extra}\n{tables}\n{rates}\n"), "demo")?;
    let base = match arg("--scenario") {
        Some(path) => Scenario::load(std::path::Path::new(&path))?,
        None => Scenario::from_toml_str(
            sim_harness::experiment::demo::DEMO_SCENARIO,
            std::path::Path::new("."),
        )?,
    };
    let mut scenario = preset.apply(&base)?;
    if let Some(rate) = arg("--tumble") {
        scenario.attitude.tumble_rate_deg_s = rate.parse()?;
    }
    if let Some(spp) = arg("--spp") {
        scenario.render.samples_per_pixel = spp.parse()?;
    }
    if let Some(e) = arg("--earth") {
        scenario.render.earth_albedo = e.parse()?;
    }
    let spp = scenario.render.samples_per_pixel;
    if let Some(m) = arg("--max-gaussians") {
        preset.max_gaussians = m.parse()?;
    }
    let scene = render_scene(&scenario, preset.init_points as usize, &mut |m| {
        eprintln!("{m}");
    })?;
    if let Some(ref_spp) = arg("--noise-ref") {
        let mut reference = scenario.clone();
        reference.render.samples_per_pixel = ref_spp.parse()?;
        let ref_scene = render_scene(&reference, 10, &mut |m| eprintln!("{m}"))?;
        let shape = gs_core::loss::ImageShape::new(
            scene.intrinsics.width as usize,
            scene.intrinsics.height as usize,
            3,
        );
        let (mut sum, mut n) = (0.0f64, 0usize);
        for (a, b) in scene.frames.iter().zip(&ref_scene.frames) {
            if a.eclipse {
                continue;
            }
            let mask = b.mask_f32();
            let p = gs_core::sunaware::trainer::masked_psnr(
                &a.rgb_f32(),
                &b.rgb_f32(),
                Some(&mask),
                shape,
            )?;
            sum += p as f64;
            n += 1;
        }
        eprintln!(
            "ground truth at {spp} spp against {ref_spp} spp: masked PSNR {:.2} dB over {n} lit frames",
            sum / n as f64
        );
        return Ok(());
    }
    if arg("--online").is_some_and(|s| s == "1") {
        if let Some(r) = arg("--rounds") {
            preset.rounds_per_window_change = r.parse()?;
        }
        if let Some(w) = arg("--window") {
            preset.window = w.parse()?;
        }
        let (o, trainer) =
            sim_harness::experiment::runner::run_config(&scene, &preset, variant, 0, &mut |m| {
                eprintln!("{m}");
            })?;
        eprintln!(
            "{} | {} steps {:.0} s",
            sim_harness::experiment::ladder::ladder_line(&format!("online {variant}"), &o),
            o.steps,
            o.train_s
        );
        // L2 per view against how far its Sun and viewpoint are from every trained frame's.
        let trained = sim_harness::experiment::runner::trained_frames(&scene, &preset);
        let suns: Vec<glam::DVec3> = trained.iter().map(|v| v.sun_dir_target).collect();
        let dirs: Vec<glam::DVec3> = trained.iter().map(|v| v.view_dir_target()).collect();
        // Sun and viewpoint of one frame together: the appearance depends on the pair, and
        // the frame nearest in Sun is rarely the one nearest in viewpoint.
        // The trained frame nearest to `view` in Sun and viewpoint together (the larger of
        // the two angles), and that angle in degrees.
        let nearest_joint = |view: &sim_harness::experiment::data::ViewData| {
            trained
                .iter()
                .zip(suns.iter().zip(&dirs))
                .map(|(t, (s, d))| {
                    let sun_deg = s.angle_between(view.sun_dir_target).to_degrees();
                    (
                        *t,
                        sun_deg.max(d.angle_between(view.view_dir_target()).to_degrees()),
                    )
                })
                .fold(
                    None,
                    |best: Option<(&sim_harness::experiment::data::ViewData, f64)>, c| match best {
                        Some(b) if b.1 <= c.1 => Some(b),
                        _ => Some(c),
                    },
                )
        };
        let joint_deg = |view: &sim_harness::experiment::data::ViewData| {
            nearest_joint(view).map_or(f64::INFINITY, |(_, deg)| deg)
        };
        for (view, (m, b)) in scene
            .eval
            .iter()
            .zip(o.eval.per_view.iter().zip(&o.black_eval.per_view))
        {
            let joint = joint_deg(view);
            eprintln!(
                "eval view {:3}: masked {:6.2} dB (black {:6.2}); nearest trained Sun {:5.1} deg, view {:5.1} deg, both in one frame {:5.1} deg",
                view.index,
                m.masked_psnr_db,
                b.masked_psnr_db,
                nearest_angle_deg(view.sun_dir_target, &suns),
                nearest_angle_deg(view.view_dir_target(), &dirs),
                joint,
            );
        }
        // L1 per frame against the same distance: whether the held-out frames far from any
        // trained (Sun, view) pair are the ones the model misses.
        let held = sim_harness::experiment::runner::held_out_frames(&scene, &preset);
        let mut by_distance: Vec<(f64, f64, f64)> = held
            .iter()
            .zip(o.held_out.per_view.iter().zip(&o.black_held_out.per_view))
            .map(|(view, (m, b))| (joint_deg(view), m.masked_psnr_db, b.masked_psnr_db))
            .collect();
        // The trained frames just before and after each held-out one, scored by the same
        // final model: low there too means forgotten, high there means a new view missed.
        let model = &trainer.trainer().model;
        let mut neighbour_sum = (0.0f64, 0usize);
        for (view, (joint, m, b)) in held.iter().zip(&by_distance) {
            let neighbours: Vec<&sim_harness::experiment::data::ViewData> = trained
                .iter()
                .copied()
                .filter(|t| t.index + 1 == view.index || t.index == view.index + 1)
                .collect();
            let (n, _) = evaluate_views(model, &scene.intrinsics, &neighbours, 0)?;
            if !neighbours.is_empty() {
                neighbour_sum.0 += n.masked_psnr_db;
                neighbour_sum.1 += 1;
            }
            eprintln!(
                "held-out frame {:3}: masked {m:6.2} dB (black {b:6.2}); its trained neighbours {:6.2} dB; nearest trained Sun and view in one frame {joint:5.1} deg",
                view.index, n.masked_psnr_db
            );
        }
        eprintln!(
            "held-out frames' trained neighbours, mean masked {:.2} dB over {} frames (how well the final model holds the frames the held-out ones sit between)",
            neighbour_sum.0 / neighbour_sum.1.max(1) as f64,
            neighbour_sum.1
        );
        if let Some(png) = arg("--png") {
            // Per held-out frame: the trained frame nearest in Sun and view together, the
            // held-out truth, the final model's render of it.
            let model = &trainer.trainer().model;
            let mut rows = Vec::new();
            for view in &held {
                let render = model
                    .render(&camera_of(&scene.intrinsics, view), sun_of(view))?
                    .image;
                rows.push(vec![
                    nearest_joint(view)
                        .map_or_else(|| vec![0; view.rgb8.len()], |(t, _)| t.rgb8.clone()),
                    view.rgb8.clone(),
                    sim_harness::experiment::evaluate::to_rgb8(&render),
                ]);
            }
            write_panels(
                &png,
                scene.intrinsics.width as usize,
                scene.intrinsics.height as usize,
                &rows,
            )?;
            eprintln!("wrote {png}: per held-out frame, nearest trained frame | truth | render");
        }
        by_distance.sort_by(|a, b| a.0.total_cmp(&b.0));
        let half = by_distance.len() / 2;
        let margin = |part: &[(f64, f64, f64)]| {
            part.iter().map(|(_, m, b)| m - b).sum::<f64>() / part.len().max(1) as f64
        };
        let deg = |part: &[(f64, f64, f64)]| {
            part.iter().map(|(d, _, _)| d).sum::<f64>() / part.len().max(1) as f64
        };
        eprintln!(
            "held-out frames nearer than the median (mean {:.1} deg): {:+.2} dB over black; farther (mean {:.1} deg): {:+.2} dB",
            deg(&by_distance[..half]),
            margin(&by_distance[..half]),
            deg(&by_distance[half..]),
            margin(&by_distance[half..])
        );
        // L1 and the L0 window split by the material each pixel's centre ray hits.
        let rt = sim_harness::raytrace::Scene::new(sim_harness::dataset::load_target(&scenario)?);
        let window = sim_harness::experiment::runner::window_frames(&scene, &trainer);
        let trained = sim_harness::experiment::runner::trained_frames(&scene, &preset);
        let seen = sim_harness::experiment::evaluate::seen_views(&trained, 20);
        for (rung, views) in [
            ("L1 held-out", &held),
            ("L0 window", &window),
            ("L0 seen", &seen),
        ] {
            let model = &trainer.trainer().model;
            print_material_split(rung, &rt, model, &scene.intrinsics, views)?;
        }
        let model = &trainer.trainer().model;
        for move_view in [false, true] {
            print_sweep(
                move_view,
                "L0 window",
                &scenario,
                &rt,
                model,
                &scene.intrinsics,
                &window,
            )?;
        }
        return Ok(());
    }
    let mut online = gs_online::online::OnlineTrainer::new(
        online_config(&preset, variant)?,
        &try_initialisation(&scene, &preset)?,
        scene_box(&scene)?,
    )?;
    let lit: Vec<usize> = (0..scene.frames.len())
        .filter(|&i| !scene.frames[i].eclipse)
        .collect();
    let views: Vec<_> = lit.iter().map(|&i| &scene.frames[i]).collect();
    let black = black_baseline(&scene.intrinsics, views.iter().copied())?;
    eprintln!(
        "{} lit frames, black masked {:.2} dB full {:.2} dB",
        lit.len(),
        black.masked_psnr_db,
        black.psnr_db
    );
    let images: Vec<Vec<f32>> = views.iter().map(|v| v.rgb_f32()).collect();
    let masks: Vec<Vec<f32>> = views.iter().map(|v| v.mask_f32()).collect();
    let densify_every = arg("--densify-every").map_or(Ok(100u64), |s| s.parse())?;
    let mut rng = 12345u64;
    let t = online.trainer_mut();
    for step in 0..steps {
        rng = rng
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        let k = ((rng >> 33) as usize) % views.len();
        let obs = Observation {
            camera: camera_of(&scene.intrinsics, views[k]),
            sun_dir: sun_of(views[k]),
            image: &images[k],
            mask: masked.then_some(&masks[k][..]),
        };
        let progress = step as f32 / steps as f32;
        t.step(&obs, progress)?;
        if (step + 1) % densify_every == 0 && step < steps / 2 {
            let r = t.densify_and_prune()?;
            let _ = r;
        }
        if (step + 1) % (steps / 6).max(1) == 0 {
            let (s, _) = evaluate_views(&t.model, &scene.intrinsics, &views, 0)?;
            eprintln!(
                "step {}: seen masked {:.2} dB full {:.2} dB, {} Gaussians",
                step + 1,
                s.masked_psnr_db,
                s.psnr_db,
                t.model.len()
            );
        }
    }
    let eval_views: Vec<_> = scene.eval.iter().collect();
    let (e, _) = evaluate_views(&t.model, &scene.intrinsics, &eval_views, 0)?;
    let black_eval = black_baseline(&scene.intrinsics, eval_views.iter().copied())?;
    eprintln!(
        "offline reference: evaluation views masked {:.2} dB (black {:.2}), full {:.2} dB (black {:.2})",
        e.masked_psnr_db, black_eval.masked_psnr_db, e.psnr_db, black_eval.psnr_db
    );
    let use_eval = arg("--png-eval").is_some_and(|s| s == "1");
    let views = if use_eval { eval_views } else { views };
    if let Some(png) = arg("--png") {
        let (w, h) = (
            scene.intrinsics.width as usize,
            scene.intrinsics.height as usize,
        );
        let mut rows = Vec::new();
        for k in (0..4).map(|i| i * views.len() / 4) {
            let render = t
                .model
                .render(&camera_of(&scene.intrinsics, views[k]), sun_of(views[k]))?
                .image;
            let render8 = sim_harness::experiment::evaluate::to_rgb8(&render);
            rows.push(vec![views[k].rgb8.clone(), render8]);
        }
        write_panels(&png, w, h, &rows)?;
    }
    Ok(())
}

//! The ablation's figures: `init.png` ([`plot`]: masked PSNR bars per target, Gaussian count over
//! rounds) and `hull.png` ([`write_hull_figure`]: each target's surface samples beside its
//! hull).
//!
//! Invariant: figures are drawn from the runs and scenes handed in; nothing is measured
//! here.

use super::{
    far_distance_m, hull_initialisation, parse_init_variant, HullReport, HullVariant,
    InitAblationJob, InitRun, GREY,
};
use crate::dataset::files;
use crate::dataset::plots::{Canvas, Rgb};
use crate::experiment::data::{load_or_render_scene, SceneData};
use crate::experiment::figure::draw_text;
use crate::experiment::preset::{InitKind, Preset};
use crate::experiment::table::target_label;
use crate::experiment::ExperimentError;
use glam::Vec3;
use gs_online::online::Initialisation;

const PALETTE: [Rgb; 4] = [[30, 80, 200], [210, 40, 40], [30, 150, 60], [150, 90, 20]];
const AXIS: Rgb = [60, 60, 60];
const PANEL_W: f64 = 360.0;
const PANEL_H: f64 = 260.0;
/// Space between panels: the next panel's axis labels sit left of its axis.
const PANEL_GAP: f64 = 60.0;
const GREY_NOTE: &str = "GREY LINE: ALL-BLACK IMAGE";

/// init.png: top, evaluation masked PSNR (the target's own pixels) per target as grouped
/// bars (one colour per initialisation, the all-black image's masked PSNR as a grey line); below, one panel per target
/// with the Gaussian count over rounds.
pub fn plot(runs: &[InitRun], inits: &[String]) -> Canvas {
    let mut targets: Vec<String> = Vec::new();
    for r in runs {
        if !targets.contains(&r.run.target) {
            targets.push(r.run.target.clone());
        }
    }
    let columns = targets.len().max(1) as f64;
    // Wide enough for the legend too (8 pixels a character at text scale 2).
    let legend_w: usize =
        40 + inits.iter().map(|n| 52 + 8 * n.len()).sum::<usize>() + 8 * GREY_NOTE.len() + 20;
    let width = (40.0 + columns * (PANEL_W + PANEL_GAP)).max(legend_w as f64) as u32;
    let height = (70.0 + 2.0 * (PANEL_H + 60.0)) as u32;
    let mut canvas = Canvas::new(width, height, [255, 255, 255]);
    // Legend.
    let mut x = 20i64;
    for (i, name) in inits.iter().enumerate() {
        let colour = PALETTE[i % PALETTE.len()];
        canvas.fill_rect(x, 14, 16, 10, colour);
        draw_text(&mut canvas, x + 22, 14, &name.to_uppercase(), 2, AXIS);
        x += 22 + (name.len() as i64 * 8) + 30;
    }
    draw_text(&mut canvas, x + 10, 14, GREY_NOTE, 2, [150, 150, 150]);
    for (t, target) in targets.iter().enumerate() {
        let left = 50.0 + t as f64 * (PANEL_W + PANEL_GAP);
        let top = 60.0;
        let of_target: Vec<&InitRun> = runs.iter().filter(|r| &r.run.target == target).collect();
        bar_panel(&mut canvas, left, top, target, &of_target, inits);
        gaussian_panel(
            &mut canvas,
            left,
            top + PANEL_H + 60.0,
            target,
            &of_target,
            inits,
        );
    }
    canvas
}

fn colour_of(init: &str, inits: &[String]) -> Rgb {
    let i = inits.iter().position(|n| n == init).unwrap_or(0);
    PALETTE[i % PALETTE.len()]
}

fn frame(canvas: &mut Canvas, left: f64, top: f64, title: &str) {
    canvas.line((left, top), (left, top + PANEL_H), 1, AXIS);
    canvas.line(
        (left, top + PANEL_H),
        (left + PANEL_W, top + PANEL_H),
        1,
        AXIS,
    );
    draw_text(canvas, left as i64, top as i64 - 20, title, 2, AXIS);
}

fn bar_panel(
    canvas: &mut Canvas,
    left: f64,
    top: f64,
    target: &str,
    runs: &[&InitRun],
    inits: &[String],
) {
    frame(
        canvas,
        left,
        top,
        &format!("{} MASKED PSNR DB", target_label(target).to_uppercase()),
    );
    let values: Vec<f64> = runs
        .iter()
        .map(|r| r.run.eval.masked_psnr_db)
        .chain(runs.first().map(|r| r.run.black_eval.masked_psnr_db))
        .filter(|v| v.is_finite())
        .collect();
    if values.is_empty() {
        return;
    }
    // Bars start 2 dB below the lowest value so differences of tenths stay visible.
    let lo = (values.iter().copied().fold(f64::INFINITY, f64::min) - 2.0).floor();
    let hi = values.iter().copied().fold(f64::NEG_INFINITY, f64::max) + 0.5;
    let y_of = |v: f64| top + PANEL_H * (1.0 - (v - lo) / (hi - lo));
    draw_text(
        canvas,
        left as i64 - 44,
        top as i64 + PANEL_H as i64 - 10,
        &format!("{lo:.0}"),
        2,
        AXIS,
    );
    let slot = PANEL_W / runs.len().max(1) as f64;
    for (i, r) in runs.iter().enumerate() {
        let v = r.run.eval.masked_psnr_db;
        if !v.is_finite() {
            continue;
        }
        let x0 = left + i as f64 * slot + 0.15 * slot;
        let y0 = y_of(v);
        canvas.fill_rect(
            x0 as i64,
            y0 as i64,
            (0.7 * slot) as i64,
            (top + PANEL_H - y0) as i64,
            colour_of(&r.init, inits),
        );
        draw_text(
            canvas,
            x0 as i64,
            y0 as i64 - 14,
            &format!("{v:.2}"),
            2,
            AXIS,
        );
    }
    if let Some(black) = runs.first().map(|r| r.run.black_eval.masked_psnr_db) {
        if black.is_finite() {
            let y = y_of(black);
            canvas.line((left, y), (left + PANEL_W, y), 2, [150, 150, 150]);
        }
    }
}

fn gaussian_panel(
    canvas: &mut Canvas,
    left: f64,
    top: f64,
    target: &str,
    runs: &[&InitRun],
    inits: &[String],
) {
    frame(
        canvas,
        left,
        top,
        &format!(
            "{} GAUSSIANS PER ROUND",
            target_label(target).to_uppercase()
        ),
    );
    let max_round = runs
        .iter()
        .flat_map(|r| r.run.curve.iter().map(|p| p.round))
        .max()
        .unwrap_or(1)
        .max(1) as f64;
    let max_g = runs
        .iter()
        .flat_map(|r| r.run.curve.iter().map(|p| p.gaussians))
        .chain(runs.iter().map(|r| r.initial_gaussians))
        .max()
        .unwrap_or(1)
        .max(1) as f64;
    let x_of = |round: f64| left + PANEL_W * round / max_round;
    let y_of = |g: f64| top + PANEL_H * (1.0 - g / max_g);
    draw_text(
        canvas,
        left as i64 - 44,
        top as i64,
        &format!("{}", max_g as u64),
        2,
        AXIS,
    );
    draw_text(
        canvas,
        left as i64 - 14,
        (top + PANEL_H) as i64 - 10,
        "0",
        2,
        AXIS,
    );
    draw_text(
        canvas,
        (left + PANEL_W) as i64 - 30,
        (top + PANEL_H) as i64 + 8,
        &format!("{}", max_round as u64),
        2,
        AXIS,
    );
    draw_text(
        canvas,
        left as i64,
        (top + PANEL_H) as i64 + 8,
        "ROUND",
        2,
        AXIS,
    );
    for r in runs {
        let colour = colour_of(&r.init, inits);
        let mut previous = (0.0, r.initial_gaussians as f64);
        for p in &r.run.curve {
            let next = (p.round as f64, p.gaussians as f64);
            canvas.line(
                (x_of(previous.0), y_of(previous.1)),
                (x_of(next.0), y_of(next.1)),
                2,
                colour,
            );
            previous = next;
        }
    }
}

/// Points of one cloud with their sRGB colours in [0, 1].
pub struct Cloud<'a> {
    pub label: String,
    pub points: &'a [Vec3],
    pub colours: &'a [[f32; 3]],
}

const CLOUD_PANEL_PX: f64 = 220.0;
const CLOUD_BACKGROUND: Rgb = [35, 35, 45];

/// hull.png: one row per target, the clouds side by side, each seen along the body z axis
/// (x right, y up) and along the body y axis (x right, z up), at one scale per row so the
/// clouds compare directly. Points are 2x2 pixel squares in their colours.
pub fn cloud_figure(rows: &[(String, Vec<Cloud>)]) -> Canvas {
    let columns = rows.iter().map(|(_, c)| 2 * c.len()).max().unwrap_or(1) as f64;
    let width = (20.0 + columns * (CLOUD_PANEL_PX + 10.0)) as u32;
    let row_h = CLOUD_PANEL_PX + 40.0;
    let height = (20.0 + rows.len() as f64 * row_h) as u32;
    let mut canvas = Canvas::new(width, height, [255, 255, 255]);
    for (r, (target, clouds)) in rows.iter().enumerate() {
        let top = 30.0 + r as f64 * row_h;
        let half_extent = clouds
            .iter()
            .flat_map(|c| c.points.iter())
            .map(|p| p.abs().max_element() as f64)
            .filter(|v| v.is_finite())
            .fold(1e-3f64, f64::max);
        let scale = 0.5 * (CLOUD_PANEL_PX - 10.0) / half_extent;
        for (c, cloud) in clouds.iter().enumerate() {
            for (view, (axis_u, axis_v, name)) in [(0usize, 1usize, "XY"), (0, 2, "XZ")]
                .into_iter()
                .enumerate()
            {
                let left = 10.0 + (2 * c + view) as f64 * (CLOUD_PANEL_PX + 10.0);
                let label = format!(
                    "{} {} {}",
                    target_label(target).to_uppercase(),
                    cloud.label,
                    name
                );
                draw_text(&mut canvas, left as i64, top as i64 - 18, &label, 2, AXIS);
                canvas.fill_rect(
                    left as i64,
                    top as i64,
                    CLOUD_PANEL_PX as i64,
                    CLOUD_PANEL_PX as i64,
                    CLOUD_BACKGROUND,
                );
                let centre = (left + 0.5 * CLOUD_PANEL_PX, top + 0.5 * CLOUD_PANEL_PX);
                for (p, colour) in cloud.points.iter().zip(cloud.colours) {
                    let x = centre.0 + scale * p[axis_u] as f64;
                    let y = centre.1 - scale * p[axis_v] as f64;
                    if !(x.is_finite() && y.is_finite()) {
                        continue;
                    }
                    let rgb = colour.map(|v| (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8);
                    canvas.fill_rect(x as i64, y as i64, 2, 2, rgb);
                }
            }
        }
    }
    canvas
}

/// The surface samples (material colours) and the hull (its initial colours) of a scene.
struct FigureRow {
    name: String,
    surface: Vec<Vec3>,
    surface_colours: Vec<[f32; 3]>,
    hull: Vec<Vec3>,
    hull_colours: Vec<[f32; 3]>,
}

fn hull_figure_row(scene: &SceneData, preset: &Preset) -> Result<FigureRow, ExperimentError> {
    let n = (preset.init_points as usize).min(scene.surface.len());
    let surface = scene.surface[..n].iter().map(|s| s.position_m).collect();
    let surface_colours = scene.surface[..n]
        .iter()
        .map(|s| {
            s.albedo_rgb
                .map(|c| crate::raytrace::linear_to_srgb8(c) as f32 / 255.0)
        })
        .collect();
    let (init, _) = hull_initialisation(scene, preset)?;
    let Initialisation::SurfaceSamples {
        points, colours, ..
    } = init
    else {
        return Err(ExperimentError::Invalid(
            "a hull initialises from points".into(),
        ));
    };
    let hull_colours = colours.unwrap_or_else(|| vec![GREY; points.len()]);
    Ok(FigureRow {
        name: scene.name.clone(),
        surface,
        surface_colours,
        hull: points,
        hull_colours,
    })
}

/// Writes `OUT/hull.png` (true surface samples beside the hull of each scenario) without
/// training; returns the hull reports. The hull is drawn as the first hull start in
/// `job.inits` makes it (surface or volume points; plain `hull` when there is none).
pub fn write_hull_figure(
    job: &InitAblationJob,
    progress: &mut dyn FnMut(&str),
) -> Result<Vec<(String, HullReport)>, ExperimentError> {
    let out = &job.out_dir;
    std::fs::create_dir_all(out).map_err(|e| ExperimentError::io(out, e))?;
    let mut variant = HullVariant::default();
    for name in &job.inits {
        if let (InitKind::Hull, v) = parse_init_variant(name)? {
            variant = v;
            break;
        }
    }
    let preset = Preset {
        init: InitKind::Hull,
        hull_grey_colours: job.preset.hull_grey_colours || variant.grey,
        hull_volume: job.preset.hull_volume || variant.volume,
        hull_photo: job.preset.hull_photo || variant.photo,
        hull_silhouette: job.preset.hull_silhouette || variant.silhouette,
        ..job.preset.clone()
    };
    let mut data = Vec::new();
    let mut reports = Vec::new();
    for scenario in &job.scenarios {
        let scenario = preset.apply(scenario)?;
        let scene = load_or_render_scene(
            &scenario,
            preset.init_points as usize,
            &out.join("cache"),
            progress,
        )?;
        let (_, report) = hull_initialisation(&scene, &preset)?;
        progress(&format!(
            "{}: hull from frames {:?}, {} points ({} occupied, {} surface voxels of {:.3} m), mean {:.3} m from the true surface, {:.1} % farther than {:.2} m; {:.1} % of the surface samples that far from every point",
            scene.name,
            report.frames,
            report.points,
            report.occupied_voxels,
            report.surface_voxels,
            report.voxel_m,
            report.mean_distance_to_surface_m,
            100.0 * report.far_fraction,
            far_distance_m(&scene, &preset),
            100.0 * report.surface_uncovered_fraction
        ));
        if report.photo_candidates > 0 {
            progress(&format!(
                "{}: photo-consistency: {} candidates, {} off the silhouette, {} seen by fewer than two views, median colour spread {:.4}",
                scene.name,
                report.photo_candidates,
                report.photo_off_silhouette,
                report.photo_unscored,
                report.photo_median_spread
            ));
        }
        reports.push((scene.name.clone(), report));
        data.push(hull_figure_row(&scene, &preset)?);
    }
    let rows: Vec<(String, Vec<Cloud>)> = data
        .iter()
        .map(|row| {
            (
                row.name.clone(),
                vec![
                    Cloud {
                        label: "MODEL".into(),
                        points: &row.surface,
                        colours: &row.surface_colours,
                    },
                    Cloud {
                        label: "HULL".into(),
                        points: &row.hull,
                        colours: &row.hull_colours,
                    },
                ],
            )
        })
        .collect();
    let canvas = cloud_figure(&rows);
    files::write_png_rgb(
        &out.join("hull.png"),
        canvas.width,
        canvas.height,
        &canvas.rgb8,
    )?;
    Ok(reports)
}

//! The sweep's figure `pareto.png` ([`pareto_plot`]) and the shared x-y panel
//! ([`draw_xy_panel`]: framed axes, linear or log ticks, series of points and lines, a
//! legend) that the skips table and the window ablation draw with too.
//!
//! Invariant: only draws what it is handed; nothing is measured here.

use super::SweepRow;
use crate::dataset::files;
use crate::dataset::plots::{Canvas, Rgb};
use crate::experiment::figure::{draw_text, text_width};
use crate::experiment::ExperimentError;
use std::path::Path;

pub(crate) fn write_canvas(path: &Path, canvas: &Canvas) -> Result<(), ExperimentError> {
    files::write_png_rgb(path, canvas.width, canvas.height, &canvas.rgb8)?;
    Ok(())
}

/// One series of a plot.
#[derive(Clone, Debug)]
pub struct PlotSeries {
    pub name: String,
    pub color: Rgb,
    pub points: Vec<(f64, f64)>,
    /// Join consecutive points with a line.
    pub line: bool,
}

/// Axis ticks: 1-2-5 steps (log: 1, 2, 5 times powers of ten) within [lo, hi].
pub(super) fn ticks(lo: f64, hi: f64, log: bool) -> Vec<f64> {
    let mut out = Vec::new();
    if !(lo.is_finite() && hi.is_finite() && hi > lo) {
        return out;
    }
    if log {
        let mut decade = 10f64.powf(lo.log10().floor());
        while decade <= hi {
            for m in [1.0, 2.0, 5.0] {
                let v = m * decade;
                if v >= lo && v <= hi {
                    out.push(v);
                }
            }
            decade *= 10.0;
        }
        return out;
    }
    let raw = (hi - lo) / 5.0;
    let mag = 10f64.powf(raw.log10().floor());
    let step = [1.0, 2.0, 5.0, 10.0]
        .iter()
        .map(|m| m * mag)
        .find(|s| *s >= raw)
        .unwrap_or(10.0 * mag);
    let mut v = (lo / step).ceil() * step;
    while v <= hi + 1e-9 * step {
        out.push(v);
        v += step;
    }
    out
}

fn tick_label(v: f64) -> String {
    if v.abs() >= 100.0 || v.fract() == 0.0 {
        format!("{v:.0}")
    } else if (10.0 * v).fract().abs() < 1e-9 {
        format!("{v:.1}")
    } else {
        format!("{v:.2}")
    }
}

/// Draws a framed x-y panel into `canvas` at (x0, y0) of `w` x `h` pixels: axes with tick
/// labels, each series' points (squares) and lines, a legend, and text labels at data points.
pub fn draw_xy_panel(
    canvas: &mut Canvas,
    (x0, y0, w, h): (i64, i64, i64, i64),
    title: &str,
    x_label: &str,
    y_label: &str,
    log_x: bool,
    series: &[PlotSeries],
    labels: &[(f64, f64, String, Rgb)],
) {
    let axis: Rgb = [60, 60, 60];
    let grid: Rgb = [225, 225, 225];
    let (left, right, top, bottom) = (70i64, 20i64, 40i64, 44i64);
    let (px0, px1, py0, py1) = (x0 + left, x0 + w - right, y0 + top, y0 + h - bottom);
    let all: Vec<(f64, f64)> = series
        .iter()
        .flat_map(|s| s.points.iter().copied())
        .filter(|p| p.0.is_finite() && p.1.is_finite() && (!log_x || p.0 > 0.0))
        .collect();
    draw_text(canvas, x0 + 8, y0 + 8, title, 2, axis);
    if all.is_empty() {
        return;
    }
    let fx = |v: f64| if log_x { v.log10() } else { v };
    let (mut xlo, mut xhi) = all.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |a, p| {
        (a.0.min(fx(p.0)), a.1.max(fx(p.0)))
    });
    let (mut ylo, mut yhi) = all.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |a, p| {
        (a.0.min(p.1), a.1.max(p.1))
    });
    let pad = |lo: &mut f64, hi: &mut f64| {
        let span = (*hi - *lo).max(1e-6);
        *lo -= 0.08 * span;
        *hi += 0.08 * span;
    };
    pad(&mut xlo, &mut xhi);
    pad(&mut ylo, &mut yhi);
    let sx = |v: f64| px0 as f64 + (px1 - px0) as f64 * (fx(v) - xlo) / (xhi - xlo);
    let sy = |v: f64| py1 as f64 - (py1 - py0) as f64 * (v - ylo) / (yhi - ylo);
    let (data_xlo, data_xhi) = if log_x {
        (10f64.powf(xlo), 10f64.powf(xhi))
    } else {
        (xlo, xhi)
    };
    for t in ticks(data_xlo, data_xhi, log_x) {
        let x = sx(t);
        canvas.line((x, py0 as f64), (x, py1 as f64), 1, grid);
        let label = tick_label(t);
        draw_text(
            canvas,
            x as i64 - text_width(&label, 2) / 2,
            py1 + 6,
            &label,
            2,
            axis,
        );
    }
    for t in ticks(ylo, yhi, false) {
        let y = sy(t);
        canvas.line((px0 as f64, y), (px1 as f64, y), 1, grid);
        let label = tick_label(t);
        draw_text(
            canvas,
            px0 - 6 - text_width(&label, 2),
            y as i64 - 5,
            &label,
            2,
            axis,
        );
    }
    canvas.rect_outline(px0, py0, px1 - px0 + 1, py1 - py0 + 1, 1, axis);
    draw_text(
        canvas,
        (px0 + px1) / 2 - text_width(x_label, 2) / 2,
        py1 + 24,
        x_label,
        2,
        axis,
    );
    draw_text(canvas, x0 + 8, y0 + 24, y_label, 2, axis);
    for s in series {
        let pts: Vec<(f64, f64)> = s
            .points
            .iter()
            .copied()
            .filter(|p| p.0.is_finite() && p.1.is_finite() && (!log_x || p.0 > 0.0))
            .collect();
        if s.line {
            for pair in pts.windows(2) {
                canvas.line(
                    (sx(pair[0].0), sy(pair[0].1)),
                    (sx(pair[1].0), sy(pair[1].1)),
                    2,
                    s.color,
                );
            }
        }
        for p in &pts {
            canvas.fill_rect(sx(p.0) as i64 - 3, sy(p.1) as i64 - 3, 7, 7, s.color);
        }
    }
    // Legend in the lower right corner (slow and poor: usually empty in these plots).
    let named = series.iter().filter(|s| !s.name.is_empty()).count() as i64;
    let mut ly = py1 - 6 - 16 * named;
    for s in series.iter().filter(|s| !s.name.is_empty()) {
        let lx = px1 - 10 - text_width(&s.name, 2) - 14;
        canvas.fill_rect(lx, ly, 10, 10, s.color);
        draw_text(canvas, lx + 14, ly, &s.name, 2, axis);
        ly += 16;
    }
    for (k, (x, y, text, color)) in labels.iter().enumerate() {
        if !(x.is_finite() && y.is_finite()) || (log_x && *x <= 0.0) {
            continue;
        }
        // Alternate above and below the point so neighbouring labels overlap less.
        let dy = if k % 2 == 0 { -16 } else { 8 };
        draw_text(
            canvas,
            sx(*x) as i64 + 6,
            sy(*y) as i64 + dy,
            text,
            2,
            *color,
        );
    }
}

/// Training CPU time against evaluation masked PSNR (the target's own pixels), every setting
/// a grey point, the front in red joined as a line and labelled with the settings' names, and
/// the all-black render's score as a black line (the floor every setting must clear).
pub fn pareto_plot(rows: &[SweepRow], front: &[bool], title: &str) -> Canvas {
    let mut canvas = Canvas::new(960, 600, [255, 255, 255]);
    let point = |r: &SweepRow| (r.train_cpu_s, r.masked_psnr_db);
    let mut on: Vec<(f64, f64, &str)> = rows
        .iter()
        .zip(front)
        .filter(|(_, f)| **f)
        .map(|(r, _)| (r.train_cpu_s, r.masked_psnr_db, r.setting.as_str()))
        .collect();
    on.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.total_cmp(&b.1)));
    let red: Rgb = [200, 30, 30];
    let grey: Rgb = [130, 130, 130];
    let (x_lo, x_hi) = rows
        .iter()
        .map(|r| r.train_cpu_s)
        .filter(|x| x.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), x| {
            (lo.min(x), hi.max(x))
        });
    let black_db = rows
        .iter()
        .filter_map(|r| r.ladder.eval.map(|e| e.black_masked_psnr_db))
        .find(|v| v.is_finite());
    let series = [
        PlotSeries {
            name: "ALL-BLACK RENDER".into(),
            color: [0, 0, 0],
            points: match black_db {
                Some(b) if x_lo <= x_hi => vec![(x_lo, b), (x_hi, b)],
                _ => Vec::new(),
            },
            line: true,
        },
        PlotSeries {
            name: "DOMINATED".into(),
            color: grey,
            points: rows
                .iter()
                .zip(front)
                .filter(|(_, f)| !**f)
                .map(|(r, _)| point(r))
                .collect(),
            line: false,
        },
        PlotSeries {
            name: "PARETO FRONT".into(),
            color: red,
            points: on.iter().map(|p| (p.0, p.1)).collect(),
            line: true,
        },
    ];
    let mut labels: Vec<(f64, f64, String, Rgb)> = on
        .iter()
        .map(|p| (p.0, p.1, p.2.to_uppercase(), red))
        .collect();
    labels.extend(rows.iter().zip(front).filter(|(_, f)| !**f).map(|(r, _)| {
        (
            r.train_cpu_s,
            r.masked_psnr_db,
            r.setting.to_uppercase(),
            grey,
        )
    }));
    draw_xy_panel(
        &mut canvas,
        (0, 0, 960, 600),
        title,
        "TRAINING CPU TIME S (LOG)",
        "EVAL MASKED PSNR DB",
        true,
        &series,
        &labels,
    );
    canvas
}

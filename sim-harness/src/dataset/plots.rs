//! Pictures for a person: the contact sheet (thumbnails across the sequence) and the trajectory
//! plot (relative orbit in three RTN projections, Sun direction in RTN over an eclipse-shaded
//! timeline, range over time), drawn with a tiny raster canvas and a 3x5 pixel font so no system
//! fonts or plotting crates are needed.
//!
//! Invariants: drawing clips to the canvas (never panics on out-of-range coordinates, skips
//! non-finite ones); output depends only on the inputs.

use glam::DVec3;

/// An RGB8 raster, row-major from the top-left.
pub struct Canvas {
    pub width: u32,
    pub height: u32,
    pub rgb8: Vec<u8>,
}

pub(crate) type Rgb = [u8; 3];
const WHITE: Rgb = [255, 255, 255];
const BLACK: Rgb = [0, 0, 0];
const GREY: Rgb = [190, 190, 190];
const BLUE: Rgb = [30, 80, 200];
const RED: Rgb = [210, 40, 40];
const GREEN: Rgb = [30, 150, 60];
const ECLIPSE: Rgb = [60, 60, 90];
const SUNLIT: Rgb = [255, 244, 200];

impl Canvas {
    pub fn new(width: u32, height: u32, background: Rgb) -> Canvas {
        let rgb8 = background.repeat(width as usize * height as usize);
        Canvas {
            width,
            height,
            rgb8,
        }
    }

    pub fn set(&mut self, x: i64, y: i64, color: Rgb) {
        if x < 0 || y < 0 || x >= self.width as i64 || y >= self.height as i64 {
            return;
        }
        let i = 3 * (y as usize * self.width as usize + x as usize);
        self.rgb8[i..i + 3].copy_from_slice(&color);
    }

    pub(crate) fn fill_rect(&mut self, x0: i64, y0: i64, w: i64, h: i64, color: Rgb) {
        for y in y0.max(0)..(y0 + h).min(self.height as i64) {
            for x in x0.max(0)..(x0 + w).min(self.width as i64) {
                self.set(x, y, color);
            }
        }
    }

    pub(crate) fn rect_outline(
        &mut self,
        x0: i64,
        y0: i64,
        w: i64,
        h: i64,
        thickness: i64,
        color: Rgb,
    ) {
        self.fill_rect(x0, y0, w, thickness, color);
        self.fill_rect(x0, y0 + h - thickness, w, thickness, color);
        self.fill_rect(x0, y0, thickness, h, color);
        self.fill_rect(x0 + w - thickness, y0, thickness, h, color);
    }

    /// A line with round-ish `width` pixels (Bresenham, each step stamped as a square).
    pub fn line(&mut self, (x0, y0): (f64, f64), (x1, y1): (f64, f64), width: i64, color: Rgb) {
        if ![x0, y0, x1, y1]
            .iter()
            .all(|v| v.is_finite() && v.abs() < 1e7)
        {
            return;
        }
        let (mut x, mut y) = (x0.round() as i64, y0.round() as i64);
        let (xe, ye) = (x1.round() as i64, y1.round() as i64);
        let dx = (xe - x).abs();
        let dy = -(ye - y).abs();
        let sx = if x < xe { 1 } else { -1 };
        let sy = if y < ye { 1 } else { -1 };
        let mut err = dx + dy;
        let half = (width - 1) / 2;
        loop {
            self.fill_rect(x - half, y - half, width, width, color);
            if x == xe && y == ye {
                break;
            }
            let e2 = 2 * err;
            if e2 >= dy {
                err += dy;
                x += sx;
            }
            if e2 <= dx {
                err += dx;
                y += sy;
            }
        }
    }

    /// Text in a 3x5 pixel font scaled by `scale`; unknown characters draw as blanks.
    pub fn text(&mut self, x: i64, y: i64, text: &str, scale: i64, color: Rgb) {
        for (k, ch) in text.chars().enumerate() {
            let rows = glyph(ch);
            for (row, bits) in rows.iter().enumerate() {
                for col in 0..3 {
                    if bits & (0b100 >> col) != 0 {
                        let px = x + (k as i64 * 4 + col) * scale;
                        self.fill_rect(px, y + row as i64 * scale, scale, scale, color);
                    }
                }
            }
        }
    }

    /// Copies an RGB8 image with its top-left corner at (x0, y0).
    pub(crate) fn blit(&mut self, x0: i64, y0: i64, width: u32, height: u32, rgb8: &[u8]) {
        for y in 0..height as i64 {
            for x in 0..width as i64 {
                let i = 3 * (y as usize * width as usize + x as usize);
                self.set(x0 + x, y0 + y, [rgb8[i], rgb8[i + 1], rgb8[i + 2]]);
            }
        }
    }
}

/// 3x5 glyphs, one row per entry, bit 2 = left column.
fn glyph(ch: char) -> [u8; 5] {
    match ch {
        '0' => [7, 5, 5, 5, 7],
        '1' => [2, 6, 2, 2, 7],
        '2' => [7, 1, 7, 4, 7],
        '3' => [7, 1, 7, 1, 7],
        '4' => [5, 5, 7, 1, 1],
        '5' => [7, 4, 7, 1, 7],
        '6' => [7, 4, 7, 5, 7],
        '7' => [7, 1, 1, 2, 2],
        '8' => [7, 5, 7, 5, 7],
        '9' => [7, 5, 7, 1, 7],
        '-' => [0, 0, 7, 0, 0],
        '+' => [0, 2, 7, 2, 0],
        '.' => [0, 0, 0, 0, 2],
        ':' => [0, 2, 0, 2, 0],
        '/' => [1, 1, 2, 4, 4],
        'R' | 'r' => [6, 5, 6, 5, 5],
        'T' | 't' => [7, 2, 2, 2, 2],
        'N' | 'n' => [6, 5, 5, 5, 5],
        'M' | 'm' => [5, 7, 7, 5, 5],
        'S' | 's' => [7, 4, 7, 1, 7],
        'E' | 'e' => [7, 4, 6, 4, 7],
        'U' | 'u' => [5, 5, 5, 5, 7],
        'A' | 'a' => [2, 5, 7, 5, 5],
        'G' | 'g' => [7, 4, 5, 5, 7],
        'I' | 'i' => [7, 2, 2, 2, 7],
        'L' | 'l' => [4, 4, 4, 4, 7],
        'C' | 'c' => [7, 4, 4, 4, 7],
        'P' | 'p' => [7, 5, 7, 4, 4],
        'O' | 'o' => [7, 5, 5, 5, 7],
        'H' | 'h' => [5, 5, 7, 5, 5],
        'D' | 'd' => [6, 5, 5, 5, 6],
        'K' | 'k' => [5, 5, 6, 5, 5],
        'F' | 'f' => [7, 4, 6, 4, 4],
        _ => [0; 5],
    }
}

/// Box-filter downscale of an RGB8 image by an integer factor (at least 1).
pub(crate) fn downscale_rgb(
    width: u32,
    height: u32,
    rgb8: &[u8],
    factor: u32,
) -> (u32, u32, Vec<u8>) {
    let factor = factor.max(1);
    let (w, h) = ((width / factor).max(1), (height / factor).max(1));
    let mut out = vec![0u8; 3 * w as usize * h as usize];
    for y in 0..h {
        for x in 0..w {
            let mut sum = [0u32; 3];
            let mut count = 0u32;
            for sy in y * factor..((y + 1) * factor).min(height) {
                for sx in x * factor..((x + 1) * factor).min(width) {
                    let i = 3 * (sy * width + sx) as usize;
                    for c in 0..3 {
                        sum[c] += rgb8[i + c] as u32;
                    }
                    count += 1;
                }
            }
            let o = 3 * (y * w + x) as usize;
            for c in 0..3 {
                out[o + c] = ((sum[c] + count / 2) / count.max(1)) as u8;
            }
        }
    }
    (w, h, out)
}

/// One thumbnail for the contact sheet.
pub(crate) struct Thumbnail {
    pub index: u32,
    pub eclipse: bool,
    pub width: u32,
    pub height: u32,
    pub rgb8: Vec<u8>,
}

/// Frame indices shown on the contact sheet: up to `max` spread evenly from first to last.
pub(crate) fn contact_sheet_indices(frame_count: u32, max: u32) -> Vec<u32> {
    if frame_count <= max {
        return (0..frame_count).collect();
    }
    (0..max)
        .map(|k| {
            ((k as u64 * (frame_count as u64 - 1) + (max as u64 - 1) / 2) / (max as u64 - 1)) as u32
        })
        .collect()
}

/// Thumbnails in a grid, each labelled with its frame index; eclipse frames framed in red.
pub(crate) fn contact_sheet(thumbnails: &[Thumbnail], columns: u32) -> Canvas {
    let columns = columns.max(1).min(thumbnails.len().max(1) as u32);
    let rows = (thumbnails.len() as u32).div_ceil(columns).max(1);
    let tw = thumbnails.iter().map(|t| t.width).max().unwrap_or(1);
    let th = thumbnails.iter().map(|t| t.height).max().unwrap_or(1);
    let (pad, label_h) = (6u32, 14u32);
    let cell_w = tw + pad;
    let cell_h = th + pad + label_h;
    let mut canvas = Canvas::new(columns * cell_w + pad, rows * cell_h + pad, [40, 40, 40]);
    for (k, t) in thumbnails.iter().enumerate() {
        let (col, row) = (k as u32 % columns, k as u32 / columns);
        let x0 = (pad + col * cell_w) as i64;
        let y0 = (pad + row * cell_h) as i64;
        canvas.text(
            x0,
            y0,
            &format!("{}", t.index),
            2,
            if t.eclipse { RED } else { WHITE },
        );
        let iy = y0 + label_h as i64;
        canvas.blit(x0, iy, t.width, t.height, &t.rgb8);
        let border = if t.eclipse { RED } else { [90, 90, 90] };
        canvas.rect_outline(
            x0 - 2,
            iy - 2,
            t.width as i64 + 4,
            t.height as i64 + 4,
            2,
            border,
        );
    }
    canvas
}

/// Per-frame values the trajectory plot needs.
pub(crate) struct TrajectorySample {
    pub time_s: f64,
    pub servicer_rtn_m: DVec3,
    pub sun_rtn: DVec3,
    pub sun_visible_fraction: f64,
    pub eclipse: bool,
}

/// A time series: its colour and the value it plots.
type Series<'a> = (Rgb, &'a dyn Fn(&TrajectorySample) -> f64);

fn nice_step(span: f64) -> f64 {
    let raw = span / 4.0;
    let magnitude = 10f64.powf(raw.log10().floor());
    [1.0, 2.0, 5.0, 10.0]
        .iter()
        .map(|m| m * magnitude)
        .find(|s| *s >= raw)
        .unwrap_or(10.0 * magnitude)
}

/// A square panel plotting coordinate `a` (horizontal) against `b` (vertical, up), equal scale.
fn projection_panel(
    canvas: &mut Canvas,
    origin: (i64, i64),
    size: i64,
    half_span_m: f64,
    (samples, outline_rtn_m): (&[TrajectorySample], &[DVec3]),
    axes: (usize, usize),
    labels: (&str, &str),
) {
    let (x0, y0) = origin;
    canvas.rect_outline(x0, y0, size, size, 1, BLACK);
    let scale = (size as f64 / 2.0 - 10.0) / half_span_m;
    let centre = (x0 as f64 + size as f64 / 2.0, y0 as f64 + size as f64 / 2.0);
    let to_px = |a: f64, b: f64| (centre.0 + a * scale, centre.1 - b * scale);
    // Grid lines at a round step, labelled on the right/bottom edges.
    let step = nice_step(2.0 * half_span_m);
    let mut k = -(half_span_m / step).floor();
    while k * step <= half_span_m {
        let v = k * step;
        let color = if k == 0.0 {
            [120, 120, 120]
        } else {
            [225, 225, 225]
        };
        canvas.line(to_px(v, -half_span_m), to_px(v, half_span_m), 1, color);
        canvas.line(to_px(-half_span_m, v), to_px(half_span_m, v), 1, color);
        if k != 0.0 {
            let (px, _) = to_px(v, 0.0);
            let label = format!("{v}");
            canvas.text(px as i64 - 8, y0 + size - 14, &label, 2, [90, 90, 90]);
            let (_, py) = to_px(0.0, v);
            canvas.text(x0 + 4, py as i64 - 4, &label, 2, [90, 90, 90]);
        }
        k += 1.0;
    }
    for pair in outline_rtn_m.windows(2) {
        let (a, b) = (pair[0].to_array(), pair[1].to_array());
        canvas.line(
            to_px(a[axes.0], a[axes.1]),
            to_px(b[axes.0], b[axes.1]),
            1,
            GREY,
        );
    }
    let coordinate = |s: &TrajectorySample, i: usize| s.servicer_rtn_m.to_array()[i];
    for pair in samples.windows(2) {
        let color = if pair[1].eclipse { [20, 20, 60] } else { BLUE };
        canvas.line(
            to_px(coordinate(&pair[0], axes.0), coordinate(&pair[0], axes.1)),
            to_px(coordinate(&pair[1], axes.0), coordinate(&pair[1], axes.1)),
            2,
            color,
        );
    }
    if let Some(first) = samples.first() {
        let (px, py) = to_px(coordinate(first, axes.0), coordinate(first, axes.1));
        canvas.fill_rect(px as i64 - 4, py as i64 - 4, 9, 9, GREEN);
    }
    let (tx, ty) = to_px(0.0, 0.0);
    canvas.fill_rect(tx as i64 - 4, ty as i64 - 4, 9, 9, RED);
    canvas.text(
        x0 + size - 60,
        y0 + size - 28,
        &format!("{} M", labels.0),
        2,
        BLACK,
    );
    canvas.text(x0 + 6, y0 + 6, &format!("{} M", labels.1), 2, BLACK);
}

/// Time series panel: eclipse-shaded background and one polyline per series, in [lo, hi].
fn timeline_panel(
    canvas: &mut Canvas,
    origin: (i64, i64),
    size: (i64, i64),
    samples: &[TrajectorySample],
    series: &[Series],
    (lo, hi): (f64, f64),
    title: &str,
) {
    let (x0, y0) = origin;
    let (w, h) = size;
    let t_end = samples.last().map_or(1.0, |s| s.time_s).max(1e-9);
    let to_x = |t: f64| x0 as f64 + 1.0 + t / t_end * (w as f64 - 2.0);
    let to_y = |v: f64| y0 as f64 + h as f64 - 2.0 - (v - lo) / (hi - lo) * (h as f64 - 4.0);
    for (k, s) in samples.iter().enumerate() {
        let next_t = samples.get(k + 1).map_or(t_end, |n| n.time_s);
        let xa = to_x(s.time_s) as i64;
        let xb = (to_x(next_t) as i64).max(xa + 1);
        let f = s.sun_visible_fraction.clamp(0.0, 1.0);
        let mix = |a: u8, b: u8| (a as f64 * f + b as f64 * (1.0 - f)).round() as u8;
        let color = if s.eclipse {
            ECLIPSE
        } else {
            [
                mix(SUNLIT[0], ECLIPSE[0]),
                mix(SUNLIT[1], ECLIPSE[1]),
                mix(SUNLIT[2], ECLIPSE[2]),
            ]
        };
        canvas.fill_rect(xa, y0, xb - xa, h, color);
    }
    if lo < 0.0 && hi > 0.0 {
        canvas.line(
            (x0 as f64, to_y(0.0)),
            ((x0 + w) as f64, to_y(0.0)),
            1,
            GREY,
        );
    }
    for (color, value) in series {
        for pair in samples.windows(2) {
            canvas.line(
                (to_x(pair[0].time_s), to_y(value(&pair[0]))),
                (to_x(pair[1].time_s), to_y(value(&pair[1]))),
                2,
                *color,
            );
        }
    }
    canvas.rect_outline(x0, y0, w, h, 1, BLACK);
    canvas.text(x0 + 6, y0 + 6, title, 2, BLACK);
}

/// The trajectory figure: R-T, N-R and T-N projections on top (target red, start green, eclipse
/// segments dark, one full orbit of the relative motion in grey), then the Sun direction's R (red), T (green), N (blue) components and the
/// range over time, on a background that is pale yellow in sunlight and dark blue in eclipse.
pub(crate) fn trajectory_plot(samples: &[TrajectorySample], outline_rtn_m: &[DVec3]) -> Canvas {
    let panel = 400i64;
    let pad = 20i64;
    let strip = 160i64;
    let width = 3 * panel + 4 * pad;
    let height = panel + 2 * strip + 4 * pad;
    let mut canvas = Canvas::new(width as u32, height as u32, WHITE);
    let half_span_m = samples
        .iter()
        .map(|s| s.servicer_rtn_m)
        .chain(outline_rtn_m.iter().copied())
        .map(|v| v.abs().max_element())
        .filter(|v| v.is_finite())
        .fold(1.0, f64::max)
        * 1.05;
    projection_panel(
        &mut canvas,
        (pad, pad),
        panel,
        half_span_m,
        (samples, outline_rtn_m),
        (1, 0),
        ("T", "R"),
    );
    projection_panel(
        &mut canvas,
        (2 * pad + panel, pad),
        panel,
        half_span_m,
        (samples, outline_rtn_m),
        (2, 0),
        ("N", "R"),
    );
    projection_panel(
        &mut canvas,
        (3 * pad + 2 * panel, pad),
        panel,
        half_span_m,
        (samples, outline_rtn_m),
        (1, 2),
        ("T", "N"),
    );
    let strip_w = width - 2 * pad;
    let sun_series: [Series; 3] = [
        (RED, &|s| s.sun_rtn.x),
        (GREEN, &|s| s.sun_rtn.y),
        (BLUE, &|s| s.sun_rtn.z),
    ];
    timeline_panel(
        &mut canvas,
        (pad, 2 * pad + panel),
        (strip_w, strip),
        samples,
        &sun_series,
        (-1.05, 1.05),
        "SUN R T N",
    );
    let max_range = samples
        .iter()
        .map(|s| s.servicer_rtn_m.length())
        .fold(1.0, f64::max)
        * 1.1;
    let range_series: [Series; 1] = [(BLACK, &|s| s.servicer_rtn_m.length())];
    timeline_panel(
        &mut canvas,
        (pad, 3 * pad + panel + strip),
        (strip_w, strip),
        samples,
        &range_series,
        (0.0, max_range),
        &format!("RANGE 0-{max_range:.0} M"),
    );
    let t_end = samples.last().map_or(0.0, |s| s.time_s);
    canvas.text(
        width - pad - 150,
        height - pad + 4,
        &format!("T 0-{t_end:.0} S"),
        2,
        BLACK,
    );
    canvas
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn contact_sheet_indices_span_the_sequence() {
        assert_eq!(contact_sheet_indices(5, 48), vec![0, 1, 2, 3, 4]);
        let idx = contact_sheet_indices(5764, 48);
        assert_eq!(idx.len(), 48);
        assert_eq!((idx[0], idx[47]), (0, 5763));
        assert!(idx.windows(2).all(|w| w[1] > w[0]));
    }

    #[test]
    fn lines_hit_their_endpoints_and_clip() {
        let mut c = Canvas::new(20, 10, BLACK);
        c.line((2.0, 3.0), (17.0, 8.0), 1, WHITE);
        let at = |c: &Canvas, x: usize, y: usize| c.rgb8[3 * (y * 20 + x)];
        assert_eq!(at(&c, 2, 3), 255);
        assert_eq!(at(&c, 17, 8), 255);
        c.line((-50.0, -50.0), (500.0, 5.0), 3, WHITE); // clipped, must not panic
        c.line((f64::NAN, 0.0), (1.0, 1.0), 1, WHITE);
    }

    #[test]
    fn downscale_averages_blocks() {
        let rgb = [0u8, 0, 0, 255, 255, 255, 0, 0, 0, 255, 255, 255];
        let (w, h, out) = downscale_rgb(2, 2, &rgb, 2);
        assert_eq!((w, h), (1, 1));
        assert_eq!(out, vec![128, 128, 128]);
    }
}

//! Comparison figures: a grid of equally sized RGB images (ground truth beside each
//! configuration's render), a label over every column and a caption (e.g. PSNR) under every
//! image, drawn on the dataset plots' canvas with its 3x5 font (plus the few glyphs it lacks).
//!
//! Invariants: every cell is the source image scaled up by the same integer factor (nearest
//! neighbour, no resampling blur); a missing image draws as a grey cell; output depends only
//! on the inputs.

use crate::dataset::plots::{Canvas, Rgb};

const BACKGROUND: Rgb = [255, 255, 255];
const TEXT: Rgb = [20, 20, 20];
const MISSING: Rgb = [128, 128, 128];
const GAP_PX: u32 = 6;
const TEXT_SCALE: i64 = 2;
const LINE_PX: u32 = 5 * TEXT_SCALE as u32 + 6;

/// Glyphs the plots font lacks (bit 2 = left column).
fn extra_glyph(ch: char) -> Option<[u8; 5]> {
    Some(match ch.to_ascii_uppercase() {
        'B' => [6, 5, 6, 5, 6],
        'W' => [5, 5, 7, 7, 5],
        'V' => [5, 5, 5, 5, 2],
        'Y' => [5, 5, 2, 2, 2],
        'X' => [5, 5, 2, 5, 5],
        'Z' => [7, 1, 2, 4, 7],
        'J' => [1, 1, 1, 5, 7],
        'Q' => [7, 5, 5, 7, 1],
        '(' => [1, 2, 2, 2, 1],
        ')' => [4, 2, 2, 2, 4],
        '=' => [0, 7, 0, 7, 0],
        '_' => [0, 0, 0, 0, 7],
        _ => return None,
    })
}

/// Text with the plots font, filling in the glyphs it lacks.
pub(crate) fn draw_text(canvas: &mut Canvas, x: i64, y: i64, text: &str, scale: i64, color: Rgb) {
    for (k, ch) in text.chars().enumerate() {
        let cx = x + k as i64 * 4 * scale;
        match extra_glyph(ch) {
            Some(rows) => {
                for (row, bits) in rows.iter().enumerate() {
                    for col in 0..3 {
                        if bits & (0b100 >> col) != 0 {
                            canvas.fill_rect(
                                cx + col * scale,
                                y + row as i64 * scale,
                                scale,
                                scale,
                                color,
                            );
                        }
                    }
                }
            }
            None => canvas.text(cx, y, &ch.to_string(), scale, color),
        }
    }
}

/// Width in pixels of `text` drawn at `scale`.
pub(crate) fn text_width(text: &str, scale: i64) -> i64 {
    (text.chars().count() as i64 * 4 - 1).max(0) * scale
}

/// Nearest-neighbour integer upscale of an RGB8 image.
pub fn upscale_rgb(width: u32, height: u32, rgb8: &[u8], factor: u32) -> Vec<u8> {
    let f = factor.max(1);
    let (w, h) = (width * f, height * f);
    let mut out = vec![0u8; 3 * w as usize * h as usize];
    for y in 0..h {
        for x in 0..w {
            let s = 3 * ((y / f) * width + x / f) as usize;
            let o = 3 * (y * w + x) as usize;
            out[o..o + 3].copy_from_slice(&rgb8[s..s + 3]);
        }
    }
    out
}

/// One cell of the grid.
#[derive(Clone, Debug, Default)]
pub(crate) struct Cell {
    /// width * height * 3 sRGB bytes, or None for a missing image.
    pub rgb8: Option<Vec<u8>>,
    /// Text under the image (may be empty).
    pub caption: String,
}

/// A grid figure: `rows[r][c]` is the image of row r, column c; all images are
/// `width x height`. Column labels go on top, an optional label at the left of each row.
pub(crate) fn grid_figure(
    width: u32,
    height: u32,
    column_labels: &[String],
    row_labels: &[String],
    rows: &[Vec<Cell>],
    min_cell_width_px: u32,
) -> Canvas {
    let factor = min_cell_width_px.div_ceil(width.max(1)).max(1);
    let (cell_w, cell_h) = (width * factor, height * factor);
    let columns = column_labels
        .len()
        .max(rows.iter().map(Vec::len).max().unwrap_or(0)) as u32;
    let left = row_labels
        .iter()
        .map(|l| text_width(l, TEXT_SCALE) as u32 + GAP_PX)
        .max()
        .unwrap_or(0);
    let canvas_w = left + GAP_PX + columns * (cell_w + GAP_PX);
    let row_h = cell_h + LINE_PX + GAP_PX;
    let canvas_h = GAP_PX + LINE_PX + rows.len() as u32 * row_h;
    let mut canvas = Canvas::new(canvas_w, canvas_h, BACKGROUND);
    let column_x = |c: u32| (left + GAP_PX + c * (cell_w + GAP_PX)) as i64;
    for (c, label) in column_labels.iter().enumerate() {
        let x = column_x(c as u32) + (cell_w as i64 - text_width(label, TEXT_SCALE)).max(0) / 2;
        draw_text(&mut canvas, x, GAP_PX as i64, label, TEXT_SCALE, TEXT);
    }
    let expected = 3 * width as usize * height as usize;
    for (r, row) in rows.iter().enumerate() {
        let y = (GAP_PX + LINE_PX + r as u32 * row_h) as i64;
        if let Some(label) = row_labels.get(r) {
            draw_text(
                &mut canvas,
                GAP_PX as i64,
                y + cell_h as i64 / 2 - 5,
                label,
                TEXT_SCALE,
                TEXT,
            );
        }
        for (c, cell) in row.iter().enumerate() {
            let x = column_x(c as u32);
            match &cell.rgb8 {
                Some(rgb8) if rgb8.len() == expected => {
                    let big = upscale_rgb(width, height, rgb8, factor);
                    canvas.blit(x, y, cell_w, cell_h, &big);
                }
                _ => canvas.fill_rect(x, y, cell_w as i64, cell_h as i64, MISSING),
            }
            let tx = x + (cell_w as i64 - text_width(&cell.caption, TEXT_SCALE)).max(0) / 2;
            draw_text(
                &mut canvas,
                tx,
                y + cell_h as i64 + 3,
                &cell.caption,
                TEXT_SCALE,
                TEXT,
            );
        }
    }
    canvas
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cells_are_upscaled_copies_and_missing_cells_are_grey() {
        let (w, h) = (4u32, 2u32);
        let img: Vec<u8> = (0..w * h * 3).map(|i| (i * 9) as u8).collect();
        let rows = vec![vec![
            Cell {
                rgb8: Some(img.clone()),
                caption: "1.0".into(),
            },
            Cell::default(),
        ]];
        let canvas = grid_figure(w, h, &["GT".into(), "(B)".into()], &[], &rows, 12);
        // factor 3: cell 12 x 6.
        let x0 = GAP_PX as usize;
        let y0 = (GAP_PX + LINE_PX) as usize;
        for y in 0..6 {
            for x in 0..12 {
                let o = 3 * ((y0 + y) * canvas.width as usize + x0 + x);
                let s = 3 * ((y / 3) * w as usize + x / 3);
                assert_eq!(&canvas.rgb8[o..o + 3], &img[s..s + 3], "({x}, {y})");
            }
        }
        let x1 = x0 + 12 + GAP_PX as usize;
        let o = 3 * ((y0 + 2) * canvas.width as usize + x1 + 2);
        assert_eq!(&canvas.rgb8[o..o + 3], &MISSING);
        // Labels draw something dark above the cells.
        let label_rows = &canvas.rgb8[..3 * canvas.width as usize * y0];
        assert!(label_rows.iter().any(|&v| v < 50));
    }
}

//! Lossless file writers: 8-bit PNG (RGB and grey), float32 depth as NumPy `.npy`, binary PLY
//! point clouds.
//!
//! Invariants: output bytes depend only on the data (no timestamps, fixed header layouts), so
//! equal inputs give byte-identical files. `.npy` files are version 1.0, dtype `<f4`, C order,
//! shape (height, width), first row at the top of the image.

use super::DatasetError;
use std::io::Write;
use std::path::Path;

fn io_error(path: &Path, e: impl std::fmt::Display) -> DatasetError {
    DatasetError::Io {
        path: path.to_path_buf(),
        message: e.to_string(),
    }
}

/// Writes `data` to `path`, replacing any existing file.
pub(crate) fn write_bytes(path: &Path, data: &[u8]) -> Result<(), DatasetError> {
    std::fs::write(path, data).map_err(|e| io_error(path, e))
}

/// Writes an 8-bit RGB PNG; `rgb8` holds width * height * 3 bytes, row-major from the top.
pub fn write_png_rgb(
    path: &Path,
    width: u32,
    height: u32,
    rgb8: &[u8],
) -> Result<(), DatasetError> {
    image::save_buffer(path, rgb8, width, height, image::ExtendedColorType::Rgb8)
        .map_err(|e| io_error(path, e))
}

/// Writes an 8-bit greyscale PNG.
pub(crate) fn write_png_grey(
    path: &Path,
    width: u32,
    height: u32,
    grey8: &[u8],
) -> Result<(), DatasetError> {
    image::save_buffer(path, grey8, width, height, image::ExtendedColorType::L8)
        .map_err(|e| io_error(path, e))
}

/// Encodes a (height, width) float32 array as NumPy `.npy` version 1.0 bytes.
pub(crate) fn npy_f32_bytes(width: u32, height: u32, values: &[f32]) -> Vec<u8> {
    let mut header =
        format!("{{'descr': '<f4', 'fortran_order': False, 'shape': ({height}, {width}), }}");
    // Magic (6) + version (2) + length (2) + header + '\n' must be a multiple of 64.
    let unpadded = 10 + header.len() + 1;
    header.push_str(&" ".repeat((64 - unpadded % 64) % 64));
    header.push('\n');
    let mut bytes = Vec::with_capacity(10 + header.len() + 4 * values.len());
    bytes.extend_from_slice(b"\x93NUMPY\x01\x00");
    bytes.extend_from_slice(&(header.len() as u16).to_le_bytes());
    bytes.extend_from_slice(header.as_bytes());
    for v in values {
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    bytes
}

/// One point of a PLY cloud.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct PlyPoint {
    pub position: [f32; 3],
    pub normal: [f32; 3],
    pub rgb8: [u8; 3],
}

/// Binary little-endian PLY with x y z nx ny nz (float) and red green blue (uchar) per vertex.
pub(crate) fn ply_bytes(points: &[PlyPoint], comment: &str) -> Vec<u8> {
    let mut bytes = Vec::with_capacity(300 + points.len() * 27);
    let header = format!(
        "ply\nformat binary_little_endian 1.0\ncomment {}\nelement vertex {}\n\
         property float x\nproperty float y\nproperty float z\n\
         property float nx\nproperty float ny\nproperty float nz\n\
         property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n",
        comment.replace('\n', " "),
        points.len()
    );
    bytes.extend_from_slice(header.as_bytes());
    for p in points {
        for v in p.position.iter().chain(p.normal.iter()) {
            bytes
                .write_all(&v.to_le_bytes())
                .expect("writing to a Vec cannot fail");
        }
        bytes.extend_from_slice(&p.rgb8);
    }
    bytes
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn npy_header_is_aligned_and_data_follows() {
        let values = [1.5f32, f32::INFINITY, -2.0, 0.0, 3.25, 7.0];
        let bytes = npy_f32_bytes(3, 2, &values);
        assert_eq!(&bytes[..8], b"\x93NUMPY\x01\x00");
        let header_len = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
        assert_eq!((10 + header_len) % 64, 0);
        let header = std::str::from_utf8(&bytes[10..10 + header_len]).unwrap();
        assert!(header.starts_with("{'descr': '<f4', 'fortran_order': False, 'shape': (2, 3), }"));
        assert!(header.ends_with('\n'));
        let data = &bytes[10 + header_len..];
        assert_eq!(data.len(), 24);
        for (i, v) in values.iter().enumerate() {
            let got = f32::from_le_bytes(data[4 * i..4 * i + 4].try_into().unwrap());
            assert_eq!(got.to_bits(), v.to_bits());
        }
    }

    #[test]
    fn ply_has_declared_vertex_count_and_record_size() {
        let p = PlyPoint {
            position: [1.0, 2.0, 3.0],
            normal: [0.0, 0.0, 1.0],
            rgb8: [10, 20, 30],
        };
        let bytes = ply_bytes(&[p, p], "test");
        let text_end = bytes
            .windows(11)
            .position(|w| w == b"end_header\n")
            .unwrap()
            + 11;
        let header = std::str::from_utf8(&bytes[..text_end]).unwrap();
        assert!(header.contains("element vertex 2\n"));
        assert_eq!(bytes.len() - text_end, 2 * 27);
        assert_eq!(&bytes[text_end + 24..text_end + 27], &[10, 20, 30]);
        assert_eq!(
            f32::from_le_bytes(bytes[text_end + 4..text_end + 8].try_into().unwrap()),
            2.0
        );
    }
}

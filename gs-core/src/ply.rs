//! The standard 3DGS PLY model file (binary little-endian).
//!
//! Layout written (what the reference implementation and common viewers read):
//! `x y z nx ny nz f_dc_0..2 f_rest_0..(3(K-1)-1) opacity scale_0..2 rot_0..3`, all
//! `float`, one `vertex` element. Values are stored raw, as 3DGS does: log scales,
//! opacity logits, unnormalised `[w, x, y, z]` quaternions, SH coefficients; the normals
//! are the learned shading normal `v / |v|` where the model has one (`Param::Normal`,
//! `shading = "lambert_learned"`; zero where `|v|` is degenerate), else zero (the reader
//! ignores them). 3DGS stores `f_rest` CHANNEL-major (all red coefficients, then green, then
//! blue: `f_rest_{c (K-1) + k-1}`) while our `ShRest` is coefficient-major
//! (`[c1.r, c1.g, c1.b, c2.r, ...]`): this module converts both ways.
//!
//! The reader accepts any property order and any scalar property type, ignores unknown
//! properties and other elements, infers the SH degree from the number of `f_rest_*`
//! properties (0, 9, 24, 45), drops and counts rows with non-finite values, and reports
//! malformed files as [`PlyError`]s. Appearance features and shadow latents are not part
//! of this format (they go in the checkpoint beside it): a loaded model has none.

use std::io::{BufRead, BufReader, Read, Write};
use std::path::Path;

use crate::model::{sh_coeff_count, GaussianModel, ModelError, ModelLayout, Param};

/// Longest header accepted, bytes.
const MAX_HEADER_BYTES: usize = 1 << 16;

/// Error reading or writing a PLY file.
#[derive(Debug)]
pub enum PlyError {
    Io(std::io::Error),
    /// The header is not a PLY header we can read; the message says why.
    Header(String),
    /// Only `binary_little_endian 1.0` is supported.
    Format(String),
    /// A property the model needs is missing.
    MissingProperty(String),
    /// `f_rest_*` properties do not form 0, 9, 24 or 45 consecutive coefficients.
    ShRestCount(usize),
    /// The body ended before `expected` vertices were read.
    Truncated {
        expected: usize,
        read: usize,
    },
    Model(ModelError),
}

impl std::fmt::Display for PlyError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            PlyError::Io(e) => write!(f, "PLY I/O: {e}"),
            PlyError::Header(why) => write!(f, "malformed PLY header: {why}"),
            PlyError::Format(fmt) => write!(
                f,
                "PLY format '{fmt}' not supported (binary_little_endian 1.0 only)"
            ),
            PlyError::MissingProperty(p) => write!(f, "PLY vertex property '{p}' is missing"),
            PlyError::ShRestCount(n) => write!(
                f,
                "{n} f_rest_* properties: expected 0, 9, 24 or 45 numbered from 0"
            ),
            PlyError::Truncated { expected, read } => write!(
                f,
                "PLY body truncated: header promises {expected} vertices, only {read} present"
            ),
            PlyError::Model(e) => write!(f, "model: {e}"),
        }
    }
}

impl std::error::Error for PlyError {}

impl From<std::io::Error> for PlyError {
    fn from(e: std::io::Error) -> Self {
        PlyError::Io(e)
    }
}

impl From<ModelError> for PlyError {
    fn from(e: ModelError) -> Self {
        PlyError::Model(e)
    }
}

/// A model read from a PLY file.
#[derive(Clone, Debug)]
pub struct LoadedPly {
    pub model: GaussianModel,
    /// Vertices skipped because one of the values used was NaN or infinite.
    pub dropped_non_finite: usize,
}

/// Property names in the order we write them, for SH degree `degree`.
pub fn property_names(degree: u32) -> Vec<String> {
    let rest = (sh_coeff_count(degree) - 1) * 3;
    let mut names: Vec<String> = ["x", "y", "z", "nx", "ny", "nz"]
        .iter()
        .map(ToString::to_string)
        .collect();
    names.extend((0..3).map(|i| format!("f_dc_{i}")));
    names.extend((0..rest).map(|i| format!("f_rest_{i}")));
    names.push("opacity".into());
    names.extend((0..3).map(|i| format!("scale_{i}")));
    names.extend((0..4).map(|i| format!("rot_{i}")));
    names
}

/// Writes `model` as a 3DGS PLY.
pub fn write_ply<W: Write>(model: &GaussianModel, out: W) -> Result<(), PlyError> {
    let mut out = std::io::BufWriter::new(out);
    let degree = model.layout().sh_degree;
    let rest_coeffs = sh_coeff_count(degree) - 1;
    let mut header = String::from("ply\nformat binary_little_endian 1.0\n");
    header += &format!("element vertex {}\n", model.len());
    for name in property_names(degree) {
        header += &format!("property float {name}\n");
    }
    header += "end_header\n";
    out.write_all(header.as_bytes())?;
    let p = &model.params;
    let mut row = Vec::with_capacity(property_names(degree).len());
    for i in 0..model.len() {
        row.clear();
        row.extend_from_slice(p.row(Param::Mean, i));
        row.extend_from_slice(&unit_normal(p, i));
        row.extend_from_slice(p.row(Param::ShDc, i));
        let rest = p.row(Param::ShRest, i);
        for c in 0..3 {
            for k in 0..rest_coeffs {
                row.push(rest[k * 3 + c]);
            }
        }
        row.extend_from_slice(p.row(Param::OpacityLogit, i));
        row.extend_from_slice(p.row(Param::LogScale, i));
        row.extend_from_slice(p.row(Param::Rotation, i));
        for v in &row {
            out.write_all(&v.to_le_bytes())?;
        }
    }
    out.flush()?;
    Ok(())
}

/// `v / |v|` of row `i`'s learned normal; zeros without a normal group or where `|v|` is
/// degenerate or not finite.
fn unit_normal(p: &crate::model::ParamSet, i: usize) -> [f32; 3] {
    if p.dim(Param::Normal) != 3 {
        return [0.0; 3];
    }
    let v = p.row(Param::Normal, i);
    let norm2: f32 = v.iter().map(|x| x * x).sum();
    if !(norm2.is_finite() && norm2 >= crate::raster::project::MIN_QUAT_NORM2) {
        return [0.0; 3];
    }
    let norm = norm2.sqrt();
    [v[0] / norm, v[1] / norm, v[2] / norm]
}

/// Writes `model` to `path`.
pub fn save_ply(model: &GaussianModel, path: impl AsRef<Path>) -> Result<(), PlyError> {
    let file = std::fs::File::create(path)?;
    write_ply(model, file)
}

/// Reads a model from `path`.
pub fn load_ply(path: impl AsRef<Path>) -> Result<LoadedPly, PlyError> {
    let file = std::fs::File::open(path)?;
    read_ply(file)
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum ScalarType {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl ScalarType {
    fn parse(s: &str) -> Option<Self> {
        Some(match s {
            "char" | "int8" => Self::I8,
            "uchar" | "uint8" => Self::U8,
            "short" | "int16" => Self::I16,
            "ushort" | "uint16" => Self::U16,
            "int" | "int32" => Self::I32,
            "uint" | "uint32" => Self::U32,
            "float" | "float32" => Self::F32,
            "double" | "float64" => Self::F64,
            _ => return None,
        })
    }

    fn size(self) -> usize {
        match self {
            Self::I8 | Self::U8 => 1,
            Self::I16 | Self::U16 => 2,
            Self::I32 | Self::U32 | Self::F32 => 4,
            Self::F64 => 8,
        }
    }

    fn decode(self, b: &[u8]) -> f32 {
        match self {
            Self::I8 => b[0] as i8 as f32,
            Self::U8 => b[0] as f32,
            Self::I16 => i16::from_le_bytes([b[0], b[1]]) as f32,
            Self::U16 => u16::from_le_bytes([b[0], b[1]]) as f32,
            Self::I32 => i32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f32,
            Self::U32 => u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f32,
            Self::F32 => f32::from_le_bytes([b[0], b[1], b[2], b[3]]),
            Self::F64 => f64::from_le_bytes(b[..8].try_into().expect("8 bytes")) as f32,
        }
    }
}

#[derive(Debug)]
struct Property {
    name: String,
    ty: ScalarType,
    offset: usize,
}

#[derive(Debug)]
struct Element {
    name: String,
    count: usize,
    properties: Vec<Property>,
    stride: usize,
}

fn parse_header<R: BufRead>(r: &mut R) -> Result<Vec<Element>, PlyError> {
    let mut lines = Vec::new();
    let mut total = 0;
    loop {
        let mut raw = Vec::new();
        let n = r.read_until(b'\n', &mut raw)?;
        if n == 0 {
            return Err(PlyError::Header("file ends before end_header".into()));
        }
        total += n;
        if total > MAX_HEADER_BYTES {
            return Err(PlyError::Header(format!(
                "no end_header within {MAX_HEADER_BYTES} bytes"
            )));
        }
        let line = String::from_utf8(raw)
            .map_err(|_| PlyError::Header("header is not ASCII text".into()))?;
        let line = line.trim_end_matches(['\n', '\r']).to_string();
        if line == "end_header" {
            break;
        }
        lines.push(line);
    }
    if lines.first().map(String::as_str) != Some("ply") {
        return Err(PlyError::Header("first line is not 'ply'".into()));
    }
    let mut elements: Vec<Element> = Vec::new();
    let mut format_seen = false;
    for line in &lines[1..] {
        let words: Vec<&str> = line.split_whitespace().collect();
        match words.as_slice() {
            [] => {}
            ["comment" | "obj_info", ..] => {}
            ["format", fmt, version] => {
                if *fmt != "binary_little_endian" || *version != "1.0" {
                    return Err(PlyError::Format(format!("{fmt} {version}")));
                }
                format_seen = true;
            }
            ["format", ..] => return Err(PlyError::Format(line.clone())),
            ["element", name, count] => {
                let count = count.parse::<usize>().map_err(|_| {
                    PlyError::Header(format!("element count '{count}' is not a number"))
                })?;
                elements.push(Element {
                    name: name.to_string(),
                    count,
                    properties: Vec::new(),
                    stride: 0,
                });
            }
            ["property", "list", ..] => {
                let element = elements.last().map_or("none", |e| e.name.as_str());
                return Err(PlyError::Header(format!(
                    "list property in element '{element}' is not supported"
                )));
            }
            ["property", ty, name] => {
                let ty = ScalarType::parse(ty)
                    .ok_or_else(|| PlyError::Header(format!("unknown property type '{ty}'")))?;
                let element = elements.last_mut().ok_or_else(|| {
                    PlyError::Header(format!("property '{name}' before any element"))
                })?;
                element.properties.push(Property {
                    name: name.to_string(),
                    ty,
                    offset: element.stride,
                });
                element.stride += ty.size();
            }
            _ => return Err(PlyError::Header(format!("unexpected line '{line}'"))),
        }
    }
    if !format_seen {
        return Err(PlyError::Header("no format line".into()));
    }
    Ok(elements)
}

/// Reads a 3DGS PLY model from any reader.
pub fn read_ply<R: Read>(input: R) -> Result<LoadedPly, PlyError> {
    let mut r = BufReader::new(input);
    let elements = parse_header(&mut r)?;
    let vertex_pos = elements
        .iter()
        .position(|e| e.name == "vertex")
        .ok_or_else(|| PlyError::Header("no 'vertex' element".into()))?;
    // Skip the bodies of elements stored before the vertices.
    for e in &elements[..vertex_pos] {
        let bytes = (e.count as u64).saturating_mul(e.stride as u64);
        let skipped = std::io::copy(&mut (&mut r).take(bytes), &mut std::io::sink())?;
        if skipped != bytes {
            return Err(PlyError::Header(format!(
                "file ends inside element '{}'",
                e.name
            )));
        }
    }
    let vertex = &elements[vertex_pos];
    let find =
        |name: &str| -> Option<&Property> { vertex.properties.iter().find(|p| p.name == name) };
    let need = |name: &str| -> Result<&Property, PlyError> {
        find(name).ok_or_else(|| PlyError::MissingProperty(name.to_string()))
    };
    let rest_total = vertex
        .properties
        .iter()
        .filter(|p| p.name.starts_with("f_rest_"))
        .count();
    let degree = match rest_total {
        0 => 0,
        9 => 1,
        24 => 2,
        45 => 3,
        n => return Err(PlyError::ShRestCount(n)),
    };
    let rest_coeffs = sh_coeff_count(degree) - 1;
    // Source property of each value, in our in-memory order per group.
    let mut sources: Vec<(Param, Vec<&Property>)> = Vec::new();
    let group = |names: Vec<String>| -> Result<Vec<&Property>, PlyError> {
        names.iter().map(|n| need(n)).collect()
    };
    sources.push((
        Param::Mean,
        group(vec!["x".into(), "y".into(), "z".into()])?,
    ));
    sources.push((
        Param::LogScale,
        group((0..3).map(|i| format!("scale_{i}")).collect())?,
    ));
    sources.push((
        Param::Rotation,
        group((0..4).map(|i| format!("rot_{i}")).collect())?,
    ));
    sources.push((Param::OpacityLogit, group(vec!["opacity".into()])?));
    sources.push((
        Param::ShDc,
        group((0..3).map(|i| format!("f_dc_{i}")).collect())?,
    ));
    let mut rest_names = Vec::with_capacity(rest_coeffs * 3);
    for k in 0..rest_coeffs {
        for c in 0..3 {
            rest_names.push(format!("f_rest_{}", c * rest_coeffs + k));
        }
    }
    let rest_sources = group(rest_names).map_err(|_| PlyError::ShRestCount(rest_total))?;
    sources.push((Param::ShRest, rest_sources));

    let mut model = GaussianModel::new(ModelLayout::sh(degree))?;
    let mut buf = vec![0u8; vertex.stride];
    let mut values: Vec<Vec<f32>> = sources.iter().map(|(_, s)| vec![0.0; s.len()]).collect();
    let empty: Vec<f32> = Vec::new();
    let mut dropped = 0;
    for read in 0..vertex.count {
        if let Err(e) = r.read_exact(&mut buf) {
            return Err(match e.kind() {
                std::io::ErrorKind::UnexpectedEof => PlyError::Truncated {
                    expected: vertex.count,
                    read,
                },
                _ => PlyError::Io(e),
            });
        }
        let mut finite = true;
        for ((_, props), vals) in sources.iter().zip(values.iter_mut()) {
            for (v, p) in vals.iter_mut().zip(props) {
                *v = p.ty.decode(&buf[p.offset..p.offset + p.ty.size()]);
                finite &= v.is_finite();
            }
        }
        if !finite {
            dropped += 1;
            continue;
        }
        model.params.push_row(|p| {
            sources
                .iter()
                .position(|(q, _)| *q == p)
                .map_or(&empty, |k| values[k].as_slice())
        })?;
    }
    Ok(LoadedPly {
        model,
        dropped_non_finite: dropped,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::init::SplitMix64;

    fn random_model(n: usize, degree: u32, seed: u64) -> GaussianModel {
        let mut m = GaussianModel::new(ModelLayout::sh(degree)).unwrap();
        m.params.push_zeros(n);
        let mut rng = SplitMix64::new(seed);
        for p in Param::ALL {
            for v in m.params.get_mut(p) {
                *v = rng.normal();
            }
        }
        m
    }

    #[test]
    fn round_trip_is_exact_for_every_degree() {
        for degree in 0..=3 {
            let m = random_model(17, degree, degree as u64);
            let mut bytes = Vec::new();
            write_ply(&m, &mut bytes).unwrap();
            let loaded = read_ply(bytes.as_slice()).unwrap();
            assert_eq!(loaded.dropped_non_finite, 0);
            assert_eq!(loaded.model, m);
            // Header + 4 bytes per property per vertex.
            let header_end = bytes
                .windows(11)
                .position(|w| w == b"end_header\n")
                .unwrap()
                + 11;
            assert_eq!(
                bytes.len() - header_end,
                17 * 4 * property_names(degree).len()
            );
        }
    }

    #[test]
    fn f_rest_is_written_channel_major() {
        let mut m = GaussianModel::new(ModelLayout::sh(1)).unwrap();
        m.params.push_zeros(1);
        // Ours: [c1.r, c1.g, c1.b, c2.r, c2.g, c2.b, c3.r, c3.g, c3.b].
        let rest: Vec<f32> = (0..9).map(|v| v as f32).collect();
        m.params.get_mut(Param::ShRest).copy_from_slice(&rest);
        let mut bytes = Vec::new();
        write_ply(&m, &mut bytes).unwrap();
        let header_end = bytes
            .windows(11)
            .position(|w| w == b"end_header\n")
            .unwrap()
            + 11;
        let body: Vec<f32> = bytes[header_end..]
            .chunks(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        // f_rest_0..8 follow x y z nx ny nz f_dc_0..2 (9 values): R coeffs, G, B.
        assert_eq!(&body[9..18], &[0.0, 3.0, 6.0, 1.0, 4.0, 7.0, 2.0, 5.0, 8.0]);
    }

    /// A hand-written file: shuffled property order, a double, an unknown uchar property,
    /// an element before the vertices, comments, CRLF line ends and a non-finite row.
    #[test]
    fn reads_a_hand_written_file() {
        let mut names: Vec<(&str, String)> = vec![("uchar", "red".into())];
        names.push(("float", "opacity".into()));
        for i in (0..9).rev() {
            names.push(("float", format!("f_rest_{i}")));
        }
        for n in [
            "rot_3", "rot_2", "rot_1", "rot_0", "scale_2", "scale_1", "scale_0",
        ] {
            names.push(("float", n.into()));
        }
        names.push(("double", "x".into()));
        for n in ["y", "z", "f_dc_0", "f_dc_1", "f_dc_2"] {
            names.push(("float", n.into()));
        }
        let mut text = String::from(
            "ply\r\nformat binary_little_endian 1.0\r\ncomment made by hand\r\n\
             element camera 1\r\nproperty ushort id\r\nelement vertex 2\r\n",
        );
        for (ty, n) in &names {
            text += &format!("property {ty} {n}\r\n");
        }
        text += "end_header\r\n";
        let mut bytes = text.into_bytes();
        bytes.extend_from_slice(&7u16.to_le_bytes()); // camera element body
        for row in 0..2 {
            for (ty, n) in &names {
                // Value = a code of the property name, so the mapping is checkable.
                let v: f32 = if let Some(k) = n.strip_prefix("f_rest_") {
                    10.0 + k.parse::<f32>().unwrap()
                } else {
                    match n.as_str() {
                        "x" => 1.5,
                        "y" => 2.5,
                        "z" if row == 1 => f32::NAN,
                        "z" => 3.5,
                        "opacity" => -0.5,
                        "red" => 200.0,
                        _ => n.bytes().map(|b| b as f32).sum::<f32>() / 100.0,
                    }
                };
                match *ty {
                    "uchar" => bytes.push(v as u8),
                    "double" => bytes.extend_from_slice(&(v as f64).to_le_bytes()),
                    _ => bytes.extend_from_slice(&v.to_le_bytes()),
                }
            }
        }
        let loaded = read_ply(bytes.as_slice()).unwrap();
        assert_eq!(loaded.dropped_non_finite, 1);
        let m = &loaded.model;
        assert_eq!((m.len(), m.layout().sh_degree), (1, 1));
        assert_eq!(m.params.row(Param::Mean, 0), &[1.5, 2.5, 3.5]);
        assert_eq!(m.params.row(Param::OpacityLogit, 0), &[-0.5]);
        let code = |s: &str| s.bytes().map(|b| b as f32).sum::<f32>() / 100.0;
        assert_eq!(
            m.params.row(Param::Rotation, 0),
            &[code("rot_0"), code("rot_1"), code("rot_2"), code("rot_3")]
        );
        // f_rest_{c*3 + k} -> ours [k*3 + c]: coefficient 1 = (f_rest_0, _3, _6).
        assert_eq!(
            m.params.row(Param::ShRest, 0),
            &[10.0, 13.0, 16.0, 11.0, 14.0, 17.0, 12.0, 15.0, 18.0]
        );
    }

    #[test]
    fn malformed_files_are_clear_errors() {
        let m = random_model(3, 1, 9);
        let mut good = Vec::new();
        write_ply(&m, &mut good).unwrap();
        let header_end = good.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
        let text = String::from_utf8(good[..header_end].to_vec()).unwrap();

        let truncated = &good[..good.len() - 5];
        assert!(matches!(
            read_ply(truncated),
            Err(PlyError::Truncated {
                expected: 3,
                read: 2
            })
        ));
        let ascii = text.replace("binary_little_endian", "ascii");
        assert!(matches!(
            read_ply(ascii.as_bytes()),
            Err(PlyError::Format(_))
        ));
        let no_opacity = text.replace("property float opacity\n", "");
        assert!(matches!(
            read_ply(no_opacity.as_bytes()),
            Err(PlyError::MissingProperty(p)) if p == "opacity"
        ));
        let odd_rest = text.replace("property float f_rest_8\n", "");
        assert!(matches!(
            read_ply(odd_rest.as_bytes()),
            Err(PlyError::ShRestCount(8))
        ));
        assert!(matches!(
            read_ply(&b"PNG not a ply"[..]),
            Err(PlyError::Header(_))
        ));
        let list = text.replace(
            "property float x\n",
            "property list uchar int vertex_indices\n",
        );
        assert!(matches!(
            read_ply(list.as_bytes()),
            Err(PlyError::Header(_))
        ));
        let bad_count = text.replace("element vertex 3", "element vertex -3");
        assert!(matches!(
            read_ply(bad_count.as_bytes()),
            Err(PlyError::Header(_))
        ));
    }
}

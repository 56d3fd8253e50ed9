//! Cache of rendered experiment scenes: one binary file per scenario, so re-running a table
//! in the same output folder skips the ray tracing.
//!
//! Format (little-endian): magic `SHXSCN01`, u64 key, u32 name length + UTF-8 name, six f64/u32
//! intrinsics, then the sequence and evaluation sets, each as u32 count followed by views:
//! u32 index, u8 has_time, f64 time, u8 eclipse, f64 x4 quaternion (w x y z), f64 x3
//! translation, f64 x3 Sun, then width * height * 3 RGB bytes and width * height mask bytes.
//! A trailing u64 FNV-1a checksum of everything before it.
//!
//! Invariants: the key hashes the scenario's full TOML serialisation, its OBJ file bytes when it
//! has one, the surface sample count and this format's version, so any change misses the
//! cache; a file with a wrong magic, key, size or checksum is ignored (re-rendered), never
//! half-read.

use super::data::{SceneData, SceneIntrinsics, ViewData};
use crate::dataset::DatasetError;
use crate::scenario::{Scenario, TargetSource};
use glam::{DQuat, DVec3};
use std::path::Path;

const MAGIC: &[u8; 8] = b"SHXSCN01";

/// FNV-1a, 64 bit.
pub(crate) fn fnv1a64(bytes: &[u8]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for &b in bytes {
        h ^= b as u64;
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    h
}

/// Cache key of a scenario rendered with `surface_points` samples.
pub(crate) fn scene_key(scenario: &Scenario, surface_points: usize) -> u64 {
    let mut text = toml::to_string(scenario).unwrap_or_default();
    text.push_str(&format!(
        "\nsurface_points={surface_points}\nformat={MAGIC:?}\n"
    ));
    let mut bytes = text.into_bytes();
    if let Ok(TargetSource::Obj(path)) = scenario.target_source() {
        bytes.extend_from_slice(path.display().to_string().as_bytes());
        bytes.extend_from_slice(&std::fs::read(&path).unwrap_or_default());
    }
    fnv1a64(&bytes)
}

/// A file-name-safe version of a scenario name.
pub(crate) fn safe_name(name: &str) -> String {
    name.chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '_' {
                c
            } else {
                '_'
            }
        })
        .collect()
}

fn put_f64(out: &mut Vec<u8>, v: f64) {
    out.extend_from_slice(&v.to_le_bytes());
}

fn put_u32(out: &mut Vec<u8>, v: u32) {
    out.extend_from_slice(&v.to_le_bytes());
}

fn put_views(out: &mut Vec<u8>, views: &[ViewData]) {
    put_u32(out, views.len() as u32);
    for v in views {
        put_u32(out, v.index);
        out.push(v.time_s.is_some() as u8);
        put_f64(out, v.time_s.unwrap_or(0.0));
        out.push(v.eclipse as u8);
        let q = v.q_camera_from_target;
        for x in [q.w, q.x, q.y, q.z] {
            put_f64(out, x);
        }
        for x in v.t_camera_from_target_m.to_array() {
            put_f64(out, x);
        }
        for x in v.sun_dir_target.to_array() {
            put_f64(out, x);
        }
        out.extend_from_slice(&v.rgb8);
        out.extend_from_slice(&v.mask8);
    }
}

/// Encodes a scene (without surface samples and bounds, which are recomputed).
pub(crate) fn encode(key: u64, scene: &SceneData) -> Vec<u8> {
    let mut out = Vec::new();
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&key.to_le_bytes());
    put_u32(&mut out, scene.name.len() as u32);
    out.extend_from_slice(scene.name.as_bytes());
    let k = scene.intrinsics;
    for x in [k.fx, k.fy, k.cx, k.cy] {
        put_f64(&mut out, x);
    }
    put_u32(&mut out, k.width);
    put_u32(&mut out, k.height);
    put_views(&mut out, &scene.frames);
    put_views(&mut out, &scene.eval);
    let checksum = fnv1a64(&out);
    out.extend_from_slice(&checksum.to_le_bytes());
    out
}

struct Reader<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl Reader<'_> {
    fn take(&mut self, n: usize) -> Option<&[u8]> {
        let end = self.at.checked_add(n)?;
        let slice = self.bytes.get(self.at..end)?;
        self.at = end;
        Some(slice)
    }
    fn u8(&mut self) -> Option<u8> {
        Some(self.take(1)?[0])
    }
    fn u32(&mut self) -> Option<u32> {
        Some(u32::from_le_bytes(self.take(4)?.try_into().ok()?))
    }
    fn u64(&mut self) -> Option<u64> {
        Some(u64::from_le_bytes(self.take(8)?.try_into().ok()?))
    }
    fn f64(&mut self) -> Option<f64> {
        Some(f64::from_le_bytes(self.take(8)?.try_into().ok()?))
    }
    fn views(&mut self, pixels: usize) -> Option<Vec<ViewData>> {
        let count = self.u32()? as usize;
        // Each view needs at least its pixels: refuse counts the file cannot hold.
        if count.checked_mul(pixels * 4)? > self.bytes.len() {
            return None;
        }
        let mut views = Vec::with_capacity(count);
        for _ in 0..count {
            let index = self.u32()?;
            let has_time = self.u8()? != 0;
            let time = self.f64()?;
            let eclipse = self.u8()? != 0;
            let (w, x, y, z) = (self.f64()?, self.f64()?, self.f64()?, self.f64()?);
            let t = DVec3::new(self.f64()?, self.f64()?, self.f64()?);
            let sun = DVec3::new(self.f64()?, self.f64()?, self.f64()?);
            let rgb8 = self.take(pixels * 3)?.to_vec();
            let mask8 = self.take(pixels)?.to_vec();
            views.push(ViewData {
                index,
                time_s: has_time.then_some(time),
                eclipse,
                q_camera_from_target: DQuat::from_xyzw(x, y, z, w),
                t_camera_from_target_m: t,
                sun_dir_target: sun,
                rgb8,
                mask8,
            });
        }
        Some(views)
    }
}

/// Decodes a cache file; None when anything does not match (magic, key, sizes, checksum).
pub(crate) fn decode(bytes: &[u8], key: u64) -> Option<SceneData> {
    let body_len = bytes.len().checked_sub(8)?;
    let stored = u64::from_le_bytes(bytes[body_len..].try_into().ok()?);
    if fnv1a64(&bytes[..body_len]) != stored {
        return None;
    }
    let mut r = Reader {
        bytes: &bytes[..body_len],
        at: 0,
    };
    if r.take(8)? != MAGIC || r.u64()? != key {
        return None;
    }
    let name_len = r.u32()? as usize;
    let name = String::from_utf8(r.take(name_len)?.to_vec()).ok()?;
    let (fx, fy, cx, cy) = (r.f64()?, r.f64()?, r.f64()?, r.f64()?);
    let (width, height) = (r.u32()?, r.u32()?);
    let pixels = (width as usize).checked_mul(height as usize)?;
    let frames = r.views(pixels)?;
    let eval = r.views(pixels)?;
    if r.at != body_len {
        return None;
    }
    Some(SceneData {
        name,
        intrinsics: SceneIntrinsics {
            fx,
            fy,
            cx,
            cy,
            width,
            height,
        },
        frames,
        eval,
        surface: Vec::new(),
        bounds_min_m: [0.0; 3],
        bounds_max_m: [0.0; 3],
        bounding_radius_m: 0.0,
        render_s: 0.0,
    })
}

/// Reads a cache file; Ok(None) when it is missing or does not match.
pub fn read(path: &Path, key: u64) -> Result<Option<SceneData>, DatasetError> {
    match std::fs::read(path) {
        Ok(bytes) => Ok(decode(&bytes, key)),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(e) => Err(DatasetError::Io {
            path: path.to_path_buf(),
            message: e.to_string(),
        }),
    }
}

/// Writes a cache file atomically (temporary file, then rename).
pub fn write(path: &Path, key: u64, scene: &SceneData) -> Result<(), DatasetError> {
    let tmp = path.with_extension("bin.tmp");
    crate::dataset::files::write_bytes(&tmp, &encode(key, scene))?;
    std::fs::rename(&tmp, path).map_err(|e| DatasetError::Io {
        path: path.to_path_buf(),
        message: e.to_string(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn view(index: u32, pixels: usize) -> ViewData {
        ViewData {
            index,
            time_s: Some(5.0 * index as f64),
            eclipse: index % 2 == 1,
            q_camera_from_target: DQuat::from_rotation_y(0.3 * index as f64),
            t_camera_from_target_m: DVec3::new(0.0, 0.0, 40.0 + index as f64),
            sun_dir_target: DVec3::new(0.6, 0.0, 0.8),
            rgb8: (0..pixels * 3)
                .map(|i| (i * 7 + index as usize) as u8)
                .collect(),
            mask8: (0..pixels)
                .map(|i| if i % 3 == 0 { 255 } else { 0 })
                .collect(),
        }
    }

    #[test]
    fn round_trip_and_rejections() {
        let (w, h) = (5u32, 3u32);
        let pixels = (w * h) as usize;
        let scene = SceneData {
            name: "unit".into(),
            intrinsics: SceneIntrinsics {
                fx: 10.0,
                fy: 10.0,
                cx: 2.5,
                cy: 1.5,
                width: w,
                height: h,
            },
            frames: (0..3).map(|i| view(i, pixels)).collect(),
            eval: vec![ViewData {
                time_s: None,
                ..view(9, pixels)
            }],
            surface: Vec::new(),
            bounds_min_m: [0.0; 3],
            bounds_max_m: [0.0; 3],
            bounding_radius_m: 0.0,
            render_s: 0.0,
        };
        let bytes = encode(42, &scene);
        let back = decode(&bytes, 42).expect("decodes");
        assert_eq!(back.frames, scene.frames);
        assert_eq!(back.eval, scene.eval);
        assert_eq!(back.intrinsics, scene.intrinsics);
        assert_eq!(back.name, "unit");
        // Another key, a flipped byte or a truncation all miss.
        assert!(decode(&bytes, 43).is_none());
        let mut corrupt = bytes.clone();
        corrupt[100] ^= 1;
        assert!(decode(&corrupt, 42).is_none());
        assert!(decode(&bytes[..bytes.len() - 1], 42).is_none());
        assert!(decode(&[], 42).is_none());
    }
}

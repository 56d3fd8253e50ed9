//! Baseline learner: the keyframe window itself, predicting by the nearest keyframe view.
//!
//! It stands in for the Sun-aware trainer when that is not wired in, and gives the bus
//! tests a model that is cheap, deterministic and whose state depends on every accepted
//! frame. A prediction is the keyframe whose view direction (target frame) is closest to
//! the requested one, resampled (nearest neighbour) to the requested size; it ignores the
//! Sun. A "round" runs when the window is full and its composition changed since the last
//! round; its loss is the mean absolute error (on [0, 1]) of each keyframe against the
//! leave-one-out prediction from the others.
//!
//! Window rule as in `keyframe.rs` (paper): added when the view moved more than theta_VIEW
//! from the newest keyframe; over capacity, the most redundant non-protected keyframe goes.
//!
//! Checkpoint format (little-endian): magic `FSWNKL01`, rounds u32, generation u64,
//! last_round_generation u64, count u32, then per keyframe (newest first) id u64,
//! view 3 x f64, width u16, height u16, format u8 (0 RGB8, 1 Gray8), len u32, pixels;
//! then CRC-32/IEEE of everything before it. Invariant: load validates everything before
//! replacing the state.

use crate::learner::{
    Learner, LearnerError, LearnerStats, ObservedFrame, OfferResult, PredictedImage, RoundSummary,
    ViewRequest,
};
use gs_online::keyframe::{
    Keyframe, KeyframeError, KeyframeWindow, OfferOutcome, ViewDirection, WindowConfig,
};
use interfaces::crc::crc32_ieee;
use interfaces::messages::PixelFormat;
use std::time::Instant;

pub const CHECKPOINT_MAGIC: &[u8; 8] = b"FSWNKL01";

#[derive(Clone, Debug, PartialEq)]
struct StoredImage {
    width: u16,
    height: u16,
    format: PixelFormat,
    pixels: Vec<u8>,
}

#[derive(Clone, Debug)]
pub struct NearestKeyframeLearner {
    window: KeyframeWindow<StoredImage>,
    last_round_generation: u64,
    rounds: u32,
}

impl NearestKeyframeLearner {
    pub fn new(config: WindowConfig) -> Result<Self, KeyframeError> {
        Ok(Self {
            window: KeyframeWindow::new(config)?,
            last_round_generation: 0,
            rounds: 0,
        })
    }

    fn nearest(&self, view: glam::DVec3, skip_index: Option<usize>) -> Option<&StoredImage> {
        let mut best: Option<(f64, &StoredImage)> = None;
        for (index, keyframe) in self.window.keyframes().iter().enumerate() {
            if Some(index) == skip_index {
                continue;
            }
            let cos = keyframe.view.get().dot(view);
            if best.is_none_or(|(best_cos, _)| cos > best_cos) {
                best = Some((cos, &keyframe.payload));
            }
        }
        best.map(|(_, image)| image)
    }
}

fn intensity(image: &StoredImage, x: usize, y: usize, channel: usize) -> u8 {
    let bpp = image.format.bytes_per_pixel();
    let base = (y * usize::from(image.width) + x) * bpp;
    match image.format {
        PixelFormat::Rgb8 => image.pixels[base + channel],
        PixelFormat::Gray8 => image.pixels[base],
    }
}

/// Nearest-neighbour resampling and format conversion (RGB -> gray by the mean).
fn resample(image: &StoredImage, width: u16, height: u16, format: PixelFormat) -> Vec<u8> {
    let (w, h) = (usize::from(width), usize::from(height));
    let (sw, sh) = (usize::from(image.width), usize::from(image.height));
    let mut out = Vec::with_capacity(w * h * format.bytes_per_pixel());
    for y in 0..h {
        let sy = (y * sh) / h;
        for x in 0..w {
            let sx = (x * sw) / w;
            match format {
                PixelFormat::Rgb8 => {
                    for c in 0..3 {
                        out.push(intensity(image, sx, sy, c));
                    }
                }
                PixelFormat::Gray8 => {
                    let sum: u32 = (0..3).map(|c| u32::from(intensity(image, sx, sy, c))).sum();
                    out.push(match image.format {
                        PixelFormat::Gray8 => intensity(image, sx, sy, 0),
                        PixelFormat::Rgb8 => (sum / 3) as u8,
                    });
                }
            }
        }
    }
    out
}

fn mean_abs_error(a: &[u8], b: &[u8]) -> f64 {
    let sum: u64 = a
        .iter()
        .zip(b)
        .map(|(&x, &y)| u64::from(x.abs_diff(y)))
        .sum();
    sum as f64 / (a.len().max(1) as f64 * 255.0)
}

impl Learner for NearestKeyframeLearner {
    fn offer(&mut self, frame: &ObservedFrame) -> OfferResult {
        let Ok(view) = ViewDirection::new(frame.telemetry.view_in_target) else {
            return OfferResult::Skipped;
        };
        let id = u64::from(frame.frame_id);
        let payload = StoredImage {
            width: frame.width,
            height: frame.height,
            format: frame.format,
            pixels: frame.pixels.clone(),
        };
        match self.window.offer(Keyframe { id, view, payload }) {
            OfferOutcome::Added { .. } => OfferResult::Added,
            OfferOutcome::NotAdded { .. } => OfferResult::NotAdded,
        }
    }

    fn run_round_if_due(&mut self) -> Result<Option<RoundSummary>, LearnerError> {
        if !self.window.is_full() || self.window.generation() == self.last_round_generation {
            return Ok(None);
        }
        let started = Instant::now();
        let mut total = 0.0;
        let keyframes = self.window.keyframes();
        for (index, keyframe) in keyframes.iter().enumerate() {
            let image = &keyframe.payload;
            let neighbour = self
                .nearest(keyframe.view.get(), Some(index))
                .unwrap_or(image);
            let predicted = resample(neighbour, image.width, image.height, image.format);
            total += mean_abs_error(&predicted, &image.pixels);
        }
        self.rounds += 1;
        self.last_round_generation = self.window.generation();
        Ok(Some(RoundSummary {
            rounds: self.rounds,
            duration_ms: u32::try_from(started.elapsed().as_millis()).unwrap_or(u32::MAX),
            loss: (total / keyframes.len() as f64) as f32,
            gaussians: 0,
            skipped_steps: 0,
        }))
    }

    fn predict(&self, view: &ViewRequest) -> Result<PredictedImage, LearnerError> {
        if view.width == 0 || view.height == 0 {
            return Err(LearnerError::BadRequest("zero image size".into()));
        }
        let direction = view
            .view_in_target()
            .ok_or_else(|| LearnerError::BadRequest("camera at the target origin".into()))?;
        let image = self
            .nearest(direction, None)
            .ok_or(LearnerError::NothingToRender)?;
        Ok(PredictedImage {
            width: view.width,
            height: view.height,
            format: view.format,
            pixels: resample(image, view.width, view.height, view.format),
        })
    }

    fn reset(&mut self) -> Result<(), LearnerError> {
        self.window.clear();
        // Like a new learner: the next round waits for a composition change.
        self.last_round_generation = self.window.generation();
        self.rounds = 0;
        Ok(())
    }

    fn save(&self) -> Vec<u8> {
        let mut out = Vec::new();
        out.extend_from_slice(CHECKPOINT_MAGIC);
        out.extend_from_slice(&self.rounds.to_le_bytes());
        out.extend_from_slice(&self.window.generation().to_le_bytes());
        out.extend_from_slice(&self.last_round_generation.to_le_bytes());
        out.extend_from_slice(&(self.window.len() as u32).to_le_bytes());
        for keyframe in self.window.keyframes() {
            out.extend_from_slice(&keyframe.id.to_le_bytes());
            for v in keyframe.view.get().to_array() {
                out.extend_from_slice(&v.to_le_bytes());
            }
            let image = &keyframe.payload;
            out.extend_from_slice(&image.width.to_le_bytes());
            out.extend_from_slice(&image.height.to_le_bytes());
            out.push(match image.format {
                PixelFormat::Rgb8 => 0,
                PixelFormat::Gray8 => 1,
            });
            out.extend_from_slice(&(image.pixels.len() as u32).to_le_bytes());
            out.extend_from_slice(&image.pixels);
        }
        let crc = crc32_ieee(&out);
        out.extend_from_slice(&crc.to_le_bytes());
        out
    }

    fn load(&mut self, bytes: &[u8]) -> Result<(), LearnerError> {
        let bad = |why: &str| LearnerError::BadCheckpoint(why.to_string());
        if bytes.len() < CHECKPOINT_MAGIC.len() + 4 || &bytes[..8] != CHECKPOINT_MAGIC {
            return Err(bad("not a nearest-keyframe checkpoint (magic)"));
        }
        let (body, crc) = bytes.split_at(bytes.len() - 4);
        if crc32_ieee(body).to_le_bytes() != crc {
            return Err(bad("checksum mismatch"));
        }
        let mut reader = Reader { bytes: body, at: 8 };
        let rounds = reader.u32()?;
        let generation = reader.u64()?;
        let last_round_generation = reader.u64()?;
        let count = reader.u32()? as usize;
        if count > self.window.capacity() {
            return Err(bad("more keyframes than the window holds"));
        }
        let mut keyframes = Vec::with_capacity(count);
        for _ in 0..count {
            let id = reader.u64()?;
            let view = [reader.f64()?, reader.f64()?, reader.f64()?];
            let view = ViewDirection::restore(glam::DVec3::from_array(view))
                .map_err(|e| bad(&format!("keyframe {id}: {e}")))?;
            let width = reader.u16()?;
            let height = reader.u16()?;
            let format = match reader.u8()? {
                0 => PixelFormat::Rgb8,
                1 => PixelFormat::Gray8,
                other => return Err(bad(&format!("pixel format {other}"))),
            };
            let len = reader.u32()? as usize;
            let expected = usize::from(width) * usize::from(height) * format.bytes_per_pixel();
            if len != expected || expected == 0 {
                return Err(bad(&format!("keyframe {id}: {len} pixel bytes")));
            }
            let pixels = reader.take(len)?.to_vec();
            let payload = StoredImage {
                width,
                height,
                format,
                pixels,
            };
            keyframes.push(Keyframe { id, view, payload });
        }
        if reader.at != body.len() {
            return Err(bad("trailing bytes"));
        }
        self.window = KeyframeWindow::restore(self.window.config(), keyframes, generation)
            .map_err(|e| bad(&e.to_string()))?;
        self.rounds = rounds;
        self.last_round_generation = last_round_generation;
        Ok(())
    }

    fn inspect(&self, bytes: &[u8]) -> Result<u64, LearnerError> {
        // The window is small (a few 8-bit keyframes): parsing into a scratch model is the
        // simplest way to accept exactly what `load` accepts.
        let mut scratch = self.clone();
        scratch.load(bytes)?;
        Ok(u64::from(scratch.rounds))
    }

    fn stats(&self) -> LearnerStats {
        LearnerStats {
            gaussians: 0,
            rounds: self.rounds,
            window_fill: self.window.len().min(255) as u8,
            window_capacity: self.window.capacity().min(255) as u8,
        }
    }
}

struct Reader<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8], LearnerError> {
        let end = self
            .at
            .checked_add(n)
            .filter(|&end| end <= self.bytes.len())
            .ok_or_else(|| LearnerError::BadCheckpoint("truncated".into()))?;
        let out = &self.bytes[self.at..end];
        self.at = end;
        Ok(out)
    }
    fn array<const N: usize>(&mut self) -> Result<[u8; N], LearnerError> {
        let mut out = [0; N];
        out.copy_from_slice(self.take(N)?);
        Ok(out)
    }
    fn u8(&mut self) -> Result<u8, LearnerError> {
        Ok(self.array::<1>()?[0])
    }
    fn u16(&mut self) -> Result<u16, LearnerError> {
        Ok(u16::from_le_bytes(self.array()?))
    }
    fn u32(&mut self) -> Result<u32, LearnerError> {
        Ok(u32::from_le_bytes(self.array()?))
    }
    fn u64(&mut self) -> Result<u64, LearnerError> {
        Ok(u64::from_le_bytes(self.array()?))
    }
    fn f64(&mut self) -> Result<f64, LearnerError> {
        Ok(f64::from_le_bytes(self.array()?))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sync::SyncedTelemetry;
    use glam::{DQuat, DVec3};

    fn frame(id: u32, view: DVec3, value: u8) -> ObservedFrame {
        let view = view.normalize();
        ObservedFrame {
            frame_id: id,
            time_us: u64::from(id) * 1_000_000,
            width: 4,
            height: 2,
            format: PixelFormat::Rgb8,
            pixels: vec![value; 24],
            mask: None,
            camera: gs_core::Intrinsics::from_fov_x(0.6, 4, 2),
            telemetry: SyncedTelemetry {
                time_us: 0,
                camera_from_target: DQuat::IDENTITY,
                target_in_camera_m: -view * 10.0,
                pose_quality: 1.0,
                sun_in_body: DVec3::Z,
                sun_in_camera: DVec3::Z,
                sun_in_target: DVec3::Z,
                view_in_target: view,
                range_m: 10.0,
                eclipse: false,
            },
        }
    }

    fn learner(capacity: usize) -> NearestKeyframeLearner {
        NearestKeyframeLearner::new(WindowConfig {
            capacity,
            min_view_angle_deg: 10.0,
        })
        .expect("valid window")
    }

    #[test]
    fn predicts_the_nearest_view_and_rounds_follow_composition() {
        let mut l = learner(3);
        assert_eq!(l.offer(&frame(1, DVec3::X, 10)), OfferResult::Added);
        assert_eq!(l.offer(&frame(2, DVec3::X, 99)), OfferResult::NotAdded);
        assert_eq!(l.offer(&frame(3, DVec3::Y, 20)), OfferResult::Added);
        assert!(
            l.run_round_if_due().unwrap().is_none(),
            "window not full yet"
        );
        assert_eq!(l.offer(&frame(4, DVec3::Z, 30)), OfferResult::Added);
        let round = l
            .run_round_if_due()
            .unwrap()
            .expect("full window, new composition");
        assert_eq!(round.rounds, 1);
        assert!(
            l.run_round_if_due().unwrap().is_none(),
            "composition unchanged"
        );
        let request = ViewRequest {
            camera_from_target: DQuat::IDENTITY,
            // Camera on the target's +Y side: the target origin at -Y in the camera frame.
            target_in_camera_m: DVec3::new(0.1, -5.0, 0.0),
            sun_in_target: DVec3::Z,
            width: 2,
            height: 1,
            format: PixelFormat::Gray8,
            intrinsics: gs_core::Intrinsics::from_fov_x(0.6, 2, 1),
        };
        assert_eq!(l.predict(&request).unwrap().pixels, vec![20, 20]);
    }

    #[test]
    fn checkpoints_round_trip_and_corruption_is_refused() {
        let mut l = learner(3);
        for (i, v) in [DVec3::X, DVec3::Y, DVec3::Z, DVec3::NEG_X]
            .iter()
            .enumerate()
        {
            l.offer(&frame(i as u32, *v, i as u8 * 40));
            l.run_round_if_due().unwrap();
        }
        let bytes = l.save();
        let mut restored = learner(3);
        restored.load(&bytes).unwrap();
        assert_eq!(restored.save(), bytes);
        assert_eq!(restored.stats(), l.stats());
        let mut corrupted = bytes.clone();
        corrupted[20] ^= 1;
        let before = restored.save();
        assert!(matches!(
            restored.load(&corrupted),
            Err(LearnerError::BadCheckpoint(_))
        ));
        assert_eq!(
            restored.save(),
            before,
            "a failed load leaves the model alone"
        );
        assert!(restored.load(&bytes[..bytes.len() - 9]).is_err());
    }
}

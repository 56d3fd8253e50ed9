//! The online trainer's own state as bytes, so that a restarted trainer continues exactly.
//!
//! The model and its optimiser live in gs-core's checkpoint; this is everything else an
//! [`OnlineTrainer`] carries between rounds: the keyframe window (compact copies of the
//! keyframes, not references, so a restart needs no frame store), the round counter (which
//! also seeds the next round's shuffle with the shuffle seed, and sets the densification
//! cadence), the window generation of the last round, the replay memory and its eviction
//! count, and the frame counters.
//!
//! Layout (little-endian):
//! ```text
//! magic b"GSONLS01"
//! settings: shuffle_seed u64, window capacity u64, min view angle f64 (degrees),
//!           replay capacity u64
//! rounds u64, last trained generation: present u8 + u64, window generation u64,
//! evictions u64, counters 8 x u64 (offered, added, evicted, skipped eclipse, empty mask,
//! unlit, view, duplicate)
//! window: count u64, frames newest first; replay: count u64, frames
//! frame: id u64, time_s f64, fx fy cx cy f32, width u32, height u32, rotation x y z w f32,
//!        translation 3 f32, Sun 3 f32, eclipse u8, image (encoding u8, values),
//!        mask (encoding u8: 0 none, else values)
//! encoding: 1 = f32 values, 2 = u8 values meaning v / 255 (used when every value is
//! exactly such a fraction, as with 8-bit camera frames: a quarter of the bytes, same bits)
//! ```
//! Invariants: the stored settings must equal the trainer's (a caller that wants the stored
//! ones reads them with [`peek_settings`] and builds a trainer with them); every count is
//! checked against its bound (window count <= W, replay count <= the replay capacity,
//! pixels per frame <= the caller's limit) and against the bytes left before anything is
//! allocated, so a hostile file cannot make the loader allocate more than about its own
//! size; every restored frame passes the same validation as [`OnlineTrainer::offer`]; a
//! refused restore changes nothing.

use glam::{Quat, Vec3};
use gs_core::{Camera, Intrinsics};

use crate::keyframe::{Keyframe, KeyframeWindow, WindowConfig};
use crate::online::{Frame, OfferCounters, OnlineError, OnlineTrainer};

pub const STATE_MAGIC: &[u8; 8] = b"GSONLS01";

/// The settings a state was saved under: they must match the trainer that restores it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StateSettings {
    pub shuffle_seed: u64,
    pub window: WindowConfig,
    pub replay_capacity: usize,
    /// Rounds run when the state was saved.
    pub rounds: u64,
}

const F32_VALUES: u8 = 1;
const U8_FRACTIONS: u8 = 2;

fn unit_byte(v: f32) -> Option<u8> {
    let q = (v * 255.0).round();
    if !(0.0..=255.0).contains(&q) {
        return None;
    }
    let b = q as u8;
    (f32::from(b) / 255.0)
        .to_bits()
        .eq(&v.to_bits())
        .then_some(b)
}

fn put_values(out: &mut Vec<u8>, values: &[f32]) {
    let bytes: Option<Vec<u8>> = values.iter().map(|&v| unit_byte(v)).collect();
    match bytes {
        Some(b) => {
            out.push(U8_FRACTIONS);
            out.extend_from_slice(&b);
        }
        None => {
            out.push(F32_VALUES);
            for v in values {
                out.extend_from_slice(&v.to_le_bytes());
            }
        }
    }
}

fn put_frame(out: &mut Vec<u8>, f: &Frame) {
    let k = &f.camera.intrinsics;
    out.extend_from_slice(&f.id.to_le_bytes());
    out.extend_from_slice(&f.time_s.to_le_bytes());
    for v in [k.fx, k.fy, k.cx, k.cy] {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out.extend_from_slice(&k.width.to_le_bytes());
    out.extend_from_slice(&k.height.to_le_bytes());
    let r = f.camera.rotation;
    let t = f.camera.translation;
    let s = f.sun_dir_target;
    for v in [r.x, r.y, r.z, r.w, t.x, t.y, t.z, s.x, s.y, s.z] {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out.push(u8::from(f.eclipse));
    put_values(out, &f.image);
    match &f.mask {
        None => out.push(0),
        Some(m) => put_values(out, m),
    }
}

struct Reader<'a> {
    buf: &'a [u8],
    pos: usize,
}

fn bad(m: impl Into<String>) -> OnlineError {
    OnlineError::Config(format!("online state: {}", m.into()))
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize, what: &str) -> Result<&'a [u8], OnlineError> {
        if self.buf.len() - self.pos < n {
            return Err(bad(format!("truncated while reading {what}")));
        }
        let s = &self.buf[self.pos..self.pos + n];
        self.pos += n;
        Ok(s)
    }
    fn u8(&mut self, what: &str) -> Result<u8, OnlineError> {
        Ok(self.take(1, what)?[0])
    }
    fn u32(&mut self, what: &str) -> Result<u32, OnlineError> {
        let b = self.take(4, what)?;
        Ok(u32::from_le_bytes(b.try_into().expect("4 bytes")))
    }
    fn u64(&mut self, what: &str) -> Result<u64, OnlineError> {
        let b = self.take(8, what)?;
        Ok(u64::from_le_bytes(b.try_into().expect("8 bytes")))
    }
    fn f64(&mut self, what: &str) -> Result<f64, OnlineError> {
        Ok(f64::from_bits(self.u64(what)?))
    }
    fn f32(&mut self, what: &str) -> Result<f32, OnlineError> {
        Ok(f32::from_bits(self.u32(what)?))
    }
    /// `count` values in either encoding; the bytes are taken (bounds-checked) before the
    /// vector is allocated.
    fn values(&mut self, count: usize, what: &str) -> Result<Vec<f32>, OnlineError> {
        match self.u8(what)? {
            F32_VALUES => {
                let n = count
                    .checked_mul(4)
                    .ok_or_else(|| bad(format!("{what}: count overflows")))?;
                let raw = self.take(n, what)?;
                Ok(raw
                    .chunks_exact(4)
                    .map(|c| f32::from_le_bytes(c.try_into().expect("4 bytes")))
                    .collect())
            }
            U8_FRACTIONS => Ok(self
                .take(count, what)?
                .iter()
                .map(|&b| f32::from(b) / 255.0)
                .collect()),
            e => Err(bad(format!("{what}: unknown encoding {e}"))),
        }
    }
    fn frame(&mut self, max_pixels: usize) -> Result<Frame, OnlineError> {
        let id = self.u64("frame id")?;
        let time_s = self.f64("frame time")?;
        let (fx, fy, cx, cy) = (
            self.f32("fx")?,
            self.f32("fy")?,
            self.f32("cx")?,
            self.f32("cy")?,
        );
        let (width, height) = (self.u32("width")?, self.u32("height")?);
        let pixels = (width as usize)
            .checked_mul(height as usize)
            .filter(|&p| p <= max_pixels)
            .ok_or_else(|| {
                bad(format!(
                    "frame {id}: {width} x {height} exceeds the limit of {max_pixels} pixels"
                ))
            })?;
        let mut v = [0f32; 10];
        for x in &mut v {
            *x = self.f32("pose and Sun")?;
        }
        let eclipse = self.u8("eclipse")? != 0;
        let image = self.values(pixels * 3, "image")?;
        let mask = match self.buf.get(self.pos) {
            Some(0) => {
                self.pos += 1;
                None
            }
            _ => Some(self.values(pixels, "mask")?),
        };
        Ok(Frame {
            id,
            time_s,
            camera: Camera {
                intrinsics: Intrinsics {
                    fx,
                    fy,
                    cx,
                    cy,
                    width,
                    height,
                },
                rotation: Quat::from_xyzw(v[0], v[1], v[2], v[3]),
                translation: Vec3::new(v[4], v[5], v[6]),
            },
            sun_dir_target: Vec3::new(v[7], v[8], v[9]),
            image,
            mask,
            eclipse,
        })
    }
}

fn read_settings(r: &mut Reader) -> Result<StateSettings, OnlineError> {
    if r.take(8, "magic")? != STATE_MAGIC {
        return Err(bad("not an online trainer state (magic)"));
    }
    let shuffle_seed = r.u64("shuffle seed")?;
    let capacity = usize::try_from(r.u64("window capacity")?).unwrap_or(usize::MAX);
    let min_view_angle_deg = r.f64("min view angle")?;
    let replay_capacity = usize::try_from(r.u64("replay capacity")?).unwrap_or(usize::MAX);
    let rounds = r.u64("rounds")?;
    Ok(StateSettings {
        shuffle_seed,
        window: WindowConfig {
            capacity,
            min_view_angle_deg,
        },
        replay_capacity,
        rounds,
    })
}

/// The settings and round count a state was saved with (reads only its header).
pub fn peek_settings(bytes: &[u8]) -> Result<StateSettings, OnlineError> {
    read_settings(&mut Reader { buf: bytes, pos: 0 })
}

impl OnlineTrainer {
    /// Everything but the model (see the module docs); the model is gs-core's checkpoint.
    pub fn state_bytes(&self) -> Vec<u8> {
        let mut out = Vec::new();
        out.extend_from_slice(STATE_MAGIC);
        let c = &self.config;
        out.extend_from_slice(&c.shuffle_seed.to_le_bytes());
        out.extend_from_slice(&(c.window.capacity as u64).to_le_bytes());
        out.extend_from_slice(&c.window.min_view_angle_deg.to_le_bytes());
        out.extend_from_slice(&(c.replay_capacity as u64).to_le_bytes());
        out.extend_from_slice(&self.rounds.to_le_bytes());
        out.push(u8::from(self.last_trained_generation.is_some()));
        out.extend_from_slice(&self.last_trained_generation.unwrap_or(0).to_le_bytes());
        out.extend_from_slice(&self.window.generation().to_le_bytes());
        out.extend_from_slice(&self.evictions.to_le_bytes());
        let n = self.counters;
        for v in [
            n.offered,
            n.added,
            n.evicted,
            n.skipped_eclipse,
            n.skipped_empty_mask,
            n.skipped_unlit,
            n.skipped_view,
            n.skipped_duplicate,
        ] {
            out.extend_from_slice(&v.to_le_bytes());
        }
        out.extend_from_slice(&(self.window.len() as u64).to_le_bytes());
        for k in self.window.keyframes() {
            put_frame(&mut out, &k.payload);
        }
        out.extend_from_slice(&(self.replay.len() as u64).to_le_bytes());
        for f in &self.replay {
            put_frame(&mut out, f);
        }
        out
    }

    /// Restores what [`OnlineTrainer::state_bytes`] saved (the model is restored separately)
    /// from a state saved under this trainer's settings; frames of more than
    /// `max_frame_pixels` pixels are refused before allocating. On error nothing changes.
    pub fn restore_state(
        &mut self,
        bytes: &[u8],
        max_frame_pixels: usize,
    ) -> Result<(), OnlineError> {
        let mut r = Reader { buf: bytes, pos: 0 };
        let stored = read_settings(&mut r)?;
        let c = &self.config;
        if (stored.shuffle_seed, stored.window, stored.replay_capacity)
            != (c.shuffle_seed, c.window, c.replay_capacity)
        {
            return Err(bad(format!(
                "saved with shuffle seed {}, window {:?}, replay capacity {}; this trainer has \
                 {}, {:?}, {}",
                stored.shuffle_seed,
                stored.window,
                stored.replay_capacity,
                c.shuffle_seed,
                c.window,
                c.replay_capacity
            )));
        }
        let last_present = r.u8("last generation flag")? != 0;
        let last = r.u64("last generation")?;
        let generation = r.u64("window generation")?;
        let evictions = r.u64("evictions")?;
        let mut n = [0u64; 8];
        for v in &mut n {
            *v = r.u64("counters")?;
        }
        let read_frames = |r: &mut Reader, bound: usize, what: &str| {
            let count = usize::try_from(r.u64(what)?).unwrap_or(usize::MAX);
            if count > bound {
                return Err(bad(format!("{count} {what} frames, at most {bound}")));
            }
            let mut frames = Vec::with_capacity(count);
            for _ in 0..count {
                let frame = r.frame(max_frame_pixels)?;
                let view = self.validate(&frame)?;
                frames.push((frame, view));
            }
            Ok(frames)
        };
        let window = read_frames(&mut r, c.window.capacity, "window")?;
        let replay = read_frames(&mut r, c.replay_capacity, "replay")?;
        if r.pos != bytes.len() {
            return Err(bad(format!("{} bytes after the end", bytes.len() - r.pos)));
        }
        let keyframes = window
            .into_iter()
            .map(|(payload, view)| Keyframe {
                id: payload.id,
                view,
                payload,
            })
            .collect();
        self.window = KeyframeWindow::restore(self.config.window, keyframes, generation)?;
        self.replay = replay.into_iter().map(|(f, _)| f).collect();
        self.rounds = stored.rounds;
        self.last_trained_generation = last_present.then_some(last);
        self.evictions = evictions;
        self.counters = OfferCounters {
            offered: n[0],
            added: n[1],
            evicted: n[2],
            skipped_eclipse: n[3],
            skipped_empty_mask: n[4],
            skipped_unlit: n[5],
            skipped_view: n[6],
            skipped_duplicate: n[7],
        };
        Ok(())
    }
}

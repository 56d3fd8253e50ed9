//! Keyframe window of the paper: add on view change, keep the two newest, evict the most redundant.
//!
//! The window holds at most `capacity` keyframes (W, default 10), ordered newest first
//! (index 0 is the paper's I_1). Each keyframe carries an id, a unit view vector w (the
//! direction from the target to the camera, in the target body frame) and a payload.
//!
//! Rules (paper, "Keyframe Management Strategy"; DESIGN.md section 4):
//! 1. A frame is added when the window is empty or `w . w_1 < cos(min_view_angle)`.
//! 2. The two newest keyframes are never evicted.
//! 3. While more than `capacity` keyframes are held, the non-protected keyframe i whose
//!    score `d_i = max_{j non-protected, j != i} w_i . w_j` is largest (the most redundant)
//!    is evicted. Ties go to the older keyframe: the maximum cosine is always attained by a
//!    pair (both members get the same score), and the paper removes "the oldest" of them.
//!
//! Invariants: `len() <= capacity()`; view vectors are finite and unit length (checked by
//! [`ViewDirection::new`]); ids in the window are unique; the result of a sequence of offers
//! depends only on that sequence (no hashing, no randomness, fixed-order arithmetic).

use glam::DVec3;
use std::fmt;

/// The paper's W.
pub const DEFAULT_CAPACITY: usize = 10;
/// The paper's theta_VIEW, degrees.
pub const DEFAULT_MIN_VIEW_ANGLE_DEG: f64 = 10.0;
/// Number of newest keyframes that are never evicted (the paper's I_1 and I_2).
pub const PROTECTED_NEWEST: usize = 2;
/// View vectors shorter than this are treated as zero (no direction).
pub const MIN_VIEW_VECTOR_NORM: f64 = 1e-9;

/// Why a view vector or window setting was refused.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum KeyframeError {
    /// A component of the view vector is NaN or infinite.
    NonFiniteViewVector { vector: [f64; 3] },
    /// The view vector's norm is below [`MIN_VIEW_VECTOR_NORM`]: it has no direction.
    ZeroViewVector { norm: f64 },
    /// The capacity must be at least [`PROTECTED_NEWEST`].
    CapacityTooSmall { capacity: usize },
    /// The minimum view angle must be finite and in [0, 180] degrees.
    InvalidMinViewAngle { degrees: f64 },
    /// A restored window holds more keyframes than its capacity.
    TooManyKeyframes { count: usize, capacity: usize },
    /// A restored window holds two keyframes with the same id.
    DuplicateId { id: u64 },
}

impl fmt::Display for KeyframeError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::NonFiniteViewVector { vector } => {
                write!(f, "view vector {vector:?} has a non-finite component")
            }
            Self::ZeroViewVector { norm } => write!(
                f,
                "view vector norm {norm:e} is below {MIN_VIEW_VECTOR_NORM:e}: no direction"
            ),
            Self::CapacityTooSmall { capacity } => write!(
                f,
                "keyframe window capacity {capacity} is below the {PROTECTED_NEWEST} protected keyframes"
            ),
            Self::InvalidMinViewAngle { degrees } => {
                write!(f, "minimum view angle {degrees} deg is not in [0, 180]")
            }
            Self::TooManyKeyframes { count, capacity } => write!(
                f,
                "{count} keyframes do not fit a window of capacity {capacity}"
            ),
            Self::DuplicateId { id } => write!(f, "keyframe id {id} appears twice"),
        }
    }
}

impl std::error::Error for KeyframeError {}

/// A unit view vector (target to camera, target body frame). Valid by construction.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ViewDirection(DVec3);

impl ViewDirection {
    /// Normalises `vector`; refuses non-finite or (near-)zero vectors.
    pub fn new(vector: DVec3) -> Result<Self, KeyframeError> {
        if !vector.is_finite() {
            return Err(KeyframeError::NonFiniteViewVector {
                vector: vector.to_array(),
            });
        }
        let norm = vector.length();
        if norm.is_infinite() {
            // Huge finite components overflow the norm: rescale, then normalise.
            let scaled = vector / vector.abs().max_element();
            return Ok(Self(scaled.normalize()));
        }
        if norm < MIN_VIEW_VECTOR_NORM {
            return Err(KeyframeError::ZeroViewVector { norm });
        }
        Ok(Self(vector / norm))
    }

    /// For a vector read back from a checkpoint: one that is already unit (within 8 ulp of
    /// norm 1, as every [`ViewDirection::get`] is) is kept bit for bit, so that save, load,
    /// save gives the same bytes (dividing by a norm of 1 +- 1 ulp again moves the last
    /// bit); anything else is normalised as by [`ViewDirection::new`].
    pub fn restore(vector: DVec3) -> Result<Self, KeyframeError> {
        let norm = vector.length();
        if vector.is_finite() && (norm - 1.0).abs() <= 8.0 * f64::EPSILON {
            return Ok(Self(vector));
        }
        Self::new(vector)
    }

    pub fn get(self) -> DVec3 {
        self.0
    }

    /// Cosine of the angle between two view directions.
    pub fn cos_to(self, other: ViewDirection) -> f64 {
        self.0.dot(other.0)
    }
}

/// One keyframe: caller-chosen id (unique within the window), view direction, payload.
#[derive(Clone, Debug, PartialEq)]
pub struct Keyframe<P> {
    pub id: u64,
    pub view: ViewDirection,
    pub payload: P,
}

/// Window settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WindowConfig {
    /// W: the most keyframes held.
    pub capacity: usize,
    /// theta_VIEW: a frame is added when its view is more than this far from the newest keyframe's.
    pub min_view_angle_deg: f64,
}

impl Default for WindowConfig {
    fn default() -> Self {
        Self {
            capacity: DEFAULT_CAPACITY,
            min_view_angle_deg: DEFAULT_MIN_VIEW_ANGLE_DEG,
        }
    }
}

/// Why an offered frame was not added.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum NotAddedReason {
    /// `w . w_1 >= cos(theta_VIEW)`: the view barely moved since the newest keyframe.
    ViewTooClose { cos_to_newest: f64 },
    /// A keyframe with the same id is already in the window.
    DuplicateId,
}

/// What an offer did to the window.
#[derive(Clone, Debug, PartialEq)]
pub enum OfferOutcome<P> {
    /// The frame is now the newest keyframe; `evicted` is the keyframe removed to make room.
    Added { evicted: Option<Keyframe<P>> },
    /// The window is unchanged; the frame is handed back.
    NotAdded {
        frame: Keyframe<P>,
        reason: NotAddedReason,
    },
}

impl<P> OfferOutcome<P> {
    /// True when the window's composition changed (a training round is due).
    pub fn composition_changed(&self) -> bool {
        matches!(self, Self::Added { .. })
    }

    /// The id of the evicted keyframe, if any.
    pub fn evicted_id(&self) -> Option<u64> {
        match self {
            Self::Added { evicted } => evicted.as_ref().map(|k| k.id),
            Self::NotAdded { .. } => None,
        }
    }
}

/// The keyframe window, newest first.
#[derive(Clone, Debug)]
pub struct KeyframeWindow<P> {
    capacity: usize,
    min_view_angle_deg: f64,
    cos_min_view_angle: f64,
    /// Newest first.
    keyframes: Vec<Keyframe<P>>,
    /// Incremented on every composition change.
    generation: u64,
}

impl<P> KeyframeWindow<P> {
    pub fn new(config: WindowConfig) -> Result<Self, KeyframeError> {
        if config.capacity < PROTECTED_NEWEST {
            return Err(KeyframeError::CapacityTooSmall {
                capacity: config.capacity,
            });
        }
        let degrees = config.min_view_angle_deg;
        if !(0.0..=180.0).contains(&degrees) {
            return Err(KeyframeError::InvalidMinViewAngle { degrees });
        }
        Ok(Self {
            capacity: config.capacity,
            min_view_angle_deg: degrees,
            cos_min_view_angle: degrees.to_radians().cos(),
            keyframes: Vec::with_capacity(config.capacity + 1),
            generation: 0,
        })
    }

    /// Rebuilds a window from saved state (a checkpoint): keyframes newest first, and the
    /// generation counter it had. Checks what [`KeyframeWindow::offer`] guarantees: at most
    /// `capacity` keyframes, unique ids.
    pub fn restore(
        config: WindowConfig,
        keyframes_newest_first: Vec<Keyframe<P>>,
        generation: u64,
    ) -> Result<Self, KeyframeError> {
        let mut window = Self::new(config)?;
        let count = keyframes_newest_first.len();
        if count > window.capacity {
            return Err(KeyframeError::TooManyKeyframes {
                count,
                capacity: window.capacity,
            });
        }
        for (index, keyframe) in keyframes_newest_first.iter().enumerate() {
            if keyframes_newest_first[..index]
                .iter()
                .any(|k| k.id == keyframe.id)
            {
                return Err(KeyframeError::DuplicateId { id: keyframe.id });
            }
        }
        window.keyframes = keyframes_newest_first;
        window.generation = generation;
        Ok(window)
    }

    pub fn config(&self) -> WindowConfig {
        WindowConfig {
            capacity: self.capacity,
            min_view_angle_deg: self.min_view_angle_deg,
        }
    }

    pub fn capacity(&self) -> usize {
        self.capacity
    }

    pub fn len(&self) -> usize {
        self.keyframes.len()
    }

    pub fn is_empty(&self) -> bool {
        self.keyframes.is_empty()
    }

    /// Training starts once the window is full (paper, Experiments).
    pub fn is_full(&self) -> bool {
        self.keyframes.len() >= self.capacity
    }

    /// Counts composition changes since creation; a trainer runs a round when it moved.
    pub fn generation(&self) -> u64 {
        self.generation
    }

    /// Keyframes, newest first.
    pub fn keyframes(&self) -> &[Keyframe<P>] {
        &self.keyframes
    }

    /// Ids, newest first.
    pub fn ids(&self) -> Vec<u64> {
        self.keyframes.iter().map(|k| k.id).collect()
    }

    pub fn newest(&self) -> Option<&Keyframe<P>> {
        self.keyframes.first()
    }

    pub fn get(&self, id: u64) -> Option<&Keyframe<P>> {
        self.keyframes.iter().find(|k| k.id == id)
    }

    /// Empties the window (RESET_MODEL); counts as a composition change when it held anything.
    pub fn clear(&mut self) {
        if !self.keyframes.is_empty() {
            self.keyframes.clear();
            self.generation += 1;
        }
    }

    /// Would a frame with this view be added (ignoring id clashes)?
    pub fn accepts_view(&self, view: ViewDirection) -> bool {
        match self.keyframes.first() {
            None => true,
            Some(newest) => view.cos_to(newest.view) < self.cos_min_view_angle,
        }
    }

    /// Offers a frame: adds it if its view moved enough, then evicts down to capacity.
    pub fn offer(&mut self, frame: Keyframe<P>) -> OfferOutcome<P> {
        if self.keyframes.iter().any(|k| k.id == frame.id) {
            return OfferOutcome::NotAdded {
                frame,
                reason: NotAddedReason::DuplicateId,
            };
        }
        if let Some(newest) = self.keyframes.first() {
            let cos_to_newest = frame.view.cos_to(newest.view);
            if cos_to_newest >= self.cos_min_view_angle {
                return OfferOutcome::NotAdded {
                    frame,
                    reason: NotAddedReason::ViewTooClose { cos_to_newest },
                };
            }
        }
        self.keyframes.insert(0, frame);
        self.generation += 1;
        // At most one keyframe over capacity after a single insertion.
        let evicted = if self.keyframes.len() > self.capacity {
            most_redundant_index(&self.keyframes).map(|index| self.keyframes.remove(index))
        } else {
            None
        };
        OfferOutcome::Added { evicted }
    }
}

/// Index (into a newest-first slice) of the keyframe to evict; `None` when every
/// keyframe is protected.
///
/// Scores use only non-protected keyframes (j in [3, n] of the paper). With a single
/// non-protected keyframe there is nothing to compare with and it is the one evicted.
/// Ties resolve to the older keyframe (larger index), hence the `>=` while scanning
/// from newest to oldest.
pub fn most_redundant_index<P>(keyframes_newest_first: &[Keyframe<P>]) -> Option<usize> {
    let n = keyframes_newest_first.len();
    if n <= PROTECTED_NEWEST {
        return None;
    }
    let mut best_index = n - 1;
    let mut best_score = f64::NEG_INFINITY;
    for i in PROTECTED_NEWEST..n {
        let wi = keyframes_newest_first[i].view;
        let mut score = f64::NEG_INFINITY;
        for (j, other) in keyframes_newest_first
            .iter()
            .enumerate()
            .skip(PROTECTED_NEWEST)
        {
            if j != i {
                score = score.max(wi.cos_to(other.view));
            }
        }
        if score >= best_score {
            best_score = score;
            best_index = i;
        }
    }
    Some(best_index)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn dir_deg(azimuth_deg: f64) -> ViewDirection {
        let a = azimuth_deg.to_radians();
        ViewDirection::new(DVec3::new(a.cos(), a.sin(), 0.0)).unwrap()
    }

    fn frame(id: u64, azimuth_deg: f64) -> Keyframe<()> {
        Keyframe {
            id,
            view: dir_deg(azimuth_deg),
            payload: (),
        }
    }

    fn window(capacity: usize) -> KeyframeWindow<()> {
        KeyframeWindow::new(WindowConfig {
            capacity,
            ..WindowConfig::default()
        })
        .unwrap()
    }

    #[test]
    fn view_direction_rejects_bad_vectors_and_normalises() {
        assert!(matches!(
            ViewDirection::new(DVec3::new(f64::NAN, 0.0, 1.0)),
            Err(KeyframeError::NonFiniteViewVector { .. })
        ));
        assert!(matches!(
            ViewDirection::new(DVec3::new(0.0, f64::INFINITY, 1.0)),
            Err(KeyframeError::NonFiniteViewVector { .. })
        ));
        assert!(matches!(
            ViewDirection::new(DVec3::ZERO),
            Err(KeyframeError::ZeroViewVector { .. })
        ));
        assert!(matches!(
            ViewDirection::new(DVec3::splat(1e-12)),
            Err(KeyframeError::ZeroViewVector { .. })
        ));
        let v = ViewDirection::new(DVec3::new(0.0, 3.0, 4.0)).unwrap().get();
        assert!((v - DVec3::new(0.0, 0.6, 0.8)).length() < 1e-15);
        // Huge but finite components overflow `length`; still a valid direction.
        let v = ViewDirection::new(DVec3::new(f64::MAX, f64::MAX, 0.0))
            .unwrap()
            .get();
        assert!((v.length() - 1.0).abs() < 1e-12 && v.x > 0.7 && v.y > 0.7);
    }

    #[test]
    fn restored_unit_vectors_keep_their_bits() {
        // (0, 0.4472.., 0.8944..): normalising it a second time moves the last bit (found by
        // fuzzing the nearest-keyframe checkpoint: save, load, save differed).
        let v = ViewDirection::new(DVec3::new(0.0, 1.0, 2.0)).unwrap().get();
        assert_eq!(ViewDirection::restore(v).unwrap().get(), v);
        for i in 0..1000 {
            let a = f64::from(i) * 0.0123;
            let v = ViewDirection::new(DVec3::new(a.cos(), a.sin(), 0.3 * a))
                .unwrap()
                .get();
            assert_eq!(ViewDirection::restore(v).unwrap().get(), v);
        }
        let v = ViewDirection::restore(DVec3::new(0.0, 3.0, 4.0))
            .unwrap()
            .get();
        assert!((v - DVec3::new(0.0, 0.6, 0.8)).length() < 1e-15);
        assert!(ViewDirection::restore(DVec3::new(f64::NAN, 0.0, 1.0)).is_err());
    }

    #[test]
    fn config_is_validated() {
        assert_eq!(
            KeyframeWindow::<()>::new(WindowConfig {
                capacity: 1,
                ..WindowConfig::default()
            })
            .unwrap_err(),
            KeyframeError::CapacityTooSmall { capacity: 1 }
        );
        for degrees in [-1.0, 181.0, f64::NAN] {
            assert!(matches!(
                KeyframeWindow::<()>::new(WindowConfig {
                    capacity: 10,
                    min_view_angle_deg: degrees
                }),
                Err(KeyframeError::InvalidMinViewAngle { .. })
            ));
        }
    }

    #[test]
    fn adds_only_when_the_view_moved_more_than_the_threshold() {
        let mut w = window(10);
        assert!(w.offer(frame(1, 0.0)).composition_changed());
        // 9.9 degrees: too close.
        let out = w.offer(frame(2, 9.9));
        match out {
            OfferOutcome::NotAdded {
                frame,
                reason: NotAddedReason::ViewTooClose { cos_to_newest },
            } => {
                assert_eq!(frame.id, 2);
                assert!((cos_to_newest - 9.9f64.to_radians().cos()).abs() < 1e-12);
            }
            other => panic!("expected NotAdded, got {other:?}"),
        }
        // 10.1 degrees from the newest keyframe: added.
        assert!(w.offer(frame(3, 10.1)).composition_changed());
        // Compared with the newest keyframe (10.1), not the first: 19 deg is 8.9 deg away.
        assert!(!w.offer(frame(4, 19.0)).composition_changed());
        assert_eq!(w.ids(), vec![3, 1]);
        assert_eq!(w.generation(), 2);
    }

    #[test]
    fn duplicate_ids_are_handed_back() {
        let mut w = window(10);
        w.offer(frame(7, 0.0));
        let out = w.offer(frame(7, 90.0));
        assert!(matches!(
            out,
            OfferOutcome::NotAdded {
                reason: NotAddedReason::DuplicateId,
                ..
            }
        ));
        assert_eq!(w.len(), 1);
    }

    #[test]
    fn evicts_the_older_member_of_the_closest_pair() {
        // Capacity 4: protected = the two newest; azimuths chosen so that the
        // closest non-protected pair is (id 2 at 30 deg, id 3 at 45 deg).
        let mut w = window(4);
        for (id, az) in [(1, 0.0), (2, 30.0), (3, 45.0), (4, 100.0)] {
            assert!(matches!(
                w.offer(frame(id, az)),
                OfferOutcome::Added { evicted: None }
            ));
        }
        assert_eq!(w.ids(), vec![4, 3, 2, 1]);
        // Adding id 5 makes 5 keyframes; protected are 5 and 4; candidates 3 (45), 2 (30), 1 (0).
        // Scores: d3 = cos15, d2 = cos15, d1 = cos30 -> tie between 3 and 2, the older (2) goes.
        let out = w.offer(frame(5, 150.0));
        assert_eq!(out.evicted_id(), Some(2));
        assert_eq!(w.ids(), vec![5, 4, 3, 1]);
        // Next: candidates 4 (100), 3 (45), 1 (0): closest pair (3, 1) at 45 deg vs (4,3) 55 deg.
        let out = w.offer(frame(6, 200.0));
        assert_eq!(out.evicted_id(), Some(1));
        assert_eq!(w.ids(), vec![6, 5, 4, 3]);
    }

    #[test]
    fn protected_keyframes_do_not_count_as_neighbours() {
        // Capacity 3 -> one candidate set of size 2 at eviction time.
        let mut w = window(3);
        // id 1 at 0 deg, id 2 at 90, id 3 at 180: then id 4 at 95 (close to id 2).
        for (id, az) in [(1, 0.0), (2, 90.0), (3, 180.0)] {
            w.offer(frame(id, az));
        }
        // After adding 4: protected {4, 3}; candidates {2, 1} with the same score: the older (1) goes,
        // even though 2 is 5 degrees from the protected newest keyframe.
        let out = w.offer(frame(4, 95.0));
        assert_eq!(out.evicted_id(), Some(1));
        assert_eq!(w.ids(), vec![4, 3, 2]);
    }

    #[test]
    fn nothing_to_evict_among_protected_keyframes() {
        assert_eq!(most_redundant_index::<()>(&[]), None);
        assert_eq!(most_redundant_index(&[frame(1, 0.0), frame(2, 90.0)]), None);
        assert_eq!(
            most_redundant_index(&[frame(1, 0.0), frame(2, 90.0), frame(3, 0.0)]),
            Some(2)
        );
    }

    #[test]
    fn capacity_two_keeps_just_the_two_newest() {
        let mut w = window(2);
        for (id, az) in [(1, 0.0), (2, 90.0), (3, 180.0), (4, 270.0)] {
            w.offer(frame(id, az));
        }
        assert_eq!(w.ids(), vec![4, 3]);
    }

    #[test]
    fn clear_counts_as_a_change_only_when_non_empty() {
        let mut w = window(3);
        w.clear();
        assert_eq!(w.generation(), 0);
        w.offer(frame(1, 0.0));
        w.clear();
        assert_eq!(w.generation(), 2);
        assert!(w.is_empty());
        assert!(w.accepts_view(dir_deg(0.0)));
    }

    #[test]
    fn restore_continues_exactly_and_refuses_what_offer_never_builds() {
        let mut original = window(3);
        for (id, azimuth) in [(1, 0.0), (2, 30.0), (3, 60.0), (4, 90.0)] {
            original.offer(frame(id, azimuth));
        }
        let mut restored = KeyframeWindow::restore(
            original.config(),
            original.keyframes().to_vec(),
            original.generation(),
        )
        .unwrap();
        for (id, azimuth) in [(5, 120.0), (6, 125.0), (7, 200.0)] {
            assert_eq!(
                original.offer(frame(id, azimuth)),
                restored.offer(frame(id, azimuth))
            );
        }
        assert_eq!(original.ids(), restored.ids());
        assert_eq!(original.generation(), restored.generation());

        let four = vec![
            frame(1, 0.0),
            frame(2, 30.0),
            frame(3, 60.0),
            frame(4, 90.0),
        ];
        assert_eq!(
            KeyframeWindow::restore(original.config(), four, 4).unwrap_err(),
            KeyframeError::TooManyKeyframes {
                count: 4,
                capacity: 3
            }
        );
        let twins = vec![frame(1, 0.0), frame(1, 30.0)];
        assert_eq!(
            KeyframeWindow::restore(original.config(), twins, 2).unwrap_err(),
            KeyframeError::DuplicateId { id: 1 }
        );
    }
}

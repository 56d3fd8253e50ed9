//! The checkpoint policy of the trainer: which checkpoint to load, and when a save may
//! replace what is on disk.
//!
//! Files and crash safety are [`crate::checkpoint`]'s (two slots, newest and previous).
//! Policy, on top:
//! - a save is refused unless the model's own reader accepts the bytes (`Learner::inspect`),
//!   so nothing is written that a restart could not load;
//! - a save is refused when the model has fewer training rounds than the newest usable
//!   checkpoint on disk (the floor), so a restart without resume, or a failed resume, never
//!   replaces a trained model by an untrained one. RESET_MODEL, the explicit command that
//!   discards the model, lowers the floor to zero;
//! - loading tries the slots newest first and takes the first one the model accepts.
//!
//! Every outcome is a value the caller turns into a bus event; nothing here logs.

use crate::checkpoint::{self, SaveError};
use crate::learner::Learner;
use interfaces::messages::event_detail;
use std::path::{Path, PathBuf};

/// What a save did.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SaveOutcome {
    /// Written and verified; the model's round count.
    Saved { rounds: u64 },
    /// Not written; `detail` is the `CheckpointSaveFailed` event detail.
    Refused { detail: u32 },
    /// Writing failed (the slots on disk are as before); `detail` as above.
    Failed { detail: u32 },
}

/// What a load did.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum LoadOutcome {
    /// Loaded; `fell_back` when the newest slot was refused and the previous one used.
    Loaded { rounds: u64, fell_back: bool },
    /// No checkpoint file exists.
    Empty,
    /// Files exist but the model accepts none of them; the model is unchanged.
    Unusable,
}

impl LoadOutcome {
    /// The `CheckpointLoadFailed` event detail this outcome calls for, if any.
    pub(crate) fn failure_detail(&self) -> Option<u32> {
        match self {
            Self::Loaded {
                fell_back: true, ..
            } => Some(event_detail::LOAD_NEWEST_FAILED_PREVIOUS_USED),
            Self::Unusable => Some(event_detail::LOAD_NOTHING_USABLE),
            Self::Loaded { .. } | Self::Empty => None,
        }
    }
}

/// The trainer's checkpoints at one path.
#[derive(Debug)]
pub struct ModelStore {
    path: PathBuf,
    /// Rounds of the newest usable checkpoint on disk (0 after RESET_MODEL).
    floor_rounds: u64,
}

impl ModelStore {
    /// Opens the slots at `path`: removes a temporary a crash left behind and reads the
    /// floor from the newest checkpoint `learner` accepts.
    pub fn open(path: &Path, learner: &dyn Learner) -> Self {
        // A failure to remove it is harmless: the next save truncates it.
        let _ = checkpoint::remove_stale_temporary(path);
        let floor_rounds = checkpoint::slots(path)
            .iter()
            .find_map(|slot| match checkpoint::read(slot) {
                Ok(Some(bytes)) => learner.inspect(&bytes).ok(),
                _ => None,
            })
            .unwrap_or(0);
        Self {
            path: path.to_path_buf(),
            floor_rounds,
        }
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Rounds below which a save is refused.
    pub fn floor_rounds(&self) -> u64 {
        self.floor_rounds
    }

    /// RESET_MODEL: the operator discarded the model, so the next save may replace the
    /// trained one on disk (which then stays as the previous slot until the save after).
    pub(crate) fn allow_replacing(&mut self) {
        self.floor_rounds = 0;
    }

    /// Saves the model as the newest checkpoint under the policy above.
    pub fn save(&mut self, learner: &dyn Learner) -> SaveOutcome {
        let bytes = learner.save();
        let rounds = match learner.inspect(&bytes) {
            Ok(rounds) => rounds,
            Err(_) => {
                return SaveOutcome::Refused {
                    detail: event_detail::SAVE_REFUSED_UNREADABLE,
                }
            }
        };
        if rounds < self.floor_rounds {
            return SaveOutcome::Refused {
                detail: event_detail::SAVE_REFUSED_FEWER_ROUNDS,
            };
        }
        let usable = |b: &[u8]| learner.inspect(b).is_ok();
        match checkpoint::save_rotating(&self.path, &bytes, usable) {
            Ok(()) => {
                self.floor_rounds = rounds;
                SaveOutcome::Saved { rounds }
            }
            Err(SaveError::Io(_)) => SaveOutcome::Failed {
                detail: event_detail::SAVE_IO,
            },
            Err(SaveError::Verify(_)) => SaveOutcome::Failed {
                detail: event_detail::SAVE_VERIFY_FAILED,
            },
        }
    }

    /// Loads the newest slot `learner` accepts.
    pub(crate) fn load_newest(&self, learner: &mut dyn Learner) -> LoadOutcome {
        let mut found_any = false;
        for (index, slot) in checkpoint::slots(&self.path).iter().enumerate() {
            let Ok(Some(bytes)) = checkpoint::read(slot) else {
                // Missing or unreadable: an unreadable file counts as damaged.
                found_any |= slot.exists();
                continue;
            };
            found_any = true;
            if learner.load(&bytes).is_ok() {
                return LoadOutcome::Loaded {
                    rounds: u64::from(learner.stats().rounds),
                    fell_back: index > 0,
                };
            }
        }
        if found_any {
            LoadOutcome::Unusable
        } else {
            LoadOutcome::Empty
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::learner::{
        LearnerError, LearnerStats, ObservedFrame, OfferResult, PredictedImage, RoundSummary,
        ViewRequest,
    };

    /// A model that is just a round count; `unreadable` makes its bytes fail `inspect`.
    #[derive(Default)]
    struct Rounds {
        rounds: u64,
        unreadable: bool,
    }

    impl Learner for Rounds {
        fn offer(&mut self, _: &ObservedFrame) -> OfferResult {
            OfferResult::NotAdded
        }
        fn run_round_if_due(&mut self) -> Result<Option<RoundSummary>, LearnerError> {
            Ok(None)
        }
        fn predict(&self, _: &ViewRequest) -> Result<PredictedImage, LearnerError> {
            Err(LearnerError::NothingToRender)
        }
        fn reset(&mut self) -> Result<(), LearnerError> {
            self.rounds = 0;
            Ok(())
        }
        fn save(&self) -> Vec<u8> {
            let mut out = b"ROUNDS".to_vec();
            out.extend_from_slice(&self.rounds.to_le_bytes());
            if self.unreadable {
                out.push(0xff);
            }
            out
        }
        fn load(&mut self, bytes: &[u8]) -> Result<(), LearnerError> {
            self.rounds = self.inspect(bytes)?;
            Ok(())
        }
        fn inspect(&self, bytes: &[u8]) -> Result<u64, LearnerError> {
            match bytes.strip_prefix(b"ROUNDS") {
                Some(rest) if rest.len() == 8 => Ok(u64::from_le_bytes(rest.try_into().unwrap())),
                _ => Err(LearnerError::BadCheckpoint("not a round count".into())),
            }
        }
        fn stats(&self) -> LearnerStats {
            LearnerStats {
                rounds: u32::try_from(self.rounds).unwrap_or(u32::MAX),
                ..LearnerStats::default()
            }
        }
    }

    #[test]
    fn saves_follow_the_policy_and_loads_fall_back() {
        let dir = std::env::temp_dir().join(format!("fsw-store-{}", std::process::id()));
        let path = dir.join("model.bin");
        let mut model = Rounds {
            rounds: 5,
            ..Rounds::default()
        };
        let mut store = ModelStore::open(&path, &model);
        assert_eq!(
            store.load_newest(&mut Rounds::default()),
            LoadOutcome::Empty
        );
        assert_eq!(store.save(&model), SaveOutcome::Saved { rounds: 5 });
        model.unreadable = true;
        let unreadable = SaveOutcome::Refused {
            detail: event_detail::SAVE_REFUSED_UNREADABLE,
        };
        assert_eq!(store.save(&model), unreadable);
        model.unreadable = false;
        model.rounds = 2;
        let fewer = SaveOutcome::Refused {
            detail: event_detail::SAVE_REFUSED_FEWER_ROUNDS,
        };
        assert_eq!(store.save(&model), fewer);
        // A new store (a restart) reads the floor back from disk.
        let mut store = ModelStore::open(&path, &model);
        assert_eq!(store.floor_rounds(), 5);
        assert_eq!(store.save(&model), fewer);
        store.allow_replacing();
        assert_eq!(store.save(&model), SaveOutcome::Saved { rounds: 2 });
        let mut loaded = Rounds::default();
        let newest = LoadOutcome::Loaded {
            rounds: 2,
            fell_back: false,
        };
        assert_eq!(store.load_newest(&mut loaded), newest);
        // The newest damaged: the previous one (rounds 5) loads, reported as a fallback.
        std::fs::write(&path, b"damaged").unwrap();
        let fallback = store.load_newest(&mut loaded);
        assert_eq!(
            fallback,
            LoadOutcome::Loaded {
                rounds: 5,
                fell_back: true
            }
        );
        assert_eq!(
            fallback.failure_detail(),
            Some(event_detail::LOAD_NEWEST_FAILED_PREVIOUS_USED)
        );
        std::fs::write(checkpoint::previous_path(&path), b"damaged").unwrap();
        assert_eq!(store.load_newest(&mut loaded), LoadOutcome::Unusable);
        assert_eq!(loaded.rounds, 5, "a failed load leaves the model unchanged");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}

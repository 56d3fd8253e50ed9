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
pub enum LoadOutcome {
    /// Loaded; `fell_back` when the newest slot was refused and the previous one used.
    Loaded { rounds: u64, fell_back: bool },
    /// No checkpoint file exists.
    Empty,
    /// Files exist but the model accepts none of them; the model is unchanged.
    Unusable,
}

impl LoadOutcome {
    /// The `CheckpointLoadFailed` event detail this outcome calls for, if any.
    pub fn failure_detail(&self) -> Option<u32> {
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
    pub fn allow_replacing(&mut self) {
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
    pub fn load_newest(&self, learner: &mut dyn Learner) -> LoadOutcome {
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

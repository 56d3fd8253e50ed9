//! Experiments of the paper on simulated data: the results table (configurations a-d on each
//! target through the online procedure, evaluated on the evaluation views) and the demo.
//!
//! Modules: [`preset`] (config/presets/*.toml), [`data`] (scenes rendered into memory) with
//! [`cache`] (their on-disk cache), [`evaluate`] (metrics on evaluation views), [`ladder`] (the
//! accuracy ladder every report prints), [`table`]
//! (CSV and Markdown writers), [`figure`] (comparison grids).
//!
//! Invariants: frames reach the online trainer in time order; evaluation views never train;
//! every number written comes from a run in this process (or a cache of rendered images whose
//! key matches), never from a constant.

pub mod ablation;
pub mod ablation_init;
pub mod cache;
pub mod data;
pub mod demo;
pub mod evaluate;
pub mod figure;
pub mod ladder;
pub mod pareto;
pub mod preset;
pub mod runner;
pub mod shadow_study;
pub mod skips;
pub mod table;
pub mod table_job;

use crate::dataset::DatasetError;
use crate::scenario::ScenarioError;
use gs_core::sunaware::SunAwareError;
use gs_online::online::OnlineError;
use std::fmt;
use std::path::{Path, PathBuf};

/// Why an experiment could not run.
#[derive(Debug)]
pub enum ExperimentError {
    Dataset(DatasetError),
    Preset(preset::PresetError),
    Online(OnlineError),
    Io { path: PathBuf, message: String },
    Invalid(String),
}

impl fmt::Display for ExperimentError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ExperimentError::Dataset(e) => write!(f, "{e}"),
            ExperimentError::Preset(e) => write!(f, "{e}"),
            ExperimentError::Online(e) => write!(f, "online training: {e}"),
            ExperimentError::Io { path, message } => {
                write!(f, "cannot write {}: {message}", path.display())
            }
            ExperimentError::Invalid(m) => write!(f, "{m}"),
        }
    }
}

impl std::error::Error for ExperimentError {}

impl ExperimentError {
    /// A failed write (or read) of `path`.
    pub(crate) fn io(path: &Path, e: impl fmt::Display) -> Self {
        ExperimentError::Io {
            path: path.to_path_buf(),
            message: e.to_string(),
        }
    }
}

/// Writes a text result file (CSV, Markdown), replacing any existing one.
pub(crate) fn write_text(path: &Path, text: &str) -> Result<(), ExperimentError> {
    std::fs::write(path, text).map_err(|e| ExperimentError::io(path, e))
}

impl From<DatasetError> for ExperimentError {
    fn from(e: DatasetError) -> Self {
        ExperimentError::Dataset(e)
    }
}

impl From<ScenarioError> for ExperimentError {
    fn from(e: ScenarioError) -> Self {
        ExperimentError::Dataset(DatasetError::Scenario(e))
    }
}

impl From<preset::PresetError> for ExperimentError {
    fn from(e: preset::PresetError) -> Self {
        ExperimentError::Preset(e)
    }
}

impl From<OnlineError> for ExperimentError {
    fn from(e: OnlineError) -> Self {
        ExperimentError::Online(e)
    }
}

impl From<SunAwareError> for ExperimentError {
    fn from(e: SunAwareError) -> Self {
        ExperimentError::Online(OnlineError::Model(e))
    }
}

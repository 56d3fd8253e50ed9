//! Checkpoint files written atomically, in two slots: a crash at any instant leaves at
//! least one complete checkpoint that was verified after writing.
//!
//! Slots: `<path>` holds the newest checkpoint, `<path>.prev` the one before it. A save
//! ([`save_rotating`]) writes `<path>.tmp`, fsyncs it and reads it back; only then does the
//! current newest (when the caller's check accepts it) become `<path>.prev`, the temporary
//! is renamed to `<path>`, the directory is fsynced, and `<path>` is read back and compared
//! with what was meant to be written. So the previous checkpoint is never touched before the
//! new one is complete on disk, and a damaged newest never pushes a good previous out. A
//! failed save removes its temporary; [`remove_stale_temporary`] removes one a crash left.
//! The bytes are the learner's own format (which carries its magic and checksum); this
//! module only moves them safely. Loading tries [`slots`] newest first.

use std::fmt;
use std::fs::{self, File};
use std::io::{self, Write};
use std::path::{Path, PathBuf};

#[derive(Debug)]
pub struct CheckpointIoError {
    pub operation: &'static str,
    pub path: PathBuf,
    pub source: io::Error,
}

impl fmt::Display for CheckpointIoError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{} {}: {}",
            self.operation,
            self.path.display(),
            self.source
        )
    }
}

impl std::error::Error for CheckpointIoError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        Some(&self.source)
    }
}

fn sibling(path: &Path, suffix: &str) -> PathBuf {
    let mut name = path.file_name().unwrap_or_default().to_os_string();
    name.push(suffix);
    path.with_file_name(name)
}

/// `<path>.tmp`: where a save writes before renaming.
pub fn temporary_path(path: &Path) -> PathBuf {
    sibling(path, ".tmp")
}

/// `<path>.prev`: the slot of the checkpoint before the newest.
pub(crate) fn previous_path(path: &Path) -> PathBuf {
    sibling(path, ".prev")
}

/// The two slots, newest first.
pub fn slots(path: &Path) -> [PathBuf; 2] {
    [path.to_path_buf(), previous_path(path)]
}

/// Why a rotating save failed; the previous checkpoints are intact in every case.
#[derive(Debug)]
pub enum SaveError {
    Io(CheckpointIoError),
    /// The file read back differs from the bytes written.
    Verify(PathBuf),
}

impl fmt::Display for SaveError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Io(e) => write!(f, "{e}"),
            Self::Verify(path) => write!(
                f,
                "{} read back differs from what was written",
                path.display()
            ),
        }
    }
}

impl std::error::Error for SaveError {}

impl From<CheckpointIoError> for SaveError {
    fn from(e: CheckpointIoError) -> Self {
        Self::Io(e)
    }
}

/// Removes a temporary a crash left behind; true when there was one.
pub fn remove_stale_temporary(path: &Path) -> Result<bool, CheckpointIoError> {
    let temporary = temporary_path(path);
    match fs::remove_file(&temporary) {
        Ok(()) => Ok(true),
        Err(e) if e.kind() == io::ErrorKind::NotFound => Ok(false),
        Err(source) => Err(CheckpointIoError {
            operation: "remove stale temporary",
            path: temporary,
            source,
        }),
    }
}

fn verify_file(path: &Path, bytes: &[u8]) -> Result<(), SaveError> {
    match read(path)? {
        Some(back) if back == bytes => Ok(()),
        _ => Err(SaveError::Verify(path.to_path_buf())),
    }
}

/// Saves `bytes` as the newest checkpoint; the current newest becomes the previous one when
/// `usable` accepts it (otherwise the previous slot is left as it is).
pub fn save_rotating(
    path: &Path,
    bytes: &[u8],
    usable: impl Fn(&[u8]) -> bool,
) -> Result<(), SaveError> {
    let temporary = temporary_path(path);
    let written = write_synced(&temporary, bytes)
        .map_err(SaveError::from)
        .and_then(|()| verify_file(&temporary, bytes));
    if let Err(e) = written {
        let _ = fs::remove_file(&temporary);
        return Err(e);
    }
    let keep_current = matches!(read(path), Ok(Some(current)) if usable(&current));
    if keep_current {
        let previous = previous_path(path);
        if let Err(source) = fs::rename(path, &previous) {
            let _ = fs::remove_file(&temporary);
            return Err(SaveError::Io(CheckpointIoError {
                operation: "rename into",
                path: previous,
                source,
            }));
        }
    }
    if let Err(source) = fs::rename(&temporary, path) {
        let _ = fs::remove_file(&temporary);
        return Err(SaveError::Io(CheckpointIoError {
            operation: "rename into",
            path: path.to_path_buf(),
            source,
        }));
    }
    sync_directory(path)?;
    verify_file(path, bytes)
}

fn directory_of(path: &Path) -> PathBuf {
    match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    }
}

/// Writes and fsyncs `path` (creating parent directories); no rename.
fn write_synced(path: &Path, bytes: &[u8]) -> Result<(), CheckpointIoError> {
    let error = |operation| {
        let path = path.to_path_buf();
        move |source| CheckpointIoError {
            operation,
            path,
            source,
        }
    };
    let directory = directory_of(path);
    fs::create_dir_all(&directory).map_err(|source| CheckpointIoError {
        operation: "create directory",
        path: directory.clone(),
        source,
    })?;
    let mut file = File::create(path).map_err(error("create"))?;
    file.write_all(bytes).map_err(error("write"))?;
    file.sync_all().map_err(error("fsync"))
}

/// Fsyncs the directory holding `path`, so that a rename survives a power cut.
fn sync_directory(path: &Path) -> Result<(), CheckpointIoError> {
    let directory = directory_of(path);
    File::open(&directory)
        .and_then(|d| d.sync_all())
        .map_err(|source| CheckpointIoError {
            operation: "fsync directory",
            path: directory,
            source,
        })
}

/// Reads a checkpoint; `Ok(None)` when there is none.
pub fn read(path: &Path) -> Result<Option<Vec<u8>>, CheckpointIoError> {
    match fs::read(path) {
        Ok(bytes) => Ok(Some(bytes)),
        Err(e) if e.kind() == io::ErrorKind::NotFound => Ok(None),
        Err(source) => Err(CheckpointIoError {
            operation: "read",
            path: path.to_path_buf(),
            source,
        }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn good(bytes: &[u8]) -> bool {
        bytes.starts_with(b"ok")
    }

    #[test]
    fn saves_rotate_the_newest_into_the_previous_slot() {
        let dir = std::env::temp_dir().join(format!("fsw-ckpt-{}", std::process::id()));
        let path = dir.join("sub/model.bin");
        let previous = previous_path(&path);
        assert!(read(&path).unwrap().is_none());
        save_rotating(&path, b"ok first", good).unwrap();
        assert!(read(&previous).unwrap().is_none(), "nothing to keep yet");
        save_rotating(&path, b"ok second", good).unwrap();
        assert_eq!(read(&path).unwrap().unwrap(), b"ok second");
        assert_eq!(read(&previous).unwrap().unwrap(), b"ok first");
        // A damaged newest is replaced, never rotated over the good previous one.
        fs::write(&path, b"damaged").unwrap();
        save_rotating(&path, b"ok third", good).unwrap();
        assert_eq!(read(&path).unwrap().unwrap(), b"ok third");
        assert_eq!(read(&previous).unwrap().unwrap(), b"ok first");
        assert!(!temporary_path(&path).exists());
        assert_eq!(slots(&path), [path.clone(), previous.clone()]);
        fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_failed_save_removes_its_temporary_and_keeps_both_slots() {
        let dir = std::env::temp_dir().join(format!("fsw-ckpt-fail-{}", std::process::id()));
        let path = dir.join("model.bin");
        save_rotating(&path, b"ok one", good).unwrap();
        save_rotating(&path, b"ok two", good).unwrap();
        // The newest slot is a directory: the final rename fails after the rotation
        // step, whose rename of a directory over a file fails first; nothing is lost.
        let blocked = dir.join("blocked.bin");
        fs::create_dir_all(blocked.join("inside")).unwrap();
        assert!(save_rotating(&blocked, b"ok x", good).is_err());
        assert!(!temporary_path(&blocked).exists(), "temporary left behind");
        let unwritable = dir.join("model.bin/inside");
        assert!(save_rotating(&unwritable, b"ok x", good).is_err());
        assert_eq!(read(&path).unwrap().unwrap(), b"ok two");
        assert_eq!(read(&previous_path(&path)).unwrap().unwrap(), b"ok one");
        fs::write(temporary_path(&path), b"half").unwrap();
        assert!(remove_stale_temporary(&path).unwrap());
        assert!(!remove_stale_temporary(&path).unwrap());
        fs::remove_dir_all(&dir).unwrap();
    }
}

//! Checkpoint files written atomically: a reader sees the old file or the new one, never half.
//!
//! Write to `<path>.tmp` in the same directory, fsync it, rename over `<path>`, then fsync the
//! directory so the rename itself survives a power cut. The bytes are the learner's own
//! format (which carries its magic and checksum); this module only moves them safely.

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

fn temporary_path(path: &Path) -> PathBuf {
    let mut name = path.file_name().unwrap_or_default().to_os_string();
    name.push(".tmp");
    path.with_file_name(name)
}

/// Atomically replaces `path` with `bytes` (creating parent directories).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), CheckpointIoError> {
    let error = |operation, path: &Path| {
        let path = path.to_path_buf();
        move |source| CheckpointIoError {
            operation,
            path,
            source,
        }
    };
    let directory = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    fs::create_dir_all(&directory).map_err(error("create directory", &directory))?;
    let temporary = temporary_path(path);
    let mut file = File::create(&temporary).map_err(error("create", &temporary))?;
    file.write_all(bytes).map_err(error("write", &temporary))?;
    file.sync_all().map_err(error("fsync", &temporary))?;
    drop(file);
    fs::rename(&temporary, path).map_err(error("rename into", path))?;
    File::open(&directory)
        .and_then(|d| d.sync_all())
        .map_err(error("fsync directory", &directory))?;
    Ok(())
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

    #[test]
    fn replaces_the_file_and_leaves_no_temporary() {
        let dir = std::env::temp_dir().join(format!("fsw-ckpt-{}", std::process::id()));
        let path = dir.join("sub/model.bin");
        assert!(read(&path).unwrap().is_none());
        write_atomic(&path, b"first").unwrap();
        write_atomic(&path, b"second").unwrap();
        assert_eq!(read(&path).unwrap().unwrap(), b"second");
        assert!(!temporary_path(&path).exists());
        let blocked = dir.join("sub/model.bin/inside");
        assert!(write_atomic(&blocked, b"x").is_err(), "a file as directory");
        fs::remove_dir_all(&dir).unwrap();
    }
}

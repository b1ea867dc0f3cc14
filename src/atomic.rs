//! Atomic file writing, for every layer that writes state or results: the bytes go to a temporary
//! file in the same directory (`.NAME.tmp-PID`), which is flushed to disk (fsync) and renamed over the
//! destination, and the rename is made durable by syncing the directory. A reader, a crash or a full
//! disk never leaves a partial file under the final name.

use std::io::Write;
use std::path::{Path, PathBuf};

/// An atomic write failed; names the destination.
#[derive(Debug, thiserror::Error)]
#[error("cannot write {path}")]
pub struct AtomicWriteError {
    /// The destination file.
    pub path: PathBuf,
    /// The I/O error (creating, writing, syncing or renaming).
    #[source]
    pub source: std::io::Error,
}

/// Whether a file name is one of [`write_atomic`]'s temporary files (`.NAME.tmp-PID`): left behind
/// only when the writing process died before its rename, so it never holds a complete result.
pub fn is_atomic_temp(name: &str) -> bool {
    name.starts_with('.') && name.contains(".tmp-")
}

/// Write `bytes` to `path` atomically (temporary file in the same directory, fsync, rename).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), AtomicWriteError> {
    let io = |source| AtomicWriteError { path: path.to_path_buf(), source };
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| "out".into());
    let tmp = dir.join(format!(".{name}.tmp-{}", std::process::id()));
    let result = (|| {
        let mut f = std::fs::File::create(&tmp)?;
        f.write_all(bytes)?;
        f.sync_all()?;
        drop(f);
        std::fs::rename(&tmp, path)?;
        if let Ok(d) = std::fs::File::open(&dir) {
            // Persist the rename; not every platform supports syncing a directory.
            let _ = d.sync_all();
        }
        Ok(())
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result.map_err(io)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn writes_replace_whole_files_and_leave_no_temporary() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("state.json");
        write_atomic(&path, b"one").expect("write");
        write_atomic(&path, b"two, longer").expect("rewrite");
        assert_eq!(std::fs::read(&path).expect("read"), b"two, longer");
        let names: Vec<String> = std::fs::read_dir(dir.path())
            .expect("list")
            .flatten()
            .map(|e| e.file_name().to_string_lossy().into())
            .collect();
        assert_eq!(names, vec!["state.json".to_owned()]);
        let err = write_atomic(&dir.path().join("missing/dir/file"), b"x").expect_err("no such directory");
        assert!(err.to_string().contains("missing/dir/file"), "{err}");
        assert!(is_atomic_temp(".report.json.tmp-1") && !is_atomic_temp("pos_000.png"));
    }
}

//! Atomic file writing, for every layer that writes state or results: the bytes go to a temporary
//! file in the same directory (`.NAME.tmp-PID`), which is flushed to disk (fsync) and renamed over the
//! destination, and the rename is made durable by syncing the directory. A reader, a crash or a full
//! disk never leaves a partial file under the final name.

use std::fs::File;
use std::io::{BufWriter, Write};
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
    // The bytes are whole already: no buffer (a write of them goes straight to the file).
    write_atomic_buffered(path, 0, |w| w.write_all(bytes))
}

/// Write `path` atomically from `produce`, which streams the file's bytes into a buffered writer
/// on the temporary file, so a large file is never held whole in memory. An error from `produce`
/// (or from creating, flushing, syncing or renaming) removes the temporary file and leaves any
/// previous file under `path` as it was.
pub fn write_atomic_with(
    path: &Path,
    produce: impl FnOnce(&mut BufWriter<File>) -> std::io::Result<()>,
) -> Result<(), AtomicWriteError> {
    write_atomic_buffered(path, WRITE_BUFFER, produce)
}

/// [`write_atomic_with`] through a buffer of `capacity` bytes.
fn write_atomic_buffered(
    path: &Path,
    capacity: usize,
    produce: impl FnOnce(&mut BufWriter<File>) -> std::io::Result<()>,
) -> Result<(), AtomicWriteError> {
    let io = |source| AtomicWriteError { path: path.to_path_buf(), source };
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| "out".into());
    let tmp = dir.join(format!(".{name}.tmp-{}", std::process::id()));
    let result = (|| {
        let mut w = BufWriter::with_capacity(capacity, File::create(&tmp)?);
        produce(&mut w)?;
        let f = w.into_inner().map_err(|e| e.into_error())?;
        f.sync_all()?;
        drop(f);
        std::fs::rename(&tmp, path)?;
        if let Ok(d) = File::open(&dir) {
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

/// Bytes [`write_atomic_with`] buffers before each write to the file.
const WRITE_BUFFER: usize = 1 << 20;

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

    #[test]
    fn a_stream_that_fails_midway_leaves_the_previous_file_and_no_temporary() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("voxels.ply");
        write_atomic(&path, b"previous").expect("write");
        // More than the buffer holds, so part of it reached the temporary file before the error.
        let err = write_atomic_with(&path, |w| {
            w.write_all(&vec![7u8; 3 * WRITE_BUFFER])?;
            Err(std::io::Error::new(std::io::ErrorKind::StorageFull, "disk full"))
        })
        .expect_err("the producer failed");
        assert!(err.to_string().contains("voxels.ply"), "{err}");
        assert_eq!(err.source.kind(), std::io::ErrorKind::StorageFull);
        assert_eq!(std::fs::read(&path).expect("read"), b"previous");
        assert_eq!(std::fs::read_dir(dir.path()).expect("list").count(), 1);
        write_atomic_with(&path, |w| {
            for i in 0..100_000u32 {
                w.write_all(&i.to_le_bytes())?;
            }
            Ok(())
        })
        .expect("stream");
        let bytes = std::fs::read(&path).expect("read");
        assert_eq!(bytes.len(), 400_000);
        assert_eq!(&bytes[399_996..], &99_999u32.to_le_bytes());
    }
}

//! The exclusive lock on a state directory: one daemon per store. Two daemons on one directory
//! would each take the other's live scan for interrupted and write into the same scan.
//!
//! `STATE_DIR/scanrigd.lock` is held with `flock(LOCK_EX | LOCK_NB)` for the daemon's life and
//! holds the holder's pid (for the message a second daemon prints). The kernel releases the lock
//! when the process dies, however it dies, so a stale file never blocks a restart.

use std::io::{Read, Seek, Write};
use std::os::fd::AsRawFd;
use std::path::{Path, PathBuf};

/// Why the state directory could not be locked.
#[derive(Debug, thiserror::Error)]
pub enum LockError {
    /// Another process holds the lock.
    #[error(
        "the state directory {dir} is in use by another scanrigd (pid {pid}); stop it or choose another --state-dir"
    )]
    Held {
        /// The state directory.
        dir: PathBuf,
        /// The holder's pid as it wrote it (`unknown` when unreadable).
        pid: String,
    },
    /// The lock file could not be created, locked or written.
    #[error("cannot lock {path}")]
    Io {
        /// The lock file.
        path: PathBuf,
        /// The error.
        #[source]
        source: std::io::Error,
    },
}

/// The held lock; released when dropped (or when the process exits).
#[derive(Debug)]
pub struct StateLock {
    _file: std::fs::File,
    path: PathBuf,
}

impl StateLock {
    /// The lock file's path.
    pub fn path(&self) -> &Path {
        &self.path
    }
}

/// Take the exclusive lock on `state_dir` (created if missing), or say who holds it.
pub fn lock(state_dir: &Path) -> Result<StateLock, LockError> {
    let path = state_dir.join("scanrigd.lock");
    let io = |source| LockError::Io { path: path.clone(), source };
    std::fs::create_dir_all(state_dir).map_err(io)?;
    let mut file =
        std::fs::OpenOptions::new().read(true).write(true).create(true).truncate(false).open(&path).map_err(io)?;
    // SAFETY: flock on a descriptor we own; no memory is passed.
    let rc = unsafe { libc::flock(file.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) };
    if rc != 0 {
        let err = std::io::Error::last_os_error();
        if err.raw_os_error() == Some(libc::EWOULDBLOCK) {
            let mut text = String::new();
            let _ = file.read_to_string(&mut text);
            let pid = text.trim();
            let pid = if pid.is_empty() { "unknown".to_owned() } else { pid.to_owned() };
            return Err(LockError::Held { dir: state_dir.to_owned(), pid });
        }
        return Err(io(err));
    }
    file.set_len(0).map_err(io)?;
    file.rewind().map_err(io)?;
    writeln!(file, "{}", std::process::id()).map_err(io)?;
    file.sync_all().map_err(io)?;
    Ok(StateLock { _file: file, path })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_second_lock_on_one_directory_is_refused_and_names_the_holder() {
        let dir = tempfile::tempdir().expect("tempdir");
        let first = lock(dir.path()).expect("first lock");
        // flock locks belong to the open file description: a second open in this process conflicts.
        match lock(dir.path()) {
            Err(LockError::Held { pid, .. }) => assert_eq!(pid, std::process::id().to_string()),
            other => panic!("second lock not refused: {other:?}"),
        }
        drop(first);
        lock(dir.path()).expect("lock after release");
    }
}

//! Replication of finished scans to object storage: the upload queue, persisted on disk, and the
//! replication state each scan's status shows. The uploader itself ([`uploader`], feature `s3`)
//! runs as a supervised task of the daemon.
//!
//! # The queue
//! `STATE_DIR/replication/queue.json` holds one entry per scan to replicate, written atomically
//! ([`crate::atomic::write_atomic`]) at every change: enqueued when the scan completes (and, at
//! start, for every complete scan not in it yet, so a crash between the two loses nothing), then
//! its file list with sizes, each file marked `verified` once it is uploaded and read back equal;
//! the entry is `replicated` once the manifest is uploaded and verified too. After a network
//! outage, a refused credential, a full bucket or a daemon crash the uploader picks up the entry
//! where it stopped: verified files are not uploaded again; a file cut off mid-upload is uploaded
//! again whole (to the same key, so nothing is duplicated).

#[cfg(feature = "s3")]
pub mod uploader;

use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex};

use serde::{Deserialize, Serialize};

use crate::atomic::{write_atomic, AtomicWriteError};

use super::metrics::Metrics;

/// Where a scan's replication is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Phase {
    /// Waiting for the uploader.
    Queued,
    /// Files are being uploaded.
    Uploading,
    /// Every file and the manifest are uploaded and verified.
    Replicated,
    /// The last attempt failed (`error` says why); it is retried with capped backoff.
    Failed,
}

/// One file of a queued scan.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct QueuedFile {
    /// Path relative to the scan directory, `/`-separated.
    pub path: String,
    /// Size when listed, bytes.
    pub size: u64,
    /// SHA-256 (hex), once verified.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sha256: Option<String>,
    /// Uploaded and read back equal.
    #[serde(default)]
    pub verified: bool,
}

/// One scan in the queue.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct QueueEntry {
    /// The scan id.
    pub id: String,
    /// Where it is.
    pub phase: Phase,
    /// The scan's files, once listed (`listed`).
    #[serde(default)]
    pub files: Vec<QueuedFile>,
    /// Whether `files` was filled from the scan directory.
    #[serde(default)]
    pub listed: bool,
    /// Failed attempts so far.
    #[serde(default)]
    pub attempts: u32,
    /// Why the last attempt failed, in words (never a credential).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    /// When it was enqueued, seconds since the Unix epoch.
    pub enqueued_unix: u64,
    /// When it was replicated, seconds since the Unix epoch.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub replicated_unix: Option<u64>,
    /// Whether its local frames were pruned after the verified upload.
    #[serde(default)]
    pub pruned: bool,
    /// Files of a replicated scan (its file list is dropped then, to keep the queue small).
    #[serde(default)]
    pub replicated_files: usize,
    /// Bytes of a replicated scan's files.
    #[serde(default)]
    pub replicated_bytes: u64,
}

/// What `GET /api/v1/scans/{id}` shows under `replication`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ReplicationStatus {
    /// `queued`, `uploading`, `replicated` or `failed`.
    pub state: Phase,
    /// Files uploaded and verified.
    pub files_done: usize,
    /// Files of the scan (0 until listed).
    pub files_total: usize,
    /// Bytes of the verified files.
    pub bytes_done: u64,
    /// Failed attempts so far.
    pub attempts: u32,
    /// Why the last attempt failed.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    /// The same in one line: `uploading 3 of 12 files`, `failed (attempt 2): ...`.
    pub message: String,
    /// The scan's folder in the bucket, `s3://BUCKET/PREFIX/RIG/SCAN`.
    pub url: String,
    /// Whether the local frames were pruned.
    pub pruned: bool,
}

#[derive(Debug, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct QueueFile {
    scans: Vec<QueueEntry>,
}

/// Why the queue failed.
#[derive(Debug, thiserror::Error)]
pub enum QueueError {
    /// The directory cannot be created or the file read.
    #[error("{what} {path}")]
    Io {
        /// What was being done.
        what: &'static str,
        /// The path.
        path: PathBuf,
        /// Why.
        #[source]
        source: std::io::Error,
    },
    /// The queue file is not valid (it is kept for a person to look at).
    #[error("replication queue {path} is malformed; move it away to start an empty queue")]
    Malformed {
        /// The file.
        path: PathBuf,
        /// Why.
        #[source]
        source: serde_json::Error,
    },
    /// The queue file cannot be written.
    #[error("cannot write the replication queue")]
    Write(#[source] AtomicWriteError),
}

/// The persisted upload queue, shared by the jobs (enqueue), the API (status) and the uploader.
#[derive(Debug)]
pub struct Queue {
    path: PathBuf,
    /// `s3://BUCKET/PREFIX/RIG`, for status URLs.
    base_url: String,
    inner: Mutex<QueueFile>,
    wake: tokio::sync::Notify,
    metrics: Arc<Metrics>,
}

impl Queue {
    /// Open (creating) `state_dir/replication/queue.json`; `base_url` is the rig's folder in the
    /// bucket (`s3://BUCKET/PREFIX/RIG`).
    pub fn open(state_dir: &Path, base_url: String, metrics: Arc<Metrics>) -> Result<Queue, QueueError> {
        let dir = state_dir.join("replication");
        std::fs::create_dir_all(&dir).map_err(|source| QueueError::Io {
            what: "cannot create",
            path: dir.clone(),
            source,
        })?;
        let path = dir.join("queue.json");
        let file = match std::fs::read(&path) {
            Ok(b) => {
                serde_json::from_slice(&b).map_err(|source| QueueError::Malformed { path: path.clone(), source })?
            }
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => QueueFile::default(),
            Err(source) => return Err(QueueError::Io { what: "cannot read", path, source }),
        };
        let q = Queue { path, base_url, inner: Mutex::new(file), wake: tokio::sync::Notify::new(), metrics };
        q.update_gauges(&q.lock());
        Ok(q)
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, QueueFile> {
        self.inner.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    fn update_gauges(&self, f: &QueueFile) {
        let pending = f.scans.iter().filter(|s| s.phase != Phase::Replicated).count();
        let failing = f.scans.iter().filter(|s| s.phase == Phase::Failed).count();
        self.metrics.replication_queued.store(pending as u64, Ordering::Relaxed);
        self.metrics.replication_failing.store(failing as u64, Ordering::Relaxed);
    }

    fn persist(&self, f: &QueueFile) -> Result<(), QueueError> {
        self.update_gauges(f);
        let json =
            serde_json::to_vec_pretty(f).map_err(|source| QueueError::Malformed { path: self.path.clone(), source })?;
        write_atomic(&self.path, &json).map_err(QueueError::Write)
    }

    /// Add scan `id` (once); wakes the uploader. A queue that cannot be written keeps the entry in
    /// memory (logged) and writes it with the next change.
    pub fn enqueue(&self, id: &str) {
        let mut f = self.lock();
        if f.scans.iter().any(|s| s.id == id) {
            return;
        }
        f.scans.push(QueueEntry {
            id: id.to_owned(),
            phase: Phase::Queued,
            files: Vec::new(),
            listed: false,
            attempts: 0,
            error: None,
            enqueued_unix: super::store::now_unix(),
            replicated_unix: None,
            pruned: false,
            replicated_files: 0,
            replicated_bytes: 0,
        });
        if let Err(e) = self.persist(&f) {
            tracing::warn!(scan = id, error = %super::rig::error_chain(&e), "replication queue kept in memory");
        }
        drop(f);
        tracing::info!(scan = id, "queued for replication");
        self.wake.notify_one();
    }

    /// Whether scan `id` is in the queue (in any phase).
    pub fn contains(&self, id: &str) -> bool {
        self.lock().scans.iter().any(|s| s.id == id)
    }

    /// A copy of entry `id`.
    pub fn entry(&self, id: &str) -> Option<QueueEntry> {
        self.lock().scans.iter().find(|s| s.id == id).cloned()
    }

    /// Every entry, in queue order.
    pub fn entries(&self) -> Vec<QueueEntry> {
        self.lock().scans.clone()
    }

    /// Change entry `id` with `f` and write the queue; the change holds in memory when the write
    /// fails (the error is returned).
    pub fn update(&self, id: &str, f: impl FnOnce(&mut QueueEntry)) -> Result<(), QueueError> {
        let mut file = self.lock();
        if let Some(e) = file.scans.iter_mut().find(|s| s.id == id) {
            f(e);
        }
        self.persist(&file)
    }

    /// Wait until something is enqueued.
    pub async fn woken(&self) {
        self.wake.notified().await;
    }

    /// Scan `id`'s replication state for its status, if it is in the queue.
    pub fn status(&self, id: &str) -> Option<ReplicationStatus> {
        let e = self.entry(id)?;
        let done: Vec<&QueuedFile> = e.files.iter().filter(|f| f.verified).collect();
        let (mut files_done, mut files_total) = (done.len(), e.files.len());
        let mut bytes_done = done.iter().map(|f| f.size).sum();
        if e.phase == Phase::Replicated {
            (files_done, files_total, bytes_done) = (e.replicated_files, e.replicated_files, e.replicated_bytes);
        }
        let message = match e.phase {
            Phase::Queued => "queued".to_owned(),
            Phase::Uploading => format!("uploading {files_done} of {files_total} files"),
            Phase::Replicated => format!("replicated: {files_total} files verified"),
            Phase::Failed => format!(
                "failed (attempt {}, {files_done} of {files_total} files verified; retrying): {}",
                e.attempts,
                e.error.as_deref().unwrap_or("unknown error")
            ),
        };
        Some(ReplicationStatus {
            state: e.phase,
            files_done,
            files_total,
            bytes_done,
            attempts: e.attempts,
            error: e.error.clone(),
            message,
            url: format!("{}/{}", self.base_url, e.id),
            pruned: e.pruned,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_queue_survives_a_reopen_with_its_progress() {
        let dir = tempfile::tempdir().expect("tempdir");
        let metrics = Arc::new(Metrics::default());
        let q = Queue::open(dir.path(), "s3://b/lab/rig".into(), metrics.clone()).expect("open");
        q.enqueue("scan-1");
        q.enqueue("scan-1");
        q.enqueue("scan-2");
        q.update("scan-1", |e| {
            e.phase = Phase::Uploading;
            e.listed = true;
            e.files = vec![
                QueuedFile { path: "rig.toml".into(), size: 10, sha256: Some("ab".into()), verified: true },
                QueuedFile { path: "frames/pos_000.png".into(), size: 99, sha256: None, verified: false },
            ];
        })
        .expect("update");
        assert_eq!(metrics.replication_queued.load(Ordering::Relaxed), 2);
        drop(q);
        let q = Queue::open(dir.path(), "s3://b/lab/rig".into(), metrics).expect("reopen");
        assert_eq!(q.entries().len(), 2);
        let s = q.status("scan-1").expect("status");
        assert_eq!((s.state, s.files_done, s.files_total, s.bytes_done), (Phase::Uploading, 1, 2, 10));
        assert_eq!(s.message, "uploading 1 of 2 files");
        assert_eq!(s.url, "s3://b/lab/rig/scan-1");
        assert!(q.status("scan-3").is_none());
        std::fs::write(dir.path().join("replication/queue.json"), b"{broken").expect("corrupt");
        let err = Queue::open(dir.path(), String::new(), Arc::new(Metrics::default())).expect_err("malformed");
        assert!(err.to_string().contains("queue.json"), "{err}");
    }
}

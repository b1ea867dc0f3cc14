//! The uploader: a task of the daemon that works through the [`Queue`], one scan at a time, until
//! the daemon's cancellation token fires. A failed attempt (outage, refused credential, full
//! bucket, checksum mismatch) is recorded in the entry with its error in words and retried after a
//! wait that doubles from `retry_initial_s` up to `retry_max_s`; a scan that keeps failing does not
//! hold back the others (each entry has its own wait).

use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::{Duration, Instant};

use tokio_util::sync::CancellationToken;

use crate::archive::{self, Archive, ArchiveError, Manifest, ManifestEntry};
use crate::config::replication::{PrunePolicy, ReplicationConfig};

use super::super::metrics::Metrics;
use super::super::rig::error_chain;
use super::super::store::{now_unix, ScanStatus, ScanStore};
use super::{Phase, Queue, QueuedFile};

/// What the uploader needs.
#[derive(Debug)]
pub struct Uploader {
    /// The queue.
    pub queue: Arc<Queue>,
    /// The bucket.
    pub archive: Archive,
    /// The scans.
    pub store: Arc<ScanStore>,
    /// The settings.
    pub config: ReplicationConfig,
    /// Key of the rig's folder (`PREFIX/RIG`).
    pub rig_key: String,
    /// The rig folder's name.
    pub rig: String,
    /// Counters.
    pub metrics: Arc<Metrics>,
}

impl Uploader {
    /// Enqueue every complete scan not in the queue yet (one that completed while the daemon
    /// died before enqueueing it, or every old one when replication is newly configured).
    pub fn enqueue_complete(&self) {
        if let Ok(list) = self.store.list() {
            for meta in list {
                if meta.status == ScanStatus::Complete && !self.queue.contains(&meta.id) {
                    self.queue.enqueue(&meta.id);
                }
            }
        }
    }

    /// Work through the queue until `token` is cancelled.
    pub async fn run(self, token: CancellationToken) {
        self.enqueue_complete();
        let initial = Duration::from_secs_f64(self.config.retry_initial_s);
        let max = Duration::from_secs_f64(self.config.retry_max_s);
        // Per scan: when it may be tried again, and the wait after its next failure.
        let mut waits: HashMap<String, (Instant, Duration)> = HashMap::new();
        loop {
            if token.is_cancelled() {
                return;
            }
            let now = Instant::now();
            let pending: Vec<String> =
                self.queue.entries().into_iter().filter(|e| e.phase != Phase::Replicated).map(|e| e.id).collect();
            let due = pending.iter().find(|id| waits.get(*id).is_none_or(|(at, _)| *at <= now)).cloned();
            let Some(id) = due else {
                let next = pending.iter().filter_map(|id| waits.get(id).map(|(at, _)| *at)).min();
                let sleep = next.map_or(Duration::from_secs(3600), |at| at.saturating_duration_since(now));
                tokio::select! {
                    _ = token.cancelled() => return,
                    _ = self.queue.woken() => {}
                    _ = tokio::time::sleep(sleep) => {}
                }
                continue;
            };
            let result = tokio::select! {
                _ = token.cancelled() => Err(ArchiveError::Stopped),
                r = self.replicate(&id) => r,
            };
            match result {
                Ok(()) => {
                    waits.remove(&id);
                    self.prune();
                }
                Err(ArchiveError::Stopped) => return,
                Err(e) => {
                    let words = words(&e);
                    let wait = waits.get(&id).map_or(initial, |(_, w)| *w);
                    tracing::warn!(scan = %id, error = %words, retry_in_s = wait.as_secs_f64(), "replication attempt failed; the local scan is kept");
                    self.metrics.replication_failures.fetch_add(1, Ordering::Relaxed);
                    let _ = self.queue.update(&id, |e| {
                        e.phase = Phase::Failed;
                        e.attempts += 1;
                        e.error = Some(words);
                    });
                    waits.insert(id, (Instant::now() + wait, (wait * 2).min(max)));
                }
            }
        }
    }

    fn scan_dir(&self, id: &str) -> PathBuf {
        self.store.dir(id)
    }

    /// Upload scan `id`'s files not yet verified, then its manifest.
    async fn replicate(&self, id: &str) -> Result<(), ArchiveError> {
        let dir = self.scan_dir(id);
        let Some(entry) = self.queue.entry(id) else { return Ok(()) };
        if !entry.listed {
            let files = archive::list_files(&dir)?
                .into_iter()
                .map(|path| {
                    let size = std::fs::metadata(dir.join(&path)).map_or(0, |m| m.len());
                    QueuedFile { path, size, sha256: None, verified: false }
                })
                .collect();
            self.save(id, |e| {
                e.files = files;
                e.listed = true;
            });
        }
        self.save(id, |e| e.phase = Phase::Uploading);
        let scan_key = archive::join_key(&[&self.rig_key, id]);
        let todo: Vec<QueuedFile> =
            self.queue.entry(id).map(|e| e.files.into_iter().filter(|f| !f.verified).collect()).unwrap_or_default();
        tracing::info!(scan = id, files = todo.len(), "uploading");
        for f in todo {
            let key = archive::join_key(&[&scan_key, &f.path]);
            let metrics = self.metrics.clone();
            let up = self
                .archive
                .upload_file(&dir.join(&f.path), &key, &mut |n| {
                    metrics.replication_bytes.fetch_add(n, Ordering::Relaxed);
                })
                .await?;
            self.metrics.replication_files.fetch_add(1, Ordering::Relaxed);
            tracing::debug!(scan = id, file = %f.path, bytes = up.size, "uploaded and verified");
            self.save(id, |e| {
                if let Some(q) = e.files.iter_mut().find(|q| q.path == f.path) {
                    q.size = up.size;
                    q.sha256 = Some(up.sha256.clone());
                    q.verified = true;
                }
            });
        }
        let Some(entry) = self.queue.entry(id) else { return Ok(()) };
        let files = entry
            .files
            .iter()
            .map(|f| ManifestEntry { path: f.path.clone(), size: f.size, sha256: f.sha256.clone().unwrap_or_default() })
            .collect();
        let manifest = Manifest { scan: id.to_owned(), rig: self.rig.clone(), created_unix: now_unix(), files };
        let bytes = serde_json::to_vec_pretty(&manifest).map_err(|e| ArchiveError::Manifest {
            bucket: self.archive.bucket().to_owned(),
            key: scan_key.clone(),
            problem: e.to_string(),
        })?;
        self.archive.put_verified(&archive::join_key(&[&scan_key, archive::MANIFEST]), bytes).await?;
        self.metrics.replication_scans.fetch_add(1, Ordering::Relaxed);
        self.save(id, |e| {
            e.phase = Phase::Replicated;
            e.error = None;
            e.replicated_unix = Some(now_unix());
            e.replicated_files = e.files.len();
            e.replicated_bytes = e.files.iter().map(|f| f.size).sum();
            // The manifest in the bucket lists them now; the queue stays small over years of scans.
            e.files = Vec::new();
        });
        tracing::info!(scan = id, files = entry.files.len(), "replicated and verified");
        Ok(())
    }

    /// Change the entry and write the queue; a failed write is logged (the change holds in
    /// memory, so this run goes on; after a crash the unrecorded files are uploaded again).
    fn save(&self, id: &str, f: impl FnOnce(&mut super::QueueEntry)) {
        if let Err(e) = self.queue.update(id, f) {
            tracing::warn!(scan = id, error = %error_chain(&e), "cannot write the replication queue");
        }
    }

    /// Apply the prune policy: with `frames_after_verified`, remove `frames/` of every replicated
    /// scan but the `keep_last` most recently replicated.
    fn prune(&self) {
        if self.config.prune != PrunePolicy::FramesAfterVerified {
            return;
        }
        let mut done: Vec<_> =
            self.queue.entries().into_iter().filter(|e| e.phase == Phase::Replicated && !e.pruned).collect();
        let mut all: Vec<_> = self.queue.entries().into_iter().filter(|e| e.phase == Phase::Replicated).collect();
        all.sort_by_key(|e| std::cmp::Reverse((e.replicated_unix, e.enqueued_unix)));
        let keep: Vec<String> = all.iter().take(self.config.keep_last as usize).map(|e| e.id.clone()).collect();
        done.retain(|e| !keep.contains(&e.id));
        for e in done {
            let frames = self.scan_dir(&e.id).join("frames");
            match std::fs::remove_dir_all(&frames) {
                Ok(()) => tracing::info!(scan = %e.id, "pruned the local frames of a verified replica"),
                Err(err) if err.kind() == std::io::ErrorKind::NotFound => {}
                Err(err) => {
                    tracing::warn!(scan = %e.id, error = %err, "cannot prune the local frames");
                    continue;
                }
            }
            self.save(&e.id, |q| q.pruned = true);
        }
    }
}

/// An error and its sources in one line, leaving out a source whose text the line already holds
/// (the object store's errors repeat their source in their own message).
fn words(e: &dyn std::error::Error) -> String {
    let mut out = e.to_string();
    let mut cur = e.source();
    while let Some(c) = cur {
        let t = c.to_string();
        if !out.contains(&t) {
            out.push_str(": ");
            out.push_str(&t);
        }
        cur = c.source();
    }
    out
}

//! The scan store: `STATE_DIR/scans/<id>/` holds one scan's frames, results and `meta.json`.
//!
//! `meta.json` is written atomically (temporary file, fsync, rename) at every status change, and a
//! scan's results are final only once `report.json` exists (written last by the scan). On start the
//! store marks scans that were running or paused when the daemon died as `interrupted`; they can be
//! resumed from their last complete frame.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{SystemTime, UNIX_EPOCH};

use serde::{Deserialize, Serialize};

use crate::config::{Method, RigConfig};
use crate::atomic::{write_atomic, AtomicWriteError};

/// Where a scan is in its life.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ScanStatus {
    /// Capturing or reconstructing now.
    Running,
    /// Stopped by a pause request at a step boundary; can be resumed.
    Paused,
    /// Finished; `report.json` and the models exist.
    Complete,
    /// Stopped by an error; frames captured before it are kept.
    Failed,
    /// Stopped on request; frames captured are kept.
    Cancelled,
    /// Was running when the daemon stopped or died; can be resumed.
    Interrupted,
}

impl std::fmt::Display for ScanStatus {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            ScanStatus::Running => "running",
            ScanStatus::Paused => "paused",
            ScanStatus::Complete => "complete",
            ScanStatus::Failed => "failed",
            ScanStatus::Cancelled => "cancelled",
            ScanStatus::Interrupted => "interrupted",
        })
    }
}

impl ScanStatus {
    /// Whether the scan can be resumed.
    pub fn resumable(self) -> bool {
        matches!(self, ScanStatus::Paused | ScanStatus::Interrupted | ScanStatus::Failed)
    }
}

/// `meta.json`: what the store knows about a scan.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ScanMeta {
    /// The scan's id (its directory name).
    pub id: String,
    /// Status.
    pub status: ScanStatus,
    /// Rig name from the config.
    pub rig: String,
    /// Reconstruction method.
    pub method: Method,
    /// Voxels along the working volume's longest side.
    #[serde(default)]
    pub resolution: u32,
    /// The stored scan whose views this entry reconstructs again (a reprocess, no acquisition).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reprocess_of: Option<String>,
    /// Turntable positions planned.
    pub positions: u32,
    /// Lights on for each frame, by index.
    pub lights: Vec<usize>,
    /// Creation time, seconds since the Unix epoch.
    pub created_unix: u64,
    /// Last status change, seconds since the Unix epoch.
    pub updated_unix: u64,
    /// How many times the scan was resumed.
    pub resumes: u32,
    /// Why it failed, for `failed` scans.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
}

/// Why the store failed.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// A directory or file could not be read or created.
    #[error("{what} {path}")]
    Io {
        /// What was being done.
        what: &'static str,
        /// The path.
        path: PathBuf,
        /// The error.
        #[source]
        source: std::io::Error,
    },
    /// `meta.json` could not be written.
    #[error("cannot write scan metadata")]
    Write(#[source] AtomicWriteError),
    /// `meta.json` could not be encoded or parsed.
    #[error("scan metadata {path} is malformed")]
    Json {
        /// The file.
        path: PathBuf,
        /// The error.
        #[source]
        source: serde_json::Error,
    },
    /// No scan with that id.
    #[error("no scan `{0}`")]
    NotFound(String),
}

/// The scans under a state directory.
#[derive(Debug)]
pub struct ScanStore {
    root: PathBuf,
    counter: AtomicU64,
}

/// Seconds since the Unix epoch.
pub fn now_unix() -> u64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map_or(0, |d| d.as_secs())
}

/// Whether `id` looks like a scan id (so it is safe as a path component).
pub fn valid_id(id: &str) -> bool {
    !id.is_empty() && id.len() <= 64 && id.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'_')
}

impl ScanStore {
    /// Open (creating) `state_dir/scans` and recover after a crash: scans left `running` or
    /// `paused` become `interrupted`, or `complete` when their `report.json` exists. Returns the
    /// store and the ids it marked interrupted.
    pub fn open(state_dir: &Path) -> Result<(ScanStore, Vec<String>), StoreError> {
        let root = state_dir.join("scans");
        std::fs::create_dir_all(&root).map_err(|source| StoreError::Io {
            what: "cannot create",
            path: root.clone(),
            source,
        })?;
        let store = ScanStore { root, counter: AtomicU64::new(0) };
        let mut interrupted = Vec::new();
        for mut meta in store.list()? {
            if meta.status == ScanStatus::Running {
                meta.status = if store.dir(&meta.id).join("report.json").is_file() {
                    ScanStatus::Complete
                } else {
                    interrupted.push(meta.id.clone());
                    ScanStatus::Interrupted
                };
                meta.updated_unix = now_unix();
                store.save(&meta)?;
            }
        }
        Ok((store, interrupted))
    }

    /// The directory of scan `id`.
    pub fn dir(&self, id: &str) -> PathBuf {
        self.root.join(id)
    }

    /// Create a new scan directory and its `meta.json` with status `running`, for a scan with the
    /// effective configuration `config`, or for reprocessing the stored scan `reprocess_of`.
    pub fn create(&self, config: &RigConfig, reprocess_of: Option<&str>) -> Result<ScanMeta, StoreError> {
        let now = now_unix();
        loop {
            let n = self.counter.fetch_add(1, Ordering::SeqCst);
            let id = format!("scan-{now}-{n}");
            let dir = self.dir(&id);
            match std::fs::create_dir(&dir) {
                Ok(()) => {
                    let meta = ScanMeta {
                        id,
                        status: ScanStatus::Running,
                        rig: config.rig.name.clone(),
                        method: config.reconstruction.method,
                        positions: config.scan.positions,
                        lights: config.scan.lights.clone(),
                        resolution: config.reconstruction.resolution,
                        reprocess_of: reprocess_of.map(str::to_owned),
                        created_unix: now,
                        updated_unix: now,
                        resumes: 0,
                        error: None,
                    };
                    self.save(&meta)?;
                    return Ok(meta);
                }
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => continue,
                Err(source) => return Err(StoreError::Io { what: "cannot create", path: dir, source }),
            }
        }
    }

    /// Write `meta.json` atomically.
    pub fn save(&self, meta: &ScanMeta) -> Result<(), StoreError> {
        let path = self.dir(&meta.id).join("meta.json");
        let json = serde_json::to_vec_pretty(meta).map_err(|source| StoreError::Json { path: path.clone(), source })?;
        write_atomic(&path, &json).map_err(StoreError::Write)
    }

    /// Read scan `id`'s metadata.
    pub fn get(&self, id: &str) -> Result<ScanMeta, StoreError> {
        if !valid_id(id) {
            return Err(StoreError::NotFound(id.to_owned()));
        }
        let path = self.dir(id).join("meta.json");
        let bytes = match std::fs::read(&path) {
            Ok(b) => b,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Err(StoreError::NotFound(id.to_owned())),
            Err(source) => return Err(StoreError::Io { what: "cannot read", path, source }),
        };
        serde_json::from_slice(&bytes).map_err(|source| StoreError::Json { path, source })
    }

    /// Every scan with a readable `meta.json`, oldest first. Unreadable ones are logged and skipped.
    pub fn list(&self) -> Result<Vec<ScanMeta>, StoreError> {
        let entries = std::fs::read_dir(&self.root).map_err(|source| StoreError::Io {
            what: "cannot list",
            path: self.root.clone(),
            source,
        })?;
        let mut out = Vec::new();
        for entry in entries.flatten() {
            let name = entry.file_name().to_string_lossy().into_owned();
            if !valid_id(&name) {
                continue;
            }
            match self.get(&name) {
                Ok(meta) => out.push(meta),
                Err(e) => tracing::warn!(scan = %name, error = %e, "skipping a scan directory"),
            }
        }
        out.sort_by(|a, b| (a.created_unix, &a.id).cmp(&(b.created_unix, &b.id)));
        Ok(out)
    }

    /// Set scan `id`'s status (and error) and save it.
    pub fn set_status(&self, id: &str, status: ScanStatus, error: Option<String>) -> Result<ScanMeta, StoreError> {
        let mut meta = self.get(id)?;
        meta.status = status;
        meta.error = error;
        meta.updated_unix = now_unix();
        self.save(&meta)?;
        Ok(meta)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config() -> RigConfig {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("config/rigs/simulated.toml");
        crate::rigfile::load(&path).expect("shipped rig")
    }

    #[test]
    fn running_scans_become_interrupted_on_reopen_and_finished_ones_complete() {
        let dir = tempfile::tempdir().expect("tempdir");
        let (store, interrupted) = ScanStore::open(dir.path()).expect("open");
        assert!(interrupted.is_empty());
        let a = store.create(&config(), None).expect("create");
        let b = store.create(&config(), None).expect("create");
        let c = store.create(&config(), None).expect("create");
        store.set_status(&c.id, ScanStatus::Cancelled, None).expect("status");
        std::fs::write(store.dir(&b.id).join("report.json"), b"{}").expect("report");
        drop(store);
        let (store, interrupted) = ScanStore::open(dir.path()).expect("reopen");
        assert_eq!(interrupted, vec![a.id.clone()]);
        assert_eq!(store.get(&a.id).expect("a").status, ScanStatus::Interrupted);
        assert_eq!(store.get(&b.id).expect("b").status, ScanStatus::Complete);
        assert_eq!(store.get(&c.id).expect("c").status, ScanStatus::Cancelled);
        assert_eq!(store.list().expect("list").len(), 3);
    }

    #[test]
    fn ids_that_could_escape_the_store_are_not_found() {
        let dir = tempfile::tempdir().expect("tempdir");
        let (store, _) = ScanStore::open(dir.path()).expect("open");
        for id in ["../etc", "a/b", "", ".."] {
            assert!(matches!(store.get(id), Err(StoreError::NotFound(_))), "{id}");
        }
    }

    #[test]
    fn a_corrupt_meta_is_skipped_by_list() {
        let dir = tempfile::tempdir().expect("tempdir");
        let (store, _) = ScanStore::open(dir.path()).expect("open");
        let a = store.create(&config(), None).expect("create");
        std::fs::create_dir_all(store.dir("scan-bad")).expect("mkdir");
        std::fs::write(store.dir("scan-bad").join("meta.json"), b"{not json").expect("write");
        let list = store.list().expect("list");
        assert_eq!(list.len(), 1);
        assert_eq!(list[0].id, a.id);
    }
}

//! The scan store: `STATE_DIR/scans/<id>/` holds one scan's frames, results and `meta.json`.
//!
//! `meta.json` is written atomically (temporary file, fsync, rename) at every status change, and a
//! scan's results are final only once `report.json` exists (written last by the scan).
//!
//! The store keeps every scan's metadata in memory too, and the memory copy is what the daemon
//! serves: when `meta.json` cannot be written (a full disk) the status is still right, the write is
//! kept pending and retried at the next store access, so the file catches up once there is room.
//!
//! # Status after a crash
//! On start (after a crash, kill -9 or power loss) the store
//! - marks scans left `running` as `interrupted` (or `complete` when their `report.json` exists):
//!   they were stopped between two steps nobody chose;
//! - leaves `paused` scans `paused`: a pause stops at a step boundary with every frame written, and
//!   `meta.json` says `paused` only after that, so nothing was in flight when the daemon died;
//!   `failed`, `cancelled` and `complete` scans also keep their status;
//! - removes the temporary files of atomic writes (`.NAME.tmp-PID`) that a killed process left in
//!   every scan directory and its `frames/`, since they never hold a complete result.

use std::collections::{HashMap, HashSet};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;
use std::time::{SystemTime, UNIX_EPOCH};

use serde::{Deserialize, Serialize};

use crate::atomic::{is_atomic_temp, write_atomic, AtomicWriteError};
use crate::config::{Method, RigConfig};

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

impl StoreError {
    /// Whether the error is the disk (or the user's quota) being full.
    pub fn is_disk_full(&self) -> bool {
        let io = match self {
            StoreError::Io { source, .. } => Some(source),
            StoreError::Write(AtomicWriteError { source, .. }) => Some(source),
            _ => None,
        };
        io.is_some_and(|e| matches!(e.raw_os_error(), Some(libc::ENOSPC) | Some(libc::EDQUOT)))
    }
}

/// The scans under a state directory.
#[derive(Debug)]
pub struct ScanStore {
    root: PathBuf,
    counter: AtomicU64,
    /// Every scan's metadata as this process last set it (the truth; `meta.json` follows it).
    memory: Mutex<Memory>,
}

#[derive(Debug, Default)]
struct Memory {
    metas: HashMap<String, ScanMeta>,
    /// Ids whose `meta.json` is behind `metas` (the last write failed).
    pending: HashSet<String>,
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
    /// Open (creating) `state_dir/scans` and recover after a crash (see the module docs): scans
    /// left `running` become `interrupted`, or `complete` when their `report.json` exists; partial
    /// writes are removed. Returns the store and the ids it marked interrupted.
    pub fn open(state_dir: &Path) -> Result<(ScanStore, Vec<String>), StoreError> {
        let root = state_dir.join("scans");
        std::fs::create_dir_all(&root).map_err(|source| StoreError::Io {
            what: "cannot create",
            path: root.clone(),
            source,
        })?;
        let store = ScanStore { root, counter: AtomicU64::new(0), memory: Mutex::default() };
        store.remove_partial_writes();
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
                // Kept in memory (and pending) if the disk is full.
                let _ = store.save(&meta);
            }
        }
        Ok((store, interrupted))
    }

    /// The directory of scan `id`.
    pub fn dir(&self, id: &str) -> PathBuf {
        self.root.join(id)
    }

    /// Remove the `.NAME.tmp-PID` files of atomic writes left by a killed process in every scan
    /// directory and its `frames/`. Only called before any scan runs.
    fn remove_partial_writes(&self) {
        let Ok(scans) = std::fs::read_dir(&self.root) else { return };
        for scan in scans.flatten() {
            if !valid_id(&scan.file_name().to_string_lossy()) {
                continue;
            }
            for d in [scan.path(), scan.path().join("frames")] {
                let Ok(entries) = std::fs::read_dir(&d) else { continue };
                for entry in entries.flatten() {
                    if is_atomic_temp(&entry.file_name().to_string_lossy()) {
                        match std::fs::remove_file(entry.path()) {
                            Ok(()) => tracing::info!(file = %entry.path().display(), "removed a partial write"),
                            Err(e) => {
                                tracing::warn!(file = %entry.path().display(), error = %e, "cannot remove a partial write")
                            }
                        }
                    }
                }
            }
        }
    }

    fn memory(&self) -> std::sync::MutexGuard<'_, Memory> {
        self.memory.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Write the `meta.json` files that are behind the memory copy; they stay pending on failure.
    pub fn flush(&self) {
        let mut memory = self.memory();
        if memory.pending.is_empty() {
            return;
        }
        let ids: Vec<String> = memory.pending.iter().cloned().collect();
        for id in ids {
            let Some(meta) = memory.metas.get(&id).cloned() else {
                memory.pending.remove(&id);
                continue;
            };
            if self.write(&meta).is_ok() {
                tracing::info!(scan = %id, "pending scan metadata written");
                memory.pending.remove(&id);
            }
        }
    }

    /// Whether `meta.json` of `id` is behind the status served (its last write failed).
    pub fn pending(&self, id: &str) -> bool {
        self.memory().pending.contains(id)
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
                    // A scan whose metadata cannot be written is not created: no directory
                    // without `meta.json` is left behind (a full disk).
                    if let Err(e) = self.write(&meta) {
                        let _ = std::fs::remove_dir_all(&dir);
                        return Err(e);
                    }
                    self.memory().metas.insert(meta.id.clone(), meta.clone());
                    return Ok(meta);
                }
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => continue,
                Err(source) => return Err(StoreError::Io { what: "cannot create", path: dir, source }),
            }
        }
    }

    /// Record `meta` (in memory at once) and write `meta.json` atomically. When the write fails
    /// the memory copy is still the status served and the write is retried by later store calls;
    /// the error is returned so that the caller can decide whether that matters.
    pub fn save(&self, meta: &ScanMeta) -> Result<(), StoreError> {
        let mut memory = self.memory();
        memory.metas.insert(meta.id.clone(), meta.clone());
        match self.write(meta) {
            Ok(()) => {
                memory.pending.remove(&meta.id);
                Ok(())
            }
            Err(e) => {
                tracing::warn!(scan = %meta.id, error = %super::rig::error_chain(&e), "scan metadata kept in memory; written when there is room");
                memory.pending.insert(meta.id.clone());
                Err(e)
            }
        }
    }

    fn write(&self, meta: &ScanMeta) -> Result<(), StoreError> {
        let path = self.dir(&meta.id).join("meta.json");
        let json = serde_json::to_vec_pretty(meta).map_err(|source| StoreError::Json { path: path.clone(), source })?;
        write_atomic(&path, &json).map_err(StoreError::Write)
    }

    /// Scan `id`'s metadata: the memory copy when this process has one, else `meta.json`.
    pub fn get(&self, id: &str) -> Result<ScanMeta, StoreError> {
        if !valid_id(id) {
            return Err(StoreError::NotFound(id.to_owned()));
        }
        self.flush();
        if let Some(meta) = self.memory().metas.get(id) {
            return Ok(meta.clone());
        }
        self.read(id)
    }

    fn read(&self, id: &str) -> Result<ScanMeta, StoreError> {
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
                // Removed under our feet (or never written): nothing to list.
                Err(StoreError::NotFound(_)) => {}
                Err(e) => tracing::warn!(scan = %name, error = %e, "skipping a scan directory"),
            }
        }
        out.sort_by(|a, b| (a.created_unix, &a.id).cmp(&(b.created_unix, &b.id)));
        Ok(out)
    }

    /// Set scan `id`'s status (and error). The new status holds (in memory) even when `meta.json`
    /// cannot be written now; that write is retried later and logged, not returned.
    pub fn set_status(&self, id: &str, status: ScanStatus, error: Option<String>) -> Result<ScanMeta, StoreError> {
        let mut meta = self.get(id)?;
        meta.status = status;
        meta.error = error;
        meta.updated_unix = now_unix();
        let _ = self.save(&meta);
        Ok(meta)
    }
}

impl ScanStore {
    /// Remove scan `id`: its directory with every frame and result, and its memory copy. The
    /// caller makes sure it is not running.
    pub fn remove(&self, id: &str) -> Result<(), StoreError> {
        self.get(id)?;
        let dir = self.dir(id);
        let mut memory = self.memory();
        std::fs::remove_dir_all(&dir).map_err(|source| StoreError::Io { what: "cannot remove", path: dir, source })?;
        memory.metas.remove(id);
        memory.pending.remove(id);
        Ok(())
    }
}

/// A UTC calendar time.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Civil {
    /// Year.
    pub year: i64,
    /// Month, 1-12.
    pub month: u32,
    /// Day of the month, 1-31.
    pub day: u32,
    /// Hour, 0-23.
    pub hour: u32,
    /// Minute, 0-59.
    pub minute: u32,
    /// Second, 0-59.
    pub second: u32,
}

/// Seconds since the Unix epoch as a UTC calendar time (proleptic Gregorian; Howard Hinnant's
/// `civil_from_days`).
pub fn civil(unix: u64) -> Civil {
    let days = (unix / 86_400) as i64;
    let rem = unix % 86_400;
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = (doy - (153 * mp + 2) / 5 + 1) as u32;
    let month = if mp < 10 { mp + 3 } else { mp - 9 } as u32;
    let year = yoe + era * 400 + i64::from(month <= 2);
    Civil { year, month, day, hour: (rem / 3600) as u32, minute: (rem / 60 % 60) as u32, second: (rem % 60) as u32 }
}

/// Seconds since the Unix epoch as RFC 3339 UTC, e.g. `2026-12-02T01:02:04Z`.
pub fn rfc3339(unix: u64) -> String {
    let c = civil(unix);
    format!("{:04}-{:02}-{:02}T{:02}:{:02}:{:02}Z", c.year, c.month, c.day, c.hour, c.minute, c.second)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unix_times_become_rfc3339() {
        assert_eq!(rfc3339(0), "1970-01-01T00:00:00Z");
        assert_eq!(rfc3339(951_782_400), "2000-02-29T00:00:00Z");
        assert_eq!(rfc3339(1_796_173_324), "2026-12-02T01:02:04Z");
    }

    #[test]
    fn removed_scans_are_gone_from_disk_and_list() {
        let dir = tempfile::tempdir().expect("tempdir");
        let (store, _) = ScanStore::open(dir.path()).expect("open");
        let a = store.create(&config(), None).expect("create");
        std::fs::create_dir_all(store.dir(&a.id).join("frames")).expect("mkdir");
        store.remove(&a.id).expect("remove");
        assert!(!store.dir(&a.id).exists());
        assert!(store.list().expect("list").is_empty());
        assert!(matches!(store.get(&a.id), Err(StoreError::NotFound(_))));
        assert!(matches!(store.remove(&a.id), Err(StoreError::NotFound(_))));
    }

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

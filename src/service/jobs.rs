//! Scan jobs: at most one job runs at a time: a scan on the rig, or the reprocessing of a stored scan
//! (no hardware). Start (any method the rig's devices allow, chosen per scan), pause (stop at a step
//! boundary, resumable), resume (replaying the views on disk and acquiring the rest), reprocess (a
//! stored scan's views with other settings, into a new scan entry), cancel. Every job runs the one
//! scan driver ([`crate::scan::run_job`]). Progress is published on a watch channel.

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use serde::{Deserialize, Serialize};
use tokio::sync::watch;

use crate::acquisition::{AcquisitionError, CancelToken};
use crate::config::{Method, RigConfig};
use crate::scan::preview::LiveSpec;
use crate::scan::{ScanError, ScanEvent};

use super::metrics::Metrics;
use super::rig::{error_chain, RigError, RigHandle, ScanJob};
use super::store::{ScanMeta, ScanStatus, ScanStore, StoreError};

/// Live progress of the current (or last) scan, as sent on the event stream.
#[derive(Debug, Clone, Default, Serialize)]
pub struct ProgressSnapshot {
    /// The scan, if any has run since the daemon started.
    pub scan_id: Option<String>,
    /// Its status.
    pub status: Option<ScanStatus>,
    /// Views processed (captured and carved), including ones reused on resume.
    pub step: usize,
    /// Views planned.
    pub total: usize,
    /// What is happening: an acquisition stage (`moving`, `capturing`...) or a pipeline stage.
    pub stage: String,
    /// A human-readable line.
    pub message: String,
    /// Seconds since this run of the scan started.
    pub elapsed_s: f64,
    /// Estimated seconds until the results are on disk: capture and processing of the views left
    /// at this run's pace, plus the method's finishing stage (see [`remaining_estimate`]).
    pub remaining_s: Option<f64>,
}

/// The latest live estimate of the running (or last-run) job, as announced on the event stream
/// (event `model`); its points are served as binary PLY (`GET /api/v1/scans/{id}/live.ply`).
#[derive(Debug, Clone, Serialize)]
pub struct LiveModel {
    /// The scan it belongs to.
    pub scan_id: String,
    /// Counts the previews of this scan from 1.
    pub version: u64,
    /// 0-based position of the last view it includes.
    pub position: usize,
    /// Points in it.
    pub points: usize,
    /// The cloud as binary little-endian PLY (object frame, metres).
    #[serde(skip)]
    pub ply: axum::body::Bytes,
}

/// What a client may ask for when starting a scan; missing fields take the rig file's values. The
/// result goes through the same [`RigConfig::validate`] as the rig file.
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StartRequest {
    /// Reconstruction method (any the rig's devices allow: see `GET /api/v1/methods`).
    pub method: Option<Method>,
    /// Turntable positions.
    pub positions: Option<u32>,
    /// Lights on for each frame, by index.
    pub lights: Option<Vec<usize>>,
    /// Voxels along the working volume's longest side.
    pub resolution: Option<u32>,
}

/// What a client may change when reprocessing a stored scan; missing fields keep the scan's own.
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ReprocessRequest {
    /// Reconstruction method (one the stored views serve: a silhouette scan's frames serve the
    /// photo methods too).
    pub method: Option<Method>,
    /// Voxels along the working volume's longest side.
    pub resolution: Option<u32>,
    /// Occupancy smoothing radius of the mesh, voxels.
    pub smooth_radius: Option<u32>,
}

/// Whether this rig can run a method, for `GET /api/v1/methods`.
#[derive(Debug, Clone, Serialize)]
pub struct MethodInfo {
    /// The method.
    pub method: Method,
    /// Whether a scan with it can start on this rig.
    pub available: bool,
    /// What is missing (a device, a calibration, a setting), each as `key: problem`.
    pub missing: Vec<String>,
}

/// Why a job request was refused.
#[derive(Debug, thiserror::Error)]
pub enum JobError {
    /// A job is already running.
    #[error("scan {0} is already running")]
    Busy(String),
    /// The request is not acceptable.
    #[error("invalid request: {field}: {problem}")]
    Invalid {
        /// The offending field.
        field: String,
        /// What is wrong with it.
        problem: String,
    },
    /// The scan is not in a state that allows this.
    #[error("scan {id} is {status}; cannot {action}")]
    WrongState {
        /// The scan.
        id: String,
        /// Its status.
        status: ScanStatus,
        /// What was asked.
        action: &'static str,
    },
    /// The rig file stored with a scan cannot be read back.
    #[error("scan {id}: its stored rig file")]
    StoredConfig {
        /// The scan.
        id: String,
        /// Why.
        #[source]
        source: crate::config::ConfigError,
    },
    /// The store failed.
    #[error("scan store")]
    Store(#[source] StoreError),
}

/// `config` with the method `method`: the problems [`RigConfig::validate`] finds, as
/// `(key, message)`, empty when the rig can run it.
fn problems_with(config: &RigConfig) -> Vec<(String, String)> {
    config.validate().into_iter().map(|p| (p.key, p.message)).collect()
}

/// Refuse `config` unless it validates; the error names every problem.
fn validated(config: RigConfig) -> Result<RigConfig, JobError> {
    let problems = problems_with(&config);
    match problems.first() {
        None => Ok(config),
        Some((key, _)) => Err(JobError::Invalid {
            field: key.clone(),
            problem: problems.iter().map(|(k, m)| format!("{k}: {m}")).collect::<Vec<_>>().join("; "),
        }),
    }
}

/// The methods `config`'s rig can run, and what the others miss.
pub fn methods(config: &RigConfig) -> Vec<MethodInfo> {
    Method::ALL
        .iter()
        .map(|&method| {
            let mut c = config.clone();
            c.reconstruction.method = method;
            let missing: Vec<String> = problems_with(&c).into_iter().map(|(k, m)| format!("{k}: {m}")).collect();
            MethodInfo { method, available: missing.is_empty(), missing }
        })
        .collect()
}

/// What a launched job runs.
enum Work {
    /// A scan on the rig (`resume`: replay the stored views first).
    Scan { config: RigConfig, resume: bool },
    /// The views of the stored scan in `source` reconstructed again, without hardware.
    Reprocess { config: RigConfig, source: PathBuf },
}

struct Active {
    id: String,
    cancel: CancelToken,
    pause: Arc<AtomicBool>,
    /// A scan on the rig (not a reprocess): it owns the hardware.
    hardware: bool,
    /// The stored scan a reprocess reads its views from.
    reads: Option<String>,
}

/// The scan jobs of one daemon.
#[derive(Clone)]
pub struct Jobs {
    store: Arc<ScanStore>,
    rig: RigHandle,
    metrics: Arc<Metrics>,
    progress: Arc<watch::Sender<ProgressSnapshot>>,
    live: Arc<watch::Sender<Option<LiveModel>>>,
    active: Arc<Mutex<Option<Active>>>,
    shutting_down: Arc<AtomicBool>,
    /// The replication queue every completed scan goes into, when replication is configured.
    replication: Option<Arc<super::replication::Queue>>,
}

impl std::fmt::Debug for Jobs {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Jobs").finish_non_exhaustive()
    }
}

impl Jobs {
    /// Jobs over `store`, running scans on `rig`.
    pub fn new(store: Arc<ScanStore>, rig: RigHandle, metrics: Arc<Metrics>) -> Jobs {
        let (progress, _) = watch::channel(ProgressSnapshot::default());
        Jobs {
            store,
            rig,
            metrics,
            progress: Arc::new(progress),
            live: Arc::new(watch::channel(None).0),
            active: Arc::new(Mutex::new(None)),
            shutting_down: Arc::new(AtomicBool::new(false)),
            replication: None,
        }
    }

    /// Put every scan that completes from now on into `queue`.
    pub fn with_replication(mut self, queue: Arc<super::replication::Queue>) -> Jobs {
        self.replication = Some(queue);
        self
    }

    /// The replication queue, when replication is configured.
    pub fn replication(&self) -> Option<&Arc<super::replication::Queue>> {
        self.replication.as_ref()
    }

    /// The store.
    pub fn store(&self) -> &ScanStore {
        &self.store
    }

    /// Subscribe to progress.
    pub fn subscribe(&self) -> watch::Receiver<ProgressSnapshot> {
        self.progress.subscribe()
    }

    /// Subscribe to the live estimates.
    pub fn subscribe_live(&self) -> watch::Receiver<Option<LiveModel>> {
        self.live.subscribe()
    }

    /// The latest live estimate of scan `id`, if it has one.
    pub fn live_model(&self, id: &str) -> Option<LiveModel> {
        self.live.borrow().as_ref().filter(|m| m.scan_id == id).cloned()
    }

    /// The latest progress.
    pub fn progress(&self) -> ProgressSnapshot {
        self.progress.borrow().clone()
    }

    /// The id of the running scan.
    pub fn running(&self) -> Option<String> {
        self.active.lock().ok().and_then(|a| a.as_ref().map(|a| a.id.clone()))
    }

    /// The id of the running job when it is a scan on the rig (it owns the camera, the table, the
    /// lights and the projector; a reprocess needs no hardware and gives `None`).
    pub fn scanning(&self) -> Option<String> {
        self.active.lock().ok().and_then(|a| a.as_ref().filter(|a| a.hardware).map(|a| a.id.clone()))
    }

    /// Delete scan `id`: its directory (frames, results) and its entry. Refused while it runs.
    pub fn delete(&self, id: &str) -> Result<(), JobError> {
        // Held while removing, so that the scan cannot be resumed or reprocessed meanwhile.
        let active = self.active.lock().map_err(|_| JobError::Busy(String::new()))?;
        let meta = self.store.get(id).map_err(JobError::Store)?;
        let runs = active.as_ref().is_some_and(|a| a.id == id);
        if runs || meta.status == ScanStatus::Running {
            return Err(JobError::WrongState { id: id.to_owned(), status: ScanStatus::Running, action: "delete" });
        }
        if let Some(a) = active.as_ref().filter(|a| a.reads.as_deref() == Some(id)) {
            return Err(JobError::Busy(a.id.clone()));
        }
        self.store.remove(id).map_err(JobError::Store)?;
        tracing::info!(scan = id, "scan deleted");
        Ok(())
    }

    /// Start a new scan with `config` adjusted by `req`.
    pub fn start(&self, config: &RigConfig, req: StartRequest) -> Result<ScanMeta, JobError> {
        let mut config = config.clone();
        if let Some(m) = req.method {
            config.reconstruction.method = m;
        }
        if let Some(n) = req.positions {
            config.scan.positions = n;
        }
        if let Some(l) = req.lights {
            config.scan.lights = l;
        }
        if let Some(r) = req.resolution {
            config.reconstruction.resolution = r;
        }
        let config = validated(config)?;
        let mut active = self.active.lock().map_err(|_| JobError::Busy(String::new()))?;
        if let Some(a) = active.as_ref() {
            return Err(JobError::Busy(a.id.clone()));
        }
        let meta = self.store.create(&config, None).map_err(JobError::Store)?;
        self.launch(&mut active, meta.clone(), Work::Scan { config, resume: false });
        Ok(meta)
    }

    /// Resume a paused, interrupted or failed scan: its stored views are replayed and the missing
    /// positions acquired with the rig file stored in the scan (its plan and method) on this rig.
    pub fn resume(&self, id: &str) -> Result<ScanMeta, JobError> {
        let mut active = self.active.lock().map_err(|_| JobError::Busy(String::new()))?;
        if let Some(a) = active.as_ref() {
            return Err(JobError::Busy(a.id.clone()));
        }
        let mut meta = self.store.get(id).map_err(JobError::Store)?;
        if !meta.status.resumable() || meta.reprocess_of.is_some() {
            return Err(JobError::WrongState { id: id.to_owned(), status: meta.status, action: "resume" });
        }
        let config = self.stored_config(id)?;
        let before = meta.clone();
        meta.status = ScanStatus::Running;
        meta.error = None;
        meta.resumes += 1;
        meta.updated_unix = super::store::now_unix();
        if let Err(e) = self.store.save(&meta) {
            // Not resumed (the disk is full): the scan keeps the status it had.
            let _ = self.store.save(&before);
            return Err(JobError::Store(e));
        }
        self.launch(&mut active, meta.clone(), Work::Scan { config, resume: true });
        Ok(meta)
    }

    /// Reconstruct the stored views of scan `id` again with `req`'s settings into a new scan entry
    /// (`reprocess_of` = `id`), leaving the original untouched.
    pub fn reprocess(&self, id: &str, req: ReprocessRequest) -> Result<ScanMeta, JobError> {
        let source = self.store.get(id).map_err(JobError::Store)?;
        if source.status == ScanStatus::Running {
            return Err(JobError::WrongState { id: id.to_owned(), status: source.status, action: "reprocess" });
        }
        let mut config = self.stored_config(id)?;
        let stored_method = config.reconstruction.method;
        if let Some(m) = req.method {
            if !views_serve(stored_method, m) {
                return Err(JobError::Invalid {
                    field: "method".into(),
                    problem: format!("the views of a {stored_method} scan cannot be reconstructed with {m}"),
                });
            }
            config.reconstruction.method = m;
        }
        if let Some(r) = req.resolution {
            config.reconstruction.resolution = r;
        }
        if let Some(r) = req.smooth_radius {
            config.reconstruction.mesh.smooth_radius = r;
        }
        let config = validated(config)?;
        let mut active = self.active.lock().map_err(|_| JobError::Busy(String::new()))?;
        if let Some(a) = active.as_ref() {
            return Err(JobError::Busy(a.id.clone()));
        }
        let meta = self.store.create(&config, Some(id)).map_err(JobError::Store)?;
        self.launch(&mut active, meta.clone(), Work::Reprocess { config, source: self.store.dir(id) });
        Ok(meta)
    }

    /// How long the finishing stage (meshing, export: from the last view to the results on disk)
    /// of a job with `config` should take, seconds: the `after_last_frame_s` of the newest
    /// complete stored scan of the same method, scaled by the cube of the resolution ratio (the
    /// finishing work grows with the voxels). `None` when no such scan is stored.
    fn finishing_estimate(&self, config: &RigConfig) -> Option<f64> {
        let method = config.reconstruction.method;
        let scans = self.store.list().ok()?;
        scans.iter().rev().filter(|m| m.method == method && m.status == ScanStatus::Complete).find_map(|m| {
            let bytes = std::fs::read(self.store.dir(&m.id).join("report.json")).ok()?;
            let report: serde_json::Value = serde_json::from_slice(&bytes).ok()?;
            let then = report["timings_s"]["after_last_frame_s"].as_f64()?;
            let ratio = f64::from(config.reconstruction.resolution) / f64::from(m.resolution.max(1));
            Some(then * ratio.powi(3))
        })
    }

    /// The rig file stored with scan `id`.
    fn stored_config(&self, id: &str) -> Result<RigConfig, JobError> {
        crate::rigfile::load(&self.store.dir(id).join(crate::scan::driver::RIG_FILE))
            .map_err(|source| JobError::StoredConfig { id: id.to_owned(), source })
    }

    /// Pause the running scan `id` at the next step boundary.
    pub fn pause(&self, id: &str) -> Result<(), JobError> {
        self.stop(id, true)
    }

    /// Cancel scan `id`: a running one stops at the next step boundary; a paused or interrupted one
    /// is marked cancelled.
    pub fn cancel(&self, id: &str) -> Result<(), JobError> {
        match self.stop(id, false) {
            Err(JobError::WrongState { status, .. }) if status.resumable() => {
                self.store.set_status(id, ScanStatus::Cancelled, None).map_err(JobError::Store)?;
                Ok(())
            }
            other => other,
        }
    }

    fn stop(&self, id: &str, pause: bool) -> Result<(), JobError> {
        let active = self.active.lock().map_err(|_| JobError::Busy(String::new()))?;
        match active.as_ref() {
            Some(a) if a.id == id => {
                a.pause.store(pause, Ordering::SeqCst);
                a.cancel.cancel();
                Ok(())
            }
            _ => {
                let meta = self.store.get(id).map_err(JobError::Store)?;
                Err(JobError::WrongState {
                    id: id.to_owned(),
                    status: meta.status,
                    action: if pause { "pause" } else { "cancel" },
                })
            }
        }
    }

    /// Stop the running scan for shutdown; it is left `interrupted` so it can be resumed.
    pub fn shutdown(&self) {
        self.shutting_down.store(true, Ordering::SeqCst);
        if let Ok(active) = self.active.lock() {
            if let Some(a) = active.as_ref() {
                a.cancel.cancel();
            }
        }
    }

    fn launch(&self, active: &mut Option<Active>, meta: ScanMeta, work: Work) {
        let cancel = CancelToken::new();
        let pause = Arc::new(AtomicBool::new(false));
        let hardware = matches!(work, Work::Scan { .. });
        let reads = meta.reprocess_of.clone();
        *active = Some(Active { id: meta.id.clone(), cancel: cancel.clone(), pause: pause.clone(), hardware, reads });
        self.metrics.scans_started.fetch_add(1, Ordering::Relaxed);
        let (config, what) = match &work {
            Work::Scan { config, resume: true } => (config, "resuming"),
            Work::Scan { config, .. } => (config, "starting"),
            Work::Reprocess { config, .. } => (config, "reprocessing"),
        };
        let total = config.scan.positions as usize;
        let id = meta.id.clone();
        let started = Instant::now();
        self.progress.send_replace(ProgressSnapshot {
            scan_id: Some(id.clone()),
            status: Some(ScanStatus::Running),
            step: 0,
            total,
            stage: "starting".into(),
            message: format!("{what}: {}", config.reconstruction.method),
            elapsed_s: 0.0,
            remaining_s: None,
        });
        self.live.send_replace(None);
        let finishing = self.finishing_estimate(config);
        let events = progress_sink(
            self.progress.clone(),
            self.live.clone(),
            id.clone(),
            self.metrics.clone(),
            started,
            finishing,
        );
        let live = Some(LiveSpec::default());
        let out = self.store.dir(&id);
        let this = self.clone();
        match work {
            Work::Scan { config, resume } => {
                let job = ScanJob { out, resume, config: Arc::new(config), cancel, events, live };
                tokio::spawn(async move {
                    let result = this.rig.scan(job).await;
                    this.finish(&id, result, pause.load(Ordering::SeqCst), started);
                });
            }
            Work::Reprocess { config, source } => {
                tokio::spawn(async move {
                    let job = tokio::task::spawn_blocking(move || {
                        let mut events = events;
                        crate::scan::reprocess(&config, &source, &out, &cancel, &mut *events, live)
                            .map_err(RigError::Scan)
                    });
                    let result = job.await.unwrap_or(Err(RigError::Stopped));
                    this.finish(&id, result, pause.load(Ordering::SeqCst), started);
                });
            }
        }
    }

    fn finish(&self, id: &str, result: Result<crate::scan::Report, RigError>, paused: bool, started: Instant) {
        let (status, error) = match &result {
            Ok(report) => {
                self.metrics.scans_completed.fetch_add(1, Ordering::Relaxed);
                self.metrics.add_timings(&report.timings_s);
                (ScanStatus::Complete, None)
            }
            Err(RigError::Scan(ScanError::Acquisition(AcquisitionError::Cancelled { .. }))) => {
                self.metrics.scans_stopped.fetch_add(1, Ordering::Relaxed);
                if self.shutting_down.load(Ordering::SeqCst) {
                    (ScanStatus::Interrupted, None)
                } else if paused {
                    (ScanStatus::Paused, None)
                } else {
                    (ScanStatus::Cancelled, None)
                }
            }
            Err(e) => {
                self.metrics.scans_failed.fetch_add(1, Ordering::Relaxed);
                (ScanStatus::Failed, Some(error_chain(e)))
            }
        };
        match &error {
            Some(e) => tracing::warn!(scan = id, error = %e, "scan failed"),
            None => tracing::info!(scan = id, ?status, "scan finished"),
        }
        // Record the status and free the slot under one lock, so that a client who sees the scan
        // finished can start the next one at once (no 409 in between).
        let mut active = self.active.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        if let Err(e) = self.store.set_status(id, status, error.clone()) {
            tracing::error!(scan = id, error = %error_chain(&e), "cannot record the scan's status");
        }
        if let (ScanStatus::Complete, Some(queue)) = (status, &self.replication) {
            queue.enqueue(id);
        }
        *active = None;
        drop(active);
        self.progress.send_modify(|p| {
            p.status = Some(status);
            p.elapsed_s = started.elapsed().as_secs_f64();
            p.stage = status.to_string();
            p.message = error.unwrap_or_else(|| p.stage.clone());
            if status == ScanStatus::Complete {
                p.step = p.total;
                p.remaining_s = Some(0.0);
            } else {
                p.remaining_s = None;
            }
        });
    }
}

/// Whether the stored views of a `stored` scan can be reconstructed with `wanted`: the same method,
/// or another of the silhouette methods (their views are the same frames).
fn views_serve(stored: Method, wanted: Method) -> bool {
    let silhouette = |m: Method| matches!(m, Method::SpaceCarving | Method::VoxelColoring | Method::SpaceCarvingPhoto);
    stored == wanted || (silhouette(stored) && silhouette(wanted))
}

/// Seconds until a job's results are on disk.
///
/// `per_view_s` is this run's pace (seconds per view captured and processed, views replayed on
/// resume left out), `views_left` the views still to capture and process, `finishing_s` the
/// expected length of the method's finishing stage (see `Jobs::finishing_estimate`; without one,
/// one view's time), and `finishing_for_s` how long the finishing stage has already run once
/// every view is in (`None` before that). The finishing part counts down and stays at 0 once it
/// overruns.
pub fn remaining_estimate(
    per_view_s: f64,
    views_left: usize,
    finishing_s: Option<f64>,
    finishing_for_s: Option<f64>,
) -> f64 {
    let finishing = finishing_s.unwrap_or(per_view_s);
    match finishing_for_s {
        Some(t) => (finishing - t).max(0.0),
        None => per_view_s * views_left as f64 + finishing,
    }
}

/// The progress sink of a job: turns scan events into the published snapshot.
/// Live previews go to `live`, as the estimate of scan `scan_id`.
fn progress_sink(
    progress: Arc<watch::Sender<ProgressSnapshot>>,
    live: Arc<watch::Sender<Option<LiveModel>>>,
    scan_id: String,
    metrics: Arc<Metrics>,
    started: Instant,
    finishing_s: Option<f64>,
) -> Box<dyn FnMut(ScanEvent) + Send> {
    let mut first_new: Option<(usize, Instant)> = None;
    let mut version = 0;
    let mut per_view_s: Option<f64> = None;
    let mut last_view = Instant::now();
    Box::new(move |e: ScanEvent| {
        if let ScanEvent::Preview { position, cloud, .. } = &e {
            version += 1;
            let model = LiveModel {
                scan_id: scan_id.clone(),
                version,
                position: *position,
                points: cloud.len(),
                ply: axum::body::Bytes::from(cloud.ply_bytes()),
            };
            live.send_replace(Some(model));
            return;
        }
        progress.send_modify(|p| {
            p.elapsed_s = started.elapsed().as_secs_f64();
            match &e {
                ScanEvent::Acquisition(a) => {
                    p.stage = a.stage.to_string();
                    p.message = format!("position {} of {}: {}", (a.step + 1).min(a.total), a.total, p.stage);
                }
                ScanEvent::ViewProcessed { position, total, message } => {
                    p.step = position + 1;
                    p.total = *total;
                    p.stage = "processing".into();
                    p.message = format!("view {} of {total}: {message}", position + 1);
                    metrics.frames.fetch_add(1, Ordering::Relaxed);
                    // The pace of views captured and processed in this run (replayed ones come fast).
                    let (k0, t0) = *first_new.get_or_insert((p.step, Instant::now()));
                    let done = p.step.saturating_sub(k0);
                    last_view = Instant::now();
                    if done > 0 {
                        let per = t0.elapsed().as_secs_f64() / done as f64;
                        per_view_s = Some(per);
                        p.remaining_s =
                            Some(remaining_estimate(per, p.total.saturating_sub(p.step), finishing_s, None));
                    }
                }
                ScanEvent::Preview { .. } => {}
                ScanEvent::Stage(s) => {
                    p.stage = (*s).to_owned();
                    if p.step >= p.total {
                        p.message = format!("reconstruction: {s}");
                        let since = Some(last_view.elapsed().as_secs_f64());
                        p.remaining_s = per_view_s
                            .or(finishing_s)
                            .map(|per| remaining_estimate(per, 0, finishing_s, since))
                            .or(Some(0.0));
                    } else {
                        p.message = format!("view {} of {}: {s}", p.step + 1, p.total);
                    }
                }
            }
        });
    })
}

#[cfg(test)]
mod remaining_tests {
    use super::remaining_estimate;

    #[test]
    fn remaining_time_counts_the_views_left_and_the_finishing_stage() {
        // 2 s a view, 5 views left, finishing measured at 3 s: 13 s.
        assert_eq!(remaining_estimate(2.0, 5, Some(3.0), None), 13.0);
        // No finishing figure yet: one view's time stands for it.
        assert_eq!(remaining_estimate(2.0, 5, None, None), 12.0);
        // Finishing, 1 s in: 2 s left; overrun: 0.
        assert_eq!(remaining_estimate(2.0, 0, Some(3.0), Some(1.0)), 2.0);
        assert_eq!(remaining_estimate(2.0, 0, Some(3.0), Some(9.0)), 0.0);
    }
}

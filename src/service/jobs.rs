//! Scan jobs: at most one scan runs at a time; start, pause (stop at a step boundary, resumable),
//! resume (from the last complete frame on disk), cancel. Progress is published on a watch channel.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use serde::{Deserialize, Serialize};
use tokio::sync::watch;

use crate::acquisition::{AcquisitionError, CancelToken};
use crate::config::{Method, RigConfig};
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
    /// Estimated seconds until the views are all captured, from the pace so far.
    pub remaining_s: Option<f64>,
}

/// What a client may ask for when starting a scan; missing fields take the rig file's values.
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StartRequest {
    /// Reconstruction method; must equal the rig file's (space carving or a photo method).
    pub method: Option<String>,
    /// Turntable positions, 3..=720.
    pub positions: Option<u32>,
    /// Lights on for each frame, by index.
    pub lights: Option<Vec<usize>>,
}

/// Why a job request was refused.
#[derive(Debug, thiserror::Error)]
pub enum JobError {
    /// A scan is already running.
    #[error("scan {0} is already running")]
    Busy(String),
    /// The request is not acceptable.
    #[error("invalid request: {field}: {problem}")]
    Invalid {
        /// The offending field.
        field: &'static str,
        /// What is wrong with it.
        problem: &'static str,
    },
    /// The scan is not in a state that allows this.
    #[error("scan {id} is {status:?}; cannot {action}")]
    WrongState {
        /// The scan.
        id: String,
        /// Its status.
        status: ScanStatus,
        /// What was asked.
        action: &'static str,
    },
    /// The store failed.
    #[error("scan store")]
    Store(#[source] StoreError),
}

struct Active {
    id: String,
    cancel: CancelToken,
    pause: Arc<AtomicBool>,
}

/// The scan jobs of one daemon.
#[derive(Clone)]
pub struct Jobs {
    store: Arc<ScanStore>,
    rig: RigHandle,
    metrics: Arc<Metrics>,
    progress: Arc<watch::Sender<ProgressSnapshot>>,
    active: Arc<Mutex<Option<Active>>>,
    shutting_down: Arc<AtomicBool>,
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
            active: Arc::new(Mutex::new(None)),
            shutting_down: Arc::new(AtomicBool::new(false)),
        }
    }

    /// The store.
    pub fn store(&self) -> &ScanStore {
        &self.store
    }

    /// Subscribe to progress.
    pub fn subscribe(&self) -> watch::Receiver<ProgressSnapshot> {
        self.progress.subscribe()
    }

    /// The latest progress.
    pub fn progress(&self) -> ProgressSnapshot {
        self.progress.borrow().clone()
    }

    /// The id of the running scan.
    pub fn running(&self) -> Option<String> {
        self.active.lock().ok().and_then(|a| a.as_ref().map(|a| a.id.clone()))
    }

    /// Start a new scan with `config` adjusted by `req`.
    pub fn start(&self, config: &RigConfig, req: StartRequest) -> Result<ScanMeta, JobError> {
        let mut config = config.clone();
        if let Some(m) = &req.method {
            if m != config.reconstruction.method.name() {
                return Err(JobError::Invalid {
                    field: "method",
                    problem: "the method is the rig file's `reconstruction.method`; change it there and reload",
                });
            }
        }
        // The daemon's scan job runs the silhouette pipeline (space carving and the photo methods);
        // the methods with their own acquisition run through `scanrig scan` for now. Refuse them
        // rather than run something else under their name.
        if matches!(config.reconstruction.method, Method::ShadowCarving | Method::DepthFusion | Method::StructuredLight)
        {
            return Err(JobError::Invalid {
                field: "method",
                problem:
                    "shadow-carving, depth-fusion and structured-light scans run with `scanrig scan`, not yet in the \
                          daemon",
            });
        }
        if config.reconstruction.method == Method::Laser {
            return Err(JobError::Invalid {
                field: "method",
                problem: "laser scans run with `scanrig scan`, not yet in the daemon",
            });
        }
        if let Some(n) = req.positions {
            if !(3..=720).contains(&n) {
                return Err(JobError::Invalid { field: "positions", problem: "must be 3..=720" });
            }
            config.scan.positions = n;
        }
        if let Some(l) = req.lights {
            let count = config.lights.as_ref().map_or(0, |l| l.lights.len());
            if l.len() > 64 {
                return Err(JobError::Invalid {
                    field: "lights",
                    problem: "at most 64 entries (one per light switched on)",
                });
            }
            if l.iter().any(|&i| i >= count) {
                return Err(JobError::Invalid {
                    field: "lights",
                    problem: "a light index is not one of the rig's lights",
                });
            }
            config.scan.lights = l;
        }
        let mut active = self.active.lock().map_err(|_| JobError::Busy(String::new()))?;
        if let Some(a) = active.as_ref() {
            return Err(JobError::Busy(a.id.clone()));
        }
        let meta = self
            .store
            .create(
                &config.rig.name,
                config.reconstruction.method.name(),
                config.scan.positions,
                config.scan.lights.clone(),
            )
            .map_err(JobError::Store)?;
        self.launch(&mut active, meta.clone(), config, false);
        Ok(meta)
    }

    /// Resume a paused, interrupted or failed scan from its last complete frame, with `config`'s
    /// devices and the plan recorded in the scan.
    pub fn resume(&self, config: &RigConfig, id: &str) -> Result<ScanMeta, JobError> {
        let mut active = self.active.lock().map_err(|_| JobError::Busy(String::new()))?;
        if let Some(a) = active.as_ref() {
            return Err(JobError::Busy(a.id.clone()));
        }
        let mut meta = self.store.get(id).map_err(JobError::Store)?;
        if !meta.status.resumable() {
            return Err(JobError::WrongState { id: id.to_owned(), status: meta.status, action: "resume" });
        }
        let mut config = config.clone();
        config.scan.positions = meta.positions;
        config.scan.lights.clone_from(&meta.lights);
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
        self.launch(&mut active, meta.clone(), config, true);
        Ok(meta)
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

    fn launch(&self, active: &mut Option<Active>, meta: ScanMeta, config: RigConfig, resume: bool) {
        let cancel = CancelToken::new();
        let pause = Arc::new(AtomicBool::new(false));
        *active = Some(Active { id: meta.id.clone(), cancel: cancel.clone(), pause: pause.clone() });
        self.metrics.scans_started.fetch_add(1, Ordering::Relaxed);
        let total = config.scan.positions as usize;
        let id = meta.id.clone();
        let started = Instant::now();
        self.progress.send_replace(ProgressSnapshot {
            scan_id: Some(id.clone()),
            status: Some(ScanStatus::Running),
            step: 0,
            total,
            stage: "starting".into(),
            message: if resume { "resuming".into() } else { "starting".into() },
            elapsed_s: 0.0,
            remaining_s: None,
        });
        let progress = self.progress.clone();
        let metrics = self.metrics.clone();
        let mut first_new: Option<(usize, Instant)> = None;
        let events = Box::new(move |e: ScanEvent| {
            progress.send_modify(|p| {
                p.elapsed_s = started.elapsed().as_secs_f64();
                match &e {
                    ScanEvent::Acquisition(a) => {
                        p.stage = format!("{:?}", a.stage).to_ascii_lowercase();
                        p.message = format!("position {} of {}: {}", (a.step + 1).min(a.total), a.total, p.stage);
                    }
                    ScanEvent::ViewProcessed { position, occupied } => {
                        p.step = position + 1;
                        p.stage = "carving".into();
                        p.message = format!("view {} carved, {occupied} voxels left", position + 1);
                        metrics.frames.fetch_add(1, Ordering::Relaxed);
                        // The pace of views captured in this run (reused ones come instantly).
                        let (k0, t0) = *first_new.get_or_insert((p.step, Instant::now()));
                        let done = p.step.saturating_sub(k0);
                        if done > 0 {
                            let per = t0.elapsed().as_secs_f64() / done as f64;
                            p.remaining_s = Some(per * p.total.saturating_sub(p.step) as f64);
                        }
                    }
                    ScanEvent::Stage(s) => {
                        p.stage = (*s).to_owned();
                        p.message = format!("reconstruction: {s}");
                        p.remaining_s = Some(0.0);
                    }
                }
            });
        });
        let job = ScanJob { out: self.store.dir(&id), resume, config: Arc::new(config), cancel, events };
        let this = self.clone();
        tokio::spawn(async move {
            let result = this.rig.scan(job).await;
            this.finish(&id, result, pause.load(Ordering::SeqCst), started);
        });
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
        let mut active = self.active.lock().unwrap_or_else(|p| p.into_inner());
        if let Err(e) = self.store.set_status(id, status, error.clone()) {
            tracing::error!(scan = id, error = %error_chain(&e), "cannot record the scan's status");
        }
        *active = None;
        drop(active);
        self.progress.send_modify(|p| {
            p.status = Some(status);
            p.elapsed_s = started.elapsed().as_secs_f64();
            p.stage = format!("{status:?}").to_ascii_lowercase();
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

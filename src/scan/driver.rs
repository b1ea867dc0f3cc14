//! The one scan-job driver: everything a scan does whatever its method. It prepares the output
//! directory and stores the effective rig file in it, replays the views already stored (a resumed
//! scan, a reprocess), runs the acquisition of the missing positions on a thread of its own over a
//! bounded channel while each arriving view is stored and processed, then has the method finish and
//! writes the results, the ground truth and `report.json` (last). The method's part is a
//! [`ScanFlow`]; the CLI (`scanrig scan`, `scanrig reconstruct --scan`) and the daemon's jobs both
//! call [`run_job`].

use std::path::Path;
use std::sync::mpsc;
use std::time::Instant;

use nalgebra::Vector3;

use super::flow::{Finish, FrameDir, PositionView, ScanFlow, ViewRecord};
use super::methods::photo::Truth;
use super::output::{self, OutputDir};
use super::preview::LiveSpec;
use super::report::{Report, Timings};
use super::{ScanError, ScanEvent};
use crate::acquisition::{AcquisitionError, AcquisitionSummary, CancelToken, Progress};
use crate::config::RigConfig;
use crate::devices::Rig;
use crate::geometry::VoxelGrid;
use crate::pipeline::Occupancy;
use crate::sim::SimWorld;

/// Where a job's views come from.
#[derive(Debug)]
pub enum Source<'a> {
    /// Acquire on this rig into the output directory. With `resume`, the views already complete in
    /// its `frames/` are replayed and only the missing positions are acquired.
    Rig {
        /// The rig's devices, owned by the caller's thread for the job.
        rig: &'a mut Rig,
        /// Continue an interrupted scan in the same directory.
        resume: bool,
    },
    /// Replay every complete view of a stored scan (no hardware); the results go to the job's
    /// output directory, which must not be the stored scan's.
    Stored {
        /// The stored scan's directory (with `frames/`).
        scan_dir: &'a Path,
    },
}

/// One scan job.
pub struct Job<'a> {
    /// The effective configuration (rig file plus request overrides, validated).
    pub config: &'a RigConfig,
    /// The output directory.
    pub out: &'a Path,
    /// Where the views come from.
    pub source: Source<'a>,
    /// Stops the acquisition at the next step boundary.
    pub cancel: &'a CancelToken,
    /// Progress sink.
    pub events: &'a mut dyn FnMut(ScanEvent),
    /// Publish live previews of the estimate among the events (`None`: no previews, as on the
    /// command line).
    pub live: Option<LiveSpec>,
}

impl std::fmt::Debug for Job<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Job").field("out", &self.out).field("source", &self.source).finish_non_exhaustive()
    }
}

/// The name of the effective rig file stored in every scan directory.
pub const RIG_FILE: &str = "rig.toml";

/// Run `job` with the flow of its configuration's method.
pub fn run_job(job: Job<'_>) -> Result<Report, ScanError> {
    // The simulated world, for ground truth: the rig's, or for a stored scan its rig file's.
    let world = match &job.source {
        Source::Rig { rig, .. } => rig.sim.clone(),
        Source::Stored { .. } => match &job.config.sim {
            Some(s) => Some(SimWorld::from_config(s, job.config).map_err(ScanError::SimWorld)?),
            None => None,
        },
    };
    super::methods::run_with_flow(job, world)
}

/// Run `job` with `flow`; `world` is the simulated scene the result is compared with.
pub(crate) fn drive<F: ScanFlow>(mut flow: F, job: Job<'_>, world: Option<SimWorld>) -> Result<Report, ScanError> {
    let started = Instant::now();
    let Job { config, out, source, cancel, events, live } = job;
    let mut publisher = live.map(Publisher::new);
    let recon = &config.reconstruction;
    let grid = VoxelGrid::from_resolution(&recon.bbox(), recon.resolution);
    let total = config.scan.positions as usize;
    let mut timings = Timings::default();

    // The output directory and where the views come from.
    let (out_dir, frames, stored, mut rig, reprocessed_from) = match source {
        Source::Rig { rig, resume } => {
            let out_dir = if resume { OutputDir::reopen(out)? } else { OutputDir::prepare(out)? };
            out_dir.write_rig_file(config)?;
            let frames = FrameDir::of_scan(out_dir.path());
            frames.create()?;
            let stored = if resume { frames.complete_records(total)? } else { Vec::new() };
            (out_dir, frames, stored, Some(rig), None)
        }
        Source::Stored { scan_dir } => {
            let out_dir = OutputDir::prepare_result(out, scan_dir)?;
            let frames = FrameDir::of_scan(scan_dir);
            let stored = frames.complete_records(total)?;
            if stored.is_empty() {
                return Err(ScanError::NoStoredViews { dir: frames.path().to_owned() });
            }
            (out_dir, frames, stored, None, Some(scan_dir.display().to_string()))
        }
    };

    // What the method measured before the positions: read back, else measured on the rig.
    let restored = if stored.is_empty() && rig.is_some() { false } else { flow.restore(&frames)? };
    if !restored {
        match rig.as_deref_mut() {
            Some(rig) => flow.prepare(rig, &frames, cancel, events)?,
            None => return Err(ScanError::NotPrepared { dir: frames.path().to_owned(), method: flow.method() }),
        }
    }

    // Ground truth on simulated rigs: the scene's occupancy on the grid depends on nothing the scan
    // measures, so it is computed while the views are processed and acquired, not after the last.
    let truth_job = world.as_ref().map(|w| {
        let scene = w.scene().clone();
        std::thread::spawn(move || Occupancy::from_fn(grid, |p| scene.contains(&p)))
    });

    // Stored views first, in position order.
    let mut last_view_at = Instant::now();
    if !stored.is_empty() {
        events(ScanEvent::Stage("replaying stored views"));
    }
    let t = Instant::now();
    for record in &stored {
        if cancel.is_cancelled() {
            return Err(ScanError::Acquisition(AcquisitionError::Cancelled { completed: record.position, total }));
        }
        let view = flow.load(&frames, record)?;
        let message = flow.process(view, events)?;
        events(ScanEvent::ViewProcessed { position: record.position, total, message });
        if let Some(p) = publisher.as_mut() {
            p.offer(&flow, record.position, total, record.position + 1 == stored.len(), events);
        }
        last_view_at = Instant::now();
    }
    if !stored.is_empty() {
        timings.capture += t.elapsed().as_secs_f64();
    }

    // The missing positions, acquired while the views are processed.
    let first = stored.len();
    let mut acquired = None;
    if let Some(rig) = rig {
        if first < total {
            let sequence = flow.sequence(first);
            let (summary, capture_s) = acquire_and_process(rig, sequence, cancel, events, |view, events| {
                let Some(view) = view else {
                    // No view for a moment (moving, exposing, paused): publish the estimate a
                    // rate-limited view skipped, so a paused scan shows its newest one.
                    if let Some(p) = publisher.as_mut() {
                        p.flush(&flow, events);
                    }
                    return Ok(());
                };
                last_view_at = Instant::now();
                let (files, lights_on) = flow.save(&frames, &view)?;
                let record = ViewRecord {
                    position: view.position(),
                    angle_deg: view.angle_deg(),
                    files,
                    lights_on,
                    sequence: view.sequence(),
                    stale_discarded: view.stale_discarded(),
                };
                // The record goes last: a position is complete on disk iff its record exists.
                frames.write_json(&format!("{}.json", FrameDir::stem(record.position)), &record)?;
                let message = flow.process(view, events)?;
                events(ScanEvent::ViewProcessed { position: record.position, total, message });
                if let Some(p) = publisher.as_mut() {
                    p.offer(&flow, record.position, total, record.position + 1 == total, events);
                }
                Ok(())
            })?;
            timings.capture += capture_s;
            acquired = Some(summary);
        } else {
            acquired = Some(AcquisitionSummary::default());
        }
    }
    let frames_summary = acquired.map(|mut s| {
        s.views += first;
        s
    });

    let truth_occupancy = truth_job.map(|job| job.join().unwrap_or_else(|panic| std::panic::resume_unwind(panic)));
    let colour_at = |p: &Vector3<f64>| world.as_ref().map_or([0, 0, 0], |w| w.scene().colour_at(p));
    let truth = truth_occupancy.as_ref().map(|occupancy| Truth { occupancy, colour_at: &colour_at });

    let method = flow.method();
    let outcome = flow.finish(Finish { grid, truth: truth.as_ref(), timings: &mut timings, events })?;
    let report = out_dir.write_outcome(output::Results {
        source: config.rig.name.clone(),
        method,
        reprocessed_from,
        outcome,
        mesh_max_error_voxels: config.reconstruction.mesh.max_error_voxels,
        truth: world.as_ref().zip(truth_occupancy.as_ref()).map(|(w, occ)| output::TruthRef {
            scene: w.scene(),
            scene_name: config.sim.as_ref().map_or("", |s| s.scene.as_str()),
            occupancy: occ,
        }),
        frames: frames_summary,
        timings,
        started,
        last_view_at,
        events,
    })?;
    Ok(report)
}

/// Run an acquisition `sequence` on a thread of its own (it owns the rig's devices for the whole
/// sequence) while `process` handles each view on this thread as it arrives, over a bounded channel
/// so a slow pipeline slows the rig instead of piling up frames. The sequence's progress is forwarded
/// to `events`. `process` gets `Some(view)` for each view and `None` whenever no view came for
/// 50 ms (the rig is moving, exposing or paused: time for deferred work). The first error of
/// `process` stops the pipeline: dropping the receiver makes the
/// sequence stop with `PipelineGone` and park, and that error is returned rather than the
/// acquisition's. Returns the acquisition summary and the sequence's busy time, seconds.
fn acquire_and_process<V: Send>(
    rig: &mut Rig,
    sequence: super::flow::Sequence<V>,
    cancel: &CancelToken,
    events: &mut dyn FnMut(ScanEvent),
    mut process: impl FnMut(Option<V>, &mut dyn FnMut(ScanEvent)) -> Result<(), ScanError>,
) -> Result<(AcquisitionSummary, f64), ScanError> {
    let (tx, rx) = mpsc::sync_channel::<V>(4);
    let (progress_tx, progress_rx) = mpsc::channel::<Progress>();
    let mut pipeline_error = None;
    let (result, busy_s) = std::thread::scope(|scope| {
        let acquisition = std::thread::Builder::new()
            .name("acquisition".into())
            .spawn_scoped(scope, move || {
                let t = Instant::now();
                let result = sequence(rig, &tx, cancel, &mut |p| {
                    let _ = progress_tx.send(p.clone());
                });
                (result, t.elapsed().as_secs_f64())
            })
            .map_err(ScanError::StartAcquisition)?;
        loop {
            // Forward progress while waiting for the next view, so a slow position still shows
            // what the rig is doing.
            match rx.recv_timeout(std::time::Duration::from_millis(50)) {
                Ok(view) => {
                    for p in progress_rx.try_iter() {
                        events(ScanEvent::Acquisition(p));
                    }
                    if let Err(e) = process(Some(view), events) {
                        pipeline_error = Some(e);
                        break;
                    }
                }
                Err(mpsc::RecvTimeoutError::Timeout) => {
                    for p in progress_rx.try_iter() {
                        events(ScanEvent::Acquisition(p));
                    }
                    if let Err(e) = process(None, events) {
                        pipeline_error = Some(e);
                        break;
                    }
                }
                Err(mpsc::RecvTimeoutError::Disconnected) => break,
            }
        }
        drop(rx);
        acquisition.join().map_err(|_| ScanError::AcquisitionPanicked)
    })?;
    for p in progress_rx.try_iter() {
        events(ScanEvent::Acquisition(p));
    }
    if let Some(e) = pipeline_error {
        return Err(e);
    }
    Ok((result.map_err(ScanError::Acquisition)?, busy_s))
}

/// When a job publishes its live previews: after a view, when [`LiveSpec::min_interval`] has passed
/// since the last one, always after the last view, and, for a view skipped by the rate limit,
/// as soon as the pipeline is idle and the interval has passed ([`Publisher::flush`]).
struct Publisher {
    spec: LiveSpec,
    last: Option<Instant>,
    /// The (position, total) of the newest view whose estimate was not published yet.
    pending: Option<(usize, usize)>,
}

impl Publisher {
    fn new(spec: LiveSpec) -> Publisher {
        Publisher { spec, last: None, pending: None }
    }

    /// Publish the estimate of a view the rate limit skipped, if the interval has passed.
    fn flush<F: ScanFlow>(&mut self, flow: &F, events: &mut dyn FnMut(ScanEvent)) {
        if let Some((position, total)) = self.pending {
            self.offer(flow, position, total, false, events);
        }
    }

    fn offer<F: ScanFlow>(
        &mut self,
        flow: &F,
        position: usize,
        total: usize,
        last_view: bool,
        events: &mut dyn FnMut(ScanEvent),
    ) {
        let due = last_view || self.last.is_none_or(|t| t.elapsed() >= self.spec.min_interval);
        if !due {
            self.pending = Some((position, total));
            return;
        }
        self.pending = None;
        if let Some(cloud) = flow.preview(self.spec.max_points) {
            events(ScanEvent::Preview { position, total, cloud: std::sync::Arc::new(cloud) });
            self.last = Some(Instant::now());
        }
    }
}

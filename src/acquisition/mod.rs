//! Scan sequences: what to move, switch and capture, in what order, and the rule that only fresh
//! frames reach the pipeline.
//!
//! A sequence runs on the thread that owns the rig's devices and streams [`CapturedView`]s over a
//! bounded channel, so a slow pipeline slows the rig down instead of piling up frames in memory.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::SyncSender;
use std::sync::Arc;
use std::time::{Duration, Instant};

mod depth;
mod laser;
mod per_light;
mod structured;

pub use depth::{capture_fresh_depth, run_depth_scan, DepthView};
pub use laser::{run_laser_scan, LaserView};
pub use per_light::{run_per_light_scan, PerLightView};
pub use structured::{run_structured_light_scan, PatternStack};

use crate::config::ScanPlan;
use crate::devices::{DeviceError, Frame, Rig};

/// A cancellation flag shared between whoever runs a sequence and whoever may stop it. The sequence
/// checks it between steps; a step in progress (a move, a capture) finishes first.
#[derive(Debug, Clone, Default)]
pub struct CancelToken(Arc<AtomicBool>);

impl CancelToken {
    /// A token that is not cancelled.
    pub fn new() -> Self {
        Self::default()
    }
    /// Ask the sequence to stop at the next step boundary.
    pub fn cancel(&self) {
        self.0.store(true, Ordering::SeqCst);
    }
    /// Whether [`CancelToken::cancel`] was called.
    pub fn is_cancelled(&self) -> bool {
        self.0.load(Ordering::SeqCst)
    }
}

/// One captured view with everything the pipeline needs to know about how it was taken.
#[derive(Debug, Clone)]
pub struct CapturedView {
    /// 0-based index of the turntable position in the plan.
    pub position: usize,
    /// Turntable angle the frame was taken at, degrees (as reported by the turntable, i.e. quantised
    /// to whole steps).
    pub angle_deg: f64,
    /// Indices of the lights that were on (full level).
    pub lights_on: Vec<usize>,
    /// The fresh frame.
    pub frame: Frame,
    /// Stale frames thrown away before this one.
    pub stale_discarded: u32,
}

/// Where a sequence is.
#[derive(Debug, Clone, PartialEq)]
pub struct Progress {
    /// Positions completed so far.
    pub step: usize,
    /// Positions in the plan.
    pub total: usize,
    /// What is happening now.
    pub stage: Stage,
}

/// What a sequence is doing.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Stage {
    /// Turning the table.
    Moving,
    /// Waiting for vibrations to die down.
    Settling,
    /// Switching lights.
    Lighting,
    /// Capturing a frame.
    Capturing,
    /// Showing pattern `pattern` (1-based) of `of` and capturing it (structured light).
    Projecting {
        /// 1-based index of the pattern on screen.
        pattern: usize,
        /// Patterns per position.
        of: usize,
    },
    /// Parking the hardware.
    Parking,
    /// Finished.
    Done,
}

impl std::fmt::Display for Stage {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Stage::Moving => f.write_str("moving"),
            Stage::Settling => f.write_str("settling"),
            Stage::Lighting => f.write_str("switching lights"),
            Stage::Capturing => f.write_str("capturing"),
            Stage::Projecting { pattern, of } => write!(f, "projecting pattern {pattern}/{of}"),
            Stage::Parking => f.write_str("parking"),
            Stage::Done => f.write_str("done"),
        }
    }
}

/// Counters of a finished sequence.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct AcquisitionSummary {
    /// Views delivered to the pipeline.
    pub views: usize,
    /// Stale frames discarded in total.
    pub stale_discarded: u64,
    /// Frames the camera dropped (gaps in its sequence numbers).
    pub dropped: u64,
}

/// Why a sequence stopped early.
#[derive(Debug, thiserror::Error)]
pub enum AcquisitionError {
    /// A device failed during a step.
    #[error("{step} at position {position}")]
    Device {
        /// What the step was doing.
        step: &'static str,
        /// 0-based position index.
        position: usize,
        /// The device's error.
        #[source]
        source: DeviceError,
    },
    /// The camera kept delivering frames exposed before the last change.
    #[error("camera delivered {count} stale frames in a row at position {position}; is it streaming?")]
    StaleFrames {
        /// 0-based position index.
        position: usize,
        /// How many.
        count: u32,
    },
    /// The sequence was cancelled.
    #[error("cancelled after {completed} of {total} positions")]
    Cancelled {
        /// Positions completed.
        completed: usize,
        /// Positions planned.
        total: usize,
    },
    /// The consumer of the views went away (the pipeline failed).
    #[error("the reconstruction pipeline stopped taking frames at position {position}")]
    PipelineGone {
        /// 0-based position index.
        position: usize,
    },
    /// Parking after the sequence failed too (the original error, if any, is reported by the caller).
    #[error("could not park the rig after the scan")]
    Park {
        /// The device's error.
        #[source]
        source: DeviceError,
    },
}

/// The angle of position `i` of `plan`, degrees.
pub fn position_angle(plan: &ScanPlan, i: usize) -> f64 {
    plan.start_deg + 360.0 * i as f64 / plan.positions as f64
}

/// Run the turntable scan in `plan` on `rig` from position `first` (0-based; the positions before it
/// are taken as already captured, as in a resumed scan): for each position move, wait for the move
/// to finish, settle, set the lights, capture a fresh frame and send it to `views`. The lights are
/// switched off and the turntable parked at the end, also after an error or cancellation. The
/// summary counts only the views captured by this call.
pub fn run_turntable_scan(
    rig: &mut Rig,
    plan: &ScanPlan,
    first: usize,
    views: &SyncSender<CapturedView>,
    cancel: &CancelToken,
    progress: &mut dyn FnMut(&Progress),
) -> Result<AcquisitionSummary, AcquisitionError> {
    run_then_park(rig, plan, first, progress, |rig, progress| {
        turntable_scan_steps(rig, plan, first, views, cancel, progress)
    })
}

/// Run the steps of a sequence that starts at position `first`, then park the rig (see [`park`])
/// whatever happened, reporting the Parking and Done stages. An error of the steps wins over a
/// parking error, which is then logged.
pub(crate) fn run_then_park(
    rig: &mut Rig,
    plan: &ScanPlan,
    first: usize,
    progress: &mut dyn FnMut(&Progress),
    steps: impl FnOnce(&mut Rig, &mut dyn FnMut(&Progress)) -> Result<AcquisitionSummary, AcquisitionError>,
) -> Result<AcquisitionSummary, AcquisitionError> {
    let result = steps(rig, progress);
    let total = plan.positions as usize;
    progress(&Progress { step: result.as_ref().map_or(first, |s| first + s.views), total, stage: Stage::Parking });
    let parked = park(rig, plan);
    match (result, parked) {
        (Ok(summary), Ok(())) => {
            progress(&Progress { step: total, total, stage: Stage::Done });
            Ok(summary)
        }
        (Ok(_), Err(source)) => Err(AcquisitionError::Park { source }),
        (Err(e), parked) => {
            if let Err(p) = parked {
                tracing::error!(error = %p, "parking after a failed scan also failed");
            }
            Err(e)
        }
    }
}

/// Turn to position `position` of `plan`, wait until the move has finished, and settle. Returns the
/// angle the turntable reports, degrees.
pub(crate) fn move_and_settle(
    rig: &mut Rig,
    plan: &ScanPlan,
    position: usize,
    progress: &mut dyn FnMut(&Progress),
) -> Result<f64, AcquisitionError> {
    let total = plan.positions as usize;
    progress(&Progress { step: position, total, stage: Stage::Moving });
    rig.turntable
        .move_to(position_angle(plan, position), Duration::from_millis(plan.move_timeout_ms))
        .map_err(|source| AcquisitionError::Device { step: "turning the table", position, source })?;
    let angle_deg = rig.turntable.angle();
    if plan.settle_ms > 0 {
        progress(&Progress { step: position, total, stage: Stage::Settling });
        std::thread::sleep(Duration::from_millis(plan.settle_ms));
    }
    Ok(angle_deg)
}

/// Lights and lasers off, projector blank, turntable parked; tries every device even if one fails
/// and returns the first error.
pub fn park(rig: &mut Rig, plan: &ScanPlan) -> Result<(), DeviceError> {
    let timeout = Duration::from_millis(plan.move_timeout_ms);
    let mut first = None;
    if let Some(lights) = rig.lights.as_mut() {
        if let Err(e) = lights.all_off(timeout) {
            first.get_or_insert(e);
        }
    }
    if let Some(p) = rig.projector.as_mut() {
        if let Err(e) = p.blank(timeout) {
            first.get_or_insert(e);
        }
    }
    if let Err(e) = rig.turntable.park(timeout) {
        first.get_or_insert(e);
    }
    first.map_or(Ok(()), Err)
}

fn turntable_scan_steps(
    rig: &mut Rig,
    plan: &ScanPlan,
    first: usize,
    views: &SyncSender<CapturedView>,
    cancel: &CancelToken,
    progress: &mut dyn FnMut(&Progress),
) -> Result<AcquisitionSummary, AcquisitionError> {
    let total = plan.positions as usize;
    let move_timeout = Duration::from_millis(plan.move_timeout_ms);
    let capture_timeout = Duration::from_millis(plan.capture_timeout_ms);
    let mut summary = AcquisitionSummary::default();
    let mut sequence = SequenceTracker::default();
    let mut lights_set = false;

    for position in first..total {
        if cancel.is_cancelled() {
            return Err(AcquisitionError::Cancelled { completed: position, total });
        }
        let span = tracing::info_span!("position", position, total);
        let _enter = span.enter();
        let device = |step: &'static str| move |source| AcquisitionError::Device { step, position, source };

        let angle_deg = move_and_settle(rig, plan, position, progress)?;

        if !lights_set {
            progress(&Progress { step: position, total, stage: Stage::Lighting });
            if let Some(lights) = rig.lights.as_mut() {
                for i in 0..lights.light_count() {
                    let level = if plan.lights.contains(&i) { 1.0 } else { 0.0 };
                    lights.set_light(i, level, move_timeout).map_err(device("switching lights"))?;
                }
            }
            lights_set = true;
        }
        // Every change (move, settle, lights) is done: only frames exposed from now on are fresh.
        let changed_at = Instant::now();

        if cancel.is_cancelled() {
            return Err(AcquisitionError::Cancelled { completed: position, total });
        }
        progress(&Progress { step: position, total, stage: Stage::Capturing });
        let (frame, stale) =
            capture_fresh(rig, changed_at, capture_timeout, plan.max_stale_frames, position, &mut sequence)?;
        summary.stale_discarded += u64::from(stale);
        tracing::debug!(sequence = frame.sequence, angle_deg, stale, "captured");

        let view = CapturedView { position, angle_deg, lights_on: plan.lights.clone(), frame, stale_discarded: stale };
        views.send(view).map_err(|_| AcquisitionError::PipelineGone { position })?;
        summary.views += 1;
    }
    summary.dropped = sequence.dropped;
    Ok(summary)
}

/// Counts gaps in a camera's frame sequence numbers (frames the driver or the camera dropped).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct SequenceTracker {
    last: Option<u64>,
    /// Frames missing from the sequence so far.
    pub dropped: u64,
}

impl SequenceTracker {
    /// Account for a received frame's sequence number.
    pub fn see(&mut self, sequence: u64) {
        if let Some(last) = self.last {
            self.dropped += sequence.saturating_sub(last.saturating_add(1));
        }
        self.last = Some(sequence);
    }
}

/// Capture until a frame exposed at or after `changed_at` arrives, discarding stale ones.
/// Returns the frame and the number of stale frames discarded.
pub fn capture_fresh(
    rig: &mut Rig,
    changed_at: Instant,
    timeout: Duration,
    max_stale: u32,
    position: usize,
    sequence: &mut SequenceTracker,
) -> Result<(Frame, u32), AcquisitionError> {
    let mut stale = 0;
    loop {
        let frame = rig.camera.capture(timeout).map_err(|source| AcquisitionError::Device {
            step: "capturing a frame",
            position,
            source,
        })?;
        sequence.see(frame.sequence);
        if frame.exposure_start >= changed_at {
            return Ok((frame, stale));
        }
        stale += 1;
        tracing::trace!(sequence = frame.sequence, "discarded a stale frame");
        if stale > max_stale {
            return Err(AcquisitionError::StaleFrames { position, count: stale });
        }
    }
}

#[cfg(test)]
mod tests;

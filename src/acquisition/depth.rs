//! The depth-camera sequence: at each turntable position move, settle, and capture one fresh depth
//! frame (exposed after the move finished), with the same freshness and sequence-gap rules as the
//! colour sequence.

use std::sync::mpsc::SyncSender;
use std::time::{Duration, Instant};

use super::{
    move_and_settle, run_then_park, AcquisitionError, AcquisitionSummary, CancelToken, Progress, SequenceTracker, Stage,
};
use crate::config::ScanPlan;
use crate::devices::{DepthFrame, DeviceError, Rig};

/// One depth frame and how it was taken.
#[derive(Debug, Clone)]
pub struct DepthView {
    /// 0-based index of the turntable position in the plan.
    pub position: usize,
    /// Turntable angle the frame was taken at, degrees (as reported by the turntable).
    pub angle_deg: f64,
    /// The fresh depth frame.
    pub frame: DepthFrame,
    /// Stale frames thrown away before this one.
    pub stale_discarded: u32,
}

/// Run the depth sequence of `plan` from position `first` on `rig` (which must have a depth camera), sending one
/// [`DepthView`] per position; lights are not touched. The rig is parked at the end, also after an
/// error or cancellation.
pub fn run_depth_scan(
    rig: &mut Rig,
    plan: &ScanPlan,
    first: usize,
    views: &SyncSender<DepthView>,
    cancel: &CancelToken,
    progress: &mut dyn FnMut(&Progress),
) -> Result<AcquisitionSummary, AcquisitionError> {
    run_then_park(rig, plan, first, progress, |rig, progress| {
        depth_scan_steps(rig, plan, first, views, cancel, progress)
    })
}

fn depth_scan_steps(
    rig: &mut Rig,
    plan: &ScanPlan,
    first: usize,
    views: &SyncSender<DepthView>,
    cancel: &CancelToken,
    progress: &mut dyn FnMut(&Progress),
) -> Result<AcquisitionSummary, AcquisitionError> {
    let total = plan.positions as usize;
    let capture_timeout = Duration::from_millis(plan.capture_timeout_ms);
    let mut summary = AcquisitionSummary::default();
    let mut sequence = SequenceTracker::default();
    for position in first..total {
        if cancel.is_cancelled() {
            return Err(AcquisitionError::Cancelled { completed: position, total });
        }
        let span = tracing::info_span!("depth_position", position, total);
        let _enter = span.enter();
        let angle_deg = move_and_settle(rig, plan, position, progress)?;
        let changed_at = Instant::now();
        if cancel.is_cancelled() {
            return Err(AcquisitionError::Cancelled { completed: position, total });
        }
        progress(&Progress { step: position, total, stage: Stage::Capturing });
        let (frame, stale) =
            capture_fresh_depth(rig, changed_at, capture_timeout, plan.max_stale_frames, position, &mut sequence)?;
        summary.stale_discarded += u64::from(stale);
        tracing::debug!(sequence = frame.sequence, angle_deg, stale, "captured depth");
        views
            .send(DepthView { position, angle_deg, frame, stale_discarded: stale })
            .map_err(|_| AcquisitionError::PipelineGone { position })?;
        summary.views += 1;
    }
    summary.dropped = sequence.dropped;
    Ok(summary)
}

/// Capture depth frames until one exposed at or after `changed_at` arrives, discarding stale ones.
/// Returns the frame and the number of stale frames discarded. A rig without a depth camera fails with
/// an `Unsupported` device error.
pub fn capture_fresh_depth(
    rig: &mut Rig,
    changed_at: Instant,
    timeout: Duration,
    max_stale: u32,
    position: usize,
    sequence: &mut SequenceTracker,
) -> Result<(DepthFrame, u32), AcquisitionError> {
    let step = "capturing a depth frame";
    let Some(camera) = rig.depth_camera.as_mut() else {
        let source = DeviceError::Unsupported {
            device: "depth_camera".into(),
            operation: "depth capture (the rig has no depth camera)",
        };
        return Err(AcquisitionError::Device { step, position, source });
    };
    let mut stale = 0;
    loop {
        let frame =
            camera.capture_depth(timeout).map_err(|source| AcquisitionError::Device { step, position, source })?;
        sequence.see(frame.sequence);
        if frame.exposure_start >= changed_at {
            return Ok((frame, stale));
        }
        stale += 1;
        tracing::trace!(sequence = frame.sequence, "discarded a stale depth frame");
        if stale > max_stale {
            return Err(AcquisitionError::StaleFrames { position, count: stale });
        }
    }
}

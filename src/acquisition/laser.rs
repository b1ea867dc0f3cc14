//! The laser sequence: at each turntable position a laser-off frame and then one frame per laser with
//! only that laser on, each captured fresh after its switch. The plan's white lights stay as the plan
//! says for every frame (so on-minus-off leaves only the laser); lasers off and the rig parked at the
//! end, also after an error or cancellation.

use std::sync::mpsc::SyncSender;
use std::time::{Duration, Instant};

use super::{
    capture_fresh, move_and_settle, run_then_park, AcquisitionError, AcquisitionSummary, CancelToken, Progress,
    SequenceTracker, Stage,
};
use crate::config::ScanPlan;
use crate::devices::{DeviceError, Frame, Rig};

/// The frames of one turntable position of the laser sequence.
#[derive(Debug, Clone)]
pub struct LaserView {
    /// 0-based index of the turntable position in the plan.
    pub position: usize,
    /// Turntable angle the frames were taken at, degrees (as reported by the turntable).
    pub angle_deg: f64,
    /// Every laser off.
    pub off: Frame,
    /// `(laser index, frame with only that laser on)`, in the order asked for.
    pub on: Vec<(usize, Frame)>,
    /// Stale frames thrown away at this position.
    pub stale_discarded: u32,
}

/// Run the laser sequence of `plan` with lasers `lasers` (indices of the light array's lasers) on
/// `rig`, sending one [`LaserView`] per position to `views`. A rig without a light array, or without
/// one of the lasers, fails at the first switch with a typed device error.
pub fn run_laser_scan(
    rig: &mut Rig,
    plan: &ScanPlan,
    lasers: &[usize],
    views: &SyncSender<LaserView>,
    cancel: &CancelToken,
    progress: &mut dyn FnMut(&Progress),
) -> Result<AcquisitionSummary, AcquisitionError> {
    run_then_park(rig, plan, 0, progress, |rig, progress| laser_steps(rig, plan, lasers, views, cancel, progress))
}

fn laser_steps(
    rig: &mut Rig,
    plan: &ScanPlan,
    lasers: &[usize],
    views: &SyncSender<LaserView>,
    cancel: &CancelToken,
    progress: &mut dyn FnMut(&Progress),
) -> Result<AcquisitionSummary, AcquisitionError> {
    let total = plan.positions as usize;
    let move_timeout = Duration::from_millis(plan.move_timeout_ms);
    let capture_timeout = Duration::from_millis(plan.capture_timeout_ms);
    let mut summary = AcquisitionSummary::default();
    let mut sequence = SequenceTracker::default();

    for position in 0..total {
        if cancel.is_cancelled() {
            return Err(AcquisitionError::Cancelled { completed: position, total });
        }
        let span = tracing::info_span!("position", position, total);
        let _enter = span.enter();
        let device = |step: &'static str| move |source| AcquisitionError::Device { step, position, source };

        let angle_deg = move_and_settle(rig, plan, position, progress)?;
        let mut stale_here = 0u32;
        let mut off = None;
        let mut on = Vec::with_capacity(lasers.len());
        // `None` = every laser off, then each laser alone.
        for only in std::iter::once(None).chain(lasers.iter().map(|&l| Some(l))) {
            if cancel.is_cancelled() {
                return Err(AcquisitionError::Cancelled { completed: position, total });
            }
            progress(&Progress { step: position, total, stage: Stage::Lighting });
            let array = rig.lights.as_mut().ok_or_else(|| {
                device("switching lasers")(DeviceError::Unsupported {
                    device: "lights".into(),
                    operation: "switching lasers (the rig has no light array)",
                })
            })?;
            if position == 0 && only.is_none() {
                for i in 0..array.light_count() {
                    let level = if plan.lights.contains(&i) { 1.0 } else { 0.0 };
                    array.set_light(i, level, move_timeout).map_err(device("switching lights"))?;
                }
            }
            if only.is_some_and(|l| l >= array.laser_count()) {
                return Err(device("switching lasers")(DeviceError::Unsupported {
                    device: "lights".into(),
                    operation: "switching a laser the light array does not have",
                }));
            }
            for i in 0..array.laser_count() {
                array.set_laser(i, Some(i) == only, move_timeout).map_err(device("switching lasers"))?;
            }
            // The switch is done: only frames exposed from now on show this laser state.
            let changed_at = Instant::now();
            progress(&Progress { step: position, total, stage: Stage::Capturing });
            let (frame, stale) =
                capture_fresh(rig, changed_at, capture_timeout, plan.max_stale_frames, position, &mut sequence)?;
            stale_here += stale;
            tracing::debug!(sequence = frame.sequence, angle_deg, laser = ?only, stale, "captured");
            match only {
                None => off = Some(frame),
                Some(l) => on.push((l, frame)),
            }
        }
        summary.stale_discarded += u64::from(stale_here);
        let Some(off) = off else { continue };
        let view = LaserView { position, angle_deg, off, on, stale_discarded: stale_here };
        views.send(view).map_err(|_| AcquisitionError::PipelineGone { position })?;
        summary.views += 1;
    }
    summary.dropped = sequence.dropped;
    Ok(summary)
}

//! The per-light sequence used by shadow carving: at each turntable position an ambient frame (every
//! light off) and then one frame per named light with only that light on, each captured fresh after
//! its switch.

use std::sync::mpsc::SyncSender;
use std::time::{Duration, Instant};

use super::{
    capture_fresh, move_and_settle, run_then_park, AcquisitionError, AcquisitionSummary, CancelToken, Progress,
    SequenceTracker, Stage,
};
use crate::config::ScanPlan;
use crate::devices::{DeviceError, Frame, LightArray, Rig};

/// The frames of one turntable position of a per-light sequence.
#[derive(Debug, Clone)]
pub struct PerLightView {
    /// 0-based index of the turntable position in the plan.
    pub position: usize,
    /// Turntable angle the frames were taken at, degrees (as reported by the turntable).
    pub angle_deg: f64,
    /// Every light off.
    pub ambient: Frame,
    /// `(light index, frame with only that light on)`, in the order of the plan's `shadow_lights`.
    pub lit: Vec<(usize, Frame)>,
    /// Stale frames thrown away at this position.
    pub stale_discarded: u32,
}

/// Run the per-light sequence of `plan` (lights `plan.shadow_lights`) on `rig` from position `first`, sending one
/// [`PerLightView`] per position to `views`. Lights off and turntable parked at the end, also after an
/// error or cancellation. A rig without a light array fails at the first switch.
pub fn run_per_light_scan(
    rig: &mut Rig,
    plan: &ScanPlan,
    first: usize,
    views: &SyncSender<PerLightView>,
    cancel: &CancelToken,
    progress: &mut dyn FnMut(&Progress),
) -> Result<AcquisitionSummary, AcquisitionError> {
    run_then_park(rig, plan, first, progress, |rig, progress| {
        per_light_steps(rig, plan, first, views, cancel, progress)
    })
}

fn per_light_steps(
    rig: &mut Rig,
    plan: &ScanPlan,
    first: usize,
    views: &SyncSender<PerLightView>,
    cancel: &CancelToken,
    progress: &mut dyn FnMut(&Progress),
) -> Result<AcquisitionSummary, AcquisitionError> {
    let switch = |lights: &mut dyn LightArray, _position: usize, only: Option<usize>, timeout: Duration| {
        for i in 0..lights.light_count() {
            lights.set_light(i, if Some(i) == only { 1.0 } else { 0.0 }, timeout)?;
        }
        Ok(())
    };
    let view = |position, angle_deg, ambient, lit, stale_discarded| PerLightView {
        position,
        angle_deg,
        ambient,
        lit,
        stale_discarded,
    };
    one_at_a_time_steps(
        rig,
        plan,
        first,
        &plan.shadow_lights,
        "switching lights",
        switch,
        view,
        views,
        cancel,
        progress,
    )
}

/// The sequence shared by the per-light and laser scans: at each position, a frame with every source
/// of `sources` off, then one frame per source alone, each captured fresh after `switch` returns (the
/// instant of return is the change the frame must be exposed after). `switch(array, position, only,
/// timeout)` puts the light array into the state "only `only` on" (`None`: all off); `step` names the
/// switching in errors; `view(position, angle_deg, off, on, stale)` builds what is sent per position.
#[allow(clippy::too_many_arguments)]
pub(super) fn one_at_a_time_steps<V>(
    rig: &mut Rig,
    plan: &ScanPlan,
    first: usize,
    sources: &[usize],
    step: &'static str,
    mut switch: impl FnMut(&mut dyn LightArray, usize, Option<usize>, Duration) -> Result<(), DeviceError>,
    view: impl Fn(usize, f64, Frame, Vec<(usize, Frame)>, u32) -> V,
    views: &SyncSender<V>,
    cancel: &CancelToken,
    progress: &mut dyn FnMut(&Progress),
) -> Result<AcquisitionSummary, AcquisitionError> {
    let total = plan.positions as usize;
    let move_timeout = Duration::from_millis(plan.move_timeout_ms);
    let capture_timeout = Duration::from_millis(plan.capture_timeout_ms);
    let mut summary = AcquisitionSummary::default();
    let mut sequence = SequenceTracker::default();

    for position in first..total {
        if cancel.is_cancelled() {
            return Err(AcquisitionError::Cancelled { completed: position, total });
        }
        let span = tracing::info_span!("position", position, total);
        let _enter = span.enter();
        let device = |source| AcquisitionError::Device { step, position, source };

        let angle_deg = move_and_settle(rig, plan, position, progress)?;

        let mut stale_here = 0u32;
        let mut off = None;
        let mut on = Vec::with_capacity(sources.len());
        // `None` = every source off, then each source alone.
        for only in std::iter::once(None).chain(sources.iter().map(|&l| Some(l))) {
            if cancel.is_cancelled() {
                return Err(AcquisitionError::Cancelled { completed: position, total });
            }
            progress(&Progress { step: position, total, stage: Stage::Lighting });
            let array = rig.lights.as_mut().ok_or_else(|| {
                device(DeviceError::Unsupported { device: "lights".into(), operation: "the rig has no light array" })
            })?;
            switch(array.as_mut(), position, only, move_timeout).map_err(device)?;
            // The switch is done: only frames exposed from now on show this state.
            let changed_at = Instant::now();
            progress(&Progress { step: position, total, stage: Stage::Capturing });
            let (frame, stale) =
                capture_fresh(rig, changed_at, capture_timeout, plan.max_stale_frames, position, &mut sequence)?;
            stale_here += stale;
            tracing::debug!(sequence = frame.sequence, angle_deg, source = ?only, stale, "captured");
            match only {
                None => off = Some(frame),
                Some(l) => on.push((l, frame)),
            }
        }
        summary.stale_discarded += u64::from(stale_here);
        let Some(off) = off else { continue };
        views
            .send(view(position, angle_deg, off, on, stale_here))
            .map_err(|_| AcquisitionError::PipelineGone { position })?;
        summary.views += 1;
    }
    summary.dropped = sequence.dropped;
    Ok(summary)
}

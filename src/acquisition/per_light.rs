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
use crate::devices::{DeviceError, Frame, Rig};

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

/// Run the per-light sequence of `plan` (lights `plan.shadow_lights`) on `rig`, sending one
/// [`PerLightView`] per position to `views`. Lights off and turntable parked at the end, also after an
/// error or cancellation. A rig without a light array fails at the first switch.
pub fn run_per_light_scan(
    rig: &mut Rig,
    plan: &ScanPlan,
    views: &SyncSender<PerLightView>,
    cancel: &CancelToken,
    progress: &mut dyn FnMut(&Progress),
) -> Result<AcquisitionSummary, AcquisitionError> {
    run_then_park(rig, plan, 0, progress, |rig, progress| per_light_steps(rig, plan, views, cancel, progress))
}

fn per_light_steps(
    rig: &mut Rig,
    plan: &ScanPlan,
    views: &SyncSender<PerLightView>,
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
        // `None` = ambient (all off), then each shadow light alone.
        let mut ambient = None;
        let mut lit = Vec::with_capacity(plan.shadow_lights.len());
        for only in std::iter::once(None).chain(plan.shadow_lights.iter().map(|&l| Some(l))) {
            if cancel.is_cancelled() {
                return Err(AcquisitionError::Cancelled { completed: position, total });
            }
            progress(&Progress { step: position, total, stage: Stage::Lighting });
            let lights = rig.lights.as_mut().ok_or_else(|| {
                device("switching lights")(DeviceError::Unsupported {
                    device: "lights".into(),
                    operation: "switching lights (the rig has no light array)",
                })
            })?;
            for i in 0..lights.light_count() {
                let level = if Some(i) == only { 1.0 } else { 0.0 };
                lights.set_light(i, level, move_timeout).map_err(device("switching lights"))?;
            }
            // The switch is done: only frames exposed from now on show this lighting.
            let changed_at = Instant::now();
            progress(&Progress { step: position, total, stage: Stage::Capturing });
            let (frame, stale) =
                capture_fresh(rig, changed_at, capture_timeout, plan.max_stale_frames, position, &mut sequence)?;
            stale_here += stale;
            tracing::debug!(sequence = frame.sequence, angle_deg, light = ?only, stale, "captured");
            match only {
                None => ambient = Some(frame),
                Some(l) => lit.push((l, frame)),
            }
        }
        summary.stale_discarded += u64::from(stale_here);
        let Some(ambient) = ambient else { continue };
        let view = PerLightView { position, angle_deg, ambient, lit, stale_discarded: stale_here };
        views.send(view).map_err(|_| AcquisitionError::PipelineGone { position })?;
        summary.views += 1;
    }
    summary.dropped = sequence.dropped;
    Ok(summary)
}

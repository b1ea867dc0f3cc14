//! The structured-light sequence: at each turntable position move and settle, then for each pattern
//! hand it to the projector, wait until the projector says it is on screen (its input lag and
//! refresh), and capture a frame whose exposure started at or after that instant. Frames exposed
//! earlier may still show the previous pattern and are discarded as stale. One [`PatternStack`] (a
//! frame per pattern) per position goes to the pipeline over the bounded channel. The projector is
//! blanked, the lights switched off and the turntable parked at the end, also after an error or
//! cancellation.

use std::sync::mpsc::SyncSender;
use std::time::{Duration, Instant};

use super::{
    capture_fresh, move_and_settle, run_then_park, AcquisitionError, AcquisitionSummary, CancelToken, Progress,
    SequenceTracker, Stage,
};
use crate::config::ScanPlan;
use crate::devices::{DeviceError, Frame, Pattern, Rig};

/// The frames of one turntable position, one per pattern, in the order of the patterns.
#[derive(Debug, Clone)]
pub struct PatternStack {
    /// 0-based index of the turntable position in the plan.
    pub position: usize,
    /// Turntable angle the frames were taken at, degrees (as reported by the turntable).
    pub angle_deg: f64,
    /// One fresh frame per pattern.
    pub frames: Vec<Frame>,
    /// Per frame, the instant its pattern was on screen (as the projector reported it); every frame's
    /// `exposure_start` is at or after it.
    pub visible_at: Vec<Instant>,
    /// Stale frames thrown away at this position.
    pub stale_discarded: u32,
}

/// Run the structured-light sequence of `plan` from position `first` on `rig` (which must have a
/// projector), showing every pattern of `patterns` at each position and sending one [`PatternStack`]
/// per position. Each pattern stays on screen for at least `hold` after the instant the projector
/// reported it visible (the camera's exposure, a whole number of projector refreshes;
/// `Duration::ZERO` for none) before the next is shown. The lights of `plan.lights` are switched on
/// once (usually none: ambient light only lowers the contrast).
#[allow(clippy::too_many_arguments)]
pub fn run_structured_light_scan(
    rig: &mut Rig,
    plan: &ScanPlan,
    first: usize,
    patterns: &[Pattern],
    hold: Duration,
    stacks: &SyncSender<PatternStack>,
    cancel: &CancelToken,
    progress: &mut dyn FnMut(&Progress),
) -> Result<AcquisitionSummary, AcquisitionError> {
    run_then_park(rig, plan, first, progress, |rig, progress| {
        steps(rig, plan, first, patterns, hold, stacks, cancel, progress)
    })
}

#[allow(clippy::too_many_arguments)]
fn steps(
    rig: &mut Rig,
    plan: &ScanPlan,
    first: usize,
    patterns: &[Pattern],
    hold: Duration,
    stacks: &SyncSender<PatternStack>,
    cancel: &CancelToken,
    progress: &mut dyn FnMut(&Progress),
) -> Result<AcquisitionSummary, AcquisitionError> {
    let total = plan.positions as usize;
    let timeout = Duration::from_millis(plan.move_timeout_ms);
    let capture_timeout = Duration::from_millis(plan.capture_timeout_ms);
    let mut summary = AcquisitionSummary::default();
    let mut sequence = SequenceTracker::default();
    if rig.projector.is_none() {
        let source =
            DeviceError::Unsupported { device: "projector".into(), operation: "structured light (the rig has none)" };
        return Err(AcquisitionError::Device { step: "showing a pattern", position: 0, source });
    }
    for position in first..total {
        if cancel.is_cancelled() {
            return Err(AcquisitionError::Cancelled { completed: position, total });
        }
        let span = tracing::info_span!("structured_light_position", position, total);
        let _enter = span.enter();
        let device = |step: &'static str| move |source| AcquisitionError::Device { step, position, source };
        let angle_deg = move_and_settle(rig, plan, position, progress)?;
        if position == first {
            progress(&Progress { step: position, total, stage: Stage::Lighting });
            if let Some(lights) = rig.lights.as_mut() {
                for i in 0..lights.light_count() {
                    let level = if plan.lights.contains(&i) { 1.0 } else { 0.0 };
                    lights.set_light(i, level, timeout).map_err(device("switching lights"))?;
                }
            }
        }
        let moved_at = Instant::now();
        progress(&Progress { step: position, total, stage: Stage::Capturing });
        let mut stack = PatternStack {
            position,
            angle_deg,
            frames: Vec::with_capacity(patterns.len()),
            visible_at: Vec::with_capacity(patterns.len()),
            stale_discarded: 0,
        };
        for (k, pattern) in patterns.iter().enumerate() {
            progress(&Progress {
                step: position,
                total,
                stage: Stage::Projecting { pattern: k + 1, of: patterns.len() },
            });
            if cancel.is_cancelled() {
                return Err(AcquisitionError::Cancelled { completed: position, total });
            }
            let projector = rig.projector.as_mut().ok_or_else(|| AcquisitionError::Device {
                step: "showing a pattern",
                position,
                source: DeviceError::Unsupported { device: "projector".into(), operation: "structured light" },
            })?;
            let visible_at = projector.show(pattern, timeout).map_err(device("showing a pattern"))?;
            // Wait for the pattern instead of spinning the camera through stale frames.
            let now = Instant::now();
            if visible_at > now {
                std::thread::sleep(visible_at - now);
            }
            let fresh_from = visible_at.max(moved_at);
            let (frame, stale) =
                capture_fresh(rig, fresh_from, capture_timeout, plan.max_stale_frames, position, &mut sequence)?;
            stack.stale_discarded += stale;
            // The exposure integrates whole refreshes: the pattern stays up for `hold`.
            let until = visible_at + hold;
            let now = Instant::now();
            if until > now {
                std::thread::sleep(until - now);
            }
            stack.frames.push(frame);
            stack.visible_at.push(visible_at);
        }
        summary.stale_discarded += u64::from(stack.stale_discarded);
        tracing::debug!(
            angle_deg,
            frames = stack.frames.len(),
            stale = stack.stale_discarded,
            "pattern stack captured"
        );
        stacks.send(stack).map_err(|_| AcquisitionError::PipelineGone { position })?;
        summary.views += 1;
    }
    summary.dropped = sequence.dropped;
    Ok(summary)
}

#[cfg(test)]
mod tests {
    use std::sync::mpsc;

    use super::*;
    use crate::config::{CameraConfig, ProjectorConfig, RigConfig};
    use crate::devices::build_rig;

    /// The small simulated box rig with a slow projector (25 ms lag, 60 Hz refresh) and a camera
    /// without a buffer queue, so staleness comes only from the projector.
    fn slow_projector_rig(positions: u32) -> RigConfig {
        slow_projector_rig_with_buffers(positions, 1)
    }

    fn slow_projector_rig_with_buffers(positions: u32, buffers: u32) -> RigConfig {
        let mut rig = crate::sim::tests::small_rig("box");
        let Some(ProjectorConfig::Sim(p)) = rig.projector.as_mut() else { panic!("the rig has a projector") };
        p.latency_ms = 25.0;
        p.frame_period_ms = 1000.0 / 60.0;
        let CameraConfig::Sim(c) = &mut rig.camera else { panic!("the rig has a simulated camera") };
        c.buffer_depth = buffers;
        rig.scan.positions = positions;
        rig.scan.lights = Vec::new();
        rig
    }

    fn mean(frame: &Frame) -> f64 {
        let px = frame.image.as_raw();
        px.iter().map(|&v| f64::from(v)).sum::<f64>() / px.len() as f64
    }

    fn white_black(rig: &Rig) -> (Pattern, Pattern) {
        let (w, h) = rig.projector.as_ref().expect("projector").resolution();
        (Pattern::uniform(w, h, [255, 255, 255]), Pattern::uniform(w, h, [0, 0, 0]))
    }

    #[test]
    fn a_capture_right_after_show_sees_the_previous_pattern_on_a_slow_projector() {
        // The control for the next test: the simulated lag is real.
        let config = slow_projector_rig(1);
        let mut rig = build_rig(&config).expect("rig");
        let (white, black) = white_black(&rig);
        let t = Duration::from_secs(1);
        let projector = rig.projector.as_mut().expect("projector");
        let at = projector.show(&white, t).expect("show");
        std::thread::sleep(at.saturating_duration_since(Instant::now()));
        let lit = rig.camera.capture(t).expect("frame");
        let at = rig.projector.as_mut().expect("projector").show(&black, t).expect("show");
        let early = rig.camera.capture(t).expect("frame");
        assert!(early.exposure_start < at);
        assert!((mean(&early) - mean(&lit)).abs() < 1.0, "a too-early frame still shows white");
    }

    #[test]
    fn every_frame_is_exposed_after_its_pattern_is_on_screen() {
        for buffers in [1, 3] {
            check_fresh_frames(buffers);
        }
    }

    /// With `buffers` queued camera buffers the frames already queued when a pattern is shown are
    /// stale and discarded; with one buffer nothing is.
    fn check_fresh_frames(buffers: u32) {
        let config = slow_projector_rig_with_buffers(2, buffers);
        let mut rig = build_rig(&config).expect("rig");
        let (white, black) = white_black(&rig);
        let patterns = [white.clone(), black.clone(), white, black];
        let (tx, rx) = mpsc::sync_channel(4);
        let summary = run_structured_light_scan(
            &mut rig,
            &config.scan,
            0,
            &patterns,
            Duration::ZERO,
            &tx,
            &CancelToken::new(),
            &mut |_| {},
        )
        .expect("scan");
        drop(tx);
        let stacks: Vec<PatternStack> = rx.iter().collect();
        assert_eq!((summary.views, stacks.len()), (2, 2));
        for s in &stacks {
            assert_eq!(s.frames.len(), 4);
            for (f, at) in s.frames.iter().zip(&s.visible_at) {
                assert!(f.exposure_start >= *at, "frame exposed before its pattern was on screen");
            }
            let m: Vec<f64> = s.frames.iter().map(mean).collect();
            // White frames are bright, black ones only show the ambient light.
            assert!(m[0] > m[1] + 5.0 && m[2] > m[3] + 5.0, "position {}: means {m:?}", s.position);
            assert!((m[0] - m[2]).abs() < 1.0 && (m[1] - m[3]).abs() < 1.0, "means {m:?}");
        }
        let stale: u32 = stacks.iter().map(|s| s.stale_discarded).sum();
        assert_eq!(u64::from(stale), summary.stale_discarded);
        if buffers == 1 {
            assert_eq!(stale, 0, "one buffer: every frame is exposed when asked for");
        } else {
            assert!(stale >= 2 * 4, "{stale} stale frames for 8 patterns with {buffers} buffers");
        }
        let world = rig.sim.as_ref().expect("sim");
        let state = world.snapshot();
        assert!(state.pattern.is_none() && state.pending_pattern.is_none(), "projector blank after the scan");
    }

    #[test]
    fn a_cancelled_scan_blanks_the_projector() {
        let config = slow_projector_rig(3);
        let mut rig = build_rig(&config).expect("rig");
        let (white, _) = white_black(&rig);
        let (tx, _rx) = mpsc::sync_channel(4);
        let cancel = CancelToken::new();
        let mut shown = 0;
        let err = run_structured_light_scan(
            &mut rig,
            &config.scan,
            0,
            &[white.clone(), white],
            Duration::ZERO,
            &tx,
            &cancel,
            &mut |p| {
                if p.stage == Stage::Capturing {
                    shown += 1;
                    cancel.cancel();
                }
            },
        )
        .expect_err("cancelled");
        assert!(matches!(err, AcquisitionError::Cancelled { completed: 0, .. }), "{err:?}");
        assert_eq!(shown, 1);
        let state = rig.sim.as_ref().expect("sim").snapshot();
        assert!(state.pattern.is_none() && state.pending_pattern.is_none());
    }
}

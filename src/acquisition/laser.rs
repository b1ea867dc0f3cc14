//! The laser sequence: at each turntable position a laser-off frame and then one frame per laser with
//! only that laser on, each captured fresh after its switch. The plan's white lights stay as the plan
//! says for every frame (so on-minus-off leaves only the laser); lasers off and the rig parked at the
//! end, also after an error or cancellation.

use std::sync::mpsc::SyncSender;
use std::time::Duration;

use super::per_light::one_at_a_time_steps;
use super::{run_then_park, AcquisitionError, AcquisitionSummary, CancelToken, Progress};
use crate::config::ScanPlan;
use crate::devices::{DeviceError, Frame, LightArray, Rig};

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

/// Run the laser sequence of `plan` from position `first` with lasers `lasers` (indices of the light array's lasers) on
/// `rig`, sending one [`LaserView`] per position to `views`. A rig without a light array, or without
/// one of the lasers, fails at the first switch with a typed device error.
pub fn run_laser_scan(
    rig: &mut Rig,
    plan: &ScanPlan,
    first: usize,
    lasers: &[usize],
    views: &SyncSender<LaserView>,
    cancel: &CancelToken,
    progress: &mut dyn FnMut(&Progress),
) -> Result<AcquisitionSummary, AcquisitionError> {
    run_then_park(rig, plan, first, progress, |rig, progress| {
        laser_steps(rig, plan, first, lasers, views, cancel, progress)
    })
}

fn laser_steps(
    rig: &mut Rig,
    plan: &ScanPlan,
    first: usize,
    lasers: &[usize],
    views: &SyncSender<LaserView>,
    cancel: &CancelToken,
    progress: &mut dyn FnMut(&Progress),
) -> Result<AcquisitionSummary, AcquisitionError> {
    let switch = |array: &mut dyn LightArray, position: usize, only: Option<usize>, timeout: Duration| {
        // The plan's white lights, once: they stay so for every frame of the scan.
        if position == first && only.is_none() {
            for i in 0..array.light_count() {
                array.set_light(i, if plan.lights.contains(&i) { 1.0 } else { 0.0 }, timeout)?;
            }
        }
        if only.is_some_and(|l| l >= array.laser_count()) {
            return Err(DeviceError::Unsupported {
                device: "lights".into(),
                operation: "switching a laser the light array does not have",
            });
        }
        for i in 0..array.laser_count() {
            array.set_laser(i, Some(i) == only, timeout)?;
        }
        Ok(())
    };
    let view =
        |position, angle_deg, off, on, stale_discarded| LaserView { position, angle_deg, off, on, stale_discarded };
    one_at_a_time_steps(rig, plan, first, lasers, "switching lasers", switch, view, views, cancel, progress)
}

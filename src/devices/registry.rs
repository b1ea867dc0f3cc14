//! Builds the rig's drivers from the config's `kind` fields.

use crate::config::{CameraConfig, DepthCameraConfig, LightsKind, ProjectorConfig, RigConfig, TurntableConfig};
use crate::sim::SimWorld;

use super::{Camera, DepthCamera, DeviceError, LightArray, Projector, Turntable};

/// The opened devices of one rig.
#[derive(Debug)]
pub struct Rig {
    /// The turntable.
    pub turntable: Box<dyn Turntable>,
    /// The light array, if the rig has one.
    pub lights: Option<Box<dyn LightArray>>,
    /// The camera.
    pub camera: Box<dyn Camera>,
    /// The projector, if any.
    pub projector: Option<Box<dyn Projector>>,
    /// The depth camera, if any.
    pub depth_camera: Option<Box<dyn DepthCamera>>,
    /// The simulated world, when any device is simulated: the ground truth for evaluation.
    pub sim: Option<SimWorld>,
    /// The serial board's controller (and its emulator), when the rig has a `[controller]`.
    pub serial: Option<super::serial::OpenedController>,
}

/// Open every device the config names.
pub fn build_rig(config: &RigConfig) -> Result<Rig, DeviceError> {
    let sim = match &config.sim {
        Some(s) => Some(SimWorld::from_config(s, config)?),
        None => None,
    };
    let need_sim = |device: &str| {
        sim.clone().ok_or_else(|| DeviceError::InvalidConfig {
            device: device.to_owned(),
            field: "kind",
            problem: "kind = \"sim\" needs a [sim] section".into(),
        })
    };
    // The turntable and lights of a serial rig share one controller on one port. With
    // `port = "emulator:..."` the emulator drives the simulated world (or, without one, a recorder).
    let serial = match &config.controller {
        Some(c) => {
            let hardware =
                sim.clone().map(|w| std::sync::Arc::new(w) as std::sync::Arc<dyn super::serial::EmulatedHardware>);
            Some(super::serial::open_controller(c, hardware)?)
        }
        None => None,
    };
    let need_serial = |device: &str| {
        serial.clone().ok_or_else(|| DeviceError::InvalidConfig {
            device: device.to_owned(),
            field: "kind",
            problem: "kind = \"serial\" needs a [controller] section".into(),
        })
    };
    let turntable: Box<dyn Turntable> = match &config.turntable {
        TurntableConfig::Sim(c) => Box::new(super::turntable::sim::SimTurntable::new(need_sim("turntable")?, c)),
        TurntableConfig::Serial(t) => {
            let spt = config.controller.as_ref().and_then(|c| c.steps_per_turn).unwrap_or(3200);
            Box::new(super::serial::SerialTurntable::new(need_serial("turntable")?.controller, t.reverse, spt))
        }
    };
    let lights: Option<Box<dyn LightArray>> = match &config.lights {
        None => None,
        Some(l) => match l.kind {
            LightsKind::Sim => Some(Box::new(super::lights::sim::SimLightArray::new(need_sim("lights")?))),
            LightsKind::Serial => Some(Box::new(super::serial::SerialLightArray::new(
                need_serial("lights")?.controller,
                l.lights.len(),
                l.lasers.len(),
            ))),
        },
    };
    let camera: Box<dyn Camera> = match &config.camera {
        CameraConfig::Sim(c) => Box::new(super::camera::sim::SimCamera::new(need_sim("camera")?, c)),
        real @ (CameraConfig::V4l2(_) | CameraConfig::Uvc(_) | CameraConfig::Genicam(_)) => {
            super::hardware::open_camera(real)?
        }
    };
    let projector: Option<Box<dyn Projector>> = match &config.projector {
        None => None,
        Some(ProjectorConfig::Sim(p)) => {
            Some(Box::new(super::projector::sim::SimProjector::new(need_sim("projector")?, p)))
        }
        Some(ProjectorConfig::Fbdev(p)) => Some(super::hardware::open_fbdev(p)?),
        Some(ProjectorConfig::Window(p)) => Some(super::hardware::open_window(p)?),
    };
    let depth_camera: Option<Box<dyn DepthCamera>> = match &config.depth_camera {
        None => None,
        Some(DepthCameraConfig::Sim(d)) => {
            Some(Box::new(super::depth::sim::SimDepthCamera::new(need_sim("depth_camera")?, d)))
        }
        Some(DepthCameraConfig::Freenect(d)) => Some(super::hardware::open_freenect(d)?),
    };
    Ok(Rig { turntable, lights, camera, projector, depth_camera, sim, serial })
}

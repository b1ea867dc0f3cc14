//! The simulated rig's world: the scene on the turntable, the renderer, and ground truth.
//! (Being written: scene, renderer, world state.)

use crate::config::{RigConfig, SimConfig};
use crate::devices::DeviceError;

/// Names of the preset scenes for `[sim] scene`.
pub const SCENE_NAMES: &[&str] = &["sphere", "box", "cup", "pit-block", "textured-box"];

/// Shared state of the simulated world (placeholder until the renderer lands).
#[derive(Debug, Clone)]
pub struct SimWorld {}

impl SimWorld {
    /// Build the world from the config.
    pub fn from_config(_sim: &SimConfig, _rig: &RigConfig) -> Result<SimWorld, DeviceError> {
        Ok(SimWorld {})
    }
}

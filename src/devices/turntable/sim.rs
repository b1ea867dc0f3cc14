//! Simulated turntable (placeholder).
use crate::config::SimTurntableConfig;
use crate::sim::SimWorld;
/// Simulated turntable.
#[derive(Debug)]
pub struct SimTurntable {}
impl SimTurntable {
    /// New.
    pub fn new(_w: SimWorld, _c: &SimTurntableConfig) -> Self {
        SimTurntable {}
    }
}
impl super::Turntable for SimTurntable {
    fn move_to(&mut self, _d: f64, _t: std::time::Duration) -> Result<(), crate::devices::DeviceError> {
        Ok(())
    }
    fn angle(&self) -> f64 {
        0.0
    }
    fn steps_per_turn(&self) -> u32 {
        1
    }
    fn park(&mut self, _t: std::time::Duration) -> Result<(), crate::devices::DeviceError> {
        Ok(())
    }
}

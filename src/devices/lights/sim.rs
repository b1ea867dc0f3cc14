//! Simulated light array (placeholder).
use crate::sim::SimWorld;
/// Simulated lights.
#[derive(Debug)]
pub struct SimLightArray {}
impl SimLightArray {
    /// New.
    pub fn new(_w: SimWorld) -> Self {
        SimLightArray {}
    }
}
impl super::LightArray for SimLightArray {
    fn light_count(&self) -> usize {
        0
    }
    fn laser_count(&self) -> usize {
        0
    }
    fn set_light(&mut self, _i: usize, _l: f32, _t: std::time::Duration) -> Result<(), crate::devices::DeviceError> {
        Ok(())
    }
    fn set_laser(&mut self, _i: usize, _o: bool, _t: std::time::Duration) -> Result<(), crate::devices::DeviceError> {
        Ok(())
    }
}

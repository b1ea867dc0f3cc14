//! Simulated projector (placeholder).
use crate::config::SimProjectorConfig;
use crate::sim::SimWorld;
/// Simulated projector.
#[derive(Debug)]
pub struct SimProjector {}
impl SimProjector {
    /// New.
    pub fn new(_w: SimWorld, _c: &SimProjectorConfig) -> Self {
        SimProjector {}
    }
}
impl super::Projector for SimProjector {
    fn resolution(&self) -> (u32, u32) {
        (1, 1)
    }
    fn show(
        &mut self,
        _p: &super::Pattern,
        _t: std::time::Duration,
    ) -> Result<std::time::Instant, crate::devices::DeviceError> {
        Ok(std::time::Instant::now())
    }
    fn blank(&mut self, _t: std::time::Duration) -> Result<(), crate::devices::DeviceError> {
        Ok(())
    }
}

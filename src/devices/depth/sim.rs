//! Simulated depth camera (placeholder).
use crate::config::SimDepthCameraConfig;
use crate::sim::SimWorld;
/// Simulated depth camera.
#[derive(Debug)]
pub struct SimDepthCamera {}
impl SimDepthCamera {
    /// New.
    pub fn new(_w: SimWorld, _c: &SimDepthCameraConfig) -> Self {
        SimDepthCamera {}
    }
}
impl super::DepthCamera for SimDepthCamera {
    fn resolution(&self) -> (u32, u32) {
        (1, 1)
    }
    fn capture_depth(&mut self, _t: std::time::Duration) -> Result<super::DepthFrame, crate::devices::DeviceError> {
        Err(crate::devices::DeviceError::unsupported("depth_camera", "capture"))
    }
}

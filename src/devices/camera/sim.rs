//! Simulated camera (placeholder).
use crate::config::SimCameraConfig;
use crate::sim::SimWorld;
/// Simulated camera.
#[derive(Debug)]
pub struct SimCamera {}
impl SimCamera {
    /// New.
    pub fn new(_w: SimWorld, _c: &SimCameraConfig) -> Self {
        SimCamera {}
    }
}
impl super::Camera for SimCamera {
    fn info(&self) -> super::CameraInfo {
        super::CameraInfo { width: 1, height: 1 }
    }
    fn capture(&mut self, _t: std::time::Duration) -> Result<super::Frame, crate::devices::DeviceError> {
        Err(crate::devices::DeviceError::unsupported("camera", "capture"))
    }
}

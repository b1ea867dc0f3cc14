//! Depth cameras: frames of metric depth.

#[cfg(feature = "freenect")]
pub mod freenect;
pub mod kinect;
pub mod sim;

use std::time::{Duration, Instant};

use super::DeviceError;

/// One depth frame: depth along the optical axis (camera-frame `z`), metres, row-major; 0 where
/// nothing was measured.
#[derive(Debug, Clone)]
pub struct DepthFrame {
    /// The camera's frame counter.
    pub sequence: u64,
    /// Monotonic time at which exposure started.
    pub exposure_start: Instant,
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// Depth, metres, 0 = no measurement.
    pub depth_m: Vec<f32>,
}

/// A depth camera.
pub trait DepthCamera: Send + std::fmt::Debug {
    /// Size in pixels (width, height).
    fn resolution(&self) -> (u32, u32);

    /// The next depth frame, waiting at most `timeout`.
    fn capture_depth(&mut self, timeout: Duration) -> Result<DepthFrame, DeviceError>;
}

//! Cameras: a stream of frames with metadata.

#[cfg(feature = "aravis")]
pub mod arv;
pub mod controls;
#[cfg(feature = "aravis")]
pub mod genicam;
pub mod genicam_features;
pub mod pixel;
pub mod sim;
pub mod stream;
pub mod streaming;
#[cfg(feature = "nokhwa")]
pub mod uvc;
#[cfg(feature = "v4l")]
pub mod v4l2;

use std::time::{Duration, Instant};

use super::DeviceError;

/// What a camera delivers.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CameraInfo {
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
}

/// One frame from a camera's stream.
#[derive(Debug, Clone)]
pub struct Frame {
    /// The camera's own frame counter; a gap means frames were dropped.
    pub sequence: u64,
    /// Monotonic time at which exposure started. A frame is fresh for a scene change (light switch,
    /// turntable move, pattern) only if it started exposing after the change.
    pub exposure_start: Instant,
    /// The image, 8-bit RGB.
    pub image: image::RgbImage,
}

/// A camera streaming frames. `capture` returns the next frame of the stream, which may have been
/// exposed before the caller's last scene change: real cameras keep a queue of buffers. The caller
/// (the acquisition layer) compares [`Frame::exposure_start`] with the time of its last change.
pub trait Camera: Send + std::fmt::Debug {
    /// Size and format.
    fn info(&self) -> CameraInfo;

    /// The next frame of the stream, waiting at most `timeout`.
    fn capture(&mut self, timeout: Duration) -> Result<Frame, DeviceError>;
}

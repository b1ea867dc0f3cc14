//! The projector: shows pattern images (structured light).

#[cfg(feature = "fbdev")]
pub mod fbdev;
pub mod framebuffer;
pub mod sim;
#[cfg(feature = "x11")]
pub mod window;

use std::sync::Arc;
use std::time::{Duration, Instant};

use super::DeviceError;

/// A pattern image at the projector's resolution, 8-bit RGB, row-major, origin top-left.
#[derive(Debug, Clone, PartialEq)]
pub struct Pattern {
    /// Width, projector pixels.
    pub width: u32,
    /// Height, projector pixels.
    pub height: u32,
    /// RGB bytes, `3 * width * height`.
    pub rgb: Arc<Vec<u8>>,
}

impl Pattern {
    /// A uniform pattern of one colour.
    pub fn uniform(width: u32, height: u32, rgb: [u8; 3]) -> Self {
        let mut v = Vec::with_capacity(3 * width as usize * height as usize);
        for _ in 0..width as usize * height as usize {
            v.extend_from_slice(&rgb);
        }
        Pattern { width, height, rgb: Arc::new(v) }
    }

    /// The colour at projector pixel `(u, v)`.
    pub fn at(&self, u: u32, v: u32) -> [u8; 3] {
        let i = 3 * (v as usize * self.width as usize + u as usize);
        [self.rgb[i], self.rgb[i + 1], self.rgb[i + 2]]
    }
}

/// A projector driven as a display.
pub trait Projector: Send + std::fmt::Debug {
    /// Resolution, projector pixels (width, height).
    fn resolution(&self) -> (u32, u32);

    /// Show a pattern; returns the instant it is (or will be, for a projector with input lag that
    /// returns at once) on screen, so a camera frame exposed at or after it is known fresh and one
    /// exposed earlier may still show the previous pattern.
    fn show(&mut self, pattern: &Pattern, timeout: Duration) -> Result<Instant, DeviceError>;

    /// Show black. Called at the end of every scan, also after errors.
    fn blank(&mut self, timeout: Duration) -> Result<(), DeviceError>;
}

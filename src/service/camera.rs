//! The live camera for framing and focus: JPEG frames shared by every MJPEG viewer.
//!
//! Viewers pull: each asks for a frame no older than its own frame period. The newest frame is
//! kept (one JPEG); when it is too old, the first viewer to ask captures a new one through the
//! device thread's shared preview capture ([`RigHandle::capture`]) and encodes it once, while the
//! others wait for it on the same lock. So the camera runs at the fastest viewer's rate (at most
//! [`MAX_FPS`]), whatever the number of viewers, and each viewer's HTTP body is polled only when
//! its socket has taken the previous part: a slow client gets fewer frames and nothing queues up
//! for it (memory per viewer is one part in flight).
//!
//! While a scan runs the camera belongs to the scan: no capture is asked for, and a viewer gets
//! the last frame again every [`KEEPALIVE`] so that its connection stays open.

use std::sync::Arc;
use std::time::{Duration, Instant};

use axum::body::Bytes;

use super::rig::{RigError, RigHandle};

/// Frame rate a viewer gets when it asks for none, frames per second.
pub const DEFAULT_FPS: f64 = 5.0;
/// Highest frame rate a viewer may ask for, frames per second.
pub const MAX_FPS: f64 = 15.0;
/// How often the last frame is sent again while the stream is paused (a scan runs).
pub const KEEPALIVE: Duration = Duration::from_secs(2);
/// JPEG quality of the live frames (1-100).
const JPEG_QUALITY: u8 = 80;
/// Longest wait for one capture.
const CAPTURE_TIMEOUT: Duration = Duration::from_secs(10);

/// One encoded live frame.
#[derive(Debug, Clone)]
pub struct JpegFrame {
    /// The camera's frame counter.
    pub sequence: u64,
    /// When it was captured (monotonic).
    pub taken: Instant,
    /// The JPEG file.
    pub jpeg: Bytes,
}

/// The newest live frame, shared by every viewer.
#[derive(Debug)]
pub struct LiveCamera {
    rig: RigHandle,
    latest: tokio::sync::Mutex<Option<JpegFrame>>,
    /// A copy of the newest frame readable without waiting for a capture in progress.
    last: std::sync::Mutex<Option<JpegFrame>>,
}

/// Why no live frame could be had.
#[derive(Debug, thiserror::Error)]
pub enum LiveError {
    /// The capture failed.
    #[error("capture failed")]
    Rig(#[source] RigError),
    /// The capture did not answer in time.
    #[error("no frame within {0:?}")]
    Timeout(Duration),
    /// The frame could not be encoded.
    #[error("cannot encode the frame as JPEG")]
    Encode(#[source] image::ImageError),
}

impl LiveCamera {
    /// Live frames from `rig`'s camera.
    pub fn new(rig: RigHandle) -> Arc<LiveCamera> {
        Arc::new(LiveCamera { rig, latest: tokio::sync::Mutex::new(None), last: std::sync::Mutex::new(None) })
    }

    /// A frame captured at most `max_age` ago: the shared newest one, or a new capture.
    pub async fn frame(&self, max_age: Duration) -> Result<JpegFrame, LiveError> {
        let mut latest = self.latest.lock().await;
        if let Some(f) = latest.as_ref().filter(|f| f.taken.elapsed() <= max_age) {
            return Ok(f.clone());
        }
        let taken = Instant::now();
        let frame = tokio::time::timeout(CAPTURE_TIMEOUT, self.rig.capture())
            .await
            .map_err(|_| LiveError::Timeout(CAPTURE_TIMEOUT))?
            .map_err(LiveError::Rig)?;
        let sequence = frame.sequence;
        let jpeg = tokio::task::spawn_blocking(move || encode_jpeg(&frame.image, JPEG_QUALITY))
            .await
            .map_err(|_| LiveError::Rig(RigError::Stopped))?
            .map_err(LiveError::Encode)?;
        let f = JpegFrame { sequence, taken, jpeg: Bytes::from(jpeg) };
        *latest = Some(f.clone());
        if let Ok(mut last) = self.last.lock() {
            *last = Some(f.clone());
        }
        Ok(f)
    }

    /// The newest frame captured so far, if any (never waits).
    pub fn last(&self) -> Option<JpegFrame> {
        self.last.lock().ok().and_then(|l| l.clone())
    }
}

/// `image` as a baseline JPEG of `quality` (1-100).
pub fn encode_jpeg(image: &image::RgbImage, quality: u8) -> Result<Vec<u8>, image::ImageError> {
    let mut out = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, quality).encode_image(image)?;
    Ok(out)
}

/// One part of a `multipart/x-mixed-replace; boundary=frame` stream: the boundary, the part's
/// headers (`Content-Type`, `Content-Length`, `X-Frame-Sequence`) and the JPEG.
pub fn mjpeg_part(frame: &JpegFrame) -> Bytes {
    let head = format!(
        "--frame\r\nContent-Type: image/jpeg\r\nContent-Length: {}\r\nX-Frame-Sequence: {}\r\n\r\n",
        frame.jpeg.len(),
        frame.sequence
    );
    let mut part = Vec::with_capacity(head.len() + frame.jpeg.len() + 2);
    part.extend_from_slice(head.as_bytes());
    part.extend_from_slice(&frame.jpeg);
    part.extend_from_slice(b"\r\n");
    Bytes::from(part)
}

/// A viewer's frame period for a requested rate: `fps` (default [`DEFAULT_FPS`]) capped at
/// [`MAX_FPS`]. `None` when `fps` is not a positive number.
pub fn frame_period(fps: Option<f64>) -> Option<Duration> {
    let fps = fps.unwrap_or(DEFAULT_FPS);
    (fps.is_finite() && fps > 0.0).then(|| Duration::from_secs_f64(1.0 / fps.min(MAX_FPS)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rates_are_capped_and_nonsense_refused() {
        assert_eq!(frame_period(None), Some(Duration::from_millis(200)));
        assert_eq!(frame_period(Some(100.0)), Some(Duration::from_secs_f64(1.0 / 15.0)));
        assert_eq!(frame_period(Some(1.0)), Some(Duration::from_secs(1)));
        for bad in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            assert_eq!(frame_period(Some(bad)), None, "{bad}");
        }
    }

    #[test]
    fn a_part_carries_its_length_and_sequence_and_a_decodable_jpeg() {
        let img = image::RgbImage::from_fn(8, 6, |x, y| image::Rgb([x as u8 * 30, y as u8 * 40, 7]));
        let jpeg = encode_jpeg(&img, 90).expect("encode");
        let f = JpegFrame { sequence: 42, taken: Instant::now(), jpeg: Bytes::from(jpeg.clone()) };
        let part = mjpeg_part(&f);
        let text = String::from_utf8_lossy(&part[..80.min(part.len())]).into_owned();
        assert!(text.starts_with("--frame\r\nContent-Type: image/jpeg\r\n"), "{text}");
        assert!(text.contains(&format!("Content-Length: {}\r\n", jpeg.len())), "{text}");
        assert!(text.contains("X-Frame-Sequence: 42\r\n"), "{text}");
        let body = &part[part.len() - 2 - jpeg.len()..part.len() - 2];
        let back = image::load_from_memory_with_format(body, image::ImageFormat::Jpeg).expect("decode");
        assert_eq!((back.width(), back.height()), (8, 6));
    }
}

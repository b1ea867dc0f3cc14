//! UVC cameras through nokhwa (cargo feature `nokhwa`), for platforms without V4L2 (macOS
//! AVFoundation, Windows Media Foundation); on Linux nokhwa itself goes through V4L2. Same
//! [`Camera`](super::Camera) trait, same pixel conversion ([`pixel`](super::pixel)) and control lock
//! ([`controls`](super::controls)) as the V4L2 driver.
//!
//! nokhwa's `frame()` blocks without a timeout, so the camera lives on a capture thread that hands
//! frames over a bounded channel of `buffers` frames (frames that find it full are dropped and
//! counted); [`capture`](super::Camera::capture) waits on the channel with its timeout.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc::{self, Receiver, RecvTimeoutError, SyncSender, TrySendError};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;

use nokhwa::pixel_format::RgbFormat;
use nokhwa::utils::{
    ApiBackend, CameraFormat, CameraIndex, ControlValueDescription, ControlValueSetter, FrameFormat,
    KnownCameraControl, RequestedFormat, RequestedFormatType,
};
use nokhwa::Camera as NokhwaCamera;

use super::controls::{cid, ControlBackend, ControlLock, ControlRange};
use super::pixel::PixelFormat;
use super::stream::TimestampSource;
use super::streaming::{BufferClock, FrameAssembler, RawFrame, RawStream};
use crate::config::RealCameraConfig;
use crate::devices::sysfs::{CameraSelector, SysRoot};
use crate::devices::DeviceError;

const NAME: &str = "camera";

fn hw(detail: impl std::fmt::Display) -> DeviceError {
    DeviceError::Hardware { device: NAME.into(), code: 0, detail: detail.to_string() }
}

/// nokhwa's frame format for ours.
pub fn frame_format(f: PixelFormat) -> FrameFormat {
    match f {
        PixelFormat::Grey => FrameFormat::GRAY,
        PixelFormat::Yuyv => FrameFormat::YUYV,
        PixelFormat::Mjpeg => FrameFormat::MJPEG,
        PixelFormat::Rgb24 => FrameFormat::RAWRGB,
    }
}

/// Ours for nokhwa's, when we convert it.
pub fn pixel_format(f: FrameFormat) -> Option<PixelFormat> {
    match f {
        FrameFormat::GRAY => Some(PixelFormat::Grey),
        FrameFormat::YUYV => Some(PixelFormat::Yuyv),
        FrameFormat::MJPEG => Some(PixelFormat::Mjpeg),
        FrameFormat::RAWRGB => Some(PixelFormat::Rgb24),
        FrameFormat::NV12 | FrameFormat::RAWBGR => None,
    }
}

/// The nokhwa control for a V4L2 control id: the manual values by name on every platform, the auto
/// switches by their V4L2 id on Linux only (other platforms have no portable auto switch; those
/// entries are skipped by the lock).
fn known_control(id: u32) -> Option<KnownCameraControl> {
    match id {
        cid::EXPOSURE_ABSOLUTE => Some(KnownCameraControl::Exposure),
        cid::GAIN => Some(KnownCameraControl::Gain),
        cid::WHITE_BALANCE_TEMPERATURE => Some(KnownCameraControl::WhiteBalance),
        cid::FOCUS_ABSOLUTE => Some(KnownCameraControl::Focus),
        other if cfg!(target_os = "linux") => Some(KnownCameraControl::Other(other as u128)),
        _ => None,
    }
}

struct NokhwaControls<'a> {
    camera: &'a mut NokhwaCamera,
}

impl ControlBackend for NokhwaControls<'_> {
    fn range(&self, id: u32) -> Option<ControlRange> {
        let c = self.camera.camera_control(known_control(id)?).ok()?;
        match c.description() {
            ControlValueDescription::IntegerRange { min, max, step, .. } => {
                Some(ControlRange { min: *min, max: *max, step: (*step).max(1) })
            }
            ControlValueDescription::Integer { .. } => Some(ControlRange { min: i64::MIN, max: i64::MAX, step: 1 }),
            ControlValueDescription::Boolean { .. } => Some(ControlRange { min: 0, max: 1, step: 1 }),
            _ => None,
        }
    }

    fn id_by_name(&self, name: &str) -> Option<u32> {
        let controls = self.camera.camera_controls().ok()?;
        controls.into_iter().find(|c| c.name().eq_ignore_ascii_case(name)).and_then(|c| match c.control() {
            KnownCameraControl::Other(id) => u32::try_from(id).ok(),
            _ => None,
        })
    }

    fn get(&mut self, id: u32) -> std::io::Result<i64> {
        let known = known_control(id).ok_or_else(|| std::io::Error::from(std::io::ErrorKind::Unsupported))?;
        let c = self.camera.camera_control(known).map_err(std::io::Error::other)?;
        match c.value() {
            ControlValueSetter::Integer(v) | ControlValueSetter::EnumValue(v) => Ok(v),
            ControlValueSetter::Boolean(b) => Ok(b as i64),
            other => Err(std::io::Error::other(format!("control {id:#x} is not an integer: {other:?}"))),
        }
    }

    fn set(&mut self, id: u32, value: i64) -> std::io::Result<()> {
        let known = known_control(id).ok_or_else(|| std::io::Error::from(std::io::ErrorKind::Unsupported))?;
        self.camera.set_camera_control(known, ControlValueSetter::Integer(value)).map_err(std::io::Error::other)
    }
}

/// What the capture thread hands over: the bytes, nokhwa's wall-clock stamp, and a sequence number
/// counting every frame nokhwa returned (including ones the full channel dropped).
type Delivery = Result<(Vec<u8>, Option<Duration>, u32), String>;

/// The capture thread's channel as a [`RawStream`].
#[derive(Debug)]
struct Channel {
    frames: Receiver<Delivery>,
    current: Vec<u8>,
}

impl RawStream for Channel {
    fn next_buffer(&mut self, timeout: Duration) -> std::io::Result<RawFrame<'_>> {
        let (data, stamp, sequence) = match self.frames.recv_timeout(timeout) {
            Ok(Ok(d)) => d,
            Ok(Err(e)) => return Err(gone(std::io::Error::other(e))),
            Err(RecvTimeoutError::Timeout) => return Err(std::io::Error::from(std::io::ErrorKind::TimedOut)),
            Err(RecvTimeoutError::Disconnected) => return Err(gone(std::io::Error::other("capture thread ended"))),
        };
        self.current = data;
        // nokhwa stamps the end of the frame in wall-clock time (UVC timestamps end of frame).
        let clock = stamp.map_or(BufferClock::None, |ts| BufferClock::Wall(ts, TimestampSource::EndOfFrame));
        Ok(RawFrame { data: &self.current, sequence, clock, corrupt: false })
    }
}

/// A capture failure from nokhwa means the camera went away: reported as `ENODEV`.
fn gone(e: std::io::Error) -> std::io::Error {
    tracing::warn!(error = %e, "UVC capture failed");
    std::io::Error::from_raw_os_error(libc::ENODEV)
}

/// A UVC camera through nokhwa.
#[derive(Debug)]
pub struct UvcCamera {
    stream: Channel,
    frames: FrameAssembler,
    stop: Arc<AtomicBool>,
    dropped: Arc<AtomicU64>,
    worker: Option<JoinHandle<()>>,
}

/// The nokhwa index of a selector: on Linux through `/sys` (the `/dev/videoN` number); `card:NAME`
/// also by the names nokhwa lists (any platform).
fn camera_index(selector: &CameraSelector, root: &SysRoot) -> Result<CameraIndex, DeviceError> {
    if let CameraSelector::Card(name) = selector {
        let cams = nokhwa::query(ApiBackend::Auto).map_err(hw)?;
        if let Some(c) = cams.iter().find(|c| c.human_name() == *name) {
            return Ok(c.index().clone());
        }
    }
    let node = root.resolve_camera(selector).map_err(|e| DeviceError::Disconnected {
        device: NAME.into(),
        source: Some(std::io::Error::new(std::io::ErrorKind::NotFound, e.to_string())),
    })?;
    let number = node
        .file_name()
        .and_then(|n| n.to_str())
        .and_then(|n| n.strip_prefix("video"))
        .and_then(|n| n.parse().ok())
        .ok_or_else(|| DeviceError::InvalidConfig {
            device: NAME.into(),
            field: "device",
            problem: format!("{} is not a /dev/videoN node", node.display()),
        })?;
    Ok(CameraIndex::Index(number))
}

impl UvcCamera {
    /// Open the camera, set the format and controls, and start the capture thread. nokhwa's camera is
    /// not `Send`, so it is opened on the thread that captures; opening waits at most 10 s for it.
    pub fn open(config: &RealCameraConfig, root: &SysRoot) -> Result<Self, DeviceError> {
        let selector = CameraSelector::parse(&config.device).map_err(|e| DeviceError::InvalidConfig {
            device: NAME.into(),
            field: "device",
            problem: e.to_string(),
        })?;
        let index = camera_index(&selector, root)?;
        let (tx, rx) = mpsc::sync_channel(config.buffers.max(1) as usize);
        let (ready_tx, ready_rx) = mpsc::sync_channel(1);
        let stop = Arc::new(AtomicBool::new(false));
        let dropped = Arc::new(AtomicU64::new(0));
        let worker = {
            let (stop, dropped, config) = (stop.clone(), dropped.clone(), config.clone());
            std::thread::Builder::new()
                .name("uvc-capture".into())
                .spawn(move || match open_on_this_thread(index, &config) {
                    Ok((camera, lock, format, fps)) => {
                        if ready_tx.send(Ok((format, fps))).is_ok() {
                            capture_loop(camera, lock, tx, &stop, &dropped);
                        }
                    }
                    Err(e) => {
                        let _ = ready_tx.send(Err(e));
                    }
                })
                .map_err(|source| DeviceError::Io { device: NAME.into(), source })?
        };
        let open_timeout = Duration::from_secs(10);
        let (format, fps) = match ready_rx.recv_timeout(open_timeout) {
            Ok(r) => r?,
            Err(_) => {
                stop.store(true, Ordering::Relaxed);
                return Err(DeviceError::Timeout {
                    device: NAME.into(),
                    waiting_for: "the camera to open",
                    timeout: open_timeout,
                });
            }
        };
        let period = Duration::from_secs_f64(1.0 / fps.max(1) as f64);
        let exposure = config.controls.exposure_us.map_or(period, |us| Duration::from_micros(us as u64));
        Ok(UvcCamera {
            stream: Channel { frames: rx, current: Vec::new() },
            frames: FrameAssembler::new(NAME, format, (config.width, config.height), 0, exposure, period),
            stop,
            dropped,
            worker: Some(worker),
        })
    }

    /// Frames dropped because the consumer was slower than the camera (also counted as sequence
    /// gaps by the frames that follow them).
    pub fn dropped_frames(&self) -> u64 {
        self.dropped.load(Ordering::Relaxed)
    }
}

/// Open the camera at the first usable format, lock its controls and start its stream.
fn open_on_this_thread(
    index: CameraIndex,
    config: &RealCameraConfig,
) -> Result<(NokhwaCamera, ControlLock, PixelFormat, u32), DeviceError> {
    let fps = config.fps.unwrap_or(30);
    let candidates: Vec<PixelFormat> = match config.format {
        Some(f) => vec![f],
        None => PixelFormat::PREFERENCE.to_vec(),
    };
    let mut last_error = None;
    let mut opened = None;
    for f in candidates {
        let want = CameraFormat::new_from(config.width, config.height, frame_format(f), fps);
        let request = RequestedFormat::new::<RgbFormat>(RequestedFormatType::Exact(want));
        match NokhwaCamera::new(index.clone(), request) {
            Ok(c) => {
                opened = Some((c, f));
                break;
            }
            Err(e) => last_error = Some(e),
        }
    }
    let Some((mut camera, format)) = opened else {
        return Err(DeviceError::InvalidConfig {
            device: NAME.into(),
            field: "format",
            problem: format!(
                "the camera opens no supported format at {}x{} {fps} fps: {}",
                config.width,
                config.height,
                last_error.map(|e| e.to_string()).unwrap_or_default()
            ),
        });
    };
    let mut lock = ControlLock::apply(&mut NokhwaControls { camera: &mut camera }, &config.controls)
        .map_err(|e| DeviceError::InvalidConfig { device: NAME.into(), field: "controls", problem: e.to_string() })?;
    if let Err(e) = camera.open_stream() {
        lock.restore(&mut NokhwaControls { camera: &mut camera });
        return Err(hw(e));
    }
    let fps = camera.frame_rate();
    Ok((camera, lock, format, fps))
}

fn capture_loop(
    mut camera: NokhwaCamera,
    mut lock: ControlLock,
    tx: SyncSender<Delivery>,
    stop: &AtomicBool,
    dropped: &AtomicU64,
) {
    let mut sequence: u32 = 0;
    while !stop.load(Ordering::Relaxed) {
        let delivery = match camera.frame() {
            Ok(buf) => Ok((buf.buffer().to_vec(), buf.capture_timestamp(), sequence)),
            Err(e) => Err(e.to_string()),
        };
        sequence = sequence.wrapping_add(1);
        let failed = delivery.is_err();
        match tx.try_send(delivery) {
            Ok(()) => {}
            Err(TrySendError::Full(_)) => {
                dropped.fetch_add(1, Ordering::Relaxed);
            }
            Err(TrySendError::Disconnected(_)) => break,
        }
        if failed {
            break;
        }
    }
    lock.restore(&mut NokhwaControls { camera: &mut camera });
    if let Err(e) = camera.stop_stream() {
        tracing::debug!(error = %e, "stopping the UVC stream");
    }
}

impl super::Camera for UvcCamera {
    fn info(&self) -> super::CameraInfo {
        let (width, height) = self.frames.size();
        super::CameraInfo { width, height }
    }

    fn capture(&mut self, timeout: Duration) -> Result<super::Frame, DeviceError> {
        self.frames.capture(&mut self.stream, timeout)
    }
}

impl Drop for UvcCamera {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        // The worker leaves at its next frame; if the camera is gone it may block in nokhwa, so it
        // is not joined here (dropping never hangs). Its controls are restored when it leaves.
        if let Some(w) = self.worker.take() {
            if w.is_finished() {
                let _ = w.join();
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn formats_map_both_ways() {
        for f in PixelFormat::PREFERENCE {
            assert_eq!(pixel_format(frame_format(f)), Some(f));
        }
        assert_eq!(pixel_format(FrameFormat::NV12), None);
        assert!(matches!(known_control(cid::EXPOSURE_ABSOLUTE), Some(KnownCameraControl::Exposure)));
    }
}

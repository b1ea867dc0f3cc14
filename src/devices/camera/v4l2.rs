//! V4L2 cameras (cargo feature `v4l`): a camera chosen by stable identity, format negotiation,
//! exposure / gain / white balance / focus locked for the scan and restored after, memory-mapped
//! streaming with the driver's timestamps and sequence numbers.
//!
//! The device-free parts live beside this file and are tested without a camera:
//! [`pixel`](super::pixel) (format conversion), [`controls`](super::controls) (the control lock),
//! [`stream`](super::stream) (timestamps, dropped frames, freshness) and
//! [`sysfs`](crate::devices::sysfs) (which node is which camera).
//!
//! Stale frames: the driver keeps `buffers` frames queued, so after a scene change the next frames
//! returned may have been exposed before it. Each [`Frame`](super::Frame) carries its start of
//! exposure from the driver's `CLOCK_MONOTONIC` timestamp (moved back by the exposure and readout
//! time when the driver stamps the end of the frame, as UVC does), and the acquisition layer drops
//! frames that started before its last change.
//!
//! External trigger: V4L2 has no standard trigger control; cameras with a trigger input expose a
//! vendor control (e.g. `trigger_mode`), set with `[camera.controls.extra]` and restored like the
//! others.

use std::path::{Path, PathBuf};
use std::time::Duration;

use v4l::buffer::{Flags as BufFlags, Type as BufType};
use v4l::control::{Control, Description as ControlDescription, Type as ControlType, Value};
use v4l::framesize::FrameSizeEnum;
use v4l::io::traits::CaptureStream;
use v4l::prelude::{Device, MmapStream};
use v4l::video::Capture;
use v4l::FourCC;

use super::controls::{cid, exposure_v4l2_to_us, ControlBackend, ControlLock, ControlRange};
use super::pixel::PixelFormat;
use super::stream::TimestampSource;
use super::streaming::{BufferClock, FrameAssembler, RawFrame, RawStream};
use crate::config::RealCameraConfig;
use crate::devices::sysfs::{CameraSelector, SysRoot};
use crate::devices::DeviceError;

const NAME: &str = "camera";

fn io_error(source: std::io::Error) -> DeviceError {
    if source.raw_os_error() == Some(libc::ENODEV) {
        DeviceError::Disconnected { device: NAME.into(), source: Some(source) }
    } else {
        DeviceError::Io { device: NAME.into(), source }
    }
}

/// Run a `v4l` query that unwraps what the device reports (non-UTF-8 names, control types it does
/// not know) and so may panic; the panic becomes an `InvalidData` error.
fn guarded<T>(what: &str, query: impl FnOnce() -> std::io::Result<T>) -> std::io::Result<T> {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(query)).unwrap_or_else(|_| {
        Err(std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!("the device reports {what} the v4l crate cannot decode"),
        ))
    })
}

fn invalid(field: &'static str, problem: String) -> DeviceError {
    DeviceError::InvalidConfig { device: NAME.into(), field, problem }
}

/// The controls of an open V4L2 device.
struct V4l2Controls<'a> {
    device: &'a Device,
    descriptions: Vec<ControlDescription>,
}

/// A control name as `v4l2-ctl --list-ctrls` prints it: lower case, words joined by `_`.
fn control_key(name: &str) -> String {
    let mut out = String::new();
    for word in name.split(|c: char| !c.is_ascii_alphanumeric()).filter(|w| !w.is_empty()) {
        if !out.is_empty() {
            out.push('_');
        }
        out.push_str(&word.to_ascii_lowercase());
    }
    out
}

impl ControlBackend for V4l2Controls<'_> {
    fn range(&self, id: u32) -> Option<ControlRange> {
        self.descriptions.iter().find(|d| d.id == id).map(|d| ControlRange {
            min: d.minimum,
            max: d.maximum,
            step: d.step.clamp(1, i64::MAX as u64) as i64,
        })
    }

    fn id_by_name(&self, name: &str) -> Option<u32> {
        let key = control_key(name);
        self.descriptions.iter().find(|d| control_key(&d.name) == key).map(|d| d.id)
    }

    fn get(&mut self, id: u32) -> std::io::Result<i64> {
        match self.device.control(id)?.value {
            Value::Integer(v) => Ok(v),
            Value::Boolean(b) => Ok(b as i64),
            other => Err(std::io::Error::other(format!("control {id:#x} is not an integer: {other:?}"))),
        }
    }

    fn set(&mut self, id: u32, value: i64) -> std::io::Result<()> {
        let boolean = self.descriptions.iter().any(|d| d.id == id && d.typ == ControlType::Boolean);
        let value = if boolean { Value::Boolean(value != 0) } else { Value::Integer(value) };
        self.device.set_control(Control { id, value })
    }
}

/// The memory-mapped stream as a [`RawStream`].
struct Mmap(MmapStream<'static>);

impl RawStream for Mmap {
    fn next_buffer(&mut self, timeout: Duration) -> std::io::Result<RawFrame<'_>> {
        self.0.set_timeout(timeout);
        let (buf, meta) = CaptureStream::next(&mut self.0)?;
        let ts = Duration::from(meta.timestamp);
        let source = if (meta.flags & BufFlags::TSTAMP_SRC_MASK) == BufFlags::TSTAMP_SRC_SOE {
            TimestampSource::StartOfExposure
        } else {
            TimestampSource::EndOfFrame
        };
        let clock = if (meta.flags & BufFlags::TIMESTAMP_MASK) == BufFlags::TIMESTAMP_MONOTONIC {
            BufferClock::Monotonic(ts, source)
        } else {
            BufferClock::None
        };
        let used = (meta.bytesused as usize).min(buf.len());
        Ok(RawFrame {
            data: if used == 0 { buf } else { &buf[..used] },
            sequence: meta.sequence,
            clock,
            corrupt: meta.flags.contains(BufFlags::ERROR),
        })
    }
}

/// A V4L2 camera streaming through memory-mapped buffers.
pub struct V4l2Camera {
    // Dropped before `device`: the stream's buffers belong to the open device.
    stream: Mmap,
    device: Device,
    path: PathBuf,
    frames: FrameAssembler,
    lock: ControlLock,
}

impl std::fmt::Debug for V4l2Camera {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("V4l2Camera").field("path", &self.path).field("frames", &self.frames).finish_non_exhaustive()
    }
}

/// True when `fourcc` at `width` x `height` is among the device's frame sizes.
fn offers_size(device: &Device, fourcc: FourCC, width: u32, height: u32) -> bool {
    let Ok(sizes) = device.enum_framesizes(fourcc) else { return false };
    sizes.into_iter().any(|s| match s.size {
        FrameSizeEnum::Discrete(d) => d.width == width && d.height == height,
        FrameSizeEnum::Stepwise(s) => {
            let fits = |v: u32, min: u32, max: u32, step: u32| v >= min && v <= max && (v - min) % step.max(1) == 0;
            fits(width, s.min_width, s.max_width, s.step_width)
                && fits(height, s.min_height, s.max_height, s.step_height)
        }
    })
}

impl V4l2Camera {
    /// Resolve `config.device` below `root`, open it, negotiate the format, lock the controls and
    /// start streaming.
    pub fn open(config: &RealCameraConfig, root: &SysRoot) -> Result<Self, DeviceError> {
        let selector = CameraSelector::parse(&config.device).map_err(|e| invalid("device", e.to_string()))?;
        let node = root.resolve_camera(&selector).map_err(|e| match e {
            crate::devices::sysfs::ResolveError::NotFound { .. } => DeviceError::Disconnected {
                device: NAME.into(),
                source: Some(std::io::Error::new(std::io::ErrorKind::NotFound, e.to_string())),
            },
            other => invalid("device", other.to_string()),
        })?;
        let path = root.path(&node);
        let device = Device::with_path(&path).map_err(io_error)?;
        let caps = guarded("capabilities", || device.query_caps()).map_err(io_error)?;
        if let CameraSelector::Bus(bus) = &selector {
            if caps.bus != *bus {
                return Err(invalid("device", format!("{} reports bus `{}`, not `{bus}`", path.display(), caps.bus)));
            }
        }
        tracing::info!(device = %path.display(), card = %caps.card, bus = %caps.bus, driver = %caps.driver, "V4L2 camera");

        let offered: Vec<PixelFormat> = device
            .enum_formats()
            .map_err(io_error)?
            .iter()
            .filter_map(|d| PixelFormat::from_fourcc(d.fourcc.repr))
            .collect();
        let usable = |f: PixelFormat| {
            offered.contains(&f) && offers_size(&device, FourCC::new(&f.fourcc()), config.width, config.height)
        };
        let format = match config.format {
            Some(f) if usable(f) => f,
            Some(f) => {
                return Err(invalid(
                    "format",
                    format!(
                        "{} does not offer {f} at {}x{} (it offers: {})",
                        path.display(),
                        config.width,
                        config.height,
                        offered.iter().map(|f| f.name()).collect::<Vec<_>>().join(", ")
                    ),
                ))
            }
            None => PixelFormat::PREFERENCE.into_iter().find(|&f| usable(f)).ok_or_else(|| {
                invalid(
                    "width",
                    format!("{} offers no known format at {}x{}", path.display(), config.width, config.height),
                )
            })?,
        };
        let want = v4l::Format::new(config.width, config.height, FourCC::new(&format.fourcc()));
        let got = device.set_format(&want).map_err(io_error)?;
        if got.width != config.width || got.height != config.height || got.fourcc != want.fourcc {
            return Err(invalid(
                "width",
                format!(
                    "asked for {}x{} {format}, the camera set {}x{} {}",
                    config.width, config.height, got.width, got.height, got.fourcc
                ),
            ));
        }
        let mut period = Duration::from_millis(100);
        if let Some(fps) = config.fps {
            device.set_params(&v4l::video::capture::Parameters::with_fps(fps)).map_err(io_error)?;
        }
        if let Ok(p) = device.params() {
            if p.interval.denominator > 0 {
                period = Duration::from_secs_f64(p.interval.numerator as f64 / p.interval.denominator as f64);
            }
        }

        let mut backend = V4l2Controls {
            device: &device,
            descriptions: guarded("controls", || device.query_controls()).map_err(io_error)?,
        };
        let lock =
            ControlLock::apply(&mut backend, &config.controls).map_err(|e| invalid("controls", e.to_string()))?;
        let exposure = match config.controls.exposure_us {
            Some(us) => Duration::from_micros(us as u64),
            None => backend
                .get(cid::EXPOSURE_ABSOLUTE)
                .map(|u| Duration::from_micros(exposure_v4l2_to_us(u)))
                .unwrap_or(period),
        };

        let stream = match MmapStream::with_buffers(&device, BufType::VideoCapture, config.buffers) {
            Ok(s) => s,
            Err(e) => {
                let mut lock = lock;
                lock.restore(&mut backend);
                return Err(io_error(e));
            }
        };
        let frames = FrameAssembler::new(NAME, format, (got.width, got.height), got.stride as usize, exposure, period);
        Ok(V4l2Camera { stream: Mmap(stream), device, path, frames, lock })
    }

    /// Frames dropped by the driver so far (gaps in its sequence numbers).
    pub fn dropped_frames(&self) -> u64 {
        self.frames.dropped()
    }

    /// The device node streaming.
    pub fn path(&self) -> &Path {
        &self.path
    }
}

impl super::Camera for V4l2Camera {
    fn info(&self) -> super::CameraInfo {
        let (width, height) = self.frames.size();
        super::CameraInfo { width, height }
    }

    fn capture(&mut self, timeout: Duration) -> Result<super::Frame, DeviceError> {
        self.frames.capture(&mut self.stream, timeout)
    }
}

impl Drop for V4l2Camera {
    fn drop(&mut self) {
        use v4l::io::traits::Stream as _;
        if let Err(e) = self.stream.0.stop() {
            tracing::debug!(error = %e, "stopping the V4L2 stream");
        }
        let descriptions = match guarded("controls", || self.device.query_controls()) {
            Ok(d) => d,
            Err(e) => {
                tracing::warn!(error = %e, "cannot read the controls to restore them");
                return;
            }
        };
        let mut backend = V4l2Controls { device: &self.device, descriptions };
        let failed = self.lock.restore(&mut backend);
        tracing::debug!(failed, dropped = self.frames.dropped(), skipped = self.frames.skipped(), "V4L2 camera closed");
    }
}

/// What a V4L2 node says about itself for `scanrig devices`: a `bus_info ... driver ...` line, then
/// one line per format with its frame sizes (`format MJPG 1920x1080 1280x720`).
pub fn describe_formats(node: &Path) -> std::io::Result<Vec<String>> {
    let device = Device::with_path(node)?;
    let caps = guarded("capabilities", || device.query_caps())?;
    let mut out = vec![format!("bus_info {} driver {}", caps.bus, caps.driver)];
    for d in device.enum_formats()? {
        let mut sizes: Vec<String> = Vec::new();
        for s in device.enum_framesizes(d.fourcc).unwrap_or_default() {
            match s.size {
                FrameSizeEnum::Discrete(d) => sizes.push(format!("{}x{}", d.width, d.height)),
                FrameSizeEnum::Stepwise(s) => {
                    sizes.push(format!("{}x{}..{}x{}", s.min_width, s.min_height, s.max_width, s.max_height))
                }
            }
        }
        let known = if PixelFormat::from_fourcc(d.fourcc.repr).is_some() { "" } else { " (not supported by scanrig)" };
        out.push(format!("format {} {}{known}", d.fourcc, sizes.join(" ")));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_panicking_query_is_an_error() {
        let e = guarded::<()>("controls", || panic!("unknown control type")).expect_err("caught");
        assert_eq!(e.kind(), std::io::ErrorKind::InvalidData);
        assert_eq!(guarded("x", || Ok(3)).expect("passes through"), 3);
    }

    #[test]
    fn control_names_match_v4l2_ctl_spelling() {
        assert_eq!(control_key("Exposure, Auto"), "exposure_auto");
        assert_eq!(control_key("White Balance Temperature"), "white_balance_temperature");
        assert_eq!(control_key("  Trigger-Mode "), "trigger_mode");
    }

    #[test]
    fn a_missing_camera_is_disconnected_not_a_crash() {
        let dir = tempfile::tempdir().expect("tempdir");
        let config: RealCameraConfig = toml::from_str(
            r#"device = "usb:046d:082d"
width = 640
height = 480
[calibration.intrinsics]
fx = 500.0
fy = 500.0
cx = 320.0
cy = 240.0
[calibration.pose]
eye_m = [0.5, 0.0, 0.2]
target_m = [0.0, 0.0, 0.05]
"#,
        )
        .expect("config");
        let e = V4l2Camera::open(&config, &SysRoot::new(dir.path())).expect_err("no camera");
        assert_eq!(e.kind(), crate::devices::ErrorKind::Disconnected, "{e}");
    }
}

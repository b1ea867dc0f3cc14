//! The capture loop shared by the real camera drivers, over a [`RawStream`] of driver buffers:
//! waits within the caller's timeout, skips frames the driver marks corrupt and frames that do not
//! convert, counts sequence gaps, turns driver timestamps into start-of-exposure instants, and maps
//! I/O failures to [`DeviceError`] kinds. The V4L2 and UVC drivers supply the stream; tests supply
//! a scripted one, so this runs without a camera.

use std::time::{Duration, Instant, SystemTime};

use super::pixel::{to_rgb, PixelFormat};
use super::stream::{exposure_start, monotonic_now, SequenceTracker, TimestampSource};
use super::Frame;
use crate::devices::DeviceError;

/// The clock a driver stamped a buffer with.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BufferClock {
    /// `CLOCK_MONOTONIC` (V4L2 `TIMESTAMP_MONOTONIC`), time since boot.
    Monotonic(Duration, TimestampSource),
    /// Wall-clock time since the Unix epoch (nokhwa).
    Wall(Duration, TimestampSource),
    /// No usable timestamp.
    None,
}

/// One buffer dequeued from a driver.
#[derive(Debug, Clone, Copy)]
pub struct RawFrame<'a> {
    /// The bytes the driver filled (`bytesused`).
    pub data: &'a [u8],
    /// The driver's sequence number (32-bit, wrapping).
    pub sequence: u32,
    /// When the driver stamped it.
    pub clock: BufferClock,
    /// The driver marked the data corrupt (`V4L2_BUF_FLAG_ERROR`).
    pub corrupt: bool,
}

/// A driver's stream of filled buffers.
pub trait RawStream {
    /// The next filled buffer, waiting at most `timeout` (never zero). Fails with
    /// `ErrorKind::TimedOut` when nothing came, `ENODEV` when the device is gone.
    fn next_buffer(&mut self, timeout: Duration) -> std::io::Result<RawFrame<'_>>;
}

/// The format of the stream and the times that bound a frame's exposure.
#[derive(Debug, Clone)]
pub struct FrameAssembler {
    device: &'static str,
    format: PixelFormat,
    width: u32,
    height: u32,
    stride: usize,
    /// Exposure time, for end-of-frame timestamps.
    exposure: Duration,
    /// Frame period, the readout time bound for end-of-frame timestamps.
    period: Duration,
    tracker: SequenceTracker,
    skipped: u64,
}

impl FrameAssembler {
    /// Frames of `format`, `width` x `height` pixels, rows `stride` bytes apart (0 = packed), exposed
    /// for `exposure` at one frame per `period`; `device` names the device in errors.
    pub fn new(
        device: &'static str,
        format: PixelFormat,
        (width, height): (u32, u32),
        stride: usize,
        exposure: Duration,
        period: Duration,
    ) -> Self {
        FrameAssembler {
            device,
            format,
            width,
            height,
            stride,
            exposure,
            period,
            tracker: SequenceTracker::new(),
            skipped: 0,
        }
    }

    /// Image size, pixels (width, height).
    pub fn size(&self) -> (u32, u32) {
        (self.width, self.height)
    }

    /// Frames lost so far: gaps in the driver's sequence numbers.
    pub fn dropped(&self) -> u64 {
        self.tracker.dropped()
    }

    /// Frames received but not delivered (corrupt, or not convertible).
    pub fn skipped(&self) -> u64 {
        self.skipped
    }

    fn io_error(&self, source: std::io::Error) -> DeviceError {
        match source.raw_os_error() {
            Some(libc::ENODEV) | Some(libc::ENXIO) | Some(libc::ESHUTDOWN) => {
                DeviceError::Disconnected { device: self.device.into(), source: Some(source) }
            }
            _ => DeviceError::Io { device: self.device.into(), source },
        }
    }

    /// The start of exposure of a frame stamped `clock`, received `now`.
    pub fn exposure_start(&self, clock: BufferClock, now: Instant) -> Instant {
        match clock {
            BufferClock::Monotonic(ts, source) => {
                exposure_start(ts, source, self.exposure, self.period, monotonic_now(), now)
            }
            BufferClock::Wall(ts, source) => match SystemTime::now().duration_since(SystemTime::UNIX_EPOCH) {
                Ok(wall) => exposure_start(ts, source, self.exposure, self.period, wall, now),
                Err(_) => self.exposure_start(BufferClock::None, now),
            },
            // Unknown: assume the frame ended now, the early (safe) side for freshness.
            BufferClock::None => now.checked_sub(self.exposure + self.period).unwrap_or(now),
        }
    }

    /// The next good frame of `stream`, waiting at most `timeout` in all.
    pub fn capture(&mut self, stream: &mut dyn RawStream, timeout: Duration) -> Result<Frame, DeviceError> {
        let deadline = Instant::now() + timeout;
        let timed_out = || DeviceError::Timeout { device: self.device.into(), waiting_for: "a frame", timeout };
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Err(timed_out());
            }
            let raw = match stream.next_buffer(left.max(Duration::from_millis(1))) {
                Ok(r) => r,
                Err(e) if e.kind() == std::io::ErrorKind::TimedOut => return Err(timed_out()),
                Err(e) => return Err(self.io_error(e)),
            };
            let now = Instant::now();
            let step = self.tracker.observe(raw.sequence);
            if raw.corrupt {
                self.skipped += 1;
                tracing::warn!(
                    device = self.device,
                    sequence = raw.sequence,
                    "frame marked corrupt by the driver; skipped"
                );
                continue;
            }
            let exposure_start = self.exposure_start(raw.clock, now);
            match to_rgb(self.format, self.width, self.height, self.stride, raw.data) {
                Ok(image) => return Ok(Frame { sequence: step.sequence, exposure_start, image }),
                Err(e) => {
                    // A truncated transfer (MJPEG, usually): the frame is lost, the stream goes on.
                    self.skipped += 1;
                    tracing::warn!(device = self.device, sequence = raw.sequence, error = %e, "frame does not convert; skipped");
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::devices::ErrorKind;
    use std::collections::VecDeque;

    /// One scripted buffer: data, sequence number, stamp, corrupt flag.
    type Scripted = (Vec<u8>, u32, BufferClock, bool);

    /// A driver that hands out scripted buffers, then times out.
    #[derive(Debug, Default)]
    struct Script {
        items: VecDeque<std::io::Result<Scripted>>,
        current: Vec<u8>,
        waits: Vec<Duration>,
    }

    impl RawStream for Script {
        fn next_buffer(&mut self, timeout: Duration) -> std::io::Result<RawFrame<'_>> {
            self.waits.push(timeout);
            match self.items.pop_front() {
                None => Err(std::io::Error::from(std::io::ErrorKind::TimedOut)),
                Some(Err(e)) => Err(e),
                Some(Ok((data, sequence, clock, corrupt))) => {
                    self.current = data;
                    Ok(RawFrame { data: &self.current, sequence, clock, corrupt })
                }
            }
        }
    }

    fn grey(v: u8) -> Vec<u8> {
        vec![v; 4 * 2]
    }

    fn assembler() -> FrameAssembler {
        FrameAssembler::new(
            "camera",
            PixelFormat::Grey,
            (4, 2),
            0,
            Duration::from_millis(10),
            Duration::from_millis(33),
        )
    }

    #[test]
    fn corrupt_and_short_frames_are_skipped_gaps_counted() {
        let mut s = Script::default();
        let now = monotonic_now();
        let soe =
            |ago_ms: u64| BufferClock::Monotonic(now - Duration::from_millis(ago_ms), TimestampSource::StartOfExposure);
        s.items.push_back(Ok((grey(10), 7, soe(50), false)));
        s.items.push_back(Ok((grey(20), 8, soe(40), true)));
        s.items.push_back(Ok((vec![0; 3], 9, soe(30), false)));
        s.items.push_back(Ok((grey(40), 12, soe(20), false)));
        let mut a = assembler();
        let t = Duration::from_secs(1);
        let f = a.capture(&mut s, t).expect("first");
        assert_eq!((f.sequence, f.image.get_pixel(0, 0).0), (0, [10, 10, 10]));
        let f = a.capture(&mut s, t).expect("after two bad ones");
        assert_eq!((f.sequence, f.image.get_pixel(3, 1).0), (5, [40, 40, 40]));
        assert_eq!((a.dropped(), a.skipped()), (2, 2));
        let e = a.capture(&mut s, t).expect_err("nothing left");
        assert_eq!(e.kind(), ErrorKind::Timeout);
        assert!(s.waits.iter().all(|w| *w <= t && !w.is_zero()));
    }

    #[test]
    fn timestamps_order_frames_around_a_change() {
        let a = assembler();
        let now = Instant::now();
        let mono = monotonic_now();
        // Stamped at the end of the frame 5 ms ago: exposure began 5 + 10 + 33 ms ago.
        let eof =
            a.exposure_start(BufferClock::Monotonic(mono - Duration::from_millis(5), TimestampSource::EndOfFrame), now);
        let age = now - eof;
        assert!(age >= Duration::from_millis(48) && age < Duration::from_millis(60), "{age:?}");
        let wall = SystemTime::now().duration_since(SystemTime::UNIX_EPOCH).expect("after 1970");
        let w = a.exposure_start(BufferClock::Wall(wall, TimestampSource::StartOfExposure), now);
        assert!(now - w < Duration::from_millis(20));
        assert_eq!(now - a.exposure_start(BufferClock::None, now), Duration::from_millis(43));
    }

    #[test]
    fn an_unplugged_device_is_disconnected_other_errors_are_io() {
        let mut s = Script::default();
        s.items.push_back(Err(std::io::Error::from_raw_os_error(libc::ENODEV)));
        s.items.push_back(Err(std::io::Error::from_raw_os_error(libc::EINVAL)));
        let mut a = assembler();
        assert_eq!(a.capture(&mut s, Duration::from_secs(1)).expect_err("gone").kind(), ErrorKind::Disconnected);
        let e = a.capture(&mut s, Duration::from_secs(1)).expect_err("io");
        assert!(matches!(e, DeviceError::Io { .. }), "{e}");
        assert_eq!(a.capture(&mut s, Duration::ZERO).expect_err("zero").kind(), ErrorKind::Timeout);
    }
}

//! GigE Vision / USB3 Vision cameras through Aravis (cargo feature `aravis`): selected by vendor,
//! model and serial number (or reached at an IP address), region, pixel format, frame rate, exposure,
//! gain and trigger written as GenICam features and read back, a pool of stream buffers, frames with
//! the camera's frame id as sequence and a start-of-exposure time, dropped frames counted from the
//! frame ids and the stream statistics. A camera that stops answering is
//! [`DeviceError::Disconnected`]; the next capture reconnects (capped backoff) and reapplies every
//! setting.
//!
//! Trigger modes and the fresh-frame rule are described in
//! [`genicam_features`](super::genicam_features).
//!
//! Start of exposure: a GigE Vision frame's device timestamp counts device ticks from an unknown
//! origin, so the driver uses the host time its first packet arrived (Aravis' system timestamp, wall
//! clock) moved back by the exposure time and one frame period (the readout bound), the early, safe
//! side; with a software trigger it is also never earlier than the trigger itself.

use std::time::{Duration, Instant};

use super::arv::{self, ArvCamera, ArvError, ArvStream, FilledBuffer, StreamStatistics, BUFFER_STATUS_SUCCESS};
use super::genicam_features::{reads_back, trigger_writes, TriggerMode, DELAY_FEATURES};
use super::stream::TimestampSource;
use super::streaming::{BufferClock, FrameAssembler, RawFrame, RawStream};
use crate::config::GenicamCameraConfig;
use crate::devices::DeviceError;

const NAME: &str = "camera";

fn invalid(field: &'static str, problem: String) -> DeviceError {
    DeviceError::InvalidConfig { device: NAME.into(), field, problem }
}

fn disconnected(detail: String) -> DeviceError {
    DeviceError::Disconnected {
        device: NAME.into(),
        source: Some(std::io::Error::new(std::io::ErrorKind::NotConnected, detail)),
    }
}

/// A setting the camera did not take: an invalid configuration, unless the camera could not be
/// reached while writing it (a timeout on a busy link), which is a disconnect to retry, not a
/// setting to fix.
fn refused(field: &'static str, problem: String, e: &ArvError) -> DeviceError {
    if e.is_unreachable() {
        disconnected(format!("{field}: {problem}"))
    } else {
        invalid(field, problem)
    }
}

/// An Aravis failure while doing `what`: unreachable devices are disconnected, the rest protocol
/// errors (a feature the camera refuses).
fn arv_error(what: &str, e: ArvError) -> DeviceError {
    if e.is_unreachable() {
        disconnected(format!("{what}: {e}"))
    } else {
        DeviceError::Protocol { device: NAME.into(), detail: format!("{what}: {e}") }
    }
}

/// What the camera reported after the settings were written: every value read back.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct GenicamSettings {
    /// The id Aravis opened.
    pub device_id: String,
    /// `DeviceVendorName`.
    pub vendor: String,
    /// `DeviceModelName`.
    pub model: String,
    /// `DeviceSerialNumber`.
    pub serial: String,
    /// Region width, pixels.
    pub width: u32,
    /// Region height, pixels.
    pub height: u32,
    /// `PixelFormat`.
    pub pixel_format: String,
    /// Exposure time, microseconds.
    pub exposure_us: f64,
    /// Gain.
    pub gain: f64,
    /// Frame rate, frames per second.
    pub fps: f64,
    /// `TriggerMode` (`Off` / `On`).
    pub trigger_mode: String,
    /// `TriggerSource`, when the trigger is on.
    pub trigger_source: Option<String>,
    /// `TriggerActivation`, when the camera has it and a line triggers.
    pub trigger_activation: Option<String>,
    /// Trigger delay, microseconds, when set.
    pub trigger_delay_us: Option<f64>,
}

/// A connected camera: its stream (dropped first) and the camera.
#[derive(Debug)]
struct Connection {
    stream: ArvStream,
    held: Option<FilledBuffer>,
    camera: ArvCamera,
    settings: GenicamSettings,
    /// Complete frames received while checking the stream after `AcquisitionStart`.
    primed: u64,
}

impl Drop for Connection {
    fn drop(&mut self) {
        if let Some(b) = self.held.take() {
            self.stream.push(b);
        }
        if let Err(e) = self.camera.stop() {
            tracing::debug!(error = %e, "AcquisitionStop");
        }
    }
}

/// The stream's buffers as a [`RawStream`]: the buffer handed out last is queued again before the
/// next one is taken.
struct Pool<'a> {
    stream: &'a ArvStream,
    held: &'a mut Option<FilledBuffer>,
}

impl RawStream for Pool<'_> {
    fn next_buffer(&mut self, timeout: Duration) -> std::io::Result<RawFrame<'_>> {
        if let Some(b) = self.held.take() {
            self.stream.push(b);
        }
        let Some(b) = self.stream.pop(timeout) else {
            return Err(std::io::Error::from(std::io::ErrorKind::TimedOut));
        };
        let b: &FilledBuffer = self.held.insert(b);
        Ok(RawFrame {
            data: b.data(),
            sequence: b.frame_id() as u32,
            clock: BufferClock::Wall(b.system_timestamp(), TimestampSource::EndOfFrame),
            corrupt: b.status() != BUFFER_STATUS_SUCCESS,
        })
    }
}

/// A GenICam camera streaming through Aravis.
#[derive(Debug)]
pub struct GenicamCamera {
    config: GenicamCameraConfig,
    connection: Option<Connection>,
    frames: FrameAssembler,
    /// Software triggers sent.
    triggers: u64,
    /// Frames delivered by `capture`.
    delivered: u64,
    /// Queued frames thrown away before a software trigger.
    drained: u64,
    /// Statistics of the streams of earlier connections.
    earlier: StreamStatistics,
    /// Frames of earlier connections received while checking their streams.
    primed_earlier: u64,
    reconnects: u64,
    backoff: Duration,
    next_attempt: Option<Instant>,
}

const FIRST_BACKOFF: Duration = Duration::from_millis(100);
const MAX_BACKOFF: Duration = Duration::from_secs(2);

/// The Aravis id of the one discovered device matching the config's vendor / model / serial.
fn find_device(config: &GenicamCameraConfig) -> Result<String, DeviceError> {
    let all = arv::list_devices();
    let matches = |want: &Option<String>, got: &str| want.as_deref().is_none_or(|w| w == got);
    let found: Vec<&arv::DeviceInfo> = all
        .iter()
        .filter(|d| {
            matches(&config.vendor, &d.vendor) && matches(&config.model, &d.model) && matches(&config.serial, &d.serial)
        })
        .collect();
    match found.as_slice() {
        [one] => Ok(one.id.clone()),
        [] => Err(disconnected(format!(
            "no GenICam camera with vendor {} model {} serial {} (found: {})",
            config.vendor.as_deref().unwrap_or("(any)"),
            config.model.as_deref().unwrap_or("(any)"),
            config.serial.as_deref().unwrap_or("(any)"),
            if all.is_empty() {
                "none".to_owned()
            } else {
                all.iter().map(|d| d.id.as_str()).collect::<Vec<_>>().join(", ")
            }
        ))),
        many => Err(invalid(
            "serial",
            format!(
                "{} cameras match: {}",
                many.len(),
                many.iter().map(|d| d.id.as_str()).collect::<Vec<_>>().join(", ")
            ),
        )),
    }
}

fn connect(config: &GenicamCameraConfig) -> Result<Connection, DeviceError> {
    let id = match &config.address {
        Some(a) => a.clone(),
        None => find_device(config)?,
    };
    let camera = ArvCamera::open(Some(&id)).map_err(|e| {
        if e.is_unreachable() {
            disconnected(format!("opening `{id}`: {e}"))
        } else {
            DeviceError::Protocol { device: NAME.into(), detail: format!("opening `{id}`: {e}") }
        }
    })?;
    let (vendor, model, serial) = camera.identity().map_err(|e| arv_error("reading the identity", e))?;
    for (field, want, got) in
        [("vendor", &config.vendor, &vendor), ("model", &config.model, &model), ("serial", &config.serial, &serial)]
    {
        if want.as_deref().is_some_and(|w| w != got) {
            return Err(invalid(
                field,
                format!("`{id}` reports {field} `{got}`, not `{}`", want.as_deref().unwrap_or("")),
            ));
        }
    }

    let (w, h) = (config.width as i32, config.height as i32);
    camera.set_region(0, 0, w, h).map_err(|e| refused("width", format!("region {w}x{h}: {e}"), &e))?;
    let (_, _, gw, gh) = camera.region().map_err(|e| arv_error("reading the region", e))?;
    if (gw, gh) != (w, h) {
        return Err(invalid("width", format!("set the region to {w}x{h}, the camera reads back {gw}x{gh}")));
    }
    let format = config.pixel_format.genicam();
    camera.set_pixel_format(format).map_err(|e| refused("pixel_format", format!("{format}: {e}"), &e))?;
    let got = camera.pixel_format().map_err(|e| arv_error("reading PixelFormat", e))?;
    if got != format {
        return Err(invalid("pixel_format", format!("set {format}, the camera reads back {got}")));
    }
    camera.set_continuous().map_err(|e| arv_error("AcquisitionMode", e))?;
    // The frame rate first: Aravis turns the frame-start trigger off to set it on some cameras.
    if let Some(fps) = config.fps {
        camera.set_frame_rate(fps).map_err(|e| refused("fps", format!("{fps}: {e}"), &e))?;
        let got = camera.frame_rate().map_err(|e| arv_error("reading the frame rate", e))?;
        if !reads_back(fps, got, 0.01) {
            return Err(invalid("fps", format!("set {fps} frames/s, the camera reads back {got}")));
        }
    }
    if let Some(us) = config.exposure_us {
        camera.set_exposure_us(us).map_err(|e| refused("exposure_us", format!("{us}: {e}"), &e))?;
        let got = camera.exposure_us().map_err(|e| arv_error("reading the exposure", e))?;
        if !reads_back(us, got, 1.0) {
            return Err(invalid("exposure_us", format!("set {us} µs, the camera reads back {got}")));
        }
    }
    if let Some(g) = config.gain {
        camera.set_gain(g).map_err(|e| refused("gain", format!("{g}: {e}"), &e))?;
        let got = camera.gain().map_err(|e| arv_error("reading the gain", e))?;
        if !reads_back(g, got, 0.01) {
            return Err(invalid("gain", format!("set {g}, the camera reads back {got}")));
        }
    }
    for write in trigger_writes(config.trigger, &config.trigger_line, config.trigger_activation) {
        let available = camera.has_feature(write.feature).map_err(|e| arv_error(write.feature, e))?;
        if !available {
            if write.optional {
                continue;
            }
            return Err(invalid("trigger", format!("the camera has no {} feature", write.feature)));
        }
        camera
            .set_string(write.feature, &write.value)
            .map_err(|e| refused("trigger", format!("{} = {}: {e}", write.feature, write.value), &e))?;
        let got = camera.string(write.feature).map_err(|e| arv_error(write.feature, e))?;
        if got != write.value {
            return Err(invalid(
                "trigger",
                format!("set {} = {}, the camera reads back {got}", write.feature, write.value),
            ));
        }
    }
    let mut trigger_delay_us = None;
    if let Some(d) = config.trigger_delay_us {
        let mut feature = None;
        for f in DELAY_FEATURES {
            if camera.has_feature(f).map_err(|e| arv_error(f, e))? {
                feature = Some(f);
                break;
            }
        }
        let f = feature.ok_or_else(|| {
            invalid("trigger_delay_us", format!("the camera has none of the features {}", DELAY_FEATURES.join(", ")))
        })?;
        camera.set_float(f, d).map_err(|e| refused("trigger_delay_us", format!("{f} = {d}: {e}"), &e))?;
        let got = camera.float(f).map_err(|e| arv_error(f, e))?;
        if !reads_back(d, got, 1.0) {
            return Err(invalid("trigger_delay_us", format!("set {f} = {d}, the camera reads back {got}")));
        }
        trigger_delay_us = Some(got);
    }

    let read_string = |f: &str| camera.has_feature(f).ok().filter(|&a| a).and_then(|_| camera.string(f).ok());
    let trigger_mode = read_string("TriggerMode").unwrap_or_else(|| "Off".into());
    let settings = GenicamSettings {
        device_id: id.clone(),
        vendor,
        model,
        serial,
        width: gw as u32,
        height: gh as u32,
        pixel_format: got,
        exposure_us: camera.exposure_us().map_err(|e| arv_error("reading the exposure", e))?,
        gain: camera.gain().map_err(|e| arv_error("reading the gain", e))?,
        fps: camera.frame_rate().map_err(|e| arv_error("reading the frame rate", e))?,
        trigger_source: if trigger_mode == "On" { read_string("TriggerSource") } else { None },
        trigger_activation: if config.trigger == TriggerMode::Line { read_string("TriggerActivation") } else { None },
        trigger_mode,
        trigger_delay_us,
    };
    let payload = camera.payload().map_err(|e| arv_error("reading PayloadSize", e))?;
    let stream = camera.create_stream(config.buffers, payload).map_err(|e| arv_error("creating the stream", e))?;
    camera.start().map_err(|e| arv_error("AcquisitionStart", e))?;
    let primed = prime(&camera, &stream, config.trigger, &settings)?;
    tracing::info!(
        settings = ?settings,
        payload,
        buffers = config.buffers,
        prime_tries = primed.tries,
        "GenICam camera streaming"
    );
    Ok(Connection { stream, held: None, camera, settings, primed: primed.frames })
}

/// What [`prime`] took.
#[derive(Debug, Clone, Copy)]
struct Primed {
    /// Waits for a frame (software triggers sent, with a software trigger).
    tries: u32,
    /// Complete frames it received and handed back unread.
    frames: u64,
}

/// How long [`prime`] waits for the first complete frame after `AcquisitionStart`.
const PRIME_TIMEOUT: Duration = Duration::from_secs(3);

/// Wait for one complete frame after `AcquisitionStart`, so that a connected camera is one whose
/// frames reach this host: a camera that answers its control channel but whose stream packets are
/// dropped (a firewall, a packet size the network does not carry) is refused here, not on the
/// first capture of a scan. With a software trigger the trigger is sent again after each frame's
/// worth of waiting: a camera may ignore a trigger that arrives before its acquisition engine is
/// running, and Aravis' fake GigE camera loses the frame of a trigger sent within a few
/// milliseconds of `AcquisitionStart`. With a line trigger nothing can make a frame, so nothing is
/// checked. The frames seen here are handed back to the stream unread.
fn prime(
    camera: &ArvCamera,
    stream: &ArvStream,
    trigger: TriggerMode,
    settings: &GenicamSettings,
) -> Result<Primed, DeviceError> {
    if trigger == TriggerMode::Line {
        return Ok(Primed { tries: 0, frames: 0 });
    }
    let period = if settings.fps > 0.0 { 1.0 / settings.fps } else { 0.1 };
    // One frame's worth of waiting: the exposure, two frame periods and the transfer.
    let step = Duration::from_secs_f64(settings.exposure_us.max(0.0) / 1e6 + 2.0 * period + 0.1);
    let deadline = Instant::now() + PRIME_TIMEOUT;
    let mut tries = 0;
    while Instant::now() < deadline {
        tries += 1;
        if trigger == TriggerMode::Software {
            camera.execute("TriggerSoftware").map_err(|e| arv_error("TriggerSoftware", e))?;
        }
        let wait_until = (Instant::now() + step).min(deadline);
        while let Some(b) = stream.pop(wait_until.saturating_duration_since(Instant::now())) {
            let complete = b.status() == BUFFER_STATUS_SUCCESS;
            stream.push(b);
            if complete {
                let mut frames = 1;
                if trigger == TriggerMode::Software && tries > 1 {
                    // An earlier trigger's frame may still be on its way: let it land here (for
                    // one more step at most), not after a capture's drain, where it would pass
                    // for a fresh one. In free run frames never stop coming, and a capture
                    // drops the stale ones by their timestamps, so there is nothing to wait for.
                    let until = Instant::now() + step;
                    while let Some(late) = stream.pop(until.saturating_duration_since(Instant::now())) {
                        frames += u64::from(late.status() == BUFFER_STATUS_SUCCESS);
                        stream.push(late);
                    }
                }
                return Ok(Primed { tries, frames });
            }
        }
    }
    let s = stream.statistics();
    Err(DeviceError::Protocol {
        device: NAME.into(),
        detail: format!(
            "no complete frame reached this host within {PRIME_TIMEOUT:?} of AcquisitionStart \
             ({tries} tries; stream: {} completed, {} failed, {} lost for want of a buffer): \
             is a firewall dropping the camera's UDP stream, or is the packet size larger than \
             the network carries?",
            s.completed, s.failures, s.underruns
        ),
    })
}

fn assembler(config: &GenicamCameraConfig, settings: &GenicamSettings) -> FrameAssembler {
    let exposure = Duration::from_secs_f64(settings.exposure_us.max(0.0) / 1e6);
    let period =
        if settings.fps > 0.0 { Duration::from_secs_f64(1.0 / settings.fps) } else { Duration::from_millis(100) };
    FrameAssembler::new(NAME, config.pixel_format.layout(), (config.width, config.height), 0, exposure, period)
}

impl GenicamCamera {
    /// Find the camera, write and read back every setting, and start streaming.
    pub fn open(config: &GenicamCameraConfig) -> Result<Self, DeviceError> {
        let connection = connect(config)?;
        let frames = assembler(config, &connection.settings);
        Ok(GenicamCamera {
            config: config.clone(),
            connection: Some(connection),
            frames,
            triggers: 0,
            delivered: 0,
            drained: 0,
            earlier: StreamStatistics::default(),
            primed_earlier: 0,
            reconnects: 0,
            backoff: FIRST_BACKOFF,
            next_attempt: None,
        })
    }

    /// The settings as the camera read them back at the last (re)connection; `None` while
    /// disconnected.
    pub fn settings(&self) -> Option<&GenicamSettings> {
        self.connection.as_ref().map(|c| &c.settings)
    }

    /// Software triggers sent so far.
    pub fn triggers(&self) -> u64 {
        self.triggers
    }

    /// Frames delivered by `capture` so far.
    pub fn delivered(&self) -> u64 {
        self.delivered
    }

    /// Frames lost so far: gaps in the camera's frame ids.
    pub fn dropped_frames(&self) -> u64 {
        self.frames.dropped()
    }

    /// Times the camera was reconnected after a disconnect.
    pub fn reconnects(&self) -> u64 {
        self.reconnects
    }

    /// Complete frames received, over every connection, while checking that the stream works
    /// right after `AcquisitionStart` (never delivered; counted in [`Self::statistics`]'
    /// `completed`).
    pub fn primed_frames(&self) -> u64 {
        self.primed_earlier + self.connection.as_ref().map_or(0, |c| c.primed)
    }

    /// Stream statistics summed over every connection: completed buffers, failed ones (missing
    /// packets, timeouts) and underruns (frames lost because every buffer was in use).
    pub fn statistics(&self) -> StreamStatistics {
        let now = self.connection.as_ref().map(|c| c.stream.statistics()).unwrap_or_default();
        StreamStatistics {
            completed: self.earlier.completed + now.completed,
            failures: self.earlier.failures + now.failures,
            underruns: self.earlier.underruns + now.underruns,
        }
    }

    fn drop_connection(&mut self, why: &DeviceError) {
        if let Some(c) = self.connection.take() {
            let s = c.stream.statistics();
            self.earlier.completed += s.completed;
            self.earlier.failures += s.failures;
            self.earlier.underruns += s.underruns;
            self.primed_earlier += c.primed;
            tracing::warn!(error = %why, "GenICam camera lost");
        }
        self.next_attempt = Some(Instant::now() + self.backoff);
    }

    /// Reconnect if disconnected, waiting for the backoff when it ends before `deadline`.
    fn ensure_connected(&mut self, deadline: Instant) -> Result<(), DeviceError> {
        if self.connection.is_some() {
            return Ok(());
        }
        if let Some(at) = self.next_attempt {
            let now = Instant::now();
            if at > deadline {
                return Err(disconnected("waiting to reconnect".into()));
            }
            if at > now {
                std::thread::sleep(at - now);
            }
        }
        match connect(&self.config) {
            Ok(c) => {
                self.frames = assembler(&self.config, &c.settings);
                self.connection = Some(c);
                self.reconnects += 1;
                self.backoff = FIRST_BACKOFF;
                self.next_attempt = None;
                tracing::info!(reconnects = self.reconnects, "GenICam camera reconnected");
                Ok(())
            }
            Err(e) => {
                self.backoff = (self.backoff * 2).min(MAX_BACKOFF);
                self.next_attempt = Some(Instant::now() + self.backoff);
                Err(e)
            }
        }
    }

    fn capture_connected(&mut self, deadline: Instant) -> Result<super::Frame, DeviceError> {
        let Some(c) = self.connection.as_mut() else { return Err(disconnected("not connected".into())) };
        let mut triggered_at = None;
        if self.config.trigger == TriggerMode::Software {
            // Frames still queued were exposed before the caller's change: requeue them unread.
            if let Some(b) = c.held.take() {
                c.stream.push(b);
            }
            while let Some(b) = c.stream.try_pop() {
                self.drained += 1;
                c.stream.push(b);
            }
            let at = Instant::now();
            if let Err(e) = c.camera.execute("TriggerSoftware") {
                // A refused command on a camera that still answers is a protocol error; one that
                // does not answer a read either is gone.
                return Err(match c.camera.integer("Width") {
                    Ok(_) => arv_error("TriggerSoftware", e),
                    Err(probe) => disconnected(format!("TriggerSoftware: {e}; the camera does not answer: {probe}")),
                });
            }
            self.triggers += 1;
            triggered_at = Some(at);
        }
        let left = deadline.saturating_duration_since(Instant::now()).max(Duration::from_millis(1));
        let mut pool = Pool { stream: &c.stream, held: &mut c.held };
        let result = self.frames.capture(&mut pool, left);
        if let Some(b) = c.held.take() {
            c.stream.push(b);
        }
        let mut frame = match result {
            Ok(f) => f,
            Err(e @ DeviceError::Timeout { .. }) => {
                // No frame: is the camera still there? A control read answers within Aravis' own
                // GVCP timeout and retries.
                return Err(match c.camera.integer("Width") {
                    Ok(_) => e,
                    Err(probe) => {
                        disconnected(format!("no frame within {left:?} and the camera does not answer: {probe}"))
                    }
                });
            }
            Err(e) => return Err(e),
        };
        if let Some(at) = triggered_at {
            frame.exposure_start = frame.exposure_start.max(at);
        }
        self.delivered += 1;
        Ok(frame)
    }
}

impl super::Camera for GenicamCamera {
    fn info(&self) -> super::CameraInfo {
        super::CameraInfo { width: self.config.width, height: self.config.height }
    }

    fn capture(&mut self, timeout: Duration) -> Result<super::Frame, DeviceError> {
        let deadline = Instant::now() + timeout;
        self.ensure_connected(deadline)?;
        match self.capture_connected(deadline) {
            Ok(f) => Ok(f),
            Err(e) => {
                if e.kind() == crate::devices::ErrorKind::Disconnected {
                    self.drop_connection(&e);
                }
                Err(e)
            }
        }
    }
}

impl Drop for GenicamCamera {
    fn drop(&mut self) {
        let s = self.statistics();
        tracing::info!(
            triggers = self.triggers,
            delivered = self.delivered,
            drained = self.drained,
            primed = self.primed_frames(),
            dropped = self.frames.dropped(),
            skipped = self.frames.skipped(),
            completed = s.completed,
            failures = s.failures,
            underruns = s.underruns,
            reconnects = self.reconnects,
            "GenICam camera closed"
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::devices::ErrorKind;

    /// A setting the camera refuses is a configuration to fix; one it could not be reached for
    /// (`ArvDeviceError` timeout) is a disconnect the daemon retries.
    #[test]
    fn a_setting_lost_to_a_timeout_is_retried_not_failed() {
        let timeout = ArvError { device_domain: true, code: 5, message: "timeout".into() };
        let e = refused("width", "region 640x480: timeout".into(), &timeout);
        assert_eq!(e.kind(), ErrorKind::Disconnected, "{e}");
        let refusal = ArvError { device_domain: false, code: 3, message: "out of range".into() };
        let e = refused("width", "region 99999x480: out of range".into(), &refusal);
        assert_eq!(e.kind(), ErrorKind::InvalidConfig, "{e}");
        assert!(e.to_string().contains("width"), "{e}");
    }
}

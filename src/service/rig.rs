//! The device thread: owns the rig's drivers, reconnects them with capped backoff when they are
//! missing, runs scans, captures preview frames and parks the hardware. Async code talks to it
//! through a cloneable [`RigHandle`] (bounded channel, command + oneshot reply); the device state is
//! published in a shared [`RigStatus`] that readers never block on the thread for.

use std::path::PathBuf;
use std::sync::mpsc::{self, Receiver, RecvTimeoutError, SyncSender, TrySendError};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use serde::Serialize;
use tokio::sync::oneshot;

use crate::acquisition::{self, CancelToken};
use crate::config::RigConfig;
use crate::devices::serial::LinkState;
use crate::devices::{build_rig, DeviceError, ErrorKind, Rig};
use crate::scan::{self, Report, ScanError, ScanEvent};

use super::control::{self, ControlCommand, ControlError, ControlState};
use super::metrics::Metrics;

/// The connection state of a device.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum DeviceState {
    /// Open and answering.
    Connected,
    /// Gone; a reconnection attempt is scheduled.
    Disconnected,
    /// A reconnection attempt is under way.
    Reconnecting,
    /// Cannot work with this configuration; not retried until the config is reloaded.
    Failed,
}

/// One device's published status.
#[derive(Debug, Clone, Serialize)]
pub struct DeviceStatus {
    /// Config section name (`turntable`, `camera`, ...).
    pub name: String,
    /// Driver kind from the config (`sim`, ...).
    pub kind: String,
    /// State.
    pub state: DeviceState,
    /// The last error, if any.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub last_error: Option<String>,
    /// Reconnections so far.
    pub reconnects: u64,
}

/// Every device's status, shared between the device thread and readers.
pub type RigStatus = Arc<Mutex<Vec<DeviceStatus>>>;

/// Why a command to the device thread failed.
#[derive(Debug, thiserror::Error)]
pub enum RigError {
    /// The thread is doing something else (a scan) and its queue is full.
    #[error("the rig is busy")]
    Busy,
    /// The thread has stopped.
    #[error("the device thread has stopped")]
    Stopped,
    /// The devices are not connected.
    #[error("the rig is not connected")]
    NotConnected,
    /// A device failed.
    #[error("device error")]
    Device(#[source] DeviceError),
    /// A preview frame could not be encoded.
    #[error("cannot encode the preview frame")]
    Encode(#[source] image::ImageError),
    /// The scan failed.
    #[error("scan failed")]
    Scan(#[source] ScanError),
    /// A preview capture that failed, shared by every request it answered.
    #[error(transparent)]
    Shared(Arc<RigError>),
    /// A manual control command failed.
    #[error(transparent)]
    Control(ControlError),
    /// No device of that name in the rig file.
    #[error("the rig has no device `{0}`")]
    UnknownDevice(String),
}

impl RigError {
    /// The error itself, looking through [`RigError::Shared`].
    pub fn inner(&self) -> &RigError {
        match self {
            RigError::Shared(e) => e.inner(),
            e => e,
        }
    }
}

/// One preview frame as captured, before any encoding.
#[derive(Debug)]
pub struct PreviewFrame {
    /// The camera's frame counter.
    pub sequence: u64,
    /// The image, 8-bit RGB.
    pub image: image::RgbImage,
}

/// What a preview capture gives every request waiting for it.
type PreviewReply = Result<Arc<PreviewFrame>, Arc<RigError>>;

/// What the device thread publishes about the camera, for `GET /api/v1/camera`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct CameraSize {
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
}

/// The preview requests waiting for the next capture: `None` when no capture is queued.
/// Concurrent previews share one capture, so at most one preview command is ever in the device
/// thread's queue and previews can never fill it (a scan's commands always find room).
type PreviewWaiters = Arc<Mutex<Option<Vec<oneshot::Sender<PreviewReply>>>>>;

/// A scan for the device thread to run.
pub struct ScanJob {
    /// Output directory.
    pub out: PathBuf,
    /// Resume from the frames in `out`.
    pub resume: bool,
    /// The configuration to scan with (plan already adjusted by the request).
    pub config: Arc<RigConfig>,
    /// Stops the scan at the next step boundary.
    pub cancel: CancelToken,
    /// Progress sink, called on the device thread.
    pub events: Box<dyn FnMut(ScanEvent) + Send>,
    /// Live previews of the estimate among the events.
    pub live: Option<scan::preview::LiveSpec>,
}

impl std::fmt::Debug for ScanJob {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ScanJob").field("out", &self.out).field("resume", &self.resume).finish_non_exhaustive()
    }
}

enum Command {
    Preview,
    Scan(ScanJob, oneshot::Sender<Result<Report, RigError>>),
    Park(oneshot::Sender<Result<(), RigError>>),
    Reload(Arc<RigConfig>),
    Control(ControlCommand, oneshot::Sender<Result<ControlState, RigError>>),
    Reconnect(String, oneshot::Sender<Result<(), RigError>>),
}

/// A cloneable handle to the device thread.
#[derive(Debug, Clone)]
pub struct RigHandle {
    tx: SyncSender<Command>,
    status: RigStatus,
    previews: PreviewWaiters,
    shared: Arc<Shared>,
}

/// What the device thread publishes besides the device status, read without asking it.
#[derive(Debug)]
struct Shared {
    /// The manual control state (see [`ControlState`]).
    control: Mutex<ControlState>,
    /// The camera's image size once it has been opened.
    camera: Mutex<Option<CameraSize>>,
    /// Bumped whenever any device's status changes (for the `devices` event).
    devices_changed: tokio::sync::watch::Sender<u64>,
}

impl std::fmt::Debug for Command {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Command::Preview => "Preview",
            Command::Scan(..) => "Scan",
            Command::Park(_) => "Park",
            Command::Reload(_) => "Reload",
            Command::Control(..) => "Control",
            Command::Reconnect(..) => "Reconnect",
        })
    }
}

/// Backoff between reconnection attempts: doubles from `RECONNECT_MIN` up to `RECONNECT_MAX`.
const RECONNECT_MIN: Duration = Duration::from_millis(250);
const RECONNECT_MAX: Duration = Duration::from_secs(8);

impl RigHandle {
    /// Start the device thread for `config`. It opens the devices at once and keeps retrying.
    /// The thread parks the hardware and exits when every handle is dropped.
    pub fn spawn(
        config: Arc<RigConfig>,
        metrics: Arc<Metrics>,
    ) -> std::io::Result<(RigHandle, std::thread::JoinHandle<()>)> {
        let (tx, rx) = mpsc::sync_channel(8);
        let status: RigStatus = Arc::new(Mutex::new(device_list(&config, DeviceState::Reconnecting, None)));
        let thread_status = status.clone();
        let previews: PreviewWaiters = Arc::default();
        let thread_previews = previews.clone();
        let shared = Arc::new(Shared {
            control: Mutex::default(),
            camera: Mutex::default(),
            devices_changed: tokio::sync::watch::Sender::new(0),
        });
        let thread_shared = shared.clone();
        let join = std::thread::Builder::new().name("devices".into()).spawn(move || {
            DeviceThread {
                config,
                rig: None,
                status: thread_status,
                previews: thread_previews,
                shared: thread_shared,
                metrics,
                ever_connected: false,
                serial_ever_connected: false,
            }
            .run(rx)
        })?;
        Ok((RigHandle { tx, status, previews, shared }, join))
    }

    /// A copy of every device's status.
    pub fn status(&self) -> Vec<DeviceStatus> {
        self.status.lock().map(|s| s.clone()).unwrap_or_default()
    }

    fn send(&self, cmd: Command) -> Result<(), RigError> {
        self.tx.try_send(cmd).map_err(|e| match e {
            TrySendError::Full(_) => RigError::Busy,
            TrySendError::Disconnected(_) => RigError::Stopped,
        })
    }

    /// Capture one frame and return it as PNG. Requests made while a capture is queued share it.
    pub async fn preview(&self) -> Result<Vec<u8>, RigError> {
        let frame = self.capture().await?;
        let encoded = tokio::task::spawn_blocking(move || {
            let mut png = Vec::new();
            frame
                .image
                .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
                .map(|()| png)
                .map_err(RigError::Encode)
        });
        encoded.await.map_err(|_| RigError::Stopped)?
    }

    /// Capture one preview frame. Requests made while a capture is queued share it (one capture
    /// for any number of waiting callers: PNG previews and every MJPEG viewer alike).
    pub async fn capture(&self) -> Result<Arc<PreviewFrame>, RigError> {
        let (tx, rx) = oneshot::channel();
        {
            let mut waiters = self.previews.lock().unwrap_or_else(|p| p.into_inner());
            match waiters.as_mut() {
                Some(list) => list.push(tx),
                None => {
                    *waiters = Some(vec![tx]);
                    if let Err(e) = self.send(Command::Preview) {
                        *waiters = None;
                        return Err(e);
                    }
                }
            }
        }
        match rx.await.map_err(|_| RigError::Stopped)? {
            Ok(frame) => Ok(frame),
            Err(e) => Err(RigError::Shared(e)),
        }
    }

    /// Run one manual control command on the device thread; answers the state it leaves.
    pub async fn control(&self, cmd: ControlCommand) -> Result<ControlState, RigError> {
        let (tx, rx) = oneshot::channel();
        self.send(Command::Control(cmd, tx))?;
        rx.await.map_err(|_| RigError::Stopped)?
    }

    /// The manual control state as last published (never waits for the device thread).
    pub fn control_state(&self) -> ControlState {
        self.shared.control.lock().map(|c| c.clone()).unwrap_or_default()
    }

    /// The camera's image size, once it has been opened.
    pub fn camera_size(&self) -> Option<CameraSize> {
        self.shared.camera.lock().ok().and_then(|c| *c)
    }

    /// Close the rig and open it again now. The devices are opened together (one rig file, one
    /// simulated world, one serial board for table and lights), so reconnecting one reopens all;
    /// `name` must be a device of the rig file. Resolves once the attempt is made; a failed
    /// attempt leaves the device `disconnected` and retried with backoff as usual.
    pub async fn reconnect(&self, name: &str) -> Result<(), RigError> {
        if !self.status().iter().any(|d| d.name == name) {
            return Err(RigError::UnknownDevice(name.to_owned()));
        }
        let (tx, rx) = oneshot::channel();
        self.send(Command::Reconnect(name.to_owned(), tx))?;
        rx.await.map_err(|_| RigError::Stopped)?
    }

    /// A receiver that changes whenever any device's status changes.
    pub fn subscribe_devices(&self) -> tokio::sync::watch::Receiver<u64> {
        self.shared.devices_changed.subscribe()
    }

    /// Run a scan; resolves when it has finished.
    pub async fn scan(&self, job: ScanJob) -> Result<Report, RigError> {
        let (tx, rx) = oneshot::channel();
        self.send(Command::Scan(job, tx))?;
        rx.await.map_err(|_| RigError::Stopped)?
    }

    /// Lights and lasers off, projector blank, turntable parked.
    pub async fn park(&self) -> Result<(), RigError> {
        let (tx, rx) = oneshot::channel();
        self.send(Command::Park(tx))?;
        rx.await.map_err(|_| RigError::Stopped)?
    }

    /// Use a new configuration: the devices are closed and opened again from it.
    pub fn reload(&self, config: Arc<RigConfig>) -> Result<(), RigError> {
        self.send(Command::Reload(config))
    }
}

fn device_list(config: &RigConfig, state: DeviceState, error: Option<String>) -> Vec<DeviceStatus> {
    let mut names = vec![("turntable", kind_of(&config.turntable)), ("camera", kind_of(&config.camera))];
    if let Some(l) = &config.lights {
        names.push(("lights", kind_of(&l.kind)));
    }
    if let Some(p) = &config.projector {
        names.push(("projector", kind_of(p)));
    }
    if let Some(d) = &config.depth_camera {
        names.push(("depth_camera", kind_of(d)));
    }
    names
        .into_iter()
        .map(|(name, kind)| DeviceStatus {
            name: name.to_owned(),
            kind,
            state,
            last_error: error.clone(),
            reconnects: 0,
        })
        .collect()
}

/// The driver kind of a config section, from its variant name (`Sim(..)` -> `sim`), so that new
/// driver kinds need no change here.
fn kind_of(section: &dyn std::fmt::Debug) -> String {
    let text = format!("{section:?}");
    text.split(|c: char| !c.is_ascii_alphanumeric()).next().unwrap_or("").to_ascii_lowercase()
}

struct DeviceThread {
    config: Arc<RigConfig>,
    rig: Option<Rig>,
    status: RigStatus,
    previews: PreviewWaiters,
    shared: Arc<Shared>,
    metrics: Arc<Metrics>,
    ever_connected: bool,
    /// The serial board has answered at least once since the rig was built.
    serial_ever_connected: bool,
}

/// The device a [`DeviceError`] is about (its config section name).
fn device_of(e: &DeviceError) -> &str {
    match e {
        DeviceError::Disconnected { device, .. }
        | DeviceError::Timeout { device, .. }
        | DeviceError::Busy { device, .. }
        | DeviceError::Protocol { device, .. }
        | DeviceError::InvalidConfig { device, .. }
        | DeviceError::Unsupported { device, .. }
        | DeviceError::Hardware { device, .. }
        | DeviceError::Io { device, .. } => device,
    }
}

/// Names of the devices behind the serial board: those whose driver kind is `serial`.
fn is_serial(d: &DeviceStatus) -> bool {
    d.kind == "serial"
}

impl DeviceThread {
    fn run(mut self, rx: Receiver<Command>) {
        let span = tracing::info_span!("devices", rig = %self.config.rig.name);
        let _enter = span.enter();
        let mut backoff = RECONNECT_MIN;
        loop {
            if self.rig.is_none() {
                if self.connect() {
                    backoff = RECONNECT_MIN;
                } else {
                    backoff = (backoff * 2).min(RECONNECT_MAX);
                }
            }
            // With the rig open, a lost serial board is reconnected on its own (capped) backoff
            // while the other devices stay in use.
            let serial_wait = if self.rig.is_some() { self.poll_serial() } else { None };
            let wait = if self.rig.is_some() || self.failed() {
                serial_wait.unwrap_or(Duration::from_secs(3600))
            } else {
                backoff
            };
            match rx.recv_timeout(wait) {
                Ok(cmd) => self.handle(cmd),
                Err(RecvTimeoutError::Timeout) => {}
                Err(RecvTimeoutError::Disconnected) => break,
            }
        }
        if let Some(rig) = self.rig.as_mut() {
            match acquisition::park(rig, &self.config.scan) {
                Ok(()) => tracing::info!("rig parked"),
                Err(e) => tracing::error!(error = %e, "parking on shutdown failed"),
            }
        }
        tracing::info!("device thread stopped");
    }

    fn failed(&self) -> bool {
        self.status.lock().map(|s| s.iter().any(|d| d.state == DeviceState::Failed)).unwrap_or(false)
    }

    /// Publish `state` for the devices `which` selects.
    fn set_where(&self, which: impl Fn(&DeviceStatus) -> bool, state: DeviceState, error: Option<String>) {
        let mut changed = false;
        if let Ok(mut s) = self.status.lock() {
            for d in s.iter_mut().filter(|d| which(d)) {
                changed |= d.state != state || d.last_error != error;
                d.state = state;
                d.last_error.clone_from(&error);
            }
        }
        if changed {
            self.devices_changed();
        }
    }

    /// Tell the `devices` event stream that some device's status changed.
    fn devices_changed(&self) {
        self.shared.devices_changed.send_modify(|n| *n += 1);
    }

    /// Publish the parked control state of the open rig (or an unknown angle without one).
    fn publish_parked(&self) {
        let state = match self.rig.as_ref() {
            Some(rig) => ControlState::parked(rig),
            None => {
                ControlState { angle_deg: None, ..self.shared.control.lock().map(|c| c.clone()).unwrap_or_default() }
            }
        };
        if let Ok(mut c) = self.shared.control.lock() {
            *c = state;
        }
    }

    /// Check the serial board's link and, when it is down and its backoff allows, make one
    /// reconnection attempt. Publishes the link state for the serial devices. Returns how long to
    /// wait before the next attempt, or `None` when the board is connected (or there is none).
    fn poll_serial(&mut self) -> Option<Duration> {
        let controller = self.rig.as_ref()?.serial.as_ref()?.controller.clone();
        let mut c = crate::devices::serial::controller::lock(&controller);
        let now = std::time::Instant::now();
        match c.state() {
            LinkState::Connected => {
                self.set_where(is_serial, DeviceState::Connected, None);
                self.serial_ever_connected = true;
                None
            }
            LinkState::Disconnected { retry_at, .. } if retry_at > now => Some(retry_at - now),
            LinkState::Disconnected { .. } => {
                self.set_where(is_serial, DeviceState::Reconnecting, None);
                match c.reconnect(now) {
                    Ok(()) => {
                        if self.serial_ever_connected {
                            self.metrics.reconnects.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                            if let Ok(mut s) = self.status.lock() {
                                s.iter_mut().filter(|d| is_serial(d)).for_each(|d| d.reconnects += 1);
                            }
                            self.devices_changed();
                            tracing::info!("serial board reconnected");
                        }
                        self.serial_ever_connected = true;
                        self.set_where(is_serial, DeviceState::Connected, None);
                        None
                    }
                    Err(e) => {
                        let message = error_chain(&e);
                        tracing::debug!(error = %message, "serial board still unreachable");
                        self.set_where(is_serial, DeviceState::Disconnected, Some(message));
                        let next = match c.state() {
                            LinkState::Disconnected { retry_at, .. } => retry_at.saturating_duration_since(now),
                            LinkState::Connected => Duration::ZERO,
                        };
                        Some(next.max(Duration::from_millis(20)))
                    }
                }
            }
        }
    }

    fn set_all(&self, state: DeviceState, error: Option<String>) {
        self.set_where(|_| true, state, error);
    }

    fn connect(&mut self) -> bool {
        self.set_all(DeviceState::Reconnecting, None);
        match build_rig(&self.config) {
            Ok(rig) => {
                self.rig = Some(rig);
                self.serial_ever_connected = false;
                if self.ever_connected {
                    self.metrics.reconnects.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                    if let Ok(mut s) = self.status.lock() {
                        s.iter_mut().for_each(|d| d.reconnects += 1);
                    }
                    self.devices_changed();
                }
                self.ever_connected = true;
                if let (Ok(mut c), Some(rig)) = (self.shared.camera.lock(), self.rig.as_ref()) {
                    let info = rig.camera.info();
                    *c = Some(CameraSize { width: info.width, height: info.height });
                }
                self.publish_parked();
                self.set_all(DeviceState::Connected, None);
                tracing::info!("devices connected");
                true
            }
            Err(e) => {
                self.device_error(&e);
                false
            }
        }
    }

    /// Publish a device error and decide from its kind: reconnect or fail.
    fn device_error(&mut self, e: &DeviceError) {
        self.metrics.device_errors.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let message = error_chain(e);
        match e.kind() {
            ErrorKind::Disconnected | ErrorKind::Timeout | ErrorKind::Protocol | ErrorKind::Hardware
                if self.serial_device(device_of(e)) =>
            {
                // The board's controller reconnects by itself; the camera and the rest stay open.
                tracing::warn!(device = device_of(e), error = %message, "serial board error");
                self.set_where(is_serial, DeviceState::Disconnected, Some(message));
            }
            ErrorKind::Disconnected | ErrorKind::Timeout | ErrorKind::Protocol | ErrorKind::Hardware => {
                tracing::warn!(error = %message, "devices disconnected");
                self.rig = None;
                self.set_all(DeviceState::Disconnected, Some(message));
            }
            ErrorKind::Busy => {
                tracing::warn!(error = %message, "device busy");
            }
            ErrorKind::InvalidConfig | ErrorKind::Unsupported => {
                tracing::error!(error = %message, "devices cannot be used with this config");
                self.rig = None;
                self.set_all(DeviceState::Failed, Some(message));
            }
        }
    }

    /// Whether `name` is a device behind the serial board of the open rig.
    fn serial_device(&self, name: &str) -> bool {
        self.rig.as_ref().is_some_and(|r| r.serial.is_some())
            && self.status.lock().map(|s| s.iter().any(|d| d.name == name && is_serial(d))).unwrap_or(false)
    }

    fn handle(&mut self, cmd: Command) {
        match cmd {
            Command::Preview => {
                let waiters = self.previews.lock().unwrap_or_else(|p| p.into_inner()).take().unwrap_or_default();
                if waiters.is_empty() {
                    return;
                }
                let result: PreviewReply = self.capture().map(Arc::new).map_err(Arc::new);
                for w in waiters {
                    let _ = w.send(result.clone());
                }
            }
            Command::Park(reply) => {
                let result = match self.rig.as_mut() {
                    None => Err(RigError::NotConnected),
                    Some(rig) => acquisition::park(rig, &self.config.scan).map_err(RigError::Device),
                };
                if let Err(RigError::Device(e)) = &result {
                    self.device_error(e);
                }
                let _ = reply.send(result);
            }
            Command::Reload(config) => {
                if let Some(rig) = self.rig.as_mut() {
                    if let Err(e) = acquisition::park(rig, &self.config.scan) {
                        tracing::warn!(error = %e, "parking before reload failed");
                    }
                }
                self.rig = None;
                self.status.lock().map(|mut s| *s = device_list(&config, DeviceState::Reconnecting, None)).ok();
                self.devices_changed();
                self.config = config;
            }
            Command::Scan(job, reply) => {
                let result = self.scan(job);
                // A scan ends parked (lights and lasers off, projector blank).
                self.publish_parked();
                let _ = reply.send(result);
            }
            Command::Control(cmd, reply) => {
                let _ = reply.send(self.control(cmd));
            }
            Command::Reconnect(name, reply) => {
                tracing::info!(device = %name, "reconnection asked for");
                if let Some(rig) = self.rig.as_mut() {
                    if let Err(e) = acquisition::park(rig, &self.config.scan) {
                        tracing::warn!(error = %e, "parking before reconnecting failed");
                    }
                }
                // Every driver is dropped (closing its device) before the rig is opened again.
                self.rig = None;
                if !self.connect() {
                    tracing::warn!(device = %name, "reconnection failed; retrying with backoff");
                }
                let _ = reply.send(Ok(()));
            }
        }
    }

    fn control(&mut self, cmd: ControlCommand) -> Result<ControlState, RigError> {
        let rig = self.rig.as_mut().ok_or(RigError::NotConnected)?;
        let timeout = Duration::from_millis(self.config.scan.move_timeout_ms);
        let mut state = self.shared.control.lock().map(|c| c.clone()).unwrap_or_default();
        let result = control::apply(rig, &mut state, cmd, timeout);
        if let Ok(mut c) = self.shared.control.lock() {
            *c = state.clone();
        }
        match result {
            Ok(()) => Ok(state),
            Err(ControlError::Device(e)) => {
                self.device_error(&e);
                Err(RigError::Device(e))
            }
            Err(e) => Err(RigError::Control(e)),
        }
    }

    fn capture(&mut self) -> Result<PreviewFrame, RigError> {
        let rig = self.rig.as_mut().ok_or(RigError::NotConnected)?;
        let timeout = Duration::from_millis(self.config.scan.capture_timeout_ms);
        match rig.camera.capture(timeout) {
            Ok(frame) => Ok(PreviewFrame { sequence: frame.sequence, image: frame.image }),
            Err(e) => {
                self.device_error(&e);
                Err(RigError::Device(e))
            }
        }
    }

    fn scan(&mut self, mut job: ScanJob) -> Result<Report, RigError> {
        let rig = self.rig.as_mut().ok_or(RigError::NotConnected)?;
        let span = tracing::info_span!("scan", out = %job.out.display(), resume = job.resume);
        let _enter = span.enter();
        let result = scan::run_job(scan::Job {
            config: &job.config,
            out: &job.out,
            source: scan::Source::Rig { rig, resume: job.resume },
            cancel: &job.cancel,
            events: &mut *job.events,
            live: job.live,
        });
        if let Err(ScanError::Acquisition(crate::acquisition::AcquisitionError::Device { source, .. })) = &result {
            self.device_error(source);
        }
        result.map_err(RigError::Scan)
    }
}

/// An error and its sources, joined with `: `.
pub fn error_chain(e: &dyn std::error::Error) -> String {
    let mut s = e.to_string();
    let mut cur = e.source();
    while let Some(c) = cur {
        s.push_str(": ");
        s.push_str(&c.to_string());
        cur = c.source();
    }
    s
}

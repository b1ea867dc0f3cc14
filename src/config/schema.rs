//! The rig file's schema: one struct per TOML table, `deny_unknown_fields` everywhere, device
//! sections tagged by `kind`.

use serde::Deserialize;

use crate::geometry::{Aabb, CameraModel, Intrinsics, Pose, Vector3};

/// A whole rig file.
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct RigConfig {
    /// `[rig]`: name and description.
    pub rig: RigSection,
    /// `[turntable]`.
    pub turntable: TurntableConfig,
    /// `[lights]`: white lights and line lasers. Optional (a rig may have none).
    #[serde(default)]
    pub lights: Option<LightsConfig>,
    /// `[camera]`.
    pub camera: CameraConfig,
    /// `[projector]`, optional.
    #[serde(default)]
    pub projector: Option<ProjectorConfig>,
    /// `[depth_camera]`, optional.
    #[serde(default)]
    pub depth_camera: Option<DepthCameraConfig>,
    /// `[controller]`: the serial board behind `kind = "serial"` devices (turntable and lights share
    /// it).
    #[serde(default)]
    pub controller: Option<ControllerConfig>,
    /// `[sim]`: the simulated world; required when any device has `kind = "sim"`.
    #[serde(default)]
    pub sim: Option<SimConfig>,
    /// `[scan]`: the scan plan.
    pub scan: ScanPlan,
    /// `[reconstruction]`.
    pub reconstruction: ReconstructionConfig,
    /// `[replication]`: archive finished scans in S3-compatible object storage (daemon only).
    /// Never written into a scan's stored `rig.toml`.
    #[serde(default, skip_serializing)]
    pub replication: Option<super::replication::ReplicationConfig>,
}

/// `[rig]`.
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct RigSection {
    /// A name for logs and reports.
    pub name: String,
    /// Free text.
    #[serde(default)]
    pub description: String,
    /// Calibration file written by `scanrig calibrate`, relative to the rig file. When set, the
    /// camera's intrinsics (`[camera]`), its pose in the rig frame (`[turntable]`) and calibrated
    /// light positions (`[[lights]]`) come from it, replacing those of this file. In a simulated rig
    /// the simulated camera and lights are then placed by the calibration too (the rig file describes
    /// one camera).
    #[serde(default)]
    pub calibration: Option<std::path::PathBuf>,
}

/// `[turntable]`, tagged by `kind`.
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
#[serde(tag = "kind", rename_all = "kebab-case", deny_unknown_fields)]
pub enum TurntableConfig {
    /// `kind = "sim"`: a simulated stepper.
    Sim(SimTurntableConfig),
    /// `kind = "serial"`: the stepper of the `[controller]` board.
    Serial(SerialTurntableConfig),
}

/// `[turntable] kind = "serial"`.
#[derive(Debug, Clone, Default, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct SerialTurntableConfig {
    /// Turn the other way (for a motor wired in reverse): the angles the host asks for are negated
    /// on the wire, so scans are not mirrored.
    #[serde(default)]
    pub reverse: bool,
}

/// `[controller]`: one microcontroller on one serial port, driving the turntable and the lights.
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct ControllerConfig {
    /// The port: `/dev/serial/by-id/...` (preferred), `usb:VID:PID[:SERIAL]` (hex ids), a device path,
    /// or `emulator:scanrig` / `emulator:horus` / `emulator:fabscan` for a firmware emulator on a
    /// pseudo-terminal.
    pub port: String,
    /// The firmware's dialect.
    #[serde(default)]
    pub dialect: SerialDialect,
    /// Bits per second.
    #[serde(default = "default_baud")]
    pub baud: u32,
    /// Motor steps per full turn of the table. The scanrig dialect reads it from the board and, when
    /// set here, refuses a board that differs; Horus and FabScan need it here.
    #[serde(default)]
    pub steps_per_turn: Option<u32>,
    /// Line lasers on the board (Horus and FabScan; the scanrig dialect asks the board).
    #[serde(default = "default_serial_lasers")]
    pub lasers: u32,
    /// Turntable speed for dialects that take one on the wire, degrees per second.
    #[serde(default = "default_speed")]
    pub speed_deg_per_s: f64,
    /// Longest wait for the reply to one line, milliseconds.
    #[serde(default = "default_reply_timeout")]
    pub reply_timeout_ms: u64,
    /// Times a line is sent again after a lost or damaged reply.
    #[serde(default = "default_retries")]
    pub retries: u32,
    /// Longest wait for the board to boot after the port opens (Arduino auto-reset), milliseconds.
    #[serde(default = "default_boot")]
    pub boot_ms: u64,
    /// Handshake attempts per connection.
    #[serde(default = "default_handshake_attempts")]
    pub handshake_attempts: u32,
    /// Longest pause between reconnection attempts, milliseconds (the backoff doubles up to it).
    #[serde(default = "default_reconnect_max")]
    pub reconnect_max_ms: u64,
    /// Checksums on every line (scanrig dialect).
    #[serde(default = "yes")]
    pub checksum: bool,
    /// Board watchdog: everything off after this much host silence, milliseconds; 0 = off
    /// (scanrig dialect).
    #[serde(default)]
    pub watchdog_ms: u32,
    /// `[controller.emulator]`: the emulated board, for `port = "emulator:..."`.
    #[serde(default)]
    pub emulator: EmulatorConfig,
}

/// Firmware dialects for `[controller] dialect`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum SerialDialect {
    /// The scanrig line protocol v1.
    #[default]
    Scanrig,
    /// Horus firmware (GRBL-derived, Ciclop scanners).
    Horus,
    /// FabScanPi firmware.
    Fabscan,
}

impl SerialDialect {
    /// The name used in TOML and in `emulator:<name>`.
    pub fn name(self) -> &'static str {
        match self {
            SerialDialect::Scanrig => "scanrig",
            SerialDialect::Horus => "horus",
            SerialDialect::Fabscan => "fabscan",
        }
    }
}

/// `[controller.emulator]`.
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct EmulatorConfig {
    /// Emulated table speed, degrees per second.
    #[serde(default = "default_emulator_speed")]
    pub speed_deg_per_s: f64,
    /// Emulated boot time after the port opens, milliseconds.
    #[serde(default = "default_emulator_boot")]
    pub boot_ms: u64,
    /// Emulated board's steps per turn (defaults to `[controller] steps_per_turn`, else 3200).
    #[serde(default)]
    pub steps_per_turn: Option<u32>,
    /// Emulated white lights (scanrig emulator).
    #[serde(default = "default_emulator_lights")]
    pub lights: u32,
    /// Test and demo knob: the emulated board is unplugged when the N-th motion command arrives,
    /// counted from 1 over the emulator's life (0 = never).
    #[serde(default)]
    pub unplug_at_move: u32,
    /// Test and demo knob: an unplugged emulated board is plugged back in after this many
    /// milliseconds (0 = it stays unplugged).
    #[serde(default)]
    pub replug_after_ms: u64,
    /// Test and demo knob: the emulated board resets itself when the N-th motion command arrives
    /// (0 = never).
    #[serde(default)]
    pub reset_at_move: u32,
}

impl Default for EmulatorConfig {
    fn default() -> Self {
        EmulatorConfig {
            speed_deg_per_s: default_emulator_speed(),
            boot_ms: default_emulator_boot(),
            steps_per_turn: None,
            lights: default_emulator_lights(),
            unplug_at_move: 0,
            replug_after_ms: 0,
            reset_at_move: 0,
        }
    }
}

fn default_baud() -> u32 {
    115_200
}
fn default_serial_lasers() -> u32 {
    2
}
fn default_reply_timeout() -> u64 {
    500
}
fn default_retries() -> u32 {
    3
}
fn default_boot() -> u64 {
    2500
}
fn default_handshake_attempts() -> u32 {
    5
}
fn default_reconnect_max() -> u64 {
    5000
}
fn default_emulator_speed() -> f64 {
    720.0
}
fn default_emulator_boot() -> u64 {
    20
}
fn default_emulator_lights() -> u32 {
    4
}

/// `[turntable] kind = "sim"`.
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct SimTurntableConfig {
    /// Micro-steps per full turn of the table.
    #[serde(default = "default_steps_per_turn")]
    pub steps_per_turn: u32,
    /// Turning speed, degrees per second of simulated time.
    #[serde(default = "default_speed")]
    pub speed_deg_per_s: f64,
    /// Whether a move really takes its simulated time (sleeps). Off makes tests fast; the motion
    /// is still reported as in progress until `move_to` returns.
    #[serde(default)]
    pub real_time: bool,
}

fn default_steps_per_turn() -> u32 {
    3200
}
fn default_speed() -> f64 {
    90.0
}

/// `[lights]`: the light array's driver and the calibrated geometry of its lights and lasers.
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct LightsConfig {
    /// Driver.
    pub kind: LightsKind,
    /// `[[lights.light]]`: white point lights, in index order.
    #[serde(default, rename = "light")]
    pub lights: Vec<PointLightConfig>,
    /// `[[lights.laser]]`: line lasers, in index order.
    #[serde(default, rename = "laser")]
    pub lasers: Vec<LaserConfig>,
}

/// Light array drivers.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum LightsKind {
    /// Simulated lights that light the simulated scene.
    Sim,
    /// The lights and lasers of the `[controller]` board.
    Serial,
}

/// One white point light.
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct PointLightConfig {
    /// Position in the rig frame, metres.
    pub position_m: [f64; 3],
    /// Radiant intensity, relative (1.0 = a light that makes a white surface facing it at 0.5 m
    /// fully bright).
    #[serde(default = "one")]
    pub intensity: f64,
}

/// One line laser: a light plane fanned out from a point.
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct LaserConfig {
    /// The laser's exit point in the rig frame, metres.
    pub origin_m: [f64; 3],
    /// Normal of the light plane in the rig frame (any length).
    pub plane_normal: [f64; 3],
    /// Colour of the line, 8-bit RGB.
    #[serde(default = "red")]
    pub colour: [u8; 3],
}

fn one() -> f64 {
    1.0
}
fn red() -> [u8; 3] {
    [255, 0, 0]
}

/// `[camera]`, tagged by `kind`.
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
#[serde(tag = "kind", rename_all = "kebab-case", deny_unknown_fields)]
pub enum CameraConfig {
    /// `kind = "sim"`: renders the simulated world.
    Sim(SimCameraConfig),
    /// `kind = "v4l2"`: a V4L2 camera (cargo feature `v4l`).
    V4l2(RealCameraConfig),
    /// `kind = "uvc"`: a UVC camera through nokhwa (cargo feature `nokhwa`), for platforms without V4L2.
    Uvc(RealCameraConfig),
    /// `kind = "genicam"`: a GigE Vision or USB3 Vision camera through Aravis (cargo feature `aravis`).
    Genicam(GenicamCameraConfig),
}

impl CameraConfig {
    /// The calibrated camera model in the rig frame.
    pub fn model(&self) -> CameraModel {
        match self {
            CameraConfig::Sim(c) => c.calibration.model(c.width, c.height),
            CameraConfig::V4l2(c) | CameraConfig::Uvc(c) => c.calibration.model(c.width, c.height),
            CameraConfig::Genicam(c) => c.calibration.model(c.width, c.height),
        }
    }

    /// Image size, pixels (width, height).
    pub fn size(&self) -> (u32, u32) {
        match self {
            CameraConfig::Sim(c) => (c.width, c.height),
            CameraConfig::V4l2(c) | CameraConfig::Uvc(c) => (c.width, c.height),
            CameraConfig::Genicam(c) => (c.width, c.height),
        }
    }

    /// The calibration (intrinsics and rig-frame pose), for a calibration file to overwrite.
    pub fn calibration_mut(&mut self) -> &mut CameraCalibration {
        match self {
            CameraConfig::Sim(c) => &mut c.calibration,
            CameraConfig::V4l2(c) | CameraConfig::Uvc(c) => &mut c.calibration,
            CameraConfig::Genicam(c) => &mut c.calibration,
        }
    }
}

/// `[camera] kind = "v4l2"` or `"uvc"`: a real camera.
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct RealCameraConfig {
    /// Which camera, by a stable identity: `/dev/v4l/by-id/...`, `usb:VID:PID[:SERIAL]`,
    /// `bus:usb-0000:00:14.0-1` (V4L2 bus info) or `card:NAME`; `scanrig devices` lists them.
    pub device: String,
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// Pixel format: `grey`, `yuyv`, `mjpeg` or `rgb24`; absent = the first the camera offers at this
    /// size, uncompressed preferred.
    #[serde(default)]
    pub format: Option<super::vocab::PixelFormat>,
    /// Frame rate, frames per second; absent = the camera's default.
    #[serde(default)]
    pub fps: Option<u32>,
    /// Driver buffers (memory-mapped); after a scene change up to this many queued frames are stale.
    #[serde(default = "default_real_buffers")]
    pub buffers: u32,
    /// `[camera.controls]`: exposure, gain, white balance, focus and further controls locked for the
    /// scan and restored after it.
    #[serde(default)]
    pub controls: super::vocab::ManualControls,
    /// `[camera.calibration]`.
    pub calibration: CameraCalibration,
}

fn default_real_buffers() -> u32 {
    4
}

/// `[camera] kind = "genicam"`: a GigE Vision / USB3 Vision camera through Aravis. It is selected
/// by its stable identity (`serial`, with `vendor` and `model` to narrow it), or reached at `address`
/// without discovery; every value below is written as a GenICam feature and read back.
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct GenicamCameraConfig {
    /// `DeviceVendorName` to match (e.g. `Basler`); absent = any.
    #[serde(default)]
    pub vendor: Option<String>,
    /// `DeviceModelName` to match; absent = any.
    #[serde(default)]
    pub model: Option<String>,
    /// `DeviceSerialNumber` to match, the stable identity (`scanrig devices` lists it).
    #[serde(default)]
    pub serial: Option<String>,
    /// Open the GigE Vision camera at this IP address directly, without broadcast discovery; the
    /// vendor, model and serial above are then checked against what it reports.
    #[serde(default)]
    pub address: Option<String>,
    /// Image width, pixels (the region of interest starts at the sensor's top-left corner).
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// `PixelFormat`: `Mono8` or `RGB8`.
    #[serde(default)]
    pub pixel_format: super::vocab::GenicamPixelFormat,
    /// Exposure time, microseconds; absent = the camera's current value.
    #[serde(default)]
    pub exposure_us: Option<f64>,
    /// Gain (`Gain` in dB, or `GainRaw` on cameras that only have it); absent = the camera's.
    #[serde(default)]
    pub gain: Option<f64>,
    /// Frame rate, frames per second (in free run, the rate; with a trigger, the upper bound);
    /// absent = the camera's.
    #[serde(default)]
    pub fps: Option<f64>,
    /// How exposures start: `free-run`, `software` or `line`.
    #[serde(default)]
    pub trigger: super::vocab::TriggerMode,
    /// With `trigger = "line"`: the input line (`TriggerSource`), e.g. `Line0`.
    #[serde(default = "default_trigger_line")]
    pub trigger_line: String,
    /// With `trigger = "line"`: the edge or level that starts an exposure.
    #[serde(default)]
    pub trigger_activation: super::vocab::TriggerActivation,
    /// With `trigger = "line"`: delay from the trigger to the start of exposure, microseconds.
    #[serde(default)]
    pub trigger_delay_us: Option<f64>,
    /// Stream buffers in the pool; after a scene change up to this many queued frames are stale.
    #[serde(default = "default_real_buffers")]
    pub buffers: u32,
    /// `[camera.calibration]`.
    pub calibration: CameraCalibration,
}

fn default_trigger_line() -> String {
    "Line0".into()
}

/// `[camera] kind = "sim"`.
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct SimCameraConfig {
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// How many frames the simulated driver queues (like V4L2 buffers): after a scene change the
    /// first `buffer_depth - 1` frames are stale.
    #[serde(default = "default_buffer_depth")]
    pub buffer_depth: u32,
    /// Standard deviation of additive Gaussian pixel noise, 8-bit levels (0 = none).
    #[serde(default)]
    pub noise_sigma: f64,
    /// Seed of the noise generator.
    #[serde(default)]
    pub seed: u64,
    /// `[camera.calibration]`.
    pub calibration: CameraCalibration,
}

fn default_buffer_depth() -> u32 {
    3
}

/// A camera's calibration: intrinsics and pose in the rig frame.
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct CameraCalibration {
    /// `[camera.calibration.intrinsics]`, pixels.
    pub intrinsics: Intrinsics,
    /// `[camera.calibration.pose]`.
    pub pose: PoseConfig,
}

impl CameraCalibration {
    /// The camera model for an image of `width` x `height` pixels.
    pub fn model(&self, width: u32, height: u32) -> CameraModel {
        CameraModel { width, height, intrinsics: self.intrinsics, pose: self.pose.pose() }
    }
}

/// A pose in the rig frame, either by look-at or by rotation + translation.
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
#[serde(untagged, deny_unknown_fields)]
pub enum PoseConfig {
    /// Camera centre `eye_m` looking at `target_m`, `up` up in the image.
    LookAt {
        /// Centre of projection, rig frame, metres.
        eye_m: [f64; 3],
        /// Point on the optical axis, rig frame, metres.
        target_m: [f64; 3],
        /// Up direction (default `+z`).
        #[serde(default = "z_up")]
        up: [f64; 3],
    },
    /// `x_cam = rotation · x_rig + translation_m`; rotation as three rows.
    Matrix {
        /// Rotation rig -> camera, row-major.
        rotation: [[f64; 3]; 3],
        /// Translation, metres.
        translation_m: [f64; 3],
    },
}

fn z_up() -> [f64; 3] {
    [0.0, 0.0, 1.0]
}

impl PoseConfig {
    /// The pose.
    pub fn pose(&self) -> Pose {
        match self {
            PoseConfig::LookAt { eye_m, target_m, up } => {
                Pose::look_at(Vector3::from(*eye_m), Vector3::from(*target_m), Vector3::from(*up))
            }
            PoseConfig::Matrix { rotation, translation_m } => Pose {
                rotation: crate::geometry::Matrix3::from_fn(|r, c| rotation[r][c]),
                translation: Vector3::from(*translation_m),
            },
        }
    }
}

/// `[projector]`, tagged by `kind`.
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
#[serde(tag = "kind", rename_all = "kebab-case", deny_unknown_fields)]
pub enum ProjectorConfig {
    /// `kind = "sim"`: projects onto the simulated scene.
    Sim(SimProjectorConfig),
    /// `kind = "fbdev"`: a projector on a video output driven as a Linux framebuffer, no desktop
    /// (cargo feature `fbdev`).
    Fbdev(FbdevProjectorConfig),
    /// `kind = "window"`: a projector on an X11 output, driven as a borderless full-screen window
    /// (cargo feature `x11`).
    Window(WindowProjectorConfig),
}

/// `[projector] kind = "window"`: a borderless full-screen X11 window on one output.
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct WindowProjectorConfig {
    /// The X display, e.g. `:0`; absent = `$DISPLAY`.
    #[serde(default)]
    pub display: Option<String>,
    /// The output the projector is plugged into: a RandR output name (`HDMI-1`, `DP-2`; the error
    /// for an unknown name lists them), or `screen:N` for the whole X screen N.
    pub output: String,
    /// Expected width, projector pixels (the output's must match).
    pub width: u32,
    /// Expected height, projector pixels.
    pub height: u32,
    /// Present each pattern at a vertical blank through the Present extension, and take its
    /// presentation time from the server (true), or draw directly and allow one refresh (false).
    #[serde(default = "yes")]
    pub vsync: bool,
    /// The projector's own delay from receiving a frame to showing it, milliseconds.
    #[serde(default)]
    pub latency_ms: u64,
    /// Refresh rate to assume when the output reports no mode timing, hertz.
    #[serde(default = "default_refresh_hz")]
    pub refresh_hz: f64,
    /// `[projector.calibration]`: intrinsics and pose in the rig frame, for triangulation.
    #[serde(default)]
    pub calibration: Option<CameraCalibration>,
}

fn yes() -> bool {
    true
}

/// `[projector] kind = "fbdev"`.
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct FbdevProjectorConfig {
    /// The framebuffer device, e.g. `/dev/fb1` (`scanrig devices` lists them with their sizes).
    pub device: String,
    /// Expected width, projector pixels (the framebuffer's must match).
    pub width: u32,
    /// Expected height, projector pixels.
    pub height: u32,
    /// The projector's own delay from receiving a frame to showing it, milliseconds (measure it:
    /// project a pattern and find the first camera frame that shows it).
    #[serde(default)]
    pub latency_ms: u64,
    /// Refresh rate to assume when the framebuffer reports no timing and cannot wait for vertical
    /// blank, hertz.
    #[serde(default = "default_refresh_hz")]
    pub refresh_hz: f64,
    /// `[projector.calibration]`: intrinsics and pose in the rig frame, for triangulation.
    #[serde(default)]
    pub calibration: Option<CameraCalibration>,
    /// A projector-camera calibration file written by `scanrig calibrate projector` (relative to
    /// the rig file; square size in metres so its translation is in metres). When set, it gives the
    /// projector's intrinsics and its rig-frame pose (its projector <- camera transform composed with
    /// the camera's rig-frame pose), replacing `[projector.calibration]`.
    #[serde(default)]
    pub procam: Option<std::path::PathBuf>,
}

fn default_refresh_hz() -> f64 {
    60.0
}

impl ProjectorConfig {
    /// The calibrated projector model (inverse pinhole) in the rig frame; `None` for a real
    /// projector without `[projector.calibration]`.
    pub fn model(&self) -> Option<CameraModel> {
        match self {
            ProjectorConfig::Sim(p) => Some(p.calibration.model(p.width, p.height)),
            ProjectorConfig::Fbdev(p) => p.calibration.as_ref().map(|c| c.model(p.width, p.height)),
            ProjectorConfig::Window(p) => p.calibration.as_ref().map(|c| c.model(p.width, p.height)),
        }
    }

    /// Resolution, projector pixels (width, height).
    pub fn size(&self) -> (u32, u32) {
        match self {
            ProjectorConfig::Sim(p) => (p.width, p.height),
            ProjectorConfig::Fbdev(p) => (p.width, p.height),
            ProjectorConfig::Window(p) => (p.width, p.height),
        }
    }

    /// One refresh period of the projector, milliseconds.
    pub fn frame_period_ms(&self) -> f64 {
        match self {
            ProjectorConfig::Sim(p) => p.frame_period_ms,
            ProjectorConfig::Fbdev(p) => 1000.0 / p.refresh_hz,
            ProjectorConfig::Window(p) => 1000.0 / p.refresh_hz,
        }
    }
}

/// `[projector] kind = "sim"`: a projector modelled as an inverse pinhole camera.
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct SimProjectorConfig {
    /// Width, projector pixels.
    pub width: u32,
    /// Height, projector pixels.
    pub height: u32,
    /// Brightness of a full-white pattern pixel on a white surface, relative to a light of
    /// intensity 1.
    #[serde(default = "one")]
    pub intensity: f64,
    /// Exponent of the input-to-light response: light = `black_level + (1 - black_level) ·
    /// (v / 255)^gamma` for input grey `v` (1 = linear, real projectors are near 2.2).
    #[serde(default = "one")]
    pub gamma: f64,
    /// Light of a black input, as a fraction 0..1 of full white (projector leakage).
    #[serde(default)]
    pub black_level: f64,
    /// `[projector.calibration]`: intrinsics and pose in the rig frame.
    pub calibration: CameraCalibration,
    /// Time from being handed a pattern to showing it, milliseconds (input lag).
    #[serde(default)]
    pub latency_ms: f64,
    /// Refresh period, milliseconds: a pattern appears at the first refresh after the latency
    /// (0 = as soon as the latency has passed).
    #[serde(default)]
    pub frame_period_ms: f64,
}

/// `[depth_camera]`, tagged by `kind`.
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
#[serde(tag = "kind", rename_all = "kebab-case", deny_unknown_fields)]
pub enum DepthCameraConfig {
    /// `kind = "sim"`: depth rendered from the simulated scene.
    Sim(SimDepthCameraConfig),
    /// `kind = "freenect"`: a Kinect v1 through libfreenect (cargo feature `freenect`).
    Freenect(FreenectDepthConfig),
}

/// `[depth_camera] kind = "freenect"`: a Kinect v1, depth 640x480 in millimetres.
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct FreenectDepthConfig {
    /// The Kinect's camera serial number (stable; `scanrig devices` lists it); absent = the first.
    #[serde(default)]
    pub serial: Option<String>,
    /// Depth registered to the RGB camera (true) or in the infrared camera's own frame (false, the
    /// frame the calibration below then describes).
    #[serde(default)]
    pub registered: bool,
    /// `mm` (the unit's calibrated millimetres) or `disparity` (raw 11-bit disparity converted by
    /// the driver; what fakenect replays).
    #[serde(default)]
    pub depth_format: super::vocab::FreenectDepthFormat,
    /// `[depth_camera.calibration]`: of the infrared camera (or the RGB camera when registered), at
    /// 640x480.
    pub calibration: CameraCalibration,
}

impl FreenectDepthConfig {
    /// Depth map width, pixels.
    pub const WIDTH: u32 = 640;
    /// Depth map height, pixels.
    pub const HEIGHT: u32 = 480;
}

/// `[depth_camera] kind = "sim"`.
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct SimDepthCameraConfig {
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// Standard deviation of depth noise, metres.
    #[serde(default)]
    pub noise_sigma_m: f64,
    /// Noise seed.
    #[serde(default)]
    pub seed: u64,
    /// `[depth_camera.calibration]`.
    pub calibration: CameraCalibration,
}

/// `[sim]`: the simulated world.
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct SimConfig {
    /// The scene on the turntable: `"sphere"`, `"box"`, `"cup"`, `"pit-block"` or `"textured-box"`.
    pub scene: String,
    /// Uniform scale applied to the preset scene (1.0 = preset size, about 8 cm across).
    #[serde(default = "one")]
    pub scale: f64,
    /// Background colour seen where no object is, 8-bit RGB.
    #[serde(default)]
    pub background: [u8; 3],
    /// Ambient light level, 0..1 of full brightness, so unlit faces stay visible.
    #[serde(default = "default_ambient")]
    pub ambient: f64,
}

fn default_ambient() -> f64 {
    0.25
}

/// `[scan]`: what the acquisition does.
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct ScanPlan {
    /// Turntable positions, evenly spaced over one turn.
    pub positions: u32,
    /// Angle of the first position, degrees.
    #[serde(default)]
    pub start_deg: f64,
    /// Lights switched on (full level) for each position's frame, by index.
    #[serde(default)]
    pub lights: Vec<usize>,
    /// Shadow carving: the lights that cast the shadows, by index. At each position the rig takes one
    /// ambient frame (all lights off) and one frame per light named here, with only that light on.
    #[serde(default)]
    pub shadow_lights: Vec<usize>,
    /// Wait after a move has finished before capturing, milliseconds (vibration settles).
    #[serde(default)]
    pub settle_ms: u64,
    /// Timeout of one turntable move, milliseconds.
    #[serde(default = "default_move_timeout")]
    pub move_timeout_ms: u64,
    /// Timeout of one frame capture, milliseconds.
    #[serde(default = "default_capture_timeout")]
    pub capture_timeout_ms: u64,
    /// Stale frames to discard after a change before giving up.
    #[serde(default = "default_max_stale")]
    pub max_stale_frames: u32,
}

fn default_move_timeout() -> u64 {
    30_000
}
fn default_capture_timeout() -> u64 {
    2_000
}
fn default_max_stale() -> u32 {
    8
}

/// `[reconstruction]`.
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct ReconstructionConfig {
    /// Method: `"space-carving"`, `"shadow-carving"`, `"depth-fusion"`, `"voxel-coloring"` or
    /// `"space-carving-photo"` or `"laser"`.
    pub method: Method,
    /// Working volume minimum corner, object frame, metres.
    pub bbox_min_m: [f64; 3],
    /// Working volume maximum corner, object frame, metres.
    pub bbox_max_m: [f64; 3],
    /// Voxels along the longest side of the working volume (cubic voxels).
    pub resolution: u32,
    /// `[reconstruction.silhouette]`.
    #[serde(default)]
    pub silhouette: SilhouetteConfig,
    /// `[reconstruction.mesh]`.
    #[serde(default)]
    pub mesh: MeshConfig,
    /// `[reconstruction.depth_fusion]` (method `depth-fusion`).
    #[serde(default)]
    pub depth_fusion: DepthFusionConfig,
    /// `[reconstruction.photo]`: photo-consistency methods only.
    #[serde(default)]
    pub photo: PhotoConfig,
    /// `[reconstruction.laser]`: method `laser` only.
    #[serde(default)]
    pub laser: LaserScanConfig,
    /// `[reconstruction.structured_light]` (method `structured-light`).
    #[serde(default)]
    pub structured_light: crate::config::structured_light::StructuredLightConfig,
    /// Memory a scan may need, megabytes (MiB): `validate` refuses a rig whose estimate (see
    /// [`crate::config::MemoryEstimate`]) is above it. Default 2048, for a small box.
    #[serde(default = "default_memory_budget_mb")]
    pub memory_budget_mb: u64,
}

fn default_memory_budget_mb() -> u64 {
    2048
}

/// `[reconstruction.depth_fusion]`: the TSDF of method `depth-fusion`.
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct DepthFusionConfig {
    /// Truncation distance, voxels.
    #[serde(default = "default_truncation_voxels")]
    pub truncation_voxels: f64,
    /// Whether a depth pixel without a measurement is free space (true for a simulated rig, whose
    /// background is empty) rather than unknown (a real sensor's dropout).
    #[serde(default)]
    pub missing_is_free: bool,
}

fn default_truncation_voxels() -> f64 {
    3.0
}

impl Default for DepthFusionConfig {
    fn default() -> Self {
        DepthFusionConfig { truncation_voxels: default_truncation_voxels(), missing_is_free: false }
    }
}

impl ReconstructionConfig {
    /// The working volume.
    pub fn bbox(&self) -> Aabb {
        Aabb { min: self.bbox_min_m, max: self.bbox_max_m }
    }
}

/// Reconstruction methods.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Deserialize, serde::Serialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
#[clap(rename_all = "kebab-case")]
pub enum Method {
    /// Visual hull by silhouette carving.
    SpaceCarving,
    /// Visual hull, then shadow carving with the lights of `scan.shadow_lights`.
    ShadowCarving,
    /// TSDF fusion of the depth camera's maps over turntable positions.
    DepthFusion,
    /// Voxel colouring with the ordinal visibility constraint: one sweep per direction, each with
    /// the views on the near side of the working volume along it (every view in some sweep).
    VoxelColoring,
    /// Generalized space carving by photo-consistency, from the visual hull (any camera placement).
    SpaceCarvingPhoto,
    /// Laser-stripe triangulation over turntable positions with the lasers of
    /// `[reconstruction.laser]`, a point cloud, and a mesh from it.
    Laser,
    /// Gray-code structured light: projector patterns, triangulation, TSDF fusion of the range images.
    StructuredLight,
}

impl std::fmt::Display for Method {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl Method {
    /// The name used in TOML, the CLI and reports.
    pub fn name(self) -> &'static str {
        match self {
            Method::SpaceCarving => "space-carving",
            Method::ShadowCarving => "shadow-carving",
            Method::DepthFusion => "depth-fusion",
            Method::VoxelColoring => "voxel-coloring",
            Method::SpaceCarvingPhoto => "space-carving-photo",
            Method::Laser => "laser",
            Method::StructuredLight => "structured-light",
        }
    }

    /// Every method, in the order the README lists them.
    pub const ALL: [Method; 7] = [
        Method::SpaceCarving,
        Method::ShadowCarving,
        Method::VoxelColoring,
        Method::SpaceCarvingPhoto,
        Method::DepthFusion,
        Method::StructuredLight,
        Method::Laser,
    ];

    /// True for the methods that measure the surface (depth, triangulation) rather than carve a
    /// volume: their mesh is compared with the true surface (Chamfer distance).
    pub fn measures_surface(self) -> bool {
        matches!(self, Method::DepthFusion | Method::Laser | Method::StructuredLight)
    }

    /// True for the photo-consistency methods (they need the images, not only silhouettes).
    pub fn is_photo(self) -> bool {
        matches!(self, Method::VoxelColoring | Method::SpaceCarvingPhoto)
    }
}

/// `[reconstruction.photo]`: the photo-consistency test (see `pipeline::photo_consistency`).
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct PhotoConfig {
    /// Largest colour standard deviation between the views of a kept voxel (of their mean colours
    /// over its footprint), 8-bit levels (0..255). Absent (the default): derived from the data's
    /// measured noise (`pipeline::PhotoNoise::threshold`: the spread of the visual hull's surface
    /// colours between views and the image noise); a number fixes it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub threshold: Option<f64>,
    /// Smallest mean normalised cross-correlation of a textured kept voxel (-1..1); absent = no NCC test.
    #[serde(default)]
    pub min_ncc: Option<f64>,
    /// Views needed to judge a voxel (at least 2).
    #[serde(default = "default_photo_min_views")]
    pub min_views: usize,
    /// Views facing a voxel's estimated normal with a cosine below this are not consulted (-1..1).
    #[serde(default = "default_photo_min_cos")]
    pub min_cos: f64,
    /// Cap on carving iterations.
    #[serde(default = "default_photo_iterations")]
    pub max_iterations: usize,
}

fn default_photo_min_views() -> usize {
    2
}
fn default_photo_min_cos() -> f64 {
    0.4
}
fn default_photo_iterations() -> usize {
    500
}

impl Default for PhotoConfig {
    fn default() -> Self {
        PhotoConfig {
            threshold: None,
            min_ncc: None,
            min_views: default_photo_min_views(),
            min_cos: default_photo_min_cos(),
            max_iterations: default_photo_iterations(),
        }
    }
}

/// Silhouette extraction: a pixel is object where the largest per-channel difference from
/// `background`, scaled to 0..1, exceeds `threshold`; then a closing (dilate, erode) with discs of the
/// given radii in pixels. With `background = [0, 0, 0]` this is the Middlebury recipe (threshold on
/// max(R, G, B)).
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct SilhouetteConfig {
    /// Threshold, 0..1.
    #[serde(default = "default_threshold")]
    pub threshold: f64,
    /// Background colour, 8-bit RGB.
    #[serde(default)]
    pub background: [u8; 3],
    /// Dilation disc radius, pixels.
    #[serde(default)]
    pub dilate_px: u32,
    /// Erosion disc radius, pixels.
    #[serde(default)]
    pub erode_px: u32,
}

fn default_threshold() -> f64 {
    0.1
}

impl Default for SilhouetteConfig {
    fn default() -> Self {
        SilhouetteConfig { threshold: default_threshold(), background: [0, 0, 0], dilate_px: 0, erode_px: 0 }
    }
}

/// `[reconstruction.mesh]`.
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct MeshConfig {
    /// Box-filter the occupancy over this many voxels (radius) before the surface is extracted, so
    /// the mesh is not a staircase; 0 = raw occupancy (the surface is still relaxed off the voxel
    /// stairs).
    #[serde(default)]
    pub smooth_radius: u32,
    /// Error bound of the mesh simplification (quadric edge collapses), voxel edges: every collapse
    /// keeps each original vertex within it of the simplified surface and each new vertex within it
    /// of the original one, and the sampled symmetric Hausdorff distance between both surfaces is
    /// measured and reported; 0 = no simplification.
    #[serde(default = "default_mesh_max_error_voxels")]
    pub max_error_voxels: f64,
}

/// Default of [`MeshConfig::max_error_voxels`]: a quarter voxel, below what any method measures to.
/// Bounded per collapse (no whole-mesh retries), the simplifier and its Hausdorff check leave 7-26 %
/// of the triangles of the shipped 128^3 rigs' meshes; they still add about 1-3 s after the last
/// frame on two cores shared with other work (README, "Meshes").
pub const DEFAULT_MESH_MAX_ERROR_VOXELS: f64 = 0.25;

fn default_mesh_max_error_voxels() -> f64 {
    DEFAULT_MESH_MAX_ERROR_VOXELS
}

impl Default for MeshConfig {
    fn default() -> Self {
        MeshConfig { smooth_radius: 0, max_error_voxels: DEFAULT_MESH_MAX_ERROR_VOXELS }
    }
}

/// `[reconstruction.laser]`: stripe detection, point cloud clean-up and meshing of method `laser`.
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct LaserScanConfig {
    /// Indices of the `[[lights.laser]]` entries to scan with, each captured on its own at every
    /// position; empty = every configured laser.
    #[serde(default)]
    pub lasers: Vec<usize>,
    /// Smallest laser signal (on minus off, weighted by the laser colour) of a stripe pixel, 8-bit levels.
    #[serde(default = "default_laser_min_peak")]
    pub min_peak: f64,
    /// Widest run of stripe pixels accepted in an image row, pixels.
    #[serde(default = "default_laser_max_width")]
    pub max_width_px: u32,
    /// Half-width of the sub-pixel centre-of-mass window, pixels.
    #[serde(default = "default_laser_half_window")]
    pub half_window_px: u32,
    /// Neighbours for normal estimation and for the outlier test (3..=64).
    #[serde(default = "default_laser_neighbours")]
    pub neighbours: usize,
    /// Outlier test: a point whose mean neighbour distance exceeds the cloud's mean by this many
    /// standard deviations is removed.
    #[serde(default = "default_laser_std_ratio")]
    pub outlier_std_ratio: f64,
    /// Oriented points averaged per signed-distance evaluation when meshing (3..=64).
    #[serde(default = "default_laser_mesh_neighbours")]
    pub mesh_neighbours: usize,
    /// Edge of the cubes the merged cloud is thinned to before normals and meshing, in voxels of the
    /// working grid (one point per cube: the mean). Thinning evens out the density of laser data,
    /// dense along each stripe and sparse across stripes, so a point's nearest neighbours span several
    /// stripes (the points of one stripe lie in one plane, the laser's, whose normal PCA would
    /// otherwise return); 0 keeps every point.
    #[serde(default = "default_laser_thin")]
    pub thin_voxels: f64,
}

fn default_laser_min_peak() -> f64 {
    40.0
}
fn default_laser_max_width() -> u32 {
    8
}
fn default_laser_half_window() -> u32 {
    3
}
fn default_laser_neighbours() -> usize {
    16
}
fn default_laser_std_ratio() -> f64 {
    2.0
}
fn default_laser_thin() -> f64 {
    1.0
}
fn default_laser_mesh_neighbours() -> usize {
    8
}

impl Default for LaserScanConfig {
    fn default() -> Self {
        LaserScanConfig {
            lasers: Vec::new(),
            min_peak: default_laser_min_peak(),
            max_width_px: default_laser_max_width(),
            half_window_px: default_laser_half_window(),
            neighbours: default_laser_neighbours(),
            outlier_std_ratio: default_laser_std_ratio(),
            mesh_neighbours: default_laser_mesh_neighbours(),
            thin_voxels: default_laser_thin(),
        }
    }
}

impl LaserScanConfig {
    /// The problems of this section for a rig with `lasers` configured lasers, as
    /// `(key, message)` pairs (empty when it is valid).
    pub fn problems(&self, lasers: usize) -> Vec<(String, String)> {
        let mut out = Vec::new();
        let key = |k: &str| format!("reconstruction.laser.{k}");
        if lasers == 0 {
            out.push(("lights.laser".to_owned(), "method \"laser\" needs at least one [[lights.laser]]".to_owned()));
        }
        for (i, &l) in self.lasers.iter().enumerate() {
            if l >= lasers {
                out.push((
                    key(&format!("lasers.{i}")),
                    format!("laser {l} does not exist: the rig has {lasers} laser(s)"),
                ));
            } else if self.lasers[..i].contains(&l) {
                out.push((key(&format!("lasers.{i}")), format!("laser {l} is named twice")));
            }
        }
        if !(self.min_peak.is_finite() && self.min_peak > 0.0 && self.min_peak < 256.0) {
            out.push((key("min_peak"), format!("must be in (0, 256) levels, got {}", self.min_peak)));
        }
        if self.max_width_px == 0 {
            out.push((key("max_width_px"), "must be at least 1 pixel".to_owned()));
        }
        for (name, k) in [("neighbours", self.neighbours), ("mesh_neighbours", self.mesh_neighbours)] {
            if !(3..=64).contains(&k) {
                out.push((key(name), format!("must be between 3 and 64, got {k}")));
            }
        }
        if !(self.thin_voxels.is_finite() && self.thin_voxels >= 0.0) {
            out.push((
                key("thin_voxels"),
                format!("must be 0 or a positive number of voxels, got {}", self.thin_voxels),
            ));
        }
        if !(self.outlier_std_ratio.is_finite() && self.outlier_std_ratio > 0.0) {
            out.push((key("outlier_std_ratio"), format!("must be positive, got {}", self.outlier_std_ratio)));
        }
        out
    }

    /// The lasers to scan with, given `lasers` configured ones: the listed indices, or all.
    pub fn selected(&self, lasers: usize) -> Vec<usize> {
        if self.lasers.is_empty() {
            (0..lasers).collect()
        } else {
            self.lasers.clone()
        }
    }
}

//! Vocabulary the rig file shares with the device drivers: pixel formats, camera controls, trigger
//! modes, depth formats and serial-port identities. It lives here, below `devices/`, so the rig file's
//! schema names them without importing the drivers; the drivers give them their behaviour.

use std::collections::BTreeMap;
use std::path::PathBuf;

use serde::Deserialize;

/// A pixel format a camera delivers, identified by its V4L2 four-character code.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Deserialize, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum PixelFormat {
    /// `GREY`: 8-bit luminance, one byte per pixel.
    Grey,
    /// `YUYV`: packed 4:2:2, `Y0 U Y1 V` for each pair of pixels (BT.601, limited range).
    Yuyv,
    /// `MJPG`: each frame a JPEG image.
    Mjpeg,
    /// `RGB3`: packed 8-bit `R G B`.
    Rgb24,
}

/// The manual settings of a scan; `None` leaves a control as the device has it.
#[derive(Debug, Clone, Default, PartialEq, serde::Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct ManualControls {
    /// Exposure time, microseconds; sets auto exposure to manual.
    #[serde(default)]
    pub exposure_us: Option<u32>,
    /// Gain, device units; turns auto gain off.
    #[serde(default)]
    pub gain: Option<i64>,
    /// White balance temperature, kelvin; turns auto white balance off.
    #[serde(default)]
    pub white_balance_k: Option<i64>,
    /// Focus, device units; turns autofocus off.
    #[serde(default)]
    pub focus: Option<i64>,
    /// Further controls by their V4L2 name (as `v4l2-ctl --list-ctrls` prints it, e.g.
    /// `"trigger_mode" = 1` for a camera with an external trigger input), set after the others.
    #[serde(default)]
    pub extra: BTreeMap<String, i64>,
}

/// `camera.pixel_format`: the GenICam pixel formats the driver converts to RGB.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize, serde::Serialize)]
pub enum GenicamPixelFormat {
    /// `Mono8`: 8-bit grey.
    #[default]
    Mono8,
    /// `RGB8`: packed 8-bit R, G, B.
    #[serde(rename = "RGB8")]
    Rgb8,
}

/// `camera.trigger`: how each exposure is started.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum TriggerMode {
    /// The camera runs at its frame rate (`TriggerMode = Off`).
    #[default]
    FreeRun,
    /// The driver triggers each frame (`TriggerSource = Software`, `TriggerSoftware`).
    Software,
    /// A hardware input line triggers each frame (`TriggerSource = camera.trigger_line`).
    Line,
}

/// `camera.trigger_activation`: which edge or level of the line starts an exposure
/// (`TriggerActivation`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum TriggerActivation {
    /// `RisingEdge`.
    #[default]
    RisingEdge,
    /// `FallingEdge`.
    FallingEdge,
    /// `AnyEdge`.
    AnyEdge,
    /// `LevelHigh`.
    LevelHigh,
    /// `LevelLow`.
    LevelLow,
}

/// How `[depth_camera] kind = "freenect"` asks libfreenect for depth.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Deserialize, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum FreenectDepthFormat {
    /// Millimetres from the unit's factory calibration (`FREENECT_DEPTH_MM`, or `REGISTERED`).
    #[default]
    Mm,
    /// Raw 11-bit disparity (`FREENECT_DEPTH_11BIT`) converted with [`disparity_to_m`]; the only
    /// format fakenect replays.
    Disparity,
}

/// Which port to open, from the config's `port` string.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum PortSpec {
    /// A device path: `/dev/serial/by-id/...` (preferred: stable across replugging) or any other.
    Path(PathBuf),
    /// `usb:VID:PID[:SERIAL]`, hexadecimal ids: the first USB serial port that matches.
    Usb {
        /// USB vendor id.
        vid: u16,
        /// USB product id.
        pid: u16,
        /// USB serial number, when given.
        serial: Option<String>,
    },
    /// `emulator:<dialect>`: a firmware emulator on a pseudo-terminal, started with the driver.
    Emulator(String),
}

/// Why a `port` string is not usable.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum PortSpecError {
    /// `usb:` not followed by `VID:PID[:SERIAL]` in hexadecimal.
    #[error("`{0}`: expected usb:VID:PID or usb:VID:PID:SERIAL with hexadecimal ids, e.g. usb:2341:0043")]
    BadUsb(String),
    /// Empty.
    #[error("port is empty")]
    Empty,
    /// Not a path, `usb:` or `emulator:`.
    #[error("`{0}`: expected a device path (/dev/serial/by-id/...), usb:VID:PID[:SERIAL] or emulator:<dialect>")]
    Unknown(String),
}

impl PortSpec {
    /// Parse the config's `port`.
    pub fn parse(s: &str) -> Result<Self, PortSpecError> {
        let s = s.trim();
        if s.is_empty() {
            return Err(PortSpecError::Empty);
        }
        if let Some(rest) = s.strip_prefix("usb:") {
            let mut parts = rest.splitn(3, ':');
            let hex = |p: Option<&str>| {
                p.filter(|p| !p.is_empty() && p.len() <= 4).and_then(|p| u16::from_str_radix(p, 16).ok())
            };
            let vid = hex(parts.next()).ok_or_else(|| PortSpecError::BadUsb(s.to_owned()))?;
            let pid = hex(parts.next()).ok_or_else(|| PortSpecError::BadUsb(s.to_owned()))?;
            let serial = match parts.next() {
                Some("") => return Err(PortSpecError::BadUsb(s.to_owned())),
                other => other.map(str::to_owned),
            };
            return Ok(PortSpec::Usb { vid, pid, serial });
        }
        if let Some(rest) = s.strip_prefix("emulator:") {
            return Ok(PortSpec::Emulator(rest.to_owned()));
        }
        if s.starts_with('/') || s.starts_with("COM") {
            return Ok(PortSpec::Path(PathBuf::from(s)));
        }
        Err(PortSpecError::Unknown(s.to_owned()))
    }
}

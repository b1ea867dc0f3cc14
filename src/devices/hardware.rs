//! The real (non-simulated) device kinds of the rig file: their checks for `RigConfig::validate`
//! and their construction for the registry, each behind its cargo feature. A kind whose feature is
//! not built in is a validation problem naming the feature to enable, and an `InvalidConfig` error
//! if it reaches the registry anyway.

use crate::config::{
    CameraConfig, FbdevProjectorConfig, FreenectDepthConfig, GenicamCameraConfig, RealCameraConfig,
    WindowProjectorConfig,
};

use super::sysfs::CameraSelector;
use super::{Camera, DepthCamera, DeviceError, Projector};

/// The cargo feature a rig-file `kind` needs, for messages: `(kind, feature, built in)`.
pub fn camera_feature(config: &CameraConfig) -> Option<(&'static str, &'static str, bool)> {
    match config {
        CameraConfig::Sim(_) => None,
        CameraConfig::V4l2(_) => Some(("v4l2", "v4l", cfg!(feature = "v4l"))),
        CameraConfig::Uvc(_) => Some(("uvc", "nokhwa", cfg!(feature = "nokhwa"))),
        CameraConfig::Genicam(_) => Some(("genicam", "aravis", cfg!(feature = "aravis"))),
    }
}

fn missing_feature(kind: &str, feature: &str) -> String {
    format!("kind = \"{kind}\" needs scanrig built with the `{feature}` feature (cargo build --release --features {feature})")
}

/// Checks of a real camera's section (`camera.*` keys).
/// The drivers' checks of a rig file's device settings (a kind whose cargo feature is not built, a
/// device path that is not a stable identity, ...), as problems keyed like `RigConfig::validate`'s.
pub fn check(config: &crate::config::RigConfig) -> Vec<crate::config::Problem> {
    use crate::config::{CameraConfig, DepthCameraConfig, ProjectorConfig};
    let mut out = Vec::new();
    let mut bad = |key: &str, message: String| {
        out.push(crate::config::Problem { key: key.to_owned(), line: None, message });
    };
    match &config.camera {
        CameraConfig::V4l2(c) | CameraConfig::Uvc(c) => validate_camera(&config.camera, c, &mut bad),
        CameraConfig::Genicam(c) => validate_genicam(c, &mut bad),
        CameraConfig::Sim(_) => {}
    }
    match &config.projector {
        Some(ProjectorConfig::Fbdev(p)) => validate_fbdev(p, &mut bad),
        Some(ProjectorConfig::Window(p)) => validate_window(p, &mut bad),
        Some(ProjectorConfig::Sim(_)) | None => {}
    }
    if let Some(DepthCameraConfig::Freenect(d)) = &config.depth_camera {
        validate_freenect(d, &mut bad);
    }
    out
}

pub fn validate_camera(config: &CameraConfig, c: &RealCameraConfig, bad: &mut dyn FnMut(&str, String)) {
    if let Some((kind, feature, false)) = camera_feature(config) {
        bad("camera.kind", missing_feature(kind, feature));
    }
    match CameraSelector::parse(&c.device) {
        Ok(s) if s.is_unstable() => bad(
            "camera.device",
            format!(
                "`{}` changes with plug order; use /dev/v4l/by-id/..., usb:VID:PID:SERIAL, bus:... or card:... (see `scanrig devices`)",
                c.device
            ),
        ),
        Ok(_) => {}
        Err(e) => bad("camera.device", e.to_string()),
    }
    if c.width % 2 != 0 && c.format == Some(super::camera::pixel::PixelFormat::Yuyv) {
        bad("camera.width", "YUYV needs an even width".into());
    }
    if !(2..=32).contains(&c.buffers) {
        bad("camera.buffers", format!("must be between 2 and 32, got {}", c.buffers));
    }
    if c.fps.is_some_and(|f| f == 0 || f > 1000) {
        bad("camera.fps", "must be between 1 and 1000".into());
    }
    if c.controls.exposure_us.is_some_and(|e| e == 0 || e > 10_000_000) {
        bad("camera.controls.exposure_us", "must be between 1 and 10000000 microseconds".into());
    }
    if c.controls.white_balance_k.is_some_and(|k| !(1000..=15_000).contains(&k)) {
        bad("camera.controls.white_balance_k", "must be between 1000 and 15000 kelvin".into());
    }
}

/// Checks of `[camera] kind = "genicam"` (`camera.*` keys).
pub fn validate_genicam(c: &GenicamCameraConfig, bad: &mut dyn FnMut(&str, String)) {
    use super::camera::genicam_features::TriggerMode;
    if !cfg!(feature = "aravis") {
        bad("camera.kind", missing_feature("genicam", "aravis"));
    }
    let blank = |v: &Option<String>| v.as_deref().is_some_and(|s| s.trim().is_empty() || s.contains('\0'));
    for (key, v) in [("vendor", &c.vendor), ("model", &c.model), ("serial", &c.serial), ("address", &c.address)] {
        if blank(v) {
            bad(&format!("camera.{key}"), "must not be empty".into());
        }
    }
    if c.serial.is_none() && c.address.is_none() {
        bad(
            "camera.serial",
            "a GenICam camera is selected by its serial number (or reached at `address`); `scanrig devices` lists them"
                .into(),
        );
    }
    if let Some(a) = &c.address {
        if a.parse::<std::net::Ipv4Addr>().is_err() {
            bad("camera.address", format!("`{a}` is not an IPv4 address"));
        }
    }
    if !(2..=64).contains(&c.buffers) {
        bad("camera.buffers", format!("must be between 2 and 64, got {}", c.buffers));
    }
    if c.exposure_us.is_some_and(|e| !(e.is_finite() && e > 0.0 && e <= 10_000_000.0)) {
        bad("camera.exposure_us", "must be between 0 and 10000000 microseconds".into());
    }
    if c.gain.is_some_and(|g| !(g.is_finite() && g >= 0.0)) {
        bad("camera.gain", "must be a non-negative number".into());
    }
    if c.fps.is_some_and(|f| !(f.is_finite() && f > 0.0 && f <= 10_000.0)) {
        bad("camera.fps", "must be between 0 and 10000 frames per second".into());
    }
    if let Some(d) = c.trigger_delay_us {
        if !(d.is_finite() && (0.0..=10_000_000.0).contains(&d)) {
            bad("camera.trigger_delay_us", "must be between 0 and 10000000 microseconds".into());
        }
        if c.trigger != TriggerMode::Line {
            bad("camera.trigger_delay_us", "applies to trigger = \"line\" only".into());
        }
    }
    if c.trigger == TriggerMode::Line
        && (c.trigger_line.is_empty() || !c.trigger_line.chars().all(|ch| ch.is_ascii_alphanumeric() || ch == '_'))
    {
        bad("camera.trigger_line", format!("`{}`: expected a GenICam line name such as Line0", c.trigger_line));
    }
}

/// Checks of `[projector] kind = "fbdev"`.
pub fn validate_fbdev(p: &FbdevProjectorConfig, bad: &mut dyn FnMut(&str, String)) {
    if !cfg!(feature = "fbdev") {
        bad("projector.kind", missing_feature("fbdev", "fbdev"));
    }
    if !p.device.starts_with('/') {
        bad("projector.device", format!("`{}`: expected a device path such as /dev/fb1", p.device));
    }
    if p.width == 0 || p.height == 0 || p.width > 16384 || p.height > 16384 {
        bad("projector.width", format!("size {}x{} is not between 1 and 16384 pixels", p.width, p.height));
    }
    if p.latency_ms > 2000 {
        bad("projector.latency_ms", "must be at most 2000".into());
    }
    if !(p.refresh_hz.is_finite() && (1.0..=1000.0).contains(&p.refresh_hz)) {
        bad("projector.refresh_hz", format!("must be between 1 and 1000 Hz, got {}", p.refresh_hz));
    }
}

/// Checks of `[projector] kind = "window"`.
pub fn validate_window(p: &WindowProjectorConfig, bad: &mut dyn FnMut(&str, String)) {
    if !cfg!(feature = "x11") {
        bad("projector.kind", missing_feature("window", "x11"));
    }
    if p.output.trim().is_empty() {
        bad("projector.output", "must name an output (e.g. HDMI-1) or `screen:N`".into());
    } else if let Some(n) = p.output.strip_prefix("screen:") {
        if n.parse::<usize>().is_err() {
            bad("projector.output", format!("`{}`: expected screen:N with N a screen number", p.output));
        }
    }
    if p.display.as_deref().is_some_and(|d| d.trim().is_empty()) {
        bad("projector.display", "must not be empty (leave it out to use $DISPLAY)".into());
    }
    if p.width == 0 || p.height == 0 || p.width > 16384 || p.height > 16384 {
        bad("projector.width", format!("size {}x{} is not between 1 and 16384 pixels", p.width, p.height));
    }
    if p.latency_ms > 2000 {
        bad("projector.latency_ms", "must be at most 2000".into());
    }
    if !(p.refresh_hz.is_finite() && (1.0..=1000.0).contains(&p.refresh_hz)) {
        bad("projector.refresh_hz", format!("must be between 1 and 1000 Hz, got {}", p.refresh_hz));
    }
}

/// Open a window projector.
pub fn open_window(config: &WindowProjectorConfig) -> Result<Box<dyn Projector>, DeviceError> {
    #[cfg(feature = "x11")]
    {
        Ok(Box::new(super::projector::window::WindowProjector::open(config)?))
    }
    #[cfg(not(feature = "x11"))]
    {
        let _ = config;
        Err(not_built("projector", "window", "x11"))
    }
}

/// Checks of `[depth_camera] kind = "freenect"`.
pub fn validate_freenect(d: &FreenectDepthConfig, bad: &mut dyn FnMut(&str, String)) {
    if !cfg!(feature = "freenect") {
        bad("depth_camera.kind", missing_feature("freenect", "freenect"));
    }
    if d.serial.as_deref().is_some_and(|s| s.trim().is_empty() || s.contains('\0')) {
        bad("depth_camera.serial", "must be a non-empty serial number".into());
    }
    if d.registered && d.depth_format == super::depth::kinect::FreenectDepthFormat::Disparity {
        bad(
            "depth_camera.registered",
            "registration needs depth_format = \"mm\" (raw disparity is unregistered)".into(),
        );
    }
}

#[cfg_attr(
    all(
        feature = "v4l",
        feature = "nokhwa",
        feature = "fbdev",
        feature = "freenect",
        feature = "aravis",
        feature = "x11"
    ),
    allow(dead_code)
)]
fn not_built(device: &str, kind: &str, feature: &str) -> DeviceError {
    DeviceError::InvalidConfig { device: device.to_owned(), field: "kind", problem: missing_feature(kind, feature) }
}

/// Open a real camera (`kind = "v4l2"` or `"uvc"`).
pub fn open_camera(config: &CameraConfig) -> Result<Box<dyn Camera>, DeviceError> {
    match config {
        CameraConfig::Sim(_) => Err(DeviceError::InvalidConfig {
            device: "camera".into(),
            field: "kind",
            problem: "the simulated camera is built by the registry".into(),
        }),
        #[cfg(feature = "v4l")]
        CameraConfig::V4l2(c) => {
            Ok(Box::new(super::camera::v4l2::V4l2Camera::open(c, &super::sysfs::SysRoot::default())?))
        }
        #[cfg(not(feature = "v4l"))]
        CameraConfig::V4l2(_) => Err(not_built("camera", "v4l2", "v4l")),
        #[cfg(feature = "nokhwa")]
        CameraConfig::Uvc(c) => {
            Ok(Box::new(super::camera::uvc::UvcCamera::open(c, &super::sysfs::SysRoot::default())?))
        }
        #[cfg(not(feature = "nokhwa"))]
        CameraConfig::Uvc(_) => Err(not_built("camera", "uvc", "nokhwa")),
        #[cfg(feature = "aravis")]
        CameraConfig::Genicam(c) => Ok(Box::new(super::camera::genicam::GenicamCamera::open(c)?)),
        #[cfg(not(feature = "aravis"))]
        CameraConfig::Genicam(_) => Err(not_built("camera", "genicam", "aravis")),
    }
}

/// Open a framebuffer projector.
pub fn open_fbdev(config: &FbdevProjectorConfig) -> Result<Box<dyn Projector>, DeviceError> {
    #[cfg(feature = "fbdev")]
    {
        Ok(Box::new(super::projector::fbdev::FbdevProjector::open(config)?))
    }
    #[cfg(not(feature = "fbdev"))]
    {
        let _ = config;
        Err(not_built("projector", "fbdev", "fbdev"))
    }
}

/// Open a Kinect v1.
pub fn open_freenect(config: &FreenectDepthConfig) -> Result<Box<dyn DepthCamera>, DeviceError> {
    #[cfg(feature = "freenect")]
    {
        Ok(Box::new(super::depth::freenect::FreenectDepthCamera::open(config)?))
    }
    #[cfg(not(feature = "freenect"))]
    {
        let _ = config;
        Err(not_built("depth_camera", "freenect", "freenect"))
    }
}

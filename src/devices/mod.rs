//! Device families: one trait each, with simulated and real drivers, built from the config by
//! [`registry`].
//!
//! Every trait is synchronous and takes `&mut self`; a device is owned by one thread. Every call that
//! can block takes an explicit timeout. Optional capabilities are default methods returning
//! [`DeviceError::Unsupported`].

pub mod camera;
pub mod depth;
pub mod discovery;
pub mod hardware;
pub mod lights;
pub mod projector;
pub mod registry;
pub mod serial;
pub mod sysfs;
pub mod turntable;

use std::time::Duration;

pub use camera::{Camera, CameraInfo, Frame};
pub use depth::{DepthCamera, DepthFrame};
pub use lights::LightArray;
pub use projector::{Pattern, Projector};
pub use registry::{build_rig, Rig};
pub use turntable::Turntable;

/// What kind of failure a device reported; the supervisor decides retry / reconnect / fail from this
/// alone.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum ErrorKind {
    /// The device went away (unplugged, port closed, board reset). Reconnect.
    Disconnected,
    /// The device did not answer in time. Retry, then treat as disconnected.
    Timeout,
    /// The device is doing something else. Retry later.
    Busy,
    /// The device answered something that does not follow its protocol.
    Protocol,
    /// The configuration cannot work with this device.
    InvalidConfig,
    /// The device cannot do this.
    Unsupported,
    /// The device reported a fault of its own (end stop, driver fault, overheating).
    Hardware,
}

/// An error from a device driver. Each variant names the device (its config section, e.g.
/// `turntable`) so that a message is useful on its own.
#[derive(Debug, thiserror::Error)]
pub enum DeviceError {
    /// The device is gone.
    #[error("{device}: disconnected")]
    Disconnected {
        /// Device name.
        device: String,
        /// The I/O error that showed it, if any.
        #[source]
        source: Option<std::io::Error>,
    },
    /// No answer in time.
    #[error("{device}: no answer within {timeout:?} while {waiting_for}")]
    Timeout {
        /// Device name.
        device: String,
        /// What the driver was waiting for.
        waiting_for: &'static str,
        /// The timeout that ran out.
        timeout: Duration,
    },
    /// The device is busy.
    #[error("{device}: busy ({reason})")]
    Busy {
        /// Device name.
        device: String,
        /// Why.
        reason: &'static str,
    },
    /// The device broke its protocol.
    #[error("{device}: protocol error: {detail}")]
    Protocol {
        /// Device name.
        device: String,
        /// What was wrong, with the offending bytes where useful.
        detail: String,
    },
    /// A setting does not work with this device.
    #[error("{device}: invalid setting `{field}`: {problem}")]
    InvalidConfig {
        /// Device name.
        device: String,
        /// The config key.
        field: &'static str,
        /// What is wrong with it.
        problem: String,
    },
    /// The device cannot do this.
    #[error("{device}: {operation} is not supported by this device")]
    Unsupported {
        /// Device name.
        device: String,
        /// What was asked.
        operation: &'static str,
    },
    /// The device reported a fault.
    #[error("{device}: hardware fault {code}: {detail}")]
    Hardware {
        /// Device name.
        device: String,
        /// The device's own fault code.
        code: u16,
        /// The device's own text.
        detail: String,
    },
    /// An I/O error that is not a disconnect.
    #[error("{device}: I/O error")]
    Io {
        /// Device name.
        device: String,
        /// The error.
        #[source]
        source: std::io::Error,
    },
}

impl DeviceError {
    /// The kind of failure, for retry / reconnect / fail decisions.
    pub fn kind(&self) -> ErrorKind {
        match self {
            DeviceError::Disconnected { .. } => ErrorKind::Disconnected,
            DeviceError::Timeout { .. } => ErrorKind::Timeout,
            DeviceError::Busy { .. } => ErrorKind::Busy,
            DeviceError::Protocol { .. } => ErrorKind::Protocol,
            DeviceError::InvalidConfig { .. } => ErrorKind::InvalidConfig,
            DeviceError::Unsupported { .. } => ErrorKind::Unsupported,
            DeviceError::Hardware { .. } => ErrorKind::Hardware,
            DeviceError::Io { source, .. } => match source.kind() {
                std::io::ErrorKind::TimedOut | std::io::ErrorKind::WouldBlock => ErrorKind::Timeout,
                std::io::ErrorKind::BrokenPipe
                | std::io::ErrorKind::NotFound
                | std::io::ErrorKind::UnexpectedEof
                | std::io::ErrorKind::ConnectionReset => ErrorKind::Disconnected,
                _ => ErrorKind::Hardware,
            },
        }
    }

    /// Shorthand for [`DeviceError::Unsupported`].
    pub fn unsupported(device: &str, operation: &'static str) -> Self {
        DeviceError::Unsupported { device: device.to_owned(), operation }
    }
}

impl From<crate::sim::SimConfigError> for DeviceError {
    fn from(e: crate::sim::SimConfigError) -> Self {
        DeviceError::InvalidConfig { device: e.section.to_owned(), field: e.field, problem: e.source.to_string() }
    }
}

/// A simulated device's refusal (`SimError`) as the device error of `device` about `field`.
pub(crate) fn sim_device_error(e: &crate::sim::SimError, device: &str, field: &'static str) -> DeviceError {
    DeviceError::InvalidConfig { device: device.to_owned(), field, problem: e.to_string() }
}

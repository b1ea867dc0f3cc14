//! Errors of the serial link, turned into [`DeviceError`]s at the driver boundary.

use std::time::Duration;

use firmware_protocol::{DecodeError, ErrorCode};

use crate::devices::DeviceError;

/// What went wrong on the serial link.
#[derive(Debug, thiserror::Error)]
pub enum LinkError {
    /// The port is gone (unplugged, closed, read end-of-file).
    #[error("port disconnected")]
    Disconnected {
        /// The I/O error that showed it, if any.
        #[source]
        source: Option<std::io::Error>,
    },
    /// The port could not be opened.
    #[error("cannot open port {port}")]
    Open {
        /// The port as configured.
        port: String,
        /// Why.
        #[source]
        source: std::io::Error,
    },
    /// The port spec names no port that is present.
    #[error("no serial port matches `{spec}`")]
    NotFound {
        /// The port as configured.
        spec: String,
    },
    /// The board did not answer in time.
    #[error("no answer within {timeout:?} while {waiting_for}")]
    Timeout {
        /// What the driver waited for.
        waiting_for: &'static str,
        /// The timeout.
        timeout: Duration,
    },
    /// The board sent its banner unasked: it was reset, and its position and outputs are lost.
    #[error("the board reset itself (banner received unasked)")]
    BoardReset,
    /// A line from the board could not be decoded, and retries did not help.
    #[error("undecodable reply")]
    Decode {
        /// Why.
        #[source]
        source: DecodeError,
    },
    /// The board answered something its dialect does not allow at this point.
    #[error("unexpected reply: {line}")]
    Unexpected {
        /// The line, cleaned for printing.
        line: String,
    },
    /// The board refused the command.
    #[error("board error {code}: {text}")]
    Board {
        /// The board's error code.
        code: u16,
        /// The board's text.
        text: String,
    },
    /// The board's motion ended early (stop, fault).
    #[error("motion {id} was stopped at {pos} steps")]
    Stopped {
        /// Motion id.
        id: u16,
        /// Position, steps.
        pos: i64,
    },
    /// The board does not speak what the config says.
    #[error("board mismatch: {problem}")]
    Mismatch {
        /// What differs.
        problem: String,
    },
    /// A write or read failed in a way that is not a disconnect.
    #[error("I/O error")]
    Io {
        /// The error.
        #[source]
        source: std::io::Error,
    },
}

impl LinkError {
    /// Whether the link must be dropped and opened again.
    pub fn needs_reconnect(&self) -> bool {
        matches!(
            self,
            LinkError::Disconnected { .. }
                | LinkError::BoardReset
                | LinkError::Open { .. }
                | LinkError::NotFound { .. }
        )
    }

    /// Classify an I/O error from the port: timeouts stay timeouts, everything else is a disconnect
    /// (an unplugged USB port shows as EIO, broken pipe or end-of-file, never as "slowness").
    pub fn from_io(source: std::io::Error, waiting_for: &'static str, timeout: Duration) -> Self {
        match source.kind() {
            std::io::ErrorKind::TimedOut | std::io::ErrorKind::WouldBlock => {
                LinkError::Timeout { waiting_for, timeout }
            }
            std::io::ErrorKind::Interrupted => LinkError::Io { source },
            _ => LinkError::Disconnected { source: Some(source) },
        }
    }

    /// The device-layer error, naming `device`.
    pub fn into_device_error(self, device: &str) -> DeviceError {
        let device = device.to_owned();
        match self {
            LinkError::Disconnected { source } => DeviceError::Disconnected { device, source },
            LinkError::Open { source, .. } => DeviceError::Disconnected { device, source: Some(source) },
            LinkError::NotFound { .. } | LinkError::BoardReset => DeviceError::Disconnected { device, source: None },
            LinkError::Timeout { waiting_for, timeout } => DeviceError::Timeout { device, waiting_for, timeout },
            LinkError::Decode { source } => DeviceError::Protocol { device, detail: source.to_string() },
            LinkError::Unexpected { line } => DeviceError::Protocol { device, detail: format!("unexpected `{line}`") },
            LinkError::Board { code, text } => match ErrorCode::from_code(code) {
                ErrorCode::Busy => DeviceError::Busy { device, reason: "a motion is under way" },
                ErrorCode::Unsupported => {
                    DeviceError::Unsupported { device, operation: "this command (board answered error:4)" }
                }
                ErrorCode::Hardware => DeviceError::Hardware { device, code, detail: text },
                _ => DeviceError::Protocol { device, detail: format!("board error {code}: {text}") },
            },
            LinkError::Stopped { id, pos } => {
                DeviceError::Hardware { device, code: 0, detail: format!("motion {id} stopped early at {pos} steps") }
            }
            LinkError::Mismatch { problem } => DeviceError::InvalidConfig { device, field: "controller", problem },
            LinkError::Io { source } => DeviceError::Io { device, source },
        }
    }
}

/// Printable form of a line for messages: ASCII kept, other bytes escaped.
pub(crate) fn printable(bytes: &[u8]) -> String {
    bytes.iter().flat_map(|&b| std::ascii::escape_default(b)).map(char::from).collect()
}

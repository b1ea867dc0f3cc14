//! Port selection and the byte transport under the link.

use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::time::Duration;

use super::error::LinkError;

/// A byte pipe to a board: a serial port, one end of a pseudo-terminal, or a test script. Reads wait
/// at most the timeout set last and then fail with `TimedOut`.
pub trait Transport: Read + Write + Send + std::fmt::Debug {
    /// Set how long one read may wait.
    fn set_read_timeout(&mut self, timeout: Duration) -> std::io::Result<()>;
}

impl Transport for serialport::TTYPort {
    fn set_read_timeout(&mut self, timeout: Duration) -> std::io::Result<()> {
        serialport::SerialPort::set_timeout(self, timeout).map_err(std::io::Error::from)
    }
}

impl Transport for Box<dyn serialport::SerialPort> {
    fn set_read_timeout(&mut self, timeout: Duration) -> std::io::Result<()> {
        serialport::SerialPort::set_timeout(self.as_mut(), timeout).map_err(std::io::Error::from)
    }
}

/// Opens (and after a disconnect, re-opens) the transport to one board.
pub trait Opener: Send + std::fmt::Debug {
    /// Open the port. Fails with [`LinkError::NotFound`] while the board is absent.
    fn open(&mut self) -> Result<Box<dyn Transport>, LinkError>;
    /// The port as configured, for logs.
    fn describe(&self) -> String;
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

/// Opens a real serial port by path or USB identity, at a baud rate, 8N1, no flow control.
#[derive(Debug, Clone)]
pub struct SystemOpener {
    spec: PortSpec,
    baud: u32,
}

impl SystemOpener {
    /// An opener for `spec` (not [`PortSpec::Emulator`]) at `baud` bits per second.
    pub fn new(spec: PortSpec, baud: u32) -> Self {
        SystemOpener { spec, baud }
    }

    fn resolve(&self) -> Result<PathBuf, LinkError> {
        match &self.spec {
            PortSpec::Path(p) => {
                if p.exists() {
                    // by-id names are symlinks; open what they point at now.
                    Ok(std::fs::canonicalize(p).unwrap_or_else(|_| p.clone()))
                } else {
                    Err(LinkError::NotFound { spec: p.display().to_string() })
                }
            }
            PortSpec::Usb { vid, pid, serial } => {
                let spec = format!(
                    "usb:{vid:04x}:{pid:04x}{}",
                    serial.as_deref().map(|s| format!(":{s}")).unwrap_or_default()
                );
                if !Path::new("/sys/class/tty").is_dir() {
                    return Err(LinkError::NotFound { spec });
                }
                let ports = serialport::available_ports()
                    .map_err(|e| LinkError::Open { port: spec.clone(), source: std::io::Error::from(e) })?;
                ports
                    .into_iter()
                    .find(|p| match &p.port_type {
                        serialport::SerialPortType::UsbPort(u) => {
                            u.vid == *vid
                                && u.pid == *pid
                                && serial.as_ref().is_none_or(|s| u.serial_number.as_deref() == Some(s.as_str()))
                        }
                        _ => false,
                    })
                    .map(|p| PathBuf::from(p.port_name))
                    .ok_or(LinkError::NotFound { spec })
            }
            PortSpec::Emulator(name) => Err(LinkError::NotFound { spec: format!("emulator:{name}") }),
        }
    }
}

impl Opener for SystemOpener {
    fn open(&mut self) -> Result<Box<dyn Transport>, LinkError> {
        let path = self.resolve()?;
        let name = path.display().to_string();
        let port = serialport::new(name.clone(), self.baud)
            .data_bits(serialport::DataBits::Eight)
            .parity(serialport::Parity::None)
            .stop_bits(serialport::StopBits::One)
            .flow_control(serialport::FlowControl::None)
            .timeout(Duration::from_millis(50))
            .open_native()
            .map_err(|e| LinkError::Open { port: name, source: std::io::Error::from(e) })?;
        Ok(Box::new(port))
    }

    fn describe(&self) -> String {
        format!("{:?} at {} baud", self.spec, self.baud)
    }
}

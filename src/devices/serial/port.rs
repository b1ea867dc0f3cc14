//! Port selection and the byte transport under the link.

use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::time::Duration;

use super::error::LinkError;

pub use crate::config::vocab::{PortSpec, PortSpecError};

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

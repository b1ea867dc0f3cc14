//! Serial boards: a turntable and lights behind one microcontroller on a USB serial line
//! (`[controller]` in the rig file, `kind = "serial"` in `[turntable]` and `[lights]`).
//!
//! Layers, each with one job:
//! - [`port`]: which port (`/dev/serial/by-id/...`, `usb:VID:PID[:SERIAL]`, a path, `emulator:...`)
//!   and the byte transport;
//! - [`link`]: deadline-bounded reads; any I/O error that is not a timeout is a disconnect;
//! - [`dialect`]: the firmware family's wire conventions (scanrig protocol v1, Horus, FabScan);
//! - [`controller`]: connection state, handshake, reconnection with capped backoff;
//! - [`devices`]: the [`Turntable`](crate::devices::Turntable) and
//!   [`LightArray`](crate::devices::LightArray) over one shared controller;
//! - [`emulator`]: firmware emulators on real pseudo-terminals, with fault knobs.

pub mod controller;
pub mod devices;
pub mod dialect;
pub mod emulator;
pub mod error;
pub mod link;
pub mod port;

use std::sync::{Arc, Mutex};
use std::time::Duration;

pub use controller::{Backoff, Expectations, LinkState, SerialController, SharedController};
pub use devices::{SerialLightArray, SerialTurntable};
pub use dialect::{BoardInfo, Dialect, Timing};
pub use emulator::{EmulatedFirmware, EmulatedHardware, Emulator, EmulatorSettings, Faults, RecordingHardware};
pub use error::LinkError;
pub use port::{PortSpec, PortSpecError};

use crate::config::{ControllerConfig, SerialDialect};
use crate::devices::DeviceError;

/// A board's controller, and its emulator when the port is `emulator:...` (kept alive with it).
#[derive(Debug, Clone)]
pub struct OpenedController {
    /// The controller, shared by the board's turntable and lights.
    pub controller: SharedController,
    /// The emulator, when one was started: its fault knobs are reachable through it.
    pub emulator: Option<Arc<Emulator>>,
}

/// The timings a config asks for.
pub fn timing(c: &ControllerConfig) -> Timing {
    Timing {
        reply_timeout: Duration::from_millis(c.reply_timeout_ms),
        retries: c.retries,
        boot: Duration::from_millis(c.boot_ms),
        handshake_attempts: c.handshake_attempts,
        poll_interval: Duration::from_millis(c.reply_timeout_ms.clamp(20, 250)),
    }
}

/// Build the dialect the config names.
pub fn dialect(c: &ControllerConfig) -> Box<dyn Dialect> {
    let t = timing(c);
    let spt = c.steps_per_turn.unwrap_or(3200);
    let lasers = c.lasers as usize;
    match c.dialect {
        SerialDialect::Scanrig => Box::new(dialect::scanrig::ScanrigDialect::new(
            t,
            c.checksum,
            dialect::scanrig::SafetyLimits { watchdog_ms: c.watchdog_ms, ..Default::default() },
        )),
        SerialDialect::Horus => Box::new(dialect::horus::HorusDialect::new(t, spt, lasers, c.speed_deg_per_s)),
        SerialDialect::Fabscan => Box::new(dialect::fabscan::FabScanDialect::new(t, spt, lasers, c.speed_deg_per_s)),
    }
}

/// Open the `[controller]` board. Nothing is sent yet: the first command connects, so a board that
/// is absent at start-up is a [`LinkState::Disconnected`] state, not a failure to start. For
/// `port = "emulator:<dialect>"`, an emulator is started that drives `hardware` (the simulated world,
/// or a recorder when `None`).
pub fn open_controller(
    c: &ControllerConfig,
    hardware: Option<Arc<dyn EmulatedHardware>>,
) -> Result<OpenedController, DeviceError> {
    let invalid = |problem: String| DeviceError::InvalidConfig { device: "controller".into(), field: "port", problem };
    let spec = PortSpec::parse(&c.port).map_err(|e| invalid(e.to_string()))?;
    let backoff =
        Backoff { initial: Duration::from_millis(100), max: Duration::from_millis(c.reconnect_max_ms.max(1)) };
    let expect = Expectations { steps_per_turn: c.steps_per_turn };
    let (opener, emulator): (Box<dyn port::Opener>, _) = match spec {
        PortSpec::Emulator(name) => {
            let fw = EmulatedFirmware::from_name(&name)
                .ok_or_else(|| invalid(format!("unknown emulator `{name}` (scanrig, horus, fabscan)")))?;
            let settings = EmulatorSettings {
                speed_deg_per_s: c.emulator.speed_deg_per_s,
                boot: Duration::from_millis(c.emulator.boot_ms),
                steps_per_turn: c.emulator.steps_per_turn.or(c.steps_per_turn).unwrap_or(3200),
                lights: u8::try_from(c.emulator.lights).unwrap_or(u8::MAX),
                lasers: u8::try_from(c.lasers).unwrap_or(u8::MAX),
            };
            let hw = hardware.unwrap_or_else(|| Arc::new(RecordingHardware::new()));
            let emu = Emulator::spawn(fw, settings, hw)
                .map_err(|source| DeviceError::Io { device: "controller".into(), source })?;
            // The test and demo fault knobs of `[controller.emulator]`.
            let faults = emu.faults();
            faults.unplug_at_move.store(c.emulator.unplug_at_move, std::sync::atomic::Ordering::SeqCst);
            faults.replug_after_ms.store(c.emulator.replug_after_ms, std::sync::atomic::Ordering::SeqCst);
            faults.reset_at_move.store(c.emulator.reset_at_move, std::sync::atomic::Ordering::SeqCst);
            (Box::new(emulator::EmulatorOpener::new(Arc::clone(&emu))), Some(emu))
        }
        other => (Box::new(port::SystemOpener::new(other, c.baud)), None),
    };
    let controller = SerialController::new(opener, dialect(c), backoff, expect);
    Ok(OpenedController { controller: Arc::new(Mutex::new(controller)), emulator })
}

//! Firmware emulators: a board model for each dialect, running in a thread on the far end of a real
//! pseudo-terminal pair, with fault knobs for tests.
//!
//! A rig file selects one with `[controller] port = "emulator:scanrig"` (or `emulator:horus`,
//! `emulator:fabscan`): the driver then opens a pseudo-terminal to the emulator instead of a device,
//! and every byte goes through the same serial code as with a real board. The emulator moves the
//! world through [`EmulatedHardware`], so a simulated rig sees the angles and lights the board was
//! told to set.

mod fabscan;
mod horus;
mod scanrig;

use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use serialport::{SerialPort, TTYPort};

use super::error::LinkError;
use super::port::{Opener, Transport};

/// What the emulated board's outputs drive: the simulated world, or a recorder in tests.
pub trait EmulatedHardware: Send + Sync + std::fmt::Debug {
    /// The table is at `degrees` (counter-clockwise from zero, seen from above).
    fn set_angle(&self, degrees: f64);
    /// White light `index` at `level`, 0..=1.
    fn set_light(&self, index: usize, level: f32);
    /// Line laser `index` on or off.
    fn set_laser(&self, index: usize, on: bool);
}

/// The simulated world is the hardware behind an emulated serial board: a scan through the real
/// serial code path (`port = "emulator:..."`) turns and lights the same simulated scene. A light or
/// laser index the scene does not have is a pin with nothing connected: ignored, logged at debug.
impl EmulatedHardware for crate::sim::SimWorld {
    fn set_angle(&self, degrees: f64) {
        self.set_turntable_angle(degrees);
    }

    fn set_light(&self, index: usize, level: f32) {
        if let Err(e) = crate::sim::SimWorld::set_light(self, index, level) {
            tracing::debug!(index, level, error = %e, "emulated board drives a light the scene does not have");
        }
    }

    fn set_laser(&self, index: usize, on: bool) {
        if let Err(e) = crate::sim::SimWorld::set_laser(self, index, on) {
            tracing::debug!(index, on, error = %e, "emulated board drives a laser the scene does not have");
        }
    }
}

/// One call made on a [`RecordingHardware`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum HardwareCall {
    /// `set_angle`.
    Angle(f64),
    /// `set_light`.
    Light(usize, f32),
    /// `set_laser`.
    Laser(usize, bool),
}

/// Hardware that records every call, for tests and for emulators that drive no world.
#[derive(Debug, Default)]
pub struct RecordingHardware {
    calls: Mutex<Vec<HardwareCall>>,
}

impl RecordingHardware {
    /// A new, empty recorder.
    pub fn new() -> Self {
        Self::default()
    }

    /// Every call so far.
    pub fn calls(&self) -> Vec<HardwareCall> {
        self.calls.lock().unwrap_or_else(|p| p.into_inner()).clone()
    }

    /// The last angle set, degrees.
    pub fn angle(&self) -> Option<f64> {
        self.calls().iter().rev().find_map(|c| match c {
            HardwareCall::Angle(a) => Some(*a),
            _ => None,
        })
    }

    fn push(&self, c: HardwareCall) {
        self.calls.lock().unwrap_or_else(|p| p.into_inner()).push(c);
    }
}

impl EmulatedHardware for RecordingHardware {
    fn set_angle(&self, degrees: f64) {
        self.push(HardwareCall::Angle(degrees));
    }
    fn set_light(&self, index: usize, level: f32) {
        self.push(HardwareCall::Light(index, level));
    }
    fn set_laser(&self, index: usize, on: bool) {
        self.push(HardwareCall::Laser(index, on));
    }
}

/// Fault knobs. Counters are consumed one per affected message; all of them can be changed while a
/// scan runs.
#[derive(Debug, Default)]
pub struct Faults {
    /// Garbage bytes (no newline) glued before each of the next N terminal replies.
    pub garbage_replies: AtomicU32,
    /// The next N terminal replies are not sent.
    pub drop_replies: AtomicU32,
    /// The next N terminal replies have one byte changed.
    pub corrupt_replies: AtomicU32,
    /// The next N motion completion reports are not sent.
    pub drop_completions: AtomicU32,
    /// Motion runs this many times slower (0 or 1 = normal).
    pub slow_motion: AtomicU32,
    /// The board resets itself when the N-th motion command arrives (counted from 1; 0 = never).
    pub reset_at_move: AtomicU32,
    /// The board is unplugged when the N-th motion command arrives (0 = never).
    pub unplug_at_move: AtomicU32,
    /// Unplugged: the port is gone and cannot be opened until [`Faults::replug`].
    pub unplugged: AtomicBool,
    /// An unplugged board is plugged back in by itself after this many milliseconds (0 = it stays
    /// unplugged until [`Faults::replug`]).
    pub replug_after_ms: AtomicU64,
    /// Motion commands seen so far.
    pub moves_seen: AtomicU32,
    /// While set, the board streams garbage bytes (never a line break) and sends nothing else.
    pub garbage_stream: AtomicBool,
    /// While set, every reply trickles out one byte at a time and never reaches its line break
    /// (or prompt): a byte of it per loop turn, for ever.
    pub trickle: AtomicBool,
    /// The next N terminal replies are preceded by a 64 KiB line of text (ended by a line break).
    pub overlong_replies: AtomicU32,
}

/// Length of the line [`Faults::overlong_replies`] sends, bytes.
pub const OVERLONG_LINE: usize = 64 * 1024;

impl Faults {
    /// Pull the cable.
    pub fn unplug(&self) {
        self.unplugged.store(true, Ordering::SeqCst);
    }

    /// Put the cable back.
    pub fn replug(&self) {
        self.unplugged.store(false, Ordering::SeqCst);
    }

    fn take(counter: &AtomicU32) -> bool {
        counter.fetch_update(Ordering::SeqCst, Ordering::SeqCst, |v| v.checked_sub(1)).is_ok()
    }

    fn speed_divisor(&self) -> f64 {
        f64::from(self.slow_motion.load(Ordering::SeqCst).max(1))
    }

    /// Count a motion command; say whether it triggers a reset or an unplug.
    fn on_motion(&self) -> MotionFault {
        let n = self.moves_seen.fetch_add(1, Ordering::SeqCst) + 1;
        if self.unplug_at_move.load(Ordering::SeqCst) == n {
            self.unplug();
            MotionFault::Unplug
        } else if self.reset_at_move.load(Ordering::SeqCst) == n {
            MotionFault::Reset
        } else {
            MotionFault::None
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum MotionFault {
    None,
    Reset,
    Unplug,
}

/// How the emulated board is built.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EmulatorSettings {
    /// Table speed, degrees per second.
    pub speed_deg_per_s: f64,
    /// Boot time after the port opens or a reset, during which input is lost.
    pub boot: Duration,
    /// Motor steps per turn of the table.
    pub steps_per_turn: u32,
    /// White lights (the FabScan LED ring counts as one).
    pub lights: u8,
    /// Line lasers.
    pub lasers: u8,
}

impl Default for EmulatorSettings {
    fn default() -> Self {
        EmulatorSettings {
            speed_deg_per_s: 720.0,
            boot: Duration::from_millis(20),
            steps_per_turn: 3200,
            lights: 4,
            lasers: 2,
        }
    }
}

/// Which firmware the emulator plays.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EmulatedFirmware {
    /// The scanrig protocol v1.
    Scanrig,
    /// Horus (GRBL-derived).
    Horus,
    /// FabScanPi.
    FabScan,
}

impl EmulatedFirmware {
    /// From the name after `emulator:`.
    pub fn from_name(name: &str) -> Option<Self> {
        match name {
            "scanrig" => Some(EmulatedFirmware::Scanrig),
            "horus" => Some(EmulatedFirmware::Horus),
            "fabscan" => Some(EmulatedFirmware::FabScan),
            _ => None,
        }
    }
}

/// What a model wants sent; the emulator applies the fault knobs by kind.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum OutKind {
    /// A terminal reply (`ok`, `error`, a FabScan prompt).
    Reply,
    /// A motion completion report.
    Completion,
    /// Anything else (banner, status, echo).
    Other,
}

#[derive(Debug, Default)]
struct Outbox {
    items: Vec<(OutKind, Vec<u8>)>,
}

impl Outbox {
    fn push(&mut self, kind: OutKind, bytes: Vec<u8>) {
        self.items.push((kind, bytes));
    }
}

/// What the board does after a byte.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Action {
    None,
    Reset,
}

/// A sans-IO firmware model: bytes and time in, bytes out.
trait BoardModel: Send {
    /// Boot finished: send the banner, if the firmware has one.
    fn banner(&mut self, out: &mut Outbox);
    /// One byte from the host.
    fn byte(&mut self, b: u8, now: Instant, out: &mut Outbox, faults: &Faults) -> Action;
    /// Time passes.
    fn tick(&mut self, now: Instant, out: &mut Outbox, faults: &Faults);
}

fn new_model(fw: EmulatedFirmware, s: EmulatorSettings, hw: Arc<dyn EmulatedHardware>) -> Box<dyn BoardModel> {
    match fw {
        EmulatedFirmware::Scanrig => Box::new(scanrig::ScanrigBoard::new(s, hw)),
        EmulatedFirmware::Horus => Box::new(horus::HorusBoard::new(s, hw)),
        EmulatedFirmware::FabScan => Box::new(fabscan::FabScanBoard::new(s, hw)),
    }
}

/// Motion in progress, shared by the models: linear from `from` to `to` steps.
#[derive(Debug, Clone, Copy)]
struct Motion {
    from: i64,
    to: i64,
    start: Instant,
    duration: Duration,
}

impl Motion {
    fn new(from: i64, to: i64, now: Instant, s: &EmulatorSettings, faults: &Faults) -> Self {
        let degrees = (to - from).unsigned_abs() as f64 * 360.0 / f64::from(s.steps_per_turn.max(1));
        let secs = degrees / s.speed_deg_per_s.max(1e-3) * faults.speed_divisor();
        Motion { from, to, start: now, duration: Duration::from_secs_f64(secs.min(3600.0)) }
    }
    fn done(&self, now: Instant) -> bool {
        now.duration_since(self.start) >= self.duration
    }
    fn position(&self, now: Instant) -> i64 {
        if self.done(now) || self.duration.is_zero() {
            return self.to;
        }
        let f = now.duration_since(self.start).as_secs_f64() / self.duration.as_secs_f64();
        self.from + ((self.to - self.from) as f64 * f).round() as i64
    }
}

#[derive(Debug)]
struct Shared {
    faults: Arc<Faults>,
    shutdown: AtomicBool,
    incoming: Mutex<Option<TTYPort>>,
}

/// A running emulator thread. Dropping it stops the thread.
#[derive(Debug)]
pub struct Emulator {
    shared: Arc<Shared>,
    thread: Option<JoinHandle<()>>,
    firmware: EmulatedFirmware,
}

impl Emulator {
    /// Start an emulator of `firmware` that drives `hardware`.
    pub fn spawn(
        firmware: EmulatedFirmware,
        settings: EmulatorSettings,
        hardware: Arc<dyn EmulatedHardware>,
    ) -> Result<Arc<Emulator>, std::io::Error> {
        let shared = Arc::new(Shared {
            faults: Arc::new(Faults::default()),
            shutdown: AtomicBool::new(false),
            incoming: Mutex::new(None),
        });
        let s2 = Arc::clone(&shared);
        let thread = std::thread::Builder::new()
            .name(format!("emulator-{firmware:?}").to_lowercase())
            .spawn(move || run(s2, firmware, settings, hardware))?;
        Ok(Arc::new(Emulator { shared, thread: Some(thread), firmware }))
    }

    /// The fault knobs.
    pub fn faults(&self) -> Arc<Faults> {
        Arc::clone(&self.shared.faults)
    }

    /// Plug a new pseudo-terminal into the board (as opening a USB port does: the board resets)
    /// and return the host's end.
    pub fn connect(&self) -> Result<TTYPort, LinkError> {
        if self.shared.faults.unplugged.load(Ordering::SeqCst) {
            return Err(LinkError::NotFound {
                spec: format!("emulator:{:?} (unplugged)", self.firmware).to_lowercase(),
            });
        }
        let (master, slave) = TTYPort::pair()
            .map_err(|e| LinkError::Open { port: "pseudo-terminal".into(), source: std::io::Error::from(e) })?;
        *self.shared.incoming.lock().unwrap_or_else(|p| p.into_inner()) = Some(master);
        Ok(slave)
    }
}

impl Drop for Emulator {
    fn drop(&mut self) {
        self.shared.shutdown.store(true, Ordering::SeqCst);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// Opens connections to an [`Emulator`].
#[derive(Debug, Clone)]
pub struct EmulatorOpener {
    emulator: Arc<Emulator>,
}

impl EmulatorOpener {
    /// An opener for `emulator`.
    pub fn new(emulator: Arc<Emulator>) -> Self {
        EmulatorOpener { emulator }
    }
}

impl Opener for EmulatorOpener {
    fn open(&mut self) -> Result<Box<dyn Transport>, LinkError> {
        Ok(Box::new(self.emulator.connect()?))
    }
    fn describe(&self) -> String {
        format!("emulator:{:?}", self.emulator.firmware).to_lowercase()
    }
}

const GARBAGE: &[u8] = b"\x00\xfe#~%\x7f";

/// What [`Faults::garbage_stream`] sends each loop turn: bytes of no dialect, no line break, no prompt.
const GARBAGE_STREAM: [u8; 64] = [0xA5; 64];

fn run(shared: Arc<Shared>, fw: EmulatedFirmware, settings: EmulatorSettings, hw: Arc<dyn EmulatedHardware>) {
    let faults = Arc::clone(&shared.faults);
    let mut master: Option<TTYPort> = None;
    let mut model = new_model(fw, settings, Arc::clone(&hw));
    let mut boot_until: Option<Instant> = None;
    let mut out = Outbox::default();
    let mut buf = [0u8; 256];
    let mut unplugged_since: Option<Instant> = None;
    while !shared.shutdown.load(Ordering::SeqCst) {
        if faults.unplugged.load(Ordering::SeqCst) {
            let since = *unplugged_since.get_or_insert_with(Instant::now);
            let after = faults.replug_after_ms.load(Ordering::SeqCst);
            if after > 0 && since.elapsed() >= Duration::from_millis(after) {
                tracing::debug!(after_ms = after, "emulated board plugged back in");
                faults.replug();
                unplugged_since = None;
            }
        } else {
            unplugged_since = None;
        }
        if let Some(m) = shared.incoming.lock().unwrap_or_else(|p| p.into_inner()).take() {
            // Opening the port resets the board, as the DTR line does on Arduino-class boards.
            master = Some(m);
            model = new_model(fw, settings, Arc::clone(&hw));
            boot_until = Some(Instant::now() + settings.boot);
        }
        if faults.unplugged.load(Ordering::SeqCst) && master.is_some() {
            master = None;
        }
        let Some(port) = master.as_mut() else {
            std::thread::park_timeout(Duration::from_millis(2));
            continue;
        };
        let _ = port.set_timeout(Duration::from_millis(2));
        let now = Instant::now();
        match std::io::Read::read(port, &mut buf) {
            Ok(0) => master = None,
            Ok(n) => {
                if boot_until.is_none() {
                    for &b in &buf[..n] {
                        if model.byte(b, now, &mut out, &faults) == Action::Reset {
                            out.items.clear();
                            model = new_model(fw, settings, Arc::clone(&hw));
                            boot_until = Some(now + settings.boot);
                            break;
                        }
                        if faults.unplugged.load(Ordering::SeqCst) {
                            break;
                        }
                    }
                }
            }
            Err(e) if matches!(e.kind(), std::io::ErrorKind::TimedOut | std::io::ErrorKind::WouldBlock) => {}
            Err(_) => master = None,
        }
        let now = Instant::now();
        if boot_until.is_some_and(|t| now >= t) {
            boot_until = None;
            model.banner(&mut out);
        }
        if boot_until.is_none() {
            model.tick(now, &mut out, &faults);
        }
        if faults.unplugged.load(Ordering::SeqCst) {
            out.items.clear();
            master = None;
            continue;
        }
        if faults.garbage_stream.load(Ordering::SeqCst) || faults.trickle.load(Ordering::SeqCst) {
            out.items.clear();
            let bytes: &[u8] = if faults.garbage_stream.load(Ordering::SeqCst) { &GARBAGE_STREAM } else { b"o" };
            if let Some(port) = master.as_mut() {
                if std::io::Write::write_all(port, bytes).is_err() {
                    master = None;
                }
            }
            continue;
        }
        for (kind, mut bytes) in out.items.drain(..) {
            match kind {
                OutKind::Reply if Faults::take(&faults.drop_replies) => continue,
                OutKind::Completion if Faults::take(&faults.drop_completions) => continue,
                OutKind::Reply => {
                    if Faults::take(&faults.corrupt_replies) && bytes.len() > 2 {
                        bytes[1] ^= 0x04;
                    }
                    if Faults::take(&faults.overlong_replies) {
                        let mut g = vec![b'x'; OVERLONG_LINE];
                        g.push(b'\n');
                        g.extend_from_slice(&bytes);
                        bytes = g;
                    }
                    if Faults::take(&faults.garbage_replies) {
                        let mut g = GARBAGE.to_vec();
                        g.extend_from_slice(&bytes);
                        bytes = g;
                    }
                }
                _ => {}
            }
            if let Some(port) = master.as_mut() {
                if std::io::Write::write_all(port, &bytes).is_err() {
                    master = None;
                }
            }
        }
    }
}

//! The host driver against the reference firmware (`firmware-protocol/firmware`), built with
//! avr-gcc and run in the simavr simulator with its UART bridged to a pseudo-terminal.
//!
//! Needs `avr-gcc`, `avr-libc`, `simavr` and `libsimavr-dev`. Where they are absent the test prints
//! why and passes, unless `SCANRIG_REQUIRE_FIRMWARE_SIM=1` is set (as CI does), where it fails.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

mod serial_common;

use scanrig::config::ControllerConfig;
use scanrig::devices::serial::link::Link;
use scanrig::devices::serial::port::{Opener, SystemOpener};
use scanrig::devices::serial::{open_controller, PortSpec, SerialLightArray, SerialTurntable};
use scanrig::devices::{ErrorKind, LightArray, Turntable};

const T: Duration = Duration::from_secs(3);

fn missing_tools() -> Option<String> {
    let have =
        |cmd: &str| Command::new(cmd).arg("--version").stdout(Stdio::null()).stderr(Stdio::null()).status().is_ok();
    for tool in ["make", "avr-gcc", "cc"] {
        if !have(tool) {
            return Some(format!("`{tool}` is not installed"));
        }
    }
    if !Path::new("/usr/include/simavr/sim_avr.h").exists() {
        return Some("simavr headers (libsimavr-dev) are not installed".into());
    }
    if !Path::new("/usr/lib/avr/include/avr/io.h").exists() {
        return Some("avr-libc is not installed".into());
    }
    None
}

/// Build the firmware and the bridge once per test process: the tests run in parallel and must not
/// write the same output files at the same time.
fn build() -> PathBuf {
    static BUILT: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    let out = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("firmware");
    let ok = *BUILT.get_or_init(|| {
        let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("firmware-protocol/firmware");
        Command::new("make")
            .arg("-C")
            .arg(&src)
            .arg(format!("OUT={}", out.display()))
            .status()
            .is_ok_and(|s| s.success())
    });
    assert!(ok, "building the firmware and the simavr bridge failed");
    out
}

/// The bridge process; killed when dropped.
struct Simulator {
    child: Child,
    pty: String,
}

impl Drop for Simulator {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn start(out: &Path) -> Simulator {
    let mut child = Command::new(out.join("uart_pty_bridge"))
        .arg(out.join("scanrig_uno.elf"))
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .expect("the bridge starts");
    let stdout = child.stdout.take().expect("piped stdout");
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines().map_while(Result::ok) {
            if let Some(p) = line.strip_prefix("PTY ") {
                let _ = tx.send(p.to_owned());
            }
        }
    });
    match rx.recv_timeout(Duration::from_secs(10)) {
        Ok(pty) => Simulator { child, pty },
        Err(_) => {
            let _ = child.kill();
            panic!("the simavr bridge did not report its pseudo-terminal within 10 s");
        }
    }
}

/// Whether the tools are there; panics when they are required and absent.
fn tools_present() -> bool {
    match missing_tools() {
        None => true,
        Some(reason) => {
            if std::env::var("SCANRIG_REQUIRE_FIRMWARE_SIM").is_ok_and(|v| v == "1") {
                panic!("firmware simulation test is required here, but {reason}");
            }
            eprintln!(
                "skipping the firmware-in-simavr test: {reason} (apt-get install gcc-avr avr-libc simavr libsimavr-dev)"
            );
            false
        }
    }
}

#[test]
fn reference_firmware_answers_every_replayable_spec_example_exactly() {
    if !tools_present() {
        return;
    }
    let out = build();
    let sim = start(&out);
    let spec = PortSpec::parse(&sim.pty).expect("a pty path");
    let mut link = Link::new(SystemOpener::new(spec, 115_200).open().expect("the pty opens"));
    serial_common::replay_spec_examples(&mut link, "the reference firmware", |_| false);
}

#[test]
fn serial_driver_runs_a_scan_on_the_reference_firmware_in_simavr() {
    if !tools_present() {
        return;
    }
    let out = build();
    let mut sim = start(&out);
    let cfg: ControllerConfig = toml::from_str(&format!(
        "port = \"{}\"\nsteps_per_turn = 3200\nreply_timeout_ms = 500\nboot_ms = 500\nreconnect_max_ms = 200\n",
        sim.pty
    ))
    .expect("config parses");
    let opened = open_controller(&cfg, None).expect("controller");
    let mut table = SerialTurntable::new(opened.controller.clone(), false, 3200);
    let mut lights = SerialLightArray::new(opened.controller.clone(), 4, 2);

    let started = Instant::now();
    for i in 0..8 {
        let angle = 45.0 * f64::from(i);
        table.move_to(angle, Duration::from_secs(10)).unwrap_or_else(|e| panic!("move to {angle}: {e}"));
        assert!((table.angle() - angle).abs() < 0.12, "firmware reports {} after a move to {angle}", table.angle());
        lights.set_light(i as usize % 4, 0.5, T).expect("light");
        lights.set_laser(i as usize % 2, true, T).expect("laser on");
        lights.set_laser(i as usize % 2, false, T).expect("laser off");
    }
    // Relative to the start, counter-clockwise: 10 degrees past zero again.
    table.move_to(370.0, Duration::from_secs(10)).expect("past a full turn");
    assert!((table.angle() - 370.0).abs() < 0.12);
    assert_eq!(table.steps_per_turn(), 3200);
    lights.all_off(T).expect("all off");
    table.park(T).expect("park");
    eprintln!("scan on the simulated board took {:?}", started.elapsed());

    // Pull the plug: the simulator goes away, and the driver says so with the right kind, quickly.
    let _ = sim.child.kill();
    let _ = sim.child.wait();
    let t0 = Instant::now();
    let err = table.move_to(0.0, Duration::from_secs(5)).expect_err("the board is gone");
    assert!(matches!(err.kind(), ErrorKind::Disconnected | ErrorKind::Timeout), "{err}");
    assert!(t0.elapsed() < Duration::from_secs(5), "disconnect took {:?} to notice", t0.elapsed());
}

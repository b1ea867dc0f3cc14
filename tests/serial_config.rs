//! The `[controller]` section and `kind = "serial"` devices: parsing, validation and building a rig
//! whose turntable and lights share one emulated board.

use std::path::Path;
use std::time::Duration;

use scanrig::config::ConfigError;
use scanrig::devices::build_rig;
use scanrig::rigfile;

fn rig(controller: &str, turntable_kind: &str, lights_kind: &str) -> String {
    format!(
        r#"
[rig]
name = "serial test rig"

[turntable]
kind = "{turntable_kind}"

[lights]
kind = "{lights_kind}"
[[lights.light]]
position_m = [0.3, 0.0, 0.3]
[[lights.laser]]
origin_m = [0.2, 0.2, 0.1]
plane_normal = [1.0, -1.0, 0.0]

{controller}

[camera]
kind = "sim"
width = 64
height = 48
[camera.calibration.intrinsics]
fx = 80.0
fy = 80.0
cx = 32.0
cy = 24.0
[camera.calibration.pose]
eye_m = [0.5, 0.0, 0.1]
target_m = [0.0, 0.0, 0.04]

[sim]
scene = "sphere"

[scan]
positions = 8

[reconstruction]
method = "space-carving"
bbox_min_m = [-0.05, -0.05, 0.0]
bbox_max_m = [0.05, 0.05, 0.1]
resolution = 32
"#
    )
}

fn problems(text: &str) -> Vec<String> {
    match rigfile::parse(text, Path::new("rig.toml")) {
        Ok(_) => Vec::new(),
        Err(ConfigError::Invalid { problems, .. }) => {
            problems.iter().map(|p| format!("{}: {}", p.key, p.message)).collect()
        }
        Err(e) => panic!("expected a parse to succeed or fail validation, got {e}"),
    }
}

const EMULATED: &str = "[controller]\nport = \"emulator:scanrig\"\nreply_timeout_ms = 200\nboot_ms = 300\n[controller.emulator]\nboot_ms = 10\nspeed_deg_per_s = 3600\n";

#[test]
fn serial_rig_parses_and_builds_one_shared_controller() {
    let text = rig(EMULATED, "serial", "serial");
    let cfg = rigfile::parse(&text, Path::new("rig.toml")).unwrap_or_else(|e| panic!("{e}"));
    let mut rig = build_rig(&cfg).unwrap_or_else(|e| panic!("{e}"));
    let serial = rig.serial.as_ref().expect("the rig has a serial controller");
    assert!(serial.emulator.is_some());
    rig.turntable.move_to(90.0, Duration::from_secs(5)).expect("turntable moves through the emulator");
    let lights = rig.lights.as_mut().expect("lights");
    assert_eq!((lights.light_count(), lights.laser_count()), (1, 1));
    lights.set_light(0, 1.0, Duration::from_secs(2)).expect("light through the same board");
    lights.set_laser(0, true, Duration::from_secs(2)).expect("laser through the same board");
    assert!((rig.turntable.angle() - 90.0).abs() < 0.2);
}

#[test]
fn serial_devices_without_controller_are_reported() {
    let p = problems(&rig("", "serial", "serial"));
    assert!(p.iter().any(|m| m.starts_with("turntable.kind")), "{p:?}");
    assert!(p.iter().any(|m| m.starts_with("lights.kind")), "{p:?}");
}

#[test]
fn unused_controller_is_reported() {
    let p = problems(&rig(EMULATED, "sim", "sim"));
    assert!(p.iter().any(|m| m.starts_with("controller:")), "{p:?}");
}

#[test]
fn bad_controller_values_are_all_reported_at_once() {
    let controller = "[controller]\nport = \"usb:zz:0043\"\ndialect = \"horus\"\nbaud = 12\nreply_timeout_ms = 0\n";
    let p = problems(&rig(controller, "serial", "serial"));
    for key in ["controller.port", "controller.baud", "controller.steps_per_turn", "controller.reply_timeout_ms"] {
        assert!(p.iter().any(|m| m.starts_with(key)), "{key} missing from {p:?}");
    }
}

#[test]
fn emulator_port_must_match_the_dialect() {
    let controller = "[controller]\nport = \"emulator:horus\"\nsteps_per_turn = 3200\n";
    let p = problems(&rig(controller, "serial", "serial"));
    assert!(p.iter().any(|m| m.starts_with("controller.port")), "{p:?}");
}

#[test]
fn port_specs_parse() {
    use scanrig::devices::serial::PortSpec;
    assert_eq!(
        PortSpec::parse("usb:2341:0043:8573531"),
        Ok(PortSpec::Usb { vid: 0x2341, pid: 0x0043, serial: Some("8573531".into()) })
    );
    assert_eq!(PortSpec::parse("usb:1a86:7523"), Ok(PortSpec::Usb { vid: 0x1a86, pid: 0x7523, serial: None }));
    assert!(matches!(PortSpec::parse("/dev/serial/by-id/usb-Arduino-if00"), Ok(PortSpec::Path(_))));
    assert_eq!(PortSpec::parse("emulator:fabscan"), Ok(PortSpec::Emulator("fabscan".into())));
    for bad in ["", "usb:2341", "usb:2341:", "usb:12345:1", "usb:2341:0043:", "ttyUSB0"] {
        assert!(PortSpec::parse(bad).is_err(), "{bad:?} should not parse");
    }
}

#[test]
fn absent_usb_board_is_a_disconnected_state_not_a_hang() {
    let controller = "[controller]\nport = \"usb:0001:0002:no-such-board\"\nreply_timeout_ms = 100\n";
    let text = rig(controller, "serial", "serial");
    let cfg = rigfile::parse(&text, Path::new("rig.toml")).unwrap_or_else(|e| panic!("{e}"));
    let mut rig = build_rig(&cfg).expect("an absent board does not stop the rig from being built");
    let err = rig.turntable.move_to(10.0, Duration::from_secs(1)).expect_err("no such board");
    assert_eq!(err.kind(), scanrig::devices::ErrorKind::Disconnected, "{err}");
}

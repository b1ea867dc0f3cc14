//! The serial drivers against firmware emulators on real pseudo-terminals: a scan through each
//! dialect, and every fault knob of the scanrig emulator. Every wait is bounded by the drivers'
//! own timeouts; no test sleeps to let things settle.

mod serial_common;

use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::{Duration, Instant};

use scanrig::config::ControllerConfig;
use scanrig::devices::serial::{
    emulator::HardwareCall, open_controller, EmulatedHardware, LinkState, OpenedController, RecordingHardware,
    SerialLightArray, SerialTurntable,
};
use scanrig::devices::{ErrorKind, LightArray, Turntable};

const MOVE_TIMEOUT: Duration = Duration::from_secs(5);
const T: Duration = Duration::from_secs(2);

fn controller_config(dialect: &str, extra: &str) -> ControllerConfig {
    let steps = if dialect == "scanrig" { "" } else { "steps_per_turn = 3200" };
    let text = format!(
        "port = \"emulator:{dialect}\"\ndialect = \"{dialect}\"\n{steps}\nreply_timeout_ms = 300\nboot_ms = 300\n\
         reconnect_max_ms = 200\n{extra}\n[emulator]\nspeed_deg_per_s = 3600\nboot_ms = 10\n"
    );
    toml::from_str(&text).expect("test controller config parses")
}

struct Board {
    opened: OpenedController,
    hw: Arc<RecordingHardware>,
    table: SerialTurntable,
    lights: SerialLightArray,
}

fn board(dialect: &str, extra: &str) -> Board {
    let cfg = controller_config(dialect, extra);
    let hw = Arc::new(RecordingHardware::new());
    let opened = open_controller(&cfg, Some(Arc::clone(&hw) as Arc<dyn EmulatedHardware>)).expect("controller opens");
    let table = SerialTurntable::new(opened.controller.clone(), false, 3200);
    let (lights, lasers) = match dialect {
        "horus" => (0, 2),
        "fabscan" => (1, 2),
        _ => (4, 2),
    };
    let lights = SerialLightArray::new(opened.controller.clone(), lights, lasers);
    Board { opened, hw, table, lights }
}

fn faults(b: &Board) -> Arc<scanrig::devices::serial::Faults> {
    b.opened.emulator.as_ref().expect("an emulator port starts an emulator").faults()
}

/// A scan: at each of `positions` angles, move, switch a light (when there is one) and a laser,
/// and "capture" (record the angle the world is at). Returns the captures made before any error.
fn scan(b: &mut Board, positions: u32) -> (Vec<f64>, Result<(), scanrig::devices::DeviceError>) {
    let mut captured = Vec::new();
    let result = (|| {
        for i in 0..positions {
            let angle = 360.0 * f64::from(i) / f64::from(positions);
            b.table.move_to(angle, MOVE_TIMEOUT)?;
            if b.lights.light_count() > 0 {
                b.lights.set_light(0, 1.0, T)?;
            }
            b.lights.set_laser(i as usize % 2, true, T)?;
            captured.push(b.hw.angle().unwrap_or(0.0));
            b.lights.set_laser(i as usize % 2, false, T)?;
        }
        Ok(())
    })();
    (captured, result)
}

fn assert_full_scan(dialect: &str) {
    let mut b = board(dialect, "");
    let (captured, result) = scan(&mut b, 12);
    result.unwrap_or_else(|e| panic!("{dialect}: scan failed: {e}"));
    let expected: Vec<f64> = (0..12).map(|i| f64::from(i) * 30.0).collect();
    assert_eq!(captured.len(), 12);
    for (got, want) in captured.iter().zip(&expected) {
        assert!((got - want).abs() < 0.2, "{dialect}: world at {got} degrees, expected {want}: {captured:?}");
    }
    assert!((b.table.angle() - 330.0).abs() < 0.2, "{dialect}: driver reports {}", b.table.angle());
    let calls = b.hw.calls();
    assert!(calls.contains(&HardwareCall::Laser(1, true)), "{dialect}: laser 1 never switched on");
    assert!(calls.contains(&HardwareCall::Laser(0, false)), "{dialect}: laser 0 never switched off");
    b.lights.all_off(T).unwrap_or_else(|e| panic!("{dialect}: all_off failed: {e}"));
    b.table.park(T).unwrap_or_else(|e| panic!("{dialect}: park failed: {e}"));
}

#[test]
fn serial_scan_through_scanrig_emulator() {
    assert_full_scan("scanrig");
}

#[test]
fn serial_scan_through_horus_emulator() {
    assert_full_scan("horus");
}

#[test]
fn serial_scan_through_fabscan_emulator() {
    assert_full_scan("fabscan");
}

#[test]
fn scanrig_board_reports_its_own_steps_per_turn_and_lights_levels() {
    let mut b = board("scanrig", "");
    b.table.move_to(90.0, MOVE_TIMEOUT).expect("move");
    assert_eq!(b.table.steps_per_turn(), 3200);
    b.lights.set_light(3, 0.5, T).expect("light 3");
    assert!(b.hw.calls().iter().any(|c| matches!(c, HardwareCall::Light(3, l) if (l - 128.0 / 255.0).abs() < 1e-3)));
    let err = b.lights.set_light(4, 1.0, T).expect_err("there are 4 lights");
    assert_eq!(err.kind(), ErrorKind::InvalidConfig);
}

#[test]
fn garbage_before_replies_is_survived() {
    let mut b = board("scanrig", "");
    faults(&b).garbage_replies.store(5, Ordering::SeqCst);
    let (captured, result) = scan(&mut b, 4);
    result.expect("garbage costs a retry, not the scan");
    assert_eq!(captured.len(), 4);
    assert_eq!(faults(&b).garbage_replies.load(Ordering::SeqCst), 0, "the garbage was really sent");
}

#[test]
fn dropped_and_corrupted_replies_are_retried_without_acting_twice() {
    let mut b = board("scanrig", "");
    b.table.move_to(0.0, MOVE_TIMEOUT).expect("connect");
    let f = faults(&b);
    let moves_before = f.moves_seen.load(Ordering::SeqCst);
    f.drop_replies.store(1, Ordering::SeqCst);
    b.table.move_to(45.0, MOVE_TIMEOUT).expect("a dropped reply is recovered by resending the line");
    f.corrupt_replies.store(1, Ordering::SeqCst);
    b.table.move_to(90.0, MOVE_TIMEOUT).expect("a corrupted reply is recovered by resending the line");
    assert_eq!(f.moves_seen.load(Ordering::SeqCst) - moves_before, 2, "a resent MOVE was executed twice");
    assert!((b.table.angle() - 90.0).abs() < 0.2);
}

#[test]
fn missed_completion_report_is_recovered_by_status() {
    let mut b = board("scanrig", "");
    b.table.move_to(0.0, MOVE_TIMEOUT).expect("connect");
    faults(&b).drop_completions.store(1, Ordering::SeqCst);
    let started = Instant::now();
    b.table.move_to(120.0, MOVE_TIMEOUT).expect("status polling finds the finished move");
    assert!(started.elapsed() < Duration::from_secs(2), "recovery took {:?}", started.elapsed());
    assert!((b.table.angle() - 120.0).abs() < 0.2);
}

#[test]
fn slow_motion_times_out_with_a_typed_error_and_stops_the_table() {
    let mut b = board("scanrig", "");
    b.table.move_to(0.0, MOVE_TIMEOUT).expect("connect");
    faults(&b).slow_motion.store(1000, Ordering::SeqCst);
    let started = Instant::now();
    let err = b.table.move_to(180.0, Duration::from_millis(400)).expect_err("180 degrees at 3.6 deg/s takes 50 s");
    assert_eq!(err.kind(), ErrorKind::Timeout, "{err}");
    assert!(started.elapsed() < Duration::from_secs(2), "timeout took {:?}", started.elapsed());
    // The board was told to stop; the next move works at normal speed.
    faults(&b).slow_motion.store(1, Ordering::SeqCst);
    b.table.move_to(10.0, MOVE_TIMEOUT).expect("the link still works after a timeout");
}

#[test]
fn board_reset_mid_scan_fails_the_scan_keeps_frames_and_reconnects() {
    let mut b = board("scanrig", "");
    faults(&b).reset_at_move.store(3, Ordering::SeqCst);
    let (captured, result) = scan(&mut b, 6);
    let err = result.expect_err("a reset loses the table position: the scan must fail");
    assert_eq!(err.kind(), ErrorKind::Disconnected, "{err}");
    assert_eq!(captured.len(), 2, "frames before the reset are kept");
    // The next command reconnects (backoff permitting) and the board works again.
    let deadline = Instant::now() + Duration::from_secs(3);
    scanrig::devices::serial::controller::lock(&b.opened.controller).reconnect(deadline).expect("reconnects");
    b.table.move_to(30.0, MOVE_TIMEOUT).expect("moves after the reset");
}

#[test]
fn unplug_is_a_state_and_replug_reconnects_with_backoff() {
    let mut b = board("scanrig", "");
    let f = faults(&b);
    f.unplug_at_move.store(2, Ordering::SeqCst);
    let started = Instant::now();
    let (captured, result) = scan(&mut b, 6);
    let err = result.expect_err("unplugged mid-scan");
    assert_eq!(err.kind(), ErrorKind::Disconnected, "{err}");
    assert!(started.elapsed() < Duration::from_secs(3), "unplug detection took {:?}", started.elapsed());
    assert_eq!(captured.len(), 1);
    let state = scanrig::devices::serial::controller::lock(&b.opened.controller).state();
    assert!(matches!(state, LinkState::Disconnected { .. }), "{state:?}");

    // While unplugged, calls fail fast with the same kind; nothing hangs.
    let t0 = Instant::now();
    for _ in 0..3 {
        let e = b.table.move_to(10.0, MOVE_TIMEOUT).expect_err("still unplugged");
        assert_eq!(e.kind(), ErrorKind::Disconnected);
    }
    assert!(t0.elapsed() < Duration::from_secs(2));
    let short = Instant::now() + Duration::from_millis(300);
    assert!(scanrig::devices::serial::controller::lock(&b.opened.controller).reconnect(short).is_err());

    f.replug();
    let deadline = Instant::now() + Duration::from_secs(3);
    scanrig::devices::serial::controller::lock(&b.opened.controller).reconnect(deadline).expect("back after replug");
    b.table.move_to(30.0, MOVE_TIMEOUT).expect("moves after replug");
}

#[test]
fn steps_per_turn_mismatch_is_refused() {
    let cfg: ControllerConfig = toml::from_str(
        "port = \"emulator:scanrig\"\nsteps_per_turn = 1600\nreply_timeout_ms = 300\nboot_ms = 300\n\
         [emulator]\nsteps_per_turn = 3200\nboot_ms = 10\n",
    )
    .expect("parses");
    let opened = open_controller(&cfg, None).expect("opens");
    let mut table = SerialTurntable::new(opened.controller.clone(), false, 1600);
    let err = table.move_to(10.0, MOVE_TIMEOUT).expect_err("board has 3200 steps per turn");
    assert_eq!(err.kind(), ErrorKind::InvalidConfig, "{err}");
}

#[test]
fn horus_step_scaling_mismatch_is_refused() {
    let cfg: ControllerConfig = toml::from_str(
        "port = \"emulator:horus\"\ndialect = \"horus\"\nsteps_per_turn = 1600\nreply_timeout_ms = 300\nboot_ms = 300\n\
         [emulator]\nsteps_per_turn = 3200\nboot_ms = 10\n",
    )
    .expect("parses");
    let opened = open_controller(&cfg, None).expect("opens");
    let mut table = SerialTurntable::new(opened.controller.clone(), false, 1600);
    let err = table.move_to(10.0, MOVE_TIMEOUT).expect_err("$100 says 3200 steps per turn");
    assert_eq!(err.kind(), ErrorKind::InvalidConfig, "{err}");
}

#[test]
fn reverse_turntable_negates_angles_on_the_wire() {
    let mut b = board("scanrig", "");
    let mut rev = SerialTurntable::new(b.opened.controller.clone(), true, 3200);
    rev.move_to(90.0, MOVE_TIMEOUT).expect("move");
    assert!((b.hw.angle().unwrap_or(0.0) + 90.0).abs() < 0.2, "board turned to {:?}", b.hw.angle());
    assert!((rev.angle() - 90.0).abs() < 0.2);
    b.table.move_to(0.0, MOVE_TIMEOUT).expect("move back");
}

#[test]
fn horus_lost_ok_is_a_bounded_typed_timeout() {
    let mut b = board("horus", "");
    b.table.move_to(0.0, MOVE_TIMEOUT).expect("connect");
    faults(&b).drop_replies.store(1, Ordering::SeqCst);
    let t0 = Instant::now();
    let err = b.table.move_to(30.0, MOVE_TIMEOUT).expect_err("Horus cannot resend a G1 safely");
    assert_eq!(err.kind(), ErrorKind::Timeout, "{err}");
    assert!(t0.elapsed() < Duration::from_secs(2), "took {:?}", t0.elapsed());
}

#[test]
fn horus_reset_mid_scan_is_a_disconnect() {
    let mut b = board("horus", "");
    faults(&b).reset_at_move.store(2, Ordering::SeqCst);
    let (captured, result) = scan(&mut b, 4);
    let err = result.expect_err("reset mid-scan");
    assert_eq!(err.kind(), ErrorKind::Disconnected, "{err}");
    assert_eq!(captured.len(), 1);
}

#[test]
fn fabscan_unplug_then_replug_reconnects() {
    let mut b = board("fabscan", "");
    let f = faults(&b);
    f.unplug_at_move.store(3, Ordering::SeqCst);
    let (captured, result) = scan(&mut b, 6);
    let err = result.expect_err("unplugged");
    assert_eq!(err.kind(), ErrorKind::Disconnected, "{err}");
    // Position 0 needs no motion on FabScan (relative moves), so the third move is position 3.
    assert_eq!(captured.len(), 3);
    f.replug();
    let deadline = Instant::now() + Duration::from_secs(5);
    scanrig::devices::serial::controller::lock(&b.opened.controller).reconnect(deadline).expect("back");
    b.table.move_to(0.0, MOVE_TIMEOUT).expect("moves after replug");
}

#[test]
fn scanrig_board_watchdog_switches_everything_off_when_the_host_goes_silent() {
    let mut b = board("scanrig", "watchdog_ms = 100");
    b.lights.set_laser(0, true, T).expect("laser on");
    // Wait, bounded, for the board's own watchdog to act; the host sends nothing meanwhile.
    let deadline = Instant::now() + Duration::from_secs(2);
    let off = |calls: &[HardwareCall]| {
        let on_at = calls.iter().position(|c| *c == HardwareCall::Laser(0, true));
        on_at.is_some_and(|i| calls[i..].contains(&HardwareCall::Laser(0, false)))
    };
    while !off(&b.hw.calls()) {
        assert!(Instant::now() < deadline, "the watchdog never switched the laser off: {:?}", b.hw.calls());
        std::thread::park_timeout(Duration::from_millis(10));
    }
    // The host notices nothing wrong with the link and can switch it on again.
    b.lights.set_laser(0, true, T).expect("laser on again");
}

#[test]
fn homing_without_end_stop_is_unsupported() {
    let mut b = board("scanrig", "");
    let err = b.table.home(T).expect_err("the emulated board has no end stop");
    assert_eq!(err.kind(), ErrorKind::Unsupported, "{err}");
    b.table.move_to(15.0, MOVE_TIMEOUT).expect("the link is fine after a refusal");
}

#[test]
fn scanrig_emulator_answers_every_replayable_spec_example_exactly() {
    let hw: Arc<dyn EmulatedHardware> = Arc::new(RecordingHardware::new());
    let settings = scanrig::devices::serial::EmulatorSettings { speed_deg_per_s: 3600.0, ..Default::default() };
    let emu =
        scanrig::devices::serial::Emulator::spawn(scanrig::devices::serial::EmulatedFirmware::Scanrig, settings, hw)
            .expect("emulator starts");
    let port = emu.connect().expect("pty pair");
    let mut link = scanrig::devices::serial::link::Link::new(Box::new(port));
    // The emulator names itself differently from the reference firmware in the spec: skip `ID`.
    serial_common::replay_spec_examples(&mut link, "the scanrig emulator", |line| line == "ID");
}

#[test]
fn field_dialects_survive_garbage_before_replies() {
    for dialect in ["horus", "fabscan"] {
        let mut b = board(dialect, "");
        faults(&b).garbage_replies.store(4, Ordering::SeqCst);
        let (captured, result) = scan(&mut b, 4);
        result.unwrap_or_else(|e| panic!("{dialect}: {e}"));
        assert_eq!(captured.len(), 4, "{dialect}");
        assert_eq!(faults(&b).garbage_replies.load(Ordering::SeqCst), 0, "{dialect}: the garbage was sent");
    }
}

#[test]
fn config_fault_knobs_unplug_once_and_replug_by_themselves() {
    let cfg = controller_config("scanrig", "");
    let text = "port = \"emulator:scanrig\"\nreply_timeout_ms = 300\nboot_ms = 300\nreconnect_max_ms = 200\n\
                [emulator]\nspeed_deg_per_s = 3600\nboot_ms = 10\nunplug_at_move = 2\nreplug_after_ms = 400\n";
    let knobs: ControllerConfig = toml::from_str(text).expect("knobs parse");
    assert_eq!((knobs.emulator.unplug_at_move, knobs.emulator.replug_after_ms), (2, 400));
    assert_eq!((cfg.emulator.unplug_at_move, cfg.emulator.replug_after_ms, cfg.emulator.reset_at_move), (0, 0, 0));
    let hw = Arc::new(RecordingHardware::new());
    let opened = open_controller(&knobs, Some(hw as Arc<dyn EmulatedHardware>)).expect("controller opens");
    let mut table = SerialTurntable::new(opened.controller.clone(), false, 3200);
    table.move_to(10.0, MOVE_TIMEOUT).expect("first move");
    let unplugged_at = Instant::now();
    let e = table.move_to(20.0, MOVE_TIMEOUT).expect_err("unplugged at the 2nd move");
    assert_eq!(e.kind(), ErrorKind::Disconnected, "{e}");
    // Still out well before replug_after_ms, back after it without anyone calling replug().
    let early = Instant::now() + Duration::from_millis(100);
    assert!(scanrig::devices::serial::controller::lock(&opened.controller).reconnect(early).is_err());
    let deadline = Instant::now() + Duration::from_secs(3);
    scanrig::devices::serial::controller::lock(&opened.controller).reconnect(deadline).expect("replugged by itself");
    assert!(unplugged_at.elapsed() >= Duration::from_millis(400), "replugged too early: {:?}", unplugged_at.elapsed());
    // The unplug happens once: later moves (the 3rd, 4th, ...) go through.
    for deg in [30.0, 40.0, 50.0] {
        table.move_to(deg, MOVE_TIMEOUT).expect("moves after the replug");
    }
}

/// Reconnect `b`'s controller once the fault is cleared and check that it moves again.
fn recovers(b: &mut Board, dialect: &str) {
    let deadline = Instant::now() + Duration::from_secs(5);
    let mut c = scanrig::devices::serial::controller::lock(&b.opened.controller);
    if !matches!(c.state(), LinkState::Connected) {
        c.reconnect(deadline).unwrap_or_else(|e| panic!("{dialect}: no reconnect after the fault: {e}"));
    }
    drop(c);
    // Bytes the fault left in flight may cost the first command (a typed error); by the third the
    // line is quiet again.
    let mut last = None;
    for _ in 0..3 {
        match b.table.move_to(10.0, MOVE_TIMEOUT) {
            Ok(_) => return,
            Err(e) => {
                assert!(matches!(e.kind(), ErrorKind::Timeout | ErrorKind::Protocol), "{dialect}: {e}");
                last = Some(e);
            }
        }
    }
    panic!("{dialect}: no move after the fault: {last:?}");
}

#[test]
fn a_board_streaming_garbage_for_ever_gives_a_typed_error_and_bounded_buffers() {
    for dialect in ["scanrig", "horus", "fabscan"] {
        let mut b = board(dialect, "");
        b.table.move_to(0.0, MOVE_TIMEOUT).unwrap_or_else(|e| panic!("{dialect}: connect: {e}"));
        let f = faults(&b);
        f.garbage_stream.store(true, Ordering::SeqCst);
        let err = b.table.move_to(90.0, MOVE_TIMEOUT).expect_err("no reply can get through the garbage");
        eprintln!("{dialect}: garbage for ever -> {:?}: {err}", err.kind());
        assert!(matches!(err.kind(), ErrorKind::Timeout | ErrorKind::Protocol), "{dialect}: {err}");
        if dialect == "fabscan" {
            // The prompt reader stops at its size cap instead of buffering until the deadline.
            let text = scanrig::service::rig::error_chain(&err);
            assert!(text.contains("bytes without the `>` prompt"), "{text}");
        }
        f.garbage_stream.store(false, Ordering::SeqCst);
        recovers(&mut b, dialect);
    }
}

#[test]
fn replies_that_trickle_without_a_line_break_time_out() {
    for dialect in ["scanrig", "horus", "fabscan"] {
        let mut b = board(dialect, "");
        b.table.move_to(0.0, MOVE_TIMEOUT).unwrap_or_else(|e| panic!("{dialect}: connect: {e}"));
        let f = faults(&b);
        f.trickle.store(true, Ordering::SeqCst);
        let err = b.lights.set_laser(0, true, T).expect_err("a reply that never ends");
        eprintln!("{dialect}: trickle -> {:?}: {err}", err.kind());
        assert!(matches!(err.kind(), ErrorKind::Timeout | ErrorKind::Protocol), "{dialect}: {err}");
        f.trickle.store(false, Ordering::SeqCst);
        recovers(&mut b, dialect);
    }
}

#[test]
fn an_overlong_line_before_a_reply_is_dropped_or_refused_never_buffered_whole() {
    for dialect in ["scanrig", "horus", "fabscan"] {
        let mut b = board(dialect, "");
        b.table.move_to(0.0, MOVE_TIMEOUT).unwrap_or_else(|e| panic!("{dialect}: connect: {e}"));
        let f = faults(&b);
        f.overlong_replies.store(1, Ordering::SeqCst);
        let result = b.lights.set_laser(0, true, T);
        eprintln!("{dialect}: a {} byte line -> {result:?}", scanrig::devices::serial::emulator::OVERLONG_LINE);
        assert_eq!(f.overlong_replies.load(Ordering::SeqCst), 0, "{dialect}: the line was sent");
        match dialect {
            // Line-based dialects skip the overlong line (resending where the dialect allows).
            "scanrig" | "horus" => result.unwrap_or_else(|e| panic!("{dialect}: {e}")),
            // FabScan has no lines, only a prompt: the cap refuses it as a protocol error.
            _ => {
                let err = result.expect_err("over the prompt reader's cap");
                assert_eq!(err.kind(), ErrorKind::Protocol, "{err}");
            }
        }
        recovers(&mut b, dialect);
    }
}

#[test]
fn field_dialects_dropped_and_corrupted_replies_are_bounded_typed_errors() {
    for dialect in ["horus", "fabscan"] {
        for knob in ["drop", "corrupt"] {
            let mut b = board(dialect, "");
            b.table.move_to(0.0, MOVE_TIMEOUT).unwrap_or_else(|e| panic!("{dialect}: connect: {e}"));
            let f = faults(&b);
            let counter = if knob == "drop" { &f.drop_replies } else { &f.corrupt_replies };
            counter.store(1, Ordering::SeqCst);
            let result = b.lights.set_laser(0, true, T);
            assert_eq!(counter.load(Ordering::SeqCst), 0, "{dialect} {knob}: the fault was applied");
            eprintln!("{dialect}: {knob}ped reply -> {result:?}");
            if let Err(e) = &result {
                assert!(matches!(e.kind(), ErrorKind::Timeout | ErrorKind::Protocol), "{dialect} {knob}: {e}");
            }
            recovers(&mut b, dialect);
        }
    }
}

#[test]
fn horus_port_vanishing_in_the_middle_of_a_read_is_a_disconnect() {
    let mut b = board("horus", "");
    // The cable goes when the second motion command arrives, while the host waits for its reply.
    faults(&b).unplug_at_move.store(2, Ordering::SeqCst);
    let (captured, result) = scan(&mut b, 4);
    let err = result.expect_err("unplugged mid-read");
    assert_eq!(err.kind(), ErrorKind::Disconnected, "{err}");
    assert_eq!(captured.len(), 1);
    faults(&b).replug();
    recovers(&mut b, "horus");
}

//! Property tests for every parser that takes outside input: rig TOML, calibration files, par and
//! P-matrix files, the serial decoders of each dialect (over a scripted byte transport), and the
//! HTTP request bodies. Each must answer any input with a value or a typed error: no panic, no
//! endless loop, bounded buffers.

use std::io::{Read, Write};
use std::path::Path;
use std::time::Duration;

use proptest::prelude::*;
use scanrig::devices::serial::dialect::fabscan::FabScanDialect;
use scanrig::devices::serial::dialect::horus::HorusDialect;
use scanrig::devices::serial::dialect::scanrig::{SafetyLimits, ScanrigDialect};
use scanrig::devices::serial::link::Link;
use scanrig::devices::serial::port::Transport;
use scanrig::devices::serial::{Dialect, Timing};

fn shipped(name: &str) -> String {
    std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("config/rigs").join(name)).expect("rig")
}

/// A text edited at random: lines dropped or duplicated, bytes replaced.
fn mutated(base: String) -> impl Strategy<Value = String> {
    let n = base.len().max(1);
    proptest::collection::vec((0..n, any::<u8>(), 0u8..4), 0..12).prop_map(move |edits| {
        let mut bytes = base.clone().into_bytes();
        for (at, b, op) in edits {
            let at = at % bytes.len().max(1);
            match op {
                0 => bytes[at] = b,
                1 => {
                    bytes.insert(at, b);
                }
                2 => {
                    bytes.remove(at);
                }
                _ => {
                    // Duplicate the line `at` is on.
                    let start = bytes[..at].iter().rposition(|&c| c == b'\n').map_or(0, |p| p + 1);
                    let end = bytes[at..].iter().position(|&c| c == b'\n').map_or(bytes.len(), |p| at + p + 1);
                    let line = bytes[start..end].to_vec();
                    bytes.splice(start..start, line);
                }
            }
            if bytes.is_empty() {
                bytes.push(b'\n');
            }
        }
        String::from_utf8_lossy(&bytes).into_owned()
    })
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 200, ..ProptestConfig::default() })]

    #[test]
    fn rig_toml_never_panics(text in mutated(shipped("simulated.toml"))) {
        let _ = scanrig::rigfile::parse(&text, Path::new("rig.toml"));
    }

    #[test]
    fn serial_rig_toml_never_panics(text in mutated(shipped("sim-serial.toml"))) {
        let _ = scanrig::rigfile::parse(&text, Path::new("rig.toml"));
    }

    #[test]
    fn arbitrary_text_as_a_rig_file_never_panics(text in "(\\PC|\n|\\[|\\]|=|\"){0,400}") {
        let _ = scanrig::rigfile::parse(&text, Path::new("rig.toml"));
    }

    #[test]
    fn calibration_files_never_panic(text in mutated(calibration_text())) {
        let _ = scanrig::calibration::file::CalibrationFile::parse(&text, Path::new("calibration.toml"));
    }

    #[test]
    fn par_files_never_panic(text in mutated(PAR.to_owned())) {
        let _ = scanrig::dataset::parse_par(&text, Path::new("set_par.txt"));
    }

    #[test]
    fn projection_files_never_panic(text in mutated(PROJECTIONS.to_owned())) {
        let _ = scanrig::dataset::parse_projections(&text, Path::new("p.txt"));
    }

    #[test]
    fn numbers_anywhere_in_par_files_never_panic(
        values in proptest::collection::vec(prop_oneof![any::<f64>().prop_map(|v| v.to_string()), "[-+0-9.eE]{0,8}", Just("nan".to_owned()), Just("inf".to_owned())], 21),
        count in "[0-9]{0,3}",
    ) {
        let text = format!("{count}\nimg.png {}\n", values.join(" "));
        let _ = scanrig::dataset::parse_par(&text, Path::new("set_par.txt"));
        let text = format!("img.png {}\n", values[..12].join(" "));
        let _ = scanrig::dataset::parse_projections(&text, Path::new("p.txt"));
    }

    #[test]
    fn start_request_bodies_never_panic(body in proptest::collection::vec(any::<u8>(), 0..200)) {
        let _ = serde_json::from_slice::<scanrig::service::jobs::StartRequest>(&body);
    }

    #[test]
    fn start_request_json_shapes_never_panic(
        positions in proptest::option::of(any::<i64>()),
        lights in proptest::option::of(proptest::collection::vec(any::<i64>(), 0..80)),
        method in proptest::option::of("[a-z-]{0,20}"),
    ) {
        let body = serde_json::json!({"positions": positions, "lights": lights, "method": method});
        let _ = serde_json::from_value::<scanrig::service::jobs::StartRequest>(body);
    }

    #[test]
    fn scanrig_dialect_answers_any_bytes(script in proptest::collection::vec(any::<u8>(), 0..600)) {
        exercise(ScanrigDialect::new(timing(), true, SafetyLimits::default()), script);
    }

    #[test]
    fn scanrig_dialect_answers_line_shaped_noise(lines in proptest::collection::vec("(ok|err|evt|id|[A-Z]{1,4})( [ -~]{0,30})?", 0..20)) {
        exercise(ScanrigDialect::new(timing(), false, SafetyLimits::default()), lines.join("\n").into_bytes());
    }

    #[test]
    fn horus_dialect_answers_any_bytes(script in proptest::collection::vec(any::<u8>(), 0..600)) {
        exercise(HorusDialect::new(timing(), 3200, 2, 90.0), script);
    }

    #[test]
    fn horus_dialect_answers_line_shaped_noise(lines in proptest::collection::vec("(ok|error:[ -~]{0,10}|ALARM:1|<Idle\\|MPos:[-0-9.,]{0,12}>|<Run[ -~]{0,20}>|[ -~]{0,40})", 0..30)) {
        exercise(HorusDialect::new(timing(), 3200, 2, 90.0), (lines.join("\r\n") + "\n").into_bytes());
    }

    #[test]
    fn fabscan_dialect_answers_any_bytes(script in proptest::collection::vec(any::<u8>(), 0..6000)) {
        exercise(FabScanDialect::new(timing(), 3200, 2, 90.0), script);
    }
}

/// Run a handshake, a move and a laser command of `dialect` against a board that sends `script`
/// (then nothing): each returns, with a value or a typed error.
fn exercise(mut dialect: impl Dialect, script: Vec<u8>) {
    let mut link = Link::new(Box::new(Scripted { script, at: 0 }));
    let _ = dialect.handshake(&mut link);
    let _ = dialect.move_to(&mut link, 800, Duration::from_millis(5));
    let _ = dialect.set_laser(&mut link, 0, true);
}

fn timing() -> Timing {
    Timing {
        // Short: the board falls silent after its script, so every call ends on a timeout, and
        // the property (an answer, never a hang) does not depend on how long the timeout is.
        reply_timeout: Duration::from_millis(3),
        retries: 1,
        boot: Duration::from_millis(1),
        handshake_attempts: 1,
        poll_interval: Duration::from_millis(1),
    }
}

/// A board that sends a fixed byte script (in small pieces) and then stays silent; every write is
/// accepted.
#[derive(Debug)]
struct Scripted {
    script: Vec<u8>,
    at: usize,
}

impl Read for Scripted {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        if self.at >= self.script.len() {
            return Err(std::io::ErrorKind::TimedOut.into());
        }
        let n = buf.len().min(17).min(self.script.len() - self.at);
        buf[..n].copy_from_slice(&self.script[self.at..self.at + n]);
        self.at += n;
        Ok(n)
    }
}

impl Write for Scripted {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        Ok(buf.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

impl Transport for Scripted {
    fn set_read_timeout(&mut self, _timeout: Duration) -> std::io::Result<()> {
        Ok(())
    }
}

const PAR: &str = "2\n\
a.png 1000 0 320 0 1000 240 0 0 1 1 0 0 0 1 0 0 0 1 0 0 1\n\
b.png 1000 0 320 0 1000 240 0 0 1 0 0 1 0 1 0 -1 0 0 0 0 1\n";

const PROJECTIONS: &str = "# name and P row by row\n\
a.png 1000 0 320 0 0 1000 240 0 0 0 1 1\n\
b.png 500 0 160 10 0 500 120 20 0 0 1 2\n";

fn calibration_text() -> String {
    // As `scanrig calibrate` writes it: camera, turntable and one light.
    "format_version = 1\n\n[camera]\nwidth_px = 640\nheight_px = 480\nfx_px = 1600.0\nfy_px = 1600.0\n\
     cx_px = 320.0\ncy_px = 240.0\nk1 = -0.05\nk2 = 0.0\nrms_px = 0.2\nviews = 12\n\n[turntable]\n\
     axis_camera = [0.0, -0.9, 0.4]\norigin_camera_m = [0.0, 0.1, 0.45]\n\
     camera_rotation = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]\n\
     camera_translation_m = [0.0, 0.0, 0.5]\ncircle_rms_m = 0.001\nmax_angle_error_deg = 0.1\nviews = 24\n\n\
     [[lights]]\nindex = 0\nposition_m = [-0.15, -0.45, 0.2]\nrms_levels = 2.0\npixels = 5000\n"
        .to_owned()
}

#[test]
fn the_unmutated_inputs_parse() {
    // The mutations start from valid inputs, so they explore near-valid files, not only noise.
    scanrig::rigfile::parse(&shipped("simulated.toml"), Path::new("rig.toml")).expect("simulated.toml");
    scanrig::calibration::file::CalibrationFile::parse(&calibration_text(), Path::new("c.toml")).expect("calibration");
    assert_eq!(scanrig::dataset::parse_par(PAR, Path::new("p_par.txt")).expect("par").len(), 2);
    assert_eq!(scanrig::dataset::parse_projections(PROJECTIONS, Path::new("p.txt")).expect("projections").len(), 2);
    let req: scanrig::service::jobs::StartRequest =
        serde_json::from_str(r#"{"positions": 8, "lights": [0, 1]}"#).expect("start request");
    assert_eq!(req.positions, Some(8));
}

use std::path::Path;

use super::*;
// The composed loader: values, the drivers' checks and the calibration file, as users load rig files.
use crate::rigfile::{load, parse};

const MINIMAL: &str = r#"
[rig]
name = "t"

[turntable]
kind = "sim"

[lights]
kind = "sim"
[[lights.light]]
position_m = [0.1, -0.4, 0.2]

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
eye_m = [0.0, -0.45, 0.2]
target_m = [0.0, 0.0, 0.03]

[sim]
scene = "sphere"

[scan]
positions = 4
lights = [0]

[reconstruction]
method = "space-carving"
bbox_min_m = [-0.05, -0.05, 0.0]
bbox_max_m = [0.05, 0.05, 0.1]
resolution = 16
"#;

#[test]
fn minimal_rig_parses() {
    let c = parse(MINIMAL, Path::new("minimal.toml")).expect("valid");
    assert_eq!(c.scan.positions, 4);
    assert_eq!(c.camera.model().width, 64);
}

#[test]
fn every_shipped_config_parses_and_validates() {
    // Everything under config/, and the example /etc/scanrig/ config shipped with the systemd unit.
    let manifest = Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut files = Vec::new();
    let mut stack = vec![manifest.join("config"), manifest.join("systemd")];
    while let Some(dir) = stack.pop() {
        for entry in std::fs::read_dir(&dir).expect("config dir readable") {
            let path = entry.expect("entry").path();
            if path.is_dir() {
                stack.push(path);
            } else if path.extension().is_some_and(|e| e == "toml") {
                files.push(path);
            }
        }
    }
    assert!(!files.is_empty(), "no config files found");
    for f in files {
        // A replication file (`scanrigd --replication`) holds only `[replication]`.
        if f.file_name().is_some_and(|n| n == "replication.toml") {
            if let Err(e) = super::replication::load_file(&f) {
                panic!("{e}");
            }
        } else if let Err(e) = load(&f) {
            panic!("{e}");
        }
    }
}

#[test]
fn unknown_key_is_reported_with_its_line() {
    let text = MINIMAL.replace("positions = 4", "positions = 4\npositoins = 5");
    let err = parse(&text, Path::new("rig.toml")).expect_err("unknown key");
    let line = text.lines().position(|l| l.starts_with("positoins")).expect("line") + 1;
    match &err {
        ConfigError::Invalid { problems, .. } => {
            assert!(
                problems
                    .iter()
                    .any(|p| p.line == Some(line) && p.key == "scan.positoins" && p.message.contains("positoins")),
                "{err}"
            );
        }
        other => panic!("expected the unknown key as a problem, got {other}"),
    }
    assert!(err.to_string().contains(&format!("rig.toml:line {line}: `scan.positoins`")), "{err}");
}

#[test]
fn unknown_device_kind_is_reported() {
    let text = MINIMAL.replace("[turntable]\nkind = \"sim\"", "[turntable]\nkind = \"warp-drive\"");
    let err = parse(&text, Path::new("rig.toml")).expect_err("unknown kind");
    let msg = err.to_string();
    assert!(msg.contains("warp-drive") && msg.contains("rig.toml:"), "{msg}");
}

#[test]
fn validate_reports_every_problem_with_lines() {
    let text = MINIMAL
        .replace("positions = 4", "positions = 0")
        .replace("resolution = 16", "resolution = 1")
        .replace("lights = [0]", "lights = [0, 3]")
        .replace("scene = \"sphere\"", "scene = \"teapot\"");
    let err = parse(&text, Path::new("rig.toml")).expect_err("invalid");
    let ConfigError::Invalid { problems, .. } = &err else { panic!("expected Invalid, got {err}") };
    let line_of = |needle: &str| text.lines().position(|l| l.trim_start().starts_with(needle)).map(|i| i + 1);
    let expect = [
        ("scan.positions", line_of("positions")),
        ("reconstruction.resolution", line_of("resolution")),
        ("scan.lights.1", line_of("lights = [0, 3]")),
        ("sim.scene", line_of("scene")),
    ];
    for (key, line) in expect {
        let p = problems.iter().find(|p| p.key == key).unwrap_or_else(|| panic!("no problem for {key}: {err}"));
        assert_eq!(p.line, line, "{key}: {err}");
    }
    assert_eq!(problems.len(), 4, "{err}");
}

#[test]
fn bad_toml_syntax_names_file_and_line() {
    let text = MINIMAL.replace("positions = 4", "positions = = 4");
    let err = parse(&text, Path::new("broken.toml")).expect_err("syntax");
    let line = text.lines().position(|l| l.contains("= = 4")).expect("line") + 1;
    assert!(err.to_string().starts_with(&format!("broken.toml:{line}:")), "{err}");
}

#[test]
fn every_unknown_key_and_a_misspelled_section_are_reported_at_once_with_their_lines() {
    let text =
        std::fs::read_to_string(std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("config/rigs/simulated.toml"))
            .expect("rig");
    let text = text
        .replacen("[scan]\n", "[scan]\npositons = 3\n", 1)
        .replacen("[camera]\nkind = \"sim\"\n", "[camera]\nkind = \"sim\"\nwidht = 10\n", 1)
        .replacen("[reconstruction]\n", "[reconstuction]\n", 1)
        .replacen("[sim]\n", "[sim]\ncolour = [\n  1,\n  2,\n]\n", 1);
    let line_of = |needle: &str| {
        text.lines().position(|l| l == needle || l.starts_with(&format!("{needle} = "))).expect("needle") + 1
    };
    let err = crate::config::parse(&text, std::path::Path::new("rig.toml")).expect_err("invalid");
    let crate::config::ConfigError::Invalid { problems, .. } = &err else { panic!("{err}") };
    let found: Vec<(String, Option<usize>)> = problems.iter().map(|p| (p.key.clone(), p.line)).collect();
    for (key, line) in [
        ("scan.positons", line_of("positons")),
        ("camera.widht", line_of("widht")),
        ("reconstuction", line_of("[reconstuction]")),
        ("sim.colour", line_of("colour = [")),
    ] {
        assert!(found.contains(&(key.to_owned(), Some(line))), "{key} at line {line} not in {found:?}\n{err}");
    }
    // The sections under the misspelled header are left without the fields it held.
    assert!(err.to_string().contains("missing field `method`"), "{err}");
}

#[test]
fn a_grid_above_the_memory_budget_is_refused_with_the_estimate() {
    let text =
        std::fs::read_to_string(std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("config/rigs/simulated.toml"))
            .expect("rig");
    let huge = text.replacen("resolution = 128", "resolution = 4096", 1);
    let err = crate::config::parse(&huge, std::path::Path::new("rig.toml")).expect_err("refused");
    let msg = err.to_string();
    assert!(
        msg.contains("reconstruction.resolution") && msg.contains("memory_budget_mb") && msg.contains(" MB"),
        "{msg}"
    );
    // A budget raised far enough lets it through; the shipped resolution is well inside the default.
    let raised = huge.replacen("[reconstruction]\n", "[reconstruction]\nmemory_budget_mb = 100000000\n", 1);
    crate::config::parse(&raised, std::path::Path::new("rig.toml")).expect("raised budget");
    let ok = crate::config::parse(&text, std::path::Path::new("rig.toml")).expect("shipped rig");
    assert!(ok.memory_estimate().total() < 2048 * 1024 * 1024);
}

#[cfg(feature = "fbdev")]
#[test]
fn a_rig_projector_takes_its_pose_from_a_procam_file() {
    let dir = tempfile::tempdir().expect("tempdir");
    let cam = crate::geometry::Intrinsics::new(900.0, 900.0, 320.0, 240.0);
    let proj =
        crate::geometry::Intrinsics::new(1200.0, 1200.0, 512.0, 700.0).with_distortion([0.1, 0.0, 1e-3, 0.0, 0.0]);
    let file = crate::calibration::procam_file::ProcamFile {
        camera: cam,
        projector: proj,
        projector_width: 1024,
        projector_height: 768,
        graycode_step: 1,
        rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        translation: [-0.2, 0.0, 0.0],
        camera_rms_px: 0.1,
        projector_rms_px: 0.2,
        views: 3,
    };
    crate::calibration::procam_file::write_procam_file(&dir.path().join("procam.toml"), &file).expect("write");
    let rig =
        std::fs::read_to_string(std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("config/rigs/simulated.toml"))
            .expect("rig");
    // Swap the simulated projector (if any) for an fbdev one that names the procam file.
    let mut doc: toml::Table = toml::from_str(&rig).expect("toml");
    doc.insert(
        "projector".into(),
        toml::Value::Table(
            toml::from_str(
                "kind = \"fbdev\"\ndevice = \"/dev/fb1\"\nwidth = 1024\nheight = 768\nprocam = \"procam.toml\"\n",
            )
            .expect("table"),
        ),
    );
    let path = dir.path().join("rig.toml");
    let text = toml::to_string(&doc).expect("serialise");
    std::fs::write(&path, &text).expect("write rig");
    let config = crate::rigfile::load(&path).expect("loads with the procam file");
    let model = config.projector.as_ref().and_then(|p| p.model()).expect("projector model");
    assert_eq!(model.intrinsics, proj);
    // The projector centre is the camera centre moved by the baseline, in the rig frame.
    let c = config.camera.model();
    let expected = c.centre() + c.pose.rotation.transpose() * crate::geometry::Vector3::new(0.2, 0.0, 0.0);
    assert!((model.centre() - expected).norm() < 1e-12, "{} vs {expected}", model.centre());
    // A procam file for another projector size is refused, naming the file.
    let wrong = text.replace("width = 1024", "width = 800");
    std::fs::write(&path, wrong).expect("write rig");
    let e = crate::rigfile::load(&path).expect_err("size mismatch");
    assert!(format!("{e}").contains("projector.procam"), "{e}");
}

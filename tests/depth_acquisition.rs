//! The depth-fusion rig file and the depth acquisition sequence: the shipped config loads, its
//! validation names a missing depth camera and a bad truncation, and the sequence delivers one fresh
//! depth frame per position at the planned angle (and fails with a typed error without a depth camera).

use std::path::{Path, PathBuf};
use std::sync::mpsc;

use scanrig::acquisition::{position_angle, run_depth_scan, AcquisitionError, CancelToken};
use scanrig::config::{ConfigError, Method};
use scanrig::devices::{build_rig, ErrorKind};
use scanrig::rigfile;

fn shipped() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("config/rigs/depth-fusion.toml")
}

fn shipped_text() -> String {
    std::fs::read_to_string(shipped()).expect("shipped rig readable")
}

/// The shipped text without its `[depth_camera]` tables.
fn without_depth_camera(text: &str) -> String {
    let start = text.find("[depth_camera]").expect("has [depth_camera]");
    let end = text.find("[sim]").expect("has [sim]");
    assert!(start < end);
    format!("{}{}", &text[..start], &text[end..])
}

fn problems(text: &str) -> Vec<scanrig::config::Problem> {
    match rigfile::parse(text, Path::new("rig.toml")) {
        Err(ConfigError::Invalid { problems, .. }) => problems,
        other => panic!("expected validation problems, got {other:?}"),
    }
}

#[test]
fn shipped_rig_loads_and_validation_names_what_depth_fusion_needs() {
    let rig = rigfile::load(&shipped()).expect("shipped depth-fusion rig loads");
    assert_eq!(rig.reconstruction.method, Method::DepthFusion);
    assert!(rig.depth_camera.is_some() && rig.reconstruction.depth_fusion.missing_is_free);

    let p = problems(&without_depth_camera(&shipped_text()));
    assert!(p.iter().any(|p| p.key == "depth_camera"), "{p:?}");

    let text = shipped_text().replace("truncation_voxels = 3.0", "truncation_voxels = 0.0");
    let p = problems(&text);
    assert!(p.iter().any(|p| p.key == "reconstruction.depth_fusion.truncation_voxels" && p.line.is_some()), "{p:?}");
}

#[test]
fn one_fresh_depth_frame_per_position_at_the_planned_angle() {
    let mut rig_config = rigfile::load(&shipped()).expect("loads");
    rig_config.scan.positions = 6;
    let mut rig = build_rig(&rig_config).expect("rig opens");
    let (tx, rx) = mpsc::sync_channel(8);
    let summary =
        run_depth_scan(&mut rig, &rig_config.scan, 0, &tx, &CancelToken::new(), &mut |_| {}).expect("depth scan runs");
    drop(tx);
    let views: Vec<_> = rx.iter().collect();
    assert_eq!(summary.views, 6);
    assert_eq!(summary.dropped, 0);
    assert_eq!(views.len(), 6);
    let mut last_sequence = None;
    for (i, v) in views.iter().enumerate() {
        assert_eq!(v.position, i);
        assert!((v.angle_deg - position_angle(&rig_config.scan, i)).abs() < 0.2, "{} at {i}", v.angle_deg);
        let f = &v.frame;
        assert_eq!(f.depth_m.len(), (f.width * f.height) as usize);
        let measured: Vec<f32> = f.depth_m.iter().copied().filter(|&z| z > 0.0).collect();
        // The cup fills part of the view, 0.3 to 0.4 m away.
        assert!(measured.len() > 1000 && measured.len() < f.depth_m.len() / 2, "{} measured", measured.len());
        assert!(measured.iter().all(|&z| (0.25..0.45).contains(&z)));
        assert!(last_sequence.is_none_or(|s| f.sequence > s));
        last_sequence = Some(f.sequence);
    }
    // Consecutive positions see the banded cup differently: the frames are not repeats.
    assert_ne!(views[0].frame.depth_m, views[1].frame.depth_m);

    // A rig without a depth camera fails at the first capture with an `Unsupported` device error.
    let mut no_depth = rigfile::parse(
        &without_depth_camera(&shipped_text()).replace("depth-fusion\"\n", "space-carving\"\n"),
        Path::new("rig.toml"),
    )
    .expect("a space-carving rig without a depth camera is valid");
    no_depth.scan.positions = 2;
    let mut rig = build_rig(&no_depth).expect("rig opens");
    let (tx, _rx) = mpsc::sync_channel(8);
    match run_depth_scan(&mut rig, &no_depth.scan, 0, &tx, &CancelToken::new(), &mut |_| {}) {
        Err(AcquisitionError::Device { position: 0, source, .. }) => assert_eq!(source.kind(), ErrorKind::Unsupported),
        other => panic!("expected an unsupported-device error, got {other:?}"),
    }
}

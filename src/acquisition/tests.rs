use std::path::Path;
use std::sync::mpsc;

use super::*;
use crate::config::RigConfig;
use crate::devices::build_rig;

fn small_rig(positions: u32) -> RigConfig {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/rigs/simulated.toml");
    let mut text = std::fs::read_to_string(&path).expect("shipped rig");
    text = text
        .replace("width = 640\nheight = 480", "width = 64\nheight = 48")
        .replace("fx = 1600.0\nfy = 1600.0\ncx = 320.0\ncy = 240.0", "fx = 160.0\nfy = 160.0\ncx = 32.0\ncy = 24.0")
        .replace("positions = 24", &format!("positions = {positions}"));
    crate::rigfile::parse(&text, &path).expect("derived rig is valid")
}

fn lights_off(rig: &Rig) -> bool {
    let world = rig.sim.as_ref().expect("sim rig");
    let s = world.snapshot();
    s.light_levels.iter().all(|&l| l == 0.0) && s.lasers_on.iter().all(|&l| !l)
}

#[test]
fn every_position_yields_one_fresh_frame_and_the_rig_is_parked() {
    let config = small_rig(6);
    let mut rig = build_rig(&config).expect("rig");
    let (tx, rx) = mpsc::sync_channel(8);
    let mut stages = Vec::new();
    let summary =
        run_turntable_scan(&mut rig, &config.scan, 0, &tx, &CancelToken::new(), &mut |p| stages.push(p.clone()))
            .expect("scan");
    drop(tx);
    let views: Vec<CapturedView> = rx.iter().collect();
    assert_eq!(views.len(), 6);
    assert_eq!(summary.views, 6);
    let depth = match &config.camera {
        crate::config::CameraConfig::Sim(c) => c.buffer_depth,
        other => panic!("a simulated camera, not {other:?}"),
    };
    for (i, v) in views.iter().enumerate() {
        assert_eq!(v.position, i);
        assert!((v.angle_deg - 60.0 * i as f64).abs() < 0.2, "position {i} at {}", v.angle_deg);
        // The stream starts at the first capture, after the first change; from then on every
        // position changes the scene (a move), so the frames queued before it are stale.
        let expected = if i == 0 { 0 } else { depth - 1 };
        assert_eq!(v.stale_discarded, expected, "position {i}");
        assert_eq!(v.lights_on, vec![0, 1, 2, 3]);
    }
    // Fresh frames differ between positions only through the scene, so consecutive sequence numbers
    // are counted, not ignored: no frame was dropped.
    assert_eq!(summary.dropped, 0);
    assert_eq!(summary.stale_discarded, u64::from(depth - 1) * 5);
    assert!(lights_off(&rig), "lights must be off after the scan");
    assert_eq!(stages.last().map(|p| p.stage), Some(Stage::Done));
}

#[test]
fn cancellation_stops_between_steps_and_parks() {
    let config = small_rig(8);
    let mut rig = build_rig(&config).expect("rig");
    let (tx, rx) = mpsc::sync_channel(8);
    let cancel = CancelToken::new();
    let c2 = cancel.clone();
    let err = run_turntable_scan(&mut rig, &config.scan, 0, &tx, &cancel, &mut |p| {
        if p.step == 3 && p.stage == Stage::Moving {
            c2.cancel();
        }
    })
    .expect_err("cancelled");
    assert!(matches!(err, AcquisitionError::Cancelled { completed: 3, total: 8 }), "{err}");
    drop(tx);
    assert_eq!(rx.iter().count(), 3, "the views captured before the cancel are kept");
    assert!(lights_off(&rig));
}

#[test]
fn a_vanished_pipeline_stops_the_scan_and_parks() {
    let config = small_rig(4);
    let mut rig = build_rig(&config).expect("rig");
    let (tx, rx) = mpsc::sync_channel(1);
    drop(rx);
    let err =
        run_turntable_scan(&mut rig, &config.scan, 0, &tx, &CancelToken::new(), &mut |_| {}).expect_err("no consumer");
    assert!(matches!(err, AcquisitionError::PipelineGone { position: 0 }), "{err}");
    assert!(lights_off(&rig));
}

#[test]
fn a_camera_that_only_delivers_stale_frames_is_an_error() {
    let config = small_rig(1);
    let mut rig = build_rig(&config).expect("rig");
    // A change "in the future" makes every frame stale.
    let later = Instant::now() + Duration::from_secs(3600);
    let mut seq = SequenceTracker::default();
    let err = capture_fresh(&mut rig, later, Duration::from_secs(1), 4, 0, &mut seq).expect_err("stale");
    assert_eq!(seq.dropped, 0);
    assert!(matches!(err, AcquisitionError::StaleFrames { position: 0, count: 5 }), "{err}");
}

#[test]
fn sequence_gaps_are_counted() {
    let mut t = SequenceTracker::default();
    for s in [5, 6, 9, 10, 14] {
        t.see(s);
    }
    assert_eq!(t.dropped, 2 + 3);
}

#[test]
fn position_angles_cover_one_turn() {
    let mut plan = small_rig(4).scan;
    plan.start_deg = 10.0;
    let angles: Vec<f64> = (0..4).map(|i| position_angle(&plan, i)).collect();
    assert_eq!(angles, vec![10.0, 100.0, 190.0, 280.0]);
}

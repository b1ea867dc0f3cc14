//! Light calibration against the simulated rig's exact light positions: a Lambertian sphere placed off
//! the turntable axis is imaged at several turntable angles under each light of the shipped
//! shadow-carving rig; the fitted positions are compared with the configured ones. The calibrated
//! positions then drive a shadow-carving scan.

use std::path::Path;

use scanrig::acquisition::CancelToken;
use scanrig::config::RigConfig;
use scanrig::geometry::{turntable_rotation, Vector3};
use scanrig::pipeline::light_calibration::{calibrate_point_light, LightFitParams, Sphere, SphereObservation};
use scanrig::rigfile;
use scanrig::scan::run_scan;
use scanrig::sim::{FrameNoise, Lighting, Material, PointLight, Primitive, RayTable, Scene, SimWorld, Solid};

fn shipped() -> RigConfig {
    rigfile::load(&Path::new(env!("CARGO_MANIFEST_DIR")).join("config/rigs/shadow-carving.toml")).expect("shipped rig")
}

fn configured_lights(rig: &RigConfig) -> Vec<(Vector3<f64>, f64)> {
    rig.lights.as_ref().expect("lights").lights.iter().map(|l| (Vector3::from(l.position_m), l.intensity)).collect()
}

/// Calibrate every light of the shipped rig; returns (fitted, true) positions.
fn calibrate(rig: &RigConfig, noise_sigma: f64) -> Vec<(Vector3<f64>, Vector3<f64>)> {
    let centre_obj = Vector3::new(0.03, 0.0, 0.025);
    let radius = 0.025;
    let solid =
        Solid::new(Primitive::Sphere { centre: centre_obj, radius }, vec![], Material::Uniform([0.8, 0.8, 0.8]))
            .expect("sphere");
    let lights = configured_lights(rig);
    let lighting = Lighting {
        lights: lights.iter().map(|&(p, i)| PointLight { position_m: p, intensity: i }).collect(),
        lasers: vec![],
        projector: None,
        ambient: 0.25,
        background: [0, 0, 0],
    };
    let world = SimWorld::new(Scene::new("calibration-sphere", vec![solid]).expect("scene"), lighting);
    let cam = rig.camera.model();
    let rays = RayTable::new(cam);
    let angles = [0.0, 45.0, 90.0, 135.0, 180.0, 225.0, 270.0, 315.0];
    let mut seq = 0;
    let mut render = |angle: f64, on: Option<usize>| {
        world.set_turntable_angle(angle);
        for l in 0..lights.len() {
            world.set_light(l, if Some(l) == on { 1.0 } else { 0.0 }).expect("light");
        }
        seq += 1;
        world.renderer().render_rgb(&rays, &world.snapshot(), FrameNoise { sigma: noise_sigma, seed: 3, sequence: seq })
    };
    let ambients: Vec<_> = angles.iter().map(|&a| render(a, None)).collect();
    (0..lights.len())
        .map(|l| {
            let lit: Vec<_> = angles.iter().map(|&a| render(a, Some(l))).collect();
            let obs: Vec<SphereObservation<'_>> = angles
                .iter()
                .zip(ambients.iter().zip(&lit))
                .map(|(&a, (ambient, lit))| SphereObservation {
                    camera: cam,
                    sphere: Sphere { centre_m: turntable_rotation(a) * centre_obj, radius_m: radius },
                    ambient,
                    lit,
                })
                .collect();
            let truth = lights[l].0;
            // A nominal position some 7 cm off, as from a rough measurement of the rig.
            let start = truth + Vector3::new(0.04, -0.03, 0.05);
            let est = calibrate_point_light(&obs, &LightFitParams::new(start)).expect("calibration converges");
            eprintln!(
                "light {l}: error {:.2} mm ({} px, rms {:.2} levels, {} iterations)",
                (est.position_m - truth).norm() * 1e3,
                est.pixels,
                est.rms_levels,
                est.iterations
            );
            (est.position_m, truth)
        })
        .collect()
}

#[test]
fn sphere_calibration_recovers_the_light_positions() {
    let rig = shipped();
    for (fitted, truth) in calibrate(&rig, 1.0) {
        let err = (fitted - truth).norm();
        assert!(err < 0.003, "light position error {:.1} mm", err * 1e3);
    }
}

#[test]
#[cfg_attr(debug_assertions, ignore = "heavy: run with --release")]
fn a_scan_with_calibrated_lights_matches_the_configured_one() {
    let mut rig = shipped();
    rig.reconstruction.resolution = 64;
    rig.scan.positions = 12;
    let fitted: Vec<_> = calibrate(&rig, 1.0).into_iter().map(|(f, _)| f).collect();
    let dir = tempfile::tempdir().expect("tempdir");
    let cancel = CancelToken::new();
    let with_config = run_scan(&rig, &dir.path().join("a"), &cancel, &mut |_| {}).expect("scan");
    // The calibrated positions go where a calibration file puts them: the rig's light positions.
    let mut calibrated = rig.clone();
    let lights = calibrated.lights.as_mut().expect("a light array");
    for (&index, p) in rig.scan.shadow_lights.iter().zip(&fitted) {
        lights.lights[index].position_m = [p.x, p.y, p.z];
    }
    let with_fit = run_scan(&calibrated, &dir.path().join("b"), &cancel, &mut |_| {}).expect("scan");
    let gt = |r: &scanrig::scan::Report| r.ground_truth.clone().expect("simulated truth");
    let (a, b) = (gt(&with_config), gt(&with_fit));
    eprintln!(
        "configured: IoU {:.3} containment {:.4}; calibrated: IoU {:.3} containment {:.4}",
        a.iou, a.containment, b.iou, b.containment
    );
    assert!(b.containment >= 0.99);
    assert!((a.iou - b.iou).abs() < 0.03);
    let used = match &with_fit.details {
        scanrig::scan::MethodDetails::ShadowCarving(s) => s.light_positions_m.clone(),
        other => panic!("not a shadow-carving report: {other:?}"),
    };
    for (u, f) in used.iter().zip(&fitted) {
        assert!((nalgebra::Vector3::from(*u) - f).norm() < 1e-12, "the scan used {u:?}, not the fitted {f:?}");
    }
}

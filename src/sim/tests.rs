//! Tests of the simulated world against the shipped rig files and against ground truth.

use std::path::{Path, PathBuf};

use nalgebra::Vector3;

use super::*;
use crate::config::{CameraConfig, RigConfig};
use crate::devices::Pattern;
use crate::geometry::{CameraModel, Intrinsics, Pose};
use crate::rigfile;

fn rig_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("config").join("rigs")
}

/// The shipped simulated rig with `scene`, its camera shrunk to 160x120 (same field of view) so debug
/// tests stay fast.
pub(crate) fn small_rig(scene: &str) -> RigConfig {
    let mut rig = rigfile::load(&rig_dir().join("simulated.toml")).expect("simulated.toml loads");
    if let Some(s) = rig.sim.as_mut() {
        s.scene = scene.to_owned();
    }
    let CameraConfig::Sim(c) = &mut rig.camera else { panic!("simulated.toml has a simulated camera") };
    let k = &mut c.calibration.intrinsics;
    (c.width, c.height) = (160, 120);
    (k.fx, k.fy, k.cx, k.cy) = (k.fx / 4.0, k.fy / 4.0, k.cx / 4.0, k.cy / 4.0);
    rig
}

/// The world of [`small_rig`].
pub(crate) fn small_world(scene: &str) -> SimWorld {
    let rig = small_rig(scene);
    SimWorld::from_config(rig.sim.as_ref().expect("sim section"), &rig).expect("world")
}

fn shipped_rigs() -> Vec<(PathBuf, RigConfig)> {
    let mut out = Vec::new();
    for entry in std::fs::read_dir(rig_dir()).expect("config/rigs") {
        let path = entry.expect("dir entry").path();
        if path.extension().is_some_and(|e| e == "toml") {
            let rig = rigfile::load(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
            if rig.sim.is_some() {
                out.push((path, rig));
            }
        }
    }
    out.sort_by(|a, b| a.0.cmp(&b.0));
    out
}

#[test]
fn every_shipped_sim_rig_builds_and_covers_every_scene() {
    let rigs = shipped_rigs();
    let mut scenes: Vec<String> = Vec::new();
    for (path, rig) in &rigs {
        let built = crate::devices::build_rig(rig).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        assert!(built.sim.is_some() && built.lights.is_some() && built.projector.is_some());
        assert!(built.depth_camera.is_some());
        scenes.push(rig.sim.as_ref().expect("sim").scene.clone());
    }
    for name in SCENE_NAMES {
        assert!(scenes.iter().any(|s| s == name), "no shipped rig uses scene `{name}`");
    }
}

/// Every part of every preset object must stand out from the background in every view of the scan,
/// even lit by ambient light alone: each surface point's projection (inside the image) must land on
/// a pixel, or a 4-neighbour, above the silhouette threshold. That is what keeps a silhouette carver
/// (closing with dilation 2, erosion 1) from cutting into the object.
#[test]
fn every_object_point_stands_out_in_every_view_of_every_shipped_rig() {
    for (path, rig) in shipped_rigs() {
        let world = SimWorld::from_config(rig.sim.as_ref().expect("sim"), &rig).expect("world");
        let model = rig.camera.model();
        let rays = RayTable::new(model);
        let sil = &rig.reconstruction.silhouette;
        let bg = sil.background.map(|c| c as f32 / 255.0);
        let is_object =
            |c: [f32; 3]| (0..3).map(|i| (c[i] - bg[i]).abs()).fold(0.0f32, f32::max) > sil.threshold as f32;
        let points = world.scene().sample_surface(300, 9);
        let bbox = rig.reconstruction.bbox();
        let b = world.scene().bounds();
        // The working volume may start at the table top, where the objects rest.
        assert!((0..3).all(|k| bbox.min[k] <= b.min[k] && bbox.max[k] > b.max[k]), "{}: bbox", path.display());
        let mut dimmest = f32::INFINITY;
        for i in 0..rig.scan.positions {
            let angle = rig.scan.start_deg + 360.0 * i as f64 / rig.scan.positions as f64;
            world.set_turntable_angle(angle);
            let state = world.snapshot(); // every light off: ambient only
            let view = model.for_turntable_angle(angle);
            for (p, _) in &points {
                let (u, v) =
                    view.pixel_of(p).unwrap_or_else(|| panic!("{}: {p} leaves the image at {angle}°", path.display()));
                let c = world.renderer().pixel(&rays, &state, u, v);
                if is_object(c) {
                    dimmest = dimmest.min(c[0].max(c[1]).max(c[2]));
                    continue;
                }
                let near = [(1i64, 0i64), (-1, 0), (0, 1), (0, -1)].iter().any(|(du, dv)| {
                    let (uu, vv) = (u as i64 + du, v as i64 + dv);
                    uu >= 0
                        && vv >= 0
                        && uu < model.width as i64
                        && vv < model.height as i64
                        && is_object(world.renderer().pixel(&rays, &state, uu as u32, vv as u32))
                });
                assert!(near, "{}: {p} at {angle}° projects onto background at ({u},{v})", path.display());
            }
        }
        println!(
            "{}: dimmest object pixel {:.1} levels, threshold {:.1}",
            path.display(),
            dimmest * 255.0,
            sil.threshold * 255.0
        );
        // Margin above the threshold for noise: at least 10 levels at 8 bits.
        assert!(dimmest - sil.threshold as f32 > 10.0 / 255.0, "{}: dimmest {dimmest}", path.display());
    }
}

/// Every rendered object pixel shows a surface point whose projection by `CameraModel::project`
/// (with distortion) falls in that very pixel, and every visible surface point is drawn in the pixel
/// `pixel_of` names.
#[test]
fn renderer_agrees_with_camera_model_projection() {
    let rig = small_rig("textured-box");
    let world = SimWorld::from_config(rig.sim.as_ref().expect("sim"), &rig).expect("world");
    let rays = RayTable::new(rig.camera.model());
    for angle in [0.0, 40.0, 200.0] {
        world.set_turntable_angle(angle);
        let depth = world.renderer().render_depth(&rays, angle);
        let view = rig.camera.model().for_turntable_angle(angle);
        let c = view.centre();
        let axis = view.pose.rotation.row(2).transpose();
        let mut object = 0;
        for v in 0..view.height {
            for u in 0..view.width {
                let z = depth[(v * view.width + u) as usize] as f64;
                if z == 0.0 {
                    continue;
                }
                object += 1;
                let d = view.pixel_ray(u as f64 + 0.5, v as f64 + 0.5);
                let q = c + d * (z / d.dot(&axis));
                assert_eq!(view.pixel_of(&q), Some((u, v)), "{angle}°: drawn at ({u},{v})");
                let s = world.scene();
                assert!(
                    !s.contains(&(q - d * 2e-6)) && s.contains(&(q + d * 2e-6)),
                    "{angle}°: {q} not on the surface"
                );
            }
        }
        assert!(object > 300, "{angle}°: {object} object pixels");
        // The other way round: a visible surface point's pixel shows that point (up to a pixel's
        // footprint on the surface).
        let mut checked = 0;
        for (p, n) in world.scene().sample_surface(400, 1) {
            let to_cam = (c - p).normalize();
            if n.dot(&to_cam) < 0.5 || world.scene().occluded(&(p + n * 1e-7), &to_cam, 0.0, (c - p).norm()) {
                continue;
            }
            let (u, v) = view.pixel_of(&p).expect("in the image");
            let d = view.pixel_ray(u as f64 + 0.5, v as f64 + 0.5);
            let at = |u: u32, v: u32| depth[(v * view.width + u) as usize] as f64;
            let z = at(u, v);
            if z == 0.0 {
                // On the silhouette edge the pixel centre may pass the object: a neighbour shows it.
                let edge = [(u.wrapping_sub(1), v), (u + 1, v), (u, v.wrapping_sub(1)), (u, v + 1)]
                    .iter()
                    .any(|&(a, b)| a < view.width && b < view.height && at(a, b) > 0.0);
                assert!(edge, "{angle}°: visible {p} falls on background at ({u},{v})");
                continue;
            }
            let q = c + d * (z / d.dot(&axis));
            // A pixel spans 0.45 m / 200 px = 2.3 mm; at cos >= 0.5 its footprint is under 5 mm.
            assert!((q - p).norm() < 5e-3, "{angle}°: {p} drawn as {q}");
            checked += 1;
        }
        assert!(checked > 50, "only {checked} visible samples");
    }
}

fn overhead_cup() -> (SimWorld, RayTable) {
    let lighting = Lighting {
        lights: vec![
            PointLight { position_m: Vector3::new(0.3, 0.0, 0.1), intensity: 1.0 },
            PointLight { position_m: Vector3::new(0.0, 0.0, 0.5), intensity: 1.0 },
        ],
        lasers: vec![],
        projector: None,
        ambient: 0.2,
        background: [0, 0, 0],
    };
    let world = SimWorld::new(Scene::preset("cup", 1.0).expect("cup"), lighting);
    let cam = CameraModel {
        width: 64,
        height: 64,
        intrinsics: Intrinsics {
            fx: 200.0,
            fy: 200.0,
            cx: 32.0,
            cy: 32.0,
            skew: 0.0,
            k1: 0.0,
            k2: 0.0,
            ..Intrinsics::default()
        },
        pose: Pose::look_at(Vector3::new(0.0, 0.0, 0.5), Vector3::zeros(), Vector3::y()),
    };
    (world, RayTable::new(cam))
}

#[test]
fn the_pit_floor_is_in_shadow_under_the_low_light_only() {
    let (world, rays) = overhead_cup();
    let floor = Vector3::new(0.01, 0.0, 0.015);
    let rim = Vector3::new(0.026, 0.0, 0.07);
    let px = |p: &Vector3<f64>| rays.model().pixel_of(p).expect("in view");
    let (fu, fv) = px(&floor);
    let (ru, rv) = px(&rim);
    let albedo = world.scene().albedo(0, &floor);
    let ambient_only = albedo[0] * 0.2;

    world.set_light(0, 1.0).expect("low light");
    let s = world.snapshot();
    let f = world.renderer().pixel(&rays, &s, fu, fv);
    // The floor faces the low light (cos > 0) but the pit wall shadows it: ambient only.
    assert!((f[0] - ambient_only).abs() < 1e-5, "floor {f:?} vs ambient {ambient_only}");
    let r = world.renderer().pixel(&rays, &s, ru, rv);
    assert!(r[0] > world.scene().albedo(0, &rim)[0] * 0.2 + 0.05, "the rim is lit by the low light: {r:?}");

    world.set_light(0, 0.0).expect("off");
    world.set_light(1, 1.0).expect("overhead light");
    let f2 = world.renderer().pixel(&rays, &world.snapshot(), fu, fv);
    assert!(f2[0] > ambient_only + 0.1, "the overhead light reaches the floor: {f2:?}");
}

#[test]
fn projector_pattern_lands_on_the_object_where_the_projector_sees_it() {
    let rig = small_rig("box");
    let world = SimWorld::from_config(rig.sim.as_ref().expect("sim"), &rig).expect("world");
    let rays = RayTable::new(rig.camera.model());
    let proj = world.renderer().lighting().projector.expect("projector");
    let (pw, ph) = (proj.model.width, proj.model.height);
    // Left half white, right half black.
    let mut rgb = vec![0u8; 3 * (pw * ph) as usize];
    for v in 0..ph {
        for u in 0..pw / 2 {
            let i = 3 * (v * pw + u) as usize;
            rgb[i..i + 3].copy_from_slice(&[255, 255, 255]);
        }
    }
    let pattern = Pattern { width: pw, height: ph, rgb: std::sync::Arc::new(rgb) };
    world.set_turntable_angle(20.0);
    let dark = world.renderer().render_rgb(&rays, &world.snapshot(), FrameNoise::NONE);
    world.set_pattern(Some(pattern)).expect("pattern");
    let lit = world.renderer().render_rgb(&rays, &world.snapshot(), FrameNoise::NONE);

    let view = rays.model().for_turntable_angle(20.0);
    let pview = proj.model.for_turntable_angle(20.0);
    let (mut brighter, mut object) = (0, 0);
    for v in 0..view.height {
        for u in 0..view.width {
            let (a, b) = (dark.get_pixel(u, v).0, lit.get_pixel(u, v).0);
            let d = view.pixel_ray(u as f64 + 0.5, v as f64 + 0.5);
            let Some(hit) = world.scene().intersect(&view.centre(), &d, 0.0, 10.0) else {
                assert_eq!(a, b, "background at ({u},{v}) changed");
                continue;
            };
            object += 1;
            let white_side = pview.project(&hit.point).is_some_and(|q| q.x < (pw / 2) as f64 - 1.0);
            let black_side = pview.project(&hit.point).is_some_and(|q| q.x >= (pw / 2) as f64 + 1.0);
            if b.iter().zip(a.iter()).any(|(x, y)| x > y) {
                brighter += 1;
                assert!(!black_side, "({u},{v}) brightened though its projector pixel is black");
            }
            if black_side {
                assert_eq!(a, b);
            }
            let _ = white_side;
        }
    }
    assert!(object > 200 && brighter > object / 5, "{brighter} of {object} object pixels brightened");
}

#[test]
fn laser_line_pixels_lie_on_the_laser_plane() {
    let rig = rigfile::load(&rig_dir().join("simulated.toml")).expect("simulated.toml");
    let world = SimWorld::from_config(rig.sim.as_ref().expect("sim"), &rig).expect("world");
    let model = rig.camera.model();
    let rays = RayTable::new(model);
    let laser = world.renderer().lighting().lasers[0];
    world.set_laser(0, true).expect("laser");
    for angle in [0.0, 75.0] {
        world.set_turntable_angle(angle);
        let img = world.renderer().render_rgb(&rays, &world.snapshot(), FrameNoise::NONE);
        let view = model.for_turntable_angle(angle);
        let to_obj = crate::geometry::turntable_rotation(-angle);
        let (o, n) = (to_obj * laser.origin_m, to_obj * laser.normal);
        let mut dists = Vec::new();
        let mut rows = std::collections::BTreeSet::new();
        for (u, v, px) in img.enumerate_pixels() {
            let [r, g, _] = px.0;
            if r as i32 - g as i32 <= 150 {
                continue;
            }
            let d = view.pixel_ray(u as f64 + 0.5, v as f64 + 0.5);
            let hit = world.scene().intersect(&view.centre(), &d, 0.0, 10.0).expect("laser pixels are on the object");
            dists.push(n.dot(&(hit.point - o)).abs());
            rows.insert(v);
        }
        assert!(rows.len() > 60, "{angle}°: the line covers only {} rows", rows.len());
        dists.sort_by(f64::total_cmp);
        let max = dists.last().copied().unwrap_or(0.0);
        let median = dists[dists.len() / 2];
        assert!(max <= render::LASER_MAX_HALF_WIDTH_M + 1e-9, "{angle}°: {max} m off the plane");
        assert!(median < 0.5e-3, "{angle}°: median {median} m off the plane");
    }
}

#[test]
fn sim_world_is_clone_debug_send_sync_and_shares_state() {
    fn assert_traits<T: Clone + std::fmt::Debug + Send + Sync>() {}
    assert_traits::<SimWorld>();
    let a = small_world("cup");
    let b = a.clone();
    a.set_turntable_angle(33.0);
    assert_eq!(b.snapshot().turntable_deg, 33.0);
}

#[test]
fn a_malformed_pattern_in_a_hand_made_state_is_ignored_not_a_panic() {
    let rig = small_rig("box");
    let world = SimWorld::from_config(rig.sim.as_ref().expect("sim"), &rig).expect("world");
    let rays = RayTable::new(rig.camera.model());
    let mut state = world.snapshot();
    let plain = world.renderer().render_rgb(&rays, &state, FrameNoise::NONE);
    state.pattern = Some(Pattern { width: 800, height: 600, rgb: std::sync::Arc::new(vec![255; 12]) });
    assert_eq!(world.renderer().render_rgb(&rays, &state, FrameNoise::NONE), plain);
}

#[test]
fn world_changes_are_counted_and_bad_requests_refused() {
    let world = small_world("sphere");
    let c0 = world.change_count();
    let t0 = world.last_change();
    world.set_turntable_angle(12.0);
    assert_eq!(world.change_count(), c0 + 1);
    assert!(world.last_change() >= t0);
    assert!(matches!(world.set_light(9, 1.0), Err(SimError::NoSuchLight { index: 9, count: 4 })));
    assert!(matches!(world.set_light(0, 1.5), Err(SimError::InvalidLevel { .. })));
    assert!(matches!(world.set_pattern(Some(Pattern::uniform(3, 3, [1, 2, 3]))), Err(SimError::PatternSize { .. })));
    let bad = Pattern { width: 800, height: 600, rgb: std::sync::Arc::new(vec![0; 10]) };
    assert!(matches!(world.set_pattern(Some(bad)), Err(SimError::PatternSize { .. })));
    assert_eq!(world.change_count(), c0 + 1, "refused requests change nothing");
}

/// Binary silhouette of an image by the rig's recipe: max per-channel difference from the background
/// above the threshold, then a closing (dilate, erode) with discs `x² + y² <= r²`.
fn silhouette(img: &image::RgbImage, sil: &crate::config::SilhouetteConfig) -> Vec<bool> {
    let (w, h) = (img.width() as i64, img.height() as i64);
    let mask: Vec<bool> = img
        .pixels()
        .map(|p| {
            (0..3).map(|i| (p.0[i] as i32 - sil.background[i] as i32).abs()).max().unwrap_or(0) as f64 / 255.0
                > sil.threshold
        })
        .collect();
    let morph = |m: &[bool], r: u32, dilate: bool| -> Vec<bool> {
        let r = r as i64;
        let disc: Vec<(i64, i64)> =
            (-r..=r).flat_map(|y| (-r..=r).map(move |x| (x, y))).filter(|(x, y)| x * x + y * y <= r * r).collect();
        (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                let hit = |&(dx, dy): &(i64, i64)| {
                    let (u, v) = (x + dx, y + dy);
                    let inside = u >= 0 && v >= 0 && u < w && v < h && m[(v * w + u) as usize];
                    inside == dilate
                };
                if dilate {
                    disc.iter().any(hit)
                } else {
                    !disc.iter().any(hit)
                }
            })
            .collect()
    };
    let closed = morph(&mask, sil.dilate_px, true);
    morph(&closed, sil.erode_px, false)
}

/// Carves each shipped rig's working volume at its configured resolution from 24 noisy views
/// (lights as the scan plan says) with its configured silhouette recipe, and measures containment:
/// the share of voxels whose centre is inside the true object that survive. Must be >= 0.995.
/// Release only (a few seconds): `cargo test --release --lib containment -- --nocapture`.
#[test]
#[cfg_attr(debug_assertions, ignore = "heavy: run in release")]
fn space_carving_containment_of_shipped_rigs() {
    for (path, rig) in shipped_rigs() {
        let mut devices = crate::devices::build_rig(&rig).expect("rig");
        let world = devices.sim.clone().expect("sim world");
        let t = std::time::Duration::from_secs(5);
        if let Some(l) = devices.lights.as_mut() {
            for &i in &rig.scan.lights {
                l.set_light(i, 1.0, t).expect("light");
            }
        }
        let grid =
            crate::geometry::VoxelGrid::from_resolution(&rig.reconstruction.bbox(), rig.reconstruction.resolution);
        let mut keep = vec![true; grid.len()];
        let model = rig.camera.model();
        // At most 24 of the plan's positions, spread over the turn (the laser rigs plan 180, and
        // containment is about the silhouette recipe, which more views only test again).
        let every = rig.scan.positions.div_ceil(24).max(1);
        for i in (0..rig.scan.positions).step_by(every as usize) {
            let angle = rig.scan.start_deg + 360.0 * i as f64 / rig.scan.positions as f64;
            devices.turntable.move_to(angle, t).expect("move");
            let changed = std::time::Instant::now();
            let frame = loop {
                let f = devices.camera.capture(t).expect("frame");
                if f.exposure_start >= changed {
                    break f;
                }
            };
            let mask = silhouette(&frame.image, &rig.reconstruction.silhouette);
            let view = model.for_turntable_angle(devices.turntable.angle());
            for k in 0..grid.dims[2] {
                for j in 0..grid.dims[1] {
                    for i in 0..grid.dims[0] {
                        let idx = grid.index(i, j, k);
                        if keep[idx] {
                            if let Some((u, v)) = view.pixel_of(&grid.centre(i, j, k)) {
                                keep[idx] = mask[(v * model.width + u) as usize];
                            }
                        }
                    }
                }
            }
        }
        let (mut inside, mut kept_inside, mut kept) = (0usize, 0usize, 0usize);
        for k in 0..grid.dims[2] {
            for j in 0..grid.dims[1] {
                for i in 0..grid.dims[0] {
                    let idx = grid.index(i, j, k);
                    let truth = world.scene().contains(&grid.centre(i, j, k));
                    inside += usize::from(truth);
                    kept_inside += usize::from(truth && keep[idx]);
                    kept += usize::from(keep[idx]);
                }
            }
        }
        let containment = kept_inside as f64 / inside as f64;
        let hull_ratio = kept as f64 / inside as f64;
        println!("{}: containment {containment:.5}, kept/true voxels {hull_ratio:.3}", path.display());
        assert!(containment >= 0.995, "{}: containment {containment}", path.display());
    }
}

/// Prints the render time of the shipped 640x480 camera with all four lights and the laser on;
/// asserts nothing about time. Release only: `cargo test --release --lib render_timing -- --nocapture`.
#[test]
#[cfg_attr(debug_assertions, ignore = "timing is only meaningful in release")]
fn render_timing_640x480() {
    let rig = rigfile::load(&rig_dir().join("simulated.toml")).expect("simulated.toml");
    let world = SimWorld::from_config(rig.sim.as_ref().expect("sim"), &rig).expect("world");
    let t = std::time::Instant::now();
    let rays = RayTable::new(rig.camera.model());
    let table = t.elapsed();
    for i in 0..4 {
        world.set_light(i, 1.0).expect("light");
    }
    let noise = FrameNoise { sigma: 1.0, seed: 1, sequence: 0 };
    let state = world.snapshot();
    let n = 20;
    let t = std::time::Instant::now();
    let mut sum = 0u64;
    for _ in 0..n {
        sum += world.renderer().render_rgb(&rays, &state, noise).as_raw()[0] as u64;
    }
    let four = t.elapsed() / n;
    let t = std::time::Instant::now();
    for _ in 0..n {
        sum += world.renderer().render_rgb(&rays, &state, FrameNoise::NONE).as_raw()[0] as u64;
    }
    let quiet = t.elapsed() / n;
    world.set_laser(0, true).expect("laser");
    let state = world.snapshot();
    let t = std::time::Instant::now();
    for _ in 0..n {
        sum += world.renderer().render_rgb(&rays, &state, noise).as_raw()[0] as u64;
    }
    let laser = t.elapsed() / n;
    let t = std::time::Instant::now();
    for _ in 0..n {
        sum += world.renderer().render_depth(&rays, 0.0).len() as u64;
    }
    let depth = t.elapsed() / n;
    println!(
        "640x480 ({} threads): ray table {table:?}; rgb, 4 lights: {four:?} (noise-free: {quiet:?}); + laser: {laser:?}; depth: {depth:?} ({sum})",
        rayon::current_num_threads()
    );
}

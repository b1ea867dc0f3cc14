//! The scan flow of method `laser`: at each turntable position a laser-off frame and one frame per
//! laser ([`crate::acquisition::run_laser_scan`]); as each position arrives, every laser's stripe is
//! detected with sub-pixel precision, triangulated on that laser's plane (rig frame), coloured from the
//! laser-off frame and turned into the object frame by the table angle. After the turn the points of
//! all lasers are merged into one cloud, statistical outliers removed, the cloud thinned to one point
//! per cube of `thin_voxels` voxels (laser data is dense along a stripe and sparse across stripes),
//! normals estimated from neighbouring points (oriented towards the cameras that saw each point), and
//! a closed mesh made from the oriented cloud ([`crate::pipeline::cloud`]). Where the lasers left the
//! surface unsampled (a part never lit while in view), the mesh is closed by the air the camera saw:
//! voxels outside the visual hull of evenly spaced laser-off silhouettes, or crossed by the line from
//! a point to the camera that saw it or to the laser that lit it.
//!
//! Outputs: `cloud.ply` (points with normals and colours, object frame, metres), `model.ply` /
//! `model.stl` / `model.obj` (the mesh, vertex colours from the nearest cloud point), `voxels.ply`
//! (the solid's voxel centres), `frames/pos_NNN_off.png` and `frames/pos_NNN_laser_K.png` when
//! `[reconstruction.laser] save_frames` is on, and `report.json` with a `laser` section (per-laser
//! planes and point counts) and, on a simulated rig, `ground_truth.chamfer_rel`: the symmetric Chamfer
//! distance between the mesh and the true surface over the scene's bounding-box diagonal.
//!
//! The laser planes are the configured `[[lights.laser]]` planes unless the caller passes calibrated
//! ones (see [`crate::pipeline::laser::calibrate_laser_plane`]).

use std::path::Path;
use std::time::Instant;

use image::RgbImage;
use nalgebra::Vector3;

use super::report::{mesh_ground_truth, Report, Timings};
use super::{silhouette_params, OutputDir, ScanError, ScanEvent};
use crate::acquisition::{self, CancelToken, LaserView};
use crate::config::RigConfig;
use crate::devices::build_rig;
use crate::geometry::{turntable_rotation, Aabb, CameraModel, VoxelGrid};
use crate::pipeline::cloud::{mark_lines_of_sight, solid_and_mesh_from_cloud_with_free_space};
use crate::pipeline::export::{self, write_atomic};
use crate::pipeline::laser::{detect_stripe, triangulate_peaks, LaserError, Plane, StripeParams};
use crate::pipeline::{
    carve_dense, extract_silhouette, reprojection_iou, CloudError, CloudMeshParams, CloudMeshStats, KnnIndex, Mask,
    PointCloud, View,
};

/// Views whose silhouettes are kept for the re-projection check (evenly spaced over the turn).
const REPROJECTION_VIEWS: usize = 24;

/// Why the laser part of a scan failed.
#[derive(Debug, thiserror::Error)]
pub enum LaserScanError {
    /// A laser named in `[reconstruction.laser] lasers` is not configured.
    #[error("laser {index} is not in [[lights.laser]] (the rig has {count})")]
    UnknownLaser {
        /// The index.
        index: usize,
        /// Lasers configured.
        count: usize,
    },
    /// Calibrated planes given to the flow do not match the lasers scanned with.
    #[error("{given} laser planes given for {expected} lasers")]
    PlaneCount {
        /// Planes given.
        given: usize,
        /// Lasers scanned with.
        expected: usize,
    },
    /// A configured laser plane is degenerate, or a stripe could not be detected.
    #[error("laser {index} at position {position}")]
    Stripe {
        /// The laser.
        index: usize,
        /// 0-based position (0 for configuration problems).
        position: usize,
        /// Why.
        #[source]
        source: LaserError,
    },
    /// The acquisition returned frames for other lasers than asked.
    #[error("position {position}: {got} laser frames for {expected} lasers")]
    FrameCount {
        /// 0-based position.
        position: usize,
        /// Frames received.
        got: usize,
        /// Lasers asked for.
        expected: usize,
    },
    /// Cleaning or meshing the cloud failed (e.g. no point inside the working volume).
    #[error("point cloud")]
    Cloud(#[source] CloudError),
}

/// One laser's part in the scan, for `report.json`.
#[derive(Debug, Clone, serde::Serialize)]
pub struct LaserPlaneSummary {
    /// The laser's index in `[[lights.laser]]`.
    pub index: usize,
    /// Its light plane, rig frame (unit normal, offset in metres).
    pub plane: Plane,
    /// Whether the plane came from a calibration rather than the rig file.
    pub calibrated: bool,
    /// Stripe peaks detected over all positions.
    pub peaks: u64,
    /// Points triangulated inside the working volume (before outlier removal).
    pub points: u64,
}

/// What the laser flow did, for `report.json` (section `laser`).
#[derive(Debug, Clone, serde::Serialize)]
pub struct LaserSummary {
    /// Per laser.
    pub lasers: Vec<LaserPlaneSummary>,
    /// Points of all lasers merged.
    pub merged_points: usize,
    /// Points removed as statistical outliers.
    pub outliers_removed: usize,
    /// Points in `cloud.ply` (after outlier removal and thinning).
    pub cloud_points: usize,
    /// What the meshing did.
    pub mesh: CloudMeshStats,
    /// Seconds spent detecting and triangulating stripes.
    pub triangulate_s: f64,
    /// Seconds spent removing outliers and estimating normals.
    pub normals_s: f64,
}

/// Points of the lasers so far (object frame) with their colours and the camera centre that saw them.
#[derive(Default)]
struct Accumulated {
    points: Vec<[f32; 3]>,
    colors: Vec<[u8; 3]>,
    viewpoints: Vec<[f32; 3]>,
    /// The exit point of the laser whose light made each point.
    light_sources: Vec<[f32; 3]>,
}

fn write_png(dir: &Path, name: String, image: &RgbImage) -> Result<(), ScanError> {
    std::fs::create_dir_all(dir).map_err(|source| ScanError::OutputDir {
        path: dir.to_owned(),
        what: "cannot create it",
        source,
    })?;
    let file = dir.join(name);
    let mut png = Vec::with_capacity(image.len() / 2);
    image
        .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .map_err(|source| ScanError::EncodeFrame { path: file.clone(), source })?;
    write_atomic(&file, &png).map_err(ScanError::Export)
}

fn inside(b: &Aabb, p: &Vector3<f64>) -> bool {
    (0..3).all(|a| p[a] >= b.min[a] && p[a] <= b.max[a])
}

/// Scan the rig described by `config` with the laser method and write the results into `out`.
///
/// `planes` overrides the planes of the scanned lasers (rig frame, in the order of
/// `[reconstruction.laser] lasers`), e.g. with calibrated ones; `None` uses `[[lights.laser]]`.
pub fn run_laser_scan(
    config: &RigConfig,
    out: &Path,
    planes: Option<&[Plane]>,
    cancel: &CancelToken,
    events: &mut dyn FnMut(ScanEvent),
) -> Result<Report, ScanError> {
    let started = Instant::now();
    let recon = &config.reconstruction;
    let lc = &recon.laser;
    let err = ScanError::Laser;
    let configured = config.lights.as_ref().map(|l| l.lasers.as_slice()).unwrap_or(&[]);
    let lasers = lc.selected(configured.len());
    let mut colours = Vec::with_capacity(lasers.len());
    let mut laser_origins = Vec::with_capacity(lasers.len());
    let mut laser_planes = Vec::with_capacity(lasers.len());
    for &index in &lasers {
        let l = configured.get(index).ok_or(err(LaserScanError::UnknownLaser { index, count: configured.len() }))?;
        colours.push(l.colour);
        laser_origins.push(Vector3::from(l.origin_m));
        let plane = Plane::through(l.origin_m, l.plane_normal)
            .map_err(|source| err(LaserScanError::Stripe { index, position: 0, source }))?;
        laser_planes.push(plane);
    }
    if let Some(p) = planes {
        if p.len() != lasers.len() {
            return Err(err(LaserScanError::PlaneCount { given: p.len(), expected: lasers.len() }));
        }
        laser_planes = p.to_vec();
    }
    let stripe =
        StripeParams { min_peak: lc.min_peak as f32, max_width_px: lc.max_width_px, half_window_px: lc.half_window_px };

    let out_dir = OutputDir::prepare(out)?;
    let out = out_dir.path().to_owned();
    let mut rig = build_rig(config).map_err(ScanError::OpenDevices)?;
    let sim = rig.sim.clone();
    let camera = config.camera.model();
    let bbox = recon.bbox();
    let grid = VoxelGrid::from_resolution(&bbox, recon.resolution);
    let sil_params = silhouette_params(config);
    let stride = (config.scan.positions as usize).div_ceil(REPROJECTION_VIEWS).max(1);
    let mut timings = Timings::default();
    let mut acc = Accumulated::default();
    let mut per_laser = vec![(0u64, 0u64); lasers.len()];
    let mut triangulate_s = 0.0f64;
    let mut silhouettes: Vec<(CameraModel, Mask)> = Vec::new();
    let mut views = 0usize;

    let plan = config.scan.clone();
    let (summary, capture_s) = super::acquire_and_process(
        &mut rig,
        |rig, tx, progress| acquisition::run_laser_scan(rig, &plan, &lasers, tx, cancel, progress),
        events,
        |view: LaserView, events| {
            if lc.save_frames {
                let dir = out.join("frames");
                write_png(&dir, format!("pos_{:03}_off.png", view.position), &view.off.image)?;
                for (index, frame) in &view.on {
                    write_png(&dir, format!("pos_{:03}_laser_{index}.png", view.position), &frame.image)?;
                }
            }
            if view.on.len() != lasers.len() {
                let (position, got, expected) = (view.position, view.on.len(), lasers.len());
                return Err(err(LaserScanError::FrameCount { position, got, expected }));
            }
            let t = Instant::now();
            let to_obj = turntable_rotation(-view.angle_deg);
            let eye = to_obj * camera.centre();
            let eye = [eye.x as f32, eye.y as f32, eye.z as f32];
            let before = acc.points.len();
            for (k, (index, frame)) in view.on.iter().enumerate() {
                let peaks = detect_stripe(&view.off.image, &frame.image, colours[k], &stripe)
                    .map_err(|source| err(LaserScanError::Stripe { index: *index, position: view.position, source }))?;
                per_laser[k].0 += peaks.len() as u64;
                let source = to_obj * laser_origins[k];
                let source = [source.x as f32, source.y as f32, source.z as f32];
                for (p, pk) in triangulate_peaks(&camera, &laser_planes[k], &peaks) {
                    let q = to_obj * p;
                    if !inside(&bbox, &q) {
                        continue;
                    }
                    let (u, v) = ((pk.u.floor() as u32).min(view.off.image.width() - 1), pk.v);
                    let c = view.off.image.get_pixel(u, v).0;
                    acc.points.push([q.x as f32, q.y as f32, q.z as f32]);
                    acc.colors.push(c);
                    acc.viewpoints.push(eye);
                    acc.light_sources.push(source);
                    per_laser[k].1 += 1;
                }
            }
            triangulate_s += t.elapsed().as_secs_f64();
            if view.position % stride == 0 {
                let t = Instant::now();
                silhouettes.push((
                    camera.for_turntable_angle(view.angle_deg),
                    extract_silhouette(&view.off.image, &sil_params),
                ));
                timings.silhouette += t.elapsed().as_secs_f64();
            }
            views += 1;
            events(ScanEvent::ViewProcessed { position: view.position, occupied: (acc.points.len() - before) as u64 });
            Ok(())
        },
    )?;
    timings.capture = capture_s;
    timings.carve = triangulate_s;

    events(ScanEvent::Stage("point cloud"));
    let t = Instant::now();
    let cloud_err = |e| err(LaserScanError::Cloud(e));
    let merged_points = acc.points.len();
    let Accumulated { points, colors, viewpoints, light_sources } = acc;
    // Until the real normals are estimated, each point's "normal" is the unit vector towards the
    // camera that saw it: thinning averages it with the rest of its cube, and it then orients the
    // estimated normal.
    let towards = |sources: &[[f32; 3]]| -> Vec<[f32; 3]> {
        points
            .iter()
            .zip(sources)
            .map(|(p, e)| {
                let d = Vector3::from(*e) - Vector3::from(*p);
                let d = d.try_normalize(0.0).unwrap_or(Vector3::z());
                [d.x, d.y, d.z]
            })
            .collect()
    };
    let towards_camera = towards(&viewpoints);
    let mut towards_laser = towards(&light_sources);
    let mut cloud = PointCloud::from_parts(points, Some(towards_camera), Some(colors)).map_err(cloud_err)?;
    let keep = cloud.inlier_mask(lc.neighbours, lc.outlier_std_ratio).map_err(cloud_err)?;
    let merged = cloud.len();
    cloud.retain_mask(&keep);
    let outliers_removed = merged - cloud.len();
    let mut kept = keep.iter();
    towards_laser.retain(|_| kept.next().copied().unwrap_or(false));
    // Air seen by the camera: outside the visual hull of the kept silhouettes, or on a line of sight
    // from a point to the camera or to the laser that lit it (the lasers' light planes hold the
    // turntable axis, so their light sweeps the air of a concavity that the oblique lines of sight
    // to the camera miss). The meshing uses it where the lasers left the surface unsampled.
    let carving_views: Vec<View<'_>> =
        silhouettes.iter().map(|(camera, mask)| View { camera: *camera, mask }).collect();
    let mut free: Vec<bool> = match carve_dense(&grid, &carving_views) {
        Ok(hull) => (0..grid.len())
            .map(|idx| {
                let d = grid.dims;
                !hull.get(idx % d[0], (idx / d[0]) % d[1], idx / (d[0] * d[1]))
            })
            .collect(),
        Err(e) => {
            tracing::warn!(error = %e, "no visual hull for the laser meshing; lines of sight only");
            vec![false; grid.len()]
        }
    };
    if let Some(towards) = cloud.normals() {
        let skip_m = (CloudMeshParams::default().band_voxels + 1.0) * grid.voxel_size;
        mark_lines_of_sight(&grid, cloud.points(), towards, skip_m, &mut free).map_err(cloud_err)?;
        mark_lines_of_sight(&grid, cloud.points(), &towards_laser, skip_m, &mut free).map_err(cloud_err)?;
    }
    if lc.thin_voxels > 0.0 {
        cloud = cloud.voxel_downsample(lc.thin_voxels * grid.voxel_size).map_err(cloud_err)?;
    }
    let eyes: Vec<[f32; 3]> = match cloud.normals() {
        Some(ns) => cloud.points().iter().zip(ns).map(|(p, n)| [0, 1, 2].map(|a| p[a] + n[a])).collect(),
        None => Vec::new(),
    };
    cloud.estimate_normals(lc.neighbours, |i| eyes.get(i).copied().unwrap_or([0.0, 0.0, 1.0])).map_err(cloud_err)?;
    let normals_s = t.elapsed().as_secs_f64();

    events(ScanEvent::Stage("mesh"));
    let t = Instant::now();
    let mesh_params = CloudMeshParams { k: lc.mesh_neighbours, ..CloudMeshParams::default() };
    let (solid, mut mesh, mesh_stats) =
        solid_and_mesh_from_cloud_with_free_space(&cloud, &grid, &mesh_params, Some(&free)).map_err(cloud_err)?;
    // Vertex colours: the nearest cloud point's.
    if let Some(cc) = cloud.colors() {
        let index = KnnIndex::new(cloud.points());
        let mut buf = Vec::new();
        let colors = mesh
            .vertices
            .iter()
            .map(|v| {
                index.k_nearest(v, 1, &mut buf);
                buf.first().map_or([128; 3], |&(_, i)| cc[i as usize])
            })
            .collect();
        mesh.colors = Some(colors);
    }
    timings.mesh = t.elapsed().as_secs_f64();

    events(ScanEvent::Stage("export"));
    let t = Instant::now();
    let p = |name: &str| out.join(name);
    cloud.write_ply(&p("cloud.ply")).map_err(ScanError::Export)?;
    export::write_ply_mesh(&p("model.ply"), &mesh).map_err(ScanError::Export)?;
    export::write_stl(&p("model.stl"), &mesh).map_err(ScanError::Export)?;
    export::write_obj(&p("model.obj"), &mesh).map_err(ScanError::Export)?;
    export::write_ply_points(&p("voxels.ply"), &export::voxel_centres(&solid), None).map_err(ScanError::Export)?;
    timings.export = t.elapsed().as_secs_f64();

    events(ScanEvent::Stage("evaluate"));
    let reprojection: Vec<f64> =
        reprojection_iou(&solid, &carving_views).into_iter().map(|v| v.unwrap_or(0.0)).collect();
    let reprojection_mean =
        if reprojection.is_empty() { 0.0 } else { reprojection.iter().sum::<f64>() / reprojection.len() as f64 };
    let ground_truth = sim.as_ref().map(|world| {
        mesh_ground_truth(world.scene(), config.sim.as_ref().map_or("", |s| s.scene.as_str()), grid, &solid, &mesh).0
    });
    if let Some(gt) = &ground_truth {
        tracing::info!(iou = gt.iou, chamfer_rel = gt.chamfer_rel, "laser scan compared with the scene");
    }
    let gb = grid.bbox();
    let mut files = vec!["cloud.ply", "model.ply", "model.stl", "model.obj", "voxels.ply"];
    if lc.save_frames {
        files.push("frames/");
    }
    files.push("report.json");
    let mut report = Report {
        scanrig_version: env!("CARGO_PKG_VERSION"),
        source: config.rig.name.clone(),
        method: recon.method.name(),
        views,
        resolution: grid.dims,
        voxel_size_m: grid.voxel_size,
        bbox_m: [gb.min, gb.max],
        occupied_voxels: solid.count(),
        volume_m3: solid.volume_m3(),
        mesh_triangles: mesh.triangles.len(),
        timings_s: timings,
        reprojection_iou: reprojection,
        reprojection_iou_mean: reprojection_mean,
        frames: Some(summary),
        ground_truth,
        files: files.into_iter().map(str::to_owned).collect(),
        visual_hull: None,
        photo: None,
        shadow_carving: None,
        depth_fusion: None,
    };
    let laser = LaserSummary {
        lasers: lasers
            .iter()
            .zip(&laser_planes)
            .zip(&per_laser)
            .map(|((&index, &plane), &(peaks, points))| LaserPlaneSummary {
                index,
                plane,
                calibrated: planes.is_some(),
                peaks,
                points,
            })
            .collect(),
        merged_points,
        outliers_removed,
        cloud_points: cloud.len(),
        mesh: mesh_stats,
        triangulate_s,
        normals_s,
    };
    report.timings_s.total = started.elapsed().as_secs_f64();
    // The shared report plus this method's own section.
    let mut json = serde_json::to_value(&report).map_err(ScanError::EncodeReport)?;
    if let Some(obj) = json.as_object_mut() {
        obj.insert("laser".into(), serde_json::to_value(&laser).map_err(ScanError::EncodeReport)?);
    }
    let bytes = serde_json::to_vec_pretty(&json).map_err(ScanError::EncodeReport)?;
    write_atomic(&p("report.json"), &bytes).map_err(ScanError::Export)?;
    Ok(report)
}

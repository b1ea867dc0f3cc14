//! The scan flow of method `depth-fusion`: one fresh depth frame per turntable position, each fused
//! into a TSDF over the object-frame grid as it arrives, then the solid and a sub-voxel mesh read off
//! the field, and the usual outputs. On a simulated rig the report compares the result with the
//! scene: voxel IoU / containment and the symmetric Chamfer distance between the mesh and the true
//! surface relative to the object's bounding-box diagonal (`ground_truth.chamfer_rel`). The visual
//! hull of the depth maps' silhouettes (pixels with a measurement) is reported alongside.
//!
//! Frames are written as `frames/pos_NNN_depth.png`: 16-bit grey, depth in units of 0.1 mm (0 = none).

use std::path::Path;
use std::time::Instant;

use super::report::{mesh_ground_truth, Report, Timings, VisualHull};
use super::{ScanError, ScanEvent};
use crate::acquisition::{self, CancelToken, DepthView};
use crate::config::{DepthCameraConfig, RigConfig};
use crate::devices::build_rig;
use crate::geometry::{CameraModel, VoxelGrid};
use crate::pipeline::export::{self, write_atomic};
use crate::pipeline::{extract_surface, reprojection_iou, FusionParams, Mask, MeshParams, SpaceCarver, Tsdf, View};

/// What the depth fusion did, for `report.json`.
#[derive(Debug, Clone, serde::Serialize)]
pub struct DepthFusionSummary {
    /// Truncation distance, metres.
    pub truncation_m: f64,
    /// Depth maps fused.
    pub views: usize,
    /// Measured pixels over all depth maps.
    pub measured_pixels: u64,
    /// Mesh vertices moved onto the TSDF's zero crossing.
    pub refined_vertices: usize,
    /// Seconds spent integrating.
    pub integrate_s: f64,
}

/// The depth camera's model in the rig frame.
fn depth_camera_model(config: &DepthCameraConfig) -> CameraModel {
    match config {
        DepthCameraConfig::Sim(c) => c.calibration.model(c.width, c.height),
        DepthCameraConfig::Freenect(c) => {
            c.calibration.model(crate::config::FreenectDepthConfig::WIDTH, crate::config::FreenectDepthConfig::HEIGHT)
        }
    }
}

fn write_depth_png(dir: &Path, view: &DepthView) -> Result<(), ScanError> {
    std::fs::create_dir_all(dir).map_err(|source| ScanError::OutputDir {
        path: dir.to_owned(),
        what: "cannot create it",
        source,
    })?;
    let f = &view.frame;
    let data: Vec<u16> = f.depth_m.iter().map(|&z| (z.max(0.0) * 10_000.0).round().min(65_535.0) as u16).collect();
    let file = dir.join(format!("pos_{:03}_depth.png", view.position));
    let image =
        image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_raw(f.width, f.height, data).ok_or_else(|| {
            ScanError::EncodeFrame {
                path: file.clone(),
                source: image::ImageError::Parameter(image::error::ParameterError::from_kind(
                    image::error::ParameterErrorKind::DimensionMismatch,
                )),
            }
        })?;
    let mut png = Vec::new();
    image
        .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .map_err(|source| ScanError::EncodeFrame { path: file.clone(), source })?;
    write_atomic(&file, &png).map_err(ScanError::Export)
}

/// Scan the rig described by `config` with depth fusion and write the results into `out`.
pub fn run_depth_scan(
    config: &RigConfig,
    out: &Path,
    cancel: &CancelToken,
    events: &mut dyn FnMut(ScanEvent),
) -> Result<Report, ScanError> {
    let started = Instant::now();
    let out_dir = super::OutputDir::prepare(out)?;
    let out = out_dir.path().to_owned();
    let mut rig = build_rig(config).map_err(ScanError::OpenDevices)?;
    let sim = rig.sim.clone();
    let recon = &config.reconstruction;
    let grid = VoxelGrid::from_resolution(&recon.bbox(), recon.resolution);
    let fusion = FusionParams {
        truncation_m: recon.depth_fusion.truncation_voxels * grid.voxel_size,
        max_weight: 64.0,
        missing_is_free: recon.depth_fusion.missing_is_free,
    };
    let mut tsdf = Tsdf::new(grid, fusion).map_err(ScanError::DepthFusion)?;
    let mut hull = SpaceCarver::new(grid).map_err(ScanError::Carve)?;
    // Validation makes a depth-fusion rig have a depth camera; without one the acquisition fails with
    // a typed device error at the first capture.
    let camera = config.depth_camera.as_ref().map(depth_camera_model);
    let mut timings = Timings::default();
    let mut views: Vec<(CameraModel, Mask)> = Vec::with_capacity(config.scan.positions as usize);
    let (mut measured_pixels, mut integrate_s) = (0u64, 0.0f64);

    let plan = config.scan.clone();
    let (summary, capture_s) = super::acquire_and_process(
        &mut rig,
        |rig, tx, progress| acquisition::run_depth_scan(rig, &plan, tx, cancel, progress),
        events,
        |view: DepthView, events| {
            write_depth_png(&out.join("frames"), &view)?;
            let Some(model) = camera else { return Ok(()) };
            let cam = model.for_turntable_angle(view.angle_deg);
            let f = &view.frame;
            let t = Instant::now();
            let stats = tsdf.integrate(&cam, &f.depth_m).map_err(ScanError::DepthFusion)?;
            tracing::debug!(position = view.position, updated = stats.updated, "fused a depth map");
            integrate_s += t.elapsed().as_secs_f64();
            let t = Instant::now();
            let mask = Mask::from_fn(f.width, f.height, |u, v| f.depth_m[(v * f.width + u) as usize] > 0.0);
            measured_pixels += mask.count() as u64;
            timings.silhouette += t.elapsed().as_secs_f64();
            let t = Instant::now();
            let stats = hull.add_view(&cam, &mask).map_err(ScanError::Carve)?;
            timings.carve += t.elapsed().as_secs_f64();
            events(ScanEvent::ViewProcessed { position: view.position, occupied: stats.occupied });
            views.push((cam, mask));
            Ok(())
        },
    )?;
    timings.capture = capture_s;
    timings.carve += integrate_s;
    tracing::info!(views = tsdf.views(), seconds = integrate_s, "depth fusion done");

    events(ScanEvent::Stage("mesh"));
    let t = Instant::now();
    let occupancy = tsdf.occupancy();
    let mut mesh = extract_surface(&occupancy, &MeshParams { smooth_radius: recon.mesh.smooth_radius })
        .map_err(ScanError::Mesh)?;
    let refined_vertices = tsdf.refine_vertices(&mut mesh);
    timings.mesh = t.elapsed().as_secs_f64();

    events(ScanEvent::Stage("export"));
    let t = Instant::now();
    let p = |name: &str| out.join(name);
    export::write_ply_mesh(&p("model.ply"), &mesh).map_err(ScanError::Export)?;
    export::write_stl(&p("model.stl"), &mesh).map_err(ScanError::Export)?;
    export::write_obj(&p("model.obj"), &mesh).map_err(ScanError::Export)?;
    export::write_ply_points(&p("voxels.ply"), &export::voxel_centres(&occupancy), None).map_err(ScanError::Export)?;
    timings.export = t.elapsed().as_secs_f64();

    events(ScanEvent::Stage("evaluate"));
    let hull_occ = hull.occupancy();
    let carving_views: Vec<View<'_>> = views.iter().map(|(camera, mask)| View { camera: *camera, mask }).collect();
    let reprojection: Vec<f64> =
        reprojection_iou(&occupancy, &carving_views).into_iter().map(|v| v.unwrap_or(0.0)).collect();
    let reprojection_mean =
        if reprojection.is_empty() { 0.0 } else { reprojection.iter().sum::<f64>() / reprojection.len() as f64 };
    let _voxel_volume = grid.voxel_size.powi(3);
    let mut hull_overlap = None;
    let ground_truth = sim.as_ref().map(|world| {
        let (gt, truth) = mesh_ground_truth(
            world.scene(),
            config.sim.as_ref().map_or("", |s| s.scene.as_str()),
            grid,
            &occupancy,
            &mesh,
        );
        hull_overlap = hull_occ.iou_and_containment(&truth).ok();
        gt
    });
    if let Some(gt) = &ground_truth {
        tracing::info!(iou = gt.iou, chamfer_rel = gt.chamfer_rel, "depth fusion compared with the scene");
    }
    timings.total = started.elapsed().as_secs_f64();
    let bbox = grid.bbox();
    let mut report = Report {
        scanrig_version: env!("CARGO_PKG_VERSION"),
        source: config.rig.name.clone(),
        method: recon.method.name(),
        views: views.len(),
        resolution: grid.dims,
        voxel_size_m: grid.voxel_size,
        bbox_m: [bbox.min, bbox.max],
        occupied_voxels: occupancy.count(),
        volume_m3: occupancy.volume_m3(),
        mesh_triangles: mesh.triangles.len(),
        timings_s: timings,
        reprojection_iou: reprojection,
        reprojection_iou_mean: reprojection_mean,
        frames: Some(summary),
        ground_truth,
        files: ["model.ply", "model.stl", "model.obj", "voxels.ply", "frames/", "report.json"]
            .map(str::to_owned)
            .to_vec(),
        visual_hull: Some(VisualHull {
            iou: hull_overlap.map(|o| o.iou),
            containment: hull_overlap.map(|o| o.containment),
            voxels: hull_occ.count(),
            volume_m3: hull_occ.volume_m3(),
            colour_error: None,
            reprojection_error: None,
        }),
        photo: None,
        shadow_carving: None,
        depth_fusion: None,
    };
    report.depth_fusion = Some(DepthFusionSummary {
        truncation_m: fusion.truncation_m,
        views: tsdf.views(),
        measured_pixels,
        refined_vertices,
        integrate_s,
    });
    report.timings_s.total = started.elapsed().as_secs_f64();
    let json = serde_json::to_vec_pretty(&report).map_err(ScanError::EncodeReport)?;
    write_atomic(&p("report.json"), &json).map_err(ScanError::Export)?;
    Ok(report)
}

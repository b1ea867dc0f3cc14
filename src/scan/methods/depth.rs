//! The flow of method `depth-fusion`: one fresh depth frame per turntable position, each fused into
//! a TSDF over the object-frame grid as it arrives, then the solid and a sub-voxel mesh read off the
//! field. The visual hull of the depth maps' silhouettes (pixels with a measurement) is reported
//! alongside.
//!
//! Frames are stored as `frames/pos_NNN_depth.png`: 16-bit grey, depth in units of 0.1 mm
//! ([`DEPTH_UNITS_PER_M`]; 0 = none). Depth is quantised to that unit before it is fused, so a
//! resumed or reprocessed scan fuses exactly the maps a live one did.

use crate::scan::preview;
use std::time::Instant;

use crate::acquisition::{self, DepthView};
use crate::config::{DepthCameraConfig, Method, RigConfig, ScanPlan};
use crate::devices::DepthFrame;
use crate::geometry::{CameraModel, VoxelGrid};
use crate::pipeline::{extract_surface_reporting, FusionParams, Mask, MeshParams, SpaceCarver, Tsdf};
use crate::scan::flow::{Finish, FrameDir, Outcome, PositionView, ScanFlow, Sequence, ViewRecord};
use crate::scan::report::{MethodDetails, Timings, VisualHull};
use crate::scan::{ScanError, ScanEvent};

use super::frame_name;

/// Stored depth units per metre (0.1 mm).
pub const DEPTH_UNITS_PER_M: f32 = 10_000.0;

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

/// Depth in metres in stored units (0.1 mm), saturated at 65535 units.
fn to_units(z: f32) -> u16 {
    (z.max(0.0) * DEPTH_UNITS_PER_M).round().min(65_535.0) as u16
}

impl PositionView for DepthView {
    fn position(&self) -> usize {
        self.position
    }
    fn angle_deg(&self) -> f64 {
        self.angle_deg
    }
    fn sequence(&self) -> u64 {
        self.frame.sequence
    }
    fn stale_discarded(&self) -> u32 {
        self.stale_discarded
    }
}

/// Depth fusion.
#[derive(Debug)]
pub struct DepthFlow {
    plan: ScanPlan,
    camera: Option<CameraModel>,
    fusion: FusionParams,
    smooth_radius: u32,
    tsdf: Tsdf,
    hull: SpaceCarver,
    views: Vec<(CameraModel, Mask)>,
    measured_pixels: u64,
    integrate_s: f64,
    timings: Timings,
}

impl DepthFlow {
    /// The flow of `config` (method `depth-fusion`).
    pub fn new(config: &RigConfig) -> Result<DepthFlow, ScanError> {
        let recon = &config.reconstruction;
        let grid = VoxelGrid::from_resolution(&recon.bbox(), recon.resolution);
        let fusion = FusionParams {
            truncation_m: recon.depth_fusion.truncation_voxels * grid.voxel_size,
            max_weight: 64.0,
            missing_is_free: recon.depth_fusion.missing_is_free,
        };
        Ok(DepthFlow {
            plan: config.scan.clone(),
            // Validation makes a depth-fusion rig have a depth camera; without one the acquisition
            // fails with a typed device error at the first capture.
            camera: config.depth_camera.as_ref().map(depth_camera_model),
            fusion,
            smooth_radius: recon.mesh.smooth_radius,
            tsdf: Tsdf::new(grid, fusion).map_err(ScanError::DepthFusion)?,
            hull: SpaceCarver::new(grid).map_err(ScanError::Carve)?,
            views: Vec::with_capacity(config.scan.positions as usize),
            measured_pixels: 0,
            integrate_s: 0.0,
            timings: Timings::default(),
        })
    }
}

impl ScanFlow for DepthFlow {
    type View = DepthView;

    fn method(&self) -> Method {
        Method::DepthFusion
    }

    fn sequence(&self, first: usize) -> Sequence<DepthView> {
        let plan = self.plan.clone();
        Box::new(move |rig, tx, cancel, progress| acquisition::run_depth_scan(rig, &plan, first, tx, cancel, progress))
    }

    fn save(&self, frames: &FrameDir, view: &DepthView) -> Result<(Vec<String>, Vec<usize>), ScanError> {
        let f = &view.frame;
        let data: Vec<u16> = f.depth_m.iter().map(|&z| to_units(z)).collect();
        Ok((vec![frames.write_grey16(&frame_name(view.position, "_depth.png"), f.width, f.height, &data)?], Vec::new()))
    }

    fn load(&self, frames: &FrameDir, record: &ViewRecord) -> Result<DepthView, ScanError> {
        let name = frame_name(record.position, "_depth.png");
        let image = frames.read_grey16(&name)?;
        let (width, height) = image.dimensions();
        let depth_m = image.into_raw().into_iter().map(|n| f32::from(n) / DEPTH_UNITS_PER_M).collect();
        Ok(DepthView {
            position: record.position,
            angle_deg: record.angle_deg,
            frame: DepthFrame { sequence: record.sequence, exposure_start: Instant::now(), width, height, depth_m },
            stale_discarded: record.stale_discarded,
        })
    }

    fn process(&mut self, view: DepthView, _events: &mut dyn FnMut(ScanEvent)) -> Result<String, ScanError> {
        let Some(model) = self.camera else { return Ok("no depth camera".into()) };
        let cam = model.for_turntable_angle(view.angle_deg);
        let f = &view.frame;
        if (f.width, f.height) != (model.width, model.height) {
            return Err(ScanError::BadFrame {
                path: frame_name(view.position, "_depth.png").into(),
                problem: format!(
                    "depth map is {}x{} pixels, the depth camera's {}x{}",
                    f.width, f.height, model.width, model.height
                ),
            });
        }
        // Fuse what is stored, so a replayed view fuses exactly like a live one.
        let depth: Vec<f32> = f.depth_m.iter().map(|&z| f32::from(to_units(z)) / DEPTH_UNITS_PER_M).collect();
        let t = Instant::now();
        let stats = self.tsdf.integrate(&cam, &depth).map_err(ScanError::DepthFusion)?;
        self.integrate_s += t.elapsed().as_secs_f64();
        let t = Instant::now();
        let mask = Mask::from_fn(f.width, f.height, |u, v| depth[(v * f.width + u) as usize] > 0.0);
        self.measured_pixels += mask.count() as u64;
        self.timings.silhouette += t.elapsed().as_secs_f64();
        let t = Instant::now();
        self.hull.add_view(&cam, &mask).map_err(ScanError::Carve)?;
        self.timings.carve += t.elapsed().as_secs_f64();
        self.views.push((cam, mask));
        Ok(format!("fused: {} voxels updated", stats.updated))
    }

    /// The voxels next to the fused surface (the TSDF's zero crossing).
    fn preview(&self, max_points: usize) -> Option<crate::pipeline::PointCloud> {
        preview::from_tsdf(&self.tsdf, self.fusion.truncation_m, max_points)
    }

    fn finish(self, finish: Finish<'_>) -> Result<Outcome, ScanError> {
        let Finish { timings, events, .. } = finish;
        timings.silhouette += self.timings.silhouette;
        timings.carve += self.timings.carve + self.integrate_s;
        tracing::info!(views = self.tsdf.views(), seconds = self.integrate_s, "depth fusion done");
        events(ScanEvent::Stage("mesh"));
        let t = Instant::now();
        let solid = self.tsdf.occupancy();
        let (mut mesh, mesh_handles) =
            extract_surface_reporting(&solid, &MeshParams::smoothed(self.smooth_radius)).map_err(ScanError::Mesh)?;
        let refined_vertices = self.tsdf.refine_vertices(&mut mesh);
        timings.mesh = t.elapsed().as_secs_f64();
        let hull = self.hull.into_occupancy();
        let hull_summary = VisualHull {
            iou: None,
            containment: None,
            voxels: hull.count(),
            volume_m3: hull.volume_m3(),
            colour_error: None,
            reprojection_error: None,
        };
        Ok(Outcome {
            views: self.views.len(),
            solid,
            mesh,
            mesh_handles,
            cloud: None,
            voxel_colours: None,
            silhouettes: self.views,
            visual_hull: Some((hull, hull_summary)),
            colour_error: None,
            details: MethodDetails::DepthFusion(DepthFusionSummary {
                truncation_m: self.fusion.truncation_m,
                views: self.tsdf.views(),
                measured_pixels: self.measured_pixels,
                refined_vertices,
                integrate_s: self.integrate_s,
            }),
        })
    }
}

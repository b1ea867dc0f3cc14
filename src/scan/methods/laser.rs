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
//! a point to the camera that saw it or to the laser that lit it. Both are gathered as the positions
//! arrive (the hull carved one silhouette at a time, the lines counted per voxel so that those of the
//! points later removed as outliers can be taken out), so little of that work is left after the turn.
//!
//! Outputs: `cloud.ply` (points with normals and colours, object frame, metres), `model.ply` /
//! `model.stl` / `model.obj` (the mesh, vertex colours from the nearest cloud point, or for a
//! vertex farther than `COLOUR_REACH_VOXELS` from every point the nearest cell of the thinned
//! cloud), `voxels.ply` (the solid's voxel centres), `frames/pos_NNN_off.png` and
//! `frames/pos_NNN_laser_K.png` (every frame, for resume and reprocessing), and `report.json` with
//! a `laser` section (per-laser planes and point counts) and, on a simulated rig,
//! `ground_truth.chamfer_rel`: the symmetric Chamfer distance between the mesh and the true surface
//! over the scene's bounding-box diagonal.
//!
//! The laser planes are the rig file's `[[lights.laser]]` planes (calibrated ones go there; see
//! [`crate::pipeline::laser::calibrate_laser_plane`]).

use crate::scan::preview;
use std::time::Instant;

use nalgebra::Vector3;
use rayon::prelude::*;

use super::{frame_name, stored_frame};
use crate::acquisition::{self, LaserView};
use crate::config::{LaserScanConfig, Method, RigConfig, ScanPlan};
use crate::geometry::{turntable_rotation, Aabb, CameraModel, VoxelGrid};
use crate::pipeline::cloud::{solid_and_mesh_from_cloud_with_free_space, SightLineCounts};
use crate::pipeline::laser::{detect_stripe, triangulate_peaks, LaserError, Plane, StripeParams};
use crate::pipeline::{
    extract_silhouette, CarveError, CloudError, CloudMeshParams, CloudMeshStats, KnnIndex, Mask, PointCloud,
    SilhouetteParams, SpaceCarver,
};
use crate::scan::flow::{Finish, FrameDir, Outcome, PositionView, ScanFlow, Sequence, ViewRecord};
use crate::scan::report::{MethodDetails, Timings};
use crate::scan::{silhouette_params, ScanError, ScanEvent};

/// Views whose silhouettes are kept for the re-projection check (evenly spaced over the turn).
const REPROJECTION_VIEWS: usize = 24;
/// Distance (voxel edges) within which a mesh vertex takes the colour of its nearest cloud point;
/// farther vertices take that of the nearest cell of the cloud thinned to cells this size.
const COLOUR_REACH_VOXELS: f64 = 4.0;

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

/// Points of the lasers so far (object frame) with their colours and the unit directions from each
/// point to the camera centre that saw it and to the exit point of the laser whose light made it.
#[derive(Debug, Default)]
struct Accumulated {
    points: Vec<[f32; 3]>,
    colors: Vec<[u8; 3]>,
    towards_camera: Vec<[f32; 3]>,
    towards_laser: Vec<[f32; 3]>,
}

/// The unit vector from `p` towards `e` (object frame), `+z` if they coincide.
fn towards(p: &[f32; 3], e: &[f32; 3]) -> [f32; 3] {
    let d = Vector3::from(*e) - Vector3::from(*p);
    let d = d.try_normalize(0.0).unwrap_or(Vector3::z());
    [d.x, d.y, d.z]
}

/// The air the camera saw, gathered as the views arrive (see the module docs): the voxels outside
/// the silhouettes' visual hull and the lines of sight of every point so far. At the end the lines
/// of the points dropped as outliers are taken out, which leaves what marking the lines of the kept
/// points would give.
#[derive(Debug)]
struct FreeSpace {
    /// The visual hull of the silhouettes so far, carved one silhouette at a time (the same voxels
    /// as carving them all at once), or why a silhouette could not be carved: the visual hull is
    /// then left out.
    hull: Result<SpaceCarver, CarveError>,
    /// Lines from each point to its camera and to its laser.
    sight: SightLineCounts,
}

fn inside(b: &Aabb, p: &Vector3<f64>) -> bool {
    (0..3).all(|a| p[a] >= b.min[a] && p[a] <= b.max[a])
}

impl PositionView for LaserView {
    fn position(&self) -> usize {
        self.position
    }
    fn angle_deg(&self) -> f64 {
        self.angle_deg
    }
    fn sequence(&self) -> u64 {
        self.off.sequence
    }
    fn stale_discarded(&self) -> u32 {
        self.stale_discarded
    }
}

/// Laser triangulation.
#[derive(Debug)]
pub struct LaserFlow {
    plan: ScanPlan,
    settings: LaserScanConfig,
    camera: CameraModel,
    bbox: Aabb,
    grid: VoxelGrid,
    lasers: Vec<usize>,
    colours: Vec<[u8; 3]>,
    laser_origins: Vec<Vector3<f64>>,
    laser_planes: Vec<Plane>,
    stripe: StripeParams,
    sil_params: SilhouetteParams,
    stride: usize,
    acc: Accumulated,
    per_laser: Vec<(u64, u64)>,
    triangulate_s: f64,
    silhouettes: Vec<(CameraModel, Mask)>,
    free: FreeSpace,
    /// Seconds spent carving silhouettes and marking lines of sight as the views arrived.
    free_space_s: f64,
    views: usize,
    timings: Timings,
}

impl LaserFlow {
    /// The flow of `config` (method `laser`).
    pub fn new(config: &RigConfig) -> Result<LaserFlow, ScanError> {
        let recon = &config.reconstruction;
        let lc = &recon.laser;
        let err = ScanError::Laser;
        let configured = config.lights.as_ref().map(|l| l.lasers.as_slice()).unwrap_or(&[]);
        let lasers = lc.selected(configured.len());
        let mut colours = Vec::with_capacity(lasers.len());
        let mut laser_origins = Vec::with_capacity(lasers.len());
        let mut laser_planes = Vec::with_capacity(lasers.len());
        for &index in &lasers {
            let l =
                configured.get(index).ok_or(err(LaserScanError::UnknownLaser { index, count: configured.len() }))?;
            colours.push(l.colour);
            laser_origins.push(Vector3::from(l.origin_m));
            let plane = Plane::through(l.origin_m, l.plane_normal)
                .map_err(|source| err(LaserScanError::Stripe { index, position: 0, source }))?;
            laser_planes.push(plane);
        }
        let stripe = StripeParams {
            min_peak: lc.min_peak as f32,
            max_width_px: lc.max_width_px,
            half_window_px: lc.half_window_px,
        };
        let bbox = recon.bbox();
        let grid = VoxelGrid::from_resolution(&bbox, recon.resolution);
        // The lines of sight start past the band the meshing evaluates around each point (its own
        // noise).
        let skip_m = (CloudMeshParams::default().band_voxels + 1.0) * grid.voxel_size;
        let free = FreeSpace { hull: SpaceCarver::new(grid), sight: SightLineCounts::new(&grid, skip_m) };
        Ok(LaserFlow {
            plan: config.scan.clone(),
            settings: lc.clone(),
            camera: config.camera.model(),
            grid,
            bbox,
            per_laser: vec![(0, 0); lasers.len()],
            lasers,
            colours,
            laser_origins,
            laser_planes,
            stripe,
            sil_params: silhouette_params(config),
            stride: (config.scan.positions as usize).div_ceil(REPROJECTION_VIEWS).max(1),
            acc: Accumulated::default(),
            triangulate_s: 0.0,
            silhouettes: Vec::new(),
            free,
            free_space_s: 0.0,
            views: 0,
            timings: Timings::default(),
        })
    }
}

impl ScanFlow for LaserFlow {
    type View = LaserView;

    fn method(&self) -> Method {
        Method::Laser
    }

    fn sequence(&self, first: usize) -> Sequence<LaserView> {
        let plan = self.plan.clone();
        let lasers = self.lasers.clone();
        Box::new(move |rig, tx, cancel, progress| {
            acquisition::run_laser_scan(rig, &plan, first, &lasers, tx, cancel, progress)
        })
    }

    fn save(&self, frames: &FrameDir, view: &LaserView) -> Result<(Vec<String>, Vec<usize>), ScanError> {
        let mut files = vec![frames.write_rgb(&frame_name(view.position, "_off.png"), &view.off.image)?];
        for (index, frame) in &view.on {
            files.push(frames.write_rgb(&frame_name(view.position, &format!("_laser_{index}.png")), &frame.image)?);
        }
        Ok((files, self.plan.lights.clone()))
    }

    fn load(&self, frames: &FrameDir, record: &ViewRecord) -> Result<LaserView, ScanError> {
        let p = record.position;
        let off = stored_frame(frames.read_rgb(&frame_name(p, "_off.png"))?, record.sequence);
        let mut on = Vec::with_capacity(self.lasers.len());
        for &index in &self.lasers {
            let image = frames.read_rgb(&frame_name(p, &format!("_laser_{index}.png")))?;
            on.push((index, stored_frame(image, record.sequence)));
        }
        Ok(LaserView { position: p, angle_deg: record.angle_deg, off, on, stale_discarded: record.stale_discarded })
    }

    fn process(&mut self, view: LaserView, _events: &mut dyn FnMut(ScanEvent)) -> Result<String, ScanError> {
        let err = ScanError::Laser;
        if view.on.len() != self.lasers.len() {
            let (position, got, expected) = (view.position, view.on.len(), self.lasers.len());
            return Err(err(LaserScanError::FrameCount { position, got, expected }));
        }
        let t = Instant::now();
        let camera = self.camera;
        let to_obj = turntable_rotation(-view.angle_deg);
        let eye = to_obj * camera.centre();
        let eye = [eye.x as f32, eye.y as f32, eye.z as f32];
        let before = self.acc.points.len();
        for (k, (index, frame)) in view.on.iter().enumerate() {
            let peaks = detect_stripe(&view.off.image, &frame.image, self.colours[k], &self.stripe)
                .map_err(|source| err(LaserScanError::Stripe { index: *index, position: view.position, source }))?;
            self.per_laser[k].0 += peaks.len() as u64;
            let source = to_obj * self.laser_origins[k];
            let source = [source.x as f32, source.y as f32, source.z as f32];
            for (p, pk) in triangulate_peaks(&camera, &self.laser_planes[k], &peaks) {
                let q = to_obj * p;
                if !inside(&self.bbox, &q) {
                    continue;
                }
                let (u, v) = ((pk.u.floor() as u32).min(view.off.image.width() - 1), pk.v);
                let c = view.off.image.get_pixel(u, v).0;
                let q = [q.x as f32, q.y as f32, q.z as f32];
                self.acc.points.push(q);
                self.acc.colors.push(c);
                self.acc.towards_camera.push(towards(&q, &eye));
                self.acc.towards_laser.push(towards(&q, &source));
                self.per_laser[k].1 += 1;
            }
        }
        self.triangulate_s += t.elapsed().as_secs_f64();
        let t = Instant::now();
        let (new, acc, sight) = (before.., &self.acc, &mut self.free.sight);
        let cloud_err = |e| err(LaserScanError::Cloud(e));
        sight.add(&acc.points[new.clone()], &acc.towards_camera[new.clone()]).map_err(cloud_err)?;
        sight.add(&acc.points[new.clone()], &acc.towards_laser[new]).map_err(cloud_err)?;
        self.free_space_s += t.elapsed().as_secs_f64();
        if view.position % self.stride == 0 {
            let t = Instant::now();
            let silhouette =
                (camera.for_turntable_angle(view.angle_deg), extract_silhouette(&view.off.image, &self.sil_params));
            self.timings.silhouette += t.elapsed().as_secs_f64();
            let t = Instant::now();
            if let Ok(carver) = &mut self.free.hull {
                if let Err(e) = carver.add_view(&silhouette.0, &silhouette.1) {
                    self.free.hull = Err(e);
                }
            }
            self.free_space_s += t.elapsed().as_secs_f64();
            self.silhouettes.push(silhouette);
        }
        self.views += 1;
        let added = self.acc.points.len() - before;
        Ok(format!("triangulated: {added} points ({} in all)", self.acc.points.len()))
    }

    /// The points triangulated so far, in their surface colours.
    fn preview(&self, max_points: usize) -> Option<PointCloud> {
        preview::from_points(&self.acc.points, Some(&self.acc.colors), max_points)
    }

    fn finish(self, finish: Finish<'_>) -> Result<Outcome, ScanError> {
        let Finish { timings, events, .. } = finish;
        let err = ScanError::Laser;
        let lc = &self.settings;
        let grid = self.grid;
        timings.silhouette += self.timings.silhouette;
        timings.carve += self.triangulate_s + self.free_space_s;
        let triangulate_s = self.triangulate_s;
        events(ScanEvent::Stage("point cloud"));
        let t = Instant::now();
        let cloud_err = |e| err(LaserScanError::Cloud(e));
        let merged_points = self.acc.points.len();
        let Accumulated { points, colors, towards_camera, towards_laser } = self.acc;
        // Until the real normals are estimated, each point's "normal" is the unit vector towards the
        // camera that saw it: thinning averages it with the rest of its cube, and it then orients the
        // estimated normal.
        let mut cloud = PointCloud::from_parts(points, Some(towards_camera), Some(colors)).map_err(cloud_err)?;
        let keep = cloud.inlier_mask(lc.neighbours, lc.outlier_std_ratio).map_err(cloud_err)?;
        // Air seen by the camera: outside the visual hull of the kept silhouettes, or on a line of sight
        // from a point to the camera or to the laser that lit it (the lasers' light planes hold the
        // turntable axis, so their light sweeps the air of a concavity that the oblique lines of sight
        // to the camera miss). The meshing uses it where the lasers left the surface unsampled. Both
        // were gathered as the views arrived; the outliers' lines of sight go now.
        let FreeSpace { hull, mut sight } = self.free;
        let mut free: Vec<bool> = match hull {
            Ok(carver) => {
                let hull = carver.into_occupancy();
                let d = grid.dims;
                (0..grid.len()).map(|idx| !hull.get(idx % d[0], (idx / d[0]) % d[1], idx / (d[0] * d[1]))).collect()
            }
            Err(e) => {
                tracing::warn!(error = %e, "no visual hull for the laser meshing; lines of sight only");
                vec![false; grid.len()]
            }
        };
        let dropped =
            |v: &[[f32; 3]]| -> Vec<[f32; 3]> { v.iter().zip(&keep).filter(|(_, &k)| !k).map(|(x, _)| *x).collect() };
        let outliers = dropped(cloud.points());
        sight.remove(&outliers, &dropped(cloud.normals().unwrap_or(&[]))).map_err(cloud_err)?;
        sight.remove(&outliers, &dropped(&towards_laser)).map_err(cloud_err)?;
        sight.mark_free(&mut free).map_err(cloud_err)?;
        drop(sight);
        let merged = cloud.len();
        cloud.retain_mask(&keep);
        let outliers_removed = merged - cloud.len();
        if lc.thin_voxels > 0.0 {
            cloud = cloud.voxel_downsample(lc.thin_voxels * grid.voxel_size).map_err(cloud_err)?;
        }
        let eyes: Vec<[f32; 3]> = match cloud.normals() {
            Some(ns) => cloud.points().iter().zip(ns).map(|(p, n)| [0, 1, 2].map(|a| p[a] + n[a])).collect(),
            None => Vec::new(),
        };
        cloud
            .estimate_normals(lc.neighbours, |i| eyes.get(i).copied().unwrap_or([0.0, 0.0, 1.0]))
            .map_err(cloud_err)?;
        let normals_s = t.elapsed().as_secs_f64();

        events(ScanEvent::Stage("mesh"));
        let t = Instant::now();
        let mesh_params = CloudMeshParams { k: lc.mesh_neighbours, ..CloudMeshParams::default() };
        let (solid, mut mesh, mesh_stats) =
            solid_and_mesh_from_cloud_with_free_space(&cloud, &grid, &mesh_params, Some(&free)).map_err(cloud_err)?;
        // Vertex colours: the nearest cloud point's. A vertex farther than COLOUR_REACH_VOXELS from
        // every point (a surface no laser lit, such as the floor closing a cup's foot) takes the
        // colour of the nearest cell of the cloud thinned to cells of that size: the search over
        // every point's cells would otherwise cross many empty shells per such vertex.
        if let Some(cc) = cloud.colors() {
            let reach = (COLOUR_REACH_VOXELS * grid.voxel_size) as f32;
            let index = KnnIndex::new(cloud.points());
            let coarse = cloud.voxel_downsample(f64::from(reach)).map_err(cloud_err)?;
            let coarse_index = KnnIndex::with_cell(coarse.points().to_vec(), reach);
            let coarse_colours = coarse.colors().unwrap_or(&[]);
            let colors = mesh
                .vertices
                .par_iter()
                .map_init(Vec::new, |buf, v| {
                    index.k_nearest_within(v, 1, reach, buf);
                    if let Some(&(_, i)) = buf.first() {
                        return cc[i as usize];
                    }
                    coarse_index.k_nearest(v, 1, buf);
                    buf.first().and_then(|&(_, i)| coarse_colours.get(i as usize).copied()).unwrap_or([128; 3])
                })
                .collect();
            mesh.colors = Some(colors);
        }
        timings.mesh = t.elapsed().as_secs_f64();

        let laser = LaserSummary {
            lasers: self
                .lasers
                .iter()
                .zip(&self.laser_planes)
                .zip(&self.per_laser)
                .map(|((&index, &plane), &(peaks, points))| LaserPlaneSummary { index, plane, peaks, points })
                .collect(),
            merged_points,
            outliers_removed,
            cloud_points: cloud.len(),
            mesh: mesh_stats,
            triangulate_s,
            normals_s,
        };
        Ok(Outcome {
            views: self.views,
            solid,
            mesh,
            mesh_handles: Some(mesh_stats.handles),
            cloud: Some(cloud),
            voxel_colours: None,
            silhouettes: self.silhouettes,
            visual_hull: None,
            colour_error: None,
            details: MethodDetails::Laser(laser),
        })
    }
}

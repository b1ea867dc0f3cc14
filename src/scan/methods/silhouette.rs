//! The silhouette methods: `space-carving` (the visual hull, carved view by view as the frames
//! arrive) and, from that hull, the photo-consistency methods `voxel-coloring` and
//! `space-carving-photo` (see [`super::photo`]). One fresh frame per turntable position with the
//! plan's lights on, stored as `frames/pos_NNN.png`.

use crate::scan::preview;
use std::time::Instant;

use image::RgbImage;

use super::super::flow::{Finish, FrameDir, Outcome, PositionView, ScanFlow, Sequence, ViewRecord};
use super::super::report::{CarvingSummary, MethodDetails, Timings};
use super::super::{silhouette_params, ScanError, ScanEvent};
use super::{frame_name, photo, stored_frame};
use crate::acquisition::{self, CapturedView};
use crate::config::{Method, PhotoConfig, RigConfig, ScanPlan};
use crate::geometry::{CameraModel, VoxelGrid};
use crate::pipeline::{
    extract_silhouette, extract_surface_reporting, Mask, MeshParams, PhotoView, SilhouetteParams, SpaceCarver,
};

impl PositionView for CapturedView {
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

/// Space carving and the photo-consistency methods.
#[derive(Debug)]
pub struct SilhouetteFlow {
    method: Method,
    plan: ScanPlan,
    camera: CameraModel,
    params: SilhouetteParams,
    photo: PhotoConfig,
    smooth_radius: u32,
    carver: SpaceCarver,
    views: Vec<(CameraModel, Mask)>,
    /// The images, kept for the photo methods only.
    images: Vec<RgbImage>,
    silhouette_pixels: u64,
    timings: Timings,
}

impl SilhouetteFlow {
    /// The flow of `config` (method `space-carving`, `voxel-coloring` or `space-carving-photo`).
    pub fn new(config: &RigConfig) -> Result<SilhouetteFlow, ScanError> {
        let recon = &config.reconstruction;
        let grid = VoxelGrid::from_resolution(&recon.bbox(), recon.resolution);
        Ok(SilhouetteFlow {
            method: recon.method,
            plan: config.scan.clone(),
            camera: config.camera.model(),
            params: silhouette_params(config),
            photo: recon.photo.clone(),
            smooth_radius: recon.mesh.smooth_radius,
            carver: SpaceCarver::new(grid).map_err(ScanError::Carve)?,
            views: Vec::with_capacity(config.scan.positions as usize),
            images: Vec::new(),
            silhouette_pixels: 0,
            timings: Timings::default(),
        })
    }
}

impl ScanFlow for SilhouetteFlow {
    type View = CapturedView;

    fn method(&self) -> Method {
        self.method
    }

    fn sequence(&self, first: usize) -> Sequence<CapturedView> {
        let plan = self.plan.clone();
        Box::new(move |rig, tx, cancel, progress| {
            acquisition::run_turntable_scan(rig, &plan, first, tx, cancel, progress)
        })
    }

    fn save(&self, frames: &FrameDir, view: &CapturedView) -> Result<(Vec<String>, Vec<usize>), ScanError> {
        let name = frames.write_rgb(&frame_name(view.position, ".png"), &view.frame.image)?;
        Ok((vec![name], view.lights_on.clone()))
    }

    fn load(&self, frames: &FrameDir, record: &ViewRecord) -> Result<CapturedView, ScanError> {
        let image = frames.read_rgb(&frame_name(record.position, ".png"))?;
        Ok(CapturedView {
            position: record.position,
            angle_deg: record.angle_deg,
            lights_on: record.lights_on.clone(),
            frame: stored_frame(image, record.sequence),
            stale_discarded: record.stale_discarded,
        })
    }

    fn process(&mut self, view: CapturedView, _events: &mut dyn FnMut(ScanEvent)) -> Result<String, ScanError> {
        let t = Instant::now();
        let mask = extract_silhouette(&view.frame.image, &self.params);
        self.timings.silhouette += t.elapsed().as_secs_f64();
        self.silhouette_pixels += mask.count() as u64;
        let cam = self.camera.for_turntable_angle(view.angle_deg);
        let t = Instant::now();
        let stats = self.carver.add_view(&cam, &mask).map_err(ScanError::Carve)?;
        self.timings.carve += t.elapsed().as_secs_f64();
        self.views.push((cam, mask));
        if self.method.is_photo() {
            self.images.push(view.frame.image);
        }
        Ok(format!("carved: {} voxels left", stats.occupied))
    }

    /// The visual hull carved so far (the photo methods refine it at the end).
    fn preview(&self, max_points: usize) -> Option<crate::pipeline::PointCloud> {
        preview::from_occupancy(self.carver.occupancy(), max_points)
    }

    fn finish(self, finish: Finish<'_>) -> Result<Outcome, ScanError> {
        let Finish { truth, timings, events, .. } = finish;
        timings.silhouette += self.timings.silhouette;
        timings.carve += self.timings.carve;
        let images: Vec<&RgbImage> = self.images.iter().collect();
        let hull = HullResult { method: self.method, carver: self.carver, views: self.views, images: &images };
        outcome_from_hull(hull, &self.photo, self.smooth_radius, self.silhouette_pixels, truth, timings, events)
    }
}

/// A carved visual hull and the views it was carved from.
pub(crate) struct HullResult<'a> {
    /// `space-carving`, `voxel-coloring` or `space-carving-photo`.
    pub method: Method,
    /// The carver holding the hull.
    pub carver: SpaceCarver,
    /// Cameras (object frame) and silhouettes.
    pub views: Vec<(CameraModel, Mask)>,
    /// The views' images, in the same order (photo methods only).
    pub images: &'a [&'a RgbImage],
}

/// The result of a silhouette method from its hull: the hull itself meshed (`space-carving`), or the
/// photo-consistency carving and colouring of it. Shared by scans and `reconstruct --dataset`.
pub(crate) fn outcome_from_hull(
    hull: HullResult<'_>,
    photo_config: &PhotoConfig,
    smooth_radius: u32,
    silhouette_pixels: u64,
    truth: Option<&photo::Truth<'_>>,
    timings: &mut Timings,
    events: &mut dyn FnMut(ScanEvent),
) -> Result<Outcome, ScanError> {
    let HullResult { method, carver, views, images } = hull;
    let count = views.len();
    if !method.is_photo() {
        events(ScanEvent::Stage("mesh"));
        let t = Instant::now();
        let (mesh, mesh_handles) = extract_surface_reporting(carver.occupancy(), &MeshParams::smoothed(smooth_radius))
            .map_err(ScanError::Mesh)?;
        timings.mesh = t.elapsed().as_secs_f64();
        return Ok(Outcome {
            views: count,
            solid: carver.into_occupancy(),
            mesh,
            mesh_handles,
            cloud: None,
            voxel_colours: None,
            silhouettes: views,
            visual_hull: None,
            colour_error: None,
            details: MethodDetails::SpaceCarving(CarvingSummary { views: count, silhouette_pixels }),
        });
    }
    events(ScanEvent::Stage("photo-consistency"));
    let t = Instant::now();
    let photo_views: Vec<PhotoView<'_>> = views
        .iter()
        .zip(images)
        .map(|((camera, mask), image)| PhotoView { camera: *camera, image, mask: Some(mask) })
        .collect();
    let (solid, outputs) = photo::reconstruct_photo(method, photo_config, carver.occupancy(), &photo_views, truth)
        .map_err(ScanError::Photo)?;
    drop(photo_views);
    timings.carve += t.elapsed().as_secs_f64();
    events(ScanEvent::Stage("mesh"));
    let t = Instant::now();
    let (mut mesh, mesh_handles) =
        extract_surface_reporting(&solid, &MeshParams::smoothed(smooth_radius)).map_err(ScanError::Mesh)?;
    let (mesh_colours, voxel_colours) = outputs.colours(&mesh, &solid);
    mesh.colors = Some(mesh_colours);
    timings.mesh = t.elapsed().as_secs_f64();
    let voxel_colours = Some(voxel_colours);
    Ok(Outcome {
        views: count,
        visual_hull: Some((carver.into_occupancy(), outputs.visual_hull.clone())),
        solid,
        mesh,
        mesh_handles,
        cloud: None,
        voxel_colours,
        silhouettes: views,
        colour_error: outputs.colour_error,
        details: MethodDetails::Photo(outputs.report),
    })
}

//! One whole job, from inputs to files on disk: [`run_scan`] drives a rig (acquisition on the thread
//! that owns the devices, reconstruction on this one as views arrive); `reconstruct` runs the same
//! pipeline on a calibrated image set on disk. Both write the same outputs (see [`output`]).

pub mod depth;
pub mod laser;
pub mod output;
pub mod photo;
pub mod reconstruct;
pub mod report;
pub mod shadow;
pub mod structured;

use std::path::{Path, PathBuf};
use std::sync::mpsc;
use std::time::Instant;

use crate::acquisition::{self, AcquisitionError, CancelToken, CapturedView, Progress};
use crate::config::RigConfig;
use crate::devices::{build_rig, DeviceError, Rig};
use crate::geometry::{CameraModel, VoxelGrid};
use crate::pipeline::{
    extract_silhouette, CarveError, ExportError, Mask, MeshError, Occupancy, SilhouetteParams, SpaceCarver, View,
};

pub use output::{FrameMeta, OutputDir};
pub use report::{GroundTruth, Report, Timings, VisualHull};

/// Why a scan failed. Frames captured before the failure stay in `frames/`; no `report.json` is
/// written, so a failed scan is never mistaken for a result.
#[derive(Debug, thiserror::Error)]
pub enum ScanError {
    /// The output directory cannot be used.
    #[error("output directory {path}: {what}")]
    OutputDir {
        /// The directory.
        path: PathBuf,
        /// What failed.
        what: &'static str,
        /// Why.
        #[source]
        source: std::io::Error,
    },
    /// A device could not be opened.
    #[error("cannot open the rig's devices")]
    OpenDevices(#[source] DeviceError),
    /// The acquisition stopped.
    #[error("acquisition failed")]
    Acquisition(#[source] AcquisitionError),
    /// A result file could not be written.
    #[error("cannot write results")]
    Export(#[source] ExportError),
    /// A frame could not be encoded as PNG.
    #[error("cannot encode frame {path}")]
    EncodeFrame {
        /// The frame file.
        path: PathBuf,
        /// The encoder's error.
        #[source]
        source: image::ImageError,
    },
    /// The report could not be serialised.
    #[error("cannot serialise report.json")]
    EncodeReport(#[source] serde_json::Error),
    /// A frame's metadata file of an interrupted scan cannot be read back.
    #[error("cannot parse frame metadata {path}")]
    FrameMeta {
        /// The metadata file.
        path: PathBuf,
        /// The parser's error.
        #[source]
        source: serde_json::Error,
    },
    /// Carving failed (an unusable grid or a view whose mask does not fit its camera).
    #[error("space carving failed")]
    Carve(#[source] CarveError),
    /// Surface extraction failed.
    #[error("surface extraction failed")]
    Mesh(#[source] MeshError),
    /// Photo-consistency reconstruction failed.
    #[error("photo-consistency reconstruction failed")]
    Photo(#[source] crate::pipeline::PhotoError),
    /// The acquisition thread could not be started.
    #[error("cannot start the acquisition thread")]
    StartAcquisition(#[source] std::io::Error),
    /// The acquisition thread died.
    #[error("the acquisition thread panicked")]
    AcquisitionPanicked,
    /// Shadow detection or shadow carving failed.
    #[error("shadow carving failed")]
    Shadow(#[source] shadow::ShadowScanError),
    /// Depth fusion rejected its input.
    #[error("depth fusion failed")]
    DepthFusion(#[source] crate::pipeline::DepthFusionError),
    /// Laser stripe triangulation or the point cloud failed.
    #[error("laser scanning failed")]
    Laser(#[source] laser::LaserScanError),
    /// Structured-light decoding, triangulation or fusion failed.
    #[error("structured light failed")]
    StructuredLight(#[source] structured::StructuredLightError),
}

/// What a running scan tells its caller.
#[derive(Debug, Clone)]
pub enum ScanEvent {
    /// Acquisition progress.
    Acquisition(Progress),
    /// A view went through the pipeline.
    ViewProcessed {
        /// 0-based position.
        position: usize,
        /// Voxels still occupied after carving with it.
        occupied: u64,
    },
    /// The pipeline moved on to a final stage (`mesh`, `export`, `evaluate`).
    Stage(&'static str),
}

/// Run an acquisition `sequence` on a thread of its own (it owns the rig's devices for the whole
/// sequence) while `process` handles each view on this thread as it arrives, over a bounded channel so
/// a slow pipeline slows the rig instead of piling up frames. The sequence's progress is forwarded to
/// `events`. The first error of `process` stops the pipeline: dropping the receiver makes the sequence
/// stop with `PipelineGone` and park, and that error is returned rather than the acquisition's.
/// Returns the acquisition summary and the sequence's busy time, seconds.
pub(crate) fn acquire_and_process<V: Send>(
    rig: &mut Rig,
    sequence: impl FnOnce(
            &mut Rig,
            &mpsc::SyncSender<V>,
            &mut dyn FnMut(&Progress),
        ) -> Result<acquisition::AcquisitionSummary, AcquisitionError>
        + Send,
    events: &mut dyn FnMut(ScanEvent),
    mut process: impl FnMut(V, &mut dyn FnMut(ScanEvent)) -> Result<(), ScanError>,
) -> Result<(acquisition::AcquisitionSummary, f64), ScanError> {
    let (tx, rx) = mpsc::sync_channel::<V>(4);
    let (progress_tx, progress_rx) = mpsc::channel::<Progress>();
    let mut pipeline_error = None;
    let (result, busy_s) = std::thread::scope(|scope| {
        let acquisition = std::thread::Builder::new()
            .name("acquisition".into())
            .spawn_scoped(scope, move || {
                let t = Instant::now();
                let result = sequence(rig, &tx, &mut |p| {
                    let _ = progress_tx.send(p.clone());
                });
                (result, t.elapsed().as_secs_f64())
            })
            .map_err(ScanError::StartAcquisition)?;
        for view in rx.iter() {
            for p in progress_rx.try_iter() {
                events(ScanEvent::Acquisition(p));
            }
            if let Err(e) = process(view, events) {
                pipeline_error = Some(e);
                break;
            }
        }
        drop(rx);
        acquisition.join().map_err(|_| ScanError::AcquisitionPanicked)
    })?;
    for p in progress_rx.try_iter() {
        events(ScanEvent::Acquisition(p));
    }
    if let Some(e) = pipeline_error {
        return Err(e);
    }
    Ok((result.map_err(ScanError::Acquisition)?, busy_s))
}

/// The silhouette parameters of a rig file.
pub fn silhouette_params(config: &RigConfig) -> SilhouetteParams {
    let s = &config.reconstruction.silhouette;
    SilhouetteParams { threshold: s.threshold as f32, background: s.background, dilate: s.dilate_px, erode: s.erode_px }
}

/// Scan the rig described by `config` and write the results into `out`.
pub fn run_scan(
    config: &RigConfig,
    out: &Path,
    cancel: &CancelToken,
    events: &mut dyn FnMut(ScanEvent),
) -> Result<Report, ScanError> {
    if config.reconstruction.method == crate::config::Method::ShadowCarving {
        return shadow::run_shadow_scan(config, out, None, cancel, events);
    }
    if config.reconstruction.method == crate::config::Method::DepthFusion {
        return depth::run_depth_scan(config, out, cancel, events);
    }
    if config.reconstruction.method == crate::config::Method::Laser {
        return laser::run_laser_scan(config, out, None, cancel, events);
    }
    if config.reconstruction.method == crate::config::Method::StructuredLight {
        return structured::run_structured_light_scan(config, out, cancel, events);
    }
    let started = Instant::now();
    let out = OutputDir::prepare(out)?;
    let mut rig = build_rig(config).map_err(ScanError::OpenDevices)?;
    scan_into(&mut rig, config, &out, 0, started, cancel, events)
}

/// Scan with an already opened `rig` into `out`. With `resume`, the frames already in `out/frames`
/// (positions 0..k with both `pos_NNN.png` and its `pos_NNN.json`) are reused and the acquisition
/// starts at position k; without it, `out` is prepared afresh like [`run_scan`] does.
pub fn run_scan_with_rig(
    rig: &mut Rig,
    config: &RigConfig,
    out: &Path,
    resume: bool,
    cancel: &CancelToken,
    events: &mut dyn FnMut(ScanEvent),
) -> Result<Report, ScanError> {
    let started = Instant::now();
    let (out, first) = if resume {
        let out = OutputDir::reopen(out)?;
        let first = out.completed_frames(config.scan.positions as usize);
        (out, first)
    } else {
        (OutputDir::prepare(out)?, 0)
    };
    scan_into(rig, config, &out, first, started, cancel, events)
}

fn scan_into(
    rig: &mut Rig,
    config: &RigConfig,
    out: &OutputDir,
    first: usize,
    started: Instant,
    cancel: &CancelToken,
    events: &mut dyn FnMut(ScanEvent),
) -> Result<Report, ScanError> {
    let sim = rig.sim.clone();
    let camera = config.camera.model();
    let recon = &config.reconstruction;
    let grid = VoxelGrid::from_resolution(&recon.bbox(), recon.resolution);
    let params = silhouette_params(config);
    let mut carver = SpaceCarver::new(grid).map_err(ScanError::Carve)?;
    let mut timings = Timings::default();
    let mut views: Vec<(CameraModel, Mask)> = Vec::with_capacity(config.scan.positions as usize);
    // The photo-consistency methods need the images too.
    let mut images: Vec<image::RgbImage> = Vec::new();
    let mut carve_one = |position: usize, angle_deg: f64, image: &image::RgbImage, timings: &mut Timings| {
        let t = Instant::now();
        let mask = extract_silhouette(image, &params);
        timings.silhouette += t.elapsed().as_secs_f64();
        let cam = camera.for_turntable_angle(angle_deg);
        let t = Instant::now();
        let stats = carver.add_view(&cam, &mask).map_err(ScanError::Carve)?;
        timings.carve += t.elapsed().as_secs_f64();
        views.push((cam, mask));
        if recon.method.is_photo() {
            images.push(image.clone());
        }
        Ok::<ScanEvent, ScanError>(ScanEvent::ViewProcessed { position, occupied: stats.occupied })
    };

    // Frames of an interrupted run, in position order.
    for position in 0..first {
        let (meta, image) = out.read_frame(position)?;
        events(carve_one(position, meta.angle_deg, &image, &mut timings)?);
    }

    let plan = config.scan.clone();
    let (mut summary, capture_s) = acquire_and_process(
        rig,
        |rig, tx, progress| acquisition::run_turntable_scan_from(rig, &plan, first, tx, cancel, progress),
        events,
        |view: CapturedView, events| {
            out.write_frame(&view)?;
            events(carve_one(view.position, view.angle_deg, &view.frame.image, &mut timings)?);
            Ok(())
        },
    )?;
    summary.views += first;
    timings.capture = capture_s;

    let truth = sim.as_ref().map(|world| {
        events(ScanEvent::Stage("ground truth"));
        let scene = world.scene();
        let name = config.sim.as_ref().map_or_else(String::new, |s| s.scene.clone());
        (name, Occupancy::from_fn(grid, |p| scene.contains(&p)))
    });
    let carving_views: Vec<View<'_>> = views.iter().map(|(camera, mask)| View { camera: *camera, mask }).collect();
    let photo = if recon.method.is_photo() {
        events(ScanEvent::Stage("photo-consistency"));
        let t = Instant::now();
        let photo_views: Vec<crate::pipeline::PhotoView<'_>> = views
            .iter()
            .zip(&images)
            .map(|((camera, mask), image)| crate::pipeline::PhotoView { camera: *camera, image, mask: Some(mask) })
            .collect();
        let colour_at = |p: &nalgebra::Vector3<f64>| sim.as_ref().map_or([0, 0, 0], |w| w.scene().colour_at(p));
        let t_truth = truth.as_ref().map(|(_, occ)| photo::Truth { occupancy: occ, colour_at: &colour_at });
        let result =
            photo::reconstruct_photo(recon.method, &recon.photo, carver.occupancy(), &photo_views, t_truth.as_ref())
                .map_err(ScanError::Photo)?;
        timings.carve += t.elapsed().as_secs_f64();
        Some(result)
    } else {
        None
    };
    let (photo_occupancy, photo_outputs) = match photo {
        Some((occ, outputs)) => (Some(occ), Some(outputs)),
        None => (None, None),
    };
    let report = out.write_results(output::Results {
        source: config.rig.name.clone(),
        method: recon.method.name(),
        occupancy: photo_occupancy.as_ref().unwrap_or(carver.occupancy()),
        views: &carving_views,
        smooth_radius: recon.mesh.smooth_radius,
        truth: truth.as_ref().map(|(name, occ)| (name.as_str(), occ)),
        frames: Some(summary),
        timings,
        started,
        events,
        photo: photo_outputs,
    })?;
    Ok(report)
}

//! The scan flow of method `shadow-carving`: per-light acquisition (an ambient frame and one frame per
//! shadow light at each position), the visual hull from silhouettes of the brightest composite, shadow
//! detection per position, then shadow carving of the hull, and the usual outputs. The report gives
//! the result's and the hull's overlap with the simulated truth.
//!
//! Frames are written as `frames/pos_NNN_ambient.png` and `frames/pos_NNN_light_K.png`.

use std::path::{Path, PathBuf};
use std::time::Instant;

use image::RgbImage;
use nalgebra::Vector3;

use super::output::{self, OutputDir};
use super::report::{Report, Timings, VisualHull};
use super::{silhouette_params, ScanError, ScanEvent};
use crate::acquisition::{self, CancelToken, PerLightView};
use crate::config::RigConfig;
use crate::devices::build_rig;
use crate::geometry::{turntable_rotation, CameraModel, VoxelGrid};
use crate::pipeline::export::write_atomic;
use crate::pipeline::{
    carve_shadows, detect_shadows, extract_silhouette, Mask, Occupancy, ShadowCarveError, ShadowCarveParams,
    ShadowError, ShadowParams, ShadowView, SpaceCarver,
};

/// Why the shadow part of a scan failed.
#[derive(Debug, thiserror::Error)]
pub enum ShadowScanError {
    /// Light positions given to the flow do not match the plan's shadow lights.
    #[error("{given} light positions given for {expected} shadow lights")]
    LightCount {
        /// Positions given.
        given: usize,
        /// `scan.shadow_lights` entries.
        expected: usize,
    },
    /// A shadow light has no configured position.
    #[error("shadow light {index} is not in [[lights.light]]")]
    UnknownLight {
        /// The light index.
        index: usize,
    },
    /// The frames of a position could not be compared.
    #[error("shadow detection at position {position}")]
    Detect {
        /// 0-based position.
        position: usize,
        /// Why.
        #[source]
        source: ShadowError,
    },
    /// The carving rejected its input.
    #[error("shadow carving")]
    Carve(#[source] ShadowCarveError),
}

/// What shadow carving did, for `report.json`.
#[derive(Debug, Clone, serde::Serialize)]
pub struct ShadowSummary {
    /// The shadow lights, by index.
    pub lights: Vec<usize>,
    /// Their positions used for carving, rig frame, metres (configured or calibrated).
    pub light_positions_m: Vec<[f64; 3]>,
    /// Whether the positions came from a light calibration rather than the rig file.
    pub calibrated_positions: bool,
    /// Voxels removed from the hull.
    pub removed_voxels: u64,
    /// Sweeps over all (view, light) pairs.
    pub sweeps: u32,
    /// Whether the last sweep removed nothing.
    pub converged: bool,
    /// Shadow pixels over all positions and lights (after erosion).
    pub shadow_pixels: u64,
    /// Unknown pixels (too dark, saturated) over all positions.
    pub unknown_pixels: u64,
    /// Seconds spent detecting shadows.
    pub detect_s: f64,
    /// Seconds spent carving with shadows.
    pub carve_s: f64,
}

/// Per-pixel maximum of the frames: every surface point lit by at least one light, for silhouettes.
fn composite(ambient: &RgbImage, lit: &[&RgbImage]) -> RgbImage {
    let mut out = ambient.clone();
    for f in lit {
        if f.dimensions() != out.dimensions() {
            continue;
        }
        for (o, &p) in out.iter_mut().zip(f.as_raw()) {
            *o = (*o).max(p);
        }
    }
    out
}

fn write_png(out: &OutputDir, name: String, image: &RgbImage) -> Result<(), ScanError> {
    let dir = out.path().join("frames");
    std::fs::create_dir_all(&dir).map_err(|source| ScanError::OutputDir {
        path: dir.clone(),
        what: "cannot create it",
        source,
    })?;
    let file: PathBuf = dir.join(name);
    let mut png = Vec::with_capacity(image.len() / 2);
    image
        .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .map_err(|source| ScanError::EncodeFrame { path: file.clone(), source })?;
    write_atomic(&file, &png).map_err(ScanError::Export)
}

/// Scan the rig described by `config` with shadow carving and write the results into `out`.
///
/// `light_positions_m` overrides the configured positions of `scan.shadow_lights` (rig frame, metres,
/// in the same order), e.g. with the output of [`crate::pipeline::light_calibration`]; `None` uses the
/// positions of `[[lights.light]]`.
pub fn run_shadow_scan(
    config: &RigConfig,
    out: &Path,
    light_positions_m: Option<&[Vector3<f64>]>,
    cancel: &CancelToken,
    events: &mut dyn FnMut(ScanEvent),
) -> Result<Report, ScanError> {
    let started = Instant::now();
    let plan = config.scan.clone();
    let shadow_err = ScanError::Shadow;
    let lights: Vec<Vector3<f64>> = match light_positions_m {
        Some(p) if p.len() != plan.shadow_lights.len() => {
            return Err(shadow_err(ShadowScanError::LightCount { given: p.len(), expected: plan.shadow_lights.len() }))
        }
        Some(p) => p.to_vec(),
        None => plan
            .shadow_lights
            .iter()
            .map(|&index| {
                config
                    .lights
                    .as_ref()
                    .and_then(|l| l.lights.get(index))
                    .map(|l| Vector3::from(l.position_m))
                    .ok_or(ShadowScanError::UnknownLight { index })
            })
            .collect::<Result<_, _>>()
            .map_err(shadow_err)?,
    };
    let out = OutputDir::prepare(out)?;
    let mut rig = build_rig(config).map_err(ScanError::OpenDevices)?;
    let sim = rig.sim.clone();
    let camera = config.camera.model();
    let recon = &config.reconstruction;
    let grid = VoxelGrid::from_resolution(&recon.bbox(), recon.resolution);
    let params = silhouette_params(config);
    let shadow_params = ShadowParams::default();
    let mut carver = SpaceCarver::new(grid).map_err(ScanError::Carve)?;
    let mut timings = Timings::default();
    let mut views: Vec<(CameraModel, Mask)> = Vec::with_capacity(plan.positions as usize);
    // Per (position, light): object-frame camera, object-frame light, shadow mask.
    let mut shadow_views: Vec<(CameraModel, Vector3<f64>, Mask)> = Vec::new();
    let (mut shadow_pixels, mut unknown_pixels, mut detect_s) = (0u64, 0u64, 0.0f64);

    let (summary, capture_s) = super::acquire_and_process(
        &mut rig,
        |rig, tx, progress| acquisition::run_per_light_scan(rig, &plan, tx, cancel, progress),
        events,
        |view: PerLightView, events| {
            let done = process_view(&out, &view, &camera, &lights, &params, &shadow_params, &mut carver, &mut timings)?;
            shadow_pixels += done.shadows.iter().map(|m| m.count() as u64).sum::<u64>();
            unknown_pixels += done.unknown;
            detect_s += done.detect_s;
            let to_obj = turntable_rotation(-view.angle_deg);
            for (mask, light) in done.shadows.into_iter().zip(&lights) {
                shadow_views.push((done.camera, to_obj * light, mask));
            }
            events(ScanEvent::ViewProcessed { position: view.position, occupied: done.occupied });
            views.push((done.camera, done.silhouette));
            Ok(())
        },
    )?;
    timings.capture = capture_s;

    events(ScanEvent::Stage("shadow carving"));
    let t = Instant::now();
    let hull = carver.occupancy();
    let carving: Vec<ShadowView<'_>> = shadow_views
        .iter()
        .map(|(camera, light_m, shadow)| ShadowView { camera: *camera, light_m: *light_m, shadow })
        .collect();
    let (carved, stats) = carve_shadows(hull, &carving, &ShadowCarveParams::default())
        .map_err(|e| shadow_err(ShadowScanError::Carve(e)))?;
    let carve_s = t.elapsed().as_secs_f64();
    timings.carve += carve_s;
    tracing::info!(removed = stats.removed, sweeps = stats.sweeps, seconds = carve_s, "shadow carving done");

    let truth = sim.as_ref().map(|world| {
        events(ScanEvent::Stage("ground truth"));
        let scene = world.scene();
        let name = config.sim.as_ref().map_or_else(String::new, |s| s.scene.clone());
        (name, Occupancy::from_fn(grid, |p| scene.contains(&p)))
    });
    let hull_overlap = truth.as_ref().and_then(|(_, t)| hull.iou_and_containment(t).ok());
    let visual_hull = VisualHull {
        iou: hull_overlap.map(|o| o.iou),
        containment: hull_overlap.map(|o| o.containment),
        voxels: hull.count(),
        volume_m3: hull.volume_m3(),
        colour_error: None,
        reprojection_error: None,
    };
    let carving_views: Vec<crate::pipeline::View<'_>> =
        views.iter().map(|(camera, mask)| crate::pipeline::View { camera: *camera, mask }).collect();
    let mut report = out.write_results(output::Results {
        source: config.rig.name.clone(),
        method: recon.method.name(),
        occupancy: &carved,
        views: &carving_views,
        smooth_radius: recon.mesh.smooth_radius,
        truth: truth.as_ref().map(|(name, occ)| (name.as_str(), occ)),
        frames: Some(summary),
        photo: None,
        timings,
        started,
        events,
    })?;
    report.visual_hull = Some(visual_hull);
    report.shadow_carving = Some(ShadowSummary {
        lights: plan.shadow_lights.clone(),
        light_positions_m: lights.iter().map(|l| [l.x, l.y, l.z]).collect(),
        calibrated_positions: light_positions_m.is_some(),
        removed_voxels: stats.removed,
        sweeps: stats.sweeps,
        converged: stats.converged,
        shadow_pixels,
        unknown_pixels,
        detect_s,
        carve_s,
    });
    report.timings_s.total = started.elapsed().as_secs_f64();
    // Rewritten atomically with the shadow carving's sections.
    let json = serde_json::to_vec_pretty(&report).map_err(ScanError::EncodeReport)?;
    write_atomic(&out.path().join("report.json"), &json).map_err(ScanError::Export)?;
    Ok(report)
}

struct ProcessedView {
    camera: CameraModel,
    silhouette: Mask,
    shadows: Vec<Mask>,
    unknown: u64,
    occupied: u64,
    detect_s: f64,
}

#[allow(clippy::too_many_arguments)]
fn process_view(
    out: &OutputDir,
    view: &PerLightView,
    camera: &CameraModel,
    lights: &[Vector3<f64>],
    params: &crate::pipeline::SilhouetteParams,
    shadow_params: &ShadowParams,
    carver: &mut SpaceCarver,
    timings: &mut Timings,
) -> Result<ProcessedView, ScanError> {
    write_png(out, format!("pos_{:03}_ambient.png", view.position), &view.ambient.image)?;
    for (light, frame) in &view.lit {
        write_png(out, format!("pos_{:03}_light_{light}.png", view.position), &frame.image)?;
    }
    if view.lit.len() != lights.len() {
        return Err(ScanError::Shadow(ShadowScanError::LightCount { given: lights.len(), expected: view.lit.len() }));
    }
    let lit: Vec<&RgbImage> = view.lit.iter().map(|(_, f)| &f.image).collect();
    let t = Instant::now();
    let silhouette = extract_silhouette(&composite(&view.ambient.image, &lit), params);
    timings.silhouette += t.elapsed().as_secs_f64();
    let cam = camera.for_turntable_angle(view.angle_deg);
    let t = Instant::now();
    let stats = carver.add_view(&cam, &silhouette).map_err(ScanError::Carve)?;
    timings.carve += t.elapsed().as_secs_f64();
    let t = Instant::now();
    let maps = detect_shadows(&view.ambient.image, &lit, shadow_params)
        .map_err(|source| ScanError::Shadow(ShadowScanError::Detect { position: view.position, source }))?;
    Ok(ProcessedView {
        camera: cam,
        silhouette,
        shadows: maps.shadows,
        unknown: maps.unknown.count() as u64,
        occupied: stats.occupied,
        detect_s: t.elapsed().as_secs_f64(),
    })
}

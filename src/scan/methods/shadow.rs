//! The flow of method `shadow-carving`: per-light acquisition (an ambient frame and one frame per
//! shadow light at each position), the visual hull from silhouettes of the brightest composite, shadow
//! detection per position, and shadow carving of the hull, all per position as it arrives: the
//! carving is restricted to the hull so far and carves with the new position's shadows
//! ([`ShadowCarver`]), so after the last frame only that position's work and the mesh remain. The
//! result equals carving the final hull with every position's shadows at the end. The report gives
//! the result's and the hull's overlap with the simulated truth. The light positions are the rig
//! file's (or its calibration file's) `[[lights.light]]` positions.
//!
//! Frames are stored as `frames/pos_NNN_ambient.png` and `frames/pos_NNN_light_K.png`.

use crate::scan::preview;
use std::time::Instant;

use image::RgbImage;
use nalgebra::Vector3;

use super::{frame_name, stored_frame};
use crate::acquisition::{self, PerLightView};
use crate::config::{Method, RigConfig, ScanPlan};
use crate::geometry::{turntable_rotation, CameraModel, VoxelGrid};
use crate::pipeline::{
    detect_shadows, extract_silhouette, extract_surface_reporting, Mask, MeshParams, ShadowCarveError,
    ShadowCarveParams, ShadowCarver, ShadowError, ShadowParams, SilhouetteParams, SpaceCarver,
};
use crate::scan::flow::{Finish, FrameDir, Outcome, PositionView, ScanFlow, Sequence, ViewRecord};
use crate::scan::report::{MethodDetails, Timings, VisualHull};
use crate::scan::{silhouette_params, ScanError, ScanEvent};

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
    /// Voxels removed from the hull.
    pub removed_voxels: u64,
    /// Rounds of re-tests while carving, over all positions (`ShadowCarveStats::sweeps`).
    pub sweeps: u32,
    /// Whether the carving ran until nothing more could go (no safety bound stopped it).
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

impl PositionView for PerLightView {
    fn position(&self) -> usize {
        self.position
    }
    fn angle_deg(&self) -> f64 {
        self.angle_deg
    }
    fn sequence(&self) -> u64 {
        self.ambient.sequence
    }
    fn stale_discarded(&self) -> u32 {
        self.stale_discarded
    }
}

/// Shadow carving.
#[derive(Debug)]
pub struct ShadowFlow {
    plan: ScanPlan,
    camera: CameraModel,
    /// The shadow lights' positions, rig frame, metres, in the order of `plan.shadow_lights`.
    lights: Vec<Vector3<f64>>,
    params: SilhouetteParams,
    shadow_params: ShadowParams,
    smooth_radius: u32,
    carver: SpaceCarver,
    views: Vec<(CameraModel, Mask)>,
    /// The shadow carving so far (from the first position on).
    shadow: Option<ShadowCarver>,
    /// Seconds spent carving with shadows.
    shadow_s: f64,
    shadow_pixels: u64,
    unknown_pixels: u64,
    detect_s: f64,
    timings: Timings,
}

impl ShadowFlow {
    /// The flow of `config` (method `shadow-carving`).
    pub fn new(config: &RigConfig) -> Result<ShadowFlow, ScanError> {
        let plan = config.scan.clone();
        let lights: Vec<Vector3<f64>> = plan
            .shadow_lights
            .iter()
            .map(|&index| {
                config
                    .lights
                    .as_ref()
                    .and_then(|l| l.lights.get(index))
                    .map(|l| Vector3::from(l.position_m))
                    .ok_or(ScanError::Shadow(ShadowScanError::UnknownLight { index }))
            })
            .collect::<Result<_, _>>()?;
        let recon = &config.reconstruction;
        let grid = VoxelGrid::from_resolution(&recon.bbox(), recon.resolution);
        Ok(ShadowFlow {
            camera: config.camera.model(),
            lights,
            params: silhouette_params(config),
            shadow_params: ShadowParams::default(),
            smooth_radius: recon.mesh.smooth_radius,
            carver: SpaceCarver::new(grid).map_err(ScanError::Carve)?,
            views: Vec::with_capacity(plan.positions as usize),
            shadow: None,
            shadow_s: 0.0,
            shadow_pixels: 0,
            unknown_pixels: 0,
            detect_s: 0.0,
            timings: Timings::default(),
            plan,
        })
    }
}

impl ScanFlow for ShadowFlow {
    type View = PerLightView;

    fn method(&self) -> Method {
        Method::ShadowCarving
    }

    fn sequence(&self, first: usize) -> Sequence<PerLightView> {
        let plan = self.plan.clone();
        Box::new(move |rig, tx, cancel, progress| {
            acquisition::run_per_light_scan(rig, &plan, first, tx, cancel, progress)
        })
    }

    fn save(&self, frames: &FrameDir, view: &PerLightView) -> Result<(Vec<String>, Vec<usize>), ScanError> {
        let mut files = vec![frames.write_rgb(&frame_name(view.position, "_ambient.png"), &view.ambient.image)?];
        for (light, frame) in &view.lit {
            files.push(frames.write_rgb(&frame_name(view.position, &format!("_light_{light}.png")), &frame.image)?);
        }
        Ok((files, Vec::new()))
    }

    fn load(&self, frames: &FrameDir, record: &ViewRecord) -> Result<PerLightView, ScanError> {
        let p = record.position;
        let ambient = stored_frame(frames.read_rgb(&frame_name(p, "_ambient.png"))?, record.sequence);
        let mut lit = Vec::with_capacity(self.plan.shadow_lights.len());
        for &light in &self.plan.shadow_lights {
            let image = frames.read_rgb(&frame_name(p, &format!("_light_{light}.png")))?;
            lit.push((light, stored_frame(image, record.sequence)));
        }
        Ok(PerLightView {
            position: p,
            angle_deg: record.angle_deg,
            ambient,
            lit,
            stale_discarded: record.stale_discarded,
        })
    }

    fn process(&mut self, view: PerLightView, _events: &mut dyn FnMut(ScanEvent)) -> Result<String, ScanError> {
        if view.lit.len() != self.lights.len() {
            return Err(ScanError::Shadow(ShadowScanError::LightCount {
                given: self.lights.len(),
                expected: view.lit.len(),
            }));
        }
        let lit: Vec<&RgbImage> = view.lit.iter().map(|(_, f)| &f.image).collect();
        let t = Instant::now();
        let silhouette = extract_silhouette(&composite(&view.ambient.image, &lit), &self.params);
        self.timings.silhouette += t.elapsed().as_secs_f64();
        let cam = self.camera.for_turntable_angle(view.angle_deg);
        let t = Instant::now();
        let stats = self.carver.add_view(&cam, &silhouette).map_err(ScanError::Carve)?;
        self.timings.carve += t.elapsed().as_secs_f64();
        let t = Instant::now();
        let maps = detect_shadows(&view.ambient.image, &lit, &self.shadow_params)
            .map_err(|source| ScanError::Shadow(ShadowScanError::Detect { position: view.position, source }))?;
        self.detect_s += t.elapsed().as_secs_f64();
        let shadows: u64 = maps.shadows.iter().map(|m| m.count() as u64).sum();
        self.shadow_pixels += shadows;
        self.unknown_pixels += maps.unknown.count() as u64;
        let to_obj = turntable_rotation(-view.angle_deg);
        let lights = self.lights.iter().map(|light| to_obj * light).zip(maps.shadows).collect();
        let t = Instant::now();
        let hull = self.carver.occupancy();
        let shadow = match &mut self.shadow {
            Some(shadow) => {
                shadow.restrict(hull).map_err(|e| ScanError::Shadow(ShadowScanError::Carve(e)))?;
                shadow
            }
            None => self.shadow.insert(
                ShadowCarver::new(hull, &ShadowCarveParams::default())
                    .map_err(|e| ScanError::Shadow(ShadowScanError::Carve(e)))?,
            ),
        };
        shadow.add_position(cam, lights).map_err(|e| ScanError::Shadow(ShadowScanError::Carve(e)))?;
        self.shadow_s += t.elapsed().as_secs_f64();
        self.views.push((cam, silhouette));
        Ok(format!("carved: {} voxels left, {shadows} shadow pixels", stats.occupied))
    }

    /// The visual hull carved so far (the shadows carve it further at the end).
    fn preview(&self, max_points: usize) -> Option<crate::pipeline::PointCloud> {
        preview::from_occupancy(self.carver.occupancy(), max_points)
    }

    fn finish(self, finish: Finish<'_>) -> Result<Outcome, ScanError> {
        let Finish { timings, events, .. } = finish;
        timings.silhouette += self.timings.silhouette;
        timings.carve += self.timings.carve;
        events(ScanEvent::Stage("shadow carving"));
        // The carving kept up with the positions; what is left is reading out the result.
        let t = Instant::now();
        let hull = self.carver.occupancy();
        let (carved, stats) = match &self.shadow {
            Some(shadow) => (shadow.occupancy(), shadow.stats()),
            None => (hull.clone(), Default::default()),
        };
        let removed = hull.count() - carved.count();
        let carve_s = self.shadow_s + t.elapsed().as_secs_f64();
        timings.carve += carve_s;
        tracing::info!(removed, rounds = stats.sweeps, seconds = carve_s, "shadow carving done");
        events(ScanEvent::Stage("mesh"));
        let t = Instant::now();
        let (mesh, mesh_handles) =
            extract_surface_reporting(&carved, &MeshParams::smoothed(self.smooth_radius)).map_err(ScanError::Mesh)?;
        timings.mesh = t.elapsed().as_secs_f64();
        let hull_summary = VisualHull {
            iou: None,
            containment: None,
            voxels: hull.count(),
            volume_m3: hull.volume_m3(),
            colour_error: None,
            reprojection_error: None,
        };
        let views = self.views.len();
        Ok(Outcome {
            views,
            solid: carved,
            mesh,
            mesh_handles,
            cloud: None,
            voxel_colours: None,
            silhouettes: self.views,
            visual_hull: Some((self.carver.into_occupancy(), hull_summary)),
            colour_error: None,
            details: MethodDetails::ShadowCarving(ShadowSummary {
                lights: self.plan.shadow_lights.clone(),
                light_positions_m: self.lights.iter().map(|l| [l.x, l.y, l.z]).collect(),
                removed_voxels: removed,
                sweeps: stats.sweeps,
                converged: stats.converged,
                shadow_pixels: self.shadow_pixels,
                unknown_pixels: self.unknown_pixels,
                detect_s: self.detect_s,
                carve_s,
            }),
        })
    }
}

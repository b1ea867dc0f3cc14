//! The scan flow of method `structured-light`: at each turntable position the projector shows the
//! sequence of `[reconstruction.structured_light] coding` and the sequencer captures one fresh frame
//! per pattern (each pattern held for `exposure_ms`, a whole number of projector refreshes, when set):
//!
//! - `"gray"` / `"binary"`: the stripe sequence (column pairs, row pairs when `rows`, white, black),
//!   decoded with the thresholds and stripe-edge sub-pixel columns by default;
//! - `"phase-shift"`, `"debruijn"`, `"sweep"`: the [`PatternSet`] patterns (RGB) followed by one
//!   full-white frame (colour of the points, the dark-background free-space test, the visual hull,
//!   and for De Bruijn the albedo normalisation of the colour frame), decoded by
//!   [`PatternSet::decode`]. With `gamma_compensation`, the projector response is measured first
//!   (uniform grey levels at the first position, [`ResponseCurve::fit`]) and the phase-shift fringes
//!   are pre-distorted with its inverse; the fit is reported under `structured_light.response`.
//!
//! Each stack is decoded into projector coordinates, triangulated with the calibrated camera and
//! projector in the object frame (the rig's turntable axis is the object frame's z axis), and the
//! view's range image is fused into a TSDF over the object-frame grid as it arrives. The merged
//! point cloud (normals from each range image, colours from the white frame), cleaned by a
//! statistical outlier test over its nearest neighbours, is written as `cloud.ply`; the mesh (`model.ply/stl/obj`) is read off the TSDF and its vertices moved onto the
//! zero crossing. On a simulated rig the report compares the mesh with the scene
//! (`ground_truth.chamfer_rel` = symmetric Chamfer distance / bounding-box diagonal, voxel IoU).
//!
//! Every captured frame is stored as `frames/pos_NNN_pattern_KK.png` (RGB, in projection order), and
//! the measured projector response, when compensation is on, as `frames/prepare.json`, so a scan can
//! be resumed and its captures decoded again with other settings.

use crate::scan::preview;
use std::time::Instant;

use super::frame_name;
use crate::acquisition::{self, CancelToken, PatternStack};
use crate::config::structured_light::{exposure_frames, PhaseUnwrapping, StripeCoding, StructuredLightConfig};
use crate::config::{Method, ProjectorConfig, RigConfig, ScanPlan};
use crate::devices::{Pattern, Rig};
use crate::geometry::{turntable_rotation, CameraModel, VoxelGrid};
use crate::pipeline::structured_light::debruijn::{DeBruijnDecodeParams, DeBruijnStripes};
use crate::pipeline::structured_light::gamma::{calibration_levels, GammaError, ResponseCurve};
use crate::pipeline::structured_light::phase::{PhaseDecodeParams, PhaseShiftPatterns, Unwrapping};
use crate::pipeline::structured_light::stripe::SweepingStripe;
use crate::pipeline::structured_light::{
    decode, interpolate_stripe_edges, CodesError, Coding, DecodeError, DecodeParams, GrayCodePatterns, PatternError,
    PatternSet, ProjectorCoords, ProjectorMap, RangeImage, TriangulateError, TriangulationParams, Triangulator,
};
use crate::pipeline::{
    extract_surface_reporting, CarveError, CloudError, DepthFusionError, FusionParams, Mask, MeshParams, PointCloud,
    SpaceCarver, Tsdf,
};
use crate::scan::flow::{Finish, FrameDir, Outcome, PositionView, ScanFlow, Sequence, ViewRecord};
use crate::scan::report::{MethodDetails, Timings, VisualHull};
use crate::scan::{ScanError, ScanEvent};
use crate::sim::SimWorld;

/// Why the structured-light part of a scan failed.
#[derive(Debug, thiserror::Error)]
pub enum StructuredLightError {
    /// The rig has no `[projector]`.
    #[error("method structured-light needs a [projector] in the rig file")]
    NoProjector,
    /// The pattern sequence cannot be laid out for the projector.
    #[error("pattern sequence for the projector")]
    Patterns(#[source] PatternError),
    /// The coding's pattern set cannot be laid out for the projector.
    #[error("pattern set of the coding for the projector")]
    Codes(#[source] CodesError),
    /// A position's frames did not decode with the coding's decoder.
    #[error("decoding the coded patterns at position {position}")]
    CodesDecode {
        /// 0-based position.
        position: usize,
        /// Why.
        #[source]
        source: CodesError,
    },
    /// The grey-level frames of the gamma measurement could not be captured.
    #[error("capturing the grey levels of the projector response measurement")]
    ResponseCapture(#[source] acquisition::AcquisitionError),
    /// The projector response could not be fitted to the grey-level frames.
    #[error("fitting the projector response (gamma) to the grey-level frames")]
    Response(#[source] GammaError),
    /// A position's frames did not decode.
    #[error("decoding the patterns at position {position}")]
    Decode {
        /// 0-based position.
        position: usize,
        /// Why.
        #[source]
        source: DecodeError,
    },
    /// A position delivered a different number of frames than patterns were shown.
    #[error("position {position} delivered {found} frames for {expected} patterns")]
    FrameCount {
        /// 0-based position.
        position: usize,
        /// Patterns shown.
        expected: usize,
        /// Frames delivered.
        found: usize,
    },
    /// A frame is not the camera's size.
    #[error(
        "frame {index} at position {position} is {found_width}x{found_height} pixels, the camera's {width}x{height}"
    )]
    FrameSize {
        /// 0-based position.
        position: usize,
        /// Frame index in the stack.
        index: usize,
        /// Camera width, pixels.
        width: u32,
        /// Camera height, pixels.
        height: u32,
        /// Frame width, pixels.
        found_width: u32,
        /// Frame height, pixels.
        found_height: u32,
    },
    /// Triangulation refused a position's data.
    #[error("triangulating position {position}")]
    Triangulate {
        /// 0-based position.
        position: usize,
        /// Why.
        #[source]
        source: TriangulateError,
    },
    /// `exposure_ms` is not a whole number of projector refreshes.
    #[error(
        "reconstruction.structured_light.exposure_ms = {exposure_ms} is not a whole multiple of \
         projector.frame_period_ms = {frame_period_ms}"
    )]
    Exposure {
        /// The exposure asked for, milliseconds.
        exposure_ms: f64,
        /// The projector's refresh period, milliseconds.
        frame_period_ms: f64,
    },
    /// The TSDF rejected its input.
    #[error("fusing the range images")]
    Fusion(#[source] DepthFusionError),
    /// The merged point cloud was rejected.
    #[error("merging the point clouds")]
    Cloud(#[source] CloudError),
    /// The visual hull of the white frames' silhouettes (for comparison) could not be carved.
    #[error("carving the visual hull")]
    Hull(#[source] CarveError),
}

/// The measured projector-camera response, for `report.json` and `frames/prepare.json`.
#[derive(Debug, Clone, Default, serde::Serialize, serde::Deserialize)]
pub struct ResponseSummary {
    /// Fitted exponent of the projector's input-to-light response (1 = linear).
    pub gamma: f64,
    /// Median camera level of projected black over the lit pixels (projector black + ambient), 8-bit grey.
    pub black: f64,
    /// Median camera level of projected white over the lit pixels, 8-bit grey.
    pub white: f64,
    /// Uniform grey levels projected for the fit, 8-bit input levels.
    pub levels: Vec<u8>,
    /// Whether the phase-shift fringes were pre-distorted with the fitted response's inverse.
    pub compensated: bool,
}

/// What the structured-light pipeline did, for `report.json` (key `structured_light`).
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct StructuredLightSummary {
    /// `"gray"`, `"binary"`, `"phase-shift"`, `"debruijn"` or `"sweep"`.
    pub coding: StripeCoding,
    /// Phase shift only: steps per period, fringe periods (projector pixels) and the unwrapping.
    pub phase: Option<PhaseSummary>,
    /// The projector response measured before the scan (`gamma_compensation = true`), else `None`.
    pub response: Option<ResponseSummary>,
    /// Each pattern stays on screen this long after it appeared (`exposure_ms`), milliseconds.
    pub exposure_ms: Option<f64>,
    /// Whether rows were projected (ray-ray triangulation) or only columns (ray-plane).
    pub rows: bool,
    /// Whether the columns were interpolated between stripe edges.
    pub subpixel: bool,
    /// Patterns projected per position.
    pub patterns_per_position: usize,
    /// Camera pixels per view (width × height).
    pub pixels_per_view: usize,
    /// Pixels that decoded, per view.
    pub decoded: Vec<usize>,
    /// Fraction of all camera pixels that decoded (0..1).
    pub valid_fraction: f64,
    /// Points kept, per view.
    pub points_per_view: Vec<usize>,
    /// Points in the merged cloud (`cloud.ply`), after outlier removal.
    pub points: usize,
    /// Points removed by the range-image neighbour test, all views.
    pub outliers: usize,
    /// Points removed from the merged cloud by the statistical outlier test.
    pub merged_outliers: usize,
    /// Seconds spent on the merged cloud's outlier removal (wall clock; it runs beside the
    /// meshing, which `timings_s.mesh` counts).
    pub merge_s: f64,
    /// Mesh vertices moved onto the TSDF's zero crossing.
    pub refined_vertices: usize,
    /// TSDF truncation distance, metres.
    pub truncation_m: f64,
    /// Simulated rig only: mean distance, metres, from each cloud point to where its camera ray
    /// really meets the scene (the triangulation error before fusion).
    pub point_error_mean_m: Option<f64>,
    /// Simulated rig only: root mean square of the same distances, metres.
    pub point_error_rms_m: Option<f64>,
    /// Seconds spent decoding.
    pub decode_s: f64,
    /// Seconds spent triangulating.
    pub triangulate_s: f64,
    /// Seconds spent integrating into the TSDF.
    pub integrate_s: f64,
}

/// The phase-shift settings used, for `report.json`.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct PhaseSummary {
    /// Phase steps per period.
    pub steps: usize,
    /// Fringe periods, projector pixels (fine first).
    pub periods_px: Vec<f64>,
    /// `"gray"` or `"multi-frequency"`.
    pub unwrapping: PhaseUnwrapping,
}

/// The [`PatternSet`] of `settings` for a `width` x `height` projector, or `None` for the Gray/binary
/// stripe codings (which the flow projects column-only with stripe-edge interpolation itself).
pub fn pattern_set(
    width: u32,
    height: u32,
    settings: &StructuredLightConfig,
) -> Result<Option<PatternSet>, CodesError> {
    let s = settings;
    Ok(Some(match s.coding {
        StripeCoding::Gray | StripeCoding::Binary => return Ok(None),
        StripeCoding::PhaseShift => {
            let period = s.periods_px.first().copied().unwrap_or(0.0);
            let unwrapping = match s.unwrapping {
                PhaseUnwrapping::Gray => Unwrapping::GrayCode,
                PhaseUnwrapping::MultiFrequency => {
                    Unwrapping::MultiFrequency { coarser_periods: s.periods_px.iter().skip(1).copied().collect() }
                }
            };
            let p = PhaseShiftPatterns::new(width, height, s.steps, period, unwrapping, s.rows)?;
            PatternSet::PhaseShift(p, PhaseDecodeParams { min_modulation: s.min_modulation })
        }
        StripeCoding::DeBruijn => PatternSet::DeBruijn(
            DeBruijnStripes::new(width, height, s.debruijn_colours, s.debruijn_window, s.stripe_px)?,
            DeBruijnDecodeParams::default(),
        ),
        StripeCoding::Sweep => PatternSet::SweepingStripe(
            SweepingStripe::new(width, height, s.stripe_px, s.sweep_step_px)?,
            s.sweep_min_contrast,
        ),
    }))
}

/// The coded colour frame divided, channel by channel, by the fully lit white frame (both RGB,
/// same size), scaled so a channel lit as brightly as under white reads 200: the surface's own colour
/// (albedo) cancels and the stripe colours remain, so a strongly coloured surface (the cup's red
/// bands have green and blue under half of red) does not turn the stripes' hues. Channels darker
/// than 8 grey levels under white read 0 (no light to compare).
fn albedo_normalised(coded: &[u8], white: &[u8]) -> Vec<u8> {
    coded
        .iter()
        .zip(white)
        .map(|(&c, &w)| if w < 8 { 0 } else { (u32::from(c) * 200 / u32::from(w)).min(255) as u8 })
        .collect()
}

/// A uniform RGB projector pattern of grey `level`.
fn uniform_pattern(level: u8, width: u32, height: u32) -> Pattern {
    Pattern { width, height, rgb: std::sync::Arc::new(vec![level; 3 * width as usize * height as usize]) }
}

/// Measures the projector-camera response before the scan: at the plan's first position the
/// projector shows uniform grey levels ([`calibration_levels`]) through the same sequencer as the
/// scan (waiting for each to be on screen), and [`ResponseCurve::fit`] fits gamma, black and white
/// levels to the luma of the pixels lit with at least `min_contrast` grey levels (the object and
/// any lit background).
fn measure_response(
    rig: &mut Rig,
    plan: &crate::config::ScanPlan,
    projector: &CameraModel,
    hold: std::time::Duration,
    min_contrast: f64,
    cancel: &CancelToken,
) -> Result<ResponseSummary, StructuredLightError> {
    let levels = calibration_levels();
    let patterns: Vec<Pattern> =
        levels.iter().map(|&l| uniform_pattern(l, projector.width, projector.height)).collect();
    let one = crate::config::ScanPlan { positions: 1, ..plan.clone() };
    let (tx, rx) = std::sync::mpsc::sync_channel(1);
    acquisition::run_structured_light_scan(rig, &one, 0, &patterns, hold, &tx, cancel, &mut |_| {})
        .map_err(StructuredLightError::ResponseCapture)?;
    drop(tx);
    let stack = rx.recv().map_err(|_| {
        StructuredLightError::ResponseCapture(acquisition::AcquisitionError::PipelineGone { position: 0 })
    })?;
    let greys: Vec<Vec<u8>> = stack.frames.iter().map(|f| image::imageops::grayscale(&f.image).into_raw()).collect();
    let images: Vec<&[u8]> = greys.iter().map(Vec::as_slice).collect();
    let curve = ResponseCurve::fit(&levels, &images, min_contrast).map_err(StructuredLightError::Response)?;
    tracing::info!(gamma = curve.gamma, black = curve.black, white = curve.white, "projector response measured");
    Ok(ResponseSummary { gamma: curve.gamma, black: curve.black, white: curve.white, levels, compensated: false })
}

/// The projector's calibrated model in the rig frame.
fn projector_model(config: &RigConfig) -> Option<CameraModel> {
    config.projector.as_ref().and_then(ProjectorConfig::model)
}

/// The pattern sequence of `settings` for a projector of `model`'s size, and the indices (into the
/// sequence) of the images projected: every column pair, the row pairs only with `rows`, white, black.
pub fn projected_patterns(
    model: &CameraModel,
    settings: &StructuredLightConfig,
) -> Result<(GrayCodePatterns, Vec<usize>), PatternError> {
    // The other codings do not use this sequence ([`pattern_set`] lays theirs out); Gray stands in.
    let coding = match settings.coding {
        StripeCoding::Binary => Coding::Binary,
        _ => Coding::Gray,
    };
    let seq = GrayCodePatterns::with_coding(model.width, model.height, coding)?;
    let cb = 2 * seq.column_bits() as usize;
    let rb = 2 * seq.row_bits() as usize;
    let mut used: Vec<usize> = (0..cb).collect();
    if settings.rows {
        used.extend(cb..cb + rb);
    }
    used.extend([seq.white_index(), seq.black_index()]);
    Ok((seq, used))
}

/// A grey pattern image as an RGB projector pattern.
fn to_pattern(grey: &[u8], width: u32, height: u32) -> Pattern {
    let rgb: Vec<u8> = grey.iter().flat_map(|&g| [g, g, g]).collect();
    Pattern { width, height, rgb: std::sync::Arc::new(rgb) }
}

/// Decodes one position's stack into projector coordinates. Without rows, the row pairs of the
/// sequence were not projected: the decoder is given (black, white) for each of them, which reads as
/// row bit 0 with full margin, so the row code is 0 and ignored (only columns are returned).
fn decode_stack(
    seq: &GrayCodePatterns,
    used: &[usize],
    greys: &[Vec<u8>],
    camera: &CameraModel,
    settings: &StructuredLightConfig,
    position: usize,
    map: &mut ProjectorMap,
) -> Result<ProjectorCoords, StructuredLightError> {
    let black = &greys[used.len() - 1];
    let white = &greys[used.len() - 2];
    let mut images: Vec<&[u8]> = vec![black.as_slice(); seq.count()];
    let mut filled = vec![false; seq.count()];
    for (k, &i) in used.iter().enumerate() {
        images[i] = greys[k].as_slice();
        filled[i] = true;
    }
    for (i, done) in filled.iter().enumerate() {
        // An unprojected row pair: pattern = black, inverse = white.
        if !done && i % 2 == 1 {
            images[i] = white.as_slice();
        }
    }
    let params = DecodeParams { black_threshold: settings.black_threshold, white_threshold: settings.white_threshold };
    decode(seq, &images, camera.width as usize, camera.height as usize, &params, map)
        .map_err(|source| StructuredLightError::Decode { position, source })?;
    Ok(if settings.subpixel {
        interpolate_stripe_edges(map, settings.rows)
    } else {
        ProjectorCoords::from_map(map, settings.rows)
    })
}

/// The depth map to fuse from a range image: the measured depth, 0 (free space) where the white frame
/// is darker than `free_below`, `NaN` (unknown) elsewhere.
fn fusion_depth(range: &RangeImage, white_grey: &[u8], free_below: u8) -> Vec<f32> {
    range
        .depth_m
        .iter()
        .zip(white_grey)
        .map(|(&d, &g)| {
            if d > 0.0 {
                d
            } else if g < free_below {
                0.0
            } else {
                f32::NAN
            }
        })
        .collect()
}

/// Distances from each point of `range` (rig frame, turntable at `angle_deg`) to the true surface
/// along its camera ray (`camera` in the object frame): `(sum, sum of squares, count)`, metres. A
/// point whose ray misses the scene is skipped (it cannot be scored).
fn point_errors(
    camera: &CameraModel,
    range: &RangeImage,
    angle_deg: f64,
    scene: &crate::sim::Scene,
) -> (f64, f64, usize) {
    let o = camera.centre();
    let to_object = turntable_rotation(-angle_deg);
    let w = range.width as usize;
    let (mut sum, mut sq, mut n) = (0.0, 0.0, 0);
    for (i, p) in range.points.iter().enumerate() {
        if range.depth_m[i] <= 0.0 {
            continue;
        }
        let d = camera.pixel_ray((i % w) as f64 + 0.5, (i / w) as f64 + 0.5);
        if let Some(hit) = scene.intersect(&o, &d, 0.0, f64::INFINITY) {
            let p = to_object * nalgebra::Vector3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
            let e = (p - hit.point).norm();
            sum += e;
            sq += e * e;
            n += 1;
        }
    }
    (sum, sq, n)
}

/// What `frames/prepare.json` holds: the response measured before the positions.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct Prepared {
    response: ResponseSummary,
}

impl PositionView for PatternStack {
    fn position(&self) -> usize {
        self.position
    }
    fn angle_deg(&self) -> f64 {
        self.angle_deg
    }
    fn sequence(&self) -> u64 {
        self.frames.first().map_or(0, |f| f.sequence)
    }
    fn stale_discarded(&self) -> u32 {
        self.stale_discarded
    }
}

/// Structured light.
#[derive(Debug)]
pub struct StructuredLightFlow {
    plan: ScanPlan,
    settings: StructuredLightConfig,
    projector: CameraModel,
    camera: CameraModel,
    seq: GrayCodePatterns,
    used: Vec<usize>,
    set: Option<PatternSet>,
    hold: std::time::Duration,
    /// The projected sequence (with the response compensation once it is known).
    patterns: Vec<Pattern>,
    tri: TriangulationParams,
    smooth_radius: u32,
    tsdf: Tsdf,
    hull: Option<SpaceCarver>,
    summary: StructuredLightSummary,
    cloud: PointCloud,
    map: ProjectorMap,
    /// The camera and projector in the rig frame, built at the first view and kept: views are
    /// triangulated in the rig frame and their points turned into the object frame.
    triangulator: Option<Triangulator>,
    /// The last view's range image (rig frame), its buffers reused from view to view.
    range: RangeImage,
    world: Option<SimWorld>,
    errors: (f64, f64, usize),
    timings: Timings,
}

impl StructuredLightFlow {
    /// The flow of `config` (method `structured-light`); `world` is the simulated scene, if any, for
    /// the triangulation error of each point.
    pub fn new(config: &RigConfig, world: Option<&SimWorld>) -> Result<StructuredLightFlow, ScanError> {
        let sl_err = ScanError::StructuredLight;
        let settings = config.reconstruction.structured_light.clone();
        let projector = projector_model(config).ok_or(sl_err(StructuredLightError::NoProjector))?;
        let (seq, used) =
            projected_patterns(&projector, &settings).map_err(|e| sl_err(StructuredLightError::Patterns(e)))?;
        let set = pattern_set(projector.width, projector.height, &settings)
            .map_err(|e| sl_err(StructuredLightError::Codes(e)))?;
        let frame_period_ms = config.projector.as_ref().map_or(0.0, ProjectorConfig::frame_period_ms);
        // Validation refuses an exposure that is not a whole number of refreshes; this re-check keeps
        // a hand-built config from reaching the sequencer with one.
        let hold = match settings.exposure_ms {
            Some(e) => {
                let frames = exposure_frames(e, frame_period_ms)
                    .ok_or(sl_err(StructuredLightError::Exposure { exposure_ms: e, frame_period_ms }))?;
                let hold_ms = if frame_period_ms > 0.0 { f64::from(frames) * frame_period_ms } else { e };
                std::time::Duration::from_secs_f64(hold_ms / 1000.0)
            }
            None => std::time::Duration::ZERO,
        };
        let recon = &config.reconstruction;
        let grid = VoxelGrid::from_resolution(&recon.bbox(), recon.resolution);
        let fusion = FusionParams {
            truncation_m: settings.truncation_voxels * grid.voxel_size,
            max_weight: 64.0,
            missing_is_free: true,
        };
        // For comparison: the visual hull of the white frames' silhouettes (pixels not darker than
        // `free_below`), what space carving alone would give. Only with a background level.
        let hull = if settings.free_below > 0 {
            Some(SpaceCarver::new(grid).map_err(|e| sl_err(StructuredLightError::Hull(e)))?)
        } else {
            None
        };
        let camera = config.camera.model();
        let tri = TriangulationParams {
            max_ray_gap_m: settings.max_ray_gap_m,
            min_neighbours: settings.min_neighbours,
            neighbour_tolerance_m: settings.neighbour_tolerance_m,
        };
        let mut flow = StructuredLightFlow {
            plan: config.scan.clone(),
            projector,
            camera,
            seq,
            used,
            hold,
            patterns: Vec::new(),
            tri,
            smooth_radius: recon.mesh.smooth_radius,
            tsdf: Tsdf::new(grid, fusion).map_err(|e| sl_err(StructuredLightError::Fusion(e)))?,
            hull,
            summary: StructuredLightSummary {
                coding: settings.coding,
                phase: (settings.coding == StripeCoding::PhaseShift).then(|| PhaseSummary {
                    steps: settings.steps,
                    periods_px: settings.periods_px.clone(),
                    unwrapping: settings.unwrapping,
                }),
                exposure_ms: settings.exposure_ms,
                rows: settings.rows,
                subpixel: settings.subpixel && set.is_none(),
                pixels_per_view: camera.width as usize * camera.height as usize,
                truncation_m: fusion.truncation_m,
                ..Default::default()
            },
            set,
            settings,
            cloud: PointCloud::new(),
            map: ProjectorMap::new(),
            triangulator: None,
            range: RangeImage::default(),
            world: world.cloned(),
            errors: (0.0, 0.0, 0),
            timings: Timings::default(),
        };
        flow.render(None)?;
        Ok(flow)
    }

    /// Lay out the projected sequence: the Gray/binary stripes as they are; any other coding's
    /// patterns (RGB, through `lut`) followed by one full-white frame, which gives the points their
    /// colour, the dark-background free-space test and the visual hull (a one-shot De Bruijn scan thus
    /// takes the coded frame plus a white frame per position).
    fn render(&mut self, lut: Option<&[u8; 256]>) -> Result<(), ScanError> {
        let sl_err = ScanError::StructuredLight;
        let (w, h) = (self.projector.width, self.projector.height);
        self.patterns = match &self.set {
            None => self
                .used
                .iter()
                .map(|&i| self.seq.render(i).map(|g| to_pattern(&g, w, h)))
                .collect::<Result<_, _>>()
                .map_err(|e| sl_err(StructuredLightError::Patterns(e)))?,
            Some(set) => (0..set.count())
                .map(|i| {
                    set.render_rgb(i, lut).map(|rgb| Pattern { width: w, height: h, rgb: std::sync::Arc::new(rgb) })
                })
                .chain(std::iter::once(Ok(uniform_pattern(255, w, h))))
                .collect::<Result<_, _>>()
                .map_err(|e| sl_err(StructuredLightError::Codes(e)))?,
        };
        self.summary.patterns_per_position = self.patterns.len();
        Ok(())
    }

    /// Take the measured response: reported, and the phase-shift fringes pre-distorted with its
    /// inverse.
    fn use_response(&mut self, mut response: ResponseSummary) -> Result<(), ScanError> {
        if matches!(self.set, Some(PatternSet::PhaseShift(..))) {
            let lut = ResponseCurve { gamma: response.gamma, black: response.black, white: response.white }
                .compensation_lut();
            response.compensated = true;
            self.render(Some(&lut))?;
        }
        self.summary.response = Some(response);
        Ok(())
    }
}

impl ScanFlow for StructuredLightFlow {
    type View = PatternStack;

    fn method(&self) -> Method {
        Method::StructuredLight
    }

    fn restore(&mut self, frames: &FrameDir) -> Result<bool, ScanError> {
        if !self.settings.gamma_compensation {
            return Ok(true);
        }
        match frames.read_json::<Prepared>("prepare.json")? {
            Some(p) => {
                self.use_response(p.response)?;
                Ok(true)
            }
            None => Ok(false),
        }
    }

    fn prepare(
        &mut self,
        rig: &mut Rig,
        frames: &FrameDir,
        cancel: &CancelToken,
        events: &mut dyn FnMut(ScanEvent),
    ) -> Result<(), ScanError> {
        if !self.settings.gamma_compensation {
            return Ok(());
        }
        events(ScanEvent::Stage("measuring the projector response"));
        let response =
            measure_response(rig, &self.plan, &self.projector, self.hold, self.settings.gamma_min_contrast, cancel)
                .map_err(ScanError::StructuredLight)?;
        frames.write_json("prepare.json", &Prepared { response: response.clone() })?;
        self.use_response(response)
    }

    fn sequence(&self, first: usize) -> Sequence<PatternStack> {
        let plan = self.plan.clone();
        let patterns = self.patterns.clone();
        let hold = self.hold;
        Box::new(move |rig, tx, cancel, progress| {
            acquisition::run_structured_light_scan(rig, &plan, first, &patterns, hold, tx, cancel, progress)
        })
    }

    fn save(&self, frames: &FrameDir, stack: &PatternStack) -> Result<(Vec<String>, Vec<usize>), ScanError> {
        let files = stack
            .frames
            .iter()
            .enumerate()
            .map(|(k, f)| frames.write_rgb(&frame_name(stack.position, &format!("_pattern_{k:02}.png")), &f.image))
            .collect::<Result<_, _>>()?;
        Ok((files, self.plan.lights.clone()))
    }

    fn load(&self, frames: &FrameDir, record: &ViewRecord) -> Result<PatternStack, ScanError> {
        let p = record.position;
        let mut stack = PatternStack {
            position: p,
            angle_deg: record.angle_deg,
            frames: Vec::with_capacity(self.patterns.len()),
            visible_at: Vec::with_capacity(self.patterns.len()),
            stale_discarded: record.stale_discarded,
        };
        for k in 0..self.patterns.len() {
            let image = frames.read_rgb(&frame_name(p, &format!("_pattern_{k:02}.png")))?;
            stack.frames.push(super::stored_frame(image, record.sequence));
            stack.visible_at.push(Instant::now());
        }
        Ok(stack)
    }

    fn process(&mut self, stack: PatternStack, events: &mut dyn FnMut(ScanEvent)) -> Result<String, ScanError> {
        let sl_err = ScanError::StructuredLight;
        let position = stack.position;
        let camera = self.camera;
        let expected = self.patterns.len();
        if stack.frames.len() != expected {
            return Err(sl_err(StructuredLightError::FrameCount { position, expected, found: stack.frames.len() }));
        }
        let mut greys = Vec::with_capacity(stack.frames.len());
        for (index, f) in stack.frames.iter().enumerate() {
            if f.image.width() != camera.width || f.image.height() != camera.height {
                return Err(sl_err(StructuredLightError::FrameSize {
                    position,
                    index,
                    width: camera.width,
                    height: camera.height,
                    found_width: f.image.width(),
                    found_height: f.image.height(),
                }));
            }
            if self.set.is_none() {
                greys.push(image::imageops::grayscale(&f.image).into_raw());
            }
        }
        events(ScanEvent::Stage("decoding"));
        let t = Instant::now();
        let (coords, white, white_grey) = match &self.set {
            None => {
                let coords =
                    decode_stack(&self.seq, &self.used, &greys, &camera, &self.settings, position, &mut self.map)
                        .map_err(sl_err)?;
                (coords, &stack.frames[stack.frames.len() - 2].image, greys.swap_remove(greys.len() - 2))
            }
            Some(set) => {
                let (white, coded) = stack.frames.split_last().ok_or(sl_err(StructuredLightError::FrameCount {
                    position,
                    expected,
                    found: 0,
                }))?;
                let normalised;
                let captures: Vec<&[u8]> = if let PatternSet::DeBruijn(..) = set {
                    normalised = albedo_normalised(coded[0].image.as_raw(), white.image.as_raw());
                    vec![normalised.as_slice()]
                } else {
                    coded.iter().map(|f| f.image.as_raw().as_slice()).collect()
                };
                let coords = set
                    .decode(&captures, camera.width as usize, camera.height as usize)
                    .map_err(|source| sl_err(StructuredLightError::CodesDecode { position, source }))?;
                let white_grey = image::imageops::grayscale(&white.image).into_raw();
                (coords, &white.image, white_grey)
            }
        };
        self.summary.decode_s += t.elapsed().as_secs_f64();
        events(ScanEvent::Stage("triangulating"));
        let t = Instant::now();
        // Triangulated in the rig frame, with the camera rays computed once per scan; the points and
        // normals are turned into the object frame at this view's angle below.
        let cam = camera.for_turntable_angle(stack.angle_deg);
        let triangulator = match &mut self.triangulator {
            Some(t) => t,
            None => self.triangulator.insert(
                Triangulator::new(&camera, &self.projector)
                    .map_err(|source| sl_err(StructuredLightError::Triangulate { position, source }))?,
            ),
        };
        triangulator
            .triangulate_into(&coords, Some(white), &self.tri, &mut self.range)
            .map_err(|source| sl_err(StructuredLightError::Triangulate { position, source }))?;
        let range = &self.range;
        self.summary.triangulate_s += t.elapsed().as_secs_f64();
        self.summary.decoded.push(range.decoded);
        self.summary.outliers += range.outliers;
        let mut view = range.valid_cloud();
        let points = view.len();
        self.summary.points_per_view.push(points);
        view.rig_to_object(stack.angle_deg);
        self.cloud.extend(view);
        if let Some(world) = &self.world {
            let (sum, sq, n) = point_errors(&cam, range, stack.angle_deg, world.scene());
            self.errors.0 += sum;
            self.errors.1 += sq;
            self.errors.2 += n;
        }
        events(ScanEvent::Stage("fusing"));
        let t = Instant::now();
        let depth = fusion_depth(range, &white_grey, self.settings.free_below);
        self.tsdf.integrate(&cam, &depth).map_err(|e| sl_err(StructuredLightError::Fusion(e)))?;
        self.summary.integrate_s += t.elapsed().as_secs_f64();
        if let Some(hull) = self.hull.as_mut() {
            let t = Instant::now();
            let free_below = self.settings.free_below;
            let mask = Mask::from_fn(camera.width, camera.height, |u, v| {
                white_grey[(v * camera.width + u) as usize] >= free_below
            });
            hull.add_view(&cam, &mask).map_err(|e| sl_err(StructuredLightError::Hull(e)))?;
            self.timings.silhouette += t.elapsed().as_secs_f64();
        }
        tracing::debug!(position, decoded = range.decoded, total_points = self.cloud.len(), "view triangulated");
        Ok(format!("triangulated: {} pixels decoded, {points} points", range.decoded))
    }

    /// The points triangulated so far.
    fn preview(&self, max_points: usize) -> Option<PointCloud> {
        preview::from_points(self.cloud.points(), self.cloud.colors(), max_points)
    }

    fn finish(mut self, finish: Finish<'_>) -> Result<Outcome, ScanError> {
        let sl_err = ScanError::StructuredLight;
        let Finish { timings, events, .. } = finish;
        let summary = &mut self.summary;
        timings.silhouette += self.timings.silhouette;
        timings.carve += summary.decode_s + summary.triangulate_s + summary.integrate_s;
        let views = summary.decoded.len();
        events(ScanEvent::Stage("merging the point clouds and meshing"));
        // The merged cloud's outlier removal and the mesh (from the TSDF, not from the cloud) are
        // independent: they run side by side on the thread pool.
        let (cloud, tsdf, smooth_radius) = (&mut self.cloud, &self.tsdf, self.smooth_radius);
        let (outliers, meshed) = rayon::join(
            || {
                let t = Instant::now();
                let removed = cloud
                    .remove_statistical_outliers(self.settings.outlier_neighbours, self.settings.outlier_std_ratio)
                    .map_err(|e| sl_err(StructuredLightError::Cloud(e)));
                (removed, t.elapsed().as_secs_f64())
            },
            || {
                let t = Instant::now();
                let solid = tsdf.occupancy();
                extract_surface_reporting(&solid, &MeshParams::smoothed(smooth_radius)).map_err(ScanError::Mesh).map(
                    |(mut mesh, handles)| {
                        let refined = tsdf.refine_vertices(&mut mesh);
                        (solid, mesh, handles, refined, t.elapsed().as_secs_f64())
                    },
                )
            },
        );
        let (removed, merge_s) = outliers;
        let (solid, mesh, mesh_handles, refined, mesh_s) = meshed?;
        summary.merged_outliers = removed?;
        summary.merge_s = merge_s;
        summary.refined_vertices = refined;
        timings.mesh = mesh_s;
        summary.points = self.cloud.len();
        let (err_sum, err_sq, err_n) = self.errors;
        if err_n > 0 {
            summary.point_error_mean_m = Some(err_sum / err_n as f64);
            summary.point_error_rms_m = Some((err_sq / err_n as f64).sqrt());
        }
        summary.valid_fraction = if views == 0 {
            0.0
        } else {
            summary.decoded.iter().sum::<usize>() as f64 / (views * summary.pixels_per_view) as f64
        };
        let visual_hull = self.hull.map(|h| {
            let occ = h.into_occupancy();
            let summary = VisualHull {
                iou: None,
                containment: None,
                voxels: occ.count(),
                volume_m3: occ.volume_m3(),
                colour_error: None,
                reprojection_error: None,
            };
            (occ, summary)
        });
        Ok(Outcome {
            views,
            solid,
            mesh,
            mesh_handles,
            cloud: Some(self.cloud),
            voxel_colours: None,
            silhouettes: Vec::new(),
            visual_hull,
            colour_error: None,
            details: MethodDetails::StructuredLight(self.summary),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{Intrinsics, Pose};

    fn projector(w: u32, h: u32) -> CameraModel {
        CameraModel {
            width: w,
            height: h,
            intrinsics: Intrinsics {
                fx: 100.0,
                fy: 100.0,
                cx: 16.0,
                cy: 8.0,
                skew: 0.0,
                k1: 0.0,
                k2: 0.0,
                ..Intrinsics::default()
            },
            pose: Pose { rotation: nalgebra::Matrix3::identity(), translation: nalgebra::Vector3::zeros() },
        }
    }

    #[test]
    fn column_only_sequences_skip_the_rows_and_still_decode_columns() {
        let model = projector(32, 16);
        let mut settings = StructuredLightConfig::default();
        let (seq, used) = projected_patterns(&model, &settings).expect("patterns");
        assert_eq!(used.len(), 2 * 5 + 2, "5 column bit pairs, white, black");
        settings.rows = true;
        assert_eq!(projected_patterns(&model, &settings).expect("patterns").1.len(), seq.count());
        settings.rows = false;
        settings.subpixel = false;
        // A camera that sees the projector pixel for pixel: each camera pixel decodes to its column.
        let greys: Vec<Vec<u8>> = used
            .iter()
            .map(|&i| seq.render(i).expect("render").iter().map(|&g| if g > 0 { 220 } else { 20 }).collect())
            .collect();
        let mut map = ProjectorMap::new();
        let coords = decode_stack(&seq, &used, &greys, &model, &settings, 0, &mut map).expect("decode");
        assert!(coords.row.is_none());
        for x in 0..32 {
            assert_eq!(coords.get(x, 5), Some((x as f32 + 0.5, None)));
        }
    }

    #[test]
    fn pixels_without_points_are_free_only_on_the_dark_background() {
        let range = RangeImage { width: 3, height: 1, depth_m: vec![0.3, 0.0, 0.0], ..Default::default() };
        let d = fusion_depth(&range, &[200, 5, 60], 12);
        assert_eq!(d[0], 0.3);
        assert_eq!(d[1], 0.0, "dark under white light: background, free space");
        assert!(d[2].is_nan(), "lit but no point (shadow, weak code): unknown");
        assert!(fusion_depth(&range, &[200, 5, 60], 0)[1].is_nan(), "free_below = 0: never free");
    }
}

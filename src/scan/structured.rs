//! The scan flow of method `structured-light`: at each turntable position the projector shows the
//! Gray/binary stripe sequence (column pairs, row pairs when `rows`, white, black) and the sequencer
//! captures one fresh frame per pattern; each stack is decoded into projector coordinates
//! (stripe-edge sub-pixel columns by default), triangulated with the calibrated camera and
//! projector in the object frame (the rig's turntable axis is the object frame's z axis), and the
//! view's range image is fused into a TSDF over the object-frame grid as it arrives. The merged
//! point cloud (normals from each range image, colours from the white frame), cleaned by a
//! statistical outlier test over its nearest neighbours, is written as `cloud.ply`; the mesh (`model.ply/stl/obj`) is read off the TSDF and its vertices moved onto the
//! zero crossing. On a simulated rig the report compares the mesh with the scene
//! (`ground_truth.chamfer_rel` = symmetric Chamfer distance / bounding-box diagonal, voxel IoU).
//!
//! Frames are written as `frames/pos_NNN_white.png` (the fully lit frame) and
//! `frames/pos_NNN_columns.png` (16-bit decoded projector column, 65535 = none).

use std::path::Path;
use std::time::Instant;

use super::report::{GroundTruth, Report, Timings, VisualHull};
use super::{ScanError, ScanEvent};
use crate::acquisition::{self, CancelToken, PatternStack};
use crate::config::structured_light::{StripeCoding, StructuredLightConfig};
use crate::config::{ProjectorConfig, RigConfig};
use crate::devices::{build_rig, Pattern};
use crate::geometry::{CameraModel, VoxelGrid};
use crate::pipeline::export::{self, write_atomic};
use crate::pipeline::structured_light::{
    decode, interpolate_stripe_edges, triangulate, Coding, DecodeError, DecodeParams, GrayCodePatterns, PatternError,
    ProjectorCoords, ProjectorMap, RangeImage, TriangulateError, TriangulationParams,
};
use crate::pipeline::{
    chamfer_distance, extract_surface, sample_mesh, CarveError, CloudError, DepthFusionError, FusionParams, Mask,
    MeshParams, Occupancy, PointCloud, SpaceCarver, Tsdf,
};

/// Surface samples per side for the Chamfer distance.
const CHAMFER_SAMPLES: usize = 60_000;

/// Why the structured-light part of a scan failed.
#[derive(Debug, thiserror::Error)]
pub enum StructuredLightError {
    /// The rig has no `[projector]`.
    #[error("method structured-light needs a [projector] in the rig file")]
    NoProjector,
    /// The pattern sequence cannot be laid out for the projector.
    #[error("pattern sequence for the projector")]
    Patterns(#[source] PatternError),
    /// A position's frames did not decode.
    #[error("decoding the patterns at position {position}")]
    Decode {
        /// 0-based position.
        position: usize,
        /// Why.
        #[source]
        source: DecodeError,
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

/// What the structured-light pipeline did, for `report.json` (key `structured_light`).
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct StructuredLightSummary {
    /// `"gray"` or `"binary"`.
    pub coding: StripeCoding,
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
    /// Seconds spent on the merged cloud's outlier removal.
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

/// The projector's calibrated model in the rig frame.
fn projector_model(config: &RigConfig) -> Option<CameraModel> {
    config.projector.as_ref().map(|p| match p {
        ProjectorConfig::Sim(p) => p.calibration.model(p.width, p.height),
    })
}

/// The pattern sequence of `settings` for a projector of `model`'s size, and the indices (into the
/// sequence) of the images projected: every column pair, the row pairs only with `rows`, white, black.
pub fn projected_patterns(
    model: &CameraModel,
    settings: &StructuredLightConfig,
) -> Result<(GrayCodePatterns, Vec<usize>), PatternError> {
    let coding = match settings.coding {
        StripeCoding::Gray => Coding::Gray,
        StripeCoding::Binary => Coding::Binary,
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

fn write_png<P: image::Pixel<Subpixel = S> + image::PixelWithColorType, S: image::Primitive>(
    file: &Path,
    width: u32,
    height: u32,
    data: Vec<S>,
) -> Result<(), ScanError>
where
    [S]: image::EncodableLayout,
{
    let encode_err = |source| ScanError::EncodeFrame { path: file.to_owned(), source };
    let image = image::ImageBuffer::<P, Vec<S>>::from_raw(width, height, data).ok_or_else(|| {
        encode_err(image::ImageError::Parameter(image::error::ParameterError::from_kind(
            image::error::ParameterErrorKind::DimensionMismatch,
        )))
    })?;
    let mut png = Vec::new();
    image.write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png).map_err(encode_err)?;
    write_atomic(file, &png).map_err(ScanError::Export)
}

/// Distances from each point of `range` to the true surface along its camera ray (`camera` in the
/// object frame): `(sum, sum of squares, count)`, metres. A point whose ray misses the scene is
/// skipped (it cannot be scored).
fn point_errors(camera: &CameraModel, range: &RangeImage, scene: &crate::sim::Scene) -> (f64, f64, usize) {
    let o = camera.centre();
    let w = range.width as usize;
    let (mut sum, mut sq, mut n) = (0.0, 0.0, 0);
    for (i, p) in range.points.iter().enumerate() {
        if range.depth_m[i] <= 0.0 {
            continue;
        }
        let d = camera.pixel_ray((i % w) as f64 + 0.5, (i / w) as f64 + 0.5);
        if let Some(hit) = scene.intersect(&o, &d, 0.0, f64::INFINITY) {
            let e = (nalgebra::Vector3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2])) - hit.point).norm();
            sum += e;
            sq += e * e;
            n += 1;
        }
    }
    (sum, sq, n)
}

/// Scan the rig described by `config` with structured light and write the results into `out`.
pub fn run_structured_light_scan(
    config: &RigConfig,
    out: &Path,
    cancel: &CancelToken,
    events: &mut dyn FnMut(ScanEvent),
) -> Result<Report, ScanError> {
    let started = Instant::now();
    let sl_err = ScanError::StructuredLight;
    let settings = &config.reconstruction.structured_light;
    let projector = projector_model(config).ok_or(sl_err(StructuredLightError::NoProjector))?;
    let (seq, used) =
        projected_patterns(&projector, settings).map_err(|e| sl_err(StructuredLightError::Patterns(e)))?;
    let patterns: Vec<Pattern> = used
        .iter()
        .map(|&i| seq.render(i).map(|g| to_pattern(&g, projector.width, projector.height)))
        .collect::<Result<_, _>>()
        .map_err(|e| sl_err(StructuredLightError::Patterns(e)))?;

    let out_dir = super::OutputDir::prepare(out)?;
    let out = out_dir.path().to_owned();
    let frames_dir = out.join("frames");
    std::fs::create_dir_all(&frames_dir).map_err(|source| ScanError::OutputDir {
        path: frames_dir.clone(),
        what: "cannot create it",
        source,
    })?;
    let mut rig = build_rig(config).map_err(ScanError::OpenDevices)?;
    let sim = rig.sim.clone();
    let recon = &config.reconstruction;
    let grid = VoxelGrid::from_resolution(&recon.bbox(), recon.resolution);
    let fusion = FusionParams {
        truncation_m: settings.truncation_voxels * grid.voxel_size,
        max_weight: 64.0,
        missing_is_free: true,
    };
    let mut tsdf = Tsdf::new(grid, fusion).map_err(|e| sl_err(StructuredLightError::Fusion(e)))?;
    // For comparison: the visual hull of the white frames' silhouettes (pixels not darker than
    // `free_below`), what space carving alone would give. Only with a background level.
    let mut hull = if settings.free_below > 0 {
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
    let mut summary = StructuredLightSummary {
        coding: settings.coding,
        rows: settings.rows,
        subpixel: settings.subpixel,
        patterns_per_position: patterns.len(),
        pixels_per_view: camera.width as usize * camera.height as usize,
        truncation_m: fusion.truncation_m,
        ..Default::default()
    };
    let mut cloud = PointCloud::new();
    let mut map = ProjectorMap::new();
    let mut timings = Timings::default();
    let (mut err_sum, mut err_sq, mut err_n) = (0.0f64, 0.0f64, 0usize);

    let plan = config.scan.clone();
    let (frames, capture_s) = super::acquire_and_process(
        &mut rig,
        |rig, tx, progress| acquisition::run_structured_light_scan(rig, &plan, &patterns, tx, cancel, progress),
        events,
        |stack: PatternStack, events| {
            let position = stack.position;
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
                greys.push(image::imageops::grayscale(&f.image).into_raw());
            }
            let white = &stack.frames[stack.frames.len() - 2].image;
            let white_grey = greys[greys.len() - 2].clone();
            let t = Instant::now();
            let coords = decode_stack(&seq, &used, &greys, &camera, settings, position, &mut map).map_err(sl_err)?;
            summary.decode_s += t.elapsed().as_secs_f64();
            write_png::<image::Rgb<u8>, u8>(
                &frames_dir.join(format!("pos_{position:03}_white.png")),
                camera.width,
                camera.height,
                white.as_raw().clone(),
            )?;
            write_png::<image::Luma<u16>, u16>(
                &frames_dir.join(format!("pos_{position:03}_columns.png")),
                camera.width,
                camera.height,
                map.columns().to_vec(),
            )?;
            let t = Instant::now();
            // Both models in the object frame at this view's angle: the points come out there.
            let cam = camera.for_turntable_angle(stack.angle_deg);
            let proj = projector.for_turntable_angle(stack.angle_deg);
            let range = triangulate(&cam, &proj, &coords, Some(white), &tri)
                .map_err(|source| sl_err(StructuredLightError::Triangulate { position, source }))?;
            summary.triangulate_s += t.elapsed().as_secs_f64();
            summary.decoded.push(range.decoded);
            summary.outliers += range.outliers;
            let (mut pts, mut nrm, mut col) = (Vec::new(), Vec::new(), Vec::new());
            for (p, n, c) in range.valid_points() {
                pts.push(p);
                nrm.push(n);
                col.push(c);
            }
            summary.points_per_view.push(pts.len());
            let view = PointCloud::from_parts(pts, Some(nrm), Some(col))
                .map_err(|e| sl_err(StructuredLightError::Cloud(e)))?;
            cloud.extend(view);
            if let Some(world) = &sim {
                let (sum, sq, n) = point_errors(&cam, &range, world.scene());
                err_sum += sum;
                err_sq += sq;
                err_n += n;
            }
            let t = Instant::now();
            let depth = fusion_depth(&range, &white_grey, settings.free_below);
            let stats = tsdf.integrate(&cam, &depth).map_err(|e| sl_err(StructuredLightError::Fusion(e)))?;
            summary.integrate_s += t.elapsed().as_secs_f64();
            if let Some(hull) = hull.as_mut() {
                let t = Instant::now();
                let mask = Mask::from_fn(camera.width, camera.height, |u, v| {
                    white_grey[(v * camera.width + u) as usize] >= settings.free_below
                });
                hull.add_view(&cam, &mask).map_err(|e| sl_err(StructuredLightError::Hull(e)))?;
                timings.silhouette += t.elapsed().as_secs_f64();
            }
            tracing::debug!(position, decoded = range.decoded, total_points = cloud.len(), "view triangulated");
            events(ScanEvent::ViewProcessed { position, occupied: stats.near_surface });
            Ok(())
        },
    )?;
    timings.capture = capture_s;
    timings.carve = summary.decode_s + summary.triangulate_s + summary.integrate_s;
    let views = summary.decoded.len();
    let t = Instant::now();
    summary.merged_outliers = cloud
        .remove_statistical_outliers(settings.outlier_neighbours, settings.outlier_std_ratio)
        .map_err(|e| sl_err(StructuredLightError::Cloud(e)))?;
    summary.merge_s = t.elapsed().as_secs_f64();
    summary.points = cloud.len();
    if err_n > 0 {
        summary.point_error_mean_m = Some(err_sum / err_n as f64);
        summary.point_error_rms_m = Some((err_sq / err_n as f64).sqrt());
    }
    summary.valid_fraction = if views == 0 {
        0.0
    } else {
        summary.decoded.iter().sum::<usize>() as f64 / (views * summary.pixels_per_view) as f64
    };

    events(ScanEvent::Stage("mesh"));
    let t = Instant::now();
    let occupancy = tsdf.occupancy();
    let mut mesh = extract_surface(&occupancy, &MeshParams { smooth_radius: recon.mesh.smooth_radius })
        .map_err(ScanError::Mesh)?;
    summary.refined_vertices = tsdf.refine_vertices(&mut mesh);
    timings.mesh = t.elapsed().as_secs_f64();

    events(ScanEvent::Stage("export"));
    let t = Instant::now();
    let p = |name: &str| out.join(name);
    export::write_ply_mesh(&p("model.ply"), &mesh).map_err(ScanError::Export)?;
    export::write_stl(&p("model.stl"), &mesh).map_err(ScanError::Export)?;
    export::write_obj(&p("model.obj"), &mesh).map_err(ScanError::Export)?;
    cloud.write_ply(&p("cloud.ply")).map_err(ScanError::Export)?;
    timings.export = t.elapsed().as_secs_f64();

    events(ScanEvent::Stage("evaluate"));
    let mut hull_overlap = None;
    let ground_truth = sim.as_ref().map(|world| {
        let scene = world.scene();
        let truth = Occupancy::from_fn(grid, |p| scene.contains(&p));
        let overlap = occupancy.iou_and_containment(&truth).map_or((0.0, 0.0), |o| (o.iou, o.containment));
        hull_overlap = hull.as_ref().and_then(|h| h.occupancy().iou_and_containment(&truth).ok());
        let true_points: Vec<[f32; 3]> = scene
            .sample_surface(CHAMFER_SAMPLES, 1)
            .iter()
            .map(|(p, _)| [p.x as f32, p.y as f32, p.z as f32])
            .collect();
        let chamfer = chamfer_distance(&sample_mesh(&mesh, CHAMFER_SAMPLES, 2), &true_points);
        let diagonal = scene.bounds().diagonal();
        GroundTruth {
            scene: config.sim.as_ref().map_or_else(String::new, |s| s.scene.clone()),
            iou: overlap.0,
            containment: overlap.1,
            voxels: truth.count(),
            volume_m3: truth.count() as f64 * grid.voxel_size.powi(3),
            chamfer_m: chamfer.map(|c| c.symmetric_m),
            chamfer_rel: chamfer.filter(|_| diagonal > 0.0).map(|c| c.symmetric_m / diagonal),
            colour_error: None,
        }
    });
    if let Some(gt) = &ground_truth {
        tracing::info!(iou = gt.iou, chamfer_rel = gt.chamfer_rel, "structured light compared with the scene");
    }
    let bbox = grid.bbox();
    let mut report = Report {
        scanrig_version: env!("CARGO_PKG_VERSION"),
        source: config.rig.name.clone(),
        method: recon.method.name(),
        views,
        resolution: grid.dims,
        voxel_size_m: grid.voxel_size,
        bbox_m: [bbox.min, bbox.max],
        occupied_voxels: occupancy.count(),
        volume_m3: occupancy.volume_m3(),
        mesh_triangles: mesh.triangles.len(),
        timings_s: timings,
        reprojection_iou: Vec::new(),
        reprojection_iou_mean: 0.0,
        frames: Some(frames),
        ground_truth,
        files: ["model.ply", "model.stl", "model.obj", "cloud.ply", "frames/", "report.json"]
            .map(str::to_owned)
            .to_vec(),
        visual_hull: hull.as_ref().map(|h| VisualHull {
            iou: hull_overlap.map(|o| o.iou),
            containment: hull_overlap.map(|o| o.containment),
            voxels: h.occupancy().count(),
            volume_m3: h.occupancy().volume_m3(),
            colour_error: None,
            reprojection_error: None,
        }),
        photo: None,
        shadow_carving: None,
        depth_fusion: None,
    };
    report.timings_s.total = started.elapsed().as_secs_f64();
    // The report's common fields, plus this method's own section.
    let mut json = serde_json::to_value(&report).map_err(ScanError::EncodeReport)?;
    if let Some(obj) = json.as_object_mut() {
        obj.insert("structured_light".into(), serde_json::to_value(&summary).map_err(ScanError::EncodeReport)?);
    }
    let bytes = serde_json::to_vec_pretty(&json).map_err(ScanError::EncodeReport)?;
    write_atomic(&p("report.json"), &bytes).map_err(ScanError::Export)?;
    Ok(report)
}

//! `report.json`: what a scan or reconstruction did and how well, machine-readable.

use serde::Serialize;

/// The report written as `report.json` next to a scan's results.
#[derive(Debug, Clone, Serialize)]
pub struct Report {
    /// scanrig version that wrote it.
    pub scanrig_version: &'static str,
    /// Rig name, or the data set directory for `reconstruct`.
    pub source: String,
    /// Reconstruction method.
    pub method: crate::config::Method,
    /// The stored scan whose views were reprocessed into this result (`reconstruct --scan`, the
    /// daemon's reprocess); absent for a scan.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reprocessed_from: Option<String>,
    /// Number of views used.
    pub views: usize,
    /// Grid size in voxels [nx, ny, nz].
    pub resolution: [usize; 3],
    /// Voxel edge, metres.
    pub voxel_size_m: f64,
    /// Working volume in the object frame, metres: [[min], [max]].
    pub bbox_m: [[f64; 3]; 2],
    /// Occupied voxels in the result.
    pub occupied_voxels: u64,
    /// Volume of the result, cubic metres.
    pub volume_m3: f64,
    /// Triangles in the mesh.
    pub mesh_triangles: usize,
    /// What the mesh clean-up removed to leave one watertight component (floating parts, internal
    /// cavities); `mesh_triangles` counts what is left.
    pub mesh_cleanup: crate::pipeline::MeshCleanStats,
    /// The voxel-scale handles (tunnels through thin walls, bridges over grooves) removed from the
    /// solid before meshing, and the voxels that took: each handle removed raised the mesh's Euler
    /// characteristic by 2 (absent for a method that meshes without it).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub mesh_handles: Option<crate::pipeline::HandleRepair>,
    /// The quadric simplification of the cleaned mesh: error bound, triangles before and after, and
    /// the sampled symmetric Hausdorff distance between the simplified and the unsimplified surface
    /// (absent when `[reconstruction.mesh] max_error_voxels = 0`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub mesh_simplification: Option<crate::pipeline::Simplification>,
    /// The exported mesh's topology: components, cavities, open edges, Euler characteristic, genus.
    pub mesh_topology: crate::pipeline::MeshTopology,
    /// Wall-clock time per stage, seconds.
    pub timings_s: Timings,
    /// Silhouette re-projection IoU per view (voxel footprints splatted), in view order.
    pub reprojection_iou: Vec<f64>,
    /// Mean of `reprojection_iou`.
    pub reprojection_iou_mean: f64,
    /// Frame counters (scans only).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub frames: Option<crate::acquisition::AcquisitionSummary>,
    /// Comparison with the simulated scene (simulated rigs only).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub ground_truth: Option<GroundTruth>,
    /// Files written, relative to the output directory.
    pub files: Vec<String>,
    /// The visual hull a refining method (shadow carving, photo-consistency) started from, or the
    /// hull of a measuring method's silhouettes, measured like the result.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub visual_hull: Option<VisualHull>,
    /// What the method did: one key named after the method's family (`space_carving`, `photo`,
    /// `shadow_carving`, `depth_fusion`, `laser`, `structured_light`).
    #[serde(flatten)]
    pub details: MethodDetails,
}

/// The method-specific part of `report.json`, one variant per method family.
#[derive(Debug, Clone, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum MethodDetails {
    /// `space-carving`.
    SpaceCarving(CarvingSummary),
    /// `voxel-coloring`, `space-carving-photo`.
    Photo(PhotoReport),
    /// `shadow-carving`.
    ShadowCarving(crate::scan::methods::shadow::ShadowSummary),
    /// `depth-fusion`.
    DepthFusion(crate::scan::methods::depth::DepthFusionSummary),
    /// `laser`.
    Laser(crate::scan::methods::laser::LaserSummary),
    /// `structured-light`.
    StructuredLight(crate::scan::methods::structured::StructuredLightSummary),
}

/// What silhouette carving did.
#[derive(Debug, Clone, Default, Serialize)]
pub struct CarvingSummary {
    /// Silhouettes carved.
    pub views: usize,
    /// Silhouette pixels over all views.
    pub silhouette_pixels: u64,
}

/// The visual hull before refinement, compared with the simulated scene where there is one.
#[derive(Debug, Clone, Serialize)]
pub struct VisualHull {
    /// Intersection over union with the true voxels (simulated rigs only).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub iou: Option<f64>,
    /// Fraction of the true voxels inside the hull (simulated rigs only).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub containment: Option<f64>,
    /// Occupied voxels.
    pub voxels: u64,
    /// Volume, cubic metres.
    pub volume_m3: f64,
    /// Mean absolute colour error per channel (0..255) of the hull's surface voxels coloured the same
    /// way as the result, against the true surface colour (photo-consistency methods, simulated rigs).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub colour_error: Option<f64>,
    /// Photometric re-projection error of the hull coloured the same way, mean absolute difference
    /// per channel (0..255) over silhouette-or-model pixels of every view (photo-consistency methods).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reprojection_error: Option<f64>,
}

/// Photo-consistency details of a `voxel-coloring` or `space-carving-photo` run.
#[derive(Debug, Clone, Default, Serialize)]
pub struct PhotoReport {
    /// Colour standard deviation threshold used, 8-bit levels.
    pub threshold: f64,
    /// The data's measured noise the threshold was derived from (absent when it was fixed).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub measured_noise: Option<crate::pipeline::PhotoNoise>,
    /// NCC threshold, if the NCC test was on.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub min_ncc: Option<f64>,
    /// Views used.
    pub views: usize,
    /// Iterations (space carving) or layers (voxel colouring).
    pub iterations: usize,
    /// Voxel colouring: ordinal sweeps run (one per direction); space carving: 0 (it carves from a
    /// worklist, not by plane sweeps).
    pub sweeps: usize,
    /// Voxel colouring: each sweep's direction (unit vector, grid frame: the world axes) and the indices
    /// of the views (in the order they were used) that satisfy the ordinal visibility constraint
    /// along it. Every view is in at least one sweep unless no direction admits it.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub ordinal_sweeps: Vec<crate::pipeline::OrdinalSweep>,
    /// Voxel visits.
    pub visits: u64,
    /// Voxels carved by photo-consistency (beyond the hull).
    pub carved: u64,
    /// Seconds spent carving and colouring; for `space-carving-photo` with a measured threshold,
    /// from the start of the noise measurement, which builds the state the carving starts from.
    pub seconds: f64,
    /// Surface voxels of the result.
    pub surface_voxels: usize,
    /// Surface voxels some view sees (the ones with a measured colour).
    pub seen_surface_voxels: usize,
    /// Photometric re-projection error of the coloured result (see [`VisualHullReport`]).
    pub reprojection_error: f64,
}

/// Stage timings, seconds of wall-clock time. Stages overlap in a scan (the pipeline runs while the
/// rig captures), so they need not add up to `total`.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Timings {
    /// Moving, switching and capturing (the acquisition thread's busy time), or loading images.
    pub capture: f64,
    /// Silhouette extraction.
    pub silhouette: f64,
    /// Carving.
    pub carve: f64,
    /// Surface extraction.
    pub mesh: f64,
    /// Writing results (meanwhile the mesh's topology for the report is counted and, on a simulated
    /// rig, the result compared with the scene).
    pub export: f64,
    /// Start to finish.
    pub total: f64,
    /// From the last frame captured (or the last stored view replayed) to the results on disk: how
    /// long a user waits after the rig stops.
    pub after_last_frame_s: f64,
}

/// How the result compares with the simulated scene's true occupancy on the same grid
/// (a voxel is truly occupied when its centre is inside the solid).
#[derive(Debug, Clone, Serialize)]
pub struct GroundTruth {
    /// The simulated scene.
    pub scene: String,
    /// Intersection over union of result and truth voxels.
    pub iou: f64,
    /// Fraction of truth voxels inside the result (1.0 = nothing of the object was carved away).
    pub containment: f64,
    /// Truth voxels.
    pub voxels: u64,
    /// Volume of the truth voxels, cubic metres.
    pub volume_m3: f64,
    /// Symmetric Chamfer distance between the mesh and the true surface, metres (mean of both directed
    /// mean nearest-neighbour distances over area-uniform samples; methods that compute it).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub chamfer_m: Option<f64>,
    /// `chamfer_m` over the scene's bounding-box diagonal.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub chamfer_rel: Option<f64>,
    /// Mean absolute colour error per channel (0..255) of the result's seen surface voxels that lie
    /// next to the true surface (a truly occupied and a truly empty voxel among their 26 neighbours
    /// and themselves) against the scene's true surface colour (reflectance) at their centres
    /// (photo-consistency methods only).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub colour_error: Option<f64>,
}

/// Area-uniform samples per surface for the Chamfer distance of the mesh-producing flows.
const CHAMFER_SAMPLES: usize = 60_000;

/// Compare a result with the simulated scene: `solid` (its voxels) against `truth` (the scene's
/// voxels on the same grid) for IoU and containment, and, with `mesh` (object frame, metres), the
/// symmetric Chamfer distance between the mesh and area-uniform samples of the true surface.
/// `scene_name` is the rig's `[sim] scene`.
pub fn ground_truth(
    scene: &crate::sim::Scene,
    scene_name: &str,
    truth: &crate::pipeline::Occupancy,
    solid: &crate::pipeline::Occupancy,
    mesh: Option<&crate::pipeline::TriangleMesh>,
) -> GroundTruth {
    use crate::pipeline::{chamfer_distance, sample_mesh};
    let overlap = solid.iou_and_containment(truth).map_or((0.0, 0.0), |o| (o.iou, o.containment));
    let chamfer = mesh.and_then(|mesh| {
        let true_points: Vec<[f32; 3]> = scene
            .sample_surface(CHAMFER_SAMPLES, 1)
            .iter()
            .map(|(p, _)| [p.x as f32, p.y as f32, p.z as f32])
            .collect();
        chamfer_distance(&sample_mesh(mesh, CHAMFER_SAMPLES, 2), &true_points)
    });
    let diagonal = scene.bounds().diagonal();
    GroundTruth {
        scene: scene_name.to_owned(),
        iou: overlap.0,
        containment: overlap.1,
        voxels: truth.count(),
        volume_m3: truth.volume_m3(),
        chamfer_m: chamfer.map(|c| c.symmetric_m),
        chamfer_rel: chamfer.filter(|_| diagonal > 0.0).map(|c| c.symmetric_m / diagonal),
        colour_error: None,
    }
}

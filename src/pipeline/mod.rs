//! Reconstruction: pure functions over images and cameras. Nothing here touches devices, the
//! simulated rig, acquisition or configuration: callers pass plain parameter structs.
//!
//! - [`silhouette`]: background-difference silhouettes with a disc closing.
//! - [`occupancy`]: brick-compressed voxel occupancy, overlap measures.
//! - [`space_carving`]: the visual hull, dense reference and hierarchical incremental carver.
//! - [`shadows`], [`shadow_carving`], [`light_calibration`]: shadow detection, shadow carving, point
//!   light positions from a calibration sphere.
//! - [`depth_fusion`], [`chamfer`]: TSDF fusion of depth maps; Chamfer distance between point sets.
//! - [`mesh`]: watertight surface extraction from an occupancy.
//! - [`topology`]: removal of voxel-scale handles from an occupancy before meshing.
//! - [`coloring`]: per-vertex colours from calibrated images.
//! - [`photo_consistency`], [`voxel_coloring`]: shape and colour from photo-consistency.
//! - [`export`]: PLY / STL / OBJ writers, written atomically.
//! - [`cloud`]: point clouds with normals and colours: merging, normals, outlier removal, meshing.
//! - [`laser`]: laser-stripe detection, triangulation on a laser plane, laser plane calibration.
//! - [`structured_light`]: Gray-code patterns and their per-pixel decoding.

pub mod chamfer;
pub mod cloud;
pub mod coloring;
pub mod depth_fusion;
pub mod display;
pub mod export;
pub mod hausdorff;
pub mod laser;
pub mod light_calibration;
pub mod mesh;
pub mod occupancy;
pub mod photo_consistency;
pub mod shadow_carving;
pub mod shadows;
pub mod silhouette;
pub(crate) mod simd;
pub mod simplify;
pub mod space_carving;
pub mod structured_light;
pub mod topology;
pub mod voxel_coloring;

pub use chamfer::{chamfer_distance, sample_mesh, Chamfer, PointIndex};
pub use cloud::{
    mesh_from_cloud, solid_and_mesh_from_cloud, CloudError, CloudMeshParams, CloudMeshStats, KnnIndex, PointCloud,
};
pub use coloring::{color_vertices, ColorView};
pub use depth_fusion::{DepthFusionError, FusionParams, IntegrateStats, Tsdf};
pub use export::ExportError;
pub use hausdorff::{
    hausdorff_distance, hausdorff_outliers, hausdorff_outliers_to, Hausdorff, Reference, TriangleIndex,
};
pub use mesh::{
    extract_surface, extract_surface_reporting, keep_main_component, MeshCleanStats, MeshError, MeshParams,
    MeshTopology, TriangleMesh,
};
pub use occupancy::{Brick, BrickBits, GridMismatch, Occupancy, Overlap};
pub use photo_consistency::{image_noise_sigma, ItemBuffer, PhotoError, PhotoNoise, PhotoParams, PhotoView};
pub use shadow_carving::{
    carve_shadows, ShadowCarveError, ShadowCarveParams, ShadowCarveStats, ShadowCarver, ShadowView,
};
pub use shadows::{detect_shadows, ShadowError, ShadowMaps, ShadowParams};
pub use silhouette::{extract_silhouette, Mask, MaskSizeError, SilhouetteParams};
pub use simplify::{simplify, simplify_in, simplify_within, Simplification, SimplifyParams, SimplifyStats};
pub use space_carving::{carve_dense, reproject, reprojection_iou, CarveError, CarveStats, SpaceCarver, View};
pub use topology::{remove_small_handles, HandleRepair};
pub use voxel_coloring::{
    carve_photo, carve_photo_measured, color_voxels, color_voxels_sweeps, colour_surface, measure_noise,
    measure_noise_and_colour, ordinal_sweeps, reprojection_error, ColouredSurface, OrdinalSweep, PhotoModel,
    PhotoStats,
};

/// Any error of the reconstruction layer, for callers that handle them alike (each keeps its cause).
#[derive(Debug, thiserror::Error)]
pub enum PipelineError {
    /// Space carving failed.
    #[error("space carving failed")]
    Carve(#[from] CarveError),
    /// Surface extraction failed.
    #[error("surface extraction failed")]
    Mesh(#[from] MeshError),
    /// Writing a file failed.
    #[error("export failed")]
    Export(#[from] ExportError),
    /// Two occupancies are on different grids.
    #[error("evaluation failed")]
    Grid(#[from] GridMismatch),
    /// A mask buffer has the wrong size.
    #[error("bad mask")]
    Mask(#[from] MaskSizeError),
    /// Photo-consistency reconstruction failed.
    #[error("photo-consistency reconstruction failed")]
    Photo(#[from] PhotoError),
}

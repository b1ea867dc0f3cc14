//! One whole scan job, from inputs to files on disk. [`driver::run_job`] is the one driver every
//! method runs under (`scanrig scan`, `scanrig reconstruct --scan`, the daemon's jobs); each method is
//! a [`flow::ScanFlow`] in [`methods`]. `reconstruct` runs space carving and the photo methods on a
//! calibrated image set in another layout (Middlebury par files, projection matrices). Both write the
//! same outputs (see [`output`]).

pub mod driver;
pub mod flow;
pub mod methods;
pub mod output;
pub mod preview;
pub mod reconstruct;
pub mod report;

use std::path::{Path, PathBuf};

use crate::acquisition::{AcquisitionError, CancelToken, Progress};
use crate::config::RigConfig;
use crate::devices::{build_rig, DeviceError};
use crate::pipeline::{CarveError, ExportError, MeshError, SilhouetteParams};

pub use driver::{run_job, Job, Source};
pub use output::OutputDir;
pub use report::{GroundTruth, MethodDetails, Report, Timings, VisualHull};

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
    /// A frame, record or report could not be written.
    #[error("cannot write the scan's files")]
    Write(#[source] crate::atomic::AtomicWriteError),
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
    /// A stored frame cannot be decoded as an image.
    #[error("cannot decode the image {path}")]
    DecodeFrame {
        /// The frame file.
        path: PathBuf,
        /// The decoder's error.
        #[source]
        source: image::ImageError,
    },
    /// A stored frame does not have the size or kind the method expects.
    #[error("{path}: {problem}")]
    BadFrame {
        /// The frame file.
        path: PathBuf,
        /// What is wrong.
        problem: String,
    },
    /// A position's record names another position than its file name.
    #[error("{path} records position {found}")]
    RecordMismatch {
        /// The record file.
        path: PathBuf,
        /// The position it records.
        found: usize,
    },
    /// A stored scan to reprocess has no complete view.
    #[error("{dir} holds no complete view (no pos_000.json)")]
    NoStoredViews {
        /// Its `frames/` directory.
        dir: PathBuf,
    },
    /// A stored scan lacks what its method measured before the positions.
    #[error("{dir} lacks prepare.json, which method {method} measured before the positions")]
    NotPrepared {
        /// Its `frames/` directory.
        dir: PathBuf,
        /// The method.
        method: crate::config::Method,
    },
    /// A reprocess would write into the stored scan it reads.
    #[error("{path}: the result of a reprocess cannot go into the stored scan itself; choose another --out")]
    OverwriteStored {
        /// The directory.
        path: PathBuf,
    },
    /// The effective rig file could not be written as TOML.
    #[error("cannot serialise the rig file")]
    EncodeRigFile(#[source] toml::ser::Error),
    /// The simulated world of a stored scan's rig file could not be built (for its ground truth).
    #[error("cannot build the simulated scene of the stored rig file")]
    SimWorld(#[source] crate::sim::SimConfigError),
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
    Shadow(#[source] methods::shadow::ShadowScanError),
    /// Depth fusion rejected its input.
    #[error("depth fusion failed")]
    DepthFusion(#[source] crate::pipeline::DepthFusionError),
    /// Laser stripe triangulation or the point cloud failed.
    #[error("laser scanning failed")]
    Laser(#[source] methods::laser::LaserScanError),
    /// Structured-light decoding, triangulation or fusion failed.
    #[error("structured light failed")]
    StructuredLight(#[source] methods::structured::StructuredLightError),
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
        /// Positions in the plan.
        total: usize,
        /// What processing it did, for the progress display ("carved: 12345 voxels left").
        message: String,
    },
    /// The pipeline moved on to a stage of its own (`decoding`, `mesh`, `export`, `evaluate`).
    Stage(&'static str),
    /// A live preview of the current estimate (only when the job asked for them, see
    /// [`preview::LiveSpec`]): object frame, metres, at most `max_points` points.
    Preview {
        /// 0-based position of the last view it includes.
        position: usize,
        /// Positions in the plan.
        total: usize,
        /// The estimate.
        cloud: std::sync::Arc<crate::pipeline::PointCloud>,
    },
}

/// The silhouette parameters of a rig file.
pub fn silhouette_params(config: &RigConfig) -> SilhouetteParams {
    let s = &config.reconstruction.silhouette;
    SilhouetteParams { threshold: s.threshold as f32, background: s.background, dilate: s.dilate_px, erode: s.erode_px }
}

/// Scan the rig described by `config` (opening its devices) into `out` with the method of
/// `config.reconstruction.method`.
pub fn run_scan(
    config: &RigConfig,
    out: &Path,
    cancel: &CancelToken,
    events: &mut dyn FnMut(ScanEvent),
) -> Result<Report, ScanError> {
    let mut rig = build_rig(config).map_err(ScanError::OpenDevices)?;
    run_job(Job { config, out, source: Source::Rig { rig: &mut rig, resume: false }, cancel, events, live: None })
}

/// Reprocess the stored scan in `scan_dir` with `config` (its own `rig.toml`, possibly with other
/// reconstruction settings) into `out`, without hardware; `cancel` stops it between views; `live`
/// asks for live previews of the estimate among the `events`.
pub fn reprocess(
    config: &RigConfig,
    scan_dir: &Path,
    out: &Path,
    cancel: &CancelToken,
    events: &mut dyn FnMut(ScanEvent),
    live: Option<preview::LiveSpec>,
) -> Result<Report, ScanError> {
    run_job(Job { config, out, source: Source::Stored { scan_dir }, cancel, events, live })
}

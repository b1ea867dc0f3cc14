//! One [`ScanFlow`](super::flow::ScanFlow) per reconstruction method, one file each. The job driver
//! ([`super::driver`]) runs whichever the configuration names; adding a method is a new file here and
//! its arm in [`run_with_flow`].

pub mod depth;
pub mod laser;
pub mod photo;
pub mod shadow;
pub mod silhouette;
pub mod structured;

use super::driver::{drive, Job};
use super::report::Report;
use super::ScanError;
use crate::config::Method;
use crate::sim::SimWorld;

/// Run `job` with the flow of its configuration's method; `world` is the simulated scene, if any.
pub(crate) fn run_with_flow(job: Job<'_>, world: Option<SimWorld>) -> Result<Report, ScanError> {
    let config = job.config;
    match config.reconstruction.method {
        Method::SpaceCarving | Method::VoxelColoring | Method::SpaceCarvingPhoto => {
            drive(silhouette::SilhouetteFlow::new(config)?, job, world)
        }
        Method::ShadowCarving => drive(shadow::ShadowFlow::new(config)?, job, world),
        Method::DepthFusion => drive(depth::DepthFlow::new(config)?, job, world),
        Method::Laser => drive(laser::LaserFlow::new(config)?, job, world),
        Method::StructuredLight => drive(structured::StructuredLightFlow::new(config, world.as_ref())?, job, world),
    }
}

/// `pos_NNN` followed by `suffix`.
pub(crate) fn frame_name(position: usize, suffix: &str) -> String {
    format!("{}{suffix}", super::flow::FrameDir::stem(position))
}

/// A frame read back from disk: the stored image with the recorded sequence number (its exposure
/// time is not stored; a replayed frame is never compared with a scene change).
pub(crate) fn stored_frame(image: image::RgbImage, sequence: u64) -> crate::devices::Frame {
    crate::devices::Frame { sequence, exposure_start: std::time::Instant::now(), image }
}

//! The simulated rig's world: the scene on the turntable ([`scene`]), the renderer ([`render`]), the
//! shared rig state ([`world`]), and ground truth for evaluating reconstructions.
//!
//! The simulated drivers in `devices/*/sim.rs` change the world (turntable angle, lights, lasers,
//! projector pattern) and render it (camera, depth camera). The scene is in the object frame; the
//! devices are posed in the rig frame (see [`crate::geometry`]).

pub mod chessboard;
pub mod render;
pub mod rng;
pub mod scene;
pub mod world;

#[cfg(test)]
pub(crate) mod tests;

pub use render::{FrameNoise, Lighting, LineLaser, PointLight, ProjectorModel, RayTable, Renderer};
pub use rng::SplitMix64;
pub use scene::{Hit, Material, Primitive, Scene, Solid};
pub use world::{SimWorld, WorldState};

/// Names of the preset scenes for `[sim] scene`.
pub const SCENE_NAMES: &[&str] = &["sphere", "box", "cup", "pit-block", "textured-box"];

/// What the simulated world refuses.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SimError {
    /// No preset has this name.
    #[error("unknown scene `{name}`; known: {}", SCENE_NAMES.join(", "))]
    UnknownScene {
        /// The name asked for.
        name: String,
    },
    /// The scene scale is not a positive number.
    #[error("scene scale must be a positive number, got {scale}")]
    InvalidScale {
        /// The scale asked for.
        scale: f64,
    },
    /// A scene needs at least one solid.
    #[error("a scene needs at least one solid")]
    EmptyScene,
    /// Too many holes in one solid.
    #[error("a solid may have at most {max} holes, got {holes}")]
    TooManyHoles {
        /// Holes given.
        holes: usize,
        /// The limit.
        max: usize,
    },
    /// Ambient level outside 0..=1.
    #[error("ambient level must be between 0 and 1, got {ambient}")]
    InvalidAmbient {
        /// The level given.
        ambient: f64,
    },
    /// A laser plane normal of zero length.
    #[error("laser plane normal must be a finite, non-zero vector")]
    DegenerateLaserPlane,
    /// A light level outside 0..=1.
    #[error("light level must be between 0 and 1, got {level}")]
    InvalidLevel {
        /// The level given.
        level: f32,
    },
    /// No white light with this index.
    #[error("light {index} does not exist: the rig has {count} light(s)")]
    NoSuchLight {
        /// Index asked for.
        index: usize,
        /// Lights there are.
        count: usize,
    },
    /// No laser with this index.
    #[error("laser {index} does not exist: the rig has {count} laser(s)")]
    NoSuchLaser {
        /// Index asked for.
        index: usize,
        /// Lasers there are.
        count: usize,
    },
    /// A pattern was shown but the rig has no projector.
    #[error("the simulated rig has no projector")]
    NoProjector,
    /// A pattern of the wrong size.
    #[error("pattern is {width}x{height} with {bytes} bytes; the projector needs {}x{} RGB", expected.0, expected.1)]
    PatternSize {
        /// The projector's resolution.
        expected: (u32, u32),
        /// Pattern width.
        width: u32,
        /// Pattern height.
        height: u32,
        /// Pattern bytes.
        bytes: usize,
    },
}

/// The simulated world cannot be built from the rig file: which section and setting, and why.
#[derive(Debug, thiserror::Error)]
#[error("[{section}] {field}: {source}")]
pub struct SimConfigError {
    /// The rig-file section (`sim`, `lights`).
    pub section: &'static str,
    /// The setting.
    pub field: &'static str,
    /// What is wrong.
    #[source]
    pub source: SimError,
}

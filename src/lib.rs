//! scanrig: drives a 3D scanner rig (turntable, lights, lasers, projector, cameras) and reconstructs
//! in process.
//!
//! Layers, each with one job; data flows one way: [`devices`] -> [`acquisition`] -> [`pipeline`].
//! - [`atomic`]: atomic file writing (the bottom layer every writer uses).
//! - [`config`]: the rig file.
//! - `archive` (feature `s3`): the scan archive in S3-compatible object storage.
//! - [`devices`]: device traits, simulated and real drivers, the registry.
//! - [`sim`]: the simulated rig's world (scene, renderer, ground truth).
//! - [`acquisition`]: scan sequences.
//! - [`pipeline`]: reconstruction, pure functions over frames and cameras.
//! - [`geometry`]: camera models and frames.
//! - [`rigfile`]: loading a rig file: config values, then the drivers' checks, then calibration.
//! - [`dataset`]: calibrated image sets on disk (cameras, view selections, masks).
//! - [`scan`]: one scan job for every method (the driver, one flow per method), from rig file to
//!   files on disk.

pub mod acquisition;
#[cfg(feature = "s3")]
pub mod archive;
pub mod atomic;
pub mod calibration;
pub mod config;
pub mod dataset;
pub mod devices;
pub mod geometry;
pub mod pipeline;
pub mod rigfile;
pub mod scan;
pub mod service;
pub mod sim;

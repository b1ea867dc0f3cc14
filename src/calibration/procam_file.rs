//! The `scanrig calibrate projector` workflow: Gray-code capture directories on disk (one per board
//! pose) -> projector-camera calibration -> a TOML calibration file, with an optional comparison
//! against a published OpenCV calibration.
//!
//! The file ([`ProcamFile`]) holds both devices' [`Intrinsics`] (pixels), the projector's size, the
//! Gray-code step, and projector <- camera `rotation` (row-major 3x3) and `translation` in the unit
//! of the board's square size.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::opencv_xml::{OpenCvXmlError, ReferenceCalibration};
use super::procam::{
    calibrate_procam, procam_view_from_frames, rotation_difference_deg, ProcamOptions, ProcamView, ProcamViewError,
    ProcamViewOptions, ProcamViewStats,
};
use super::{BoardSpec, CalibrationError};
use crate::atomic::{write_atomic, AtomicWriteError};
use crate::geometry::Intrinsics;
use crate::geometry::Pose;
use crate::pipeline::structured_light::{load_capture_dir, CaptureError, GrayCodePatterns, PatternError};

/// A projector-camera calibration file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ProcamFile {
    /// Camera intrinsics, camera pixels.
    pub camera: Intrinsics,
    /// Projector intrinsics, projector pixels.
    pub projector: Intrinsics,
    /// Projector width, pixels.
    pub projector_width: u32,
    /// Projector height, pixels.
    pub projector_height: u32,
    /// Projector pixels per Gray-code pixel.
    pub graycode_step: u32,
    /// Rotation projector <- camera, row-major.
    pub rotation: [[f64; 3]; 3],
    /// Translation projector <- camera, in the unit of the board's square size.
    pub translation: [f64; 3],
    /// Camera re-projection RMS, pixels.
    pub camera_rms_px: f64,
    /// Projector re-projection RMS, projector pixels.
    pub projector_rms_px: f64,
    /// Board poses used.
    pub views: usize,
}

/// Why the workflow failed; each names the file or directory at fault.
#[derive(Debug, thiserror::Error)]
pub enum ProcamFileError {
    /// A capture directory could not be read.
    #[error("capture {}", dir.display())]
    Capture {
        /// The directory.
        dir: PathBuf,
        /// The cause.
        #[source]
        source: CaptureError,
    },
    /// A capture gave no usable view.
    #[error("capture {}", dir.display())]
    View {
        /// The directory.
        dir: PathBuf,
        /// The cause.
        #[source]
        source: ProcamViewError,
    },
    /// The projector size has no pattern sequence.
    #[error("projector size")]
    Patterns(#[from] PatternError),
    /// The calibration failed.
    #[error("calibration")]
    Calibration(#[from] CalibrationError),
    /// The reference file could not be read.
    #[error("reference calibration")]
    Reference(#[from] OpenCvXmlError),
    /// A calibration file (`--camera-calib`, or one read back) could not be read or parsed.
    #[error("{}: {reason}", path.display())]
    ReadFile {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// Intrinsics were asked from a reference but none was given.
    #[error("--intrinsics-from-reference needs --reference")]
    NoReference,
    /// The output could not be written.
    #[error(transparent)]
    Write(#[from] AtomicWriteError),
    /// A point cloud or mesh could not be written.
    #[error("cannot write the point cloud")]
    Export(#[from] crate::pipeline::export::ExportError),
}

/// What `scanrig calibrate projector` does.
#[derive(Debug, Clone, PartialEq)]
pub struct ProcamRequest {
    /// Capture directories, one per board pose, each holding the Gray-code sequence's images.
    pub captures: Vec<PathBuf>,
    /// The board (square size in the unit the translation should come out in).
    pub board: BoardSpec,
    /// Gray-code pattern size, projector pixels / step.
    pub patterns: (u32, u32),
    /// Capture options (decoder thresholds, detector, local homographies incl. the Gray-code step).
    pub view: ProcamViewOptions,
    /// A TOML file with a `[camera]` table of [`Intrinsics`] fields (e.g. a file this workflow wrote) to
    /// hold the camera intrinsics fixed.
    pub camera_calib: Option<PathBuf>,
    /// A published OpenCV `calibration_result.xml` to compare with.
    pub reference: Option<PathBuf>,
    /// Length of one unit of the reference's translation in the board's unit (metres when the square
    /// size is in metres; 1 when both use the same unit).
    pub reference_unit_m: f64,
    /// Hold both devices' intrinsics at the reference's (one pose then suffices).
    pub intrinsics_from_reference: bool,
}

/// The comparison with a reference calibration.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ReferenceComparison {
    /// Angle between our and the reference rotation, degrees.
    pub rotation_deg: f64,
    /// `|t - t_ref| / |t_ref|`, fraction.
    pub translation_rel: f64,
    /// Camera RMS of our views under the reference rotation/translation (board poses refitted), pixels.
    pub camera_rms_px: f64,
    /// Projector RMS likewise, projector pixels.
    pub projector_rms_px: f64,
}

/// The result of [`run_procam`].
#[derive(Debug, Clone, PartialEq)]
pub struct ProcamReport {
    /// The calibration as written.
    pub file: ProcamFile,
    /// Figures of each capture, in input order.
    pub views: Vec<ProcamViewStats>,
    /// The comparison with `--reference`, if given.
    pub reference: Option<ReferenceComparison>,
}

fn read_camera_file(path: &Path) -> Result<Intrinsics, ProcamFileError> {
    #[derive(Deserialize)]
    struct CameraOnly {
        camera: Intrinsics,
    }
    let bad = |reason: String| ProcamFileError::ReadFile { path: path.to_path_buf(), reason };
    let text = std::fs::read_to_string(path).map_err(|e| bad(e.to_string()))?;
    // Other tables and keys (a whole procam file, say) are ignored; only `[camera]` is read.
    let lens: CameraOnly = toml::from_str(&text).map_err(|e| bad(e.to_string()))?;
    if !lens.camera.is_valid() {
        return Err(bad("[camera]: focal lengths must be positive and every value finite".into()));
    }
    Ok(lens.camera)
}

/// Load, decode and calibrate; write nothing.
pub fn run_procam(req: &ProcamRequest) -> Result<ProcamReport, ProcamFileError> {
    let patterns = GrayCodePatterns::new(req.patterns.0, req.patterns.1)?;
    let reference = req
        .reference
        .as_deref()
        .map(ReferenceCalibration::load)
        .transpose()?
        .map(|r| ReferenceCalibration { translation: r.translation * req.reference_unit_m, ..r });
    let mut views: Vec<ProcamView> = Vec::new();
    let mut stats = Vec::new();
    for dir in &req.captures {
        let cap = load_capture_dir(dir, patterns.count())
            .map_err(|source| ProcamFileError::Capture { dir: dir.clone(), source })?;
        let (v, s) = procam_view_from_frames(&cap.slices(), cap.width, cap.height, &patterns, &req.board, &req.view)
            .map_err(|source| ProcamFileError::View { dir: dir.clone(), source })?;
        views.push(v);
        stats.push(s);
    }
    let mut opts = ProcamOptions::default();
    if let Some(path) = &req.camera_calib {
        opts.camera = Some(read_camera_file(path)?);
    }
    if req.intrinsics_from_reference {
        let r = reference.as_ref().ok_or(ProcamFileError::NoReference)?;
        opts.camera = Some(r.camera);
        opts.projector = Some(r.projector);
    }
    let cal = calibrate_procam(&views, &opts)?;
    let comparison = match &reference {
        Some(r) => {
            let fixed = ProcamOptions {
                camera: Some(cal.camera),
                projector: Some(cal.projector),
                fixed_stereo: Some(Pose { rotation: r.rotation, translation: r.translation }),
                ..ProcamOptions::default()
            };
            let at_ref = calibrate_procam(&views, &fixed)?;
            Some(ReferenceComparison {
                rotation_deg: rotation_difference_deg(&cal.rotation, &r.rotation),
                translation_rel: (cal.translation - r.translation).norm() / r.translation.norm().max(1e-300),
                camera_rms_px: at_ref.camera_rms_px,
                projector_rms_px: at_ref.projector_rms_px,
            })
        }
        None => None,
    };
    let step = req.view.local.graycode_step.max(1);
    let r = cal.rotation;
    let file = ProcamFile {
        camera: cal.camera,
        projector: cal.projector,
        projector_width: req.patterns.0 * step,
        projector_height: req.patterns.1 * step,
        graycode_step: step,
        rotation: [
            [r[(0, 0)], r[(0, 1)], r[(0, 2)]],
            [r[(1, 0)], r[(1, 1)], r[(1, 2)]],
            [r[(2, 0)], r[(2, 1)], r[(2, 2)]],
        ],
        translation: [cal.translation.x, cal.translation.y, cal.translation.z],
        camera_rms_px: cal.camera_rms_px,
        projector_rms_px: cal.projector_rms_px,
        views: views.len(),
    };
    Ok(ProcamReport { file, views: stats, reference: comparison })
}

/// Write a calibration file atomically (TOML).
pub fn write_procam_file(path: &Path, file: &ProcamFile) -> Result<(), ProcamFileError> {
    let text = toml::to_string_pretty(file).map_err(|e| {
        ProcamFileError::Write(AtomicWriteError {
            path: path.to_path_buf(),
            source: std::io::Error::other(e.to_string()),
        })
    })?;
    write_atomic(path, text.as_bytes())?;
    Ok(())
}

/// Read a calibration file written by [`write_procam_file`].
pub fn read_procam_file(path: &Path) -> Result<ProcamFile, ProcamFileError> {
    let bad = |reason: String| ProcamFileError::ReadFile { path: path.to_path_buf(), reason };
    let text = std::fs::read_to_string(path).map_err(|e| bad(e.to_string()))?;
    toml::from_str(&text).map_err(|e| bad(e.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn camera_file_round_trips_and_errors_name_the_file() {
        let dir = tempfile::tempdir().expect("tempdir");
        let lens = Intrinsics {
            fx: 800.0,
            fy: 790.0,
            cx: 320.5,
            cy: 240.5,
            skew: 0.0,
            k1: -0.1,
            k2: 0.01,
            p1: 0.0,
            p2: 0.0,
            k3: 0.0,
        };
        let file = ProcamFile {
            camera: lens,
            projector: Intrinsics { fx: 400.0, ..lens },
            projector_width: 320,
            projector_height: 240,
            graycode_step: 1,
            rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            translation: [0.1, 0.0, 0.0],
            camera_rms_px: 0.1,
            projector_rms_px: 0.2,
            views: 3,
        };
        let path = dir.path().join("procam.toml");
        write_procam_file(&path, &file).expect("write");
        assert_eq!(read_procam_file(&path).expect("read"), file);
        // A procam file serves as --camera-calib: only its [camera] table is read.
        assert_eq!(read_camera_file(&path).expect("camera"), lens);

        let bad = dir.path().join("bad.toml");
        std::fs::write(&bad, "[camera]\nfx = 800.0\nfy = 790.0\ncx = 320.0\n").expect("write");
        let e = read_camera_file(&bad).expect_err("cy missing");
        let msg = e.to_string();
        assert!(msg.contains("bad.toml") && msg.contains("cy"), "{msg}");
        std::fs::write(&bad, "[camera]\nfx = -800.0\nfy = 790.0\ncx = 320.0\ncy = 240.0\n").expect("write");
        assert!(read_camera_file(&bad).expect_err("negative fx").to_string().contains("positive"));
        std::fs::write(&bad, "[lens]\nfx = 1.0\n").expect("write");
        assert!(read_camera_file(&bad).expect_err("no camera").to_string().contains("camera"));
        assert!(read_camera_file(&dir.path().join("missing.toml")).is_err());
    }
}

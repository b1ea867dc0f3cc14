//! The output directory of a scan or reconstruction:
//!
//! ```text
//! DIR/frames/pos_000.png ...   captured frames (scans only), written as they arrive
//! DIR/frames/pos_000.json ...  how each frame was taken (angle, lights, sequence), written after it
//! DIR/model.ply                binary PLY triangle mesh (vertex colours from the photo methods)
//! DIR/model.stl                binary STL
//! DIR/model.obj                OBJ
//! DIR/voxels.ply               occupied voxel centres as a point cloud (coloured by the photo methods)
//! DIR/report.json              written last: a directory is a finished result iff it has one
//! ```
//! Every file is written atomically (temporary file, fsync, rename), so a crash or a full disk never
//! leaves a half-written file under a final name.

use std::path::{Path, PathBuf};
use std::time::Instant;

use super::report::{GroundTruth, Report, Timings};
use super::{ScanError, ScanEvent};
use crate::acquisition::{AcquisitionSummary, CapturedView};
use crate::pipeline::export::{self, write_atomic};
use crate::pipeline::{extract_surface, reprojection_iou, MeshParams, Occupancy, View};

/// What `frames/pos_NNN.json` records about how frame NNN was taken.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FrameMeta {
    /// 0-based position in the plan.
    pub position: usize,
    /// Turntable angle reported when the frame was taken, degrees.
    pub angle_deg: f64,
    /// Lights that were on, by index.
    pub lights_on: Vec<usize>,
    /// The camera's sequence number of the frame.
    pub sequence: u64,
    /// Stale frames discarded before it.
    pub stale_discarded: u32,
}

/// A prepared output directory.
#[derive(Debug)]
pub struct OutputDir {
    path: PathBuf,
}

/// Everything [`OutputDir::write_results`] needs.
pub struct Results<'a> {
    /// Rig name or data set.
    pub source: String,
    /// Method name.
    pub method: &'static str,
    /// The carved occupancy.
    pub occupancy: &'a Occupancy,
    /// Cameras (in the grid's frame) and silhouettes of the views used.
    pub views: &'a [View<'a>],
    /// Occupancy smoothing radius for the mesh, voxels.
    pub smooth_radius: u32,
    /// Scene name and true occupancy on the same grid, for simulated rigs.
    pub truth: Option<(&'a str, &'a Occupancy)>,
    /// Acquisition counters (scans only).
    pub frames: Option<AcquisitionSummary>,
    /// Timings so far.
    pub timings: Timings,
    /// When the job started.
    pub started: Instant,
    /// Progress sink.
    pub events: &'a mut dyn FnMut(ScanEvent),
    /// Colours and figures of the photo-consistency methods (`None` for space carving).
    pub photo: Option<super::photo::PhotoOutputs>,
}

impl std::fmt::Debug for Results<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Results").field("source", &self.source).field("method", &self.method).finish_non_exhaustive()
    }
}

/// Remove the temporary files of atomic writes that a killed process left in `dir` and `dir/frames`
/// (see [`export::is_atomic_temp`]); complete files are never touched.
fn remove_partial_writes(dir: &Path) -> Result<(), ScanError> {
    for d in [dir.to_owned(), dir.join("frames")] {
        let Ok(entries) = std::fs::read_dir(&d) else { continue };
        for entry in entries.flatten() {
            if export::is_atomic_temp(&entry.file_name().to_string_lossy()) {
                std::fs::remove_file(entry.path()).map_err(|source| ScanError::OutputDir {
                    path: entry.path(),
                    what: "cannot remove a partial write left by an earlier run",
                    source,
                })?;
            }
        }
    }
    Ok(())
}

impl OutputDir {
    /// Create `path` if needed, check that it is writable, and remove a previous `report.json` and
    /// previous frames so that nothing from an earlier run is presented as this run's result.
    pub fn prepare(path: &Path) -> Result<OutputDir, ScanError> {
        let err = |what: &'static str| move |source| ScanError::OutputDir { path: path.to_owned(), what, source };
        std::fs::create_dir_all(path).map_err(err("cannot create it"))?;
        remove_partial_writes(path)?;
        let probe = path.join(".scanrig-write-test");
        std::fs::write(&probe, b"ok").map_err(err("is not writable"))?;
        std::fs::remove_file(&probe).map_err(err("is not writable"))?;
        match std::fs::remove_file(path.join("report.json")) {
            Ok(()) => {}
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
            Err(e) => return Err(err("cannot remove the previous report.json")(e)),
        }
        let frames = path.join("frames");
        if frames.is_dir() {
            for entry in std::fs::read_dir(&frames).map_err(err("cannot list frames/"))? {
                let entry = entry.map_err(err("cannot list frames/"))?;
                let name = entry.file_name();
                let name = name.to_string_lossy();
                if name.starts_with("pos_") && (name.ends_with(".png") || name.ends_with(".json")) {
                    std::fs::remove_file(entry.path()).map_err(err("cannot remove a previous frame"))?;
                }
            }
        }
        Ok(OutputDir { path: path.to_owned() })
    }

    /// Open the directory of an interrupted scan to resume it: keeps its frames, removes a
    /// `report.json` (there should be none) so the directory is not taken as finished.
    pub fn reopen(path: &Path) -> Result<OutputDir, ScanError> {
        let err = |what: &'static str| move |source| ScanError::OutputDir { path: path.to_owned(), what, source };
        std::fs::create_dir_all(path).map_err(err("cannot create it"))?;
        remove_partial_writes(path)?;
        match std::fs::remove_file(path.join("report.json")) {
            Ok(()) => {}
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
            Err(e) => return Err(err("cannot remove the previous report.json")(e)),
        }
        Ok(OutputDir { path: path.to_owned() })
    }

    /// How many leading positions (0, 1, ... k-1, at most `total`) have a complete frame on disk: the
    /// PNG and its metadata file, which is written after the PNG.
    pub fn completed_frames(&self, total: usize) -> usize {
        let dir = self.path.join("frames");
        (0..total)
            .take_while(|&i| {
                dir.join(format!("pos_{i:03}.png")).is_file() && dir.join(format!("pos_{i:03}.json")).is_file()
            })
            .count()
    }

    /// Read back frame `position` and its metadata.
    pub fn read_frame(&self, position: usize) -> Result<(FrameMeta, image::RgbImage), ScanError> {
        let dir = self.path.join("frames");
        let meta_path = dir.join(format!("pos_{position:03}.json"));
        let bytes = std::fs::read(&meta_path).map_err(|source| ScanError::OutputDir {
            path: meta_path.clone(),
            what: "cannot read frame metadata",
            source,
        })?;
        let meta: FrameMeta = serde_json::from_slice(&bytes)
            .map_err(|source| ScanError::FrameMeta { path: meta_path.clone(), source })?;
        let png = dir.join(format!("pos_{position:03}.png"));
        let image = image::open(&png).map_err(|source| ScanError::EncodeFrame { path: png.clone(), source })?.to_rgb8();
        Ok((meta, image))
    }

    /// The directory.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Write one captured frame as `frames/pos_NNN.png`.
    pub fn write_frame(&self, view: &CapturedView) -> Result<(), ScanError> {
        let dir = self.path.join("frames");
        std::fs::create_dir_all(&dir).map_err(|source| ScanError::OutputDir {
            path: dir.clone(),
            what: "cannot create it",
            source,
        })?;
        let file = dir.join(format!("pos_{:03}.png", view.position));
        let mut png = Vec::with_capacity(view.frame.image.len() / 2);
        view.frame
            .image
            .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
            .map_err(|source| ScanError::EncodeFrame { path: file.clone(), source })?;
        write_atomic(&file, &png).map_err(ScanError::Export)?;
        // The metadata goes last: a position is complete on disk iff its JSON exists.
        let meta = FrameMeta {
            position: view.position,
            angle_deg: view.angle_deg,
            lights_on: view.lights_on.clone(),
            sequence: view.frame.sequence,
            stale_discarded: view.stale_discarded,
        };
        let json = serde_json::to_vec_pretty(&meta).map_err(ScanError::EncodeReport)?;
        write_atomic(&dir.join(format!("pos_{:03}.json", view.position)), &json).map_err(ScanError::Export)
    }

    /// Mesh, export, evaluate, and write `report.json` last.
    pub fn write_results(&self, r: Results<'_>) -> Result<Report, ScanError> {
        let Results {
            source,
            method,
            occupancy,
            views,
            smooth_radius,
            truth,
            frames,
            mut timings,
            started,
            events,
            photo,
        } = r;
        events(ScanEvent::Stage("mesh"));
        let t = Instant::now();
        let mut mesh = extract_surface(occupancy, &MeshParams { smooth_radius }).map_err(ScanError::Mesh)?;
        if let Some(p) = &photo {
            mesh.colors = Some(p.mesh_colours(&mesh));
        }
        timings.mesh = t.elapsed().as_secs_f64();

        events(ScanEvent::Stage("export"));
        let t = Instant::now();
        let p = |name: &str| self.path.join(name);
        export::write_ply_mesh(&p("model.ply"), &mesh).map_err(ScanError::Export)?;
        export::write_stl(&p("model.stl"), &mesh).map_err(ScanError::Export)?;
        export::write_obj(&p("model.obj"), &mesh).map_err(ScanError::Export)?;
        let centres = export::voxel_centres(occupancy);
        let voxel_colours = photo.as_ref().map(|ph| ph.voxel_colours(occupancy));
        export::write_ply_points(&p("voxels.ply"), &centres, voxel_colours.as_ref()).map_err(ScanError::Export)?;
        timings.export = t.elapsed().as_secs_f64();

        events(ScanEvent::Stage("evaluate"));
        // A view whose mask does not fit its camera cannot reach here (carving rejected it).
        let reprojection: Vec<f64> = reprojection_iou(occupancy, views).into_iter().map(|v| v.unwrap_or(0.0)).collect();
        let mean =
            if reprojection.is_empty() { 0.0 } else { reprojection.iter().sum::<f64>() / reprojection.len() as f64 };
        let grid = occupancy.grid();
        let voxel_volume = grid.voxel_size.powi(3);
        let ground_truth = truth.map(|(scene, truth)| {
            // Same grid by construction.
            let overlap = occupancy.iou_and_containment(truth).map_or((0.0, 0.0), |o| (o.iou, o.containment));
            GroundTruth {
                scene: scene.to_owned(),
                iou: overlap.0,
                containment: overlap.1,
                voxels: truth.count(),
                volume_m3: truth.count() as f64 * voxel_volume,
                chamfer_m: None,
                chamfer_rel: None,
                colour_error: photo.as_ref().and_then(|p| p.colour_error),
            }
        });
        let mut files = vec!["model.ply".to_owned(), "model.stl".into(), "model.obj".into(), "voxels.ply".into()];
        if frames.is_some() {
            files.push("frames/".into());
        }
        files.push("report.json".into());
        timings.total = started.elapsed().as_secs_f64();
        let bbox = grid.bbox();
        let report = Report {
            scanrig_version: env!("CARGO_PKG_VERSION"),
            source,
            method,
            views: views.len(),
            resolution: grid.dims,
            voxel_size_m: grid.voxel_size,
            bbox_m: [bbox.min, bbox.max],
            occupied_voxels: occupancy.count(),
            volume_m3: occupancy.count() as f64 * voxel_volume,
            mesh_triangles: mesh.triangles.len(),
            timings_s: timings,
            reprojection_iou: reprojection,
            reprojection_iou_mean: mean,
            frames,
            ground_truth,
            visual_hull: photo.as_ref().map(|p| p.visual_hull.clone()),
            photo: photo.map(|p| p.report),
            files,
            shadow_carving: None,
            depth_fusion: None,
        };
        let json = serde_json::to_vec_pretty(&report).map_err(ScanError::EncodeReport)?;
        write_atomic(&p("report.json"), &json).map_err(ScanError::Export)?;
        Ok(report)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reopening_removes_partial_writes_and_keeps_complete_frames() {
        let dir = tempfile::tempdir().expect("tempdir");
        let frames = dir.path().join("frames");
        std::fs::create_dir_all(&frames).expect("mkdir");
        std::fs::write(frames.join("pos_000.png"), b"complete").expect("write");
        std::fs::write(frames.join(".pos_001.json.tmp-4242"), b"half").expect("write");
        std::fs::write(dir.path().join(".model.ply.tmp-4242"), b"half").expect("write");
        let out = OutputDir::reopen(dir.path()).expect("reopen");
        assert!(frames.join("pos_000.png").is_file());
        assert!(!frames.join(".pos_001.json.tmp-4242").exists());
        assert!(!dir.path().join(".model.ply.tmp-4242").exists());
        assert_eq!(out.path(), dir.path());
        assert!(export::is_atomic_temp(".report.json.tmp-1") && !export::is_atomic_temp("pos_000.png"));
    }
}

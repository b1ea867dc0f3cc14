//! The output directory of a scan or reconstruction (the stored-scan layout; see the README's
//! "Stored scans"):
//!
//! ```text
//! DIR/rig.toml                 the effective rig file the scan ran with (scans only)
//! DIR/frames/pos_NNN*.png ...  each position's raw frames, written as they arrive (scans only)
//! DIR/frames/pos_NNN.json ...  each position's record (angle, files, lights), written after them
//! DIR/frames/prepare.json      what a method measured before the positions (structured light)
//! DIR/model.ply                binary PLY triangle mesh (vertex colours where the method gives them)
//! DIR/model.stl                binary STL
//! DIR/model.obj                OBJ
//! DIR/voxels.ply               occupied voxel centres as a point cloud (coloured by the photo methods)
//! DIR/cloud.ply                measured points with normals and colours (laser, structured light)
//! DIR/report.json              written last: a directory is a finished result iff it has one
//! ```
//! Every file is written atomically (temporary file, fsync, rename), so a crash or a full disk never
//! leaves a half-written file under a final name.

use std::path::{Path, PathBuf};
use std::time::Instant;

use rayon::prelude::*;

use super::flow::Outcome;
use super::report::{ground_truth, Report, Timings};
use super::{ScanError, ScanEvent};
use crate::acquisition::AcquisitionSummary;
use crate::atomic::{is_atomic_temp, write_atomic};
use crate::config::{Method, RigConfig};
use crate::pipeline::export;
use crate::pipeline::{keep_main_component, reprojection_iou, simplify_within, Occupancy, View};

/// Area samples per surface (besides its vertices) for the Hausdorff distance of the simplified mesh.
const HAUSDORFF_SAMPLES: usize = 100_000;

/// The files of an earlier result that [`OutputDir::prepare`] removes (`report.json` first).
const RESULT_FILES: [&str; 6] = ["model.ply", "model.stl", "model.obj", "voxels.ply", "cloud.ply", "rig.toml"];

/// A prepared output directory.
#[derive(Debug)]
pub struct OutputDir {
    path: PathBuf,
}

/// The simulated scene a result is compared with.
#[derive(Debug)]
pub struct TruthRef<'a> {
    /// The scene (object frame, metres).
    pub scene: &'a crate::sim::Scene,
    /// Its name in the rig file (`[sim] scene`).
    pub scene_name: &'a str,
    /// Its true occupancy on the result's grid.
    pub occupancy: &'a Occupancy,
}

/// Everything [`OutputDir::write_outcome`] needs.
pub struct Results<'a> {
    /// Rig name or data set.
    pub source: String,
    /// The method.
    pub method: Method,
    /// The stored scan a reprocess read its views from.
    pub reprocessed_from: Option<String>,
    /// What the method produced.
    pub outcome: Outcome,
    /// Error bound of the mesh simplification, voxel edges (`[reconstruction.mesh] max_error_voxels`;
    /// 0 = none).
    pub mesh_max_error_voxels: f64,
    /// The simulated truth (simulated rigs only).
    pub truth: Option<TruthRef<'a>>,
    /// Acquisition counters (scans only).
    pub frames: Option<AcquisitionSummary>,
    /// Timings so far.
    pub timings: Timings,
    /// When the job started.
    pub started: Instant,
    /// When the last view arrived (captured, or replayed from disk).
    pub last_view_at: Instant,
    /// Progress sink.
    pub events: &'a mut dyn FnMut(ScanEvent),
}

impl std::fmt::Debug for Results<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Results").field("source", &self.source).field("method", &self.method).finish_non_exhaustive()
    }
}

/// Remove the temporary files of atomic writes that a killed process left in `dir` and `dir/frames`
/// (see [`is_atomic_temp`]); complete files are never touched.
fn remove_partial_writes(dir: &Path) -> Result<(), ScanError> {
    for d in [dir.to_owned(), dir.join("frames")] {
        let Ok(entries) = std::fs::read_dir(&d) else { continue };
        for entry in entries.flatten() {
            if is_atomic_temp(&entry.file_name().to_string_lossy()) {
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
        for name in RESULT_FILES {
            match std::fs::remove_file(path.join(name)) {
                Ok(()) => {}
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
                Err(e) => return Err(err("cannot remove a previous result file")(e)),
            }
        }
        let frames = path.join("frames");
        if frames.is_dir() {
            for entry in std::fs::read_dir(&frames).map_err(err("cannot list frames/"))? {
                let entry = entry.map_err(err("cannot list frames/"))?;
                let name = entry.file_name();
                let name = name.to_string_lossy();
                if (name.starts_with("pos_") && (name.ends_with(".png") || name.ends_with(".json")))
                    || name == "prepare.json"
                {
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

    /// The directory.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Prepare `path` for the result of reprocessing the stored scan in `scan_dir`: as
    /// [`OutputDir::prepare`], refusing the stored scan's own directory (its frames would go).
    pub fn prepare_result(path: &Path, scan_dir: &Path) -> Result<OutputDir, ScanError> {
        let same = match (std::fs::canonicalize(path), std::fs::canonicalize(scan_dir)) {
            (Ok(a), Ok(b)) => a == b,
            _ => path == scan_dir,
        };
        if same {
            return Err(ScanError::OverwriteStored { path: path.to_owned() });
        }
        OutputDir::prepare(path)
    }

    /// Store the effective rig file as `rig.toml` (calibration already applied, so the file stands
    /// alone), for resuming and reprocessing.
    pub fn write_rig_file(&self, config: &RigConfig) -> Result<(), ScanError> {
        let mut config = config.clone();
        config.rig.calibration = None;
        let text = toml::to_string(&config).map_err(ScanError::EncodeRigFile)?;
        let text = format!(
            "# The rig file this scan ran with (request overrides and calibration applied), written by scanrig {}.\n{text}",
            env!("CARGO_PKG_VERSION")
        );
        write_atomic(&self.path.join(super::driver::RIG_FILE), text.as_bytes()).map_err(ScanError::Write)
    }

    /// Export the outcome, evaluate it, and write `report.json` last.
    pub fn write_outcome(&self, r: Results<'_>) -> Result<Report, ScanError> {
        let Results {
            source,
            method,
            reprocessed_from,
            outcome,
            mesh_max_error_voxels,
            truth,
            frames,
            mut timings,
            started,
            last_view_at,
            events,
        } = r;
        let Outcome {
            views: view_count,
            solid,
            mesh,
            mesh_handles,
            cloud,
            voxel_colours,
            silhouettes,
            visual_hull,
            colour_error,
            details,
        } = outcome;

        // One watertight surface: parts floating apart from the main one and internal cavities go;
        // then it is simplified within the error bound, checked by its Hausdorff distance. The
        // solid's re-projection into the silhouettes (evaluated below) does not depend on the mesh:
        // it is measured meanwhile, the two sharing the thread pool.
        let t = Instant::now();
        let views: Vec<View<'_>> = silhouettes.iter().map(|(camera, mask)| View { camera: *camera, mask }).collect();
        let ((mesh, mesh_cleanup, mesh_simplification), reprojection) = rayon::join(
            || {
                // The raw mesh goes once its main component is copied out: it is not read again,
                // and the simplifier's state is the stage's peak memory.
                let raw = mesh;
                let (mesh, mesh_cleanup) = keep_main_component(&raw);
                drop(raw);
                if mesh_cleanup.triangles_removed > 0 {
                    tracing::info!(?mesh_cleanup, "mesh cleaned to its main component");
                }
                let max_error_m = mesh_max_error_voxels * solid.grid().voxel_size;
                match simplify_within(&mesh, max_error_m, HAUSDORFF_SAMPLES) {
                    Some((simple, s)) => (simple, mesh_cleanup, Some(s)),
                    None => (mesh, mesh_cleanup, None),
                }
            },
            // A view whose mask does not fit its camera cannot reach here (carving rejected it).
            || -> Vec<f64> { reprojection_iou(&solid, &views).into_iter().map(|v| v.unwrap_or(0.0)).collect() },
        );
        timings.mesh += t.elapsed().as_secs_f64();
        if let Some(s) = &mesh_simplification {
            tracing::info!(
                before = s.stats.triangles_before,
                after = s.stats.triangles_after,
                hausdorff_m = s.hausdorff.symmetric_m,
                bound_m = s.max_error_m,
                simplify_s = s.simplify_s,
                check_s = s.check_s,
                "mesh simplified"
            );
            if !s.within_bound {
                // Every vertex is within the bound by construction; a sample inside a triangle was not.
                tracing::warn!(
                    hausdorff_m = s.hausdorff.symmetric_m,
                    bound_m = s.max_error_m,
                    "simplified mesh measured beyond its error bound (kept; the report says so)"
                );
            }
        }

        events(ScanEvent::Stage("export"));
        let t = Instant::now();
        // The files are independent: written side by side (each atomically), the first error reported.
        let p = |name: &str| self.path.join(name);
        type Write<'w> = Box<dyn Fn() -> Result<(), export::ExportError> + Send + Sync + 'w>;
        let mut writes: Vec<(&str, Write<'_>)> = vec![
            ("model.ply", Box::new(|| export::write_ply_mesh(&p("model.ply"), &mesh))),
            ("model.stl", Box::new(|| export::write_stl(&p("model.stl"), &mesh))),
            ("model.obj", Box::new(|| export::write_obj(&p("model.obj"), &mesh))),
            ("voxels.ply", Box::new(|| export::write_ply_voxels(&p("voxels.ply"), &solid, voxel_colours.as_ref()))),
        ];
        if let Some(cloud) = &cloud {
            writes.push(("cloud.ply", Box::new(|| cloud.write_ply(&p("cloud.ply")))));
        }
        // Meanwhile the mesh's topology (for the report) is counted and, on a simulated rig, the
        // result is compared with the scene: both only read what the writes read, and the writes
        // spend much of their time waiting for the disk (fsync).
        let grid = *solid.grid();
        let (written, (mesh_topology, ground_truth)) = rayon::join(
            || -> Vec<Result<(), export::ExportError>> { writes.par_iter().map(|(_, write)| write()).collect() },
            || {
                let ground_truth = truth.as_ref().map(|t| {
                    // The surface-measuring methods are judged by their mesh too; a carved hull's mesh
                    // is as far from the truth as its excess volume, which IoU already says (and is
                    // slow to measure).
                    let mesh = method.measures_surface().then_some(&mesh);
                    let mut gt = ground_truth(t.scene, t.scene_name, t.occupancy, &solid, mesh);
                    gt.colour_error = colour_error;
                    gt
                });
                (mesh.topology(), ground_truth)
            },
        );
        written.into_iter().collect::<Result<(), _>>().map_err(ScanError::Export)?;
        let mut files: Vec<String> = writes.iter().map(|(name, _)| (*name).to_owned()).collect();
        timings.export = t.elapsed().as_secs_f64();

        let mean =
            if reprojection.is_empty() { 0.0 } else { reprojection.iter().sum::<f64>() / reprojection.len() as f64 };
        if let Some(gt) = &ground_truth {
            tracing::info!(iou = gt.iou, chamfer_rel = gt.chamfer_rel, "result compared with the simulated scene");
        }
        let visual_hull = visual_hull.map(|(hull, mut summary)| {
            if let Some(o) = truth.as_ref().and_then(|t| hull.iou_and_containment(t.occupancy).ok()) {
                summary.iou = Some(o.iou);
                summary.containment = Some(o.containment);
            }
            summary
        });
        if frames.is_some() {
            files.push("frames/".into());
            files.push(super::driver::RIG_FILE.into());
        }
        files.push("report.json".into());
        timings.total = started.elapsed().as_secs_f64();
        timings.after_last_frame_s = last_view_at.elapsed().as_secs_f64();
        let bbox = grid.bbox();
        let report = Report {
            scanrig_version: env!("CARGO_PKG_VERSION"),
            source,
            method,
            reprocessed_from,
            views: view_count,
            resolution: grid.dims,
            voxel_size_m: grid.voxel_size,
            bbox_m: [bbox.min, bbox.max],
            occupied_voxels: solid.count(),
            volume_m3: solid.volume_m3(),
            mesh_triangles: mesh.triangles.len(),
            mesh_cleanup,
            mesh_handles,
            mesh_simplification,
            mesh_topology,
            timings_s: timings,
            reprojection_iou: reprojection,
            reprojection_iou_mean: mean,
            frames,
            ground_truth,
            files,
            visual_hull,
            details,
        };
        let json = serde_json::to_vec_pretty(&report).map_err(ScanError::EncodeReport)?;
        write_atomic(&p("report.json"), &json).map_err(ScanError::Write)?;
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
        assert!(is_atomic_temp(".report.json.tmp-1") && !is_atomic_temp("pos_000.png"));
    }
}

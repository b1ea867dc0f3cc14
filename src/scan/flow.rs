//! What a reconstruction method contributes to a scan job: [`ScanFlow`], one implementation per
//! method (in [`super::methods`]). Everything every method shares (the output directory, resume
//! replay, the acquisition thread and its bounded channel, progress, export, ground truth and
//! `report.json`) is the driver's ([`super::driver`]).
//!
//! A flow's life: built from the rig file ([`super::methods::for_config`]); `restore` what an earlier
//! run of the same scan measured before its positions, else `prepare` it on the rig; every stored
//! view is `load`ed and `process`ed in position order; the `sequence` acquires the remaining
//! positions on the thread that owns the devices, and each view it delivers is `save`d (atomically,
//! before the driver writes the position's record) and `process`ed as it arrives; `finish` turns
//! the accumulated state into a [`Outcome`].

use std::path::{Path, PathBuf};
use std::sync::mpsc::SyncSender;

use crate::acquisition::{AcquisitionError, AcquisitionSummary, CancelToken, Progress};
use crate::config::Method;
use crate::devices::Rig;
use crate::geometry::{CameraModel, VoxelGrid};
use crate::pipeline::{HandleRepair, Mask, Occupancy, PointCloud, TriangleMesh};

use super::report::{MethodDetails, Timings, VisualHull};
use super::{ScanError, ScanEvent};

/// The acquisition of a flow's positions `first..` of the plan: runs on the acquisition thread with
/// the rig's devices, sends one view per position, and parks the rig at the end (also after an error
/// or cancellation).
pub type Sequence<V> = Box<
    dyn FnOnce(
            &mut Rig,
            &SyncSender<V>,
            &CancelToken,
            &mut dyn FnMut(&Progress),
        ) -> Result<AcquisitionSummary, AcquisitionError>
        + Send,
>;

/// What the driver needs to know of every view, whatever the method: where it was taken.
pub trait PositionView {
    /// 0-based position in the plan.
    fn position(&self) -> usize;
    /// Turntable angle the view was taken at, degrees (as the turntable reported it).
    fn angle_deg(&self) -> f64;
    /// The camera's sequence number of the view's first frame (0 for a stored view).
    fn sequence(&self) -> u64;
    /// Stale frames thrown away while taking it.
    fn stale_discarded(&self) -> u32;
}

/// `frames/pos_NNN.json`: the record of one stored position, written after every file of the view,
/// so a position is complete on disk if and only if its record exists. Other rigs' captures are laid
/// out the same way (see the README's "Stored scans").
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ViewRecord {
    /// 0-based position in the plan.
    pub position: usize,
    /// Turntable angle of the view, degrees (object frame = rig frame turned by -angle about +z).
    pub angle_deg: f64,
    /// The view's files, relative to `frames/`.
    #[serde(default)]
    pub files: Vec<String>,
    /// White lights on for the view's frames, by index (silhouette methods).
    #[serde(default)]
    pub lights_on: Vec<usize>,
    /// The camera's sequence number of the view's first frame.
    #[serde(default)]
    pub sequence: u64,
    /// Stale frames discarded before the view.
    #[serde(default)]
    pub stale_discarded: u32,
}

/// The `frames/` directory of a stored scan: where views are written to and read back from.
#[derive(Debug, Clone)]
pub struct FrameDir {
    dir: PathBuf,
}

impl FrameDir {
    /// The `frames/` directory below a scan directory.
    pub fn of_scan(scan_dir: &Path) -> FrameDir {
        FrameDir { dir: scan_dir.join("frames") }
    }

    /// The directory.
    pub fn path(&self) -> &Path {
        &self.dir
    }

    /// A file in it.
    pub fn file(&self, name: &str) -> PathBuf {
        self.dir.join(name)
    }

    /// Create the directory.
    pub fn create(&self) -> Result<(), ScanError> {
        std::fs::create_dir_all(&self.dir).map_err(|source| ScanError::OutputDir {
            path: self.dir.clone(),
            what: "cannot create it",
            source,
        })
    }

    /// `pos_NNN` for `position`.
    pub fn stem(position: usize) -> String {
        format!("pos_{position:03}")
    }

    /// The record file of `position`.
    pub fn record_path(&self, position: usize) -> PathBuf {
        self.dir.join(format!("{}.json", Self::stem(position)))
    }

    /// Write an RGB image as PNG (fast compression: frames are written as they arrive), atomically.
    pub fn write_rgb(&self, name: &str, image: &image::RgbImage) -> Result<String, ScanError> {
        self.write_png(name, image.width(), image.height(), image.as_raw(), image::ExtendedColorType::Rgb8)?;
        Ok(name.to_owned())
    }

    /// Write a 16-bit grey image as PNG, atomically.
    pub fn write_grey16(&self, name: &str, width: u32, height: u32, data: &[u16]) -> Result<String, ScanError> {
        let bytes: Vec<u8> = data.iter().flat_map(|v| v.to_ne_bytes()).collect();
        self.write_png(name, width, height, &bytes, image::ExtendedColorType::L16)?;
        Ok(name.to_owned())
    }

    fn write_png(
        &self,
        name: &str,
        width: u32,
        height: u32,
        bytes: &[u8],
        colour: image::ExtendedColorType,
    ) -> Result<(), ScanError> {
        use image::ImageEncoder;
        let file = self.file(name);
        let mut png = Vec::with_capacity(bytes.len() / 2);
        let encoder = image::codecs::png::PngEncoder::new_with_quality(
            &mut png,
            image::codecs::png::CompressionType::Fast,
            image::codecs::png::FilterType::Sub,
        );
        encoder
            .write_image(bytes, width, height, colour)
            .map_err(|source| ScanError::EncodeFrame { path: file.clone(), source })?;
        crate::atomic::write_atomic(&file, &png).map_err(ScanError::Write)
    }

    /// Read an 8-bit RGB image (any format the image crate reads; grey images are expanded).
    pub fn read_rgb(&self, name: &str) -> Result<image::RgbImage, ScanError> {
        let file = self.file(name);
        Ok(open_image(&file)?.to_rgb8())
    }

    /// Read a 16-bit grey image.
    pub fn read_grey16(&self, name: &str) -> Result<image::ImageBuffer<image::Luma<u16>, Vec<u16>>, ScanError> {
        let file = self.file(name);
        Ok(open_image(&file)?.into_luma16())
    }

    /// Write a JSON document atomically.
    pub fn write_json<T: serde::Serialize>(&self, name: &str, value: &T) -> Result<(), ScanError> {
        let json = serde_json::to_vec_pretty(value).map_err(ScanError::EncodeReport)?;
        crate::atomic::write_atomic(&self.file(name), &json).map_err(ScanError::Write)
    }

    /// Read a JSON document; `Ok(None)` when the file does not exist.
    pub fn read_json<T: serde::de::DeserializeOwned>(&self, name: &str) -> Result<Option<T>, ScanError> {
        let path = self.file(name);
        let bytes = match std::fs::read(&path) {
            Ok(b) => b,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(source) => return Err(ScanError::OutputDir { path, what: "cannot read it", source }),
        };
        serde_json::from_slice(&bytes).map(Some).map_err(|source| ScanError::FrameMeta { path, source })
    }

    /// The record of `position`, if that position is complete on disk.
    pub fn read_record(&self, position: usize) -> Result<Option<ViewRecord>, ScanError> {
        let record: Option<ViewRecord> = self.read_json(&format!("{}.json", Self::stem(position)))?;
        match record {
            Some(r) if r.position != position => {
                Err(ScanError::RecordMismatch { path: self.record_path(position), found: r.position })
            }
            other => Ok(other),
        }
    }

    /// The records of the leading complete positions 0, 1, ... (at most `total`).
    pub fn complete_records(&self, total: usize) -> Result<Vec<ViewRecord>, ScanError> {
        let mut out = Vec::new();
        for position in 0..total {
            match self.read_record(position)? {
                Some(r) => out.push(r),
                None => break,
            }
        }
        Ok(out)
    }
}

/// Open an image file, with an error that names it (missing, unreadable, not an image).
fn open_image(file: &Path) -> Result<image::DynamicImage, ScanError> {
    image::ImageReader::open(file)
        .map_err(|source| ScanError::OutputDir { path: file.to_owned(), what: "cannot open the frame", source })?
        .with_guessed_format()
        .map_err(|source| ScanError::OutputDir { path: file.to_owned(), what: "cannot read the frame", source })?
        .decode()
        .map_err(|source| ScanError::DecodeFrame { path: file.to_owned(), source })
}

/// What a flow hands the driver at the end.
#[derive(Debug)]
pub struct Outcome {
    /// Views the result was made from.
    pub views: usize,
    /// The reconstructed solid on the job's grid (voxels.ply, volume, IoU with the truth).
    pub solid: Occupancy,
    /// The surface (object frame, metres), with vertex colours where the method gives them.
    pub mesh: TriangleMesh,
    /// What removing voxel-scale handles before meshing changed (`None` when it did not run).
    pub mesh_handles: Option<HandleRepair>,
    /// A point cloud (object frame, metres) for `cloud.ply`, from the methods that measure points.
    pub cloud: Option<PointCloud>,
    /// Colours of the solid's occupied voxels in `for_each_occupied` order (photo methods).
    pub voxel_colours: Option<Vec<[u8; 3]>>,
    /// Cameras (object frame) and silhouettes to check the solid against (re-projection IoU).
    pub silhouettes: Vec<(CameraModel, Mask)>,
    /// The visual hull a refining method started from or is compared with (the driver fills in its
    /// overlap with the truth).
    pub visual_hull: Option<(Occupancy, VisualHull)>,
    /// Mean absolute colour error of the result against the simulated truth (photo methods).
    pub colour_error: Option<f64>,
    /// The method's own figures for `report.json`.
    pub details: MethodDetails,
}

/// What the driver gives a flow's `finish`.
pub struct Finish<'a> {
    /// The job's grid (object frame).
    pub grid: VoxelGrid,
    /// The simulated scene's true occupancy on the grid and its colour, on simulated rigs.
    pub truth: Option<&'a super::methods::photo::Truth<'a>>,
    /// Timings so far; the flow adds its finishing stages (carve, mesh).
    pub timings: &'a mut Timings,
    /// Progress sink.
    pub events: &'a mut dyn FnMut(ScanEvent),
}

impl std::fmt::Debug for Finish<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Finish").field("grid", &self.grid).finish_non_exhaustive()
    }
}

/// One reconstruction method as the job driver runs it. Implementations live one per file in
/// [`super::methods`]; adding a method is one such file plus its arm in
/// [`super::methods::for_config`].
pub trait ScanFlow {
    /// The raw data of one turntable position, as the acquisition delivers it and as it is stored.
    type View: PositionView + Send + 'static;

    /// The method.
    fn method(&self) -> Method;

    /// Read back what [`ScanFlow::prepare`] stored in `frames` for an earlier run of this scan;
    /// `Ok(false)` when nothing was stored (the driver then prepares on the rig, or fails a
    /// reprocess that needs it).
    fn restore(&mut self, _frames: &FrameDir) -> Result<bool, ScanError> {
        Ok(true)
    }

    /// Measure on the rig what the method needs before the positions (e.g. the projector's
    /// response) and store it in `frames`.
    fn prepare(
        &mut self,
        _rig: &mut Rig,
        _frames: &FrameDir,
        _cancel: &CancelToken,
        _events: &mut dyn FnMut(ScanEvent),
    ) -> Result<(), ScanError> {
        Ok(())
    }

    /// The acquisition of positions `first..`.
    fn sequence(&self, first: usize) -> Sequence<Self::View>;

    /// Store `view`'s raw data in `frames` (each file atomically); returns the files written and the
    /// lights that were on. The driver writes the position's record after this returns.
    fn save(&self, frames: &FrameDir, view: &Self::View) -> Result<(Vec<String>, Vec<usize>), ScanError>;

    /// Read the view of `record` back from `frames`.
    fn load(&self, frames: &FrameDir, record: &ViewRecord) -> Result<Self::View, ScanError>;

    /// Process one view as it arrives (stored views first, in position order). Returns a line for
    /// the progress display ("carved, 12345 voxels left").
    fn process(&mut self, view: Self::View, events: &mut dyn FnMut(ScanEvent)) -> Result<String, ScanError>;

    /// The current estimate as a compact point cloud for a live view (object frame, metres, at
    /// most `max_points` points; see [`super::preview`]), or `None` while there is nothing to show.
    /// Called between views, so it must cost little beside a view's processing.
    fn preview(&self, _max_points: usize) -> Option<PointCloud> {
        None
    }

    /// Turn everything processed into the result.
    fn finish(self, finish: Finish<'_>) -> Result<Outcome, ScanError>;
}

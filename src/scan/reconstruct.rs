//! `scanrig reconstruct`: the space carving pipeline on a calibrated image set on disk, writing the
//! same outputs as a scan.

use std::path::{Path, PathBuf};
use std::time::Instant;

use nalgebra::{Matrix3, Vector3};

use super::methods::silhouette::{outcome_from_hull, HullResult};
use super::output::{self, OutputDir};
use super::report::{Report, Timings};
use super::{ScanError, ScanEvent};
use crate::config::Method;
use crate::dataset::{self, Dataset, DatasetError, DatasetOptions};
use crate::geometry::{Aabb, VoxelGrid};
use crate::pipeline::{CarveError, SpaceCarver};

/// What to reconstruct and how.
#[derive(Debug, Clone)]
pub struct ReconstructOptions {
    /// The data set: directory, calibration, views, masks.
    pub dataset: DatasetOptions,
    /// The method (`space-carving`).
    pub method: Method,
    /// Voxels along the longest side of the box.
    pub resolution: u32,
    /// The working volume in the data set's frame, metres; `None` estimates it from the cameras and
    /// silhouettes (see [`estimate_box`]).
    pub bbox: Option<Aabb>,
    /// Occupancy smoothing radius for the mesh, voxels.
    pub smooth_radius: u32,
    /// Error bound of the mesh simplification, voxel edges (0 = none; see
    /// [`crate::config::MeshConfig::max_error_voxels`]).
    pub mesh_max_error_voxels: f64,
    /// The photo-consistency test (`voxel-coloring`, `space-carving-photo`).
    pub photo: crate::config::PhotoConfig,
    /// Output directory.
    pub out: PathBuf,
}

/// Why a reconstruction failed.
#[derive(Debug, thiserror::Error)]
pub enum ReconstructError {
    /// The data set could not be loaded.
    #[error(transparent)]
    Dataset(#[from] DatasetError),
    /// Carving failed.
    #[error("space carving failed")]
    Carve(#[source] CarveError),
    /// The box could not be estimated.
    #[error("cannot estimate a working volume: {0}; give one with --bbox")]
    NoBox(&'static str),
    /// No view shows any object pixel where the box projects: the box misses the object
    /// (wrong units or frame?).
    #[error("no view shows any silhouette pixel inside the bounding box {min:?} .. {max:?} (metres): the box misses the object; check its units and frame")]
    BoxMissesObject {
        /// Minimum corner, metres.
        min: [f64; 3],
        /// Maximum corner, metres.
        max: [f64; 3],
    },
    /// Writing the results failed.
    #[error(transparent)]
    Output(#[from] ScanError),
    /// Photo-consistency reconstruction failed.
    #[error("photo-consistency reconstruction failed")]
    Photo(#[source] crate::pipeline::PhotoError),
    /// A photo-consistency method needs the images, and this view has none loaded.
    #[error("view {name}: the photo-consistency methods need its image")]
    NoImage {
        /// The view's image name.
        name: String,
    },
}

/// Load the data set, carve, mesh and write the results into `opts.out`.
pub fn run_reconstruct(
    opts: &ReconstructOptions,
    events: &mut dyn FnMut(ScanEvent),
) -> Result<Report, ReconstructError> {
    let started = Instant::now();
    let out = OutputDir::prepare(&opts.out)?;
    let mut timings = Timings::default();

    events(ScanEvent::Stage("load"));
    let t = Instant::now();
    let data = dataset::load(&opts.dataset)?;
    // Loading includes silhouette extraction when the masks come from the images.
    timings.capture = t.elapsed().as_secs_f64();

    let bbox = match opts.bbox {
        Some(b) => b,
        None => estimate_box(&data)?,
    };
    data.check_box_seen(&bbox)?;
    if !box_holds_silhouette(&data, &bbox) {
        return Err(ReconstructError::BoxMissesObject { min: bbox.min, max: bbox.max });
    }
    let grid = VoxelGrid::from_resolution(&bbox, opts.resolution);
    let views = data.carving_views();

    events(ScanEvent::Stage("carve"));
    let mut carver = SpaceCarver::new(grid).map_err(ReconstructError::Carve)?;
    let t = Instant::now();
    carver.add_views(&views).map_err(ReconstructError::Carve)?;
    timings.carve = t.elapsed().as_secs_f64();
    tracing::info!(occupied = carver.occupancy().count(), carve_s = timings.carve, "carved");

    let mut images = Vec::new();
    if opts.method.is_photo() {
        for v in &data.views {
            images.push(v.image.as_ref().ok_or_else(|| ReconstructError::NoImage { name: v.name.clone() })?);
        }
    }
    let silhouettes: Vec<_> = data.views.iter().map(|v| (v.camera, v.mask.clone())).collect();
    let silhouette_pixels = silhouettes.iter().map(|(_, m)| m.count() as u64).sum();
    drop(views);
    let hull = HullResult { method: opts.method, carver, views: silhouettes, images: &images };
    let outcome =
        outcome_from_hull(hull, &opts.photo, opts.smooth_radius, silhouette_pixels, None, &mut timings, events)?;
    let report = out.write_outcome(output::Results {
        source: opts.dataset.dir.display().to_string(),
        method: opts.method,
        reprocessed_from: None,
        outcome,
        mesh_max_error_voxels: opts.mesh_max_error_voxels,
        truth: None,
        frames: None,
        timings,
        started,
        last_view_at: Instant::now(),
        events,
    })?;
    Ok(report)
}

/// Estimate a working volume from the data set alone: the point nearest to every optical axis
/// (least squares) is taken as the object's centre; in a cube reaching half the median camera
/// distance around it, sampled at 64 voxels a side, a voxel counts as object when no view carves it
/// and at least half of the views see it (its centre projects inside their image; voxels seen by
/// few views are the unconstrained space around the object). Their bounds, grown by two voxels on
/// every side, are the box.
pub fn estimate_box(data: &Dataset) -> Result<Aabb, ReconstructError> {
    use rayon::prelude::*;
    let mut a = Matrix3::zeros();
    let mut b = Vector3::zeros();
    for v in &data.views {
        let c = v.camera.centre();
        let axis = v.camera.pose.rotation.row(2).transpose();
        let m = Matrix3::identity() - axis * axis.transpose();
        a += m;
        b += m * c;
    }
    let centre = a.try_inverse().ok_or(ReconstructError::NoBox("the optical axes are parallel"))? * b;
    let mut d: Vec<f64> = data.views.iter().map(|v| (v.camera.centre() - centre).norm()).collect();
    d.sort_by(f64::total_cmp);
    let half = d[d.len() / 2] * 0.5;
    if !(half.is_finite() && half > 0.0) {
        return Err(ReconstructError::NoBox("the cameras coincide with the estimated centre"));
    }
    const N: usize = 64;
    let coarse = Aabb { min: (centre - Vector3::repeat(half)).into(), max: (centre + Vector3::repeat(half)).into() };
    let grid = VoxelGrid::from_resolution(&coarse, N as u32);
    let need = data.views.len().div_ceil(2);
    let object: Vec<[usize; 3]> = (0..grid.len())
        .into_par_iter()
        .filter_map(|idx| {
            let (i, j, k) =
                (idx % grid.dims[0], (idx / grid.dims[0]) % grid.dims[1], idx / (grid.dims[0] * grid.dims[1]));
            let p = grid.centre(i, j, k);
            let mut seen = 0;
            for v in &data.views {
                if let Some((u, w)) = v.camera.pixel_of(&p) {
                    if !v.mask.get(u, w) {
                        return None;
                    }
                    seen += 1;
                }
            }
            (seen >= need).then_some([i, j, k])
        })
        .collect();
    if object.is_empty() {
        return Err(ReconstructError::NoBox("no voxel is inside the silhouettes of at least half of the views"));
    }
    let mut lo = [usize::MAX; 3];
    let mut hi = [0usize; 3];
    for v in &object {
        for a in 0..3 {
            lo[a] = lo[a].min(v[a]);
            hi[a] = hi[a].max(v[a]);
        }
    }
    let s = grid.voxel_size;
    let min = [0, 1, 2].map(|a| grid.origin[a] + (lo[a] as f64 - 2.0) * s);
    let max = [0, 1, 2].map(|a| grid.origin[a] + (hi[a] as f64 + 3.0) * s);
    Ok(Aabb { min, max })
}

/// Whether any of 24^3 points spread evenly through the box projects inside a silhouette in some
/// view (points behind a camera or outside its image do not count).
pub fn box_holds_silhouette(data: &Dataset, bbox: &Aabb) -> bool {
    use rayon::prelude::*;
    const N: usize = 24;
    let e = bbox.extent();
    (0..N * N * N).into_par_iter().any(|idx| {
        let (i, j, k) = (idx % N, (idx / N) % N, idx / (N * N));
        let p = Vector3::new(
            bbox.min[0] + (i as f64 + 0.5) / N as f64 * e[0],
            bbox.min[1] + (j as f64 + 0.5) / N as f64 * e[1],
            bbox.min[2] + (k as f64 + 0.5) / N as f64 * e[2],
        );
        data.views.iter().any(|v| v.camera.pixel_of(&p).is_some_and(|(u, w)| v.mask.get(u, w)))
    })
}

/// Parse `xmin,ymin,zmin,xmax,ymax,zmax` (metres).
pub fn parse_bbox(s: &str) -> Result<Aabb, String> {
    let v: Vec<f64> = s
        .split(',')
        .map(|x| x.trim().parse::<f64>().map_err(|_| format!("`{}` is not a number", x.trim())))
        .collect::<Result<_, _>>()?;
    if v.len() != 6 {
        return Err(format!("expected 6 numbers xmin,ymin,zmin,xmax,ymax,zmax, got {}", v.len()));
    }
    let b = Aabb { min: [v[0], v[1], v[2]], max: [v[3], v[4], v[5]] };
    if !b.is_valid() {
        return Err("the box must be finite with max > min on every axis".into());
    }
    Ok(b)
}

/// Parse `threshold=0.19,dilate=10,erode=7` (any subset; background black unless
/// `background=r:g:b`).
pub fn parse_silhouette(s: &str) -> Result<crate::pipeline::SilhouetteParams, String> {
    let mut p = crate::pipeline::SilhouetteParams::MIDDLEBURY;
    for part in s.split(',').map(str::trim).filter(|x| !x.is_empty()) {
        let (k, v) = part.split_once('=').ok_or_else(|| format!("`{part}` is not key=value"))?;
        let num = |v: &str| v.trim().parse::<f64>().map_err(|_| format!("`{k}`: `{v}` is not a number"));
        match k.trim() {
            "threshold" => {
                let t = num(v)?;
                if !(0.0..1.0).contains(&t) {
                    return Err(format!("threshold {t} is not in [0, 1)"));
                }
                p.threshold = t as f32;
            }
            "dilate" | "erode" => {
                let r = num(v)?;
                if !((0.0..=64.0).contains(&r) && r.fract() == 0.0) {
                    return Err(format!("`{k}` must be a whole number of pixels from 0 to 64"));
                }
                if k.trim() == "dilate" {
                    p.dilate = r as u32;
                } else {
                    p.erode = r as u32;
                }
            }
            "background" => {
                let c: Vec<u8> = v
                    .split(':')
                    .map(|x| x.trim().parse::<u8>())
                    .collect::<Result<_, _>>()
                    .map_err(|_| format!("background `{v}` is not r:g:b with 0..255 values"))?;
                if c.len() != 3 {
                    return Err(format!("background `{v}` is not r:g:b"));
                }
                p.background = [c[0], c[1], c[2]];
            }
            other => {
                return Err(format!("unknown silhouette parameter `{other}` (threshold, dilate, erode, background)"))
            }
        }
    }
    Ok(p)
}

/// The default location of the calibration when only a directory is given.
pub fn dataset_options(
    dir: &Path,
    calibration: Option<PathBuf>,
    views: Option<&str>,
    masks: Option<PathBuf>,
    silhouette: crate::pipeline::SilhouetteParams,
) -> DatasetOptions {
    DatasetOptions {
        dir: dir.to_owned(),
        calibration,
        views: views.map_or(dataset::ViewSelection::All, dataset::ViewSelection::parse),
        masks: masks.map_or(dataset::MaskSource::Extract(silhouette), dataset::MaskSource::Directory),
        load_images: false,
    }
}

/// Parse `threshold=T,min_cos=C,min_views=N,ncc=X,iterations=I` (any subset, any order) over
/// the defaults of `[reconstruction.photo]`; `threshold=measured` (the default) derives the threshold
/// from the data's measured noise.
pub fn parse_photo(text: &str) -> Result<crate::config::PhotoConfig, &'static str> {
    let mut c = crate::config::PhotoConfig::default();
    for part in text.split(',').filter(|p| !p.trim().is_empty()) {
        let (key, value) = part.split_once('=').ok_or("expected key=value pairs")?;
        let num = || value.trim().parse::<f64>().map_err(|_| "a value is not a number");
        match key.trim() {
            "threshold" if value.trim() == "measured" => c.threshold = None,
            "threshold" => c.threshold = Some(num()?),
            "min_cos" => c.min_cos = num()?,
            "ncc" => c.min_ncc = Some(num()?),
            "min_views" => c.min_views = value.trim().parse().map_err(|_| "min_views is not a count")?,
            "iterations" => c.max_iterations = value.trim().parse().map_err(|_| "iterations is not a count")?,
            _ => return Err("unknown key (known: threshold, min_cos, min_views, ncc, iterations)"),
        }
    }
    if c.threshold.is_some_and(|t| !(t > 0.0 && t <= 255.0)) {
        return Err("threshold must be in (0, 255]");
    }
    if !(-1.0..=1.0).contains(&c.min_cos) || c.min_ncc.is_some_and(|n| !(-1.0..=1.0).contains(&n)) {
        return Err("min_cos and ncc must be in [-1, 1]");
    }
    if c.min_views < 2 {
        return Err("min_views must be at least 2");
    }
    Ok(c)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bbox_and_silhouette_arguments_parse_or_say_why() {
        let b = parse_bbox("-1,-2,-3,1,2,3").expect("valid");
        assert_eq!(b.min, [-1.0, -2.0, -3.0]);
        assert!(parse_bbox("1,2,3").expect_err("short").contains("6 numbers"));
        assert!(parse_bbox("0,0,0,1,x,1").expect_err("nan").contains("`x`"));
        assert!(parse_bbox("0,0,0,1,-1,1").expect_err("inverted").contains("max > min"));
        let p = parse_silhouette("threshold=0.2,dilate=3,erode=1").expect("valid");
        assert_eq!((p.threshold, p.dilate, p.erode), (0.2, 3, 1));
        assert_eq!(parse_silhouette("").expect("defaults"), crate::pipeline::SilhouetteParams::MIDDLEBURY);
        assert!(parse_silhouette("thresh=1").expect_err("unknown").contains("thresh"));
        assert!(parse_silhouette("dilate=2.5").expect_err("fraction").contains("whole number"));
    }
}

//! `scanrig calibrate camera | turntable | lights`: the calibration workflow behind the CLI. Each
//! command takes board images from a directory (a real rig) or captures them from a simulated rig
//! file, reports per-image results (re-projection RMS, or the reason an image was rejected), and
//! updates the calibration file (see [`super::file`]) atomically, keeping its other sections.
//!
//! Image names for `turntable --images DIR` carry the table angle: `angle_<degrees>.png`
//! (e.g. `angle_30.png`, `angle_-12.5.png`); `--save-images` writes captures under those names.

use std::path::{Path, PathBuf};

use image::GrayImage;
use nalgebra::Vector3;

use super::capture::SimBoardRig;
use super::detect::{detect_chessboard, to_gray, DetectError, DetectOptions};
use super::file::{CalibrationFile, CalibrationFileError, CameraSection, LightSection, TurntableSection};
use super::turntable::{calibrate_turntable, TurntableOptions, TurntableView};
use super::zhang::{calibrate_camera, CalibrationOptions, PlanarView};
use super::{BoardSpec, CalibrationError};
use crate::config::{CameraConfig, ConfigError, RigConfig, TurntableConfig};
use crate::geometry::{turntable_rotation, Intrinsics};
use crate::pipeline::light_calibration::{
    calibrate_point_light, LightCalibrationError, LightFitParams, Sphere, SphereObservation,
};
use crate::rigfile;
use crate::sim::chessboard::ChessboardTarget;
use crate::sim::{FrameNoise, Lighting, Material, PointLight, Primitive, RayTable, Scene, SimWorld, Solid};

/// File extensions of board images (PNG 8/16-bit, JPEG, PNM, TIFF, BMP), case-insensitive.
pub const IMAGE_EXTENSIONS: [&str; 10] = ["png", "jpg", "jpeg", "pgm", "ppm", "pnm", "pbm", "tif", "tiff", "bmp"];

/// Read an image of any supported format as 8-bit grey; errors name the file.
fn read_gray(p: &Path) -> Result<GrayImage, WorkflowError> {
    crate::dataset::load_gray(p).map_err(|e| match e {
        crate::dataset::DatasetError::Image { path, source } => {
            WorkflowError::Image { path, what: "cannot read image", source }
        }
        crate::dataset::DatasetError::Read { path, source } => {
            WorkflowError::Io { path, what: "cannot read image", source }
        }
        other => WorkflowError::Io {
            path: p.to_owned(),
            what: "cannot read image",
            source: std::io::Error::other(other.to_string()),
        },
    })
}

/// Board views needed for a camera calibration.
const MIN_CAMERA_VIEWS: usize = 3;

/// What to calibrate.
#[derive(Debug, clap::Subcommand)]
pub enum CalibrateCommand {
    /// Camera intrinsics and radial distortion from chessboard views (Zhang's method).
    Camera {
        /// Where the board images come from.
        #[command(flatten)]
        source: BoardSource,
        /// Do not estimate the distortion (k1 = k2 = p1 = p2 = k3 = 0).
        #[arg(long)]
        no_distortion: bool,
        /// Distortion terms to estimate: 2 (k1 k2) or 5 (OpenCV's k1 k2 p1 p2 k3).
        #[arg(long, default_value_t = 2)]
        distortion_terms: u8,
        /// Hold the principal point at the image centre (for one or two views).
        #[arg(long)]
        fix_principal_point: bool,
    },
    /// Turntable axis and the camera's pose in the rig frame, from a board lying on the table.
    Turntable {
        /// Where the board images come from.
        #[command(flatten)]
        source: BoardSource,
        /// Calibration file with the camera's `[camera]` intrinsics (default: `--out` if it has
        /// them, else the rig file's camera).
        #[arg(long)]
        intrinsics: Option<PathBuf>,
        /// Height of the board's origin above the table top, millimetres (its thickness when lying).
        #[arg(long, default_value_t = 0.0)]
        board_height_mm: f64,
    },
    /// Laser planes (camera frame) from a chessboard under the lasers: laser-on / laser-off frame
    /// pairs of the board at two or more poses, the camera's intrinsics known. Every plane that two
    /// poses' stripes share is fitted (several lasers may be on), ordered left to right.
    Laser {
        /// Camera intrinsics: a calibration file with `[camera]` or an OpenCV FileStorage YAML/XML
        /// (default: `--out`).
        #[arg(long)]
        intrinsics: Option<PathBuf>,
        /// Inner corners COLSxROWS, e.g. 11x6.
        #[arg(long)]
        board: String,
        /// Square size, millimetres.
        #[arg(long)]
        square_mm: f64,
        /// Laser-on frames of the board, one per pose.
        #[arg(long, num_args = 1.., required = true)]
        laser: Vec<PathBuf>,
        /// Laser-off frames, the same poses in the same order.
        #[arg(long, num_args = 1.., required = true)]
        background: Vec<PathBuf>,
        /// Well-lit frames of the same poses to find the board in, `-` for none (default: find it
        /// in the contrast-stretched laser frames).
        #[arg(long, num_args = 1..)]
        pattern: Vec<PathBuf>,
        /// Laser colour r,g,b (weights of the on-minus-off difference).
        #[arg(long, default_value = "255,0,0")]
        laser_colour: String,
        /// Smallest stripe signal, 8-bit levels.
        #[arg(long, default_value_t = 40.0)]
        min_peak: f32,
        /// Plane-fit inlier distance, millimetres.
        #[arg(long, default_value_t = 1.0)]
        inlier_mm: f64,
        /// Index of the first `[[lasers]]` entry to write (the planes found go to this index and the
        /// following ones, left to right).
        #[arg(long, default_value_t = 0)]
        index: usize,
        /// A published plane nx,ny,nz,d (camera frame, d in millimetres) to compare with.
        #[arg(long, allow_hyphen_values = true)]
        reference_plane: Option<String>,
        /// A reference cloud of stripe points (PLY, camera frame, millimetres) to compare with.
        #[arg(long)]
        reference_cloud: Option<PathBuf>,
        /// The calibration file to create or update.
        #[arg(long)]
        out: PathBuf,
    },
    /// Positions of the rig's white lights, from a matte sphere on the turntable (simulated rig).
    Lights {
        /// The rig file (TOML); its `[lights]` positions are the starting guesses.
        #[arg(long)]
        rig: PathBuf,
        /// Sphere centre on the table, object frame, millimetres `x,y,z`.
        #[arg(long, default_value = "30,0,25", allow_hyphen_values = true)]
        sphere_centre_mm: String,
        /// Sphere radius, millimetres.
        #[arg(long, default_value_t = 25.0)]
        sphere_radius_mm: f64,
        /// Table angles to view the sphere at (evenly over a turn).
        #[arg(long, default_value_t = 8)]
        views: usize,
        /// Offset added to every starting guess, millimetres `x,y,z` (to start from a rough
        /// measurement).
        #[arg(long, default_value = "0,0,0", allow_hyphen_values = true)]
        start_offset_mm: String,
        /// The calibration file to create or update.
        #[arg(long)]
        out: PathBuf,
    },
}

/// Board images: a directory, or captures from a simulated rig.
#[derive(Debug, clap::Args)]
pub struct BoardSource {
    /// Directory of board images (PNG), processed in name order.
    #[arg(long, required_unless_present = "rig", conflicts_with = "rig")]
    pub images: Option<PathBuf>,
    /// Capture the views with this (simulated) rig file instead.
    #[arg(long)]
    pub rig: Option<PathBuf>,
    /// Views to capture with `--rig`.
    #[arg(long, default_value_t = 12)]
    pub views: usize,
    /// Also write the captured views here as PNG.
    #[arg(long)]
    pub save_images: Option<PathBuf>,
    /// Inner corners COLSxROWS, e.g. 9x6.
    #[arg(long)]
    pub board: String,
    /// Square size, millimetres.
    #[arg(long)]
    pub square_mm: f64,
    /// The calibration file to create or update.
    #[arg(long)]
    pub out: PathBuf,
}

/// Why a calibration command failed.
#[derive(Debug, thiserror::Error)]
pub enum WorkflowError {
    /// A command-line value that cannot be used.
    #[error("--{arg}: {message}")]
    Argument {
        /// The option.
        arg: &'static str,
        /// What is wrong.
        message: String,
    },
    /// The rig file.
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// The calibration file.
    #[error(transparent)]
    File(#[from] CalibrationFileError),
    /// The calibration maths refused the views.
    #[error("calibration failed: {0}")]
    Calibration(#[from] CalibrationError),
    /// Too few usable images.
    #[error("only {good} usable board image(s) of {total}; at least {need} needed")]
    TooFewImages {
        /// Images with a board found.
        good: usize,
        /// Images looked at.
        total: usize,
        /// Images needed.
        need: usize,
    },
    /// A file or directory could not be read or written.
    #[error("{path}: {what}")]
    Io {
        /// The path.
        path: PathBuf,
        /// What was being done.
        what: &'static str,
        /// Why.
        #[source]
        source: std::io::Error,
    },
    /// An image could not be decoded or encoded.
    #[error("{path}: {what}")]
    Image {
        /// The path.
        path: PathBuf,
        /// What was being done.
        what: &'static str,
        /// Why.
        #[source]
        source: image::ImageError,
    },
    /// A light could not be calibrated.
    #[error("light {index}: {source}")]
    Light {
        /// Light index.
        index: usize,
        /// Why.
        #[source]
        source: LightCalibrationError,
    },
    /// The rig cannot do what was asked.
    #[error("{0}")]
    Unsupported(&'static str),
    /// An output file could not be written.
    #[error(transparent)]
    Export(#[from] crate::pipeline::export::ExportError),
}

/// Run one `calibrate` command, printing progress to stdout.
pub fn run(command: CalibrateCommand) -> Result<(), WorkflowError> {
    match command {
        CalibrateCommand::Camera { source, no_distortion, distortion_terms, fix_principal_point } => {
            if !matches!(distortion_terms, 2 | 5) {
                return Err(WorkflowError::Argument {
                    arg: "distortion-terms",
                    message: format!("2 (k1 k2) or 5 (k1 k2 p1 p2 k3), got {distortion_terms}"),
                });
            }
            calibrate_camera_command(&source, !no_distortion, distortion_terms == 5, fix_principal_point)
        }
        CalibrateCommand::Turntable { source, intrinsics, board_height_mm } => {
            calibrate_turntable_command(&source, intrinsics.as_deref(), board_height_mm)
        }
        CalibrateCommand::Laser {
            intrinsics,
            board,
            square_mm,
            laser,
            background,
            pattern,
            laser_colour,
            min_peak,
            inlier_mm,
            index,
            reference_plane,
            reference_cloud,
            out,
        } => {
            let board = parse_board(&board, square_mm)?;
            if laser.len() != background.len() {
                return Err(WorkflowError::Argument {
                    arg: "background",
                    message: format!("{} laser frames but {} backgrounds", laser.len(), background.len()),
                });
            }
            if !pattern.is_empty() && pattern.len() != laser.len() {
                return Err(WorkflowError::Argument {
                    arg: "pattern",
                    message: format!("{} laser frames but {} patterns", laser.len(), pattern.len()),
                });
            }
            let colour = parse_colour(&laser_colour)?;
            let reference = reference_plane.as_deref().map(parse_plane_mm).transpose()?;
            let intrinsics = load_intrinsics(intrinsics.as_deref().unwrap_or(&out))?.0;
            let stripe = crate::pipeline::laser::StripeParams { min_peak, ..Default::default() };
            calibrate_laser_command(LaserJob {
                intrinsics,
                board,
                patterns: (0..laser.len()).map(|i| pattern.get(i).filter(|p| p.as_os_str() != "-").cloned()).collect(),
                pairs: laser.into_iter().zip(background).collect(),
                colour,
                stripe,
                inlier_m: inlier_mm * 1e-3,
                index,
                reference,
                reference_cloud,
                out,
            })
        }
        CalibrateCommand::Lights { rig, sphere_centre_mm, sphere_radius_mm, views, start_offset_mm, out } => {
            let centre = parse_triple("sphere-centre-mm", &sphere_centre_mm)? * 1e-3;
            let offset = parse_triple("start-offset-mm", &start_offset_mm)? * 1e-3;
            calibrate_lights_command(&rig, centre, sphere_radius_mm * 1e-3, views, offset, &out)
        }
    }
}

fn parse_triple(arg: &'static str, s: &str) -> Result<Vector3<f64>, WorkflowError> {
    let v: Vec<f64> =
        s.split(',').map(|t| t.trim().parse::<f64>()).collect::<Result<_, _>>().map_err(|_| {
            WorkflowError::Argument { arg, message: format!("expected three numbers x,y,z, got `{s}`") }
        })?;
    match v[..] {
        [x, y, z] if v.iter().all(|a| a.is_finite()) => Ok(Vector3::new(x, y, z)),
        _ => Err(WorkflowError::Argument { arg, message: format!("expected three numbers x,y,z, got `{s}`") }),
    }
}

/// Parse a colour `r,g,b` (0..255 each).
pub fn parse_colour(s: &str) -> Result<[u8; 3], WorkflowError> {
    let bad =
        || WorkflowError::Argument { arg: "laser-colour", message: format!("expected r,g,b (0..255), got `{s}`") };
    let v: Vec<u8> = s.split(',').map(|t| t.trim().parse::<u8>()).collect::<Result<_, _>>().map_err(|_| bad())?;
    match v[..] {
        [r, g, b] => Ok([r, g, b]),
        _ => Err(bad()),
    }
}

/// Parse a plane `nx,ny,nz,d` with `d` in millimetres into a plane in metres (normal normalised).
pub fn parse_plane_mm(s: &str) -> Result<crate::pipeline::laser::Plane, WorkflowError> {
    let bad = || WorkflowError::Argument { arg: "plane", message: format!("expected nx,ny,nz,d_mm, got `{s}`") };
    let v: Vec<f64> = s.split(',').map(|t| t.trim().parse::<f64>()).collect::<Result<_, _>>().map_err(|_| bad())?;
    match v[..] {
        [x, y, z, d] if v.iter().all(|a| a.is_finite()) => {
            let n = Vector3::new(x, y, z);
            let len = n.norm();
            if len == 0.0 {
                return Err(bad());
            }
            Ok(crate::pipeline::laser::Plane { normal: (n / len).into(), offset_m: d * 1e-3 / len })
        }
        _ => Err(bad()),
    }
}

/// Camera intrinsics and, when the file says, the image size: from a calibration file's `[camera]`
/// or from an OpenCV FileStorage YAML/XML file (told apart by content).
pub fn load_intrinsics(path: &Path) -> Result<(Intrinsics, Option<(u32, u32)>), WorkflowError> {
    let text = std::fs::read_to_string(path).map_err(|source| WorkflowError::Io {
        path: path.to_owned(),
        what: "cannot read the intrinsics file",
        source,
    })?;
    let head = text.trim_start();
    if head.starts_with("%YAML") || head.starts_with('<') {
        let c = super::opencv_yaml::parse_camera(&text, path).map_err(|e| WorkflowError::Io {
            path: path.to_owned(),
            what: "not a usable OpenCV camera file",
            source: std::io::Error::other(e.to_string()),
        })?;
        return Ok((c.intrinsics, c.size));
    }
    let file = CalibrationFile::parse(&text, path)?;
    let cam = file.camera.ok_or(WorkflowError::Argument {
        arg: "intrinsics",
        message: format!("{} has no [camera] section; run `scanrig calibrate camera` first", path.display()),
    })?;
    Ok((cam.intrinsics(), Some((cam.width_px, cam.height_px))))
}

/// Stripe points each of two board poses must give a laser plane.
const MIN_POINTS_PER_POSE: usize = 30;

/// Inputs of `calibrate laser`.
struct LaserJob {
    intrinsics: Intrinsics,
    board: BoardSpec,
    pairs: Vec<(PathBuf, PathBuf)>,
    patterns: Vec<Option<PathBuf>>,
    colour: [u8; 3],
    stripe: crate::pipeline::laser::StripeParams,
    inlier_m: f64,
    index: usize,
    reference: Option<crate::pipeline::laser::Plane>,
    reference_cloud: Option<PathBuf>,
    out: PathBuf,
}

fn laser_error(e: super::laser_board::LaserBoardError) -> WorkflowError {
    WorkflowError::Io { path: PathBuf::new(), what: "laser calibration", source: std::io::Error::other(chain(&e)) }
}

/// The error and its sources, `: `-joined.
fn chain(e: &dyn std::error::Error) -> String {
    let mut s = e.to_string();
    let mut cur = e.source();
    while let Some(c) = cur {
        s.push_str(": ");
        s.push_str(&c.to_string());
        cur = c.source();
    }
    s
}

fn calibrate_laser_command(job: LaserJob) -> Result<(), WorkflowError> {
    use super::laser_board::{board_laser_view, fit_laser_planes, read_ply_xyz};
    let mut views = Vec::new();
    for ((on, off), pattern) in job.pairs.iter().zip(&job.patterns) {
        let v = board_laser_view(&job.intrinsics, &job.board, on, off, pattern.as_deref(), job.colour, &job.stripe)
            .map_err(laser_error)?;
        println!(
            "{}: board found in {}, posed (RMS {:.3} px) at {:.1} mm, {} stripe peaks, {} on the board",
            on.display(),
            v.board_frame.display(),
            v.pose_rms_px,
            1e3 * v.pose.translation.norm(),
            v.peaks,
            v.points.len()
        );
        if let Some(r) = &job.reference {
            let near: Vec<f64> =
                v.points.iter().map(|x| r.distance(x)).filter(|d| d.abs() <= 5.0 * job.inlier_m).collect();
            let rms = (near.iter().map(|d| d * d).sum::<f64>() / near.len().max(1) as f64).sqrt();
            let mean = near.iter().sum::<f64>() / near.len().max(1) as f64;
            println!(
                "  {} of its board points within {:.1} mm of the published plane: mean {:.3} mm, RMS {:.3} mm",
                near.len(),
                5e3 * job.inlier_m,
                1e3 * mean,
                1e3 * rms
            );
        }
        views.push(v);
    }
    if views.iter().filter(|v| !v.points.is_empty()).count() < 2 {
        return Err(WorkflowError::Argument {
            arg: "laser",
            message: "the stripe points of one board pose lie on a line; a laser plane needs two or more board poses"
                .into(),
        });
    }
    let fits = fit_laser_planes(&views, job.inlier_m, MIN_POINTS_PER_POSE, 4).map_err(laser_error)?;
    let pts: Vec<Vector3<f64>> = views.iter().flat_map(|v| v.points.iter().copied()).collect();
    let cloud = match &job.reference_cloud {
        Some(path) => {
            let c: Vec<Vector3<f64>> = read_ply_xyz(path).map_err(laser_error)?.into_iter().map(|x| x * 1e-3).collect();
            Some((path, c))
        }
        None => None,
    };
    let cloud_stats = |cloud: &[Vector3<f64>], pl: &crate::pipeline::laser::Plane| {
        let d: Vec<f64> = cloud.iter().map(|x| pl.distance(x)).collect();
        let mean = d.iter().sum::<f64>() / d.len().max(1) as f64;
        let rms = (d.iter().map(|v| v * v).sum::<f64>() / d.len().max(1) as f64).sqrt();
        (mean, rms)
    };
    let mut file = CalibrationFile::load_or_default(&job.out)?;
    for (k, fit) in fits.iter().enumerate() {
        let p = fit.plane;
        let index = job.index + k;
        let inl: Vec<&Vector3<f64>> = pts.iter().filter(|x| p.distance(x).abs() <= job.inlier_m).collect();
        let poses = views.iter().filter(|v| v.points.iter().any(|x| p.distance(x).abs() <= job.inlier_m)).count();
        println!(
            "laser {index} plane (camera frame): n = ({:.5}, {:.5}, {:.5}), d = {:.3} mm; RMS {:.3} mm over {} of {} points from {} poses",
            p.normal[0],
            p.normal[1],
            p.normal[2],
            1e3 * p.offset_m,
            1e3 * fit.rms_m,
            fit.inliers,
            fit.points,
            poses
        );
        let centroid = inl.iter().copied().sum::<Vector3<f64>>() / inl.len().max(1) as f64;
        if let Some(r) = &job.reference {
            println!(
                "  laser {index} vs published plane: {:.3} deg between the normals, {:.3} mm apart at its points' centroid",
                p.angle_deg(r),
                1e3 * r.offset_at(&p, &centroid).unwrap_or(f64::NAN)
            );
        }
        if let Some((path, cloud)) = &cloud {
            let (mean, rms) = cloud_stats(cloud, &p);
            println!(
                "  laser {index} vs reference cloud {} ({} points): distance to this plane mean {:.3} mm, RMS {:.3} mm",
                path.display(),
                cloud.len(),
                1e3 * mean,
                1e3 * rms
            );
            if let Some(r) = &job.reference {
                let (m2, r2) = cloud_stats(cloud, r);
                println!("    (to the published plane: mean {:.3} mm, RMS {:.3} mm)", 1e3 * m2, 1e3 * r2);
            }
        }
        file.lasers.retain(|l| l.index != index);
        file.lasers.push(super::file::LaserSection {
            index,
            normal_camera: p.normal,
            offset_camera_m: p.offset_m,
            rms_m: fit.rms_m,
            points: fit.inliers,
        });
    }
    file.lasers.sort_by_key(|l| l.index);
    file.save(&job.out)?;
    println!("wrote {}", job.out.display());
    Ok(())
}

/// Parse `--board COLSxROWS` and `--square-mm`.
pub fn parse_board(board: &str, square_mm: f64) -> Result<BoardSpec, WorkflowError> {
    let bad = || WorkflowError::Argument {
        arg: "board",
        message: format!("expected COLSxROWS inner corners, got `{board}`"),
    };
    let (c, r) = board.split_once(['x', 'X']).ok_or_else(bad)?;
    let (cols, rows) = (c.trim().parse::<usize>().map_err(|_| bad())?, r.trim().parse::<usize>().map_err(|_| bad())?);
    BoardSpec::new(cols, rows, square_mm * 1e-3)
        .map_err(|e| WorkflowError::Argument { arg: "board", message: e.to_string() })
}

/// A named grey board image.
struct BoardImage {
    name: String,
    gray: GrayImage,
    /// Table angle, degrees, when known.
    angle_deg: Option<f64>,
}

/// The table angle of an image named `angle_<degrees>.png`.
fn angle_from_name(name: &str) -> Option<f64> {
    let stem = Path::new(name).file_stem()?.to_str()?;
    stem.strip_prefix("angle_")?.parse::<f64>().ok().filter(|a| a.is_finite())
}

fn load_images(dir: &Path) -> Result<(Vec<BoardImage>, (u32, u32)), WorkflowError> {
    let io = |what, source| WorkflowError::Io { path: dir.to_owned(), what, source };
    let mut paths: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(|e| io("cannot list the image directory", e))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.extension()
                .and_then(|x| x.to_str())
                .is_some_and(|x| IMAGE_EXTENSIONS.iter().any(|e| x.eq_ignore_ascii_case(e)))
        })
        .collect();
    paths.sort();
    let mut out = Vec::with_capacity(paths.len());
    let mut size = None;
    for p in paths {
        let gray = read_gray(&p)?;
        let dims = gray.dimensions();
        if *size.get_or_insert(dims) != dims {
            return Err(WorkflowError::Argument {
                arg: "images",
                message: format!("{} is {}x{}, the others are {:?}", p.display(), dims.0, dims.1, size),
            });
        }
        let name = p.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        out.push(BoardImage { angle_deg: angle_from_name(&name), name, gray });
    }
    Ok((out, size.unwrap_or((0, 0))))
}

/// The simulated board rig of a rig file.
fn sim_board_rig(rig: &RigConfig, board: &BoardSpec) -> Result<SimBoardRig, WorkflowError> {
    let CameraConfig::Sim(cam) = &rig.camera else {
        return Err(WorkflowError::Unsupported(
            "--rig renders the board with a simulated camera; for a real camera capture the images and pass --images",
        ));
    };
    let steps_per_turn = match &rig.turntable {
        TurntableConfig::Sim(t) => t.steps_per_turn,
        TurntableConfig::Serial(_) => 0,
    };
    Ok(SimBoardRig {
        camera: rig.camera.model(),
        noise_sigma: cam.noise_sigma,
        seed: cam.seed,
        target: ChessboardTarget {
            cols: board.cols,
            rows: board.rows,
            square_m: board.square_m,
            border_m: 0.75 * board.square_m,
            dark: 0.08,
            light: 0.9,
        },
        steps_per_turn,
    })
}

fn check_sim_rig(rig: &RigConfig) -> Result<(), WorkflowError> {
    if rig.sim.is_none() {
        return Err(WorkflowError::Unsupported(
            "capturing from a rig needs a simulated rig ([sim]); for a real rig capture the board images and pass --images",
        ));
    }
    Ok(())
}

fn save_png(dir: &Path, name: &str, img: &GrayImage) -> Result<(), WorkflowError> {
    std::fs::create_dir_all(dir).map_err(|source| WorkflowError::Io {
        path: dir.to_owned(),
        what: "cannot create directory",
        source,
    })?;
    let path = dir.join(name);
    img.save(&path).map_err(|source| WorkflowError::Image { path, what: "cannot write image", source })
}

/// Detect the board in every image; print each result; return the views that worked.
fn detect_all(images: &[BoardImage], board: &BoardSpec) -> Vec<(usize, PlanarView)> {
    let mut out = Vec::new();
    for (k, img) in images.iter().enumerate() {
        match detect_chessboard(&img.gray, board, &DetectOptions::default()) {
            Ok(det) => out.push((k, PlanarView { object: board.object_points(), image: det.corners })),
            Err(e) => report_rejection(&img.name, &e),
        }
    }
    out
}

fn report_rejection(name: &str, e: &DetectError) {
    println!("{name}: rejected: {e}");
}

fn calibrate_camera_command(
    source: &BoardSource,
    distortion: bool,
    full_distortion: bool,
    fix_pp: bool,
) -> Result<(), WorkflowError> {
    let board = parse_board(&source.board, source.square_mm)?;
    let (images, (width, height)) = match (&source.images, &source.rig) {
        (Some(dir), _) => load_images(dir)?,
        (None, Some(rig_path)) => {
            let rig = rigfile::load(rig_path)?;
            check_sim_rig(&rig)?;
            let sim = sim_board_rig(&rig, &board)?;
            let imgs: Vec<BoardImage> = sim
                .camera_view_poses(source.views)
                .iter()
                .enumerate()
                .map(|(k, p)| BoardImage {
                    name: format!("view_{k:02}.png"),
                    gray: to_gray(&sim.render_fixed(p, k as u64)),
                    angle_deg: None,
                })
                .collect();
            (imgs, (sim.camera.width, sim.camera.height))
        }
        (None, None) => {
            return Err(WorkflowError::Argument { arg: "images", message: "give --images or --rig".into() })
        }
    };
    if let Some(dir) = &source.save_images {
        for img in &images {
            save_png(dir, &img.name, &img.gray)?;
        }
    }
    let views = detect_all(&images, &board);
    let need = if fix_pp { 1 } else { MIN_CAMERA_VIEWS };
    if views.len() < need {
        return Err(WorkflowError::TooFewImages { good: views.len(), total: images.len(), need });
    }
    let options = CalibrationOptions {
        fixed_principal_point: fix_pp.then_some((width as f64 / 2.0, height as f64 / 2.0)),
        estimate_distortion: distortion,
        full_distortion,
        ..CalibrationOptions::default()
    };
    let planar: Vec<PlanarView> = views.iter().map(|(_, v)| v.clone()).collect();
    let cal = calibrate_camera(&planar, &options)?;
    for ((k, _), rms) in views.iter().zip(&cal.per_view_rms_px) {
        println!("{}: re-projection RMS {rms:.3} px", images[*k].name);
    }
    let i = cal.intrinsics;
    println!(
        "camera: fx {:.2} fy {:.2} cx {:.2} cy {:.2} px, k1 {:.5} k2 {:.5} p1 {:.3e} p2 {:.3e} k3 {:.5}; RMS {:.3} px over {} of {} images",
        i.fx,
        i.fy,
        i.cx,
        i.cy,
        i.k1,
        i.k2,
        i.p1,
        i.p2,
        i.k3,
        cal.rms_px,
        views.len(),
        images.len()
    );
    let mut file = CalibrationFile::load_or_default(&source.out)?;
    file.camera = Some(CameraSection {
        width_px: width,
        height_px: height,
        fx_px: i.fx,
        fy_px: i.fy,
        cx_px: i.cx,
        cy_px: i.cy,
        k1: i.k1,
        k2: i.k2,
        p1: i.p1,
        p2: i.p2,
        k3: i.k3,
        rms_px: cal.rms_px,
        views: views.len(),
    });
    file.save(&source.out)?;
    println!("wrote {}", source.out.display());
    let yaml = source.out.with_extension("yaml");
    let text = super::opencv_yaml::camera_yaml(&i, width, height, cal.rms_px);
    crate::atomic::write_atomic(&yaml, text.as_bytes()).map_err(crate::pipeline::export::ExportError::from)?;
    println!("wrote {} (OpenCV FileStorage)", yaml.display());
    Ok(())
}

fn calibrate_turntable_command(
    source: &BoardSource,
    intrinsics_file: Option<&Path>,
    board_height_mm: f64,
) -> Result<(), WorkflowError> {
    let board = parse_board(&source.board, source.square_mm)?;
    if !board_height_mm.is_finite() {
        return Err(WorkflowError::Argument { arg: "board-height-mm", message: "must be a finite number".into() });
    }
    let rig = source.rig.as_deref().map(rigfile::load).transpose()?;
    let (images, (width, height)) = match (&source.images, &rig) {
        (Some(dir), _) => load_images(dir)?,
        (None, Some(rig)) => {
            check_sim_rig(rig)?;
            let sim = sim_board_rig(rig, &board)?;
            let on_table = sim.lying_board_pose([0.01, -0.01], board_height_mm * 1e-3);
            let n = source.views.max(1);
            let imgs: Vec<BoardImage> = (0..n)
                .map(|k| {
                    let angle = sim.reachable_angle(k as f64 * 360.0 / n as f64);
                    BoardImage {
                        name: format!("angle_{angle}.png"),
                        gray: to_gray(&sim.render_on_table(&on_table, angle, k as u64)),
                        angle_deg: Some(angle),
                    }
                })
                .collect();
            (imgs, (sim.camera.width, sim.camera.height))
        }
        (None, None) => {
            return Err(WorkflowError::Argument { arg: "images", message: "give --images or --rig".into() })
        }
    };
    if let Some(dir) = &source.save_images {
        for img in &images {
            save_png(dir, &img.name, &img.gray)?;
        }
    }
    let intrinsics = turntable_intrinsics(intrinsics_file, &source.out, rig.as_ref(), (width, height))?;
    let mut views = Vec::new();
    let mut used = Vec::new();
    for (idx, v) in detect_all(&images, &board) {
        let Some(angle_deg) = images[idx].angle_deg else {
            println!("{}: rejected: no table angle in the name (expected angle_<degrees>.png)", images[idx].name);
            continue;
        };
        views.push(TurntableView { angle_deg, view: v });
        used.push(idx);
    }
    if views.len() < 3 {
        return Err(WorkflowError::TooFewImages { good: views.len(), total: images.len(), need: 3 });
    }
    let cal =
        calibrate_turntable(&intrinsics, &views, &TurntableOptions { board_origin_height_m: board_height_mm * 1e-3 })?;
    for (idx, rms) in used.iter().zip(&cal.per_view_rms_px) {
        println!("{}: re-projection RMS {rms:.3} px", images[*idx].name);
    }
    let c = cal.camera_pose.centre();
    println!(
        "turntable: axis (camera frame) [{:.4}, {:.4}, {:.4}], camera centre in the rig frame [{:.4}, {:.4}, {:.4}] m, \
         circle RMS {:.3} mm, largest turn error {:.3} deg, {} views",
        cal.axis_camera.x,
        cal.axis_camera.y,
        cal.axis_camera.z,
        c.x,
        c.y,
        c.z,
        cal.circle_rms_m * 1e3,
        cal.max_angle_error_deg,
        views.len()
    );
    let mut file = CalibrationFile::load_or_default(&source.out)?;
    let r = cal.camera_pose.rotation;
    file.turntable = Some(TurntableSection {
        axis_camera: cal.axis_camera.into(),
        origin_camera_m: cal.origin_camera_m.into(),
        camera_rotation: [0, 1, 2].map(|row| [r[(row, 0)], r[(row, 1)], r[(row, 2)]]),
        camera_translation_m: cal.camera_pose.translation.into(),
        circle_rms_m: cal.circle_rms_m,
        max_angle_error_deg: cal.max_angle_error_deg,
        views: views.len(),
    });
    file.save(&source.out)?;
    println!("wrote {}", source.out.display());
    Ok(())
}

/// The intrinsics for the turntable step: `--intrinsics`, else `--out`'s `[camera]`, else the rig's.
fn turntable_intrinsics(
    explicit: Option<&Path>,
    out: &Path,
    rig: Option<&RigConfig>,
    size: (u32, u32),
) -> Result<Intrinsics, WorkflowError> {
    let from_file = |p: &Path| -> Result<Option<Intrinsics>, WorkflowError> {
        let f = CalibrationFile::load(p)?;
        match f.camera {
            Some(c) if (c.width_px, c.height_px) == size => Ok(Some(c.intrinsics())),
            Some(c) => Err(WorkflowError::Argument {
                arg: "intrinsics",
                message: format!(
                    "{}: calibrated for {}x{} images, these are {}x{}",
                    p.display(),
                    c.width_px,
                    c.height_px,
                    size.0,
                    size.1
                ),
            }),
            None => Ok(None),
        }
    };
    if let Some(p) = explicit {
        return from_file(p)?.ok_or_else(|| WorkflowError::Argument {
            arg: "intrinsics",
            message: format!("{} has no [camera] section; run `scanrig calibrate camera` first", p.display()),
        });
    }
    if out.exists() {
        if let Some(i) = from_file(out)? {
            println!("intrinsics from {}", out.display());
            return Ok(i);
        }
    }
    match rig {
        Some(r) => {
            println!("intrinsics from the rig file's camera");
            Ok(r.camera.model().intrinsics)
        }
        None => Err(WorkflowError::Argument {
            arg: "intrinsics",
            message: "no intrinsics: pass --intrinsics FILE or run `scanrig calibrate camera --out` first".into(),
        }),
    }
}

fn calibrate_lights_command(
    rig_path: &Path,
    centre_obj: Vector3<f64>,
    radius: f64,
    views: usize,
    start_offset: Vector3<f64>,
    out: &Path,
) -> Result<(), WorkflowError> {
    let rig = rigfile::load(rig_path)?;
    check_sim_rig(&rig)?;
    if !(radius.is_finite() && radius > 0.0) {
        return Err(WorkflowError::Argument { arg: "sphere-radius-mm", message: "must be a positive length".into() });
    }
    let lights: Vec<(Vector3<f64>, f64)> = rig
        .lights
        .as_ref()
        .map(|l| l.lights.iter().map(|l| (Vector3::from(l.position_m), l.intensity)).collect())
        .unwrap_or_default();
    if lights.is_empty() {
        return Err(WorkflowError::Unsupported("the rig file has no [[lights.light]] to calibrate"));
    }
    let sim = rig.sim.as_ref().ok_or(WorkflowError::Unsupported("no [sim] section"))?;
    let solid =
        Solid::new(Primitive::Sphere { centre: centre_obj, radius }, vec![], Material::Uniform([0.8, 0.8, 0.8]))
            .map_err(|_| WorkflowError::Unsupported("invalid calibration sphere"))?;
    let lighting = Lighting {
        lights: lights.iter().map(|&(p, i)| PointLight { position_m: p, intensity: i }).collect(),
        lasers: vec![],
        projector: None,
        ambient: sim.ambient,
        background: sim.background,
    };
    let scene =
        Scene::new("calibration-sphere", vec![solid]).map_err(|_| WorkflowError::Unsupported("invalid scene"))?;
    let world = SimWorld::new(scene, lighting);
    let camera = rig.camera.model();
    let CameraConfig::Sim(cam_cfg) = &rig.camera else {
        return Err(WorkflowError::Unsupported(
            "light calibration renders with a simulated camera; the rig's camera is real",
        ));
    };
    let rays = RayTable::new(camera);
    let angles: Vec<f64> = (0..views.max(1)).map(|k| k as f64 * 360.0 / views.max(1) as f64).collect();
    let mut seq = 0u64;
    let mut render = |angle: f64, on: Option<usize>| -> Result<image::RgbImage, WorkflowError> {
        world.set_turntable_angle(angle);
        for l in 0..lights.len() {
            world
                .set_light(l, if Some(l) == on { 1.0 } else { 0.0 })
                .map_err(|_| WorkflowError::Unsupported("light index out of range"))?;
        }
        seq += 1;
        Ok(world.renderer().render_rgb(
            &rays,
            &world.snapshot(),
            FrameNoise { sigma: cam_cfg.noise_sigma, seed: cam_cfg.seed, sequence: seq },
        ))
    };
    let ambients: Vec<_> = angles.iter().map(|&a| render(a, None)).collect::<Result<_, _>>()?;
    let mut file = CalibrationFile::load_or_default(out)?;
    file.lights.clear();
    for (index, &(nominal, _)) in lights.iter().enumerate() {
        let lit: Vec<_> = angles.iter().map(|&a| render(a, Some(index))).collect::<Result<_, _>>()?;
        let obs: Vec<SphereObservation<'_>> = angles
            .iter()
            .zip(ambients.iter().zip(&lit))
            .map(|(&a, (ambient, lit))| SphereObservation {
                camera,
                sphere: Sphere { centre_m: turntable_rotation(a) * centre_obj, radius_m: radius },
                ambient,
                lit,
            })
            .collect();
        let start = nominal + start_offset;
        let est = calibrate_point_light(&obs, &LightFitParams::new(start))
            .map_err(|source| WorkflowError::Light { index, source })?;
        println!(
            "light {index}: position [{:.4}, {:.4}, {:.4}] m (rig file [{:.4}, {:.4}, {:.4}], {:.2} mm apart), \
             RMS {:.2} levels over {} pixels",
            est.position_m.x,
            est.position_m.y,
            est.position_m.z,
            nominal.x,
            nominal.y,
            nominal.z,
            (est.position_m - nominal).norm() * 1e3,
            est.rms_levels,
            est.pixels
        );
        file.lights.push(LightSection {
            index,
            position_m: est.position_m.into(),
            rms_levels: est.rms_levels,
            pixels: est.pixels,
        });
    }
    file.save(out)?;
    println!("wrote {}", out.display());
    Ok(())
}

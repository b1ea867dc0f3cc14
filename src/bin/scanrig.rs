//! `scanrig`: the command-line tool. Thin: parses arguments and calls the library.

use std::io::IsTerminal;
use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;
use clap::{Parser, Subcommand};
use scanrig::acquisition::{CancelToken, Stage};
use scanrig::scan::{self, reconstruct, ScanEvent};
use scanrig::service::client::{self, Client};

#[derive(Parser, Debug)]
#[command(name = "scanrig", version, about = "Drive a 3D scanner rig and reconstruct what it sees")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum CalibrateCommand {
    /// Camera, turntable and lights.
    #[command(flatten)]
    Rig(scanrig::calibration::cli::CalibrateCommand),
    /// Projector-camera calibration (Moreno & Taubin local homographies) from Gray-code captures of a
    /// chessboard, one directory per board pose; writes a TOML calibration file.
    Projector(ProjectorArgs),
}

/// `scanrig triangulate` options.
#[derive(clap::Args, Debug)]
struct TriangulateArgs {
    /// Directory of the captured Gray-code sequence (sorted by name: pattern/inverse pairs for the
    /// columns then the rows, MSB first, then all-white and all-black).
    #[arg(long)]
    images: PathBuf,
    /// Projector-camera calibration: a TOML file of `scanrig calibrate projector` or an OpenCV
    /// FileStorage XML (calibration_result.xml).
    #[arg(long)]
    procam: PathBuf,
    /// Gray-code pattern resolution WIDTHxHEIGHT, pixels (for an XML calibration).
    #[arg(long, default_value = "1024x768")]
    projector: String,
    /// Projector pixels per Gray-code pixel (for an XML calibration).
    #[arg(long, default_value_t = 1)]
    graycode_step: u32,
    /// A pixel is lit when |white - black| exceeds this (grey levels).
    #[arg(long, default_value_t = 40)]
    black_threshold: u8,
    /// Every bit needs |pattern - inverse| of at least this (grey levels).
    #[arg(long, default_value_t = 5)]
    white_threshold: u8,
    /// The chessboard in view, inner corners COLSxROWS, to measure the cloud (needs --square).
    #[arg(long, requires = "square")]
    board: Option<String>,
    /// Square size of --board, in the calibration's length unit.
    #[arg(long)]
    square: Option<f64>,
    /// Output point cloud (binary PLY).
    #[arg(long)]
    out: PathBuf,
}

/// `scanrig laser-view` options.
#[derive(clap::Args, Debug)]
struct LaserViewArgs {
    /// Camera intrinsics: a calibration file with `[camera]` or an OpenCV FileStorage YAML/XML.
    #[arg(long)]
    intrinsics: PathBuf,
    /// The laser plane: a calibration file with `[[lasers]]` (see --laser-index) ...
    #[arg(long, conflicts_with = "plane")]
    calibration: Option<PathBuf>,
    /// Which `[[lasers]]` entry of --calibration.
    #[arg(long, default_value_t = 0)]
    laser_index: usize,
    /// ... or the plane itself, nx,ny,nz,d (camera frame, d in millimetres).
    #[arg(long, allow_hyphen_values = true)]
    plane: Option<String>,
    /// The laser-on frame.
    #[arg(long)]
    laser: PathBuf,
    /// The laser-off frame.
    #[arg(long)]
    background: PathBuf,
    /// A frame under white light to colour the points (default: the laser-off frame).
    #[arg(long)]
    texture: Option<PathBuf>,
    /// Laser colour r,g,b.
    #[arg(long, default_value = "255,0,0")]
    laser_colour: String,
    /// Smallest stripe signal, 8-bit levels.
    #[arg(long, default_value_t = 40.0)]
    min_peak: f32,
    /// Widest accepted run of stripe pixels in a row, pixels.
    #[arg(long, default_value_t = 8)]
    max_width_px: u32,
    /// A plane nx,ny,nz,d (camera frame, d in millimetres; e.g. the turntable top) to check the
    /// points within --check-band-mm of it against.
    #[arg(long, allow_hyphen_values = true)]
    check_plane: Option<String>,
    /// Half-width of the band around --check-plane, millimetres.
    #[arg(long, default_value_t = 10.0)]
    check_band_mm: f64,
    /// Output point cloud (binary PLY, metres, coloured).
    #[arg(long)]
    out: PathBuf,
}

/// `scanrig calibrate projector` options.
#[derive(clap::Args, Debug)]
struct ProjectorArgs {
    /// Capture directories (the Gray-code sequence's images, sorted by name), one per pose.
    #[arg(long, num_args = 1.., required = true)]
    captures: Vec<PathBuf>,
    /// Board inner corners COLSxROWS.
    #[arg(long)]
    board: String,
    /// Square size, millimetres (the translation is written in metres, as a rig's `procam` needs).
    #[arg(long)]
    square_mm: f64,
    /// Length of one unit of the --reference file's translation, millimetres.
    #[arg(long, default_value_t = 1.0)]
    reference_unit_mm: f64,
    /// Gray-code pattern resolution WIDTHxHEIGHT, pixels.
    #[arg(long, default_value = "1024x768")]
    projector: String,
    /// Projector pixels per Gray-code pixel.
    #[arg(long, default_value_t = 1)]
    graycode_step: u32,
    /// A TOML file with a [camera] table (fx, fy, cx, cy, k1, k2, p1, p2, k3) holding the camera fixed.
    #[arg(long)]
    camera_calib: Option<PathBuf>,
    /// A published OpenCV calibration_result.xml to compare with.
    #[arg(long)]
    reference: Option<PathBuf>,
    /// Hold both devices' intrinsics at the reference's (then one pose suffices).
    #[arg(long, requires = "reference")]
    intrinsics_from_reference: bool,
    /// A pixel is lit when |white - black| exceeds this (grey levels).
    #[arg(long, default_value_t = 40)]
    black_threshold: u8,
    /// Every bit needs |pattern - inverse| of at least this (grey levels).
    #[arg(long, default_value_t = 5)]
    white_threshold: u8,
    /// Output calibration file (TOML).
    #[arg(long)]
    out: PathBuf,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Scan with the rig described by a rig file and write the model into a directory.
    Scan {
        /// The rig file (TOML), e.g. config/rigs/simulated.toml.
        #[arg(long)]
        rig: PathBuf,
        /// Output directory (created if missing).
        #[arg(long)]
        out: PathBuf,
        /// Replace an existing result (a `report.json`) in `--out`.
        #[arg(long)]
        force: bool,
    },
    /// Reconstruct a stored scan again (`--scan DIR`: any method its views serve, other settings;
    /// no hardware), or a calibrated image set on disk (`--dataset DIR`: Middlebury `*_par.txt` or a
    /// file of 3x4 projection matrices), and write the same outputs as `scan`.
    Reconstruct {
        /// A stored scan directory (with `rig.toml` and `frames/`), e.g. a `scan --out` directory,
        /// or a replicated scan in object storage, `s3://BUCKET/PREFIX/RIG/SCAN` (downloaded and
        /// checked against its manifest; the result is also uploaded to `SCAN/reprocess-TIME/`).
        #[arg(long, conflicts_with_all = ["dataset", "bbox", "views", "masks", "silhouette"])]
        scan: Option<PathBuf>,
        /// For an `s3://` scan: a file with a `[replication]` section giving the endpoint, region,
        /// allow_http and credentials (default: the AWS_* environment variables).
        #[arg(long, requires = "scan")]
        replication: Option<PathBuf>,
        /// The data set directory (image names in the calibration are relative to it).
        #[arg(long, required_unless_present = "scan")]
        dataset: Option<PathBuf>,
        /// Reconstruction method (default: the stored scan's, or space-carving for a data set).
        #[arg(long, value_enum)]
        method: Option<scanrig::config::Method>,
        /// Voxels along the longest side of the box (default: the stored scan's; required for a
        /// data set).
        #[arg(long)]
        resolution: Option<u32>,
        /// Working volume xmin,ymin,zmin,xmax,ymax,zmax in metres (default: estimated from the views).
        #[arg(long, allow_hyphen_values = true)]
        bbox: Option<String>,
        /// Calibration file. With --dataset: Middlebury `*_par.txt`, projection matrices, a COLMAP
        /// model or an OpenCV FileStorage file (YAML or XML: one camera, `extrinsic_parameters` with a
        /// row per view and the views' names in `images`) (default: the one `*_par.txt` in the data
        /// set directory). With --scan: a calibration
        /// file of `scanrig calibrate` or an OpenCV FileStorage camera file (YAML or XML:
        /// camera_matrix, distortion_coefficients, optional pose R, T in metres) applied over the
        /// stored rig's camera, as a rig file's `[rig] calibration` is.
        #[arg(long)]
        calibration: Option<PathBuf>,
        /// Views to use: a file with one image name per line, or a comma-separated list.
        #[arg(long)]
        views: Option<String>,
        /// Directory of silhouette masks (same file stems, non-zero = object).
        #[arg(long, conflicts_with = "silhouette")]
        masks: Option<PathBuf>,
        /// Silhouette extraction from the images: threshold=T,dilate=D,erode=E[,background=r:g:b]
        /// (object where max over R,G,B of |pixel - background| / 255 > T, then a closing with discs
        /// of D and E pixels). Default: the Middlebury recipe threshold=0.19,dilate=10,erode=7.
        #[arg(long)]
        silhouette: Option<String>,
        /// Occupancy smoothing radius for the mesh, voxels (default: the stored scan's, or 0).
        #[arg(long)]
        smooth: Option<u32>,
        /// Photo-consistency test of voxel-coloring / space-carving-photo:
        /// threshold=T,min_cos=C,min_views=N[,ncc=X][,iterations=I] (T in 0..255 levels, or
        /// `measured`).
        #[arg(long)]
        photo: Option<String>,
        /// Output directory.
        #[arg(long)]
        out: PathBuf,
    },
    /// Decode a Gray-code structured-light capture (a directory of the 2 * (column bits + row bits) + 2
    /// images, sorted by name) into projector columns/rows per camera pixel: writes `columns.png` and
    /// `rows.png` (16-bit, 65535 = not decoded) and `decode.json` (valid fraction, timing).
    Decode {
        /// Directory of the captured images.
        #[arg(long)]
        images: PathBuf,
        /// Projector resolution WIDTHxHEIGHT, pixels.
        #[arg(long, default_value = "1024x768")]
        projector: String,
        /// A pixel is lit when |white - black| exceeds this (grey levels).
        #[arg(long, default_value_t = 40)]
        black_threshold: u8,
        /// Every bit needs |pattern - inverse| of at least this (grey levels).
        #[arg(long, default_value_t = 5)]
        white_threshold: u8,
        /// Decode this many times and report the median time (the images are loaded once).
        #[arg(long, default_value_t = 1)]
        repeat: u32,
        /// Output directory.
        #[arg(long)]
        out: PathBuf,
    },
    /// List cameras, serial ports, framebuffers and depth cameras with their stable identities and
    /// capabilities, and the rig-file lines that select each.
    Devices {
        /// Look for devices below this directory instead of `/` (a fake `sys/` + `dev/` tree; also
        /// the SCANRIG_SYSFS_ROOT environment variable).
        #[arg(long, hide = true)]
        root: Option<PathBuf>,
    },
    /// Calibrate the camera, the turntable axis, the lights or a projector into a calibration file
    /// (a rig file points to the camera/turntable/lights one with `[rig] calibration = "calib.toml"`).
    Calibrate {
        /// What to calibrate.
        #[command(subcommand)]
        what: CalibrateCommand,
    },
    /// Triangulate a Gray-code structured-light capture with its projector-camera calibration into a
    /// coloured point cloud (camera frame, the calibration's length unit); with --board, also measure
    /// the chessboard in view (plane-fit RMS, neighbouring-corner distances against the square).
    Triangulate(TriangulateArgs),
    /// Triangulate one laser view (laser-on and laser-off frames) on a calibrated laser plane into a
    /// coloured point cloud (camera frame, metres); optionally check the points near a known plane
    /// (e.g. the turntable top) against it.
    LaserView(LaserViewArgs),
    /// Check a rig file and report every problem in it.
    Validate {
        /// The rig file (TOML).
        #[arg(long)]
        rig: PathBuf,
    },
    /// Daemon: rig, device and scan status.
    Status {
        #[command(flatten)]
        daemon: DaemonArgs,
        /// The daemon's JSON as it is.
        #[arg(long)]
        json: bool,
    },
    /// Daemon: the stored scans (id, date, method, status, figures).
    Scans {
        #[command(flatten)]
        daemon: DaemonArgs,
        /// The daemon's JSON as it is.
        #[arg(long)]
        json: bool,
    },
    /// Daemon: delete a scan (its frames and results) for good.
    Delete {
        #[command(flatten)]
        daemon: DaemonArgs,
        /// Scan id.
        id: String,
    },
    /// Daemon: close a device (with the rest of the rig) and open it again.
    Reconnect {
        #[command(flatten)]
        daemon: DaemonArgs,
        /// Device name as `scanrig status` lists it (turntable, camera, lights, projector...).
        name: String,
    },
    /// Daemon: manual control of the rig between scans (refused while a scan runs).
    Control {
        #[command(flatten)]
        daemon: DaemonArgs,
        #[command(subcommand)]
        what: ControlArgs,
    },
    /// Daemon: start a scan (defaults from the daemon's rig file).
    Start {
        #[command(flatten)]
        daemon: DaemonArgs,
        /// Reconstruction method (any the rig allows: see `scanrig methods`).
        #[arg(long, value_enum)]
        method: Option<scanrig::config::Method>,
        /// Turntable positions.
        #[arg(long)]
        positions: Option<u32>,
        /// Voxels along the working volume's longest side.
        #[arg(long)]
        resolution: Option<u32>,
        /// Lights on for each frame, by index, comma-separated.
        #[arg(long, value_delimiter = ',')]
        lights: Option<Vec<usize>>,
        /// Follow its progress until it ends.
        #[arg(long)]
        watch: bool,
    },
    /// Daemon: follow the running scan's progress until it ends.
    Watch(DaemonArgs),
    /// Daemon: the methods the rig can run, and what the others miss.
    Methods(DaemonArgs),
    /// Daemon: reconstruct a stored scan again with other settings into a new scan entry.
    Reprocess {
        #[command(flatten)]
        daemon: DaemonArgs,
        /// Scan id.
        id: String,
        /// Reconstruction method (one the stored views serve).
        #[arg(long, value_enum)]
        method: Option<scanrig::config::Method>,
        /// Voxels along the working volume's longest side.
        #[arg(long)]
        resolution: Option<u32>,
        /// Occupancy smoothing radius of the mesh, voxels.
        #[arg(long)]
        smooth: Option<u32>,
        /// Follow its progress until it ends.
        #[arg(long)]
        watch: bool,
    },
    /// Daemon: pause a running scan at the next step.
    Pause {
        #[command(flatten)]
        daemon: DaemonArgs,
        /// Scan id.
        id: String,
    },
    /// Daemon: resume a paused or interrupted scan from its last complete frame.
    Resume {
        #[command(flatten)]
        daemon: DaemonArgs,
        /// Scan id.
        id: String,
    },
    /// Daemon: cancel a scan.
    Cancel {
        #[command(flatten)]
        daemon: DaemonArgs,
        /// Scan id.
        id: String,
    },
    /// Daemon: download a scan's results (models and report) into a directory.
    Fetch {
        #[command(flatten)]
        daemon: DaemonArgs,
        /// Scan id.
        id: String,
        /// Output directory.
        #[arg(long)]
        out: PathBuf,
        /// Also the frames: the whole scan directory (frames/, rig.toml...), unpacked into --out.
        #[arg(long)]
        frames: bool,
        /// Also keep the whole scan directory as one zip, --out/ID.zip.
        #[arg(long)]
        archive: bool,
    },
}

/// `scanrig control` commands.
#[derive(Subcommand, Debug)]
enum ControlArgs {
    /// Show the control state (table angle, lights, lasers, projector).
    Show,
    /// Turn the table by DEGREES from where it is (negative: the other way).
    Turn {
        /// Degrees.
        #[arg(allow_hyphen_values = true)]
        degrees: f64,
    },
    /// Home the table (its end stop, or back to 0 degrees without one).
    Home,
    /// Switch white light INDEX on or off.
    Light {
        /// Light index, 0-based.
        index: usize,
        /// `on` or `off`.
        state: OnOff,
    },
    /// Switch line laser INDEX on or off.
    Laser {
        /// Laser index, 0-based.
        index: usize,
        /// `on` or `off`.
        state: OnOff,
    },
    /// Show a test pattern (checker, gray, white, black), a colour or nothing on the projector.
    Projector {
        /// A test pattern.
        #[arg(long, value_enum, conflicts_with_all = ["colour", "blank"])]
        pattern: Option<PatternArg>,
        /// A solid colour R,G,B (0-255 each).
        #[arg(long, conflicts_with = "blank")]
        colour: Option<String>,
        /// Blank the projector.
        #[arg(long)]
        blank: bool,
    },
}

#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
enum OnOff {
    On,
    Off,
}

#[derive(clap::ValueEnum, Clone, Copy, Debug)]
enum PatternArg {
    Checker,
    Gray,
    White,
    Black,
}

/// Where the daemon is.
#[derive(clap::Args, Debug)]
struct DaemonArgs {
    /// Daemon address, host:port.
    #[arg(long, default_value = "127.0.0.1:8470", global = true)]
    daemon: String,
    /// File holding the bearer token, readable by its owner only, when the daemon needs one (else
    /// the SCANRIG_TOKEN environment variable). There is no `--token`: `ps` would show it.
    #[arg(long, global = true)]
    token_file: Option<PathBuf>,
}

impl DaemonArgs {
    fn client(&self) -> anyhow::Result<Client> {
        let token = match &self.token_file {
            Some(p) => Some(scanrig::service::token::from_file(p)?),
            None => scanrig::service::token::from_env("SCANRIG_TOKEN")?,
        };
        Ok(Client::new(&self.daemon, token)?)
    }
}

#[cfg(feature = "s3")]
type Remote = Option<scanrig::archive::remote::RemoteScan>;
#[cfg(not(feature = "s3"))]
type Remote = Option<std::convert::Infallible>;

#[cfg(feature = "s3")]
fn fetch_remote(url: &str, settings: Option<&std::path::Path>) -> anyhow::Result<scanrig::archive::remote::RemoteScan> {
    let r = scanrig::archive::remote::fetch(url, settings).with_context(|| format!("cannot download {url}"))?;
    eprintln!("downloaded {} files of {url} (checked against its manifest)", r.manifest.files.len());
    Ok(r)
}

#[cfg(not(feature = "s3"))]
fn fetch_remote(url: &str, _: Option<&std::path::Path>) -> anyhow::Result<std::convert::Infallible> {
    anyhow::bail!("{url}: reading scans from object storage needs scanrig built with the `s3` feature")
}

#[cfg(feature = "s3")]
fn remote_dir(remote: &Remote) -> Option<PathBuf> {
    remote.as_ref().map(|r| r.dir.clone())
}

#[cfg(not(feature = "s3"))]
fn remote_dir(_: &Remote) -> Option<PathBuf> {
    None
}

#[cfg(feature = "s3")]
fn store_remote(remote: &Remote, out: &std::path::Path) -> anyhow::Result<()> {
    if let Some(r) = remote {
        let url = r.store_result(out).context("cannot upload the result beside the scan")?;
        println!("results in {url}");
    }
    Ok(())
}

#[cfg(not(feature = "s3"))]
fn store_remote(_: &Remote, _: &std::path::Path) -> anyhow::Result<()> {
    Ok(())
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let filter = tracing_subscriber::EnvFilter::try_from_env("SCANRIG_LOG")
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn"));
    tracing_subscriber::fmt().with_env_filter(filter).with_writer(std::io::stderr).init();
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

fn decode_capture(
    images: &std::path::Path,
    projector: &str,
    bt: u8,
    wt: u8,
    repeat: u32,
    out: &std::path::Path,
) -> anyhow::Result<()> {
    use scanrig::pipeline::structured_light as sl;
    let (w, h) = projector
        .split_once('x')
        .and_then(|(w, h)| Some((w.parse::<u32>().ok()?, h.parse::<u32>().ok()?)))
        .ok_or_else(|| anyhow::anyhow!("--projector {projector}: expected WIDTHxHEIGHT"))?;
    let patterns = sl::GrayCodePatterns::new(w, h)?;
    let t0 = std::time::Instant::now();
    let capture = sl::load_capture_dir(images, patterns.count())?;
    let load_s = t0.elapsed().as_secs_f64();
    let params = sl::DecodeParams { black_threshold: bt, white_threshold: wt };
    let slices = capture.slices();
    let mut map = sl::ProjectorMap::new();
    let mut times = Vec::new();
    let mut valid = 0;
    for _ in 0..repeat.max(1) {
        let t = std::time::Instant::now();
        valid = sl::decode(&patterns, &slices, capture.width, capture.height, &params, &mut map)?;
        times.push(t.elapsed().as_secs_f64());
    }
    times.sort_by(f64::total_cmp);
    let decode_s = times[times.len() / 2];
    let pixels = capture.width * capture.height;
    let (pairs, within) = map.horizontal_consistency(2);
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    sl::save_map_png(&map, out)?;
    let report = serde_json::json!({
        "camera": [capture.width, capture.height],
        "projector": [w, h],
        "images": capture.paths.len(),
        "black_threshold": bt,
        "white_threshold": wt,
        "valid_pixels": valid,
        "valid_fraction": valid as f64 / pixels as f64,
        "adjacent_valid_pairs": pairs,
        "adjacent_within_2_columns_fraction": if pairs > 0 { within as f64 / pairs as f64 } else { 0.0 },
        "load_s": load_s,
        "decode_s_median": decode_s,
        "repeats": times.len(),
        "megapixels_per_s": pixels as f64 / decode_s / 1e6,
    });
    let json = out.join("decode.json");
    std::fs::write(&json, serde_json::to_string_pretty(&report)? + "\n")
        .with_context(|| format!("cannot write {}", json.display()))?;
    println!(
        "{}x{} camera, {:.2}% valid, {:.4}% of adjacent valid pixels within 2 columns, decode {:.2} ms ({:.0} Mpx/s)",
        capture.width,
        capture.height,
        100.0 * valid as f64 / pixels as f64,
        if pairs > 0 { 100.0 * within as f64 / pairs as f64 } else { 0.0 },
        decode_s * 1e3,
        pixels as f64 / decode_s / 1e6
    );
    Ok(())
}

fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Devices { root } => {
            let root =
                root.map_or_else(scanrig::devices::sysfs::SysRoot::from_env, scanrig::devices::sysfs::SysRoot::new);
            print!("{}", scanrig::devices::discovery::render(&scanrig::devices::discovery::discover(&root)));
            Ok(())
        }
        Command::Validate { rig } => {
            scanrig::rigfile::load(&rig)?;
            println!("{}: ok", rig.display());
            Ok(())
        }
        Command::Reconstruct {
            scan: Some(scan_arg),
            method,
            resolution,
            smooth,
            photo,
            out,
            replication,
            calibration,
            ..
        } => {
            let remote = match scan_arg.to_str().filter(|s| s.starts_with("s3://")) {
                Some(url) => Some(fetch_remote(url, replication.as_deref())?),
                None => None,
            };
            let scan_dir = remote_dir(&remote).unwrap_or_else(|| scan_arg.clone());
            let mut config = scanrig::rigfile::load(&scan_dir.join(scan::driver::RIG_FILE))
                .with_context(|| format!("{} is not a stored scan", scan_dir.display()))?;
            if let Some(c) = &calibration {
                scanrig::calibration::file::apply_to_rig(c, &mut config)
                    .with_context(|| format!("--calibration {}", c.display()))?;
            }
            if let Some(m) = method {
                config.reconstruction.method = m;
            }
            if let Some(r) = resolution {
                config.reconstruction.resolution = r;
            }
            if let Some(r) = smooth {
                config.reconstruction.mesh.smooth_radius = r;
            }
            if let Some(p) = &photo {
                config.reconstruction.photo =
                    reconstruct::parse_photo(p).map_err(|e| anyhow::anyhow!("--photo {p}: {e}"))?;
            }
            let problems = config.validate();
            if !problems.is_empty() {
                let list: Vec<String> = problems.iter().map(|p| format!("{}: {}", p.key, p.message)).collect();
                anyhow::bail!("the options do not fit the stored scan:\n  {}", list.join("\n  "));
            }
            let mut reporter = Reporter::new(config.scan.positions as u64);
            let report =
                scan::reprocess(&config, &scan_dir, &out, &CancelToken::new(), &mut |e| reporter.event(&e), None)
                    .with_context(|| format!("reprocessing {} failed", scan_arg.display()))?;
            reporter.finish();
            print_summary(&report);
            println!("results in {}", out.display());
            store_remote(&remote, &out)?;
            Ok(())
        }
        Command::Reconstruct {
            dataset,
            method,
            resolution,
            bbox,
            calibration,
            views,
            masks,
            silhouette,
            smooth,
            photo,
            out,
            ..
        } => {
            let dataset = dataset.context("--dataset or --scan is required")?;
            let method = method.unwrap_or(scanrig::config::Method::SpaceCarving);
            if !(method == scanrig::config::Method::SpaceCarving || method.is_photo()) {
                anyhow::bail!(
                    "--method {method}: a data set of calibrated images is reconstructed with space-carving, \
                     voxel-coloring or space-carving-photo; other methods reconstruct a stored scan (--scan DIR)"
                );
            }
            let resolution = resolution.context("--resolution is required with --dataset")?;
            let smooth = smooth.unwrap_or(0);
            if !(2..=4096).contains(&resolution) {
                anyhow::bail!("--resolution {resolution}: must be between 2 and 4096 voxels");
            }
            if smooth > scanrig::pipeline::MeshParams::MAX_SMOOTH_RADIUS {
                anyhow::bail!("--smooth {smooth}: at most {} voxels", scanrig::pipeline::MeshParams::MAX_SMOOTH_RADIUS);
            }
            let bbox = bbox
                .map(|b| reconstruct::parse_bbox(&b).map_err(|e| anyhow::anyhow!("--bbox {b}: {e}")))
                .transpose()?;
            let params = match &silhouette {
                Some(s) => reconstruct::parse_silhouette(s).map_err(|e| anyhow::anyhow!("--silhouette {s}: {e}"))?,
                None => scanrig::pipeline::SilhouetteParams::MIDDLEBURY,
            };
            let mut dataset_opts = reconstruct::dataset_options(&dataset, calibration, views.as_deref(), masks, params);
            // The photo-consistency methods need the images, not only the silhouettes.
            dataset_opts.load_images |= method.is_photo();
            let opts = reconstruct::ReconstructOptions {
                dataset: dataset_opts,
                method,
                photo: match &photo {
                    Some(p) => reconstruct::parse_photo(p).map_err(|e| anyhow::anyhow!("--photo {p}: {e}"))?,
                    None => scanrig::config::PhotoConfig::default(),
                },
                resolution,
                bbox,
                smooth_radius: smooth,
                mesh_max_error_voxels: scanrig::config::DEFAULT_MESH_MAX_ERROR_VOXELS,
                out: out.clone(),
            };
            let mut reporter = Reporter::new(0);
            let report = reconstruct::run_reconstruct(&opts, &mut |e| reporter.event(&e))
                .with_context(|| format!("reconstruction of {} failed", dataset.display()))?;
            reporter.finish();
            println!(
                "{} views, {} voxels occupied ({}x{}x{}), carving {:.4} s, mean re-projection IoU {:.4}, mesh {} triangles",
                report.views,
                report.occupied_voxels,
                report.resolution[0],
                report.resolution[1],
                report.resolution[2],
                report.timings_s.carve,
                report.reprojection_iou_mean,
                report.mesh_triangles
            );
            println!("results in {}", out.display());
            Ok(())
        }
        Command::Decode { images, projector, black_threshold, white_threshold, repeat, out } => {
            decode_capture(&images, &projector, black_threshold, white_threshold, repeat, &out)
        }
        Command::Calibrate { what: CalibrateCommand::Rig(what) } => Ok(scanrig::calibration::cli::run(what)?),
        Command::Calibrate { what: CalibrateCommand::Projector(args) } => calibrate_projector(args),
        Command::Triangulate(args) => triangulate_capture(args),
        Command::LaserView(args) => laser_view(args),
        Command::Status { daemon, json } => {
            let v = daemon.client()?.get_json("/api/v1/status")?;
            if json {
                println!("{}", serde_json::to_string_pretty(&v)?);
            } else {
                print!("{}", console_text::status(&v));
            }
            Ok(())
        }
        Command::Scans { daemon, json } => {
            let v = daemon.client()?.get_json("/api/v1/scans")?;
            if json {
                println!("{}", serde_json::to_string_pretty(&v)?);
            } else {
                print!("{}", console_text::scans_table(&v));
            }
            Ok(())
        }
        Command::Delete { daemon, id } => {
            daemon.client()?.delete(&format!("/api/v1/scans/{id}"))?;
            println!("deleted {id}");
            Ok(())
        }
        Command::Reconnect { daemon, name } => {
            let v = daemon.client()?.post_json(&format!("/api/v1/devices/{name}/reconnect"), &serde_json::json!({}))?;
            println!("reconnecting {name}");
            print!("{}", console_text::devices(&v["devices"]));
            Ok(())
        }
        Command::Control { daemon, what } => control(&daemon, what),
        Command::Start { daemon, method, positions, resolution, lights, watch } => {
            let c = daemon.client()?;
            let mut body = serde_json::json!({});
            if let Some(m) = method {
                body["method"] = serde_json::to_value(m)?;
            }
            if let Some(n) = positions {
                body["positions"] = n.into();
            }
            if let Some(r) = resolution {
                body["resolution"] = r.into();
            }
            if let Some(l) = lights {
                body["lights"] = l.into();
            }
            let v = c.post_json("/api/v1/scans", &body)?;
            println!("started {}", v["id"].as_str().unwrap_or("?"));
            println!("method {}", v["method"].as_str().unwrap_or("?"));
            if watch {
                watch_progress(&c)?;
            }
            Ok(())
        }
        Command::Methods(d) => {
            let v = d.client()?.get_json("/api/v1/methods")?;
            for m in v["methods"].as_array().map(Vec::as_slice).unwrap_or(&[]) {
                let name = m["method"].as_str().unwrap_or("?");
                if m["available"].as_bool() == Some(true) {
                    println!("{name:<20} available");
                } else {
                    let missing: Vec<&str> = m["missing"]
                        .as_array()
                        .map(|a| a.iter().filter_map(|x| x.as_str()).collect())
                        .unwrap_or_default();
                    println!("{name:<20} not available: {}", missing.join("; "));
                }
            }
            Ok(())
        }
        Command::Reprocess { daemon, id, method, resolution, smooth, watch } => {
            let c = daemon.client()?;
            let mut body = serde_json::json!({});
            if let Some(m) = method {
                body["method"] = serde_json::to_value(m)?;
            }
            if let Some(r) = resolution {
                body["resolution"] = r.into();
            }
            if let Some(r) = smooth {
                body["smooth_radius"] = r.into();
            }
            let v = c.post_json(&format!("/api/v1/scans/{id}/reprocess"), &body)?;
            println!("reprocessing {id} as {}", v["id"].as_str().unwrap_or("?"));
            if watch {
                watch_progress(&c)?;
            }
            Ok(())
        }
        Command::Watch(d) => watch_progress(&d.client()?),
        Command::Pause { daemon, id } => scan_action(&daemon, &id, "pause"),
        Command::Resume { daemon, id } => scan_action(&daemon, &id, "resume"),
        Command::Cancel { daemon, id } => scan_action(&daemon, &id, "cancel"),
        Command::Fetch { daemon, id, out, frames, archive } => {
            let c = daemon.client()?;
            if frames || archive {
                std::fs::create_dir_all(&out).with_context(|| format!("cannot create {}", out.display()))?;
                let zip = out.join(format!("{id}.zip"));
                let files = client::fetch_archive(&c, &id, &zip, frames.then_some(out.as_path()))?;
                println!("{} files from {id} in {}", files.len(), out.display());
                if archive {
                    println!("{}", zip.display());
                } else {
                    std::fs::remove_file(&zip).with_context(|| format!("cannot remove {}", zip.display()))?;
                }
                return Ok(());
            }
            let files = client::fetch_results(&c, &id, &out)?;
            for f in files {
                println!("{}", out.join(f).display());
            }
            Ok(())
        }
        Command::Scan { rig, out, force } => {
            if !force && out.join("report.json").exists() {
                anyhow::bail!("{} holds a scan result (report.json); pass --force to replace it", out.display());
            }
            let config = scanrig::rigfile::load(&rig)?;
            let total = config.scan.positions as u64;
            let mut reporter = Reporter::new(total);
            let cancel = CancelToken::new();
            let report = scan::run_scan(&config, &out, &cancel, &mut |e| reporter.event(&e))
                .with_context(|| format!("scan with {} failed", rig.display()))?;
            reporter.finish();
            print_summary(&report);
            println!("results in {}", out.display());
            Ok(())
        }
    }
}

/// One line of figures of a finished result, and its ground truth on a simulated rig.
fn print_summary(report: &scan::Report) {
    println!(
        "{}: {} views, {} voxels occupied ({}x{}x{}), mesh {} triangles, {:.2} s ({:.2} s after the last frame)",
        report.method,
        report.views,
        report.occupied_voxels,
        report.resolution[0],
        report.resolution[1],
        report.resolution[2],
        report.mesh_triangles,
        report.timings_s.total,
        report.timings_s.after_last_frame_s
    );
    if let Some(gt) = &report.ground_truth {
        let chamfer = gt.chamfer_rel.map_or(String::new(), |c| format!(", Chamfer {:.4} of the diagonal", c));
        println!("ground truth ({}): IoU {:.4}, containment {:.4}{chamfer}", gt.scene, gt.iou, gt.containment);
    }
}

/// `scanrig control ...`: one manual control request, then the state it left.
fn control(d: &DaemonArgs, what: ControlArgs) -> anyhow::Result<()> {
    let c = d.client()?;
    let on = |s: OnOff| s == OnOff::On;
    let state = match what {
        ControlArgs::Show => c.get_json("/api/v1/control")?,
        ControlArgs::Turn { degrees } => {
            c.post_json("/api/v1/control/turntable", &serde_json::json!({ "turn_deg": degrees }))?;
            c.get_json("/api/v1/control")?
        }
        ControlArgs::Home => {
            c.post_json("/api/v1/control/turntable", &serde_json::json!({ "home": true }))?;
            c.get_json("/api/v1/control")?
        }
        ControlArgs::Light { index, state } => {
            c.post_json("/api/v1/control/light", &serde_json::json!({ "index": index, "on": on(state) }))?
        }
        ControlArgs::Laser { index, state } => {
            c.post_json("/api/v1/control/laser", &serde_json::json!({ "index": index, "on": on(state) }))?
        }
        ControlArgs::Projector { pattern, colour, blank } => {
            let body = match (pattern, colour, blank) {
                (Some(p), _, _) => {
                    let name = match p {
                        PatternArg::Checker => "checker",
                        PatternArg::Gray => "gray",
                        PatternArg::White => "white",
                        PatternArg::Black => "black",
                    };
                    serde_json::json!({ "pattern": name })
                }
                (None, Some(c), _) => {
                    let rgb: Vec<u8> =
                        c.split(',').map(|t| t.trim().parse::<u8>()).collect::<Result<_, _>>().map_err(|_| {
                            anyhow::anyhow!("--colour {c}: expected R,G,B with each 0 to 255, e.g. 255,128,0")
                        })?;
                    if rgb.len() != 3 {
                        anyhow::bail!("--colour {c}: expected three values R,G,B, got {}", rgb.len());
                    }
                    serde_json::json!({ "colour": rgb })
                }
                (None, None, true) => serde_json::json!({ "blank": true }),
                (None, None, false) => anyhow::bail!("give --pattern NAME, --colour R,G,B or --blank"),
            };
            c.post_json("/api/v1/control/projector", &body)?
        }
    };
    print!("{}", console_text::control(&state));
    Ok(())
}

/// Plain-text views of the daemon's JSON for a terminal.
mod console_text {
    use serde_json::Value;
    use std::fmt::Write;

    fn num(v: &Value, digits: usize) -> String {
        v.as_f64().map_or("-".into(), |x| format!("{x:.digits$}"))
    }

    /// `scanrig status`.
    pub fn status(v: &Value) -> String {
        let mut s = String::new();
        let _ = writeln!(
            s,
            "rig {} (scanrig {}), up {:.0} s",
            v["rig"].as_str().unwrap_or("?"),
            v["version"].as_str().unwrap_or("?"),
            v["uptime_s"].as_f64().unwrap_or(0.0)
        );
        let d = &v["defaults"];
        let _ = writeln!(
            s,
            "defaults: {}, {} positions, resolution {}",
            d["method"].as_str().unwrap_or("?"),
            d["positions"],
            d["resolution"]
        );
        s.push_str(&devices(&v["devices"]));
        let p = &v["progress"];
        match (v["running"].as_str(), p["scan_id"].as_str()) {
            (Some(id), _) => {
                let left = p["remaining_s"].as_f64().map_or(String::new(), |r| format!(", about {r:.0} s left"));
                let _ = writeln!(
                    s,
                    "scan {id} running: {} ({}/{} views, {:.0} s in{left})",
                    p["message"].as_str().unwrap_or(""),
                    p["step"],
                    p["total"],
                    p["elapsed_s"].as_f64().unwrap_or(0.0)
                );
            }
            (None, Some(id)) => {
                let _ = writeln!(s, "no scan running; the last, {id}, is {}", p["status"].as_str().unwrap_or("?"));
            }
            (None, None) => s.push_str("no scan running\n"),
        }
        s
    }

    /// The device list.
    pub fn devices(list: &Value) -> String {
        let mut s = String::new();
        for d in list.as_array().map(Vec::as_slice).unwrap_or(&[]) {
            let err = d["last_error"].as_str().map_or(String::new(), |e| format!(": {e}"));
            let _ = writeln!(
                s,
                "  {:<13} {:<7} {:<13} {} reconnects{err}",
                d["name"].as_str().unwrap_or("?"),
                d["kind"].as_str().unwrap_or("?"),
                d["state"].as_str().unwrap_or("?"),
                d["reconnects"]
            );
        }
        s
    }

    /// `scanrig scans`: one line per scan.
    pub fn scans_table(v: &Value) -> String {
        let mut s = format!(
            "{:<24} {:<20} {:<20} {:<11} {:>5} {:>9} {:>10} {:>7}\n",
            "ID", "CREATED (UTC)", "METHOD", "STATUS", "VIEWS", "TRIANGLES", "VOLUME cm3", "IOU"
        );
        let scans = v["scans"].as_array().map(Vec::as_slice).unwrap_or(&[]);
        for e in scans {
            let r = &e["report"];
            let created = e["created"].as_str().unwrap_or("?").replace('T', " ").trim_end_matches('Z').to_owned();
            let volume = r["volume_m3"].as_f64().map_or("-".into(), |m3| format!("{:.2}", m3 * 1e6));
            let _ = writeln!(
                s,
                "{:<24} {:<20} {:<20} {:<11} {:>5} {:>9} {:>10} {:>7}",
                e["id"].as_str().unwrap_or("?"),
                created,
                e["method"].as_str().unwrap_or("?"),
                e["status"].as_str().unwrap_or("?"),
                r["views"].as_u64().map_or("-".into(), |n| n.to_string()),
                r["mesh_triangles"].as_u64().map_or("-".into(), |n| n.to_string()),
                volume,
                num(&r["iou"], 4),
            );
            if let Some(err) = e["error"].as_str() {
                let _ = writeln!(s, "  failed: {err}");
            }
        }
        if scans.is_empty() {
            s.push_str("(no scans)\n");
        }
        s
    }

    /// `scanrig control`.
    pub fn control(v: &Value) -> String {
        let switches = |a: &Value| {
            let list: Vec<String> = a
                .as_array()
                .map(Vec::as_slice)
                .unwrap_or(&[])
                .iter()
                .enumerate()
                .map(|(i, on)| format!("{i} {}", if on.as_bool() == Some(true) { "on" } else { "off" }))
                .collect();
            if list.is_empty() {
                "none".to_owned()
            } else {
                list.join(", ")
            }
        };
        format!(
            "turntable at {} degrees\nlights: {}\nlasers: {}\nprojector: {}\n",
            num(&v["angle_deg"], 2),
            switches(&v["lights"]),
            switches(&v["lasers"]),
            v["projector"].as_str().unwrap_or("none")
        )
    }
}

fn scan_action(d: &DaemonArgs, id: &str, action: &str) -> anyhow::Result<()> {
    d.client()?.post_json(&format!("/api/v1/scans/{id}/{action}"), &serde_json::json!({}))?;
    println!("{action}: {id}");
    Ok(())
}

/// Follow the event stream with a progress bar (a terminal) or lines, until the scan ends.
fn watch_progress(c: &Client) -> anyhow::Result<()> {
    let bar = std::io::stderr().is_terminal().then(|| {
        let bar = indicatif::ProgressBar::new(0);
        if let Ok(style) = indicatif::ProgressStyle::with_template("[{bar:40}] {pos}/{len} {msg}") {
            bar.set_style(style.progress_chars("=> "));
        }
        bar
    });
    let mut last = String::new();
    let mut outcome = String::new();
    c.watch(|p| {
        let status = p["status"].as_str().unwrap_or("");
        let remaining = p["remaining_s"].as_f64().map_or(String::new(), |r| format!(", {r:.0} s left"));
        let msg = format!("{}{remaining}", p["message"].as_str().unwrap_or(""));
        match &bar {
            Some(bar) => {
                bar.set_length(p["total"].as_u64().unwrap_or(0));
                bar.set_position(p["step"].as_u64().unwrap_or(0));
                bar.set_message(msg);
            }
            None if msg != last => {
                eprintln!("{}/{} {msg}", p["step"], p["total"]);
                last = msg;
            }
            None => {}
        }
        if status != "running" && !status.is_empty() {
            outcome = format!("{} {}", p["scan_id"].as_str().unwrap_or("?"), status);
            return false;
        }
        status == "running" || p["scan_id"].is_string()
    })?;
    if let Some(bar) = bar {
        bar.finish_and_clear();
    }
    if outcome.is_empty() {
        println!("no scan running");
    } else {
        println!("{outcome}");
    }
    Ok(())
}

/// A progress bar on a terminal, plain log lines otherwise.
struct Reporter {
    bar: Option<indicatif::ProgressBar>,
}

impl Reporter {
    fn new(total: u64) -> Self {
        let bar = std::io::stderr().is_terminal().then(|| {
            let bar = indicatif::ProgressBar::new(total);
            if let Ok(style) = indicatif::ProgressStyle::with_template("{spinner} [{bar:40}] {pos}/{len} {msg} ({eta})")
            {
                bar.set_style(style.progress_chars("=> "));
            }
            bar
        });
        Reporter { bar }
    }

    fn event(&mut self, e: &ScanEvent) {
        match (e, &self.bar) {
            (ScanEvent::Acquisition(p), Some(bar)) => {
                bar.set_message(p.stage.to_string());
            }
            (ScanEvent::Acquisition(p), None) => {
                if matches!(p.stage, Stage::Moving | Stage::Done) {
                    eprintln!("scan: position {}/{}: {}", p.step, p.total, p.stage);
                }
            }
            (ScanEvent::ViewProcessed { position, total, message }, Some(bar)) => {
                bar.set_length(*total as u64);
                bar.set_position(*position as u64 + 1);
                bar.set_message(message.clone());
            }
            (ScanEvent::ViewProcessed { position, total, message }, None) => {
                eprintln!("pipeline: view {}/{total}: {message}", position + 1);
            }
            (ScanEvent::Stage(s), Some(bar)) => bar.set_message(*s),
            (ScanEvent::Stage(s), None) => eprintln!("pipeline: {s}"),
            // Live previews are for the daemon's viewers; the command line asks for none.
            (ScanEvent::Preview { .. }, _) => {}
        }
    }

    fn finish(&self) {
        if let Some(bar) = &self.bar {
            bar.finish_and_clear();
        }
    }
}

/// `WxH` -> (w, h).
fn parse_size(s: &str, what: &str) -> anyhow::Result<(u32, u32)> {
    let (a, b) = s.split_once(['x', 'X']).with_context(|| format!("{what}: expected WIDTHxHEIGHT, got {s:?}"))?;
    Ok((
        a.trim().parse().with_context(|| format!("{what}: bad width {a:?}"))?,
        b.trim().parse().with_context(|| format!("{what}: bad height {b:?}"))?,
    ))
}

fn calibrate_projector(args: ProjectorArgs) -> anyhow::Result<()> {
    use scanrig::calibration::procam_file::{run_procam, write_procam_file, ProcamRequest};
    let ProjectorArgs {
        captures,
        board,
        square_mm,
        reference_unit_mm,
        projector,
        graycode_step,
        camera_calib,
        reference,
        intrinsics_from_reference,
        black_threshold,
        white_threshold,
        out,
    } = args;
    let (cols, rows) = parse_size(&board, "--board")?;
    let board = scanrig::calibration::BoardSpec::new(cols as usize, rows as usize, square_mm * 1e-3)
        .context("--board/--square-mm")?;
    let mut view = scanrig::calibration::procam::ProcamViewOptions::default();
    view.decode.black_threshold = black_threshold;
    view.decode.white_threshold = white_threshold;
    if graycode_step == 0 {
        anyhow::bail!("--graycode-step must be at least 1");
    }
    view.local.graycode_step = graycode_step;
    let req = ProcamRequest {
        captures,
        board,
        patterns: parse_size(&projector, "--projector")?,
        view,
        camera_calib,
        reference,
        reference_unit_m: reference_unit_mm * 1e-3,
        intrinsics_from_reference,
    };
    let report = run_procam(&req)?;
    for (dir, s) in req.captures.iter().zip(&report.views) {
        println!(
            "{}: {:.1}% decoded, {}/{} corners placed in the projector ({:.0} px per local homography, fit RMS {:.3} px)",
            dir.display(),
            100.0 * s.valid_fraction,
            s.projector_corners,
            s.camera_corners,
            s.mean_inliers,
            s.mean_fit_rms_px
        );
    }
    let f = &report.file;
    println!(
        "camera    fx {:.2} fy {:.2} cx {:.2} cy {:.2} k1 {:.4} k2 {:.4}",
        f.camera.fx, f.camera.fy, f.camera.cx, f.camera.cy, f.camera.k1, f.camera.k2
    );
    println!(
        "projector fx {:.2} fy {:.2} cx {:.2} cy {:.2} k1 {:.4} k2 {:.4}",
        f.projector.fx, f.projector.fy, f.projector.cx, f.projector.cy, f.projector.k1, f.projector.k2
    );
    println!("translation projector<-camera {:?}", f.translation);
    println!("re-projection RMS: camera {:.3} px, projector {:.3} px", f.camera_rms_px, f.projector_rms_px);
    if let Some(c) = &report.reference {
        println!(
            "vs reference: rotation {:.3} deg, translation {:.2}%; reference transform on these views: RMS camera {:.3} px, projector {:.3} px",
            c.rotation_deg,
            100.0 * c.translation_rel,
            c.camera_rms_px,
            c.projector_rms_px
        );
    }
    write_procam_file(&out, f)?;
    println!("wrote {}", out.display());
    Ok(())
}

fn triangulate_capture(args: TriangulateArgs) -> anyhow::Result<()> {
    use scanrig::calibration::procam_cloud::{run_triangulate, TriangulateRequest};
    if args.graycode_step == 0 {
        anyhow::bail!("--graycode-step must be at least 1");
    }
    let board = match (&args.board, args.square) {
        (Some(b), Some(sq)) => {
            let (cols, rows) = parse_size(b, "--board")?;
            Some(scanrig::calibration::BoardSpec::new(cols as usize, rows as usize, sq).context("--board/--square")?)
        }
        _ => None,
    };
    let mut view = scanrig::calibration::procam::ProcamViewOptions::default();
    view.decode.black_threshold = args.black_threshold;
    view.decode.white_threshold = args.white_threshold;
    view.local.graycode_step = args.graycode_step;
    let req = TriangulateRequest {
        images: args.images,
        procam: args.procam,
        patterns: parse_size(&args.projector, "--projector")?,
        graycode_step: args.graycode_step,
        view,
        board,
        out: args.out,
    };
    let r = run_triangulate(&req).with_context(|| format!("triangulating {}", req.images.display()))?;
    println!(
        "{}x{} camera, {:.1}% decoded, {} points ({} outliers removed)",
        r.camera_size.0,
        r.camera_size.1,
        100.0 * r.decoded_fraction,
        r.points,
        r.outliers
    );
    if let Some(b) = &r.board {
        println!(
            "board plane: {} points, RMS {:.3}, max {:.3}; corners: {} triangulated (mean ray gap {:.3}), {} neighbour pairs, spacing mean {:.3} (square {}), RMS error {:.3}, max error {:.2}%",
            b.plane_points,
            b.plane_rms,
            b.plane_max,
            b.corners,
            b.corner_ray_gap_mean,
            b.pairs,
            b.spacing_mean,
            req.board.map_or(0.0, |x| x.square_m),
            b.spacing_rms,
            100.0 * b.spacing_max_rel_error
        );
    }
    println!("wrote {}", req.out.display());
    Ok(())
}

fn laser_view(args: LaserViewArgs) -> anyhow::Result<()> {
    use scanrig::calibration::cli::{load_intrinsics, parse_colour, parse_plane_mm};
    use scanrig::calibration::laser_board;
    let (intrinsics, _) = load_intrinsics(&args.intrinsics)?;
    let plane = match (&args.plane, &args.calibration) {
        (Some(p), _) => parse_plane_mm(p)?,
        (None, Some(c)) => {
            let file = scanrig::calibration::file::CalibrationFile::load(c)?;
            let l =
                file.lasers.iter().find(|l| l.index == args.laser_index).with_context(|| {
                    format!("{} has no [[lasers]] entry with index {}", c.display(), args.laser_index)
                })?;
            scanrig::pipeline::laser::Plane { normal: l.normal_camera, offset_m: l.offset_camera_m }
        }
        (None, None) => anyhow::bail!("give --plane or --calibration"),
    };
    let stripe = scanrig::pipeline::laser::StripeParams {
        min_peak: args.min_peak,
        max_width_px: args.max_width_px,
        ..Default::default()
    };
    let cloud = laser_board::laser_view(
        &intrinsics,
        &plane,
        &args.laser,
        &args.background,
        args.texture.as_deref(),
        parse_colour(&args.laser_colour)?,
        &stripe,
    )?;
    println!("{} stripe peaks, {} points triangulated", cloud.peaks, cloud.points.len());
    if let Some(c) = &args.check_plane {
        let check = parse_plane_mm(c)?;
        let band = args.check_band_mm * 1e-3;
        let d: Vec<f64> = cloud.points.iter().map(|p| check.distance(p)).filter(|d| d.abs() <= band).collect();
        if d.is_empty() {
            println!("check plane: no point within {} mm", args.check_band_mm);
        } else {
            let mean = d.iter().sum::<f64>() / d.len() as f64;
            let rms = (d.iter().map(|v| v * v).sum::<f64>() / d.len() as f64).sqrt();
            let sd = (d.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / d.len() as f64).sqrt();
            println!(
                "check plane: {} points within {} mm, residual mean {:.3} mm, RMS {:.3} mm, spread (SD) {:.3} mm",
                d.len(),
                args.check_band_mm,
                1e3 * mean,
                1e3 * rms,
                1e3 * sd
            );
        }
    }
    let pts: Vec<[f32; 3]> = cloud.points.iter().map(|p| [p.x as f32, p.y as f32, p.z as f32]).collect();
    scanrig::pipeline::export::write_ply_points(&args.out, &pts, Some(&cloud.colours))?;
    println!("wrote {}", args.out.display());
    Ok(())
}

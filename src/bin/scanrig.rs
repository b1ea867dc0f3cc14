//! `scanrig`: the command-line tool. Thin: parses arguments and calls the library.

use std::io::IsTerminal;
use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;
use clap::{Parser, Subcommand};
use scanrig::acquisition::{CancelToken, Stage};
use scanrig::scan::{self, reconstruct, ScanEvent};

#[derive(Parser, Debug)]
#[command(name = "scanrig", version, about = "Drive a 3D scanner rig and reconstruct what it sees")]
struct Cli {
    #[command(subcommand)]
    command: Command,
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
    },
    /// Reconstruct from a calibrated image set on disk (Middlebury `*_par.txt` or a file of 3x4
    /// projection matrices) and write the same outputs as `scan`.
    Reconstruct {
        /// The data set directory (image names in the calibration are relative to it).
        #[arg(long)]
        dataset: PathBuf,
        /// Reconstruction method.
        #[arg(long, default_value = "space-carving")]
        method: String,
        /// Voxels along the longest side of the box.
        #[arg(long)]
        resolution: u32,
        /// Working volume xmin,ymin,zmin,xmax,ymax,zmax in metres (default: estimated from the views).
        #[arg(long, allow_hyphen_values = true)]
        bbox: Option<String>,
        /// Calibration file (default: the one `*_par.txt` in the data set directory).
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
        /// Occupancy smoothing radius for the mesh, voxels.
        #[arg(long, default_value_t = 0)]
        smooth: u32,
        /// Output directory.
        #[arg(long)]
        out: PathBuf,
    },
    /// Check a rig file and report every problem in it.
    Validate {
        /// The rig file (TOML).
        #[arg(long)]
        rig: PathBuf,
    },
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

fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Validate { rig } => {
            scanrig::config::load(&rig)?;
            println!("{}: ok", rig.display());
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
            out,
        } => {
            let method = match method.as_str() {
                "space-carving" => scanrig::config::Method::SpaceCarving,
                other => anyhow::bail!("--method {other}: unknown method (known: space-carving)"),
            };
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
            let opts = reconstruct::ReconstructOptions {
                dataset: reconstruct::dataset_options(&dataset, calibration, views.as_deref(), masks, params),
                method,
                resolution,
                bbox,
                smooth_radius: smooth,
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
        Command::Scan { rig, out } => {
            let config = scanrig::config::load(&rig)?;
            let total = config.scan.positions as u64;
            let mut reporter = Reporter::new(total);
            let cancel = CancelToken::new();
            let report = scan::run_scan(&config, &out, &cancel, &mut |e| reporter.event(&e))
                .with_context(|| format!("scan with {} failed", rig.display()))?;
            reporter.finish();
            println!(
                "{} views, {} voxels occupied ({}x{}x{}), mesh {} triangles, {:.2} s",
                report.views,
                report.occupied_voxels,
                report.resolution[0],
                report.resolution[1],
                report.resolution[2],
                report.mesh_triangles,
                report.timings_s.total
            );
            if let Some(gt) = &report.ground_truth {
                println!("ground truth ({}): IoU {:.4}, containment {:.4}", gt.scene, gt.iou, gt.containment);
            }
            println!("results in {}", out.display());
            Ok(())
        }
    }
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
                bar.set_message(format!("{:?}", p.stage).to_lowercase());
            }
            (ScanEvent::Acquisition(p), None) => {
                if matches!(p.stage, Stage::Moving | Stage::Done) {
                    eprintln!("scan: position {}/{}: {:?}", p.step, p.total, p.stage);
                }
            }
            (ScanEvent::ViewProcessed { position, occupied }, Some(bar)) => {
                bar.set_position(*position as u64 + 1);
                bar.set_message(format!("{occupied} voxels"));
            }
            (ScanEvent::ViewProcessed { position, occupied }, None) => {
                eprintln!("pipeline: view {} carved, {occupied} voxels left", position + 1);
            }
            (ScanEvent::Stage(s), Some(bar)) => bar.set_message(*s),
            (ScanEvent::Stage(s), None) => eprintln!("pipeline: {s}"),
        }
    }

    fn finish(&self) {
        if let Some(bar) = &self.bar {
            bar.finish_and_clear();
        }
    }
}

//! `scanrig`: the command-line tool. Thin: parses arguments and calls the library.

use std::io::IsTerminal;
use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;
use clap::{Parser, Subcommand};
use scanrig::acquisition::{CancelToken, Stage};
use scanrig::scan::{self, ScanEvent};

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

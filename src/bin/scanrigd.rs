//! `scanrigd`: the scanner daemon. Thin: parses arguments, sets up logging and signals, and calls
//! [`scanrig::service::run`].

use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use anyhow::Context;
use clap::Parser;

#[derive(Parser, Debug)]
#[command(name = "scanrigd", version, about = "The scanrig daemon: HTTP API over a 3D scanner rig")]
struct Args {
    /// The rig file (TOML).
    #[arg(long, default_value = "/etc/scanrig/rig.toml")]
    config: PathBuf,
    /// Address to listen on. Anything but loopback needs a token.
    #[arg(long, default_value = "127.0.0.1:8470")]
    listen: SocketAddr,
    /// Where scans are stored.
    #[arg(long, default_value = "/var/lib/scanrig")]
    state_dir: PathBuf,
    /// File holding the bearer token, readable by its owner only (else the SCANRIGD_TOKEN
    /// environment variable). An empty token is refused.
    #[arg(long)]
    token_file: Option<PathBuf>,
    /// Seconds allowed for shutdown (stop the scan, park the rig).
    #[arg(long, default_value_t = 10.0)]
    shutdown_deadline: f64,
    /// A file with a `[replication]` section (e.g. /etc/scanrig/replication.toml): replicate
    /// finished scans to S3-compatible object storage. Replaces the rig file's `[replication]`.
    #[arg(long)]
    replication: Option<PathBuf>,
}

fn main() -> ExitCode {
    // Before any thread starts: a few malloc arenas, not eight per core (see the module's docs).
    let arenas = scanrig::service::allocator::cap_arenas();
    let args = Args::parse();
    let filter = tracing_subscriber::EnvFilter::try_from_env("SCANRIG_LOG")
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    tracing_subscriber::fmt().with_env_filter(filter).with_writer(std::io::stderr).init();
    tracing::info!(?arenas, "malloc arenas");
    match run(args) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

fn run(args: Args) -> anyhow::Result<()> {
    // A token file must be private and non-empty; so must the environment token.
    let token = match &args.token_file {
        Some(p) => Some(scanrig::service::token::from_file(p)?),
        None => scanrig::service::token::from_env("SCANRIGD_TOKEN")?,
    };
    if !args.shutdown_deadline.is_finite() || args.shutdown_deadline <= 0.0 {
        anyhow::bail!("--shutdown-deadline must be a positive number of seconds");
    }
    let opts = scanrig::service::Options {
        config_path: args.config,
        listen: args.listen,
        state_dir: args.state_dir,
        token,
        shutdown_deadline: Duration::from_secs_f64(args.shutdown_deadline),
        replication: args.replication,
    };
    let runtime = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
    runtime.block_on(async move {
        use tokio::signal::unix::{signal, SignalKind};
        let mut term = signal(SignalKind::terminate()).context("cannot install the SIGTERM handler")?;
        let mut int = signal(SignalKind::interrupt()).context("cannot install the SIGINT handler")?;
        let shutdown = async move {
            tokio::select! {
                _ = term.recv() => tracing::info!("SIGTERM"),
                _ = int.recv() => tracing::info!("SIGINT"),
            }
        };
        scanrig::service::run(opts, shutdown, |addr| {
            // Tests and scripts read the bound address (port 0 picks one) from this line.
            println!("scanrigd listening on {addr}");
        })
        .await
        .context("scanrigd failed")
    })
}

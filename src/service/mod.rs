//! The daemon: one supervisor running the HTTP API, the device thread, the scan jobs, config reload
//! on SIGHUP and the systemd watchdog, all stopped by one cancellation token.
//!
//! [`run`] takes the shutdown future, so tests can stop it; the binary passes SIGTERM/SIGINT.
//! On shutdown the running scan is stopped at its next step boundary and left `interrupted`
//! (resumable), the hardware is parked (lights and lasers off, projector blank, turntable parked)
//! and the process exits within [`Options::shutdown_deadline`].

pub mod allocator;
pub mod api;
pub mod archive;
pub mod camera;
pub mod client;
pub mod console;
pub mod control;
pub mod http;
pub mod jobs;
pub mod metrics;
pub mod notify;
pub mod replication;
pub mod rig;
pub mod session;
pub mod state_lock;
pub mod store;
pub mod token;
pub mod web;

use std::future::Future;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::{Arc, RwLock};
use std::time::{Duration, Instant};

use tokio_util::sync::CancellationToken;

use crate::config::ConfigError;

/// How the daemon runs.
#[derive(Debug, Clone)]
pub struct Options {
    /// The rig file.
    pub config_path: PathBuf,
    /// Address to listen on (port 0 picks a free port).
    pub listen: SocketAddr,
    /// Where scans are stored.
    pub state_dir: PathBuf,
    /// Bearer token; required when `listen` is not a loopback address.
    pub token: Option<String>,
    /// How long shutdown may take (stop the scan, park the rig), seconds.
    pub shutdown_deadline: Duration,
    /// A file with a `[replication]` section (`--replication FILE`); it replaces the rig file's.
    pub replication: Option<PathBuf>,
}

/// Why the daemon could not start or stopped with an error.
#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    /// The rig file is invalid.
    #[error("cannot load the rig file")]
    Config(#[source] ConfigError),
    /// The scan store cannot be opened.
    #[error("cannot open the scan store")]
    Store(#[source] store::StoreError),
    /// Another daemon uses the state directory (or it cannot be locked).
    #[error("cannot take the state directory")]
    Lock(#[source] state_lock::LockError),
    /// Listening on a non-loopback address without a token.
    #[error("listening on {0} needs a bearer token (--token-file or SCANRIGD_TOKEN)")]
    TokenRequired(SocketAddr),
    /// The listener could not be bound.
    #[error("cannot listen on {addr}")]
    Bind {
        /// The address.
        addr: SocketAddr,
        /// The error.
        #[source]
        source: std::io::Error,
    },
    /// The device thread could not be started.
    #[error("cannot start the device thread")]
    Thread(#[source] std::io::Error),
    /// The HTTP server failed.
    #[error("the HTTP server failed")]
    Serve(#[source] std::io::Error),
    /// Shutdown took longer than the deadline.
    #[error("shutdown did not finish within {0:?}")]
    ShutdownDeadline(Duration),
    /// The replication file is invalid.
    #[error("cannot load the replication settings")]
    ReplicationConfig(#[source] ConfigError),
    /// The replication queue cannot be opened.
    #[error("cannot open the replication queue")]
    ReplicationQueue(#[source] replication::QueueError),
    /// Replication is configured but this build has no object store client.
    #[error("replication is configured but scanrigd was built without the `s3` feature")]
    ReplicationUnsupported,
    /// The object store client cannot be set up (credentials, endpoint).
    #[cfg(feature = "s3")]
    #[error("cannot set up replication")]
    Archive(#[source] crate::archive::ArchiveError),
}

/// The replication settings in force: `--replication FILE` (with the file it came from), else the
/// rig file's `[replication]`.
fn replication_settings(
    opts: &Options,
    config: &crate::config::RigConfig,
) -> Result<Option<(crate::config::replication::ReplicationConfig, PathBuf)>, ServiceError> {
    match &opts.replication {
        Some(p) => {
            Ok(Some((crate::config::replication::load_file(p).map_err(ServiceError::ReplicationConfig)?, p.clone())))
        }
        None => Ok(config.replication.clone().map(|r| (r, opts.config_path.clone()))),
    }
}

/// Open the queue and build the uploader of `settings` (feature `s3`).
#[cfg(feature = "s3")]
fn start_replication(
    settings: &(crate::config::replication::ReplicationConfig, PathBuf),
    opts: &Options,
    rig_name: &str,
    store: &Arc<store::ScanStore>,
    metrics: &Arc<metrics::Metrics>,
) -> Result<(Arc<replication::Queue>, replication::uploader::Uploader), ServiceError> {
    let (cfg, file) = settings;
    let credentials = crate::archive::Credentials::for_config(cfg, file).map_err(ServiceError::Archive)?;
    let archive = crate::archive::Archive::open(cfg, &credentials).map_err(ServiceError::Archive)?;
    let rig = cfg.rig_folder(rig_name).to_owned();
    let rig_key = crate::archive::join_key(&[&cfg.prefix, &rig]);
    let queue = Arc::new(
        replication::Queue::open(&opts.state_dir, format!("s3://{}/{rig_key}", cfg.bucket), metrics.clone())
            .map_err(ServiceError::ReplicationQueue)?,
    );
    tracing::info!(bucket = %cfg.bucket, folder = %rig_key, archive = ?archive, "replicating finished scans");
    let uploader = replication::uploader::Uploader {
        queue: queue.clone(),
        archive,
        store: store.clone(),
        config: cfg.clone(),
        rig_key,
        rig,
        metrics: metrics.clone(),
    };
    Ok((queue, uploader))
}

/// Run the daemon until `shutdown` resolves. `on_listening` is called with the bound address once
/// the API answers.
pub async fn run(
    opts: Options,
    shutdown: impl Future<Output = ()> + Send + 'static,
    on_listening: impl FnOnce(SocketAddr),
) -> Result<(), ServiceError> {
    if !opts.listen.ip().is_loopback() && opts.token.is_none() {
        return Err(ServiceError::TokenRequired(opts.listen));
    }
    let config = Arc::new(crate::rigfile::load(&opts.config_path).map_err(ServiceError::Config)?);
    // Held until `run` returns (the kernel drops it if the process dies).
    let state_lock = state_lock::lock(&opts.state_dir).map_err(ServiceError::Lock)?;
    tracing::debug!(lock = %state_lock.path().display(), "state directory locked");
    let (store, interrupted) = store::ScanStore::open(&opts.state_dir).map_err(ServiceError::Store)?;
    for id in &interrupted {
        tracing::warn!(scan = %id, "scan was interrupted by a crash or power loss; it can be resumed");
    }
    let metrics = Arc::new(metrics::Metrics::default());
    let settings = replication_settings(&opts, &config)?;
    let _ = metrics
        .rig
        .set(settings.as_ref().map_or(config.rig.name.as_str(), |(r, _)| r.rig_folder(&config.rig.name)).to_owned());
    let store = Arc::new(store);
    #[cfg(feature = "s3")]
    let replication =
        settings.as_ref().map(|s| start_replication(s, &opts, &config.rig.name, &store, &metrics)).transpose()?;
    #[cfg(not(feature = "s3"))]
    if settings.is_some() {
        return Err(ServiceError::ReplicationUnsupported);
    }
    let (rig, rig_thread) = rig::RigHandle::spawn(config.clone(), metrics.clone()).map_err(ServiceError::Thread)?;
    let jobs = jobs::Jobs::new(store, rig.clone(), metrics.clone());
    let token = CancellationToken::new();
    let camera = camera::LiveCamera::new(rig.clone());
    // The uploader: a supervised task stopped by the daemon's token (its progress is on disk).
    #[cfg(feature = "s3")]
    let (jobs, uploader_task) = match replication {
        Some((queue, uploader)) => (jobs.with_replication(queue), Some(tokio::spawn(uploader.run(token.clone())))),
        None => (jobs, None),
    };
    #[cfg(not(feature = "s3"))]
    let uploader_task: Option<tokio::task::JoinHandle<()>> = None;
    let state = api::AppState {
        config: Arc::new(RwLock::new(config)),
        rig,
        jobs: jobs.clone(),
        metrics,
        token: opts.token.as_deref().map(Arc::from),
        shutdown: token.clone(),
        started: Instant::now(),
        camera,
        sessions: Arc::new(session::Sessions::new()),
        sign_in_gate: Arc::new(tokio::sync::Mutex::new(())),
    };
    let listener = tokio::net::TcpListener::bind(opts.listen)
        .await
        .map_err(|source| ServiceError::Bind { addr: opts.listen, source })?;
    let addr = listener.local_addr().map_err(|source| ServiceError::Bind { addr: opts.listen, source })?;
    tracing::info!(%addr, "listening");

    // Supervisor: the shutdown future, SIGHUP reload, the watchdog, the server.
    let trigger = token.clone();
    tokio::spawn(async move {
        shutdown.await;
        trigger.cancel();
    });
    let reload = tokio::spawn(reload_on_sighup(opts.config_path.clone(), state.clone(), token.clone()));
    if let Some(every) = notify::watchdog_interval() {
        let t = token.clone();
        tokio::spawn(async move {
            let mut tick = tokio::time::interval(every);
            loop {
                tokio::select! {
                    _ = t.cancelled() => break,
                    _ = tick.tick() => { let _ = notify::notify("WATCHDOG=1"); }
                }
            }
        });
    }
    let server = http::serve(listener, api::router(state.clone()), token.clone(), http::Limits::default());
    let server = tokio::spawn(server);
    on_listening(addr);
    if let Err(e) = notify::notify("READY=1\nSTATUS=listening") {
        tracing::warn!(error = %e, "cannot notify systemd");
    }

    token.cancelled().await;
    tracing::info!("shutting down");
    let _ = notify::notify("STOPPING=1");
    let deadline = opts.shutdown_deadline;
    let stopped = tokio::time::timeout(deadline, async {
        jobs.shutdown();
        // Wait for the scan to stop at its step boundary (it parks the rig itself).
        while jobs.running().is_some() {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        reload.abort();
        if let Some(t) = uploader_task {
            if let Err(e) = t.await {
                tracing::error!(error = %e, "the replication task failed");
            }
        }
        let served = server.await;
        // Every handle gone: the device thread parks the hardware and exits.
        drop(state);
        drop(jobs);
        let _ = tokio::task::spawn_blocking(move || rig_thread.join()).await;
        served
    })
    .await;
    drop(state_lock);
    match stopped {
        Err(_) => Err(ServiceError::ShutdownDeadline(deadline)),
        Ok(Ok(Ok(()))) => Ok(()),
        Ok(Ok(Err(e))) => Err(ServiceError::Serve(e)),
        Ok(Err(_)) => Err(ServiceError::Serve(std::io::Error::other("server task panicked"))),
    }
}

/// On SIGHUP load the rig file again; keep the old config if the new one is invalid or a scan runs.
async fn reload_on_sighup(path: PathBuf, state: api::AppState, token: CancellationToken) {
    let Ok(mut hup) = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::hangup()) else {
        tracing::warn!("cannot install the SIGHUP handler; reload disabled");
        return;
    };
    loop {
        tokio::select! {
            _ = token.cancelled() => return,
            got = hup.recv() => if got.is_none() { return },
        }
        let _ = notify::notify("RELOADING=1");
        match crate::rigfile::load(&path) {
            Err(e) => {
                tracing::error!(error = %rig::error_chain(&e), "reload: the new rig file is invalid; keeping the old one")
            }
            Ok(_) if state.jobs.running().is_some() => {
                tracing::warn!("reload: a scan is running; keeping the old config")
            }
            Ok(new) => {
                let new = Arc::new(new);
                if let Err(e) = state.rig.reload(new.clone()) {
                    tracing::error!(error = %e, "reload: cannot reach the device thread");
                } else if let Ok(mut c) = state.config.write() {
                    *c = new;
                    tracing::info!("reload: config reloaded");
                }
            }
        }
        let _ = notify::notify("READY=1");
    }
}

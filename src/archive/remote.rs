//! `scanrig reconstruct --scan s3://BUCKET/KEY`: a stored scan read from object storage and its new
//! result written beside it. The scan's objects are downloaded into a local temporary directory
//! (removed afterwards), each checked against the scan's manifest (size and SHA-256), so the one
//! scan driver reprocesses them as it does a directory; the result is uploaded (verified, with its
//! own manifest) to `KEY/reprocess-<UNIX TIME>/`.

use std::path::{Path, PathBuf};

use crate::config::replication::{PrunePolicy, ReplicationConfig};

use super::{join_key, parse_s3_url, Archive, ArchiveError, Credentials, Manifest};

/// A scan downloaded from object storage.
#[derive(Debug)]
pub struct RemoteScan {
    archive: Archive,
    /// The scan's key in the bucket.
    pub key: String,
    /// Its manifest.
    pub manifest: Manifest,
    /// The local copy (a temporary directory, removed on drop).
    pub dir: PathBuf,
}

impl Drop for RemoteScan {
    fn drop(&mut self) {
        if let Err(e) = std::fs::remove_dir_all(&self.dir) {
            tracing::warn!(dir = %self.dir.display(), error = %e, "cannot remove the downloaded scan");
        }
    }
}

/// Why a remote reprocess failed.
#[derive(Debug, thiserror::Error)]
pub enum RemoteError {
    /// The settings file is invalid.
    #[error("replication settings")]
    Settings(#[source] crate::config::ConfigError),
    /// The object store failed.
    #[error(transparent)]
    Archive(#[from] ArchiveError),
    /// The async runtime could not start.
    #[error("cannot start the I/O runtime")]
    Runtime(#[source] std::io::Error),
}

fn runtime() -> Result<tokio::runtime::Runtime, RemoteError> {
    tokio::runtime::Builder::new_current_thread().enable_all().build().map_err(RemoteError::Runtime)
}

/// The client settings for `bucket`: those of `settings_file` (a `[replication]` file: endpoint,
/// region, allow_http, credentials), else the environment (`AWS_ENDPOINT_URL` or `AWS_ENDPOINT`,
/// `AWS_REGION` or `AWS_DEFAULT_REGION`, `AWS_ALLOW_HTTP=true`, the credential variables).
pub fn settings(bucket: &str, settings_file: Option<&Path>) -> Result<(ReplicationConfig, Credentials), RemoteError> {
    match settings_file {
        Some(f) => {
            let mut c = crate::config::replication::load_file(f).map_err(RemoteError::Settings)?;
            c.bucket = bucket.to_owned();
            let creds = Credentials::for_config(&c, f)?;
            Ok((c, creds))
        }
        None => {
            let env = |k: &str| std::env::var(k).ok().filter(|v| !v.is_empty());
            let c = ReplicationConfig {
                endpoint: env("AWS_ENDPOINT_URL").or_else(|| env("AWS_ENDPOINT")),
                bucket: bucket.to_owned(),
                region: env("AWS_REGION").or_else(|| env("AWS_DEFAULT_REGION")).unwrap_or_else(|| "us-east-1".into()),
                prefix: String::new(),
                rig: None,
                credentials_file: None,
                credentials_profile: "default".into(),
                allow_http: env("AWS_ALLOW_HTTP").is_some_and(|v| v == "true"),
                part_size: 8 << 20,
                max_rate_kib_per_s: 0,
                retry_initial_s: 1.0,
                retry_max_s: 60.0,
                request_timeout_s: 30.0,
                prune: PrunePolicy::Never,
                keep_last: 0,
            };
            Ok((c, Credentials::from_env()?))
        }
    }
}

/// Download the scan at `url` (`s3://BUCKET/KEY`) into a new temporary directory, verified.
pub fn fetch(url: &str, settings_file: Option<&Path>) -> Result<RemoteScan, RemoteError> {
    let (bucket, key) = parse_s3_url(url)?;
    let (config, creds) = settings(&bucket, settings_file)?;
    let archive = Archive::open(&config, &creds)?;
    let nanos = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_nanos());
    let dir = std::env::temp_dir().join(format!("scanrig-s3-{}-{nanos}", std::process::id()));
    std::fs::create_dir_all(&dir).map_err(|source| ArchiveError::Local {
        what: "cannot create",
        path: dir.clone(),
        source,
    })?;
    let rt = runtime()?;
    match rt.block_on(archive.download_scan(&key, &dir)) {
        Ok(manifest) => Ok(RemoteScan { archive, key, manifest, dir }),
        Err(e) => {
            let _ = std::fs::remove_dir_all(&dir);
            Err(e.into())
        }
    }
}

impl RemoteScan {
    /// Upload the result directory `out` beside the scan, to `KEY/reprocess-<UNIX TIME>/`
    /// (verified, manifest last); returns its `s3://` URL.
    pub fn store_result(&self, out: &Path) -> Result<String, RemoteError> {
        let now = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_secs());
        let key = join_key(&[&self.key, &format!("reprocess-{now}")]);
        runtime()?.block_on(self.archive.upload_dir(out, &key, &self.manifest.scan, &self.manifest.rig))?;
        Ok(format!("s3://{}/{key}", self.archive.bucket()))
    }
}

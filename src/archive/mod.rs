//! The scan archive in S3-compatible object storage (AWS S3, MinIO, Ceph RGW, Garage), through the
//! `object_store` crate: uploads with checksums verified by reading every object back, multipart
//! uploads for large files, downloads verified against the scan's manifest.
//!
//! # Layout and checksums
//! A scan `SCAN` of rig `RIG` lives under `PREFIX/RIG/SCAN/`, one object per file of the scan
//! directory at the same relative path (`rig.toml`, `meta.json`, `report.json`, the models,
//! `frames/...`). Each object carries its SHA-256 as user metadata (`x-amz-meta-sha256`); after
//! upload the object is read back whole and its size and SHA-256 compared with the local file's.
//! `manifest.json` (every file's path, size in bytes and SHA-256) is uploaded last, when every other
//! object is verified, and verified the same way: a scan is replicated iff its manifest is there.
//! Downloads check every object against the manifest.

pub mod remote;

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use futures_util::StreamExt;
use object_store::aws::{AmazonS3, AmazonS3Builder};
use object_store::path::Path as ObjectPath;
use object_store::{
    Attribute, AttributeValue, Attributes, BackoffConfig, ClientOptions, ObjectStore, ObjectStoreExt,
    PutMultipartOptions, PutOptions, PutPayload, RetryConfig, WriteMultipart,
};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use tokio::io::AsyncReadExt;

use crate::config::replication::ReplicationConfig;

/// The name of a scan's manifest object, uploaded last.
pub const MANIFEST: &str = "manifest.json";

/// Why an archive operation failed.
#[derive(Debug, thiserror::Error)]
pub enum ArchiveError {
    /// The credentials file cannot be read or is not private.
    #[error("credentials file {path}: {problem}")]
    CredentialsFile {
        /// The file.
        path: PathBuf,
        /// What is wrong (never its content).
        problem: String,
    },
    /// No credentials in the environment.
    #[error("no credentials: set replication.credentials_file or AWS_ACCESS_KEY_ID and AWS_SECRET_ACCESS_KEY")]
    NoCredentials,
    /// The object store client could not be built from the settings.
    #[error("cannot set up the object store client for bucket `{bucket}`")]
    Client {
        /// The bucket.
        bucket: String,
        /// Why.
        #[source]
        source: Box<object_store::Error>,
    },
    /// A key is not a valid object path.
    #[error("`{key}` is not a valid object key")]
    Key {
        /// The key.
        key: String,
        /// Why.
        #[source]
        source: Box<object_store::path::Error>,
    },
    /// A local file could not be read or written.
    #[error("{what} {path}")]
    Local {
        /// What was being done.
        what: &'static str,
        /// The file.
        path: PathBuf,
        /// Why.
        #[source]
        source: std::io::Error,
    },
    /// A request to the server failed.
    #[error("{}: {what} s3://{bucket}/{key}", hint(source))]
    Request {
        /// What was being done (`upload`, `read back`, `download`).
        what: &'static str,
        /// The bucket.
        bucket: String,
        /// The key.
        key: String,
        /// The client's error (the server's answer).
        #[source]
        source: Box<object_store::Error>,
    },
    /// An object read back or downloaded differs from what it should be.
    #[error("checksum mismatch: s3://{bucket}/{key} has {found_size} bytes with SHA-256 {found_sha256}, expected {size} bytes with SHA-256 {sha256}")]
    Mismatch {
        /// The bucket.
        bucket: String,
        /// The key.
        key: String,
        /// Expected size, bytes.
        size: u64,
        /// Expected SHA-256 (hex).
        sha256: String,
        /// Size found, bytes.
        found_size: u64,
        /// SHA-256 found (hex).
        found_sha256: String,
    },
    /// The manifest is not valid JSON or names an unsafe path.
    #[error("manifest s3://{bucket}/{key}: {problem}")]
    Manifest {
        /// The bucket.
        bucket: String,
        /// The key.
        key: String,
        /// What is wrong.
        problem: String,
    },
    /// An `s3://` URL is malformed.
    #[error("`{0}` is not an s3://BUCKET/KEY URL")]
    Url(String),
    /// The upload was stopped (shutdown).
    #[error("stopped")]
    Stopped,
}

/// The words that lead an error of the server or the network, so a person sees what to fix.
fn hint(e: &object_store::Error) -> &'static str {
    let mut text = e.to_string();
    let mut cur: Option<&dyn std::error::Error> = std::error::Error::source(e);
    while let Some(c) = cur {
        text.push_str(": ");
        text.push_str(&c.to_string());
        cur = c.source();
    }
    let has = |s: &[&str]| s.iter().any(|w| text.contains(w));
    // No answer at all first: the text of a failed connection holds numbers (ports, times) that a
    // status code must not be read out of.
    let unreachable = [
        "tcp connect error",
        "Connection refused",
        "Connection reset",
        "connection closed",
        "error sending request",
        "dns error",
        "timed out",
    ];
    if has(&unreachable) {
        "cannot reach the object store"
    } else if has(&[
        "SignatureDoesNotMatch",
        "InvalidAccessKeyId",
        "AccessDenied",
        "403 Forbidden",
        "status 403",
        "InvalidToken",
        "ExpiredToken",
    ]) {
        "the server refused the credentials"
    } else if has(&["NoSuchBucket"]) {
        "the bucket does not exist"
    } else if has(&["QuotaExceeded", "Insufficient Storage", "XMinioStorageFull", "StorageFull", "EntityTooLarge"]) {
        "the bucket is full or over its quota"
    } else if has(&["connect", "HTTP error"]) {
        "cannot reach the object store"
    } else {
        "the object store failed"
    }
}

#[cfg(test)]
mod hint_tests {
    use super::hint;

    fn generic(message: &str) -> object_store::Error {
        object_store::Error::Generic { store: "S3", source: message.to_owned().into() }
    }

    #[test]
    fn a_refused_connection_is_unreachable_whatever_numbers_it_holds() {
        // A port of 34035 and a time of 224.6 ms once read as a 403 (the credentials).
        let e = generic(
            "Error performing GET http://127.0.0.1:34035/scans/x in 224.622614ms, after 2 retries - HTTP error: \
             error sending request: client error (Connect): tcp connect error: Connection refused (os error 111)",
        );
        assert_eq!(hint(&e), "cannot reach the object store");
        assert_eq!(
            hint(&generic("Client error with status 403 Forbidden: AccessDenied")),
            "the server refused the credentials"
        );
        assert_eq!(
            hint(&generic("InvalidAccessKeyId: the key id 4035 is unknown")),
            "the server refused the credentials"
        );
        assert_eq!(hint(&generic("NoSuchBucket")), "the bucket does not exist");
        assert_eq!(hint(&generic("507 Insufficient Storage")), "the bucket is full or over its quota");
        assert_eq!(hint(&generic("something else")), "the object store failed");
    }
}

/// A secret string: its `Debug` and `Display` never show it.
#[derive(Clone)]
pub struct Secret(String);

impl std::fmt::Debug for Secret {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Secret(***)")
    }
}

/// Credentials for the object store. `Debug` shows the access key id only.
#[derive(Clone, Debug)]
pub struct Credentials {
    /// The access key id (not secret; it names the key in the server's logs).
    pub access_key_id: String,
    /// The secret access key.
    pub secret_access_key: Secret,
    /// A session token, for temporary credentials.
    pub session_token: Option<Secret>,
}

impl Credentials {
    /// Read credentials from an AWS shared-credentials file (`[PROFILE]`, `aws_access_key_id`,
    /// `aws_secret_access_key`, `aws_session_token`), which must be readable by its owner only.
    pub fn from_file(path: &Path, profile: &str) -> Result<Credentials, ArchiveError> {
        use std::os::unix::fs::PermissionsExt;
        let bad = |problem: String| ArchiveError::CredentialsFile { path: path.to_owned(), problem };
        let meta = std::fs::metadata(path).map_err(|e| bad(format!("cannot read it: {e}")))?;
        let mode = meta.permissions().mode() & 0o777;
        if mode & 0o077 != 0 {
            return Err(bad(format!("mode {mode:o} lets others read it; chmod 600 it")));
        }
        let text = std::fs::read_to_string(path).map_err(|e| bad(format!("cannot read it: {e}")))?;
        let mut section = String::new();
        let (mut id, mut secret, mut token) = (None, None, None);
        for line in text.lines() {
            let line = line.trim();
            if line.is_empty() || line.starts_with('#') || line.starts_with(';') {
                continue;
            }
            if let Some(name) = line.strip_prefix('[').and_then(|l| l.strip_suffix(']')) {
                section = name.trim().trim_start_matches("profile ").to_owned();
                continue;
            }
            if section != profile {
                continue;
            }
            let Some((k, v)) = line.split_once('=') else { continue };
            let v = v.trim().trim_matches('"').to_owned();
            match k.trim() {
                "aws_access_key_id" => id = Some(v),
                "aws_secret_access_key" => secret = Some(v),
                "aws_session_token" => token = Some(v),
                _ => {}
            }
        }
        match (id, secret) {
            (Some(id), Some(secret)) if !id.is_empty() && !secret.is_empty() => Ok(Credentials {
                access_key_id: id,
                secret_access_key: Secret(secret),
                session_token: token.filter(|t| !t.is_empty()).map(Secret),
            }),
            _ => Err(bad(format!("profile [{profile}] lacks aws_access_key_id or aws_secret_access_key"))),
        }
    }

    /// Credentials from `AWS_ACCESS_KEY_ID`, `AWS_SECRET_ACCESS_KEY` and `AWS_SESSION_TOKEN`.
    pub fn from_env() -> Result<Credentials, ArchiveError> {
        let get = |k: &str| std::env::var(k).ok().filter(|v| !v.is_empty());
        match (get("AWS_ACCESS_KEY_ID"), get("AWS_SECRET_ACCESS_KEY")) {
            (Some(id), Some(secret)) => Ok(Credentials {
                access_key_id: id,
                secret_access_key: Secret(secret),
                session_token: get("AWS_SESSION_TOKEN").map(Secret),
            }),
            _ => Err(ArchiveError::NoCredentials),
        }
    }

    /// The credentials `config` names: its `credentials_file` (relative to `config_file`) or the
    /// environment.
    pub fn for_config(config: &ReplicationConfig, config_file: &Path) -> Result<Credentials, ArchiveError> {
        match config.credentials_path(config_file) {
            Some(p) => Credentials::from_file(&p, &config.credentials_profile),
            None => Credentials::from_env(),
        }
    }
}

/// One file of a scan in its manifest.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ManifestEntry {
    /// Path relative to the scan directory, `/`-separated.
    pub path: String,
    /// Size, bytes.
    pub size: u64,
    /// SHA-256 of the content, lower-case hex.
    pub sha256: String,
}

/// `manifest.json`: every file of a replicated scan.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Manifest {
    /// The scan id.
    pub scan: String,
    /// The rig folder it was replicated from.
    pub rig: String,
    /// When the manifest was written, seconds since the Unix epoch.
    pub created_unix: u64,
    /// The files, sorted by path.
    pub files: Vec<ManifestEntry>,
}

/// A file uploaded and verified.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Uploaded {
    /// Size, bytes.
    pub size: u64,
    /// SHA-256, hex.
    pub sha256: String,
}

/// A bucket of an S3-compatible object store.
#[derive(Clone)]
pub struct Archive {
    store: Arc<AmazonS3>,
    bucket: String,
    endpoint: String,
    part_size: usize,
    bytes_per_s: Option<u64>,
}

impl std::fmt::Debug for Archive {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Archive")
            .field("endpoint", &self.endpoint)
            .field("bucket", &self.bucket)
            .finish_non_exhaustive()
    }
}

fn now_unix() -> u64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_secs())
}

/// Lower-case hex of a digest.
fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// SHA-256 (hex) and size of a local file, read in 1 MiB blocks.
pub async fn hash_file(path: &Path) -> Result<Uploaded, ArchiveError> {
    let local = |what, source| ArchiveError::Local { what, path: path.to_owned(), source };
    let mut f = tokio::fs::File::open(path).await.map_err(|e| local("cannot open", e))?;
    let mut h = Sha256::new();
    let mut buf = vec![0u8; 1 << 20];
    let mut size = 0u64;
    loop {
        let n = f.read(&mut buf).await.map_err(|e| local("cannot read", e))?;
        if n == 0 {
            break;
        }
        h.update(&buf[..n]);
        size += n as u64;
    }
    Ok(Uploaded { size, sha256: hex(&h.finalize()) })
}

/// SHA-256 (hex) of bytes.
pub fn sha256_hex(bytes: &[u8]) -> String {
    hex(&Sha256::digest(bytes))
}

/// Split `s3://BUCKET/KEY` into the bucket and the key (without a trailing `/`).
pub fn parse_s3_url(url: &str) -> Result<(String, String), ArchiveError> {
    let rest = url.strip_prefix("s3://").ok_or_else(|| ArchiveError::Url(url.to_owned()))?;
    let (bucket, key) = rest.split_once('/').unwrap_or((rest, ""));
    let key = key.trim_matches('/');
    if bucket.is_empty() || key.is_empty() {
        return Err(ArchiveError::Url(url.to_owned()));
    }
    Ok((bucket.to_owned(), key.to_owned()))
}

/// Join key segments with `/`, skipping empty ones.
pub fn join_key(parts: &[&str]) -> String {
    parts.iter().map(|p| p.trim_matches('/')).filter(|p| !p.is_empty()).collect::<Vec<_>>().join("/")
}

impl Archive {
    /// A client of `config`'s bucket with `credentials`. Requests time out after
    /// `request_timeout_s`; the client itself retries a request at most twice (the replication
    /// queue retries whole files with its own capped backoff).
    pub fn open(config: &ReplicationConfig, credentials: &Credentials) -> Result<Archive, ArchiveError> {
        // TLS runs on rustls with ring (see Cargo.toml); an already installed provider is kept.
        let _ = rustls::crypto::ring::default_provider().install_default();
        let timeout = Duration::from_secs_f64(config.request_timeout_s);
        let mut b = AmazonS3Builder::new()
            .with_bucket_name(&config.bucket)
            .with_region(&config.region)
            .with_access_key_id(&credentials.access_key_id)
            .with_secret_access_key(&credentials.secret_access_key.0)
            .with_allow_http(config.allow_http)
            .with_client_options(
                ClientOptions::new()
                    .with_timeout(timeout)
                    .with_connect_timeout(Duration::from_secs(5).min(timeout))
                    .with_allow_http(config.allow_http),
            )
            .with_retry(RetryConfig {
                backoff: BackoffConfig {
                    init_backoff: Duration::from_millis(100),
                    max_backoff: Duration::from_secs(2),
                    base: 2.0,
                },
                max_retries: 2,
                retry_timeout: timeout * 3,
            });
        if let Some(t) = &credentials.session_token {
            b = b.with_token(&t.0);
        }
        let endpoint = match &config.endpoint {
            Some(e) => {
                b = b.with_endpoint(e).with_virtual_hosted_style_request(false);
                e.clone()
            }
            None => format!("aws:{}", config.region),
        };
        let store = b
            .build()
            .map_err(|source| ArchiveError::Client { bucket: config.bucket.clone(), source: Box::new(source) })?;
        let rate = config.max_rate_kib_per_s;
        Ok(Archive {
            store: Arc::new(store),
            bucket: config.bucket.clone(),
            endpoint,
            part_size: usize::try_from(config.part_size).unwrap_or(8 << 20),
            bytes_per_s: (rate > 0).then_some(rate * 1024),
        })
    }

    /// The bucket.
    pub fn bucket(&self) -> &str {
        &self.bucket
    }

    fn path(key: &str) -> Result<ObjectPath, ArchiveError> {
        ObjectPath::parse(key).map_err(|source| ArchiveError::Key { key: key.to_owned(), source: Box::new(source) })
    }

    fn request(&self, what: &'static str, key: &str) -> impl FnOnce(object_store::Error) -> ArchiveError {
        let (bucket, key) = (self.bucket.clone(), key.to_owned());
        move |source| ArchiveError::Request { what, bucket, key, source: Box::new(source) }
    }

    /// Upload the local file `local` as `key` (in parts of `part_size` when it is larger), with
    /// its SHA-256 as metadata, then read the object back and check its size and SHA-256.
    /// `sent` is called with the bytes of each block sent.
    pub async fn upload_file(
        &self,
        local: &Path,
        key: &str,
        sent: &mut (dyn FnMut(u64) + Send),
    ) -> Result<Uploaded, ArchiveError> {
        let want = hash_file(local).await?;
        let path = Self::path(key)?;
        let mut attributes = Attributes::new();
        attributes.insert(Attribute::Metadata("sha256".into()), AttributeValue::from(want.sha256.clone()));
        let io = |what, source| ArchiveError::Local { what, path: local.to_owned(), source };
        let mut f = tokio::fs::File::open(local).await.map_err(|e| io("cannot open", e))?;
        let started = Instant::now();
        let mut total = 0u64;
        if want.size as usize <= self.part_size {
            let mut buf = Vec::with_capacity(want.size as usize);
            f.read_to_end(&mut buf).await.map_err(|e| io("cannot read", e))?;
            total += buf.len() as u64;
            self.throttle(started, total).await;
            let opts = PutOptions { attributes, ..PutOptions::default() };
            self.store.put_opts(&path, PutPayload::from(buf), opts).await.map_err(self.request("upload", key))?;
            sent(total);
        } else {
            let opts = PutMultipartOptions { attributes, ..PutMultipartOptions::default() };
            let upload =
                self.store.put_multipart_opts(&path, opts).await.map_err(self.request("start the upload of", key))?;
            let mut w = WriteMultipart::new_with_chunk_size(upload, self.part_size);
            let mut buf = vec![0u8; self.part_size.min(1 << 20)];
            let result: Result<(), ArchiveError> = async {
                loop {
                    let n = f.read(&mut buf).await.map_err(|e| io("cannot read", e))?;
                    if n == 0 {
                        break;
                    }
                    w.wait_for_capacity(2).await.map_err(self.request("upload a part of", key))?;
                    w.write(&buf[..n]);
                    total += n as u64;
                    sent(n as u64);
                    self.throttle(started, total).await;
                }
                Ok(())
            }
            .await;
            match result {
                Ok(()) => {
                    w.finish().await.map_err(self.request("complete the upload of", key))?;
                }
                Err(e) => {
                    // Parts already sent are discarded by the server.
                    let _ = w.abort().await;
                    return Err(e);
                }
            }
        }
        self.verify(key, &want).await?;
        Ok(want)
    }

    /// Sleep so that `total` bytes since `started` stay under the rate limit.
    async fn throttle(&self, started: Instant, total: u64) {
        if let Some(rate) = self.bytes_per_s {
            let due = Duration::from_secs_f64(total as f64 / rate as f64);
            if let Some(wait) = due.checked_sub(started.elapsed()) {
                tokio::time::sleep(wait).await;
            }
        }
    }

    /// Read object `key` whole and check its size and SHA-256 (and its `sha256` metadata, when the
    /// server returns it) against `want`.
    pub async fn verify(&self, key: &str, want: &Uploaded) -> Result<(), ArchiveError> {
        let found = self.read(key, None).await?;
        self.compare(key, want, &found)
    }

    fn compare(&self, key: &str, want: &Uploaded, found: &Uploaded) -> Result<(), ArchiveError> {
        if found == want {
            Ok(())
        } else {
            Err(ArchiveError::Mismatch {
                bucket: self.bucket.clone(),
                key: key.to_owned(),
                size: want.size,
                sha256: want.sha256.clone(),
                found_size: found.size,
                found_sha256: found.sha256.clone(),
            })
        }
    }

    /// Stream object `key`, hashing it (and writing it to `out` when given).
    async fn read(&self, key: &str, mut out: Option<&mut tokio::fs::File>) -> Result<Uploaded, ArchiveError> {
        use tokio::io::AsyncWriteExt;
        let path = Self::path(key)?;
        let got = self.store.get(&path).await.map_err(self.request("read back", key))?;
        let meta_sha = got.attributes.get(&Attribute::Metadata("sha256".into())).map(|v| v.as_ref().to_owned());
        let mut stream = got.into_stream();
        let mut h = Sha256::new();
        let mut size = 0u64;
        while let Some(chunk) = stream.next().await {
            let chunk = chunk.map_err(self.request("read back", key))?;
            h.update(&chunk);
            size += chunk.len() as u64;
            if let Some(f) = out.as_deref_mut() {
                f.write_all(&chunk).await.map_err(|source| ArchiveError::Local {
                    what: "cannot write",
                    path: PathBuf::from(key),
                    source,
                })?;
            }
        }
        let sha256 = hex(&h.finalize());
        if let Some(m) = meta_sha {
            if m != sha256 {
                return Err(ArchiveError::Mismatch {
                    bucket: self.bucket.clone(),
                    key: key.to_owned(),
                    size,
                    sha256: m,
                    found_size: size,
                    found_sha256: sha256,
                });
            }
        }
        Ok(Uploaded { size, sha256 })
    }

    /// Upload `bytes` as `key` (with its SHA-256 as metadata) and read it back to verify.
    pub async fn put_verified(&self, key: &str, bytes: Vec<u8>) -> Result<Uploaded, ArchiveError> {
        let want = Uploaded { size: bytes.len() as u64, sha256: sha256_hex(&bytes) };
        let mut attributes = Attributes::new();
        attributes.insert(Attribute::Metadata("sha256".into()), AttributeValue::from(want.sha256.clone()));
        let opts = PutOptions { attributes, ..PutOptions::default() };
        self.store
            .put_opts(&Self::path(key)?, PutPayload::from(bytes), opts)
            .await
            .map_err(self.request("upload", key))?;
        self.verify(key, &want).await?;
        Ok(want)
    }

    /// The bytes of object `key`.
    pub async fn get_bytes(&self, key: &str) -> Result<Vec<u8>, ArchiveError> {
        let got = self.store.get(&Self::path(key)?).await.map_err(self.request("download", key))?;
        Ok(got.bytes().await.map_err(self.request("download", key))?.to_vec())
    }

    /// Every key under `prefix/` with its size, bytes.
    pub async fn list(&self, prefix: &str) -> Result<Vec<(String, u64)>, ArchiveError> {
        let p = Self::path(prefix)?;
        let mut out = Vec::new();
        let mut s = self.store.list(Some(&p));
        while let Some(m) = s.next().await {
            let m = m.map_err(self.request("list", prefix))?;
            out.push((m.location.to_string(), m.size));
        }
        out.sort();
        Ok(out)
    }

    /// The manifest of the scan under `scan_key`.
    pub async fn manifest(&self, scan_key: &str) -> Result<Manifest, ArchiveError> {
        let key = join_key(&[scan_key, MANIFEST]);
        let bytes = self.get_bytes(&key).await?;
        let bad = |problem: String| ArchiveError::Manifest { bucket: self.bucket.clone(), key: key.clone(), problem };
        let m: Manifest = serde_json::from_slice(&bytes).map_err(|e| bad(e.to_string()))?;
        for f in &m.files {
            if f.path.split('/').any(|s| s.is_empty() || s == "." || s == "..") || f.path.starts_with('/') {
                return Err(bad(format!("unsafe path `{}`", f.path)));
            }
        }
        Ok(m)
    }

    /// Download the scan under `scan_key` into `dir` (created), every file checked against its
    /// manifest (size and SHA-256); returns the manifest.
    pub async fn download_scan(&self, scan_key: &str, dir: &Path) -> Result<Manifest, ArchiveError> {
        let manifest = self.manifest(scan_key).await?;
        for f in &manifest.files {
            let local = dir.join(&f.path);
            let io = |what, source| ArchiveError::Local { what, path: local.clone(), source };
            if let Some(parent) = local.parent() {
                tokio::fs::create_dir_all(parent).await.map_err(|e| io("cannot create the directory of", e))?;
            }
            let mut file = tokio::fs::File::create(&local).await.map_err(|e| io("cannot create", e))?;
            let key = join_key(&[scan_key, &f.path]);
            let found = self.read(&key, Some(&mut file)).await?;
            self.compare(&key, &Uploaded { size: f.size, sha256: f.sha256.clone() }, &found)?;
            file.sync_all().await.map_err(|e| io("cannot sync", e))?;
        }
        Ok(manifest)
    }

    /// Upload every file under `dir` to `key_prefix/` (verified), then its manifest; returns the
    /// manifest.
    pub async fn upload_dir(
        &self,
        dir: &Path,
        key_prefix: &str,
        scan: &str,
        rig: &str,
    ) -> Result<Manifest, ArchiveError> {
        let mut files = Vec::new();
        for rel in list_files(dir)? {
            let up = self.upload_file(&dir.join(&rel), &join_key(&[key_prefix, &rel]), &mut |_| {}).await?;
            files.push(ManifestEntry { path: rel, size: up.size, sha256: up.sha256 });
        }
        let manifest = Manifest { scan: scan.to_owned(), rig: rig.to_owned(), created_unix: now_unix(), files };
        let bytes = serde_json::to_vec_pretty(&manifest).map_err(|e| ArchiveError::Manifest {
            bucket: self.bucket.clone(),
            key: key_prefix.to_owned(),
            problem: e.to_string(),
        })?;
        self.put_verified(&join_key(&[key_prefix, MANIFEST]), bytes).await?;
        Ok(manifest)
    }
}

/// Every regular file under `dir`, as `/`-separated paths relative to it, sorted; the temporary
/// files of atomic writes and a `manifest.json` at the top are left out.
pub fn list_files(dir: &Path) -> Result<Vec<String>, ArchiveError> {
    fn walk(root: &Path, rel: &str, out: &mut Vec<String>) -> Result<(), ArchiveError> {
        let d = if rel.is_empty() { root.to_path_buf() } else { root.join(rel) };
        let entries = std::fs::read_dir(&d).map_err(|source| ArchiveError::Local {
            what: "cannot list",
            path: d.clone(),
            source,
        })?;
        for e in entries {
            let e = e.map_err(|source| ArchiveError::Local { what: "cannot list", path: d.clone(), source })?;
            let name = e.file_name().to_string_lossy().into_owned();
            if crate::atomic::is_atomic_temp(&name) || (rel.is_empty() && name == MANIFEST) {
                continue;
            }
            let child = if rel.is_empty() { name } else { format!("{rel}/{name}") };
            let ty =
                e.file_type().map_err(|source| ArchiveError::Local { what: "cannot stat", path: e.path(), source })?;
            if ty.is_dir() {
                walk(root, &child, out)?;
            } else if ty.is_file() {
                out.push(child);
            }
        }
        Ok(())
    }
    let mut out = Vec::new();
    walk(dir, "", &mut out)?;
    out.sort();
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn credentials_never_show_the_secret() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("credentials");
        std::fs::write(&path, "[other]\naws_access_key_id = X\n[default]\naws_access_key_id = AKIDEXAMPLE\naws_secret_access_key = verysecret-42\n").expect("write");
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o644)).expect("chmod");
        let err = Credentials::from_file(&path, "default").expect_err("world-readable");
        assert!(err.to_string().contains("chmod 600"), "{err}");
        std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o600)).expect("chmod");
        let c = Credentials::from_file(&path, "default").expect("read");
        assert_eq!(c.access_key_id, "AKIDEXAMPLE");
        let shown = format!("{c:?}");
        assert!(!shown.contains("verysecret-42") && shown.contains("AKIDEXAMPLE"), "{shown}");
        let config = crate::config::replication::parse_file(
            "[replication]\nbucket = \"scans\"\nendpoint = \"http://127.0.0.1:1\"\nallow_http = true\n",
            Path::new("r.toml"),
        )
        .expect("config");
        let archive = Archive::open(&config, &c).expect("client");
        let shown = format!("{archive:?}");
        assert!(!shown.contains("verysecret-42") && shown.contains("scans"), "{shown}");
        let missing = Credentials::from_file(&path, "nope").expect_err("no such profile");
        assert!(!missing.to_string().contains("verysecret-42"), "{missing}");
    }

    #[test]
    fn s3_urls_split_into_bucket_and_key() {
        assert_eq!(parse_s3_url("s3://b/lab/rig/scan-1/").expect("url"), ("b".into(), "lab/rig/scan-1".into()));
        assert!(parse_s3_url("s3://b").is_err() && parse_s3_url("/local/dir").is_err());
        assert_eq!(join_key(&["", "lab/", "rig", "f.png"]), "lab/rig/f.png");
    }
}

//! `[replication]`: where finished scans are archived in S3-compatible object storage, in the rig
//! file or in a file of its own (`scanrigd --replication FILE`, e.g. `/etc/scanrig/replication.toml`).
//!
//! Objects of a scan go under `PREFIX/RIG/SCAN_ID/` (`RIG` is `rig` here, else the rig file's
//! `[rig] name`). Credentials are never part of this section: they come from `credentials_file`
//! (readable by its owner only) or from the standard `AWS_ACCESS_KEY_ID` / `AWS_SECRET_ACCESS_KEY`
//! / `AWS_SESSION_TOKEN` environment variables, and are never logged or served.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::{ConfigError, Problem};

/// Which local files are removed once a scan's upload is verified.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PrunePolicy {
    /// Keep every local file (the default).
    #[default]
    Never,
    /// Remove a replicated scan's `frames/` (the bulk of it) once every object, the manifest last,
    /// is uploaded and verified; the results, `rig.toml`, `meta.json` and `report.json` stay. The
    /// `keep_last` most recently replicated scans keep their frames too.
    FramesAfterVerified,
}

/// `[replication]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ReplicationConfig {
    /// The S3 endpoint URL (`https://s3.example.org`, `http://127.0.0.1:9000`); unset = AWS for
    /// `region`.
    #[serde(default)]
    pub endpoint: Option<String>,
    /// The bucket (it must exist: scanrig never creates buckets).
    pub bucket: String,
    /// The region used to sign requests.
    #[serde(default = "default_region")]
    pub region: String,
    /// Key prefix shared by the rigs of a lab (`lab-a/scans`); may be empty.
    #[serde(default)]
    pub prefix: String,
    /// This rig's folder under `prefix` (default: the rig file's `[rig] name`).
    #[serde(default)]
    pub rig: Option<String>,
    /// A file with the credentials, in the AWS shared-credentials format (`[default]`,
    /// `aws_access_key_id = ...`, `aws_secret_access_key = ...`, optional `aws_session_token`),
    /// readable by its owner only; relative to the file this section is in. Unset: the
    /// environment variables.
    #[serde(default)]
    pub credentials_file: Option<PathBuf>,
    /// The profile (section) of `credentials_file` to use.
    #[serde(default = "default_profile")]
    pub credentials_profile: String,
    /// Allow plain `http://` endpoints (a server on loopback, a lab network).
    #[serde(default)]
    pub allow_http: bool,
    /// Files larger than this are uploaded in parts of this size, bytes (AWS S3 needs at least
    /// 5 MiB for every part but the last; servers that accept smaller parts may use down to 4 KiB).
    #[serde(default = "default_part_size")]
    pub part_size: u64,
    /// Upload rate limit, KiB/s (0 = none): keeps a rig's uplink usable for others.
    #[serde(default)]
    pub max_rate_kib_per_s: u64,
    /// First wait after a failed attempt, seconds; doubled on each failure up to `retry_max_s`.
    #[serde(default = "default_retry_initial")]
    pub retry_initial_s: f64,
    /// Longest wait between attempts, seconds.
    #[serde(default = "default_retry_max")]
    pub retry_max_s: f64,
    /// Timeout of one request to the server, seconds.
    #[serde(default = "default_request_timeout")]
    pub request_timeout_s: f64,
    /// What is removed locally after a verified upload (default `never`).
    #[serde(default)]
    pub prune: PrunePolicy,
    /// With `prune = "frames_after_verified"`: the newest replicated scans that keep their frames.
    #[serde(default)]
    pub keep_last: u32,
}

fn default_region() -> String {
    "us-east-1".into()
}
fn default_profile() -> String {
    "default".into()
}
fn default_part_size() -> u64 {
    8 << 20
}
fn default_retry_initial() -> f64 {
    1.0
}
fn default_retry_max() -> f64 {
    60.0
}
fn default_request_timeout() -> f64 {
    30.0
}

/// The smallest `part_size` accepted, bytes.
pub const MIN_PART_SIZE: u64 = 4096;

/// Whether `s` is usable as one segment of an object key (no `/`, no `.`/`..`, printable ASCII
/// without spaces, quotes or backslashes).
pub fn key_segment_ok(s: &str) -> bool {
    !s.is_empty()
        && s != "."
        && s != ".."
        && s.bytes().all(|b| b.is_ascii_graphic() && !matches!(b, b'/' | b'\\' | b'"' | b'\'' | b'*' | b'?'))
}

impl ReplicationConfig {
    /// Every problem with the values, keys under `replication.`, at once.
    pub fn validate(&self) -> Vec<Problem> {
        let mut out = Vec::new();
        let mut bad =
            |key: &str, message: String| out.push(Problem { key: format!("replication.{key}"), line: None, message });
        if let Some(e) = &self.endpoint {
            match e.split_once("://") {
                Some(("https", rest)) | Some(("http", rest)) if !rest.is_empty() => {
                    if e.starts_with("http://") && !self.allow_http {
                        bad("endpoint", format!("`{e}` is plain http; set allow_http = true to allow it"));
                    }
                }
                _ => bad("endpoint", format!("`{e}` must be an http:// or https:// URL")),
            }
        }
        // S3 bucket naming rules: 3..63 of lower-case letters, digits, '.', '-'.
        let b = &self.bucket;
        if b.len() < 3
            || b.len() > 63
            || !b.bytes().all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == b'.' || c == b'-')
        {
            bad("bucket", format!("`{b}` is not a bucket name (3 to 63 of a-z, 0-9, '.', '-')"));
        }
        if self.region.is_empty() {
            bad("region", "must not be empty".into());
        }
        if !self.prefix.is_empty() && !self.prefix.trim_matches('/').split('/').all(key_segment_ok) {
            bad("prefix", format!("`{}` has an empty or unusable path segment", self.prefix));
        }
        if let Some(r) = &self.rig {
            if !key_segment_ok(r) {
                bad("rig", format!("`{r}` is not usable as a key segment (no '/', spaces or quotes)"));
            }
        }
        if self.credentials_profile.is_empty() {
            bad("credentials_profile", "must not be empty".into());
        }
        if self.part_size < MIN_PART_SIZE || self.part_size > (5 << 30) {
            bad("part_size", format!("must be between {MIN_PART_SIZE} bytes and 5 GiB, got {}", self.part_size));
        }
        for (key, v) in [
            ("retry_initial_s", self.retry_initial_s),
            ("retry_max_s", self.retry_max_s),
            ("request_timeout_s", self.request_timeout_s),
        ] {
            if !(v.is_finite() && v > 0.0 && v <= 86_400.0) {
                bad(key, format!("must be a positive number of seconds up to 86400, got {v}"));
            }
        }
        if self.retry_max_s < self.retry_initial_s {
            bad("retry_max_s", "must be at least retry_initial_s".into());
        }
        if self.keep_last > 0 && self.prune == PrunePolicy::Never {
            bad("keep_last", "only applies with prune = \"frames_after_verified\"".into());
        }
        out
    }

    /// This rig's folder under the prefix: `rig` if set, else `rig_name`.
    pub fn rig_folder<'a>(&'a self, rig_name: &'a str) -> &'a str {
        self.rig.as_deref().unwrap_or(rig_name)
    }

    /// `credentials_file` resolved against the directory of `config_file` (the file this section
    /// was read from).
    pub fn credentials_path(&self, config_file: &Path) -> Option<PathBuf> {
        self.credentials_file.as_ref().map(|f| match config_file.parent() {
            Some(d) if f.is_relative() => d.join(f),
            _ => f.clone(),
        })
    }
}

/// A file holding only a `[replication]` section.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ReplicationFile {
    replication: ReplicationConfig,
}

/// Read a replication file (`[replication]` alone, e.g. `/etc/scanrig/replication.toml`); every
/// problem is reported with its line.
pub fn load_file(path: &Path) -> Result<ReplicationConfig, ConfigError> {
    let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read { path: path.to_owned(), source })?;
    parse_file(&text, path)
}

/// [`load_file`] on the file's text; `path` names it in messages.
pub fn parse_file(text: &str, path: &Path) -> Result<ReplicationConfig, ConfigError> {
    let file: ReplicationFile = toml::from_str(text).map_err(|e| {
        let line = e.span().map(|s| text[..s.start.min(text.len())].matches('\n').count() + 1);
        ConfigError::Invalid {
            path: path.to_owned(),
            problems: vec![Problem { key: "replication".into(), line, message: e.message().to_owned() }],
        }
    })?;
    let mut problems = file.replication.validate();
    for p in &mut problems {
        p.line = super::line_of(text, &p.key);
    }
    if problems.is_empty() {
        Ok(file.replication)
    } else {
        Err(ConfigError::Invalid { path: path.to_owned(), problems })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(body: &str) -> Result<ReplicationConfig, ConfigError> {
        parse_file(&format!("[replication]\n{body}"), Path::new("replication.toml"))
    }

    #[test]
    fn defaults_and_a_minimal_section() {
        let c = parse("bucket = \"scans\"\n").expect("minimal");
        assert_eq!(c.region, "us-east-1");
        assert_eq!(c.prune, PrunePolicy::Never);
        assert_eq!(c.part_size, 8 << 20);
        assert_eq!(c.rig_folder("bench-1"), "bench-1");
    }

    #[test]
    fn every_bad_field_is_named_with_its_line() {
        let err = parse(
            "endpoint = \"http://127.0.0.1:9000\"\nbucket = \"No_Such\"\npart_size = 10\nretry_initial_s = -1\n\
             keep_last = 3\nrig = \"a/b\"\n",
        )
        .expect_err("invalid");
        let text = err.to_string() + &format!("{err:?}");
        for key in [
            "replication.endpoint",
            "replication.bucket",
            "replication.part_size",
            "replication.retry_initial_s",
            "replication.keep_last",
            "replication.rig",
        ] {
            assert!(text.contains(key), "{key} missing from {text}");
        }
        let ConfigError::Invalid { problems, .. } = err else { panic!("not a value error") };
        let endpoint = problems.iter().find(|p| p.key == "replication.endpoint").expect("endpoint");
        assert_eq!(endpoint.line, Some(2), "{endpoint:?}");
        let unknown = parse("bucket = \"scans\"\nsecret = \"x\"\n").expect_err("unknown key");
        assert!(format!("{unknown:?}").contains("secret"), "{unknown:?}");
    }

    #[test]
    fn a_rig_file_section_is_validated_with_lines_and_never_stored_with_a_scan() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/rigs/simulated.toml");
        let base = std::fs::read_to_string(&path).expect("shipped rig");
        let good = format!("{base}\n[replication]\nbucket = \"lab-scans\"\nprefix = \"lab-a\"\n");
        let config = crate::config::parse_with(&good, &path, |_| Vec::new()).expect("valid");
        assert_eq!(config.replication.as_ref().map(|r| r.bucket.as_str()), Some("lab-scans"));
        let stored = toml::to_string(&config).expect("serialise");
        assert!(!stored.contains("replication") && !stored.contains("lab-scans"), "{stored}");
        let bad = format!("{base}\n[replication]\nbucket = \"x\"\n");
        let err = crate::config::parse_with(&bad, &path, |_| Vec::new()).expect_err("bad bucket");
        let ConfigError::Invalid { problems, .. } = err else { panic!("not a value error") };
        let p = problems.iter().find(|p| p.key == "replication.bucket").expect("bucket named");
        assert_eq!(p.line, Some(base.lines().count() + 3), "{p:?}");
    }

    #[test]
    fn the_shipped_example_parses() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("systemd/etc-scanrig/replication.toml");
        let c = load_file(&path).expect("systemd/etc-scanrig/replication.toml");
        assert_eq!((c.bucket.as_str(), c.prefix.as_str(), c.prune), ("lab-scans", "lab-a", PrunePolicy::Never));
        assert_eq!(c.credentials_path(&path), Some(path.with_file_name("credentials")));
    }
}

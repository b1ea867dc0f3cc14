//! Counters exported in the Prometheus text format on `/metrics`.

use std::fmt::Write as _;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;

use crate::scan::Timings;

/// The daemon's counters. All are monotonic except the ones named as gauges.
#[derive(Debug, Default)]
pub struct Metrics {
    /// Scans started (new or resumed).
    pub scans_started: AtomicU64,
    /// Scans that finished with results.
    pub scans_completed: AtomicU64,
    /// Scans that failed.
    pub scans_failed: AtomicU64,
    /// Scans cancelled or paused.
    pub scans_stopped: AtomicU64,
    /// Frames captured and stored.
    pub frames: AtomicU64,
    /// Device errors seen by the device thread.
    pub device_errors: AtomicU64,
    /// Successful reconnections.
    pub reconnects: AtomicU64,
    /// HTTP requests served.
    pub http_requests: AtomicU64,
    /// Sum of stage timings of completed scans, seconds.
    pub stage_seconds: Mutex<Timings>,
    /// The `rig` label on every sample (the rig file's `[rig] name`, or `[replication] rig`).
    pub rig: std::sync::OnceLock<String>,
    /// Gauge: scans in the replication queue not yet replicated.
    pub replication_queued: AtomicU64,
    /// Gauge: scans whose last replication attempt failed.
    pub replication_failing: AtomicU64,
    /// Scans replicated and verified.
    pub replication_scans: AtomicU64,
    /// Files uploaded and verified.
    pub replication_files: AtomicU64,
    /// Bytes sent to the object store (including attempts that failed).
    pub replication_bytes: AtomicU64,
    /// Failed replication attempts.
    pub replication_failures: AtomicU64,
}

impl Metrics {
    /// Add a finished scan's stage timings.
    pub fn add_timings(&self, t: &Timings) {
        if let Ok(mut sum) = self.stage_seconds.lock() {
            sum.capture += t.capture;
            sum.silhouette += t.silhouette;
            sum.carve += t.carve;
            sum.mesh += t.mesh;
            sum.export += t.export;
            sum.total += t.total;
        }
    }

    /// The Prometheus text exposition (format 0.0.4). Every sample carries the label
    /// `rig="NAME"`, so one Prometheus scraping a fleet tells the rigs apart.
    pub fn render(&self, scan_running: bool) -> String {
        let rig =
            self.rig.get().map_or("", String::as_str).replace('\\', "\\\\").replace('"', "\\\"").replace('\n', "\\n");
        let label = format!("rig=\"{rig}\"");
        let mut out = String::new();
        let mut counter = |name: &str, help: &str, v: u64| {
            let _ = writeln!(out, "# HELP {name} {help}\n# TYPE {name} counter\n{name}{{{label}}} {v}");
        };
        let get = |a: &AtomicU64| a.load(Ordering::Relaxed);
        counter("scanrig_scans_started_total", "Scans started, new or resumed.", get(&self.scans_started));
        counter("scanrig_scans_completed_total", "Scans finished with results.", get(&self.scans_completed));
        counter("scanrig_scans_failed_total", "Scans that failed.", get(&self.scans_failed));
        counter("scanrig_scans_stopped_total", "Scans cancelled or paused.", get(&self.scans_stopped));
        counter("scanrig_frames_total", "Frames captured and stored.", get(&self.frames));
        counter("scanrig_device_errors_total", "Device errors.", get(&self.device_errors));
        counter("scanrig_reconnects_total", "Device reconnections.", get(&self.reconnects));
        counter("scanrig_http_requests_total", "HTTP requests served.", get(&self.http_requests));
        counter(
            "scanrig_replication_scans_total",
            "Scans replicated to object storage and verified.",
            get(&self.replication_scans),
        );
        counter("scanrig_replication_files_total", "Files uploaded and verified.", get(&self.replication_files));
        counter(
            "scanrig_replication_bytes_total",
            "Bytes sent to object storage, failed attempts included.",
            get(&self.replication_bytes),
        );
        counter("scanrig_replication_failures_total", "Failed replication attempts.", get(&self.replication_failures));
        let mut gauge = |name: &str, help: &str, v: u64| {
            let _ = writeln!(out, "# HELP {name} {help}\n# TYPE {name} gauge\n{name}{{{label}}} {v}");
        };
        gauge("scanrig_scan_running", "Whether a scan is running.", u64::from(scan_running));
        gauge(
            "scanrig_replication_queued",
            "Scans waiting in the replication queue or being uploaded.",
            get(&self.replication_queued),
        );
        gauge(
            "scanrig_replication_failing",
            "Scans whose last replication attempt failed.",
            get(&self.replication_failing),
        );
        let _ = writeln!(
            out,
            "# HELP scanrig_stage_seconds_total Wall-clock seconds per stage, summed over completed scans.\n# TYPE scanrig_stage_seconds_total counter"
        );
        if let Ok(t) = self.stage_seconds.lock() {
            for (stage, v) in [
                ("capture", t.capture),
                ("silhouette", t.silhouette),
                ("carve", t.carve),
                ("mesh", t.mesh),
                ("export", t.export),
                ("total", t.total),
            ] {
                let _ = writeln!(out, "scanrig_stage_seconds_total{{{label},stage=\"{stage}\"}} {v}");
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn renders_every_counter_with_type_lines() {
        let m = Metrics::default();
        let _ = m.rig.set("bench \"2\"".into());
        m.frames.fetch_add(3, Ordering::Relaxed);
        m.add_timings(&Timings { carve: 1.5, ..Timings::default() });
        let text = m.render(true);
        let rig = "rig=\"bench \\\"2\\\"\"";
        assert!(
            text.contains(&format!("# TYPE scanrig_frames_total counter\nscanrig_frames_total{{{rig}}} 3\n")),
            "{text}"
        );
        assert!(text.contains(&format!("scanrig_stage_seconds_total{{{rig},stage=\"carve\"}} 1.5\n")), "{text}");
        assert!(text.contains(&format!("scanrig_scan_running{{{rig}}} 1\n")), "{text}");
        assert!(text.contains(&format!("scanrig_replication_queued{{{rig}}} 0\n")), "{text}");
        for line in text.lines().filter(|l| !l.starts_with('#')) {
            let mut parts = line.rsplitn(2, ' ');
            let value = parts.next().unwrap_or("");
            assert!(value.parse::<f64>().is_ok(), "bad sample line {line}");
        }
    }
}

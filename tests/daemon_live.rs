//! The live estimate of a running scan through the real `scanrigd`: the event stream announces each
//! new estimate (`model` events, versions increasing), `GET /api/v1/scans/{id}/live.ply` serves it
//! as binary PLY, and what it shows changes the way the method's estimate does: the carved hull
//! tightens view by view, the laser cloud grows position by position.

mod daemon_common;

use std::path::Path;
use std::time::Duration;

use daemon_common::{client, rig_from, spawn, wait_finished};
use scanrig::service::client::Client;

/// A parsed binary PLY point cloud: points (metres) and whether it has colours.
struct Cloud {
    points: Vec<[f32; 3]>,
    coloured: bool,
}

impl Cloud {
    /// Axis-aligned box of the points, metres.
    fn extent(&self) -> [f32; 3] {
        let mut lo = [f32::INFINITY; 3];
        let mut hi = [f32::NEG_INFINITY; 3];
        for p in &self.points {
            for a in 0..3 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a]);
            }
        }
        [0, 1, 2].map(|a| hi[a] - lo[a])
    }
}

/// Parse the binary little-endian PLY the daemon serves (x y z float, optional red green blue uchar);
/// panics on anything else, and when the body is not exactly the announced vertices.
fn parse_ply(bytes: &[u8]) -> Cloud {
    let end = bytes.windows(11).position(|w| w == b"end_header\n").expect("PLY header") + 11;
    let header = std::str::from_utf8(&bytes[..end]).expect("ASCII header");
    assert!(header.starts_with("ply\nformat binary_little_endian 1.0\n"), "{header}");
    let n: usize = header
        .lines()
        .find_map(|l| l.strip_prefix("element vertex "))
        .and_then(|v| v.trim().parse().ok())
        .expect("vertex count");
    let coloured = header.contains("property uchar red");
    let stride = 12 + if coloured { 3 } else { 0 };
    let body = &bytes[end..];
    assert_eq!(body.len(), n * stride, "body of {n} vertices");
    let points = body
        .chunks_exact(stride)
        .map(|c| [0, 1, 2].map(|a| f32::from_le_bytes(c[4 * a..4 * a + 4].try_into().expect("4 bytes"))))
        .collect();
    Cloud { points, coloured }
}

/// Start a scan with `method` on a daemon and collect every live estimate announced until it ends:
/// `(version, position, cloud)`.
fn live_estimates(c: &Client, method: &str, positions: u32) -> (String, Vec<(u64, u64, Cloud)>) {
    let body = serde_json::json!({"method": method, "positions": positions, "resolution": 48});
    let started = c.post_json("/api/v1/scans", &body).expect("start");
    let id = started["id"].as_str().expect("id").to_owned();
    let mut seen = Vec::new();
    c.watch_events(|name, v| match name {
        "model" => {
            assert_eq!(v["scan_id"], id.as_str(), "{v}");
            let version = v["version"].as_u64().expect("version");
            let position = v["position"].as_u64().expect("position");
            // The newest estimate; a later one may already have replaced the announced one.
            let r = c.request("GET", &format!("/api/v1/scans/{id}/live.ply"), None).expect("live.ply");
            let served: u64 = r.header("x-model-version").and_then(|v| v.parse().ok()).expect("version header");
            assert!(served >= version, "served {served} after announcing {version}");
            let cloud = parse_ply(&r.body);
            if served == version {
                assert_eq!(cloud.points.len() as u64, v["points"].as_u64().expect("points"), "{v}");
            }
            seen.push((served, position, cloud));
            true
        }
        "progress" => v["scan_id"] != id.as_str() || v["status"] == "running",
        _ => true,
    })
    .expect("event stream");
    let meta = wait_finished(c, &id, Duration::from_secs(120));
    assert_eq!(meta["status"], "complete", "{meta}");
    (id, seen)
}

fn rig(dir: &Path) -> std::path::PathBuf {
    // A settle time so that views arrive apart and each gets its own estimate.
    rig_from(dir, "simulated.toml", &[("settle_ms = 0", "settle_ms = 120")])
}

#[test]
fn carved_hull_tightens_view_by_view() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = spawn(&rig(dir.path()), dir.path());
    let c = client(&d);
    let r = c.raw("GET", "/api/v1/scans/nosuchscan/live.ply", None).expect("request");
    assert_eq!(r.status, 404);

    let (id, seen) = live_estimates(&c, "space-carving", 10);
    assert!(seen.len() >= 4, "{} estimates", seen.len());
    assert!(seen.windows(2).all(|w| w[0].0 <= w[1].0 && w[0].1 <= w[1].1), "versions and positions never go back");
    assert_eq!(seen.last().map(|s| s.1), Some(9), "the last view gets its estimate");
    // The hull after one view is the silhouette's cone through the whole box; later views cut it
    // down: its footprint in the table plane shrinks.
    let first = seen.first().expect("first").2.extent();
    let last = seen.last().expect("last").2.extent();
    assert!(last[0] * last[1] < 0.8 * first[0] * first[1], "first {first:?} last {last:?}");
    assert!(!seen[0].2.coloured);
    // The estimate stays served after the scan (for a page opened late), and not for another scan.
    let r = c.request("GET", &format!("/api/v1/scans/{id}/live.ply"), None).expect("after the scan");
    assert_eq!(parse_ply(&r.body).points.len(), seen.last().expect("last").2.points.len());
}

#[test]
fn laser_cloud_grows_position_by_position() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = spawn(&rig(dir.path()), dir.path());
    let c = client(&d);
    let (_, seen) = live_estimates(&c, "laser", 10);
    assert!(seen.len() >= 4, "{} estimates", seen.len());
    let counts: Vec<usize> = seen.iter().map(|s| s.2.points.len()).collect();
    assert!(counts.windows(2).all(|w| w[0] <= w[1]), "the cloud only grows: {counts:?}");
    assert!(counts.last() > counts.first(), "{counts:?}");
    assert!(seen.iter().all(|s| s.2.coloured), "laser points carry the surface colour");
}

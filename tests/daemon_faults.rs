//! Faults against the real `scanrigd` binary: an unplugged serial board, a full disk, and a
//! SIGHUP reload with a broken then a valid rig file. Every wait is bounded.

mod daemon_common;

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use daemon_common::{client, device_states, frames_on_disk, rig_from, spawn, wait_finished, wait_for};

/// The serial rig, small: 8 positions, a coarse grid.
fn small_serial_edits<'a>(extra_emulator: &'a str) -> Vec<(&'a str, &'a str)> {
    vec![("positions = 24", "positions = 8"), ("resolution = 128", "resolution = 40"), ("lights = 4\n", extra_emulator)]
}

#[test]
fn an_unplugged_board_fails_the_scan_shows_disconnected_reconnects_and_the_daemon_stays_up() {
    let dir = tempfile::tempdir().expect("tempdir");
    // The board is pulled out at the 4th motion command and comes back 1.5 s later.
    let rig = rig_from(
        dir.path(),
        "sim-serial.toml",
        &small_serial_edits("lights = 4\nunplug_at_move = 4\nreplug_after_ms = 1500\n"),
    );
    let mut d = spawn(&rig, dir.path());
    let c = client(&d);
    wait_for("devices connected", Duration::from_secs(10), || {
        let s = device_states(&c);
        !s.is_empty() && s.iter().all(|(_, st)| st == "connected")
    });

    // Record the turntable's and the camera's published states while the scan runs and after.
    let seen: Arc<Mutex<Vec<(String, String)>>> = Arc::default();
    let stop = Arc::new(AtomicBool::new(false));
    let poller = {
        let (seen, stop, addr) = (seen.clone(), stop.clone(), d.addr.clone());
        std::thread::spawn(move || {
            let c = scanrig::service::client::Client::new(&addr, None).expect("client");
            let mut n = 0;
            while !stop.load(Ordering::SeqCst) && n < 2000 {
                if let Ok(v) = c.get_json("/api/v1/devices") {
                    let pick = |name: &str| {
                        v["devices"]
                            .as_array()
                            .and_then(|a| a.iter().find(|d| d["name"] == name))
                            .and_then(|d| d["state"].as_str())
                            .unwrap_or("")
                            .to_owned()
                    };
                    let now = (pick("turntable"), pick("camera"));
                    let mut s = seen.lock().expect("lock");
                    if s.last() != Some(&now) {
                        s.push(now);
                    }
                }
                n += 1;
                std::thread::sleep(Duration::from_millis(10));
            }
        })
    };

    let id =
        c.post_json("/api/v1/scans", &serde_json::json!({})).expect("start")["id"].as_str().expect("id").to_owned();
    let meta = wait_finished(&c, &id, Duration::from_secs(30));
    assert_eq!(meta["status"], "failed", "{meta}");
    let error = meta["error"].as_str().unwrap_or("");
    assert!(error.contains("turntable: disconnected"), "not a clear disconnect error: {error}");
    // The frames captured before the unplug are kept; there is no report.
    let frames = frames_on_disk(dir.path(), &id);
    let pngs = frames.iter().filter(|f| f.ends_with(".png")).count();
    assert!((1..8).contains(&pngs), "{frames:?}");
    assert!(frames.contains(&"pos_000.png".to_owned()), "{frames:?}");
    assert!(!dir.path().join("scans").join(&id).join("report.json").exists());

    // The board comes back by itself; the device thread reconnects it.
    let back = |seen: &[(String, String)]| {
        let tt: Vec<&str> = seen.iter().map(|(t, _)| t.as_str()).collect();
        tt.iter().position(|s| *s == "disconnected").is_some_and(|down| tt[down..].contains(&"connected"))
    };
    wait_for("the board to be shown disconnected then connected", Duration::from_secs(15), || {
        back(&seen.lock().expect("lock"))
    });
    assert!(device_states(&c).iter().all(|(_, st)| st == "connected"));
    stop.store(true, Ordering::SeqCst);
    poller.join().expect("poller");
    let seen = seen.lock().expect("lock").clone();
    let tt: Vec<&str> = seen.iter().map(|(t, _)| t.as_str()).collect();
    let down = tt.iter().position(|s| *s == "disconnected" || *s == "reconnecting");
    let down = down.unwrap_or_else(|| panic!("turntable never shown as disconnected: {seen:?}"));
    assert!(tt[down..].contains(&"connected"), "turntable not connected again: {seen:?}");
    // The camera is not behind the board: it stays connected throughout.
    assert!(seen.iter().all(|(_, cam)| cam == "connected"), "{seen:?}");
    let devices = c.get_json("/api/v1/devices").expect("devices");
    let turntable = devices["devices"].as_array().and_then(|a| a.iter().find(|d| d["name"] == "turntable")).cloned();
    assert!(turntable.as_ref().is_some_and(|t| t["reconnects"].as_u64() >= Some(1)), "{devices}");

    // The daemon stayed up and a second scan now succeeds.
    assert!(d.alive());
    let id2 =
        c.post_json("/api/v1/scans", &serde_json::json!({})).expect("start")["id"].as_str().expect("id").to_owned();
    let meta2 = wait_finished(&c, &id2, Duration::from_secs(30));
    assert_eq!(meta2["status"], "complete", "{meta2}");
    assert_eq!(frames_on_disk(dir.path(), &id2).len(), 16);
    assert!(d.alive());
    eprintln!("published turntable/camera states: {seen:?}");
}

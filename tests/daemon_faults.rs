//! Faults against the real `scanrigd` binary: an unplugged serial board, a full disk, and a
//! SIGHUP reload with a broken then a valid rig file. Every wait is bounded.

mod daemon_common;

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use daemon_common::{client, device_states, frames_on_disk, rig_from, spawn, wait_finished, wait_for};

/// The serial rig, small: 8 positions, a coarse grid.
fn small_serial_edits(extra_emulator: &str) -> Vec<(&str, &str)> {
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

/// The small simulated rig (8 positions), with `name` as its rig name.
fn small_sim_edits(name: &str) -> Vec<(&'static str, String)> {
    vec![
        ("name = \"simulated\"", format!("name = \"{name}\"")),
        ("positions = 24", "positions = 8".to_owned()),
        ("resolution = 128", "resolution = 40".to_owned()),
    ]
}

fn write_small_sim(dir: &std::path::Path, name: &str) -> std::path::PathBuf {
    let edits = small_sim_edits(name);
    let edits: Vec<(&str, &str)> = edits.iter().map(|(a, b)| (*a, b.as_str())).collect();
    rig_from(dir, "simulated.toml", &edits)
}

#[test]
fn sighup_keeps_the_old_config_when_the_new_one_is_invalid_and_loads_a_valid_one() {
    let dir = tempfile::tempdir().expect("tempdir");
    let rig = write_small_sim(dir.path(), "before-reload");
    let mut d = spawn(&rig, dir.path());
    let c = client(&d);
    assert_eq!(c.get_json("/api/v1/status").expect("status")["rig"], "before-reload");
    let hup = |d: &daemon_common::Daemon| {
        // SAFETY: sending a signal to our own child process.
        assert_eq!(unsafe { libc::kill(d.pid(), libc::SIGHUP) }, 0);
    };

    // An invalid file (an unknown field): the old config stays, the error is logged.
    let good = std::fs::read_to_string(&rig).expect("rig");
    std::fs::write(&rig, good.replace("[scan]\n", "[scan]\nspeed_of_light = 3\n")).expect("write");
    hup(&d);
    wait_for("the reload error in the log", Duration::from_secs(10), || {
        d.log().contains("reload: the new rig file is invalid; keeping the old one")
    });
    assert!(d.log().contains("speed_of_light"), "the log does not name the bad field: {}", d.log());
    assert!(d.alive());
    let status = c.get_json("/api/v1/status").expect("status");
    assert_eq!(status["rig"], "before-reload");
    assert_eq!(status["defaults"]["positions"], 8);

    // A valid new file: it is used.
    std::fs::write(&rig, good.replace("before-reload", "after-reload").replace("positions = 8", "positions = 6"))
        .expect("write");
    hup(&d);
    wait_for("the new config", Duration::from_secs(10), || {
        c.get_json("/api/v1/status").expect("status")["rig"] == "after-reload"
    });
    assert_eq!(c.get_json("/api/v1/status").expect("status")["defaults"]["positions"], 6);
    assert!(d.log().contains("reload: config reloaded"));
    // The devices were reopened from the new config and a scan runs with it.
    wait_for("devices connected", Duration::from_secs(10), || {
        device_states(&c).iter().all(|(_, st)| st == "connected")
    });
    let id =
        c.post_json("/api/v1/scans", &serde_json::json!({})).expect("start")["id"].as_str().expect("id").to_owned();
    let meta = wait_finished(&c, &id, Duration::from_secs(30));
    assert_eq!(meta["status"], "complete", "{meta}");
    assert_eq!(meta["rig"], "after-reload");
    assert_eq!(meta["positions"], 6);
    assert!(d.alive());
}

/// A tmpfs mounted for one test, unmounted when dropped.
struct Tmpfs(std::path::PathBuf);

impl Tmpfs {
    fn mount(at: &std::path::Path, size: &str) -> Option<Tmpfs> {
        std::fs::create_dir_all(at).ok()?;
        let ok = std::process::Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={size}"), "tmpfs"])
            .arg(at)
            .status()
            .is_ok_and(|s| s.success());
        ok.then(|| Tmpfs(at.to_path_buf()))
    }

    /// Bytes free for an unprivileged writer.
    fn free(&self) -> u64 {
        let path = std::ffi::CString::new(self.0.as_os_str().as_encoded_bytes()).expect("path");
        // SAFETY: statvfs fills the zeroed struct we own; the path is a valid C string.
        let mut st: libc::statvfs = unsafe { std::mem::zeroed() };
        assert_eq!(unsafe { libc::statvfs(path.as_ptr(), &mut st) }, 0);
        st.f_bavail * st.f_frsize
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        let _ = std::process::Command::new("umount").arg("-l").arg(&self.0).status();
    }
}

#[test]
fn a_full_disk_fails_the_scan_cleanly_and_keeps_what_was_written() {
    // SAFETY: getuid has no preconditions.
    if unsafe { libc::getuid() } != 0 {
        assert!(
            std::env::var_os("CI").is_none(),
            "CI must run this test, but mounting a small tmpfs for the store needs root"
        );
        eprintln!("skipped: mounting a small tmpfs for the store needs root");
        return;
    }
    let dir = tempfile::tempdir().expect("tempdir");
    let rig = write_small_sim(dir.path(), "small-disk");
    let Some(fs) = Tmpfs::mount(&dir.path().join("state"), "16m") else {
        assert!(std::env::var_os("CI").is_none(), "CI must run this test, but cannot mount a tmpfs here");
        eprintln!("skipped: cannot mount a tmpfs here");
        return;
    };
    let state = fs.0.clone();
    let d = daemon_common::spawn_in(&rig, &state, dir.path());
    let c = client(&d);
    wait_for("devices connected", Duration::from_secs(10), || {
        device_states(&c).iter().all(|(_, st)| st == "connected")
    });
    // Leave room for about two and a half frames: the third frame's PNG cannot be written.
    let frame = c.request("GET", "/api/v1/preview", None).expect("preview").body.len() as u64;
    let filler_len = fs.free().saturating_sub(frame * 5 / 2);
    std::fs::write(state.join("filler"), vec![0u8; usize::try_from(filler_len).expect("size")]).expect("filler");

    let id =
        c.post_json("/api/v1/scans", &serde_json::json!({})).expect("start")["id"].as_str().expect("id").to_owned();
    let meta = wait_finished(&c, &id, Duration::from_secs(30));
    assert_eq!(meta["status"], "failed", "{meta}");
    let error = meta["error"].as_str().unwrap_or("");
    assert!(error.contains("No space left on device"), "{error}");
    assert!(error.contains("frames/pos_"), "the error does not name the file: {error}");

    // What was written is intact: every PNG decodes, every JSON parses, no temp files left.
    let frames = frames_on_disk(&state, &id);
    let pngs: Vec<&String> = frames.iter().filter(|f| f.ends_with(".png")).collect();
    assert!(!pngs.is_empty() && pngs.len() < 8, "{frames:?}");
    let fdir = state.join("scans").join(&id).join("frames");
    for name in &frames {
        assert!(!name.starts_with('.'), "temp file left behind: {frames:?}");
        let bytes = std::fs::read(fdir.join(name)).expect("frame");
        if name.ends_with(".png") {
            image::load_from_memory(&bytes).unwrap_or_else(|e| panic!("{name} is damaged: {e}"));
        } else {
            serde_json::from_slice::<serde_json::Value>(&bytes).unwrap_or_else(|e| panic!("{name}: {e}"));
        }
    }
    assert!(!state.join("scans").join(&id).join("report.json").exists());

    // The daemon is up, answers, and scans again once there is room.
    assert_eq!(c.get_json("/api/v1/status").expect("status")["rig"], "small-disk");
    std::fs::remove_file(state.join("filler")).expect("rm filler");
    let id2 =
        c.post_json("/api/v1/scans", &serde_json::json!({})).expect("start")["id"].as_str().expect("id").to_owned();
    assert_eq!(wait_finished(&c, &id2, Duration::from_secs(30))["status"], "complete");
    eprintln!("frame PNG {frame} bytes; kept {} frames; error: {error}", pngs.len());
    drop(d);
    drop(fs);
}

/// Fill `dir`'s file system completely (until ENOSPC); returns the filler file.
fn fill_completely(dir: &std::path::Path, name: &str) -> std::path::PathBuf {
    use std::io::Write;
    let path = dir.join(name);
    let mut f = std::fs::File::create(&path).expect("filler");
    let chunk = vec![0u8; 64 * 1024];
    loop {
        match f.write(&chunk) {
            Ok(0) => break,
            Ok(_) => {}
            Err(e) if e.raw_os_error() == Some(libc::ENOSPC) => break,
            Err(e) => panic!("filler: {e}"),
        }
    }
    // Single pages a partial chunk left.
    while f.write(&[0u8; 512]).is_ok_and(|n| n > 0) {}
    path
}

#[test]
fn a_completely_full_disk_keeps_the_status_true_and_resume_works_once_space_is_freed() {
    // SAFETY: getuid has no preconditions.
    if unsafe { libc::getuid() } != 0 {
        assert!(
            std::env::var_os("CI").is_none(),
            "CI must run this test, but mounting a small tmpfs for the store needs root"
        );
        eprintln!("skipped: mounting a small tmpfs for the store needs root");
        return;
    }
    let dir = tempfile::tempdir().expect("tempdir");
    // The turntable takes its real time per move, so the disk can be filled between two frames.
    let mut edits = small_sim_edits("full-disk");
    edits.push(("real_time = false", "real_time = true".to_owned()));
    let edits: Vec<(&str, &str)> = edits.iter().map(|(a, b)| (*a, b.as_str())).collect();
    let rig = rig_from(dir.path(), "simulated.toml", &edits);
    let Some(fs) = Tmpfs::mount(&dir.path().join("state"), "16m") else {
        assert!(std::env::var_os("CI").is_none(), "CI must run this test, but cannot mount a tmpfs here");
        eprintln!("skipped: cannot mount a tmpfs here");
        return;
    };
    let state = fs.0.clone();
    let d = daemon_common::spawn_in(&rig, &state, dir.path());
    let c = client(&d);
    wait_for("devices connected", Duration::from_secs(10), || {
        device_states(&c).iter().all(|(_, st)| st == "connected")
    });
    let id =
        c.post_json("/api/v1/scans", &serde_json::json!({})).expect("start")["id"].as_str().expect("id").to_owned();
    wait_for("the first frame", Duration::from_secs(30), || {
        frames_on_disk(&state, &id).iter().any(|f| f == "pos_000.png")
    });
    // Nothing more can be written: not the next frame, not meta.json.
    let filler = fill_completely(&state, "filler");
    let meta = wait_finished(&c, &id, Duration::from_secs(30));
    assert_eq!(meta["status"], "failed", "the status served is not the scan's: {meta}");
    assert!(meta["error"].as_str().unwrap_or("").contains("No space left on device"), "{meta}");
    let on_disk = |id: &str| -> serde_json::Value {
        let bytes = std::fs::read(state.join("scans").join(id).join("meta.json")).expect("meta.json");
        serde_json::from_slice(&bytes).expect("meta.json parses")
    };
    // meta.json could not follow (this is what the test is about), but it is intact.
    assert_eq!(on_disk(&id)["status"], "running");

    // While the disk is full: a resume and a new scan are refused with a JSON 507, and the refused
    // start leaves no scan directory behind.
    let r = c.raw("POST", &format!("/api/v1/scans/{id}/resume"), None).expect("resume");
    assert_eq!(r.status, 507, "{}", String::from_utf8_lossy(&r.body));
    assert_eq!(r.json().expect("json")["error"]["code"], "disk_full");
    assert_eq!(scan_meta_of(&c, &id)["status"], "failed");
    let r = c.raw("POST", "/api/v1/scans", Some(b"{}")).expect("start");
    assert_eq!(r.status, 507, "{}", String::from_utf8_lossy(&r.body));
    for entry in std::fs::read_dir(state.join("scans")).expect("scans").flatten() {
        assert!(entry.path().join("meta.json").is_file(), "{} has no meta.json", entry.path().display());
    }
    assert_eq!(c.get_json("/api/v1/scans").expect("list")["scans"].as_array().map(Vec::len), Some(1));

    // Space freed: meta.json catches up, resume and cancel work.
    std::fs::remove_file(filler).expect("rm filler");
    assert_eq!(scan_meta_of(&c, &id)["status"], "failed");
    assert_eq!(on_disk(&id)["status"], "failed");
    let r = c.raw("POST", &format!("/api/v1/scans/{id}/resume"), None).expect("resume");
    assert_eq!(r.status, 202, "{}", String::from_utf8_lossy(&r.body));
    let meta = wait_finished(&c, &id, Duration::from_secs(60));
    assert_eq!(meta["status"], "complete", "{meta}");
    assert_eq!(on_disk(&id)["status"], "complete");
    let id2 =
        c.post_json("/api/v1/scans", &serde_json::json!({})).expect("start")["id"].as_str().expect("id").to_owned();
    c.post_json(&format!("/api/v1/scans/{id2}/cancel"), &serde_json::json!({})).expect("cancel");
    assert_eq!(wait_finished(&c, &id2, Duration::from_secs(30))["status"], "cancelled");
    drop(d);
    drop(fs);
}

fn scan_meta_of(c: &scanrig::service::client::Client, id: &str) -> serde_json::Value {
    c.get_json(&format!("/api/v1/scans/{id}")).expect("scan")["scan"].clone()
}

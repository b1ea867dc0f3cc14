//! Real-hardware code paths that need no device: `scanrig devices` against a fake `/sys` + `/dev`
//! tree through the real binary, rig files with real device kinds (validation with and without the
//! drivers' cargo features), and opening a real driver when its device is absent.

use std::os::unix::fs::symlink;
use std::path::{Path, PathBuf};
use std::process::Command;

fn write(root: &Path, rel: &str, text: &str) {
    let p = root.join(rel);
    std::fs::create_dir_all(p.parent().expect("parent")).expect("mkdir");
    std::fs::write(p, text).expect("write");
}

fn link(root: &Path, rel: &str, target: &str) {
    let p = root.join(rel);
    std::fs::create_dir_all(p.parent().expect("parent")).expect("mkdir");
    symlink(target, p).expect("symlink");
}

/// A fake tree as udev and the kernel lay it out: a UVC webcam (capture node video0, metadata node
/// video1) with a serial number, a second camera without one, a USB CDC controller board, a virtual
/// console, and a framebuffer.
fn fake_tree(root: &Path) {
    let hc = "sys/devices/pci0000:00/0000:00:14.0/usb3";
    for (port, n, card, vid, pid, serial) in [
        ("3-2", 0, "HD Pro Webcam C920", "046d", "082d", Some("9F3A1B2C")),
        ("3-4.1", 2, "UVC Camera", "0c45", "6366", None),
    ] {
        let dev = format!("{hc}/{port}");
        write(root, &format!("{dev}/idVendor"), &format!("{vid}\n"));
        write(root, &format!("{dev}/idProduct"), &format!("{pid}\n"));
        write(root, &format!("{dev}/devpath"), &format!("{}\n", &port[2..]));
        if let Some(s) = serial {
            write(root, &format!("{dev}/serial"), &format!("{s}\n"));
        }
        for (node, index) in [(n, 0), (n + 1, 1)] {
            let cdev = format!("{dev}/{port}:1.0/video4linux/video{node}");
            write(root, &format!("{cdev}/name"), &format!("{card}\n"));
            write(root, &format!("{cdev}/index"), &format!("{index}\n"));
            link(root, &format!("{cdev}/device"), "../..");
            link(root, &format!("sys/class/video4linux/video{node}"), &format!("../../{}", &cdev[4..]));
            write(root, &format!("dev/video{node}"), "");
            if let Some(s) = serial {
                link(
                    root,
                    &format!("dev/v4l/by-id/usb-046d_{}_{s}-video-index{index}", card.replace(' ', "_")),
                    &format!("../../video{node}"),
                );
            }
        }
    }
    let dev = format!("{hc}/3-3");
    write(root, &format!("{dev}/idVendor"), "2e8a\n");
    write(root, &format!("{dev}/idProduct"), "000a\n");
    write(root, &format!("{dev}/devpath"), "3\n");
    write(root, &format!("{dev}/serial"), "CTRL01\n");
    write(root, &format!("{dev}/product"), "Scanrig Controller\n");
    let tty = format!("{dev}/3-3:1.0/tty/ttyACM0");
    write(root, &format!("{tty}/dev"), "166:0\n");
    link(root, &format!("{tty}/device"), "../..");
    link(root, "sys/class/tty/ttyACM0", &format!("../../{}", &tty[4..]));
    write(root, "dev/ttyACM0", "");
    link(root, "dev/serial/by-id/usb-Scanrig_Controller_CTRL01-if00", "../../ttyACM0");
    write(root, "sys/devices/virtual/tty/tty1/dev", "4:1\n");
    link(root, "sys/class/tty/tty1", "../../devices/virtual/tty/tty1");
    write(root, "sys/devices/platform/vc4/graphics/fb0/name", "vc4drmfb\n");
    write(root, "sys/devices/platform/vc4/graphics/fb0/virtual_size", "1280,800\n");
    write(root, "sys/devices/platform/vc4/graphics/fb0/bits_per_pixel", "32\n");
    link(root, "sys/class/graphics/fb0", "../../devices/platform/vc4/graphics/fb0");
}

fn scanrig() -> Command {
    Command::new(env!("CARGO_BIN_EXE_scanrig"))
}

#[test]
fn devices_lists_stable_identities_and_pasteable_snippets() {
    let dir = tempfile::tempdir().expect("tempdir");
    fake_tree(dir.path());
    let out = scanrig().arg("devices").arg("--root").arg(dir.path()).output().expect("runs");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let text = String::from_utf8(out.stdout).expect("utf-8");
    assert!(text.contains("Cameras (2):"), "metadata nodes are not listed as cameras:\n{text}");
    assert!(text.contains("/dev/video0  \"HD Pro Webcam C920\""), "{text}");
    assert!(text.contains("usb 046d:082d  serial 9F3A1B2C  port 3-2  bus usb-0000:00:14.0-2"), "{text}");
    assert!(text.contains("device = \"/dev/v4l/by-id/usb-046d_HD_Pro_Webcam_C920_9F3A1B2C-video-index0\""), "{text}");
    assert!(text.contains("device = \"bus:usb-0000:00:14.0-4.1\""), "no serial: the USB port instead:\n{text}");
    assert!(text.contains("Serial ports (1):"), "the virtual console is not a serial port:\n{text}");
    assert!(text.contains("port = \"/dev/serial/by-id/usb-Scanrig_Controller_CTRL01-if00\""), "{text}");
    assert!(text.contains("# or: port = \"usb:2e8a:000a:CTRL01\""), "{text}");
    assert!(text.contains("/dev/fb0  \"vc4drmfb\"  1280x800  32 bits per pixel"), "{text}");
    assert!(!text.contains(&dir.path().display().to_string()), "paths are system paths, not the fake root's");

    // The same through the environment variable.
    let out = scanrig().arg("devices").env("SCANRIG_SYSFS_ROOT", dir.path()).output().expect("runs");
    assert_eq!(String::from_utf8_lossy(&out.stdout), text);

    // An empty tree: nothing, and no error.
    let empty = tempfile::tempdir().expect("tempdir");
    let out = scanrig().arg("devices").arg("--root").arg(empty.path()).output().expect("runs");
    assert!(out.status.success());
    assert!(String::from_utf8_lossy(&out.stdout).contains("Cameras (0):"));
}

fn fixture() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/rigs/real-hardware.toml")
}

#[test]
fn a_real_rig_validates_or_names_each_missing_feature_at_its_line() {
    let text = std::fs::read_to_string(fixture()).expect("fixture");
    let line_of = |needle: &str| text.lines().position(|l| l.trim() == needle).expect("line") + 1;
    let expected: Vec<(&str, &str, usize)> = [
        ("camera.kind", "v4l", cfg!(feature = "v4l"), line_of("kind = \"v4l2\"")),
        ("projector.kind", "fbdev", cfg!(feature = "fbdev"), line_of("kind = \"fbdev\"")),
        ("depth_camera.kind", "freenect", cfg!(feature = "freenect"), line_of("kind = \"freenect\"")),
    ]
    .into_iter()
    .filter(|(_, _, built, _)| !built)
    .map(|(k, f, _, l)| (k, f, l))
    .collect();
    match scanrig::rigfile::parse(&text, &fixture()) {
        Ok(rig) => {
            assert!(expected.is_empty(), "features missing but the rig validated");
            assert_eq!(rig.camera.model().width, 1280);
        }
        Err(scanrig::config::ConfigError::Invalid { problems, .. }) => {
            assert_eq!(problems.len(), expected.len(), "{problems:?}");
            for (p, (key, feature, line)) in problems.iter().zip(&expected) {
                assert_eq!(p.key, *key);
                assert_eq!(p.line, Some(*line), "{p}");
                assert!(p.message.contains(&format!("--features {feature}")), "{p}");
            }
        }
        Err(e) => panic!("{e}"),
    }
}

#[test]
fn camera_identities_and_settings_are_checked() {
    let text = std::fs::read_to_string(fixture()).expect("fixture");
    let bad = text
        .replace(
            "device = \"/dev/v4l/by-id/usb-046d_HD_Pro_Webcam_C920_ABC123-video-index0\"",
            "device = \"/dev/video0\"",
        )
        .replace("buffers = 4", "buffers = 1")
        .replace("exposure_us = 20000", "exposure_us = 0")
        .replace("device = \"/dev/fb1\"", "device = \"fb1\"");
    let Err(scanrig::config::ConfigError::Invalid { problems, .. }) =
        scanrig::rigfile::parse(&bad, Path::new("rig.toml"))
    else {
        panic!("invalid rig accepted")
    };
    let find = |key: &str| problems.iter().find(|p| p.key == key).unwrap_or_else(|| panic!("no {key}: {problems:?}"));
    assert!(find("camera.device").message.contains("changes with plug order"));
    let line = bad.lines().position(|l| l.starts_with("device = \"/dev/video0\"")).expect("line") + 1;
    assert_eq!(find("camera.device").line, Some(line));
    assert!(find("camera.buffers").message.contains("between 2 and 32"));
    assert!(find("camera.controls.exposure_us").line.is_some());
    assert!(find("projector.device").message.contains("/dev/fb1"));

    let unknown = text.replace("gain = 0", "gian = 0");
    let e = scanrig::rigfile::parse(&unknown, Path::new("rig.toml")).expect_err("unknown control key");
    assert!(e.to_string().contains("gian"), "{e}");
}

#[test]
fn opening_an_absent_device_is_a_typed_error_naming_what_is_missing() {
    use scanrig::config::{CameraConfig, DepthCameraConfig, ProjectorConfig};
    use scanrig::devices::hardware;
    use scanrig::devices::ErrorKind;
    let text = std::fs::read_to_string(fixture()).expect("fixture");
    // Parse without validation, so the kinds reach the drivers whatever the features.
    let rig: scanrig::config::RigConfig = toml::from_str(&text).expect("schema");
    let expect = |r: Result<(), scanrig::devices::DeviceError>, built: bool, feature: &str| {
        let e = r.expect_err("no such device here");
        if built {
            assert_eq!(e.kind(), ErrorKind::Disconnected, "{e}");
        } else {
            assert_eq!(e.kind(), ErrorKind::InvalidConfig, "{e}");
            assert!(e.to_string().contains(&format!("--features {feature}")), "{e}");
        }
    };
    assert!(matches!(rig.camera, CameraConfig::V4l2(_)));
    expect(hardware::open_camera(&rig.camera).map(drop), cfg!(feature = "v4l"), "v4l");
    let Some(ProjectorConfig::Fbdev(p)) = &rig.projector else { panic!("fbdev projector") };
    let mut p = p.clone();
    p.device = "/nonexistent/fb7".into();
    expect(hardware::open_fbdev(&p).map(drop), cfg!(feature = "fbdev"), "fbdev");
    if !cfg!(feature = "freenect") {
        // With the feature, opening talks to libusb; whether a Kinect is attached is the machine's.
        let Some(DepthCameraConfig::Freenect(d)) = &rig.depth_camera else { panic!("freenect") };
        expect(hardware::open_freenect(d).map(drop), false, "freenect");
    }
}

/// The real-hardware fixture with its camera and projector swapped for a GenICam camera and a window
/// projector (`camera` and `projector` TOML sections given whole).
fn with_genicam_and_window(camera: &str, projector: &str) -> String {
    let text = std::fs::read_to_string(fixture()).expect("fixture");
    let mut out = String::new();
    let mut skip = false;
    for line in text.lines() {
        if line.starts_with('[') {
            let section = line.trim_matches(|c| c == '[' || c == ']');
            skip = section == "camera"
                || section == "projector"
                || section.starts_with("camera.controls")
                || section.starts_with("projector.");
            if section == "camera" {
                out.push_str(camera);
                out.push('\n');
            }
            if section == "projector" {
                out.push_str(projector);
                out.push('\n');
            }
        }
        if !skip {
            out.push_str(line);
            out.push('\n');
        }
    }
    out
}

#[test]
fn genicam_and_window_settings_are_checked_at_their_lines() {
    let camera = "[camera]\nkind = \"genicam\"\nvendor = \"Basler\"\nwidth = 1280\nheight = 720\nexposure_us = -5.0\n\
                  fps = 0.0\nbuffers = 1\ntrigger = \"software\"\ntrigger_delay_us = 10.0\n";
    let projector =
        "[projector]\nkind = \"window\"\noutput = \"screen:x\"\nwidth = 1280\nheight = 800\nrefresh_hz = 0.5\n";
    let text = with_genicam_and_window(camera, projector);
    let Err(scanrig::config::ConfigError::Invalid { problems, .. }) =
        scanrig::rigfile::parse(&text, Path::new("rig.toml"))
    else {
        panic!("invalid rig accepted:\n{text}")
    };
    let find = |key: &str| problems.iter().find(|p| p.key == key).unwrap_or_else(|| panic!("no {key}: {problems:?}"));
    assert!(find("camera.serial").message.contains("serial number"), "no stable identity");
    assert!(find("camera.exposure_us").line.is_some());
    assert!(find("camera.fps").message.contains("frames per second"));
    assert!(find("camera.buffers").message.contains("between 2 and 64"));
    assert!(find("camera.trigger_delay_us").message.contains("line"));
    assert!(find("projector.output").message.contains("screen:N"));
    assert!(find("projector.refresh_hz").line.is_some());
    let line = text.lines().position(|l| l == "output = \"screen:x\"").expect("line") + 1;
    assert_eq!(find("projector.output").line, Some(line));
    assert_eq!(
        problems.iter().any(|p| p.key == "camera.kind"),
        !cfg!(feature = "aravis"),
        "the aravis feature is named only when it is not built in: {problems:?}"
    );
    assert_eq!(problems.iter().any(|p| p.key == "projector.kind"), !cfg!(feature = "x11"), "{problems:?}");

    // A good GenICam camera and window projector validate (given their features).
    let camera = "[camera]\nkind = \"genicam\"\nserial = \"22317405\"\nwidth = 1280\nheight = 720\n\
                  trigger = \"line\"\ntrigger_line = \"Line1\"\ntrigger_activation = \"falling-edge\"\ntrigger_delay_us = 10.0\n";
    let projector = "[projector]\nkind = \"window\"\noutput = \"HDMI-1\"\nwidth = 1280\nheight = 800\n";
    let text = with_genicam_and_window(camera, projector);
    match scanrig::rigfile::parse(&text, Path::new("rig.toml")) {
        Ok(rig) => assert!(matches!(rig.camera, scanrig::config::CameraConfig::Genicam(_))),
        Err(scanrig::config::ConfigError::Invalid { problems, .. }) => {
            let keys: Vec<&str> = problems.iter().map(|p| p.key.as_str()).collect();
            let mut want = Vec::new();
            if !cfg!(feature = "aravis") {
                want.push("camera.kind");
            }
            if !cfg!(feature = "x11") {
                want.push("projector.kind");
            }
            if !cfg!(feature = "freenect") {
                want.push("depth_camera.kind");
            }
            want.sort_unstable();
            let mut keys = keys;
            keys.sort_unstable();
            assert_eq!(keys, want, "{problems:?}");
        }
        Err(e) => panic!("{e}"),
    }
}

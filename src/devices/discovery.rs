//! `scanrig devices`: the cameras, serial ports, framebuffers and depth cameras attached, with their
//! stable identities and capabilities, and the rig-file lines that select each one.

use std::fmt::Write as _;

use super::sysfs::{FramebufferNode, SerialNode, SysRoot, VideoNode};

/// One camera capture node and what could be learnt about it.
#[derive(Debug, Clone)]
pub struct CameraEntry {
    /// The node and its identities.
    pub node: VideoNode,
    /// What the driver says, one line each (`bus_info ... driver ...`, `format MJPG 1920x1080
    /// 1280x720`), when the `v4l` feature could open it.
    pub formats: Vec<String>,
    /// Why the formats are unknown, when they are.
    pub formats_note: Option<String>,
}

/// One depth camera.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DepthEntry {
    /// The driver family (`freenect`).
    pub kind: &'static str,
    /// Its serial number, the stable identity.
    pub serial: String,
}

/// One GenICam camera (GigE Vision or USB3 Vision) found by Aravis discovery.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct GenicamEntry {
    /// `DeviceVendorName`.
    pub vendor: String,
    /// `DeviceModelName`.
    pub model: String,
    /// `DeviceSerialNumber`, the stable identity.
    pub serial: String,
    /// `GigEVision` or `USB3Vision`.
    pub protocol: String,
    /// IP address or USB path.
    pub address: String,
}

/// Everything `scanrig devices` found.
#[derive(Debug, Clone, Default)]
pub struct Listing {
    /// Camera capture nodes (index 0 of each V4L2 device).
    pub cameras: Vec<CameraEntry>,
    /// Hardware serial ports.
    pub serial_ports: Vec<SerialNode>,
    /// Framebuffers (projector outputs).
    pub framebuffers: Vec<FramebufferNode>,
    /// Depth cameras (needs the driver's feature).
    pub depth_cameras: Vec<DepthEntry>,
    /// GenICam cameras (needs the `aravis` feature).
    pub genicam_cameras: Vec<GenicamEntry>,
    /// Lines about what could not be probed (a feature not built in, a library error).
    pub notes: Vec<String>,
}

/// List the devices below `root`. Formats and depth cameras are probed only on the real system
/// (`root` = `/`) and only when the driver's feature is built in.
pub fn discover(root: &SysRoot) -> Listing {
    let mut listing =
        Listing { serial_ports: root.serial_ports(), framebuffers: root.framebuffers(), ..Listing::default() };
    for node in root.video_nodes().into_iter().filter(|n| n.index == 0) {
        let (formats, formats_note) = probe_formats(root, &node);
        listing.cameras.push(CameraEntry { node, formats, formats_note });
    }
    probe_depth(root, &mut listing);
    probe_genicam(root, &mut listing);
    listing
}

/// GenICam cameras through Aravis discovery (GigE Vision discovery broadcasts on every network
/// interface; USB3 Vision enumerates USB), on the real system only.
#[cfg(feature = "aravis")]
fn probe_genicam(root: &SysRoot, listing: &mut Listing) {
    if !root.is_system() {
        return;
    }
    listing.genicam_cameras.extend(super::camera::arv::list_devices().into_iter().map(|d| GenicamEntry {
        vendor: d.vendor,
        model: d.model,
        serial: d.serial,
        protocol: d.protocol,
        address: d.address,
    }));
}

#[cfg(not(feature = "aravis"))]
fn probe_genicam(_root: &SysRoot, listing: &mut Listing) {
    listing
        .notes
        .push("GenICam cameras: build with `--features aravis` to list GigE Vision / USB3 Vision cameras".into());
}

#[cfg(feature = "v4l")]
fn probe_formats(root: &SysRoot, node: &VideoNode) -> (Vec<String>, Option<String>) {
    if !root.is_system() {
        return (Vec::new(), Some("formats are probed on the real system only".into()));
    }
    match super::camera::v4l2::describe_formats(&node.node) {
        Ok(f) => (f, None),
        Err(e) => (Vec::new(), Some(format!("cannot query formats: {e}"))),
    }
}

#[cfg(not(feature = "v4l"))]
fn probe_formats(_root: &SysRoot, _node: &VideoNode) -> (Vec<String>, Option<String>) {
    (Vec::new(), Some("formats: build with `--features v4l` to list them".into()))
}

#[cfg(feature = "freenect")]
fn probe_depth(root: &SysRoot, listing: &mut Listing) {
    if !root.is_system() {
        return;
    }
    match super::depth::freenect::list_serials() {
        Ok(serials) => {
            listing.depth_cameras.extend(serials.into_iter().map(|serial| DepthEntry { kind: "freenect", serial }))
        }
        Err(e) => listing.notes.push(format!("Kinect (freenect): {e}")),
    }
}

#[cfg(not(feature = "freenect"))]
fn probe_depth(_root: &SysRoot, listing: &mut Listing) {
    listing.notes.push("depth cameras: build with `--features freenect` to list Kinect v1 devices".into());
}

fn toml_string(s: &str) -> String {
    let mut out = String::with_capacity(s.len() + 2);
    out.push('"');
    for c in s.chars() {
        match c {
            '"' => out.push_str("\\\""),
            '\\' => out.push_str("\\\\"),
            c if c.is_control() => {
                let _ = write!(out, "\\u{:04X}", c as u32);
            }
            c => out.push(c),
        }
    }
    out.push('"');
    out
}

/// The listing as text for a person, with a rig-file snippet under each device.
pub fn render(listing: &Listing) -> String {
    let mut out = String::new();
    let _ = writeln!(out, "Cameras ({}):", listing.cameras.len());
    for c in &listing.cameras {
        let n = &c.node;
        let _ = writeln!(out, "  {}  {}", n.node.display(), toml_string(&n.card));
        if let Some(u) = &n.usb {
            let _ = writeln!(
                out,
                "    usb {:04x}:{:04x}  serial {}  port {}  bus {}",
                u.vid,
                u.pid,
                u.serial.as_deref().unwrap_or("(none)"),
                u.port,
                u.bus_info.as_deref().unwrap_or("?")
            );
        }
        for l in &n.by_id {
            let _ = writeln!(out, "    by-id {}", l.display());
        }
        for l in &n.by_path {
            let _ = writeln!(out, "    by-path {}", l.display());
        }
        for f in &c.formats {
            let _ = writeln!(out, "    {f}");
        }
        if let Some(note) = &c.formats_note {
            let _ = writeln!(out, "    ({note})");
        }
        let _ = writeln!(
            out,
            "    # rig file:\n    [camera]\n    kind = \"v4l2\"\n    device = {}",
            toml_string(&n.best_selector())
        );
    }
    let _ = writeln!(out, "GenICam cameras ({}):", listing.genicam_cameras.len());
    for g in &listing.genicam_cameras {
        let _ = writeln!(
            out,
            "  {} {}  serial {}  {} {}",
            toml_string(&g.vendor),
            toml_string(&g.model),
            toml_string(&g.serial),
            g.protocol,
            g.address
        );
        let _ = writeln!(
            out,
            "    # rig file:\n    [camera]\n    kind = \"genicam\"\n    vendor = {}\n    model = {}\n    serial = {}",
            toml_string(&g.vendor),
            toml_string(&g.model),
            toml_string(&g.serial)
        );
    }
    let _ = writeln!(out, "Serial ports ({}):", listing.serial_ports.len());
    for p in &listing.serial_ports {
        let _ = writeln!(out, "  {}", p.node.display());
        if let Some(u) = &p.usb {
            let _ = writeln!(
                out,
                "    usb {:04x}:{:04x}  serial {}  product {}  port {}",
                u.vid,
                u.pid,
                u.serial.as_deref().unwrap_or("(none)"),
                toml_string(u.product.as_deref().unwrap_or("")),
                u.port
            );
        }
        for l in &p.by_id {
            let _ = writeln!(out, "    by-id {}", l.display());
        }
        let port = match (p.by_id.first(), &p.usb) {
            (Some(l), _) => l.display().to_string(),
            (None, Some(u)) => u.selector(),
            (None, None) => p.node.display().to_string(),
        };
        let _ = writeln!(out, "    # rig file:\n    [controller]\n    port = {}", toml_string(&port));
        if let (Some(_), Some(u)) = (p.by_id.first(), &p.usb) {
            let _ = writeln!(out, "    # or: port = {}", toml_string(&u.selector()));
        }
    }
    let _ = writeln!(out, "Framebuffers ({}):", listing.framebuffers.len());
    for f in &listing.framebuffers {
        let size = f.size.map(|(w, h)| format!("{w}x{h}")).unwrap_or_else(|| "?".into());
        let bpp = f.bits_per_pixel.map(|b| b.to_string()).unwrap_or_else(|| "?".into());
        let _ = writeln!(out, "  {}  {}  {size}  {bpp} bits per pixel", f.node.display(), toml_string(&f.driver));
        let (w, h) = f.size.unwrap_or((0, 0));
        let _ = writeln!(
            out,
            "    # rig file:\n    [projector]\n    kind = \"fbdev\"\n    device = {}\n    width = {w}\n    height = {h}",
            toml_string(&f.node.display().to_string())
        );
    }
    let _ = writeln!(out, "Depth cameras ({}):", listing.depth_cameras.len());
    for d in &listing.depth_cameras {
        let _ = writeln!(out, "  {} serial {}", d.kind, d.serial);
        let _ = writeln!(
            out,
            "    # rig file:\n    [depth_camera]\n    kind = {}\n    serial = {}",
            toml_string(d.kind),
            toml_string(&d.serial)
        );
    }
    for n in &listing.notes {
        let _ = writeln!(out, "({n})");
    }
    out
}

#[cfg(test)]
mod tests {
    use super::super::sysfs::fake;
    use super::*;

    #[test]
    fn listing_names_each_device_with_a_pasteable_selector() {
        let dir = tempfile::tempdir().expect("tempdir");
        let r = dir.path();
        fake::usb_camera(r, "1-1", 0, "HD Pro Webcam C920", ("046d", "082d"), Some("ABC123"));
        fake::usb_camera(r, "1-2", 2, "USB \"Cam\"", ("0c45", "6366"), None);
        fake::usb_serial(r, "1-4", 0, ("2e8a", "000a"), "SCANRIG-CTRL-01", "Scanrig Controller");
        fake::framebuffer(r, 1, "projector", (1280, 800), 32);
        let mut listing = discover(&SysRoot::new(r));
        assert!(listing.genicam_cameras.is_empty(), "no network discovery for a fake tree");
        listing.genicam_cameras.push(GenicamEntry {
            vendor: "Basler".into(),
            model: "acA1920-40gm".into(),
            serial: "2231\"7".into(),
            protocol: "GigEVision".into(),
            address: "192.168.1.20".into(),
        });
        assert_eq!(listing.cameras.len(), 2, "metadata nodes are not cameras");
        let text = render(&listing);
        assert!(text.contains("device = \"/dev/v4l/by-id/usb-HD_Pro_Webcam_C920_ABC123-video-index0\""), "{text}");
        assert!(text.contains("device = \"bus:usb-0000:00:14.0-2\""), "{text}");
        assert!(text.contains("\"USB \\\"Cam\\\"\""), "quotes escaped: {text}");
        assert!(
            text.contains(
                "kind = \"genicam\"\n    vendor = \"Basler\"\n    model = \"acA1920-40gm\"\n    serial = \"2231\\\"7\""
            ),
            "{text}"
        );
        assert!(text.contains("port = \"/dev/serial/by-id/usb-Scanrig_Controller_SCANRIG-CTRL-01-if00\""), "{text}");
        assert!(text.contains("# or: port = \"usb:2e8a:000a:SCANRIG-CTRL-01\""), "{text}");
        assert!(
            text.contains("kind = \"fbdev\"\n    device = \"/dev/fb1\"\n    width = 1280\n    height = 800"),
            "{text}"
        );
        // The snippets parse as TOML.
        for block in text.split("# rig file:\n").skip(1) {
            let snippet: String = block
                .lines()
                .take_while(|l| l.starts_with("    ") && !l.trim_start().starts_with("# or"))
                .map(|l| format!("{}\n", l.trim_start()))
                .collect();
            toml::from_str::<toml::Table>(&snippet).unwrap_or_else(|e| panic!("{snippet}: {e}"));
        }
    }
}

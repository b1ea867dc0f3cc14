//! Stable device identities from `/sys` and `/dev`: which camera, serial port or framebuffer is
//! which, independent of the order the kernel numbered them in.
//!
//! Everything reads below a [`SysRoot`] (normally `/`), so the same code runs against a fake
//! `sys/` + `dev/` tree in a temporary directory in tests. Paths returned to the user (`node`,
//! `by_id`) are absolute device paths as they are on the real system (`/dev/video0`), never the
//! rooted test paths.

use std::path::{Component, Path, PathBuf};

/// The directory that plays `/` for device lookups.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SysRoot {
    root: PathBuf,
}

impl Default for SysRoot {
    fn default() -> Self {
        SysRoot { root: PathBuf::from("/") }
    }
}

impl SysRoot {
    /// Device lookups below `root` (`/` for the real system).
    pub fn new(root: impl Into<PathBuf>) -> Self {
        SysRoot { root: root.into() }
    }

    /// The real system's root unless the environment variable `SCANRIG_SYSFS_ROOT` names another.
    pub fn from_env() -> Self {
        match std::env::var_os("SCANRIG_SYSFS_ROOT") {
            Some(r) if !r.is_empty() => SysRoot::new(r),
            _ => SysRoot::default(),
        }
    }

    /// True for the real system's root.
    pub fn is_system(&self) -> bool {
        self.root == Path::new("/")
    }

    /// Where the absolute path `abs` (e.g. `/dev/video0`) is below this root.
    pub fn path(&self, abs: &Path) -> PathBuf {
        let rel: PathBuf =
            abs.components().filter(|c| !matches!(c, Component::RootDir | Component::Prefix(_))).collect();
        self.root.join(rel)
    }

    /// The absolute system path of `rooted` (a path below this root), the inverse of [`Self::path`].
    pub fn unroot(&self, rooted: &Path) -> PathBuf {
        match rooted.strip_prefix(&self.root) {
            Ok(rel) => Path::new("/").join(rel),
            Err(_) => rooted.to_owned(),
        }
    }

    /// The absolute system path `abs` leads to, with every symbolic link along it resolved (relative
    /// targets against the link's directory, absolute targets re-rooted; at most 40 links), like
    /// `realpath` below this root. Parts that do not exist are kept as written.
    pub fn follow(&self, abs: &Path) -> PathBuf {
        let mut out = PathBuf::from("/");
        let mut pending: std::collections::VecDeque<std::ffi::OsString> =
            abs.components().filter_map(|c| component_name(&c)).collect();
        let mut hops = 0;
        while let Some(c) = pending.pop_front() {
            if c == ".." {
                out.pop();
                continue;
            }
            out.push(&c);
            if hops >= 40 {
                continue;
            }
            if let Ok(target) = std::fs::read_link(self.path(&out)) {
                hops += 1;
                out.pop();
                if target.is_absolute() {
                    out = PathBuf::from("/");
                }
                for t in target.components().rev().filter_map(|c| component_name(&c)) {
                    pending.push_front(t);
                }
            }
        }
        out
    }

    fn read_attr(&self, dir: &Path, name: &str) -> Option<String> {
        let s = std::fs::read_to_string(dir.join(name)).ok()?;
        let t = s.trim();
        (!t.is_empty()).then(|| t.to_owned())
    }

    /// The symbolic links in the absolute directory `dir` (e.g. `/dev/v4l/by-id`) that lead to the
    /// absolute device `node`, sorted.
    pub fn links_to(&self, dir: &Path, node: &Path) -> Vec<PathBuf> {
        let Ok(entries) = std::fs::read_dir(self.path(dir)) else { return Vec::new() };
        let mut out: Vec<PathBuf> = entries
            .filter_map(|e| e.ok())
            .map(|e| dir.join(e.file_name()))
            .filter(|link| self.follow(link) == node)
            .collect();
        out.sort();
        out
    }

    /// The USB device a class device (e.g. `/sys/class/video4linux/video0`) belongs to, if it is on USB.
    pub fn usb_identity(&self, class_dev: &Path) -> Option<UsbIdentity> {
        let dev = self.follow(&class_dev.join("device"));
        // Walk up to the USB device: the first ancestor with idVendor (interfaces have none).
        let sys = Path::new("/sys");
        let mut dir = dev.as_path();
        loop {
            let rooted = self.path(dir);
            if let (Some(v), Some(p)) = (self.read_attr(&rooted, "idVendor"), self.read_attr(&rooted, "idProduct")) {
                let vid = u16::from_str_radix(&v, 16).ok()?;
                let pid = u16::from_str_radix(&p, 16).ok()?;
                let devpath = self.read_attr(&rooted, "devpath");
                // The host controller is the parent of the `usbN` root hub directory.
                let hc = dir
                    .ancestors()
                    .find(|a| {
                        a.file_name().and_then(|n| n.to_str()).is_some_and(|n| {
                            n.strip_prefix("usb")
                                .is_some_and(|d| !d.is_empty() && d.bytes().all(|b| b.is_ascii_digit()))
                        })
                    })
                    .and_then(|hub| hub.parent())
                    .and_then(|p| p.file_name())
                    .map(|n| n.to_string_lossy().into_owned());
                let bus_info = match (hc, devpath) {
                    (Some(hc), Some(dp)) => Some(format!("usb-{hc}-{dp}")),
                    _ => None,
                };
                return Some(UsbIdentity {
                    vid,
                    pid,
                    serial: self.read_attr(&rooted, "serial"),
                    manufacturer: self.read_attr(&rooted, "manufacturer"),
                    product: self.read_attr(&rooted, "product"),
                    port: dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default(),
                    bus_info,
                });
            }
            match dir.parent() {
                Some(p) if p.starts_with(sys) && p != sys => dir = p,
                _ => return None,
            }
        }
    }

    /// Every V4L2 node (`/sys/class/video4linux/video*`), sorted by node number.
    pub fn video_nodes(&self) -> Vec<VideoNode> {
        let class = Path::new("/sys/class/video4linux");
        let mut out: Vec<VideoNode> = list_class(self, class, "video")
            .into_iter()
            .map(|(name, number)| {
                let cdev = class.join(&name);
                let rooted = self.path(&cdev);
                let node = Path::new("/dev").join(&name);
                VideoNode {
                    card: self.read_attr(&rooted, "name").unwrap_or_default(),
                    index: self.read_attr(&rooted, "index").and_then(|i| i.parse().ok()).unwrap_or(0),
                    by_id: self.links_to(Path::new("/dev/v4l/by-id"), &node),
                    by_path: self.links_to(Path::new("/dev/v4l/by-path"), &node),
                    usb: self.usb_identity(&cdev),
                    number,
                    node,
                }
            })
            .collect();
        out.sort_by_key(|n| n.number);
        out
    }

    /// Serial ports that belong to hardware (`ttyACM*`, `ttyUSB*`, and any other tty on USB or with a
    /// `/dev/serial/by-id` link), sorted by name.
    pub fn serial_ports(&self) -> Vec<SerialNode> {
        let class = Path::new("/sys/class/tty");
        let Ok(entries) = std::fs::read_dir(self.path(class)) else { return Vec::new() };
        let mut out: Vec<SerialNode> = entries
            .filter_map(|e| e.ok())
            .filter_map(|e| {
                let name = e.file_name().to_string_lossy().into_owned();
                let cdev = class.join(&name);
                let node = Path::new("/dev").join(&name);
                let usb = self.usb_identity(&cdev);
                let by_id = self.links_to(Path::new("/dev/serial/by-id"), &node);
                let usb_like = name.starts_with("ttyACM") || name.starts_with("ttyUSB");
                (usb_like || usb.is_some() || !by_id.is_empty()).then_some(SerialNode { node, by_id, usb })
            })
            .collect();
        out.sort_by(|a, b| a.node.cmp(&b.node));
        out
    }

    /// Framebuffer devices (`/sys/class/graphics/fb*`), sorted by number.
    pub fn framebuffers(&self) -> Vec<FramebufferNode> {
        let class = Path::new("/sys/class/graphics");
        let mut out: Vec<FramebufferNode> = list_class(self, class, "fb")
            .into_iter()
            .map(|(name, number)| {
                let rooted = self.path(&class.join(&name));
                let size = self.read_attr(&rooted, "virtual_size").and_then(|s| {
                    let (w, h) = s.split_once(',')?;
                    Some((w.trim().parse().ok()?, h.trim().parse().ok()?))
                });
                FramebufferNode {
                    node: Path::new("/dev").join(&name),
                    number,
                    driver: self.read_attr(&rooted, "name").unwrap_or_default(),
                    size,
                    bits_per_pixel: self.read_attr(&rooted, "bits_per_pixel").and_then(|b| b.parse().ok()),
                }
            })
            .collect();
        out.sort_by_key(|f| f.number);
        out
    }

    /// Resolve a camera selector to the absolute device node it names now.
    pub fn resolve_camera(&self, selector: &CameraSelector) -> Result<PathBuf, ResolveError> {
        let candidates = || self.video_nodes().into_iter().filter(|n| n.index == 0);
        let pick = |matches: Vec<VideoNode>| match matches.len() {
            0 => Err(ResolveError::NotFound { selector: selector.to_string() }),
            1 => Ok(matches[0].node.clone()),
            _ => Err(ResolveError::Ambiguous {
                selector: selector.to_string(),
                nodes: matches.iter().map(|n| n.node.display().to_string()).collect(),
            }),
        };
        match selector {
            CameraSelector::Path(p) => {
                if !self.path(p).exists() {
                    return Err(ResolveError::NotFound { selector: selector.to_string() });
                }
                Ok(self.follow(p))
            }
            CameraSelector::Usb { vid, pid, serial } => pick(
                candidates()
                    .filter(|n| {
                        n.usb.as_ref().is_some_and(|u| {
                            u.vid == *vid
                                && u.pid == *pid
                                && serial.as_ref().is_none_or(|s| u.serial.as_ref() == Some(s))
                        })
                    })
                    .collect(),
            ),
            CameraSelector::Bus(bus) => pick(
                candidates()
                    .filter(|n| n.usb.as_ref().and_then(|u| u.bus_info.as_deref()) == Some(bus.as_str()))
                    .collect(),
            ),
            CameraSelector::Card(card) => pick(candidates().filter(|n| n.card == *card).collect()),
        }
    }
}

/// `(entry name, number)` for the entries `PREFIXnumber` of a class directory.
fn list_class(root: &SysRoot, class: &Path, prefix: &str) -> Vec<(String, u32)> {
    let Ok(entries) = std::fs::read_dir(root.path(class)) else { return Vec::new() };
    entries
        .filter_map(|e| e.ok())
        .filter_map(|e| {
            let name = e.file_name().to_string_lossy().into_owned();
            let number = name.strip_prefix(prefix)?.parse().ok()?;
            Some((name, number))
        })
        .collect()
}

/// A path component as a name to walk (`..` kept, `.` and the root dropped).
fn component_name(c: &Component<'_>) -> Option<std::ffi::OsString> {
    match c {
        Component::Normal(n) => Some(n.to_os_string()),
        Component::ParentDir => Some("..".into()),
        _ => None,
    }
}

/// The USB identity of a device.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct UsbIdentity {
    /// Vendor id.
    pub vid: u16,
    /// Product id.
    pub pid: u16,
    /// Serial number string, when the device has one.
    pub serial: Option<String>,
    /// Manufacturer string.
    pub manufacturer: Option<String>,
    /// Product string.
    pub product: Option<String>,
    /// The USB port path (`1-1.2`): stable while the device stays in the same port.
    pub port: String,
    /// V4L2's `bus_info` for this device (`usb-0000:00:14.0-1.2`): host controller + port path.
    pub bus_info: Option<String>,
}

impl UsbIdentity {
    /// `usb:VID:PID[:SERIAL]`, the selector form used in rig files.
    pub fn selector(&self) -> String {
        match &self.serial {
            Some(s) => format!("usb:{:04x}:{:04x}:{s}", self.vid, self.pid),
            None => format!("usb:{:04x}:{:04x}", self.vid, self.pid),
        }
    }
}

/// One V4L2 device node.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct VideoNode {
    /// `/dev/videoN` (changes with plug order: do not put it in a rig file).
    pub node: PathBuf,
    /// `N`.
    pub number: u32,
    /// The driver's card name (`name` in sysfs).
    pub card: String,
    /// The node's index within its device: 0 is the capture node; UVC cameras add a metadata node 1.
    pub index: u32,
    /// `/dev/v4l/by-id/...` links to it.
    pub by_id: Vec<PathBuf>,
    /// `/dev/v4l/by-path/...` links to it.
    pub by_path: Vec<PathBuf>,
    /// The USB device, for USB cameras.
    pub usb: Option<UsbIdentity>,
}

impl VideoNode {
    /// The most stable selector for a rig file: a by-id link, else `usb:VID:PID:SERIAL`, else the
    /// bus, else the card name.
    pub fn best_selector(&self) -> String {
        if let Some(l) = self.by_id.first() {
            return l.display().to_string();
        }
        match &self.usb {
            Some(u) if u.serial.is_some() => u.selector(),
            Some(UsbIdentity { bus_info: Some(b), .. }) => format!("bus:{b}"),
            _ if !self.card.is_empty() => format!("card:{}", self.card),
            _ => self.node.display().to_string(),
        }
    }
}

/// One serial port.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SerialNode {
    /// `/dev/ttyACM0` etc.
    pub node: PathBuf,
    /// `/dev/serial/by-id/...` links to it.
    pub by_id: Vec<PathBuf>,
    /// The USB device, for USB serial adapters and boards.
    pub usb: Option<UsbIdentity>,
}

/// One framebuffer device.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FramebufferNode {
    /// `/dev/fbN`.
    pub node: PathBuf,
    /// `N`.
    pub number: u32,
    /// The driver's name (`name` in sysfs).
    pub driver: String,
    /// Virtual size in pixels (width, height).
    pub size: Option<(u32, u32)>,
    /// Bits per pixel.
    pub bits_per_pixel: Option<u32>,
}

/// How a rig file names a camera.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum CameraSelector {
    /// A device path, preferably `/dev/v4l/by-id/...` (symbolic links are followed).
    Path(PathBuf),
    /// `usb:VID:PID[:SERIAL]` (hexadecimal ids): the capture node of that USB camera.
    Usb {
        /// Vendor id.
        vid: u16,
        /// Product id.
        pid: u16,
        /// Serial number.
        serial: Option<String>,
    },
    /// `bus:usb-0000:00:14.0-1`: V4L2's bus info (the USB port the camera is in).
    Bus(String),
    /// `card:NAME`: the driver's card name, when only one such camera is connected.
    Card(String),
}

impl CameraSelector {
    /// Parse a rig file's `device`.
    pub fn parse(s: &str) -> Result<Self, SelectorError> {
        let s = s.trim();
        if s.is_empty() {
            return Err(SelectorError::Empty);
        }
        if let Some(rest) = s.strip_prefix("usb:") {
            // The serial port syntax, shared.
            return match crate::devices::serial::PortSpec::parse(s) {
                Ok(crate::devices::serial::PortSpec::Usb { vid, pid, serial }) => {
                    Ok(CameraSelector::Usb { vid, pid, serial })
                }
                _ => Err(SelectorError::BadUsb(rest.to_owned())),
            };
        }
        if let Some(rest) = s.strip_prefix("bus:") {
            return if rest.is_empty() { Err(SelectorError::Empty) } else { Ok(CameraSelector::Bus(rest.to_owned())) };
        }
        if let Some(rest) = s.strip_prefix("card:") {
            return if rest.is_empty() { Err(SelectorError::Empty) } else { Ok(CameraSelector::Card(rest.to_owned())) };
        }
        if s.starts_with('/') {
            return Ok(CameraSelector::Path(PathBuf::from(s)));
        }
        Err(SelectorError::Unknown(s.to_owned()))
    }

    /// True for a bare `/dev/videoN`, whose number changes with plug order.
    pub fn is_unstable(&self) -> bool {
        matches!(self, CameraSelector::Path(p) if p.parent() == Some(Path::new("/dev")))
    }
}

impl std::fmt::Display for CameraSelector {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            CameraSelector::Path(p) => write!(f, "{}", p.display()),
            CameraSelector::Usb { vid, pid, serial: Some(s) } => write!(f, "usb:{vid:04x}:{pid:04x}:{s}"),
            CameraSelector::Usb { vid, pid, serial: None } => write!(f, "usb:{vid:04x}:{pid:04x}"),
            CameraSelector::Bus(b) => write!(f, "bus:{b}"),
            CameraSelector::Card(c) => write!(f, "card:{c}"),
        }
    }
}

/// Why a camera selector string is not usable.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SelectorError {
    /// Empty, or a prefix with nothing after it.
    #[error("device is empty")]
    Empty,
    /// `usb:` not followed by `VID:PID[:SERIAL]`.
    #[error("`usb:{0}`: expected usb:VID:PID or usb:VID:PID:SERIAL with hexadecimal ids, e.g. usb:046d:082d")]
    BadUsb(String),
    /// None of the forms.
    #[error("`{0}`: expected /dev/v4l/by-id/..., usb:VID:PID[:SERIAL], bus:BUS_INFO or card:NAME")]
    Unknown(String),
}

/// Why a selector matched no device, or more than one.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ResolveError {
    /// Nothing matches (unplugged?).
    #[error("no camera matches `{selector}` (run `scanrig devices` to list them)")]
    NotFound {
        /// The selector.
        selector: String,
    },
    /// More than one capture node matches.
    #[error("`{selector}` matches {} cameras ({}); use a by-id path or add the serial number", nodes.len(), nodes.join(", "))]
    Ambiguous {
        /// The selector.
        selector: String,
        /// The matching nodes.
        nodes: Vec<String>,
    },
}

/// Builders of fake `/sys` + `/dev` trees, shared by the unit tests here and the tests of
/// `scanrig devices` (which build the same tree through their own code).
#[cfg(test)]
pub(crate) mod fake {
    use std::os::unix::fs::symlink;
    use std::path::Path;

    /// Write `text` to `root/rel`, creating directories.
    pub fn write(root: &Path, rel: &str, text: &str) {
        let p = root.join(rel);
        std::fs::create_dir_all(p.parent().expect("parent")).expect("mkdir");
        std::fs::write(p, text).expect("write");
    }

    /// A symbolic link `root/rel` -> `target`, creating directories.
    pub fn link(root: &Path, rel: &str, target: &str) {
        let p = root.join(rel);
        std::fs::create_dir_all(p.parent().expect("parent")).expect("mkdir");
        symlink(target, p).expect("symlink");
    }

    /// A USB camera at port `port` (e.g. `1-1`) of host controller 0000:00:14.0 with capture node
    /// `videoN` and metadata node `video{N+1}`.
    pub fn usb_camera(root: &Path, port: &str, n: u32, card: &str, vid_pid: (&str, &str), serial: Option<&str>) {
        let usbdev = format!("sys/devices/pci0000:00/0000:00:14.0/usb1/{port}");
        write(root, &format!("{usbdev}/idVendor"), &format!("{}\n", vid_pid.0));
        write(root, &format!("{usbdev}/idProduct"), &format!("{}\n", vid_pid.1));
        write(root, &format!("{usbdev}/devpath"), &format!("{}\n", port.trim_start_matches("1-")));
        if let Some(s) = serial {
            write(root, &format!("{usbdev}/serial"), &format!("{s}\n"));
        }
        write(root, &format!("{usbdev}/product"), &format!("{card}\n"));
        for (node, index) in [(n, 0), (n + 1, 1)] {
            let cdev = format!("{usbdev}/{port}:1.0/video4linux/video{node}");
            write(root, &format!("{cdev}/name"), &format!("{card}\n"));
            write(root, &format!("{cdev}/index"), &format!("{index}\n"));
            link(root, &format!("{cdev}/device"), "../..");
            link(
                root,
                &format!("sys/class/video4linux/video{node}"),
                &format!("../../{}", cdev.trim_start_matches("sys/")),
            );
            write(root, &format!("dev/video{node}"), "");
            if let Some(s) = serial {
                let id = format!("usb-{}_{}-video-index{index}", card.replace(' ', "_"), s);
                link(root, &format!("dev/v4l/by-id/{id}"), &format!("../../video{node}"));
            }
        }
    }

    /// A USB CDC serial board `ttyACMn` at port `port`.
    pub fn usb_serial(root: &Path, port: &str, n: u32, vid_pid: (&str, &str), serial: &str, product: &str) {
        let usbdev = format!("sys/devices/pci0000:00/0000:00:14.0/usb1/{port}");
        write(root, &format!("{usbdev}/idVendor"), &format!("{}\n", vid_pid.0));
        write(root, &format!("{usbdev}/idProduct"), &format!("{}\n", vid_pid.1));
        write(root, &format!("{usbdev}/devpath"), &format!("{}\n", port.trim_start_matches("1-")));
        write(root, &format!("{usbdev}/serial"), &format!("{serial}\n"));
        write(root, &format!("{usbdev}/product"), &format!("{product}\n"));
        let cdev = format!("{usbdev}/{port}:1.0/tty/ttyACM{n}");
        write(root, &format!("{cdev}/dev"), "166:0\n");
        link(root, &format!("{cdev}/device"), "../..");
        link(root, &format!("sys/class/tty/ttyACM{n}"), &format!("../../{}", cdev.trim_start_matches("sys/")));
        write(root, &format!("dev/ttyACM{n}"), "");
        let id = format!("usb-{}_{serial}-if00", product.replace(' ', "_"));
        link(root, &format!("dev/serial/by-id/{id}"), &format!("../../ttyACM{n}"));
    }

    /// A virtual console tty (no device link): not listed.
    pub fn console(root: &Path) {
        write(root, "sys/devices/virtual/tty/tty0/dev", "4:0\n");
        link(root, "sys/class/tty/tty0", "../../devices/virtual/tty/tty0");
    }

    /// A framebuffer `fbN`.
    pub fn framebuffer(root: &Path, n: u32, driver: &str, size: (u32, u32), bpp: u32) {
        let cdev = format!("sys/devices/platform/fbdev/graphics/fb{n}");
        write(root, &format!("{cdev}/name"), &format!("{driver}\n"));
        write(root, &format!("{cdev}/virtual_size"), &format!("{},{}\n", size.0, size.1));
        write(root, &format!("{cdev}/bits_per_pixel"), &format!("{bpp}\n"));
        link(root, &format!("sys/class/graphics/fb{n}"), &format!("../../{}", cdev.trim_start_matches("sys/")));
        write(root, &format!("dev/fb{n}"), "");
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tree() -> (tempfile::TempDir, SysRoot) {
        let dir = tempfile::tempdir().expect("tempdir");
        let r = dir.path();
        fake::usb_camera(r, "1-1", 0, "HD Pro Webcam C920", ("046d", "082d"), Some("ABC123"));
        fake::usb_camera(r, "1-2", 2, "USB Camera", ("0c45", "6366"), None);
        fake::usb_camera(r, "1-3", 4, "USB Camera", ("0c45", "6366"), None);
        fake::usb_serial(r, "1-4", 0, ("2e8a", "000a"), "SCANRIG-CTRL-01", "Scanrig Controller");
        fake::console(r);
        fake::framebuffer(r, 0, "simpledrmdrmfb", (1920, 1080), 32);
        let root = SysRoot::new(r);
        (dir, root)
    }

    #[test]
    fn video_nodes_carry_card_index_links_and_usb_identity() {
        let (_d, root) = tree();
        let nodes = root.video_nodes();
        assert_eq!(nodes.iter().map(|n| n.number).collect::<Vec<_>>(), vec![0, 1, 2, 3, 4, 5]);
        let c920 = &nodes[0];
        assert_eq!(c920.node, Path::new("/dev/video0"));
        assert_eq!(c920.card, "HD Pro Webcam C920");
        assert_eq!(c920.index, 0);
        assert_eq!(nodes[1].index, 1);
        assert_eq!(c920.by_id, vec![PathBuf::from("/dev/v4l/by-id/usb-HD_Pro_Webcam_C920_ABC123-video-index0")]);
        let usb = c920.usb.as_ref().expect("usb");
        assert_eq!((usb.vid, usb.pid, usb.serial.as_deref()), (0x046d, 0x082d, Some("ABC123")));
        assert_eq!(usb.bus_info.as_deref(), Some("usb-0000:00:14.0-1"));
        assert_eq!(usb.port, "1-1");
        assert_eq!(c920.best_selector(), "/dev/v4l/by-id/usb-HD_Pro_Webcam_C920_ABC123-video-index0");
        assert_eq!(nodes[2].best_selector(), "bus:usb-0000:00:14.0-2");
    }

    #[test]
    fn selectors_resolve_to_the_capture_node_or_say_why_not() {
        let (_d, root) = tree();
        let r = |s: &str| root.resolve_camera(&CameraSelector::parse(s).expect("parses"));
        assert_eq!(r("/dev/v4l/by-id/usb-HD_Pro_Webcam_C920_ABC123-video-index0"), Ok(PathBuf::from("/dev/video0")));
        assert_eq!(r("usb:046d:082d"), Ok(PathBuf::from("/dev/video0")));
        assert_eq!(r("usb:046d:082d:ABC123"), Ok(PathBuf::from("/dev/video0")));
        assert!(matches!(r("usb:046d:082d:OTHER"), Err(ResolveError::NotFound { .. })));
        assert_eq!(r("card:HD Pro Webcam C920"), Ok(PathBuf::from("/dev/video0")));
        assert_eq!(r("bus:usb-0000:00:14.0-3"), Ok(PathBuf::from("/dev/video4")));
        let e = r("card:USB Camera").expect_err("two of them");
        assert_eq!(
            e,
            ResolveError::Ambiguous {
                selector: "card:USB Camera".into(),
                nodes: vec!["/dev/video2".into(), "/dev/video4".into()]
            }
        );
        assert!(matches!(r("/dev/v4l/by-id/missing"), Err(ResolveError::NotFound { .. })));
        assert_eq!(r("/dev/video2"), Ok(PathBuf::from("/dev/video2")));
        assert!(CameraSelector::parse("/dev/video2").expect("path").is_unstable());
    }

    #[test]
    fn selector_parsing_errors() {
        assert_eq!(CameraSelector::parse(""), Err(SelectorError::Empty));
        assert_eq!(CameraSelector::parse("card:"), Err(SelectorError::Empty));
        assert!(matches!(CameraSelector::parse("usb:zz:1"), Err(SelectorError::BadUsb(_))));
        assert!(matches!(CameraSelector::parse("video0"), Err(SelectorError::Unknown(_))));
        for s in ["usb:046d:082d:ABC", "usb:046d:082d", "bus:usb-0000:00:14.0-1", "card:X Y", "/dev/v4l/by-id/a"] {
            assert_eq!(CameraSelector::parse(s).expect("parses").to_string(), s);
        }
    }

    #[test]
    fn serial_ports_and_framebuffers() {
        let (_d, root) = tree();
        let ports = root.serial_ports();
        assert_eq!(ports.len(), 1, "{ports:?}");
        assert_eq!(ports[0].node, Path::new("/dev/ttyACM0"));
        assert_eq!(
            ports[0].by_id,
            vec![PathBuf::from("/dev/serial/by-id/usb-Scanrig_Controller_SCANRIG-CTRL-01-if00")]
        );
        let usb = ports[0].usb.as_ref().expect("usb");
        assert_eq!(usb.selector(), "usb:2e8a:000a:SCANRIG-CTRL-01");
        let spec = crate::devices::serial::PortSpec::parse(&usb.selector()).expect("a valid port");
        assert!(matches!(spec, crate::devices::serial::PortSpec::Usb { vid: 0x2e8a, pid: 0x000a, .. }));
        let fbs = root.framebuffers();
        assert_eq!(fbs.len(), 1);
        assert_eq!((fbs[0].size, fbs[0].bits_per_pixel), (Some((1920, 1080)), Some(32)));
    }

    #[test]
    fn an_empty_root_lists_nothing() {
        let dir = tempfile::tempdir().expect("tempdir");
        let root = SysRoot::new(dir.path());
        assert!(root.video_nodes().is_empty() && root.serial_ports().is_empty() && root.framebuffers().is_empty());
    }
}

//! A projector on a video output driven as a Linux framebuffer device (`/dev/fbN`, cargo feature
//! `fbdev`): no desktop, no compositor. Patterns are packed into the framebuffer's pixel layout
//! ([`framebuffer`](super::framebuffer)) and written with positioned writes; `show` then waits for
//! vertical blank where the driver supports it and reports when the pattern is on screen, including
//! the projector's own latency.
//!
//! On a KMS system the framebuffer is the DRM driver's emulation (`drm_kms_helper.fbdev_emulation`,
//! on by default); the projector should be the only output on that card, or mirrored.

use std::fs::{File, OpenOptions};
use std::os::fd::AsRawFd;
use std::os::unix::fs::FileExt;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use super::framebuffer::{frame_period, visible_at, Channel, FbLayout};
use super::Pattern;
use crate::config::FbdevProjectorConfig;
use crate::devices::DeviceError;

const NAME: &str = "projector";

/// `struct fb_bitfield` (linux/fb.h).
#[repr(C)]
#[derive(Debug, Default, Clone, Copy)]
struct FbBitfield {
    offset: u32,
    length: u32,
    msb_right: u32,
}

/// `struct fb_var_screeninfo` (linux/fb.h).
#[repr(C)]
#[derive(Debug, Default, Clone, Copy)]
struct FbVarScreeninfo {
    xres: u32,
    yres: u32,
    xres_virtual: u32,
    yres_virtual: u32,
    xoffset: u32,
    yoffset: u32,
    bits_per_pixel: u32,
    grayscale: u32,
    red: FbBitfield,
    green: FbBitfield,
    blue: FbBitfield,
    transp: FbBitfield,
    nonstd: u32,
    activate: u32,
    height: u32,
    width: u32,
    accel_flags: u32,
    pixclock: u32,
    left_margin: u32,
    right_margin: u32,
    upper_margin: u32,
    lower_margin: u32,
    hsync_len: u32,
    vsync_len: u32,
    sync: u32,
    vmode: u32,
    rotate: u32,
    colorspace: u32,
    reserved: [u32; 4],
}

/// `struct fb_fix_screeninfo` (linux/fb.h).
#[repr(C)]
#[derive(Debug, Default, Clone, Copy)]
struct FbFixScreeninfo {
    id: [u8; 16],
    smem_start: libc::c_ulong,
    smem_len: u32,
    type_: u32,
    type_aux: u32,
    visual: u32,
    xpanstep: u16,
    ypanstep: u16,
    ywrapstep: u16,
    line_length: u32,
    mmio_start: libc::c_ulong,
    mmio_len: u32,
    accel: u32,
    capabilities: u16,
    reserved: [u16; 2],
}

const FBIOGET_VSCREENINFO: libc::c_ulong = 0x4600;
const FBIOGET_FSCREENINFO: libc::c_ulong = 0x4602;
/// `_IOW('F', 0x20, __u32)`.
const FBIO_WAITFORVSYNC: libc::c_ulong = 0x4004_4620;
/// `FB_VISUAL_TRUECOLOR`.
const FB_VISUAL_TRUECOLOR: u32 = 2;

fn ioctl_read<T: Default>(file: &File, request: libc::c_ulong) -> std::io::Result<T> {
    let mut out = T::default();
    // SAFETY: `request` is one of the FBIOGET_* requests whose argument is a pointer to the
    // `#[repr(C)]` struct `T` mirrors; the kernel writes at most `size_of::<T>()` bytes into it.
    let rc = unsafe { libc::ioctl(file.as_raw_fd(), request as _, &mut out as *mut T) };
    if rc < 0 {
        return Err(std::io::Error::last_os_error());
    }
    Ok(out)
}

/// A projector on a framebuffer device.
#[derive(Debug)]
pub struct FbdevProjector {
    file: File,
    path: PathBuf,
    layout: FbLayout,
    period: Duration,
    latency: Duration,
    vsync: bool,
    row: Vec<u8>,
}

impl FbdevProjector {
    /// Open `config.device`, read its mode and check it against the configured size.
    pub fn open(config: &FbdevProjectorConfig) -> Result<Self, DeviceError> {
        let path = PathBuf::from(&config.device);
        let file = OpenOptions::new().read(true).write(true).open(&path).map_err(|source| match source.kind() {
            std::io::ErrorKind::NotFound => DeviceError::Disconnected { device: NAME.into(), source: Some(source) },
            _ => DeviceError::Io { device: NAME.into(), source },
        })?;
        let io = |source| DeviceError::Io { device: NAME.into(), source };
        let var: FbVarScreeninfo = ioctl_read(&file, FBIOGET_VSCREENINFO).map_err(io)?;
        let fix: FbFixScreeninfo = ioctl_read(&file, FBIOGET_FSCREENINFO).map_err(io)?;
        if fix.visual != FB_VISUAL_TRUECOLOR {
            return Err(DeviceError::InvalidConfig {
                device: NAME.into(),
                field: "device",
                problem: format!("{} is not a true-colour framebuffer (visual {})", path.display(), fix.visual),
            });
        }
        let channel = |b: FbBitfield| Channel { offset: b.offset, length: b.length };
        let bytes = var.bits_per_pixel as u64 / 8;
        let layout = FbLayout {
            width: var.xres,
            height: var.yres,
            line_length: fix.line_length,
            bits_per_pixel: var.bits_per_pixel,
            red: channel(var.red),
            green: channel(var.green),
            blue: channel(var.blue),
            origin: var.yoffset as u64 * fix.line_length as u64 + var.xoffset as u64 * bytes,
        };
        let period = frame_period(
            var.pixclock,
            var.xres + var.left_margin + var.right_margin + var.hsync_len,
            var.yres + var.upper_margin + var.lower_margin + var.vsync_len,
        )
        .unwrap_or_else(|| Duration::from_secs_f64(1.0 / config.refresh_hz));
        let p = Self::with_layout(file, path, layout, period, Duration::from_millis(config.latency_ms))?;
        if (p.layout.width, p.layout.height) != (config.width, config.height) {
            return Err(DeviceError::InvalidConfig {
                device: NAME.into(),
                field: "width",
                problem: format!(
                    "{} shows {}x{}, the rig file says {}x{}",
                    p.path.display(),
                    p.layout.width,
                    p.layout.height,
                    config.width,
                    config.height
                ),
            });
        }
        tracing::info!(device = %p.path.display(), width = layout.width, height = layout.height,
            bpp = layout.bits_per_pixel, period_ms = period.as_secs_f64() * 1e3, "framebuffer projector");
        Ok(p)
    }

    /// A projector writing into `file` (a framebuffer device, or any file in tests) with a known
    /// layout, refresh period and projector latency.
    pub fn with_layout(
        file: File,
        path: PathBuf,
        layout: FbLayout,
        period: Duration,
        latency: Duration,
    ) -> Result<Self, DeviceError> {
        layout.check().map_err(|e| DeviceError::InvalidConfig {
            device: NAME.into(),
            field: "device",
            problem: format!("{}: {e}", path.display()),
        })?;
        let row = vec![0u8; layout.line_length as usize];
        Ok(FbdevProjector { file, path, layout, period, latency, vsync: true, row })
    }

    fn write_pattern(&mut self, pattern: &Pattern) -> Result<(), DeviceError> {
        self.layout.check_pattern(pattern).map_err(|e| DeviceError::InvalidConfig {
            device: NAME.into(),
            field: "pattern",
            problem: e.to_string(),
        })?;
        let used = self.layout.width as usize * self.layout.bytes_per_pixel();
        for y in 0..self.layout.height {
            self.layout.pack_row(pattern, y, &mut self.row);
            let at = self.layout.origin + y as u64 * self.layout.line_length as u64;
            self.file.write_all_at(&self.row[..used], at).map_err(|source| match source.raw_os_error() {
                Some(libc::ENODEV) | Some(libc::ENXIO) => {
                    DeviceError::Disconnected { device: NAME.into(), source: Some(source) }
                }
                _ => DeviceError::Io { device: NAME.into(), source },
            })?;
        }
        Ok(())
    }

    /// Wait for the next vertical blank; `None` when the driver cannot (then it is not asked again).
    fn wait_vsync(&mut self) -> Option<Instant> {
        if !self.vsync {
            return None;
        }
        let mut crtc: u32 = 0;
        // SAFETY: FBIO_WAITFORVSYNC takes a pointer to a u32 CRTC index, which it only reads.
        let rc = unsafe { libc::ioctl(self.file.as_raw_fd(), FBIO_WAITFORVSYNC as _, &mut crtc as *mut u32) };
        if rc < 0 {
            tracing::debug!(error = %std::io::Error::last_os_error(), "no vsync wait; assuming one frame period");
            self.vsync = false;
            return None;
        }
        Some(Instant::now())
    }
}

impl super::Projector for FbdevProjector {
    fn resolution(&self) -> (u32, u32) {
        (self.layout.width, self.layout.height)
    }

    fn show(&mut self, pattern: &Pattern, timeout: Duration) -> Result<Instant, DeviceError> {
        let start = Instant::now();
        self.write_pattern(pattern)?;
        let written = Instant::now();
        let vsync = self.wait_vsync();
        let at = visible_at(written, vsync, self.period, self.latency);
        // Sleep until it is on screen, so the caller's next frame is exposed after it.
        if at > start + timeout {
            return Err(DeviceError::Timeout { device: NAME.into(), waiting_for: "the pattern on screen", timeout });
        }
        let now = Instant::now();
        if at > now {
            std::thread::sleep(at - now);
        }
        Ok(at)
    }

    fn blank(&mut self, timeout: Duration) -> Result<(), DeviceError> {
        let black = Pattern::uniform(self.layout.width, self.layout.height, [0, 0, 0]);
        self.show(&black, timeout).map(|_| ())
    }
}

#[cfg(test)]
mod tests {
    use super::super::Projector;
    use super::*;

    #[test]
    fn patterns_land_at_the_panned_origin_in_the_device_layout() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("fb");
        std::fs::write(&path, vec![0xAAu8; 4096]).expect("file");
        let file = OpenOptions::new().read(true).write(true).open(&path).expect("open");
        let layout = FbLayout {
            width: 3,
            height: 2,
            line_length: 16,
            bits_per_pixel: 32,
            red: Channel { offset: 16, length: 8 },
            green: Channel { offset: 8, length: 8 },
            blue: Channel { offset: 0, length: 8 },
            origin: 32,
        };
        let mut p = FbdevProjector::with_layout(file, path.clone(), layout, Duration::from_millis(1), Duration::ZERO)
            .expect("projector");
        let before = Instant::now();
        let at = p.show(&Pattern::uniform(3, 2, [1, 2, 3]), Duration::from_secs(1)).expect("show");
        assert!(at >= before + Duration::from_millis(1), "a regular file has no vsync: one period");
        let bytes = std::fs::read(&path).expect("read");
        assert!(bytes[..32].iter().all(|&b| b == 0xAA), "before the origin untouched");
        assert_eq!(&bytes[32..44], &[3, 2, 1, 0, 3, 2, 1, 0, 3, 2, 1, 0]);
        assert!(bytes[44..48].iter().all(|&b| b == 0xAA), "row padding untouched");
        assert_eq!(&bytes[48..52], &[3, 2, 1, 0]);
        let e = p.show(&Pattern::uniform(4, 2, [0; 3]), Duration::from_secs(1)).expect_err("size");
        assert_eq!(e.kind(), crate::devices::ErrorKind::InvalidConfig);
        p.blank(Duration::from_secs(1)).expect("blank");
        assert_eq!(&std::fs::read(&path).expect("read")[32..44], &[0; 12]);
    }

    #[test]
    fn a_missing_device_is_disconnected() {
        let config = FbdevProjectorConfig {
            device: "/nonexistent/fb9".into(),
            width: 640,
            height: 480,
            latency_ms: 0,
            refresh_hz: 60.0,
            calibration: None,
            procam: None,
        };
        let e = FbdevProjector::open(&config).expect_err("absent");
        assert_eq!(e.kind(), crate::devices::ErrorKind::Disconnected);
    }
}

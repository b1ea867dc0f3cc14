//! Kinect v1 depth camera through libfreenect (cargo feature `freenect`, Debian package
//! `libfreenect-dev`): a small hand-written binding over the C API's asynchronous interface, so
//! every wait honours its timeout (`freenect_process_events_timeout`), unlike the library's
//! blocking `sync` wrapper.
//!
//! Depth comes in millimetres (`FREENECT_DEPTH_MM`, or `FREENECT_DEPTH_REGISTERED` aligned to the RGB
//! camera), 640x480, 0 where nothing was measured, and is handed on in metres. With
//! `depth_format = "disparity"` the driver takes the raw 11-bit disparity (`FREENECT_DEPTH_11BIT`)
//! and converts it itself ([`kinect`](super::kinect)); that is the only format fakenect replays.

use std::ffi::{c_char, c_int, c_void, CStr, CString};
use std::time::{Duration, Instant};

use crate::config::FreenectDepthConfig;
use crate::devices::camera::stream::SequenceTracker;
use crate::devices::DeviceError;

const NAME: &str = "depth_camera";
const WIDTH: usize = FreenectDepthConfig::WIDTH as usize;
const HEIGHT: usize = FreenectDepthConfig::HEIGHT as usize;
/// The Kinect's depth frame period (30 Hz).
const PERIOD: Duration = Duration::from_micros(33_333);

#[repr(C)]
struct FreenectContext {
    _private: [u8; 0],
}

#[repr(C)]
struct FreenectDevice {
    _private: [u8; 0],
}

/// `struct freenect_device_attributes`.
#[repr(C)]
struct DeviceAttributes {
    next: *mut DeviceAttributes,
    camera_serial: *const c_char,
}

/// `freenect_frame_mode`, passed by value.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
struct FrameMode {
    reserved: u32,
    resolution: c_int,
    format: i32,
    bytes: i32,
    width: i16,
    height: i16,
    data_bits_per_pixel: i8,
    padding_bits_per_pixel: i8,
    framerate: i8,
    is_valid: i8,
}

const FREENECT_DEVICE_CAMERA: c_int = 0x02;
const FREENECT_RESOLUTION_MEDIUM: c_int = 1;
const FREENECT_DEPTH_11BIT: c_int = 0;
const FREENECT_DEPTH_REGISTERED: c_int = 4;
const FREENECT_DEPTH_MM: c_int = 5;

type DepthCallback = extern "C" fn(dev: *mut FreenectDevice, depth: *mut c_void, timestamp: u32);

#[link(name = "freenect")]
extern "C" {
    fn freenect_init(ctx: *mut *mut FreenectContext, usb_ctx: *mut c_void) -> c_int;
    fn freenect_shutdown(ctx: *mut FreenectContext) -> c_int;
    fn freenect_select_subdevices(ctx: *mut FreenectContext, subdevs: c_int);
    fn freenect_open_device(ctx: *mut FreenectContext, dev: *mut *mut FreenectDevice, index: c_int) -> c_int;
    fn freenect_open_device_by_camera_serial(
        ctx: *mut FreenectContext,
        dev: *mut *mut FreenectDevice,
        serial: *const c_char,
    ) -> c_int;
    fn freenect_close_device(dev: *mut FreenectDevice) -> c_int;
    fn freenect_set_user(dev: *mut FreenectDevice, user: *mut c_void);
    fn freenect_get_user(dev: *mut FreenectDevice) -> *mut c_void;
    fn freenect_set_depth_callback(dev: *mut FreenectDevice, cb: DepthCallback);
    fn freenect_find_depth_mode(res: c_int, fmt: c_int) -> FrameMode;
    fn freenect_set_depth_mode(dev: *mut FreenectDevice, mode: FrameMode) -> c_int;
    fn freenect_start_depth(dev: *mut FreenectDevice) -> c_int;
    fn freenect_stop_depth(dev: *mut FreenectDevice) -> c_int;
    fn freenect_process_events_timeout(ctx: *mut FreenectContext, timeout: *mut libc::timeval) -> c_int;
}

/// Written by the depth callback, read by `capture_depth`; both run on the thread that calls
/// `freenect_process_events_timeout`.
#[derive(Debug, Default)]
struct Latest {
    /// Depth, millimetres (or raw disparity in disparity mode).
    depth_mm: Vec<u16>,
    received: Option<Instant>,
    /// Frames delivered by the library, including ones replaced before being taken.
    count: u32,
}

extern "C" fn on_depth(dev: *mut FreenectDevice, depth: *mut c_void, _timestamp: u32) {
    // SAFETY: the user pointer was set in `open` to the `Latest` boxed in the camera, which outlives
    // the device (the device is closed in `Drop` before the box is freed); the callback runs inside
    // `freenect_process_events_timeout`, called with `&mut self`, so nothing else touches it.
    let latest = unsafe { &mut *(freenect_get_user(dev) as *mut Latest) };
    if depth.is_null() {
        return;
    }
    // SAFETY: in FREENECT_DEPTH_MM / REGISTERED / 11BIT mode at medium resolution the library hands a
    // buffer of 640 x 480 u16 valid for the duration of the callback.
    let frame = unsafe { std::slice::from_raw_parts(depth as *const u16, WIDTH * HEIGHT) };
    latest.depth_mm.clear();
    latest.depth_mm.extend_from_slice(frame);
    latest.received = Some(Instant::now());
    latest.count = latest.count.wrapping_add(1);
}

/// An initialised libfreenect context, shut down on drop.
struct Context(*mut FreenectContext);

impl Context {
    fn new() -> Result<Self, DeviceError> {
        let mut ctx = std::ptr::null_mut();
        // SAFETY: freenect_init writes a context pointer; a null USB context asks it to make its own.
        let rc = unsafe { freenect_init(&mut ctx, std::ptr::null_mut()) };
        if rc < 0 || ctx.is_null() {
            return Err(DeviceError::Hardware {
                device: NAME.into(),
                code: 0,
                detail: format!("freenect_init failed ({rc})"),
            });
        }
        // SAFETY: a valid context; only the camera subdevice is wanted (no motor, no audio firmware).
        unsafe { freenect_select_subdevices(ctx, FREENECT_DEVICE_CAMERA) };
        Ok(Context(ctx))
    }
}

impl Drop for Context {
    fn drop(&mut self) {
        // SAFETY: the context was created by freenect_init and every device on it is closed by now.
        unsafe { freenect_shutdown(self.0) };
    }
}

type ListAttributes = unsafe extern "C" fn(ctx: *mut FreenectContext, list: *mut *mut DeviceAttributes) -> c_int;
type FreeAttributes = unsafe extern "C" fn(list: *mut DeviceAttributes);

/// A libfreenect function looked up at run time: the device listing is missing from some builds of
/// the library (fakenect's replay library has none), and a binary linked against it directly would
/// not even start there.
fn optional_symbol(name: &CStr) -> Option<*mut c_void> {
    // SAFETY: dlsym with RTLD_DEFAULT and a NUL-terminated name only looks the symbol up.
    let p = unsafe { libc::dlsym(libc::RTLD_DEFAULT, name.as_ptr()) };
    (!p.is_null()).then_some(p)
}

/// The camera serial numbers of the Kinects connected, for `scanrig devices`.
pub fn list_serials() -> Result<Vec<String>, DeviceError> {
    let missing = || DeviceError::Unsupported {
        device: NAME.into(),
        operation: "listing Kinects (this libfreenect has no device list)",
    };
    let list_fn = optional_symbol(c"freenect_list_device_attributes").ok_or_else(missing)?;
    let free_fn = optional_symbol(c"freenect_free_device_attributes").ok_or_else(missing)?;
    // SAFETY: the symbols are libfreenect's functions of these signatures (libfreenect.h).
    let (list_fn, free_fn) = unsafe {
        (
            std::mem::transmute::<*mut c_void, ListAttributes>(list_fn),
            std::mem::transmute::<*mut c_void, FreeAttributes>(free_fn),
        )
    };
    let ctx = Context::new()?;
    let mut list = std::ptr::null_mut();
    // SAFETY: a valid context; the list is freed below with the matching call.
    let n = unsafe { list_fn(ctx.0, &mut list) };
    let mut out = Vec::new();
    let mut cur = list;
    while !cur.is_null() {
        // SAFETY: `cur` is a node of the list libfreenect allocated; its serial is a C string or null.
        let node = unsafe { &*cur };
        if !node.camera_serial.is_null() {
            // SAFETY: non-null, NUL-terminated by libfreenect.
            out.push(unsafe { CStr::from_ptr(node.camera_serial) }.to_string_lossy().into_owned());
        }
        cur = node.next;
    }
    if !list.is_null() {
        // SAFETY: the list returned above, freed once.
        unsafe { free_fn(list) };
    }
    if n < 0 {
        return Err(DeviceError::Hardware {
            device: NAME.into(),
            code: 0,
            detail: format!("listing Kinects failed ({n})"),
        });
    }
    Ok(out)
}

/// A Kinect v1 streaming depth.
pub struct FreenectDepthCamera {
    // Field order: the device is closed in Drop before the context goes.
    device: *mut FreenectDevice,
    latest: Box<Latest>,
    tracker: SequenceTracker,
    disparity: bool,
    context: Context,
}

// SAFETY: the context and device are only used through `&mut self`, i.e. from one thread at a time;
// libfreenect keeps no thread-local state for them.
unsafe impl Send for FreenectDepthCamera {}

impl std::fmt::Debug for FreenectDepthCamera {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FreenectDepthCamera")
            .field("delivered", &self.tracker.delivered())
            .field("dropped", &self.tracker.dropped())
            .finish_non_exhaustive()
    }
}

impl FreenectDepthCamera {
    /// Open the Kinect with `config.serial` (or the first) and start its depth stream.
    pub fn open(config: &FreenectDepthConfig) -> Result<Self, DeviceError> {
        let context = Context::new()?;
        let mut device = std::ptr::null_mut();
        let rc = match &config.serial {
            Some(s) => {
                let c = CString::new(s.as_str()).map_err(|_| DeviceError::InvalidConfig {
                    device: NAME.into(),
                    field: "serial",
                    problem: "contains a NUL byte".into(),
                })?;
                // SAFETY: valid context, out pointer, NUL-terminated serial.
                unsafe { freenect_open_device_by_camera_serial(context.0, &mut device, c.as_ptr()) }
            }
            // SAFETY: valid context and out pointer.
            None => unsafe { freenect_open_device(context.0, &mut device, 0) },
        };
        if rc < 0 || device.is_null() {
            let what =
                config.serial.as_deref().map_or_else(|| "the first Kinect".to_owned(), |s| format!("Kinect {s}"));
            return Err(DeviceError::Disconnected {
                device: NAME.into(),
                source: Some(std::io::Error::new(std::io::ErrorKind::NotFound, format!("cannot open {what} ({rc})"))),
            });
        }
        let disparity = config.depth_format == super::kinect::FreenectDepthFormat::Disparity;
        let mut cam =
            FreenectDepthCamera { device, latest: Box::default(), tracker: SequenceTracker::new(), disparity, context };
        let format = match (disparity, config.registered) {
            (true, _) => FREENECT_DEPTH_11BIT,
            (false, true) => FREENECT_DEPTH_REGISTERED,
            (false, false) => FREENECT_DEPTH_MM,
        };
        // SAFETY: the device is open; the user pointer is the boxed `Latest`, which lives as long as
        // the device (see Drop); the callback only runs inside process_events on this thread.
        let rc = unsafe {
            freenect_set_user(cam.device, &mut *cam.latest as *mut Latest as *mut c_void);
            freenect_set_depth_callback(cam.device, on_depth);
            let mode = freenect_find_depth_mode(FREENECT_RESOLUTION_MEDIUM, format);
            if mode.is_valid == 0 || mode.width as usize != WIDTH || mode.height as usize != HEIGHT {
                -1000
            } else {
                let rc = freenect_set_depth_mode(cam.device, mode);
                if rc < 0 {
                    rc
                } else {
                    freenect_start_depth(cam.device)
                }
            }
        };
        if rc < 0 {
            return Err(DeviceError::Hardware {
                device: NAME.into(),
                code: rc.unsigned_abs().min(u16::MAX as u32) as u16,
                detail: format!(
                    "cannot start the 640x480 {} depth stream",
                    if disparity { "disparity" } else { "millimetre" }
                ),
            });
        }
        Ok(cam)
    }
}

/// Millimetres (0 = no measurement) to metres.
pub fn mm_to_m(depth_mm: &[u16]) -> Vec<f32> {
    depth_mm.iter().map(|&d| d as f32 * 0.001).collect()
}

impl super::DepthCamera for FreenectDepthCamera {
    fn resolution(&self) -> (u32, u32) {
        (WIDTH as u32, HEIGHT as u32)
    }

    fn capture_depth(&mut self, timeout: Duration) -> Result<super::DepthFrame, DeviceError> {
        let deadline = Instant::now() + timeout;
        // Only a frame delivered from now on: an older one may predate the caller's last change.
        self.latest.received = None;
        loop {
            if let Some(received) = self.latest.received.take() {
                let step = self.tracker.observe(self.latest.count);
                // The frame was exposed before it arrived: at most a frame period for exposure and
                // one for transfer.
                let exposure_start = received.checked_sub(2 * PERIOD).unwrap_or(received);
                return Ok(super::DepthFrame {
                    sequence: step.sequence,
                    exposure_start,
                    width: WIDTH as u32,
                    height: HEIGHT as u32,
                    depth_m: if self.disparity {
                        self.latest.depth_mm.iter().map(|&d| super::kinect::disparity_to_m(d & 0x7ff)).collect()
                    } else {
                        mm_to_m(&self.latest.depth_mm)
                    },
                });
            }
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Err(DeviceError::Timeout { device: NAME.into(), waiting_for: "a depth frame", timeout });
            }
            let slice = left.min(Duration::from_millis(100));
            let mut tv = libc::timeval {
                tv_sec: slice.as_secs() as libc::time_t,
                tv_usec: slice.subsec_micros() as libc::suseconds_t,
            };
            // SAFETY: a valid context; the callback it may run writes only `self.latest`.
            let rc = unsafe { freenect_process_events_timeout(self.context.0, &mut tv) };
            if rc < 0 {
                return Err(DeviceError::Disconnected {
                    device: NAME.into(),
                    source: Some(std::io::Error::other(format!("libusb error {rc} while streaming"))),
                });
            }
        }
    }
}

impl Drop for FreenectDepthCamera {
    fn drop(&mut self) {
        // SAFETY: the device is open; after closing it no callback can run, so the boxed `Latest`
        // may go. The context is shut down after this, when its field drops.
        unsafe {
            freenect_stop_depth(self.device);
            freenect_close_device(self.device);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn millimetres_become_metres_and_zero_stays_missing() {
        assert_eq!(mm_to_m(&[0, 1000, 2500]), vec![0.0, 1.0, 2.5]);
    }

    #[test]
    fn the_frame_mode_struct_matches_the_c_layout() {
        // freenect_frame_mode: u32, enum, union(int32), int32, 2 x int16, 4 x int8 = 24 bytes.
        assert_eq!(std::mem::size_of::<FrameMode>(), 24);
        // SAFETY: a pure lookup in libfreenect's static mode table.
        let mode = unsafe { freenect_find_depth_mode(FREENECT_RESOLUTION_MEDIUM, FREENECT_DEPTH_MM) };
        assert_eq!((mode.is_valid, mode.width, mode.height), (1, 640, 480));
        assert_eq!(mode.bytes, 640 * 480 * 2);
    }
}

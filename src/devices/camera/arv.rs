//! A small binding to the C library Aravis 0.8 (`libaravis-0.8`, GenICam over GigE Vision and USB3
//! Vision): the two dozen calls the [`genicam`](super::genicam) driver and `scanrig devices` use,
//! with safe wrappers that turn `GError`s into [`ArvError`]s and own the GObjects they return.
//!
//! A binding of our own instead of the `aravis` crate: that crate pulls in the whole glib / gobject
//! binding stack (a long build on a small machine) and tracks Aravis releases through version
//! features; these calls exist unchanged since Aravis 0.8.0, so this links against any 0.8 library
//! (Debian's is 0.8.26) and needs no build script (the library names are fixed by the 0.8 ABI).

use std::ffi::{c_char, c_double, c_int, c_uint, c_void, CStr, CString};
use std::ptr::NonNull;
use std::time::Duration;

#[repr(C)]
struct GError {
    domain: u32,
    code: c_int,
    message: *mut c_char,
}

/// Opaque `ArvCamera`.
#[repr(C)]
struct ArvCameraRaw {
    _private: [u8; 0],
}
/// Opaque `ArvStream`.
#[repr(C)]
struct ArvStreamRaw {
    _private: [u8; 0],
}
/// Opaque `ArvBuffer`.
#[repr(C)]
struct ArvBufferRaw {
    _private: [u8; 0],
}

type GErrorOut = *mut *mut GError;

#[link(name = "aravis-0.8")]
extern "C" {
    fn arv_device_error_quark() -> u32;
    fn arv_update_device_list();
    fn arv_get_n_devices() -> c_uint;
    fn arv_get_device_id(index: c_uint) -> *const c_char;
    fn arv_get_device_vendor(index: c_uint) -> *const c_char;
    fn arv_get_device_model(index: c_uint) -> *const c_char;
    fn arv_get_device_serial_nbr(index: c_uint) -> *const c_char;
    fn arv_get_device_protocol(index: c_uint) -> *const c_char;
    fn arv_get_device_address(index: c_uint) -> *const c_char;

    fn arv_camera_new(name: *const c_char, error: GErrorOut) -> *mut ArvCameraRaw;
    fn arv_camera_get_vendor_name(camera: *mut ArvCameraRaw, error: GErrorOut) -> *const c_char;
    fn arv_camera_get_model_name(camera: *mut ArvCameraRaw, error: GErrorOut) -> *const c_char;
    fn arv_camera_get_device_serial_number(camera: *mut ArvCameraRaw, error: GErrorOut) -> *const c_char;
    fn arv_camera_set_region(camera: *mut ArvCameraRaw, x: c_int, y: c_int, w: c_int, h: c_int, error: GErrorOut);
    fn arv_camera_get_region(
        camera: *mut ArvCameraRaw,
        x: *mut c_int,
        y: *mut c_int,
        w: *mut c_int,
        h: *mut c_int,
        error: GErrorOut,
    );
    fn arv_camera_set_pixel_format_from_string(camera: *mut ArvCameraRaw, format: *const c_char, error: GErrorOut);
    fn arv_camera_get_pixel_format_as_string(camera: *mut ArvCameraRaw, error: GErrorOut) -> *const c_char;
    fn arv_camera_set_acquisition_mode(camera: *mut ArvCameraRaw, mode: c_int, error: GErrorOut);
    fn arv_camera_set_frame_rate(camera: *mut ArvCameraRaw, rate: c_double, error: GErrorOut);
    fn arv_camera_get_frame_rate(camera: *mut ArvCameraRaw, error: GErrorOut) -> c_double;
    fn arv_camera_set_exposure_time(camera: *mut ArvCameraRaw, us: c_double, error: GErrorOut);
    fn arv_camera_get_exposure_time(camera: *mut ArvCameraRaw, error: GErrorOut) -> c_double;
    fn arv_camera_set_gain(camera: *mut ArvCameraRaw, gain: c_double, error: GErrorOut);
    fn arv_camera_get_gain(camera: *mut ArvCameraRaw, error: GErrorOut) -> c_double;
    fn arv_camera_is_feature_available(camera: *mut ArvCameraRaw, feature: *const c_char, error: GErrorOut) -> c_int;
    fn arv_camera_set_string(camera: *mut ArvCameraRaw, feature: *const c_char, value: *const c_char, error: GErrorOut);
    fn arv_camera_get_string(camera: *mut ArvCameraRaw, feature: *const c_char, error: GErrorOut) -> *const c_char;
    fn arv_camera_set_float(camera: *mut ArvCameraRaw, feature: *const c_char, value: c_double, error: GErrorOut);
    fn arv_camera_get_float(camera: *mut ArvCameraRaw, feature: *const c_char, error: GErrorOut) -> c_double;
    fn arv_camera_get_integer(camera: *mut ArvCameraRaw, feature: *const c_char, error: GErrorOut) -> i64;
    fn arv_camera_execute_command(camera: *mut ArvCameraRaw, feature: *const c_char, error: GErrorOut);
    fn arv_camera_get_payload(camera: *mut ArvCameraRaw, error: GErrorOut) -> c_uint;
    fn arv_camera_create_stream(
        camera: *mut ArvCameraRaw,
        callback: *mut c_void,
        user_data: *mut c_void,
        error: GErrorOut,
    ) -> *mut ArvStreamRaw;
    fn arv_camera_start_acquisition(camera: *mut ArvCameraRaw, error: GErrorOut);
    fn arv_camera_stop_acquisition(camera: *mut ArvCameraRaw, error: GErrorOut);

    fn arv_stream_push_buffer(stream: *mut ArvStreamRaw, buffer: *mut ArvBufferRaw);
    fn arv_stream_timeout_pop_buffer(stream: *mut ArvStreamRaw, timeout_us: u64) -> *mut ArvBufferRaw;
    fn arv_stream_try_pop_buffer(stream: *mut ArvStreamRaw) -> *mut ArvBufferRaw;
    fn arv_stream_get_statistics(
        stream: *mut ArvStreamRaw,
        completed: *mut u64,
        failures: *mut u64,
        underruns: *mut u64,
    );

    fn arv_buffer_new(size: usize, preallocated: *mut c_void) -> *mut ArvBufferRaw;
    fn arv_buffer_get_status(buffer: *mut ArvBufferRaw) -> c_int;
    fn arv_buffer_get_data(buffer: *mut ArvBufferRaw, size: *mut usize) -> *const c_void;
    fn arv_buffer_get_system_timestamp(buffer: *mut ArvBufferRaw) -> u64;
    fn arv_buffer_get_frame_id(buffer: *mut ArvBufferRaw) -> u64;
    fn arv_buffer_get_image_width(buffer: *mut ArvBufferRaw) -> c_int;
    fn arv_buffer_get_image_height(buffer: *mut ArvBufferRaw) -> c_int;
}

#[link(name = "gobject-2.0")]
extern "C" {
    fn g_object_unref(object: *mut c_void);
}

#[link(name = "glib-2.0")]
extern "C" {
    fn g_error_free(error: *mut GError);
}

/// An error reported by Aravis (a `GError`): whether it is an `ArvDeviceError`, its code, and its
/// message.
#[derive(Debug, Clone, thiserror::Error)]
#[error("{message} (Aravis error {code})")]
pub struct ArvError {
    /// The error is in the `ArvDeviceError` domain (the device or its transport), not the GenICam
    /// or another domain.
    pub device_domain: bool,
    /// The `GError` code within its domain.
    pub code: i32,
    /// The library's text.
    pub message: String,
}

/// `ArvDeviceError` codes that mean the device cannot be reached: not connected, transfer error,
/// timeout, not found.
const UNREACHABLE: [i32; 4] = [2, 4, 5, 6];

impl ArvError {
    /// True when the error says the device is unreachable (not connected, transfer error, timeout,
    /// not found) rather than that a feature or value is wrong.
    pub fn is_unreachable(&self) -> bool {
        self.device_domain && UNREACHABLE.contains(&self.code)
    }

    fn other(message: impl Into<String>) -> Self {
        ArvError { device_domain: false, code: -1, message: message.into() }
    }
}

/// Run one Aravis call with a `GError` out-parameter; its error, if set, becomes the `Err`.
fn call<T>(f: impl FnOnce(GErrorOut) -> T) -> Result<T, ArvError> {
    let mut err: *mut GError = std::ptr::null_mut();
    let value = f(&mut err);
    if err.is_null() {
        return Ok(value);
    }
    // SAFETY: Aravis set `err` to a valid GError it allocated; we read it once and free it.
    let e = unsafe {
        let message = if (*err).message.is_null() {
            String::new()
        } else {
            CStr::from_ptr((*err).message).to_string_lossy().into_owned()
        };
        let code = (*err).code;
        let device_domain = (*err).domain == arv_device_error_quark();
        g_error_free(err);
        ArvError { device_domain, code, message }
    };
    Err(e)
}

/// A string Aravis owns, copied; `None` for a null pointer.
///
/// # Safety
/// `p` is null or a NUL-terminated string valid for the duration of the call.
unsafe fn owned(p: *const c_char) -> Option<String> {
    if p.is_null() {
        None
    } else {
        // SAFETY: by the caller's contract.
        Some(unsafe { CStr::from_ptr(p) }.to_string_lossy().into_owned())
    }
}

fn cstring(s: &str) -> Result<CString, ArvError> {
    CString::new(s).map_err(|_| ArvError::other(format!("`{s}` contains a NUL byte")))
}

/// One device Aravis discovered (GigE Vision on every network interface, USB3 Vision on USB).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DeviceInfo {
    /// The id `arv_camera_new` opens (`Vendor-Model-Serial` for GigE Vision).
    pub id: String,
    /// `DeviceVendorName`.
    pub vendor: String,
    /// `DeviceModelName`.
    pub model: String,
    /// `DeviceSerialNumber`, the stable identity.
    pub serial: String,
    /// `GigEVision` or `USB3Vision`.
    pub protocol: String,
    /// IP address (GigE Vision) or USB bus path.
    pub address: String,
}

/// Discover the devices reachable now. GigE Vision discovery broadcasts on every network interface
/// of the host.
pub fn list_devices() -> Vec<DeviceInfo> {
    // SAFETY: the device list calls take an index below arv_get_n_devices() and return strings the
    // library owns until the next update, copied at once.
    unsafe {
        arv_update_device_list();
        (0..arv_get_n_devices())
            .map(|i| DeviceInfo {
                id: owned(arv_get_device_id(i)).unwrap_or_default(),
                vendor: owned(arv_get_device_vendor(i)).unwrap_or_default(),
                model: owned(arv_get_device_model(i)).unwrap_or_default(),
                serial: owned(arv_get_device_serial_nbr(i)).unwrap_or_default(),
                protocol: owned(arv_get_device_protocol(i)).unwrap_or_default(),
                address: owned(arv_get_device_address(i)).unwrap_or_default(),
            })
            .collect()
    }
}

/// An open GenICam camera (`ArvCamera`), unreferenced on drop.
#[derive(Debug)]
pub struct ArvCamera(NonNull<ArvCameraRaw>);

// SAFETY: an ArvCamera is a GObject whose calls Aravis serialises internally (its GVCP/USB control
// channel has its own lock); the driver owns it from one thread at a time.
unsafe impl Send for ArvCamera {}

/// Status of a filled buffer (`ArvBufferStatus`).
pub const BUFFER_STATUS_SUCCESS: i32 = 0;

impl ArvCamera {
    /// Open the device `name`: a discovered id, an IP address or `None` for the first one.
    pub fn open(name: Option<&str>) -> Result<Self, ArvError> {
        let c = name.map(cstring).transpose()?;
        let ptr = c.as_ref().map_or(std::ptr::null(), |c| c.as_ptr());
        // SAFETY: `ptr` is null or a valid C string for the call.
        let raw = call(|e| unsafe { arv_camera_new(ptr, e) })?;
        NonNull::new(raw).map(ArvCamera).ok_or_else(|| ArvError::other("arv_camera_new returned no camera"))
    }

    fn raw(&self) -> *mut ArvCameraRaw {
        self.0.as_ptr()
    }

    /// `DeviceVendorName`, `DeviceModelName`, `DeviceSerialNumber`.
    pub fn identity(&self) -> Result<(String, String, String), ArvError> {
        // SAFETY: valid camera; the strings are owned by the camera's feature nodes and copied.
        unsafe {
            let v = call(|e| arv_camera_get_vendor_name(self.raw(), e))?;
            let v = owned(v).unwrap_or_default();
            let m = call(|e| arv_camera_get_model_name(self.raw(), e))?;
            let m = owned(m).unwrap_or_default();
            let s = call(|e| arv_camera_get_device_serial_number(self.raw(), e))?;
            let s = owned(s).unwrap_or_default();
            Ok((v, m, s))
        }
    }

    /// Set the region of interest, pixels.
    pub fn set_region(&self, x: i32, y: i32, width: i32, height: i32) -> Result<(), ArvError> {
        // SAFETY: valid camera.
        call(|e| unsafe { arv_camera_set_region(self.raw(), x, y, width, height, e) })
    }

    /// The region of interest `(x, y, width, height)`, pixels.
    pub fn region(&self) -> Result<(i32, i32, i32, i32), ArvError> {
        let (mut x, mut y, mut w, mut h) = (0, 0, 0, 0);
        // SAFETY: valid camera and four valid out pointers.
        call(|e| unsafe { arv_camera_get_region(self.raw(), &mut x, &mut y, &mut w, &mut h, e) })?;
        Ok((x, y, w, h))
    }

    /// Set `PixelFormat` by its GenICam name (`Mono8`, `RGB8`).
    pub fn set_pixel_format(&self, name: &str) -> Result<(), ArvError> {
        let c = cstring(name)?;
        // SAFETY: valid camera and C string.
        call(|e| unsafe { arv_camera_set_pixel_format_from_string(self.raw(), c.as_ptr(), e) })
    }

    /// `PixelFormat` as its GenICam name.
    pub fn pixel_format(&self) -> Result<String, ArvError> {
        // SAFETY: valid camera; the string is the feature node's, copied.
        unsafe { call(|e| arv_camera_get_pixel_format_as_string(self.raw(), e)).map(|p| owned(p).unwrap_or_default()) }
    }

    /// `AcquisitionMode = Continuous`.
    pub fn set_continuous(&self) -> Result<(), ArvError> {
        // SAFETY: valid camera; 0 is ARV_ACQUISITION_MODE_CONTINUOUS.
        call(|e| unsafe { arv_camera_set_acquisition_mode(self.raw(), 0, e) })
    }

    /// Set the frame rate, frames per second.
    pub fn set_frame_rate(&self, fps: f64) -> Result<(), ArvError> {
        // SAFETY: valid camera.
        call(|e| unsafe { arv_camera_set_frame_rate(self.raw(), fps, e) })
    }

    /// The frame rate, frames per second.
    pub fn frame_rate(&self) -> Result<f64, ArvError> {
        // SAFETY: valid camera.
        call(|e| unsafe { arv_camera_get_frame_rate(self.raw(), e) })
    }

    /// Set the exposure time, microseconds (`ExposureTime` or `ExposureTimeAbs`).
    pub fn set_exposure_us(&self, us: f64) -> Result<(), ArvError> {
        // SAFETY: valid camera.
        call(|e| unsafe { arv_camera_set_exposure_time(self.raw(), us, e) })
    }

    /// The exposure time, microseconds.
    pub fn exposure_us(&self) -> Result<f64, ArvError> {
        // SAFETY: valid camera.
        call(|e| unsafe { arv_camera_get_exposure_time(self.raw(), e) })
    }

    /// Set the gain (`Gain` in dB, or `GainRaw` in the camera's units).
    pub fn set_gain(&self, gain: f64) -> Result<(), ArvError> {
        // SAFETY: valid camera.
        call(|e| unsafe { arv_camera_set_gain(self.raw(), gain, e) })
    }

    /// The gain.
    pub fn gain(&self) -> Result<f64, ArvError> {
        // SAFETY: valid camera.
        call(|e| unsafe { arv_camera_get_gain(self.raw(), e) })
    }

    /// True when the camera has the feature `name` and it is available now.
    pub fn has_feature(&self, name: &str) -> Result<bool, ArvError> {
        let c = cstring(name)?;
        // SAFETY: valid camera and C string.
        call(|e| unsafe { arv_camera_is_feature_available(self.raw(), c.as_ptr(), e) }).map(|b| b != 0)
    }

    /// Set an enumeration or string feature.
    pub fn set_string(&self, feature: &str, value: &str) -> Result<(), ArvError> {
        let (f, v) = (cstring(feature)?, cstring(value)?);
        // SAFETY: valid camera and C strings.
        call(|e| unsafe { arv_camera_set_string(self.raw(), f.as_ptr(), v.as_ptr(), e) })
    }

    /// Read an enumeration or string feature.
    pub fn string(&self, feature: &str) -> Result<String, ArvError> {
        let f = cstring(feature)?;
        // SAFETY: valid camera and C string; the result is the node's, copied.
        unsafe { call(|e| arv_camera_get_string(self.raw(), f.as_ptr(), e)).map(|p| owned(p).unwrap_or_default()) }
    }

    /// Set a float feature.
    pub fn set_float(&self, feature: &str, value: f64) -> Result<(), ArvError> {
        let f = cstring(feature)?;
        // SAFETY: valid camera and C string.
        call(|e| unsafe { arv_camera_set_float(self.raw(), f.as_ptr(), value, e) })
    }

    /// Read a float feature.
    pub fn float(&self, feature: &str) -> Result<f64, ArvError> {
        let f = cstring(feature)?;
        // SAFETY: valid camera and C string.
        call(|e| unsafe { arv_camera_get_float(self.raw(), f.as_ptr(), e) })
    }

    /// Read an integer feature.
    pub fn integer(&self, feature: &str) -> Result<i64, ArvError> {
        let f = cstring(feature)?;
        // SAFETY: valid camera and C string.
        call(|e| unsafe { arv_camera_get_integer(self.raw(), f.as_ptr(), e) })
    }

    /// Execute a command feature (`TriggerSoftware`).
    pub fn execute(&self, feature: &str) -> Result<(), ArvError> {
        let f = cstring(feature)?;
        // SAFETY: valid camera and C string.
        call(|e| unsafe { arv_camera_execute_command(self.raw(), f.as_ptr(), e) })
    }

    /// Bytes of one frame's payload.
    pub fn payload(&self) -> Result<usize, ArvError> {
        // SAFETY: valid camera.
        call(|e| unsafe { arv_camera_get_payload(self.raw(), e) }).map(|p| p as usize)
    }

    /// Create the stream and queue `buffers` buffers of `payload` bytes.
    pub fn create_stream(&self, buffers: u32, payload: usize) -> Result<ArvStream, ArvError> {
        // SAFETY: valid camera; no callback.
        let raw =
            call(|e| unsafe { arv_camera_create_stream(self.raw(), std::ptr::null_mut(), std::ptr::null_mut(), e) })?;
        let stream = NonNull::new(raw).map(ArvStream).ok_or_else(|| ArvError::other("no stream"))?;
        for _ in 0..buffers {
            // SAFETY: a new buffer owned by the library's allocation, handed to the stream.
            unsafe {
                let b = arv_buffer_new(payload, std::ptr::null_mut());
                if b.is_null() {
                    return Err(ArvError::other("cannot allocate a stream buffer"));
                }
                arv_stream_push_buffer(stream.0.as_ptr(), b);
            }
        }
        Ok(stream)
    }

    /// `AcquisitionStart`.
    pub fn start(&self) -> Result<(), ArvError> {
        // SAFETY: valid camera.
        call(|e| unsafe { arv_camera_start_acquisition(self.raw(), e) })
    }

    /// `AcquisitionStop`.
    pub fn stop(&self) -> Result<(), ArvError> {
        // SAFETY: valid camera.
        call(|e| unsafe { arv_camera_stop_acquisition(self.raw(), e) })
    }
}

impl Drop for ArvCamera {
    fn drop(&mut self) {
        // SAFETY: we hold the only reference we took.
        unsafe { g_object_unref(self.0.as_ptr().cast()) }
    }
}

/// A camera's stream with its buffer pool (`ArvStream`), unreferenced on drop (which frees the
/// buffers it holds).
#[derive(Debug)]
pub struct ArvStream(NonNull<ArvStreamRaw>);

// SAFETY: ArvStream's queues are thread-safe (GAsyncQueue); the driver owns it from one thread.
unsafe impl Send for ArvStream {}

/// Stream statistics (`arv_stream_get_statistics`), buffers since the stream was created.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct StreamStatistics {
    /// Buffers completed successfully.
    pub completed: u64,
    /// Buffers that failed (missing packets, timeout, size mismatch).
    pub failures: u64,
    /// Frames lost because no buffer was queued (the pool ran dry).
    pub underruns: u64,
}

/// A filled buffer popped from the stream; push it back with [`ArvStream::push`].
#[derive(Debug)]
pub struct FilledBuffer(NonNull<ArvBufferRaw>);

// SAFETY: a popped buffer belongs to whoever popped it until pushed back.
unsafe impl Send for FilledBuffer {}

impl FilledBuffer {
    fn raw(&self) -> *mut ArvBufferRaw {
        self.0.as_ptr()
    }

    /// `ArvBufferStatus` (0 = success).
    pub fn status(&self) -> i32 {
        // SAFETY: valid buffer.
        unsafe { arv_buffer_get_status(self.raw()) }
    }

    /// The frame id the camera gave this frame (16-bit in GigE Vision 1.x, wrapping).
    pub fn frame_id(&self) -> u64 {
        // SAFETY: valid buffer.
        unsafe { arv_buffer_get_frame_id(self.raw()) }
    }

    /// Host wall-clock time (`g_get_real_time`, nanoseconds since the Unix epoch) at which the frame's
    /// first packet arrived.
    pub fn system_timestamp(&self) -> Duration {
        // SAFETY: valid buffer.
        Duration::from_nanos(unsafe { arv_buffer_get_system_timestamp(self.raw()) })
    }

    /// Image size, pixels.
    pub fn size(&self) -> (u32, u32) {
        // SAFETY: valid buffer.
        unsafe {
            (
                arv_buffer_get_image_width(self.raw()).max(0) as u32,
                arv_buffer_get_image_height(self.raw()).max(0) as u32,
            )
        }
    }

    /// The payload bytes.
    pub fn data(&self) -> &[u8] {
        let mut size = 0usize;
        // SAFETY: valid buffer; the data stays valid while we hold the buffer (it is not queued).
        unsafe {
            let p = arv_buffer_get_data(self.raw(), &mut size);
            if p.is_null() {
                &[]
            } else {
                std::slice::from_raw_parts(p.cast::<u8>(), size)
            }
        }
    }
}

impl ArvStream {
    /// The next filled buffer, waiting at most `timeout`.
    pub fn pop(&self, timeout: Duration) -> Option<FilledBuffer> {
        // SAFETY: valid stream; the popped buffer is ours.
        NonNull::new(unsafe { arv_stream_timeout_pop_buffer(self.0.as_ptr(), timeout.as_micros() as u64) })
            .map(FilledBuffer)
    }

    /// A filled buffer if one is waiting, without blocking.
    pub fn try_pop(&self) -> Option<FilledBuffer> {
        // SAFETY: valid stream.
        NonNull::new(unsafe { arv_stream_try_pop_buffer(self.0.as_ptr()) }).map(FilledBuffer)
    }

    /// Queue a buffer again.
    pub fn push(&self, buffer: FilledBuffer) {
        // SAFETY: valid stream and buffer; ownership passes to the stream.
        unsafe { arv_stream_push_buffer(self.0.as_ptr(), buffer.raw()) };
        std::mem::forget(buffer);
    }

    /// The stream's statistics.
    pub fn statistics(&self) -> StreamStatistics {
        let mut s = StreamStatistics::default();
        // SAFETY: valid stream and out pointers.
        unsafe { arv_stream_get_statistics(self.0.as_ptr(), &mut s.completed, &mut s.failures, &mut s.underruns) };
        s
    }
}

impl Drop for FilledBuffer {
    fn drop(&mut self) {
        // SAFETY: a buffer not pushed back is ours to free.
        unsafe { g_object_unref(self.0.as_ptr().cast()) }
    }
}

impl Drop for ArvStream {
    fn drop(&mut self) {
        // SAFETY: our only reference; the stream frees its queued buffers.
        unsafe { g_object_unref(self.0.as_ptr().cast()) }
    }
}

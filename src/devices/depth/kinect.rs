//! The Kinect v1's raw depth encoding and fakenect's recording format, free of libfreenect.
//!
//! The Kinect reports an 11-bit disparity per pixel (`FREENECT_DEPTH_11BIT`, 2047 = no reading);
//! depth along the optical axis follows from it as `z = 1 / (a·d + b)` metres with the widely used
//! calibration of N. Burrus (`a = -0.0030711016`, `b = 3.3309495161`), valid for `d` in
//! `0..=1083` (`z` from 0.30 m to far). A real unit's own constants differ by a few percent; the
//! driver's millimetre mode (`FREENECT_DEPTH_MM`) uses the unit's factory calibration instead.
//!
//! fakenect (Debian `libfreenect-bin`) replays a directory through the real libfreenect API: an
//! `INDEX.txt` with one file name per line, in time order, each named `T-SECONDS-TIMESTAMP-...`
//! where `T` is `d` (depth), `r` (RGB) or `a` (accelerometer), `SECONDS` the recording time in
//! seconds (replay keeps the gaps) and `TIMESTAMP` the device's 32-bit frame timestamp. A depth file
//! is a one-line PGM header `P5 640 480 65535` and a newline, then 640 x 480 disparities as
//! native-endian `u16`, as `fakenect-record` writes them. fakenect only plays `FREENECT_DEPTH_11BIT`.

use std::io::Write as _;
use std::path::Path;

pub use crate::config::vocab::FreenectDepthFormat;

/// `a` of `z = 1 / (a·d + b)`, 1/metres per disparity unit.
pub const DISPARITY_A: f64 = -0.003_071_101_6;
/// `b` of `z = 1 / (a·d + b)`, 1/metres.
pub const DISPARITY_B: f64 = 3.330_949_516_1;
/// The disparity value of a pixel with no reading.
pub const NO_READING: u16 = 2047;
/// The largest disparity that maps to a positive depth.
pub const MAX_DISPARITY: u16 = 1083;

/// Depth in metres of raw disparity `d`; 0 (no measurement) for [`NO_READING`] and for values past
/// [`MAX_DISPARITY`].
pub fn disparity_to_m(d: u16) -> f32 {
    if d > MAX_DISPARITY {
        return 0.0;
    }
    (1.0 / (DISPARITY_A * d as f64 + DISPARITY_B)) as f32
}

/// The raw disparity the Kinect reports for depth `z_m` metres (rounded to the nearest unit, depths
/// nearer than 0.30 m clamped to 0); [`NO_READING`] for 0 or a non-finite depth.
pub fn m_to_disparity(z_m: f32) -> u16 {
    if !(z_m.is_finite() && z_m > 0.0) {
        return NO_READING;
    }
    let d = (1.0 / z_m as f64 - DISPARITY_B) / DISPARITY_A;
    d.round().clamp(0.0, MAX_DISPARITY as f64) as u16
}

/// Why a recording could not be written.
#[derive(Debug, thiserror::Error)]
pub enum RecordingError {
    /// A depth map is not 640 x 480.
    #[error("depth map {index} is {width}x{height}, the Kinect's is 640x480")]
    Size {
        /// Which map.
        index: usize,
        /// Its width, pixels.
        width: u32,
        /// Its height, pixels.
        height: u32,
    },
    /// Writing a file failed.
    #[error("writing {path}")]
    Io {
        /// The file.
        path: std::path::PathBuf,
        /// The error.
        #[source]
        source: std::io::Error,
    },
}

/// Write a fakenect recording into `dir`: the depth maps `frames` (metres, 640 x 480, 0 = no
/// reading) encoded as raw disparity, played in order one per `period_s` seconds, and repeated
/// `repeat` times (files for a repeated map are links to its first file, so a long replay costs one
/// file per map).
pub fn write_fakenect_recording(
    dir: &Path,
    frames: &[(u32, u32, &[f32])],
    period_s: f64,
    repeat: usize,
) -> Result<(), RecordingError> {
    let io = |path: &Path| {
        let path = path.to_owned();
        move |source| RecordingError::Io { path, source }
    };
    std::fs::create_dir_all(dir).map_err(io(dir))?;
    let mut firsts = Vec::with_capacity(frames.len());
    for (index, &(width, height, depth)) in frames.iter().enumerate() {
        if (width, height) != (640, 480) || depth.len() != 640 * 480 {
            return Err(RecordingError::Size { index, width, height });
        }
        let name = format!("frame-{index:04}.pgm");
        let mut bytes = Vec::with_capacity(20 + 2 * depth.len());
        bytes.extend_from_slice(b"P5 640 480 65535\n");
        for &z in depth {
            bytes.extend_from_slice(&m_to_disparity(z).to_ne_bytes());
        }
        let path = dir.join(&name);
        std::fs::write(&path, &bytes).map_err(io(&path))?;
        firsts.push(name);
    }
    let mut index = String::new();
    let mut n = 0u64;
    for _ in 0..repeat {
        for first in &firsts {
            let t = n as f64 * period_s;
            // The device timestamp counts at 60 MHz / 2 (the Kinect's clock) per frame period.
            let ts = ((t * 30e6) as u64 & 0xffff_ffff) as u32;
            let name = format!("d-{t:.6}-{ts}-{n}.pgm");
            let link = dir.join(&name);
            std::os::unix::fs::symlink(first, &link).map_err(io(&link))?;
            index.push_str(&name);
            index.push('\n');
            n += 1;
        }
    }
    let path = dir.join("INDEX.txt");
    let mut f = std::fs::File::create(&path).map_err(io(&path))?;
    f.write_all(index.as_bytes()).map_err(io(&path))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn disparity_round_trips_within_one_unit_of_depth() {
        for z in [0.35f32, 0.5, 0.8, 1.5, 3.0] {
            let d = m_to_disparity(z);
            let back = disparity_to_m(d);
            // One disparity unit is z² · |a| metres.
            let unit = z * z * DISPARITY_A.abs() as f32;
            assert!((back - z).abs() <= 0.5 * unit + 1e-6, "{z} -> {d} -> {back}");
        }
        assert_eq!(m_to_disparity(0.0), NO_READING);
        assert_eq!(disparity_to_m(NO_READING), 0.0);
        assert_eq!(m_to_disparity(0.1), 0, "nearer than the range clamps");
        // Known points of the curve: d = 0 is 0.300 m, d = 800 is 1.144 m.
        assert!((disparity_to_m(0) - 0.3002).abs() < 1e-3);
        assert!((disparity_to_m(800) - 1.1441).abs() < 1e-3);
    }

    #[test]
    fn a_recording_has_an_index_in_time_order_and_pgm_depth_files() {
        let dir = tempfile::tempdir().expect("tempdir");
        let a = vec![0.5f32; 640 * 480];
        let mut b = vec![0.0f32; 640 * 480];
        b[1] = 1.0;
        write_fakenect_recording(dir.path(), &[(640, 480, &a), (640, 480, &b)], 0.05, 2).expect("write");
        let index = std::fs::read_to_string(dir.path().join("INDEX.txt")).expect("index");
        let lines: Vec<&str> = index.lines().collect();
        assert_eq!(lines.len(), 4);
        assert!(lines[0].starts_with("d-0.000000-0-") && lines[1].starts_with("d-0.050000-"), "{lines:?}");
        let times: Vec<f64> =
            lines.iter().map(|l| l.split('-').nth(1).and_then(|t| t.parse().ok()).expect("t")).collect();
        assert!(times.windows(2).all(|w| w[1] > w[0]));
        let data = std::fs::read(dir.path().join(lines[3])).expect("frame via link");
        assert!(data.starts_with(b"P5 640 480 65535\n"));
        let px = |i: usize| u16::from_ne_bytes([data[17 + 2 * i], data[18 + 2 * i]]);
        assert_eq!((px(0), px(1)), (NO_READING, m_to_disparity(1.0)));
        assert_eq!(data.len(), 17 + 2 * 640 * 480);
        let bad = write_fakenect_recording(dir.path(), &[(320, 240, &a[..320 * 240])], 0.05, 1);
        assert!(matches!(bad, Err(RecordingError::Size { index: 0, .. })));
    }
}

//! Camera pixel formats and their conversion to 8-bit RGB: the device-free half of the real camera
//! drivers (V4L2, UVC), tested without a camera.
//!
//! Buffers are row-major from the top-left pixel; `stride` is the number of bytes from the start of
//! one row to the next (V4L2's `bytesperline`), at least the packed row size.

use std::fmt;

pub use crate::config::vocab::PixelFormat;

impl PixelFormat {
    /// Every format, in the order a driver prefers them when the rig file says `auto`: lossless
    /// uncompressed first (no JPEG artefacts in Gray-code stripes), then MJPEG.
    pub const PREFERENCE: [PixelFormat; 4] =
        [PixelFormat::Rgb24, PixelFormat::Yuyv, PixelFormat::Grey, PixelFormat::Mjpeg];

    /// The V4L2 four-character code.
    pub fn fourcc(self) -> [u8; 4] {
        match self {
            PixelFormat::Grey => *b"GREY",
            PixelFormat::Yuyv => *b"YUYV",
            PixelFormat::Mjpeg => *b"MJPG",
            PixelFormat::Rgb24 => *b"RGB3",
        }
    }

    /// The format with this four-character code, if it is one this crate converts. `JPEG` is taken
    /// as MJPEG (some drivers report it for the same stream).
    pub fn from_fourcc(code: [u8; 4]) -> Option<Self> {
        match &code {
            b"GREY" => Some(PixelFormat::Grey),
            b"YUYV" => Some(PixelFormat::Yuyv),
            b"MJPG" | b"JPEG" => Some(PixelFormat::Mjpeg),
            b"RGB3" => Some(PixelFormat::Rgb24),
            _ => None,
        }
    }

    /// Bytes per pixel of the packed format; `None` for compressed MJPEG.
    pub fn bytes_per_pixel(self) -> Option<usize> {
        match self {
            PixelFormat::Grey => Some(1),
            PixelFormat::Yuyv => Some(2),
            PixelFormat::Rgb24 => Some(3),
            PixelFormat::Mjpeg => None,
        }
    }

    /// The name used in rig files.
    pub fn name(self) -> &'static str {
        match self {
            PixelFormat::Grey => "grey",
            PixelFormat::Yuyv => "yuyv",
            PixelFormat::Mjpeg => "mjpeg",
            PixelFormat::Rgb24 => "rgb24",
        }
    }
}

impl fmt::Display for PixelFormat {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// Why a camera buffer could not be converted.
#[derive(Debug, thiserror::Error)]
pub enum PixelError {
    /// The buffer holds fewer bytes than the format and size need.
    #[error("{format} {width}x{height} (stride {stride} bytes) needs {needed} bytes, the buffer has {got}")]
    ShortBuffer {
        /// The format.
        format: PixelFormat,
        /// Width, pixels.
        width: u32,
        /// Height, pixels.
        height: u32,
        /// Row stride, bytes.
        stride: usize,
        /// Bytes needed.
        needed: usize,
        /// Bytes in the buffer.
        got: usize,
    },
    /// The stride is smaller than one packed row, or a YUYV width is odd.
    #[error("{format} {width}x{height}: bad layout ({problem})")]
    Layout {
        /// The format.
        format: PixelFormat,
        /// Width, pixels.
        width: u32,
        /// Height, pixels.
        height: u32,
        /// What is wrong.
        problem: &'static str,
    },
    /// A JPEG frame did not decode (a truncated USB transfer, usually).
    #[error("MJPEG frame does not decode")]
    Jpeg(#[source] image::ImageError),
    /// A JPEG frame decoded to another size than the stream's.
    #[error("MJPEG frame is {got_w}x{got_h}, the stream is {width}x{height}")]
    JpegSize {
        /// Stream width, pixels.
        width: u32,
        /// Stream height, pixels.
        height: u32,
        /// Decoded width, pixels.
        got_w: u32,
        /// Decoded height, pixels.
        got_h: u32,
    },
}

/// Convert one frame of `format`, `width` x `height` pixels, rows `stride` bytes apart (`0` =
/// packed), to 8-bit RGB.
pub fn to_rgb(
    format: PixelFormat,
    width: u32,
    height: u32,
    stride: usize,
    data: &[u8],
) -> Result<image::RgbImage, PixelError> {
    let Some(bpp) = format.bytes_per_pixel() else {
        return decode_mjpeg(width, height, data);
    };
    if format == PixelFormat::Yuyv && width % 2 != 0 {
        return Err(PixelError::Layout { format, width, height, problem: "YUYV width must be even" });
    }
    let row = width as usize * bpp;
    let stride = if stride == 0 { row } else { stride };
    if stride < row {
        return Err(PixelError::Layout { format, width, height, problem: "stride shorter than a row" });
    }
    let needed = if height == 0 { 0 } else { stride * (height as usize - 1) + row };
    if data.len() < needed {
        return Err(PixelError::ShortBuffer { format, width, height, stride, needed, got: data.len() });
    }
    let mut out = vec![0u8; 3 * width as usize * height as usize];
    for (y, dst) in out.chunks_exact_mut(3 * width as usize).enumerate() {
        let src = &data[y * stride..y * stride + row];
        match format {
            PixelFormat::Grey => {
                for (d, &g) in dst.chunks_exact_mut(3).zip(src) {
                    d.copy_from_slice(&[g, g, g]);
                }
            }
            PixelFormat::Rgb24 => dst.copy_from_slice(src),
            PixelFormat::Yuyv => {
                for (d, s) in dst.chunks_exact_mut(6).zip(src.chunks_exact(4)) {
                    let (u, v) = (s[1], s[3]);
                    d[..3].copy_from_slice(&yuv_to_rgb(s[0], u, v));
                    d[3..].copy_from_slice(&yuv_to_rgb(s[2], u, v));
                }
            }
            PixelFormat::Mjpeg => unreachable!("handled above"),
        }
    }
    image::RgbImage::from_raw(width, height, out).ok_or(PixelError::Layout {
        format,
        width,
        height,
        problem: "size overflows",
    })
}

/// BT.601 limited-range YCbCr to RGB, integer arithmetic (16.16 fixed point), clamped to 0..255.
pub fn yuv_to_rgb(y: u8, u: u8, v: u8) -> [u8; 3] {
    let c = (y as i32 - 16).max(0) * 76_309; // 1.164 * 65536
    let d = u as i32 - 128;
    let e = v as i32 - 128;
    let clamp = |x: i32| ((x + 32_768) >> 16).clamp(0, 255) as u8;
    [
        clamp(c + 104_597 * e),             // 1.596
        clamp(c - 25_675 * d - 53_279 * e), // 0.392, 0.813
        clamp(c + 132_201 * d),             // 2.017
    ]
}

/// Decode an MJPEG frame and check its size against the stream's.
fn decode_mjpeg(width: u32, height: u32, data: &[u8]) -> Result<image::RgbImage, PixelError> {
    let img = image::load_from_memory_with_format(data, image::ImageFormat::Jpeg).map_err(PixelError::Jpeg)?;
    let rgb = img.into_rgb8();
    if rgb.width() != width || rgb.height() != height {
        return Err(PixelError::JpegSize { width, height, got_w: rgb.width(), got_h: rgb.height() });
    }
    Ok(rgb)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fourcc_round_trips_and_unknown_codes_are_none() {
        for f in PixelFormat::PREFERENCE {
            assert_eq!(PixelFormat::from_fourcc(f.fourcc()), Some(f));
        }
        assert_eq!(PixelFormat::from_fourcc(*b"JPEG"), Some(PixelFormat::Mjpeg));
        assert_eq!(PixelFormat::from_fourcc(*b"NV12"), None);
    }

    #[test]
    fn yuv_reference_colours() {
        assert_eq!(yuv_to_rgb(16, 128, 128), [0, 0, 0]);
        assert_eq!(yuv_to_rgb(235, 128, 128), [255, 255, 255]);
        // BT.601 limited-range primaries (Y, Cb, Cr) from the standard's colour bars, +-1 rounding.
        let close = |a: [u8; 3], b: [u8; 3]| a.iter().zip(&b).all(|(x, y)| (*x as i32 - *y as i32).abs() <= 1);
        assert!(close(yuv_to_rgb(81, 90, 240), [255, 0, 0]), "{:?}", yuv_to_rgb(81, 90, 240));
        assert!(close(yuv_to_rgb(145, 54, 34), [0, 255, 0]), "{:?}", yuv_to_rgb(145, 54, 34));
        assert!(close(yuv_to_rgb(41, 240, 110), [0, 0, 255]), "{:?}", yuv_to_rgb(41, 240, 110));
    }

    #[test]
    fn yuyv_with_padding_stride() {
        // 2x2 pixels, stride 6 (2 bytes of padding per row).
        let data = [
            16, 128, 235, 128, 0xEE, 0xEE, //
            81, 90, 81, 240, 0xEE, 0xEE,
        ];
        let img = to_rgb(PixelFormat::Yuyv, 2, 2, 6, &data).expect("converts");
        assert_eq!(img.get_pixel(0, 0).0, [0, 0, 0]);
        assert_eq!(img.get_pixel(1, 0).0, [255, 255, 255]);
        assert_eq!(img.get_pixel(0, 1).0, img.get_pixel(1, 1).0);
        assert!(img.get_pixel(0, 1).0[0] > 250);
    }

    #[test]
    fn grey_and_rgb24_are_exact() {
        let img = to_rgb(PixelFormat::Grey, 3, 1, 0, &[0, 100, 255]).expect("grey");
        assert_eq!(img.as_raw(), &vec![0, 0, 0, 100, 100, 100, 255, 255, 255]);
        let raw: Vec<u8> = (0..12).collect();
        let img = to_rgb(PixelFormat::Rgb24, 2, 2, 0, &raw).expect("rgb");
        assert_eq!(img.as_raw(), &raw);
    }

    #[test]
    fn short_buffers_and_bad_layouts_are_typed_errors() {
        let e = to_rgb(PixelFormat::Grey, 4, 4, 0, &[0; 15]).expect_err("short");
        assert!(matches!(e, PixelError::ShortBuffer { needed: 16, got: 15, .. }), "{e}");
        // The last row needs no padding after it.
        assert!(to_rgb(PixelFormat::Grey, 4, 2, 8, &[0; 12]).is_ok());
        let e = to_rgb(PixelFormat::Yuyv, 3, 1, 0, &[0; 8]).expect_err("odd");
        assert!(matches!(e, PixelError::Layout { .. }));
        let e = to_rgb(PixelFormat::Rgb24, 4, 1, 6, &[0; 12]).expect_err("stride");
        assert!(matches!(e, PixelError::Layout { .. }));
    }

    #[test]
    fn mjpeg_decodes_checks_size_and_rejects_garbage() {
        let mut src = image::RgbImage::new(16, 8);
        for (x, _, p) in src.enumerate_pixels_mut() {
            *p = image::Rgb(if x < 8 { [250, 250, 250] } else { [5, 5, 5] });
        }
        let mut jpeg = Vec::new();
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, 95).encode_image(&src).expect("encode");
        let img = to_rgb(PixelFormat::Mjpeg, 16, 8, 0, &jpeg).expect("decode");
        assert!(img.get_pixel(2, 4).0[0] > 230 && img.get_pixel(13, 4).0[0] < 25);
        let e = to_rgb(PixelFormat::Mjpeg, 32, 8, 0, &jpeg).expect_err("size");
        assert!(matches!(e, PixelError::JpegSize { got_w: 16, .. }));
        let e = to_rgb(PixelFormat::Mjpeg, 16, 8, 0, &jpeg[..jpeg.len() / 3]).expect_err("truncated");
        assert!(matches!(e, PixelError::Jpeg(_)));
    }
}

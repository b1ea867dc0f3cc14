//! The device-free half of a projector driven as a Linux framebuffer: packing RGB patterns into the
//! framebuffer's pixel layout, the display's refresh period from its video mode, and when a written
//! pattern is on screen.

use std::time::{Duration, Instant};

use super::Pattern;

/// Where one colour channel sits in a framebuffer pixel (`struct fb_bitfield`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Channel {
    /// Bit offset from the least significant bit of the pixel.
    pub offset: u32,
    /// Bits.
    pub length: u32,
}

/// A framebuffer's pixel layout (from `FBIOGET_VSCREENINFO` / `FBIOGET_FSCREENINFO`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FbLayout {
    /// Visible width, pixels.
    pub width: u32,
    /// Visible height, pixels.
    pub height: u32,
    /// Bytes from one row to the next.
    pub line_length: u32,
    /// 16, 24 or 32.
    pub bits_per_pixel: u32,
    /// Red channel.
    pub red: Channel,
    /// Green channel.
    pub green: Channel,
    /// Blue channel.
    pub blue: Channel,
    /// Byte offset of the visible area's top-left pixel (panning).
    pub origin: u64,
}

/// Why a pattern cannot go to the framebuffer.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum FbError {
    /// The pattern's size is not the screen's.
    #[error("pattern is {pattern_w}x{pattern_h}, the framebuffer shows {width}x{height}")]
    Size {
        /// Pattern width, pixels.
        pattern_w: u32,
        /// Pattern height, pixels.
        pattern_h: u32,
        /// Screen width, pixels.
        width: u32,
        /// Screen height, pixels.
        height: u32,
    },
    /// A layout this driver does not write (palette modes, channels past the pixel).
    #[error("unsupported framebuffer layout: {0}")]
    Layout(&'static str),
}

impl FbLayout {
    /// Bytes per pixel.
    pub fn bytes_per_pixel(&self) -> usize {
        self.bits_per_pixel as usize / 8
    }

    /// Check that the layout is one [`pack_row`](Self::pack_row) writes: 16, 24 or 32 bits per pixel,
    /// channels of 1..=8 bits inside the pixel, rows long enough.
    pub fn check(&self) -> Result<(), FbError> {
        if !matches!(self.bits_per_pixel, 16 | 24 | 32) {
            return Err(FbError::Layout("bits per pixel must be 16, 24 or 32"));
        }
        for c in [self.red, self.green, self.blue] {
            if c.length == 0 || c.length > 8 || c.offset + c.length > self.bits_per_pixel {
                return Err(FbError::Layout("a colour channel is empty, wider than 8 bits or outside the pixel"));
            }
        }
        if (self.line_length as usize) < self.width as usize * self.bytes_per_pixel() {
            return Err(FbError::Layout("line length shorter than a row"));
        }
        Ok(())
    }

    /// Pack one 8-bit RGB pixel: each channel keeps its top `length` bits.
    pub fn pack_pixel(&self, rgb: [u8; 3]) -> u32 {
        let put = |v: u8, c: Channel| ((v as u32) >> (8 - c.length)) << c.offset;
        put(rgb[0], self.red) | put(rgb[1], self.green) | put(rgb[2], self.blue)
    }

    /// Pack row `y` of `pattern` into `out` (at least `width * bytes_per_pixel` bytes),
    /// little-endian pixels as the framebuffer stores them.
    pub fn pack_row(&self, pattern: &Pattern, y: u32, out: &mut [u8]) {
        let bpp = self.bytes_per_pixel();
        let w = self.width as usize;
        let src = &pattern.rgb[3 * w * y as usize..3 * w * (y as usize + 1)];
        for (dst, px) in out[..w * bpp].chunks_exact_mut(bpp).zip(src.chunks_exact(3)) {
            let v = self.pack_pixel([px[0], px[1], px[2]]).to_le_bytes();
            dst.copy_from_slice(&v[..bpp]);
        }
    }

    /// Check that `pattern` fits the screen.
    pub fn check_pattern(&self, pattern: &Pattern) -> Result<(), FbError> {
        if pattern.width != self.width || pattern.height != self.height {
            return Err(FbError::Size {
                pattern_w: pattern.width,
                pattern_h: pattern.height,
                width: self.width,
                height: self.height,
            });
        }
        Ok(())
    }
}

/// The refresh period of a video mode from its pixel clock (picoseconds per pixel) and its
/// blanking, as `fb_var_screeninfo` gives them; `None` when the driver reports no timing (pixel
/// clock 0, as many KMS-emulated framebuffers do).
pub fn frame_period(pixclock_ps: u32, h_total: u32, v_total: u32) -> Option<Duration> {
    if pixclock_ps == 0 || h_total == 0 || v_total == 0 {
        return None;
    }
    let ps = pixclock_ps as u128 * h_total as u128 * v_total as u128;
    Some(Duration::from_nanos((ps / 1000) as u64))
}

/// When a pattern written into the framebuffer is fully on screen and can be captured.
///
/// `written` is when the last byte was written. With `vsync_at` (the end of a wait for vertical
/// blank *after* the write) the next refresh scans it out whole from then; without it the frame
/// being scanned out may be torn, so the first whole frame starts at most one `period` later. The
/// projector itself shows what it receives `latency` later (its scaler and DLP/LCD response,
/// measured per projector).
pub fn visible_at(written: Instant, vsync_at: Option<Instant>, period: Duration, latency: Duration) -> Instant {
    let scanout = match vsync_at {
        Some(v) if v >= written => v,
        _ => written + period,
    };
    scanout + latency
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Arc;

    fn xrgb8888(w: u32, h: u32) -> FbLayout {
        FbLayout {
            width: w,
            height: h,
            line_length: w * 4 + 8,
            bits_per_pixel: 32,
            red: Channel { offset: 16, length: 8 },
            green: Channel { offset: 8, length: 8 },
            blue: Channel { offset: 0, length: 8 },
            origin: 0,
        }
    }

    #[test]
    fn xrgb8888_and_rgb565_packing() {
        let l = xrgb8888(2, 1);
        l.check().expect("valid");
        let p = Pattern { width: 2, height: 1, rgb: Arc::new(vec![0x12, 0x34, 0x56, 255, 0, 0]) };
        let mut row = vec![0u8; 8];
        l.pack_row(&p, 0, &mut row);
        assert_eq!(row, vec![0x56, 0x34, 0x12, 0, 0, 0, 0xff, 0]);

        let rgb565 = FbLayout {
            bits_per_pixel: 16,
            line_length: 4,
            red: Channel { offset: 11, length: 5 },
            green: Channel { offset: 5, length: 6 },
            blue: Channel { offset: 0, length: 5 },
            ..l
        };
        rgb565.check().expect("valid");
        assert_eq!(rgb565.pack_pixel([255, 255, 255]), 0xffff);
        assert_eq!(rgb565.pack_pixel([255, 0, 0]), 0xf800);
        assert_eq!(rgb565.pack_pixel([0, 4, 0]), 1 << 5);
        let mut row = vec![0u8; 4];
        rgb565.pack_row(&p, 0, &mut row);
        assert_eq!(&row[2..], &[0x00, 0xf8]);
    }

    #[test]
    fn bad_layouts_and_sizes_are_refused() {
        let l = xrgb8888(4, 2);
        assert!(matches!(FbLayout { bits_per_pixel: 8, ..l }.check(), Err(FbError::Layout(_))));
        assert!(matches!(FbLayout { line_length: 15, ..l }.check(), Err(FbError::Layout(_))));
        assert!(matches!(FbLayout { red: Channel { offset: 28, length: 8 }, ..l }.check(), Err(FbError::Layout(_))));
        let e = l.check_pattern(&Pattern::uniform(4, 3, [0; 3])).expect_err("size");
        assert_eq!(e, FbError::Size { pattern_w: 4, pattern_h: 3, width: 4, height: 2 });
        assert!(l.check_pattern(&Pattern::uniform(4, 2, [0; 3])).is_ok());
    }

    #[test]
    fn refresh_period_from_the_video_mode() {
        // CEA 1080p60: 148.5 MHz pixel clock (6734 ps), 2200 x 1125 total.
        let p = frame_period(6734, 2200, 1125).expect("timed");
        assert!((p.as_secs_f64() - 1.0 / 60.0).abs() < 1e-4, "{p:?}");
        assert_eq!(frame_period(0, 2200, 1125), None);
    }

    #[test]
    fn visibility_waits_a_period_without_vsync_plus_latency() {
        let t = Instant::now();
        let period = Duration::from_millis(16);
        let lat = Duration::from_millis(30);
        assert_eq!(visible_at(t, None, period, lat), t + period + lat);
        let v = t + Duration::from_millis(5);
        assert_eq!(visible_at(t, Some(v), period, lat), v + lat);
        // A vsync that returned before the write finished says nothing about it.
        assert_eq!(visible_at(v, Some(t), period, lat), v + period + lat);
    }
}

//! A single sweeping stripe: frame `k` lights projector columns `k·step .. k·step + width`, so the
//! stripe's centre in frame `k` is at `k·step + width / 2` (continuous projector coordinates as in
//! [`ProjectorCoords`]: column `x` covers `[x, x + 1)`). Each camera pixel takes the frame of its maximum response and
//! refines it to a sub-frame position by the centroid of the response above the pixel's floor (its
//! minimum over the sweep, i.e. ambient light) over the frames around the peak that the stripe
//! can overlap; the column is that position mapped through the stripe centre.
//!
//! Slow to capture (one frame per `step` pixels) but immune to global illumination between
//! stripes and to codeword errors: the classic laser-stripe scanner done with a projector.

use rayon::prelude::*;

use super::coords::ProjectorCoords;

/// Errors of the sweeping-stripe layout and decoder.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum StripeError {
    /// A stripe width or step of 0, or a step wider than the stripe (columns left unlit).
    #[error("stripe width {width} and step {step} pixels: need 1 <= step <= width")]
    Layout {
        /// Stripe width, projector pixels.
        width: u32,
        /// Step per frame, projector pixels.
        step: u32,
    },
    /// A projector side of 0 or more than 32768 pixels.
    #[error("projector resolution {width}x{height} pixels: each side must be 1..=32768")]
    Resolution {
        /// Width, pixels.
        width: u32,
        /// Height, pixels.
        height: u32,
    },
    /// A pattern index beyond the sweep.
    #[error("pattern index {index} out of range: the sweep has {count} frames")]
    Index {
        /// The index.
        index: usize,
        /// Frames in the sweep.
        count: usize,
    },
    /// A pattern buffer of the wrong length.
    #[error("pattern buffer holds {found} bytes, the projector needs {expected}")]
    Buffer {
        /// `width * height`.
        expected: usize,
        /// The buffer's length.
        found: usize,
    },
    /// Not one image per frame.
    #[error("{found} images given, the sweep has {expected}")]
    ImageCount {
        /// Frames in the sweep.
        expected: usize,
        /// Images given.
        found: usize,
    },
    /// A captured image of the wrong size (or an empty camera).
    #[error("image {index} holds {found} bytes, a {width}x{height} camera image has {}", width * height)]
    ImageSize {
        /// Position in the sweep.
        index: usize,
        /// Camera width, pixels.
        width: usize,
        /// Camera height, pixels.
        height: usize,
        /// The buffer's length.
        found: usize,
    },
}

/// A vertical stripe swept across the projector's columns.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SweepingStripe {
    width: u32,
    height: u32,
    stripe: u32,
    step: u32,
}

impl SweepingStripe {
    /// A `stripe`-pixel-wide stripe moving `step` pixels per frame over a `width` x `height`
    /// projector.
    pub fn new(width: u32, height: u32, stripe: u32, step: u32) -> Result<Self, StripeError> {
        if !(1..=32768).contains(&width) || !(1..=32768).contains(&height) {
            return Err(StripeError::Resolution { width, height });
        }
        if step == 0 || stripe == 0 || step > stripe {
            return Err(StripeError::Layout { width: stripe, step });
        }
        Ok(Self { width, height, stripe, step })
    }

    /// Projector width, pixels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Projector height, pixels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// Frames in the sweep: enough to light every column.
    pub fn count(&self) -> usize {
        self.width.saturating_sub(self.stripe).div_ceil(self.step) as usize + 1
    }

    /// Renders frame `index` (`width * height` 8-bit grey, 255 in the stripe, 0 elsewhere).
    pub fn render_into(&self, index: usize, out: &mut [u8]) -> Result<(), StripeError> {
        let (w, h) = (self.width as usize, self.height as usize);
        if out.len() != w * h {
            return Err(StripeError::Buffer { expected: w * h, found: out.len() });
        }
        if index >= self.count() {
            return Err(StripeError::Index { index, count: self.count() });
        }
        let x0 = index * self.step as usize;
        let x1 = (x0 + self.stripe as usize).min(w);
        for row in out.chunks_exact_mut(w) {
            row.fill(0);
            row[x0.min(w)..x1].fill(255);
        }
        Ok(())
    }

    /// Frame `index` as a new buffer.
    pub fn render(&self, index: usize) -> Result<Vec<u8>, StripeError> {
        let mut out = vec![0u8; self.width as usize * self.height as usize];
        self.render_into(index, &mut out)?;
        Ok(out)
    }

    /// Decodes the captured sweep (8-bit grey, `width` x `height` camera pixels, frame order) into
    /// sub-pixel projector columns; a pixel is valid when its peak rises at least `min_contrast`
    /// grey levels above its floor. Rows are not coded (`row` is `None`).
    pub fn decode(
        &self,
        images: &[&[u8]],
        width: usize,
        height: usize,
        min_contrast: u8,
    ) -> Result<ProjectorCoords, StripeError> {
        if images.len() != self.count() {
            return Err(StripeError::ImageCount { expected: self.count(), found: images.len() });
        }
        let n = width * height;
        if let Some((index, img)) = images.iter().enumerate().find(|(_, i)| i.len() != n || n == 0) {
            return Err(StripeError::ImageSize { index, width, height, found: img.len() });
        }
        let mut column = vec![f32::NAN; n];
        // Frames on either side of the peak the stripe can still overlap.
        let reach = self.stripe.div_ceil(self.step) as usize;
        let centre = self.stripe as f32 / 2.0;
        let (step, last) = (self.step as f32, self.width as f32);
        column.par_chunks_mut(width).enumerate().for_each_init(
            || (vec![0u8; width], vec![255u8; width], vec![0u32; width]),
            |(peak, floor, at), (y, out)| {
                let span = y * width..(y + 1) * width;
                peak.fill(0);
                floor.fill(255);
                // One streaming pass: running max (first frame wins ties), min and arg max.
                for (k, img) in images.iter().enumerate() {
                    for (((p, f), a), &v) in
                        peak.iter_mut().zip(floor.iter_mut()).zip(at.iter_mut()).zip(&img[span.clone()])
                    {
                        let higher = v > *p;
                        *a = if higher { k as u32 } else { *a };
                        *p = (*p).max(v);
                        *f = (*f).min(v);
                    }
                }
                for (x, o) in out.iter_mut().enumerate() {
                    if peak[x].saturating_sub(floor[x]) < min_contrast {
                        continue;
                    }
                    let k = at[x] as usize;
                    let (lo, hi) = (k.saturating_sub(reach), (k + reach).min(images.len() - 1));
                    let (mut sw, mut swk) = (0f32, 0f32);
                    for (j, img) in images.iter().enumerate().take(hi + 1).skip(lo) {
                        let wgt = f32::from(img[y * width + x] - floor[x]);
                        sw += wgt;
                        swk += wgt * j as f32;
                    }
                    let c = swk / sw * step + centre;
                    if (0.0..=last).contains(&c) {
                        *o = c;
                    }
                }
            },
        );
        Ok(ProjectorCoords { width, height, column, row: None })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sweep_covers_every_column_once_per_stripe_width() {
        for (stripe, step) in [(1, 1), (3, 1), (4, 2), (5, 5)] {
            let s = SweepingStripe::new(37, 2, stripe, step).expect("valid");
            let mut lit = [0u32; 37];
            for k in 0..s.count() {
                let img = s.render(k).expect("in range");
                for (x, l) in lit.iter_mut().enumerate() {
                    *l += u32::from(img[x] == 255);
                }
            }
            assert!(lit.iter().all(|&l| l >= 1), "{stripe}/{step}: {lit:?}");
        }
        assert!(SweepingStripe::new(10, 10, 2, 3).is_err());
        assert!(SweepingStripe::new(10, 10, 0, 0).is_err());
    }

    #[test]
    fn decodes_blurred_stripes_to_sub_pixel_columns() {
        // A camera 2.5x finer than the projector with a one-pixel box blur: camera pixel x sees
        // projector columns around 0.4 x.
        let s = SweepingStripe::new(60, 1, 3, 1).expect("valid");
        let frames: Vec<Vec<u8>> = (0..s.count())
            .map(|k| {
                let pat = s.render(k).expect("in range");
                (0..150)
                    .map(|x| {
                        let t = 0.4 * x as f64;
                        // Average over [t - 0.5, t + 0.5] of the stripe (projector pixel p spans p-0.5..p+0.5).
                        let mut acc = 0.0;
                        for i in 0..10 {
                            let q = t - 0.45 + 0.1 * i as f64;
                            let p = q.round().clamp(0.0, 59.0) as usize;
                            acc += f64::from(pat[p]) / 10.0;
                        }
                        (10.0 + 0.8 * acc).round() as u8
                    })
                    .collect()
            })
            .collect();
        let imgs: Vec<&[u8]> = frames.iter().map(Vec::as_slice).collect();
        let out = s.decode(&imgs, 150, 1, 30).expect("decodes");
        // Away from the sweep's ends, where the window around the peak is cut off.
        for x in 5..140 {
            let d = out.column[x];
            let t = 0.4 * x as f32 + 0.5; // continuous coordinate of projector index 0.4 x
            assert!((d - t).abs() < 0.3, "camera {x}: {d} vs {t}");
        }
        let dark = vec![vec![7u8; 150]; s.count()];
        let imgs: Vec<&[u8]> = dark.iter().map(Vec::as_slice).collect();
        assert_eq!(s.decode(&imgs, 150, 1, 30).expect("decodes").valid_count(), 0);
        assert!(matches!(s.decode(&imgs[1..], 150, 1, 30), Err(StripeError::ImageCount { .. })));
    }
}

//! Silhouette extraction: background difference, threshold, then a closing with discs.
//!
//! A pixel is object when `max_c |pixel_c - background_c| / 255 > threshold` (the largest
//! per-channel difference, scaled to 0..1). The raw mask is then dilated with a disc of radius
//! `dilate` pixels and eroded with a disc of radius `erode` pixels. A disc of radius `r` is the set of
//! offsets `(dx, dy)` with `dx² + dy² <= r²`. Dilation treats pixels outside the image as background;
//! erosion ignores them (an object pixel at the image border is not eroded by the border), which is
//! what image-processing toolboxes do.
//!
//! With a black background, `threshold = 0.19, dilate = 10, erode = 7` is the recipe of the
//! Middlebury dino data set's authors.

use image::RgbImage;
use rayon::prelude::*;

/// A binary image: `1` object, `0` background, row-major, origin top-left, pixel `(u, v)` covers
/// `[u, u+1) x [v, v+1)`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Mask {
    width: u32,
    height: u32,
    data: Vec<u8>,
}

/// The mask's buffer does not match its size.
#[derive(Debug, thiserror::Error)]
#[error("a {width}x{height} mask needs {expected} bytes, got {actual}")]
pub struct MaskSizeError {
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// Bytes needed.
    pub expected: usize,
    /// Bytes given.
    pub actual: usize,
}

impl Mask {
    /// A mask from row-major bytes (any non-zero byte is object).
    pub fn from_raw(width: u32, height: u32, mut data: Vec<u8>) -> Result<Mask, MaskSizeError> {
        let expected = width as usize * height as usize;
        if data.len() != expected {
            return Err(MaskSizeError { width, height, expected, actual: data.len() });
        }
        for b in &mut data {
            *b = (*b != 0) as u8;
        }
        Ok(Mask { width, height, data })
    }

    /// A mask from a per-pixel predicate `f(u, v)`.
    pub fn from_fn(width: u32, height: u32, f: impl Fn(u32, u32) -> bool) -> Mask {
        let mut data = Vec::with_capacity(width as usize * height as usize);
        for v in 0..height {
            for u in 0..width {
                data.push(f(u, v) as u8);
            }
        }
        Mask { width, height, data }
    }

    /// Width, pixels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Height, pixels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// Row-major bytes, `0` or `1`.
    pub fn data(&self) -> &[u8] {
        &self.data
    }

    /// Is pixel `(u, v)` object? Out of range -> false.
    pub fn get(&self, u: u32, v: u32) -> bool {
        u < self.width && v < self.height && self.data[v as usize * self.width as usize + u as usize] != 0
    }

    /// Number of object pixels.
    pub fn count(&self) -> usize {
        self.data.iter().filter(|&&b| b != 0).count()
    }

    /// Intersection over union with another mask of the same size (`None` if sizes differ; 1 when
    /// both are empty).
    pub fn iou(&self, other: &Mask) -> Option<f64> {
        if self.width != other.width || self.height != other.height {
            return None;
        }
        let (mut i, mut u) = (0usize, 0usize);
        for (&a, &b) in self.data.iter().zip(&other.data) {
            i += (a & b) as usize;
            u += (a | b) as usize;
        }
        Some(if u == 0 { 1.0 } else { i as f64 / u as f64 })
    }

    /// As an 8-bit grey image (object 255).
    pub fn to_image(&self) -> image::GrayImage {
        image::GrayImage::from_fn(self.width, self.height, |u, v| image::Luma([if self.get(u, v) { 255 } else { 0 }]))
    }
}

/// Parameters of [`extract_silhouette`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SilhouetteParams {
    /// Background colour, 8-bit RGB.
    pub background: [u8; 3],
    /// Threshold on the largest per-channel difference, 0..1.
    pub threshold: f32,
    /// Dilation disc radius, pixels.
    pub dilate: u32,
    /// Erosion disc radius, pixels.
    pub erode: u32,
}

impl SilhouetteParams {
    /// The Middlebury dino recipe: black background, threshold 0.19, dilate 10 px, erode 7 px.
    pub const MIDDLEBURY: SilhouetteParams =
        SilhouetteParams { background: [0, 0, 0], threshold: 0.19, dilate: 10, erode: 7 };
}

/// Extract a silhouette mask from an RGB image (see the module docs).
pub fn extract_silhouette(image: &RgbImage, params: &SilhouetteParams) -> Mask {
    let (w, h) = image.dimensions();
    let bg = params.background.map(i32::from);
    let mut data: Vec<u8> = image
        .pixels()
        .map(|p| {
            let d = (0..3).map(|c| (i32::from(p.0[c]) - bg[c]).unsigned_abs()).max().unwrap_or(0);
            (d as f32 / 255.0 > params.threshold) as u8
        })
        .collect();
    data = dilate_disc(&data, w as usize, h as usize, params.dilate, 1);
    data = dilate_disc(&data, w as usize, h as usize, params.erode, 0);
    Mask { width: w, height: h, data }
}

/// Dilate the pixels equal to `value` with a disc of radius `r`: the output pixel is `value` when any
/// pixel of value `value` lies within the disc around it (pixels outside the image never count).
/// With `value = 0` this is an erosion of the object.
fn dilate_disc(src: &[u8], w: usize, h: usize, r: u32, value: u8) -> Vec<u8> {
    if r == 0 || w == 0 || h == 0 {
        return src.to_vec();
    }
    let r = r as i64;
    // Per-row prefix counts of pixels equal to `value`.
    let stride = w + 1;
    let mut prefix = vec![0u32; stride * h];
    prefix.par_chunks_mut(stride).zip(src.par_chunks(w)).for_each(|(p, row)| {
        for x in 0..w {
            p[x + 1] = p[x] + (row[x] == value) as u32;
        }
    });
    let half: Vec<i64> = (-r..=r).map(|dy| ((r * r - dy * dy) as f64).sqrt().floor() as i64).collect();
    let mut out = vec![0u8; w * h];
    out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        for (x, o) in row.iter_mut().enumerate() {
            let mut hit = false;
            for (n, dy) in (-r..=r).enumerate() {
                let yy = y as i64 + dy;
                if yy < 0 || yy >= h as i64 {
                    continue;
                }
                let a = (x as i64 - half[n]).max(0) as usize;
                let b = ((x as i64 + half[n] + 1).min(w as i64)) as usize;
                let p = &prefix[yy as usize * stride..];
                if p[b] > p[a] {
                    hit = true;
                    break;
                }
            }
            *o = if hit { value } else { 1 - value };
        }
    });
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn threshold_uses_the_largest_channel_difference() {
        let mut img = RgbImage::new(3, 1);
        img.put_pixel(0, 0, image::Rgb([60, 0, 0])); // 0.235 > 0.19 on red only
        img.put_pixel(1, 0, image::Rgb([40, 40, 40])); // 0.157
        img.put_pixel(2, 0, image::Rgb([0, 0, 49])); // 0.192
        let p = SilhouetteParams { background: [0, 0, 0], threshold: 0.19, dilate: 0, erode: 0 };
        let m = extract_silhouette(&img, &p);
        assert_eq!(m.data(), &[1, 0, 1]);
        let p = SilhouetteParams { background: [60, 0, 0], ..p };
        assert_eq!(extract_silhouette(&img, &p).data(), &[0, 0, 1]);
    }

    #[test]
    fn dilation_of_a_point_is_a_disc_and_erosion_undoes_it() {
        let (w, h) = (31usize, 29usize);
        let mut src = vec![0u8; w * h];
        src[14 * w + 15] = 1;
        let d = dilate_disc(&src, w, h, 5, 1);
        for y in 0..h {
            for x in 0..w {
                let (dx, dy) = (x as i64 - 15, y as i64 - 14);
                assert_eq!(d[y * w + x] == 1, dx * dx + dy * dy <= 25, "{x} {y}");
            }
        }
        let e = dilate_disc(&d, w, h, 5, 0);
        assert_eq!(e, src);
    }

    #[test]
    fn erosion_ignores_the_image_border() {
        let (w, h) = (10usize, 8usize);
        let src = vec![1u8; w * h];
        assert_eq!(dilate_disc(&src, w, h, 3, 0), src);
        assert!(Mask::from_raw(3, 3, vec![0; 8]).is_err());
    }
}

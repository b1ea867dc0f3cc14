//! The projector-camera response: black and white levels and gamma, measured from images of
//! uniform grey levels, and the pattern pre-distortion that makes projected sinusoids linear.
//!
//! Model: a camera pixel sees `black + (white - black) · (v / 255)^γ` when the projector shows
//! grey level `v` (black = the projector's black level plus ambient, white = full white; camera
//! grey levels). Phase shifting assumes `γ = 1`; with `γ ≈ 2.2` the fringes carry harmonics that
//! alias into the N-step phase as a periodic error. [`ResponseCurve::fit`] measures `γ` from the
//! pixels that see the projector well, and [`ResponseCurve::compensation_lut`] gives the input
//! level to send for each wanted linear level, `v' = 255 · (v / 255)^(1/γ)`.

/// Errors of [`ResponseCurve::fit`].
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GammaError {
    /// Fewer than 3 levels, or levels without 0 and 255, or not one image per level.
    #[error("{levels} projected levels with {images} images: need >= 3 levels including 0 and 255, one image each")]
    Levels {
        /// Levels given.
        levels: usize,
        /// Images given.
        images: usize,
    },
    /// Images of different sizes.
    #[error("image {index} holds {found} bytes, the first holds {expected}")]
    ImageSize {
        /// Position of the image.
        index: usize,
        /// Bytes of the first image.
        expected: usize,
        /// Bytes of this image.
        found: usize,
    },
    /// Too few pixels see the projector with a white-black contrast of at least `min_contrast`.
    #[error("only {pixels} pixels see the projector with white - black >= {min_contrast} grey levels")]
    NoContrast {
        /// Pixels that passed.
        pixels: usize,
        /// The contrast asked for, grey levels.
        min_contrast: f64,
    },
}

/// A fitted projector-camera response.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ResponseCurve {
    /// Exponent of the projector's input-to-light response (1 = linear).
    pub gamma: f64,
    /// Median camera level of projected black over the lit pixels, 8-bit grey levels.
    pub black: f64,
    /// Median camera level of projected white over the lit pixels, 8-bit grey levels.
    pub white: f64,
}

impl ResponseCurve {
    /// Fits the response to images of uniform projected grey `levels` (one 8-bit grey camera
    /// image each, same size; 0 and 255 among the levels). Uses the pixels whose white minus black
    /// is at least `min_contrast` grey levels; for every other level the median over those pixels
    /// of the normalised response `(I - black) / (white - black)` is fitted by least squares in
    /// log-log to `(v / 255)^γ` (levels whose response is below 2% or above 98% are left out: noise
    /// and clipping dominate there).
    pub fn fit(levels: &[u8], images: &[&[u8]], min_contrast: f64) -> Result<ResponseCurve, GammaError> {
        let (Some(ib), Some(iw)) = (levels.iter().position(|&l| l == 0), levels.iter().position(|&l| l == 255)) else {
            return Err(GammaError::Levels { levels: levels.len(), images: images.len() });
        };
        if levels.len() < 3 || images.len() != levels.len() {
            return Err(GammaError::Levels { levels: levels.len(), images: images.len() });
        }
        let n = images[0].len();
        if let Some((index, img)) = images.iter().enumerate().find(|(_, i)| i.len() != n) {
            return Err(GammaError::ImageSize { index, expected: n, found: img.len() });
        }
        let (bi, wi) = (images[ib], images[iw]);
        let lit: Vec<usize> = (0..n).filter(|&i| f64::from(wi[i]) - f64::from(bi[i]) >= min_contrast).collect();
        if lit.len() < 16 {
            return Err(GammaError::NoContrast { pixels: lit.len(), min_contrast });
        }
        let median = |mut v: Vec<f64>| {
            v.sort_by(f64::total_cmp);
            v[v.len() / 2]
        };
        let black = median(lit.iter().map(|&i| f64::from(bi[i])).collect());
        let white = median(lit.iter().map(|&i| f64::from(wi[i])).collect());
        let (mut sxx, mut sxy) = (0.0, 0.0);
        for (&level, img) in levels.iter().zip(images) {
            if level == 0 || level == 255 {
                continue;
            }
            let r = median(
                lit.iter()
                    .map(|&i| (f64::from(img[i]) - f64::from(bi[i])) / (f64::from(wi[i]) - f64::from(bi[i])))
                    .collect(),
            );
            if !(0.02..=0.98).contains(&r) {
                continue;
            }
            // Through the origin in log-log: ln r = γ ln(v / 255).
            let x = (f64::from(level) / 255.0).ln();
            sxx += x * x;
            sxy += x * r.ln();
        }
        if sxx == 0.0 {
            return Err(GammaError::Levels { levels: levels.len(), images: images.len() });
        }
        Ok(ResponseCurve { gamma: sxy / sxx, black, white })
    }

    /// The input level to send for each wanted linear level: `lut[v] = round(255 (v/255)^(1/γ))`.
    pub fn compensation_lut(&self) -> [u8; 256] {
        let inv = if self.gamma.is_finite() && self.gamma > 0.0 { 1.0 / self.gamma } else { 1.0 };
        let mut lut = [0u8; 256];
        for (v, o) in lut.iter_mut().enumerate() {
            *o = (255.0 * (v as f64 / 255.0).powf(inv)).round().clamp(0.0, 255.0) as u8;
        }
        lut
    }
}

/// The grey levels [`ResponseCurve::fit`] is usually given: 0, 32, .., 224, 255.
pub fn calibration_levels() -> Vec<u8> {
    let mut l: Vec<u8> = (0..8).map(|i| (i * 32) as u8).collect();
    l.push(255);
    l
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fits_a_synthetic_gamma_and_inverts_it() {
        let levels = calibration_levels();
        for gamma in [1.0, 1.8, 2.2, 2.6] {
            // 100 pixels with different gains and black levels, plus a dark unlit block.
            let images: Vec<Vec<u8>> = levels
                .iter()
                .map(|&v| {
                    (0..120)
                        .map(|i| {
                            if i >= 100 {
                                return 3;
                            }
                            let (b, w) = (10.0 + (i % 7) as f64, 180.0 + (i % 13) as f64 * 5.0);
                            (b + (w - b) * (f64::from(v) / 255.0).powf(gamma)).round() as u8
                        })
                        .collect()
                })
                .collect();
            let s: Vec<&[u8]> = images.iter().map(Vec::as_slice).collect();
            let r = ResponseCurve::fit(&levels, &s, 40.0).expect("fits");
            assert!((r.gamma - gamma).abs() < 0.05, "fitted {} for {gamma}", r.gamma);
            assert!(r.black >= 10.0 && r.black <= 16.0 && r.white >= 180.0);
            let lut = r.compensation_lut();
            for v in [64u8, 128, 192] {
                let out = 255.0 * (f64::from(lut[v as usize]) / 255.0).powf(gamma);
                assert!((out - f64::from(v)).abs() < 4.0, "gamma {gamma}: {v} -> {out}");
            }
        }
    }

    #[test]
    fn refuses_bad_inputs() {
        let img = vec![0u8; 10];
        assert!(matches!(ResponseCurve::fit(&[0, 255], &[&img, &img], 10.0), Err(GammaError::Levels { .. })));
        assert!(matches!(
            ResponseCurve::fit(&[0, 128, 255], &[&img, &img, &img[..5]], 10.0),
            Err(GammaError::ImageSize { .. })
        ));
        assert!(matches!(
            ResponseCurve::fit(&[0, 128, 255], &[&img, &img, &img], 10.0),
            Err(GammaError::NoContrast { .. })
        ));
    }
}

//! Shadow detection for shadow carving: which pixels of one turntable position lie in the cast or
//! attached shadow of each light, from one frame per light (only that light on) and one ambient frame
//! (all lights off).
//!
//! # The test
//! Per pixel, `s₀` is the ambient frame's `R + G + B` and `sₖ` that of light `k`'s frame; the direct
//! term of light `k` is `dₖ = sₖ - s₀`. Under Lambertian shading with reflectance `a` both terms scale
//! with `a`: `s₀ ∝ a·ambient`, `dₖ ∝ a·Eₖ` (`Eₖ` = the light's irradiance, 0 in shadow), so the ratio
//! `dₖ / s₀ = Eₖ / ambient` does not depend on the albedo. That is what makes the test robust to dark
//! surfaces, as long as the surface is bright enough to measure at all.
//!
//! - A pixel is **unknown** (never shadow, never used to carve) when any channel of any of its frames
//!   is at or above `saturation` (specular highlights and clipped pixels: the ratio is meaningless),
//!   when `s₀ < min_ambient` (too dark: low albedo, the ratio is noise), or, if `lit_ratio > 0`, when
//!   no light lights it clearly, `max dₖ < lit_ratio · s₀`. The default `lit_ratio = 0` leaves that
//!   last test off: the ambient frame is already a per-pixel reference for the albedo, so a pixel that
//!   every light leaves dark (deep in a pit) is a shadow of every light, and those are the shadows that
//!   carve pits. Set it above 0 on rigs whose ambient frame is too weak to serve as the reference,
//!   so that a pixel counts only when some other light shows it lit (the comparison across lights).
//! - A known pixel is **shadowed by light `k`** when `dₖ <= shadow_ratio · s₀`.
//! - The shadow masks are then **eroded** by `erode_px` (a pixel stays shadow only if every pixel of
//!   the `(2r+1)²` square around it is shadow). Erosion removes isolated noise pixels, pulls shadow
//!   regions back from their blurred boundaries and from grazing terminators (where `Eₖ` fades to 0
//!   continuously), and makes sure a voxel whose centre projects into an eroded shadow pixel is seen
//!   through shadow over the whole of its footprint. The carving rule's conservativeness depends on
//!   a shadow pixel really being in shadow, so errors must go towards "not shadow".
//!
//! With the defaults (`shadow_ratio = 0.15`, ambient 0.25 of full scale) a light counts as shadowing a
//! point when it adds less than 0.0375 of full-scale irradiance there: a light of intensity 0.5 at
//! 0.45 m is then within about 3.5° of grazing. Pixel noise of σ levels per channel makes the ratio's
//! noise about `2.5σ / s₀`; with `min_ambient = 45` (15 levels per channel) and σ = 1 that is 0.05.

use image::RgbImage;
use rayon::prelude::*;

use super::silhouette::Mask;

/// Thresholds of [`detect_shadows`]; see the module documentation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ShadowParams {
    /// A known pixel is shadowed by light `k` when `dₖ <= shadow_ratio · s₀` (dimensionless).
    pub shadow_ratio: f32,
    /// If above 0, a pixel is known only if some light adds at least `lit_ratio · s₀`
    /// (dimensionless); 0 turns that test off.
    pub lit_ratio: f32,
    /// A pixel is known only if its ambient `R + G + B` is at least this, 8-bit levels summed (0..765).
    pub min_ambient: f32,
    /// A pixel with any channel of any frame at or above this 8-bit level is unknown.
    pub saturation: u8,
    /// Erosion of the shadow masks, pixels (square radius).
    pub erode_px: u32,
}

impl Default for ShadowParams {
    fn default() -> Self {
        ShadowParams { shadow_ratio: 0.15, lit_ratio: 0.0, min_ambient: 45.0, saturation: 250, erode_px: 2 }
    }
}

/// The shadows of one turntable position.
#[derive(Debug, Clone)]
pub struct ShadowMaps {
    /// Per light (in the order the frames were given): eroded shadow mask, `1` = shadowed by it.
    pub shadows: Vec<Mask>,
    /// `1` = unknown (saturated, too dark, or lit by no light); never shadow in any mask.
    pub unknown: Mask,
}

/// Frames that cannot be compared.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ShadowError {
    /// A light frame's size differs from the ambient frame's.
    #[error("frame of light {index} is {actual:?} pixels, the ambient frame {expected:?}")]
    SizeMismatch {
        /// Position of the frame in the list given.
        index: usize,
        /// Ambient frame size (width, height).
        expected: (u32, u32),
        /// This frame's size.
        actual: (u32, u32),
    },
    /// No light frames.
    #[error("shadow detection needs at least one light frame")]
    NoLights,
}

/// Detect each light's shadows from an `ambient` frame (all lights off) and one frame per light
/// (`lit[k]`: only light `k` on), all of one camera at one turntable position.
pub fn detect_shadows(ambient: &RgbImage, lit: &[&RgbImage], params: &ShadowParams) -> Result<ShadowMaps, ShadowError> {
    if lit.is_empty() {
        return Err(ShadowError::NoLights);
    }
    let (w, h) = ambient.dimensions();
    for (index, f) in lit.iter().enumerate() {
        if f.dimensions() != (w, h) {
            return Err(ShadowError::SizeMismatch { index, expected: (w, h), actual: f.dimensions() });
        }
    }
    let n = lit.len();
    let npx = w as usize * h as usize;
    // Raw per-pixel classification: bit k = shadowed by light k; bit 31 = unknown.
    const UNKNOWN: u32 = 1 << 31;
    let lights = n.min(31);
    let mut raw = vec![0u32; npx];
    let a = ambient.as_raw();
    raw.par_iter_mut().enumerate().for_each(|(i, out)| {
        let px = |img: &[u8]| -> ([u8; 3], f32) {
            let c = [img[3 * i], img[3 * i + 1], img[3 * i + 2]];
            (c, c[0] as f32 + c[1] as f32 + c[2] as f32)
        };
        let (c0, s0) = px(a);
        let mut saturated = c0.iter().any(|&c| c >= params.saturation);
        let mut dmax = f32::NEG_INFINITY;
        let mut bits = 0u32;
        for (k, f) in lit.iter().enumerate().take(lights) {
            let (c, s) = px(f.as_raw());
            saturated |= c.iter().any(|&c| c >= params.saturation);
            let d = s - s0;
            dmax = dmax.max(d);
            if d <= params.shadow_ratio * s0 {
                bits |= 1 << k;
            }
        }
        let unlit = params.lit_ratio > 0.0 && dmax < params.lit_ratio * s0;
        *out = if saturated || s0 < params.min_ambient || unlit { UNKNOWN } else { bits };
    });
    let unknown = Mask::from_raw(w, h, raw.iter().map(|&b| (b & UNKNOWN != 0) as u8).collect())
        .unwrap_or_else(|_| Mask::from_fn(w, h, |_, _| true));
    let shadows = (0..n)
        .map(|k| {
            let bit = if k < lights { 1u32 << k } else { 0 };
            let m: Vec<u8> = raw.iter().map(|&b| (b & UNKNOWN == 0 && b & bit != 0) as u8).collect();
            erode_square(&m, w as usize, h as usize, params.erode_px as usize)
        })
        .map(|data| Mask::from_raw(w, h, data).unwrap_or_else(|_| Mask::from_fn(w, h, |_, _| false)))
        .collect();
    Ok(ShadowMaps { shadows, unknown })
}

/// Erosion with a `(2r+1)²` square; pixels outside the image count as not set (so nothing within
/// `r` of the border survives: a shadow cut by the border is not known to be whole).
fn erode_square(m: &[u8], w: usize, h: usize, r: usize) -> Vec<u8> {
    if r == 0 {
        return m.to_vec();
    }
    // Separable: rows, then columns (min over a window).
    let mut rows = vec![0u8; m.len()];
    rows.par_chunks_mut(w.max(1)).enumerate().for_each(|(v, row)| {
        let src = &m[v * w..(v + 1) * w];
        for u in 0..w {
            row[u] = (u >= r && u + r < w && src[u - r..=u + r].iter().all(|&b| b != 0)) as u8;
        }
    });
    let mut out = vec![0u8; m.len()];
    out.par_chunks_mut(w.max(1)).enumerate().for_each(|(v, row)| {
        if v < r || v + r >= h {
            return;
        }
        for (u, o) in row.iter_mut().enumerate() {
            *o = (v - r..=v + r).all(|vv| rows[vv * w + u] != 0) as u8;
        }
    });
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn flat(w: u32, h: u32, c: [u8; 3]) -> RgbImage {
        RgbImage::from_fn(w, h, |_, _| image::Rgb(c))
    }

    #[test]
    fn shadow_is_where_one_light_adds_nothing() {
        let ambient = flat(20, 20, [30, 30, 30]);
        let a = flat(20, 20, [90, 90, 90]);
        // Light b lights the left half only.
        let b = RgbImage::from_fn(20, 20, |u, _| image::Rgb(if u < 10 { [80, 80, 80] } else { [31, 30, 30] }));
        let p = ShadowParams { erode_px: 1, ..ShadowParams::default() };
        let maps = detect_shadows(&ambient, &[&a, &b], &p).expect("same sizes");
        assert_eq!(maps.shadows[0].count(), 0);
        assert!(maps.shadows[1].get(15, 10));
        assert!(!maps.shadows[1].get(5, 10));
        // Eroded: the column next to the boundary and the image border are not shadow.
        assert!(!maps.shadows[1].get(10, 10));
        assert!(!maps.shadows[1].get(19, 10));
        assert_eq!(maps.unknown.count(), 0);
    }

    #[test]
    fn dark_and_saturated_pixels_are_unknown() {
        // Ambient 3 levels per channel: too dark to tell.
        let ambient = flat(8, 8, [3, 3, 3]);
        let a = flat(8, 8, [10, 10, 10]);
        let b = flat(8, 8, [3, 3, 3]);
        let maps = detect_shadows(&ambient, &[&a, &b], &ShadowParams::default()).expect("same sizes");
        assert_eq!(maps.unknown.count(), 64);
        assert_eq!(maps.shadows[1].count(), 0);
        // Saturated light frame.
        let ambient = flat(8, 8, [60, 60, 60]);
        let a = flat(8, 8, [255, 200, 200]);
        let maps = detect_shadows(&ambient, &[&a, &ambient], &ShadowParams { erode_px: 0, ..Default::default() })
            .expect("same sizes");
        assert_eq!(maps.unknown.count(), 64);
        assert_eq!(maps.shadows[1].count(), 0);
    }

    #[test]
    fn ratio_test_ignores_albedo() {
        // A dark but measurable surface (albedo 0.25 of the bright one) shadows the same way.
        for level in [120u8, 30] {
            let ambient = flat(9, 9, [level; 3]);
            let lit_a = flat(9, 9, [2 * level; 3]);
            let b = flat(9, 9, [level; 3]);
            let maps = detect_shadows(&ambient, &[&lit_a, &b], &ShadowParams { erode_px: 0, ..Default::default() })
                .expect("same sizes");
            assert_eq!(maps.unknown.count(), 0, "level {level}");
            assert_eq!(maps.shadows[1].count(), 81, "level {level}");
            assert_eq!(maps.shadows[0].count(), 0, "level {level}");
        }
    }

    #[test]
    fn dark_under_every_light_is_shadow_unless_a_lit_light_is_required() {
        let ambient = flat(8, 8, [60, 60, 60]);
        let a = flat(8, 8, [61, 60, 60]);
        let b = flat(8, 8, [60, 60, 61]);
        let p = ShadowParams { erode_px: 0, ..ShadowParams::default() };
        let maps = detect_shadows(&ambient, &[&a, &b], &p).expect("same sizes");
        assert_eq!((maps.shadows[0].count(), maps.shadows[1].count(), maps.unknown.count()), (64, 64, 0));
        let p = ShadowParams { lit_ratio: 0.5, ..p };
        let maps = detect_shadows(&ambient, &[&a, &b], &p).expect("same sizes");
        assert_eq!((maps.shadows[0].count(), maps.shadows[1].count(), maps.unknown.count()), (0, 0, 64));
    }

    #[test]
    fn mismatched_sizes_are_an_error() {
        let ambient = flat(8, 8, [60, 60, 60]);
        let a = flat(8, 9, [90, 90, 90]);
        assert!(matches!(
            detect_shadows(&ambient, &[&a], &ShadowParams::default()),
            Err(ShadowError::SizeMismatch { index: 0, .. })
        ));
        assert!(matches!(detect_shadows(&ambient, &[], &ShadowParams::default()), Err(ShadowError::NoLights)));
    }
}

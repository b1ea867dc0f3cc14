//! Sub-pixel projector coordinates from a decoded Gray/binary [`ProjectorMap`] by stripe-edge
//! interpolation.
//!
//! A decoded column map is a staircase: where the camera samples the surface more finely than the
//! projector, a run of camera pixels along a camera row decodes to the same projector column `c`.
//! Where the run is bounded on both sides by its neighbours `c - 1` and `c + 1` (or `c + 1` and `c - 1`
//! for a mirrored view), its two ends are the projector's column edges `c` and `c + 1` (continuous
//! projector coordinates), located at the camera pixel boundaries where the code changes. The column
//! of each pixel centre in the run is interpolated linearly between them. Each edge is known to half
//! a camera pixel, so the error shrinks with the number of camera pixels per projector column; runs
//! without both neighbours (object borders, shadows, camera pixels coarser than the projector's)
//! keep the column's centre `c + 0.5`. Rows are interpolated the same way along camera columns.
//!
//! (Reading the stripe edge from the intensities of the finest pattern pair would be finer still;
//! this works on any decoded map, e.g. a recorded one.)

use super::coords::ProjectorCoords;
use super::decode::{ProjectorMap, INVALID};

/// Interpolates one line of codes (`len` values `stride` apart from `codes[start]`) into `out`
/// (same indexing).
fn interpolate_line(codes: &[u16], start: usize, stride: usize, len: usize, out: &mut [f32]) {
    let at = |i: usize| codes[start + i * stride];
    let mut a = 0;
    while a < len {
        let c = at(a);
        let mut b = a;
        while b + 1 < len && at(b + 1) == c {
            b += 1;
        }
        if c != INVALID {
            let left = (a > 0).then(|| at(a - 1)).filter(|&v| v != INVALID);
            let right = (b + 1 < len).then(|| at(b + 1)).filter(|&v| v != INVALID);
            let cf = f32::from(c);
            let span = (b + 1 - a) as f32;
            let up = |n: Option<u16>, d: i32| n.is_some_and(|n| i32::from(n) == i32::from(c) + d);
            for i in a..=b {
                // Position of the pixel centre within the run, 0..1.
                let t = (i - a) as f32 + 0.5;
                let v = if up(left, -1) && up(right, 1) {
                    cf + t / span
                } else if up(left, 1) && up(right, -1) {
                    cf + 1.0 - t / span
                } else {
                    cf + 0.5
                };
                out[start + i * stride] = v;
            }
        } else {
            for i in a..=b {
                out[start + i * stride] = f32::NAN;
            }
        }
        a = b + 1;
    }
}

/// Continuous projector coordinates of `map` with stripe-edge interpolation (see the module docs):
/// columns along camera rows, and, with `with_rows`, rows along camera columns. Invalid pixels are
/// `NaN`.
pub fn interpolate_stripe_edges(map: &ProjectorMap, with_rows: bool) -> ProjectorCoords {
    let (w, h) = (map.width(), map.height());
    let mut column = vec![f32::NAN; w * h];
    for y in 0..h {
        interpolate_line(map.columns(), y * w, 1, w, &mut column);
    }
    let row = with_rows.then(|| {
        let mut row = vec![f32::NAN; w * h];
        for x in 0..w {
            interpolate_line(map.rows(), x, w, h, &mut row);
        }
        row
    });
    ProjectorCoords { width: w, height: h, column, row }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn line(codes: &[u16]) -> Vec<f32> {
        let mut out = vec![0.0; codes.len()];
        interpolate_line(codes, 0, 1, codes.len(), &mut out);
        out
    }

    #[test]
    fn runs_between_both_neighbours_are_interpolated_from_edge_to_edge() {
        // Three camera pixels per projector column, increasing: column 5 spans pixels 3..6, its edges
        // 5.0 and 6.0 at camera x = 3 and 6, so the centres 3.5, 4.5, 5.5 get 5 + 1/6, 5.5, 5 + 5/6.
        let out = line(&[4, 4, 4, 5, 5, 5, 6, 6, 6]);
        assert!((out[3] - (5.0 + 1.0 / 6.0)).abs() < 1e-6);
        assert!((out[4] - 5.5).abs() < 1e-6);
        assert!((out[5] - (5.0 + 5.0 / 6.0)).abs() < 1e-6);
        // The end runs have one neighbour only: centres.
        assert_eq!(out[0], 4.5);
        assert_eq!(out[8], 6.5);
        // Decreasing (a mirrored view).
        let out = line(&[6, 6, 5, 5, 4, 4]);
        assert!((out[2] - 5.75).abs() < 1e-6 && (out[3] - 5.25).abs() < 1e-6);
    }

    #[test]
    fn invalid_pixels_and_jumps_fall_back() {
        let out = line(&[INVALID, 3, 3, 9, 9, INVALID]);
        assert!(out[0].is_nan() && out[5].is_nan());
        assert_eq!(&out[1..5], &[3.5, 3.5, 9.5, 9.5]);
    }
}

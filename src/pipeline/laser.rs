//! Laser-stripe triangulation and laser plane calibration.
//!
//! A line laser fans a plane of light (rig frame). With the laser off and then on, the difference
//! image shows only the stripe. [`detect_stripe`] finds it with sub-pixel precision, row by row (the
//! stripe must run more up-down than sideways in the image, as with vertical laser planes beside a
//! camera looking at a turntable):
//!
//! - the per-pixel signal is the on-minus-off difference weighted by the laser's colour
//!   (`Σ_c colour_c · (on_c - off_c) / Σ_c colour_c`, 8-bit levels), so a red laser reads the red
//!   channel;
//! - in each row, every run of pixels whose signal reaches `min_peak` is a candidate; a run wider than
//!   `max_width_px` is rejected (a reflection or a lit patch, not a line);
//! - each surviving run gives one peak: the centre of mass of the signal over `±half_window_px` around
//!   the run's maximum (negative values count as 0). A row can thus give several peaks: a stripe that
//!   falls on two surfaces at once (the outer wall of a cup and its inner wall behind) is two points,
//!   both real; the runs must be separated by at least one pixel below `min_peak`.
//!
//! Pixel coordinates are continuous: pixel `(u, v)` covers `[u, u+1) × [v, v+1)`, so a peak exactly
//! on the centre of column 10 is at `u = 10.5`.
//!
//! [`triangulate_peaks`] undistorts each peak into a camera ray (rig frame) and intersects it with
//! the laser plane. [`fit_plane`] fits a plane to points with RANSAC and a least-squares refit of the
//! inliers; [`calibrate_laser_plane`] uses it on stripe points on a known target (a box of known size
//! on the turntable, seen at two or more turntable angles so the stripe points are not collinear).

use image::RgbImage;
use nalgebra::{Matrix3, SymmetricEigen, Vector3};

use crate::geometry::{turntable_rotation, Aabb, CameraModel};

/// Errors of stripe detection, triangulation and plane fitting; each names the offending input.
#[derive(Debug, thiserror::Error)]
pub enum LaserError {
    /// The laser-on and laser-off frames differ in size, or do not match the camera.
    #[error("frame sizes differ: laser off {off:?}, laser on {on:?}, camera {camera:?} (pixels)")]
    FrameSize {
        /// Laser-off frame `(width, height)`.
        off: (u32, u32),
        /// Laser-on frame `(width, height)`.
        on: (u32, u32),
        /// Camera `(width, height)`.
        camera: (u32, u32),
    },
    /// The laser colour is black, so no channel carries the stripe.
    #[error("laser colour {colour:?} has no channel to detect the stripe in")]
    BlackLaser {
        /// The configured colour.
        colour: [u8; 3],
    },
    /// A stripe parameter is out of range.
    #[error("stripe parameter {name} = {value} is out of range ({expected})")]
    Parameter {
        /// Its name.
        name: &'static str,
        /// The value given.
        value: f64,
        /// What is accepted.
        expected: &'static str,
    },
    /// A laser plane normal is zero or not finite.
    #[error("laser plane normal {normal:?} is not a finite non-zero vector")]
    DegeneratePlane {
        /// The normal given.
        normal: [f64; 3],
    },
    /// No plane holds the points of two or more target poses.
    #[error("no plane holds {needed} or more stripe points of each of two target poses ({poses} poses, {points} points, at most {largest} in one pose)")]
    PlaneAcrossPoses {
        /// Poses given.
        poses: usize,
        /// Points over all poses.
        points: usize,
        /// Points of the largest pose.
        largest: usize,
        /// Inliers each of two poses must give.
        needed: usize,
    },
    /// Too few points, or points that do not span a plane, for a plane fit.
    #[error("plane fit: {points} points, {inliers} on the best plane (at least {needed} needed, not all on a line)")]
    PlaneFit {
        /// Points given.
        points: usize,
        /// Inliers of the best candidate.
        inliers: usize,
        /// Minimum inlier count.
        needed: usize,
    },
}

/// Parameters of [`detect_stripe`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StripeParams {
    /// Smallest laser signal (on minus off, 8-bit levels) of a stripe pixel.
    pub min_peak: f32,
    /// Widest accepted run of stripe pixels in a row, pixels.
    pub max_width_px: u32,
    /// Half-width of the centre-of-mass window around a run's maximum, pixels.
    pub half_window_px: u32,
}

impl Default for StripeParams {
    fn default() -> Self {
        StripeParams { min_peak: 40.0, max_width_px: 8, half_window_px: 3 }
    }
}

impl StripeParams {
    fn check(&self) -> Result<(), LaserError> {
        if !(self.min_peak.is_finite() && self.min_peak > 0.0) {
            let value = f64::from(self.min_peak);
            return Err(LaserError::Parameter { name: "min_peak", value, expected: "positive, finite levels" });
        }
        if self.max_width_px == 0 {
            return Err(LaserError::Parameter { name: "max_width_px", value: 0.0, expected: ">= 1 pixel" });
        }
        Ok(())
    }
}

/// One stripe peak: sub-pixel column `u` in row `v` (continuous pixel coordinates, see the module
/// docs) and its signal at the maximum, 8-bit levels.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StripePeak {
    /// Column, continuous pixel coordinates.
    pub u: f64,
    /// Row index.
    pub v: u32,
    /// Laser signal at the run's maximum, 8-bit levels.
    pub strength: f32,
}

/// The laser signal per pixel (row-major, 8-bit levels, may be negative): the on-minus-off
/// difference weighted by the laser colour.
pub fn laser_signal(off: &RgbImage, on: &RgbImage, colour: [u8; 3]) -> Result<Vec<f32>, LaserError> {
    if off.dimensions() != on.dimensions() {
        return Err(LaserError::FrameSize { off: off.dimensions(), on: on.dimensions(), camera: on.dimensions() });
    }
    let w = colour.map(f32::from);
    let sum = w[0] + w[1] + w[2];
    if sum <= 0.0 {
        return Err(LaserError::BlackLaser { colour });
    }
    let w = w.map(|x| x / sum);
    Ok(off
        .as_raw()
        .chunks_exact(3)
        .zip(on.as_raw().chunks_exact(3))
        .map(|(a, b)| (0..3).map(|c| w[c] * (f32::from(b[c]) - f32::from(a[c]))).sum())
        .collect())
}

/// The peaks of one row of laser signal (see the module docs), appended to `out` with row index `v`.
pub fn row_peaks(row: &[f32], v: u32, params: &StripeParams, out: &mut Vec<StripePeak>) {
    let n = row.len();
    let mut u = 0;
    while u < n {
        if row[u] < params.min_peak {
            u += 1;
            continue;
        }
        let start = u;
        while u < n && row[u] >= params.min_peak {
            u += 1;
        }
        let end = u; // exclusive
        if end - start > params.max_width_px as usize {
            continue;
        }
        let (imax, &peak) = row[start..end]
            .iter()
            .enumerate()
            .max_by(|a, b| a.1.total_cmp(b.1))
            .map(|(i, p)| (start + i, p))
            .unwrap_or((start, &row[start]));
        let h = params.half_window_px as usize;
        let (lo, hi) = (imax.saturating_sub(h), (imax + h + 1).min(n));
        let (mut sw, mut swu) = (0.0f64, 0.0f64);
        for (i, &s) in row.iter().enumerate().take(hi).skip(lo) {
            let wgt = f64::from(s.max(0.0));
            sw += wgt;
            swu += wgt * (i as f64 + 0.5);
        }
        if sw > 0.0 {
            out.push(StripePeak { u: swu / sw, v, strength: peak });
        }
    }
}

/// The stripe's peaks in every row (see the module docs), from a laser-off and a laser-on frame of
/// the same camera and a laser of colour `colour`.
pub fn detect_stripe(
    off: &RgbImage,
    on: &RgbImage,
    colour: [u8; 3],
    params: &StripeParams,
) -> Result<Vec<StripePeak>, LaserError> {
    params.check()?;
    let signal = laser_signal(off, on, colour)?;
    let w = off.width() as usize;
    let mut out = Vec::new();
    if w == 0 {
        return Ok(out);
    }
    for (v, row) in signal.chunks_exact(w).enumerate() {
        row_peaks(row, v as u32, params, &mut out);
    }
    Ok(out)
}

/// A plane `normal · x = offset_m` (rig frame unless said otherwise), `normal` a unit vector.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Plane {
    /// Unit normal.
    pub normal: [f64; 3],
    /// Signed distance of the plane from the origin along `normal`, metres.
    pub offset_m: f64,
}

impl Plane {
    /// The plane through `point` (metres) with normal `normal` (any non-zero length).
    pub fn through(point: [f64; 3], normal: [f64; 3]) -> Result<Plane, LaserError> {
        let n = Vector3::from(normal);
        let len = n.norm();
        if !(len.is_finite() && len > 0.0 && point.iter().all(|x| x.is_finite())) {
            return Err(LaserError::DegeneratePlane { normal });
        }
        let n = n / len;
        Ok(Plane { normal: n.into(), offset_m: n.dot(&Vector3::from(point)) })
    }

    /// Signed distance of `p` from the plane, metres (positive on the normal's side).
    pub fn distance(&self, p: &Vector3<f64>) -> f64 {
        Vector3::from(self.normal).dot(p) - self.offset_m
    }

    /// Where the ray `origin + t·dir` (t > 0) meets the plane; `None` if it runs parallel or away.
    pub fn intersect(&self, origin: &Vector3<f64>, dir: &Vector3<f64>) -> Option<Vector3<f64>> {
        let n = Vector3::from(self.normal);
        let denom = n.dot(dir);
        if denom.abs() < 1e-12 {
            return None;
        }
        let t = (self.offset_m - n.dot(origin)) / denom;
        (t > 0.0 && t.is_finite()).then(|| origin + dir * t)
    }

    /// The angle between the two planes' normals, degrees (0..=90, orientation ignored).
    pub fn angle_deg(&self, other: &Plane) -> f64 {
        let c = Vector3::from(self.normal).dot(&Vector3::from(other.normal)).abs().min(1.0);
        c.acos().to_degrees()
    }

    /// How far `other` is from this plane at `at` (metres): the distance between the points where the
    /// line through `at` along this plane's normal meets the two planes.
    pub fn offset_at(&self, other: &Plane, at: &Vector3<f64>) -> Option<f64> {
        let n = Vector3::from(self.normal);
        let a = self.intersect_line(at, &n)?;
        let b = other.intersect_line(at, &n)?;
        Some((a - b).norm())
    }

    fn intersect_line(&self, origin: &Vector3<f64>, dir: &Vector3<f64>) -> Option<Vector3<f64>> {
        let n = Vector3::from(self.normal);
        let denom = n.dot(dir);
        (denom.abs() > 1e-12).then(|| origin + dir * ((self.offset_m - n.dot(origin)) / denom))
    }
}

/// Triangulate stripe peaks seen by `camera` (rig frame) on the laser plane `plane` (rig frame):
/// each peak's pixel is undistorted into a ray and intersected with the plane. Returns, per peak that
/// meets the plane in front of the camera, the point (rig frame, metres) and the peak.
pub fn triangulate_peaks(camera: &CameraModel, plane: &Plane, peaks: &[StripePeak]) -> Vec<(Vector3<f64>, StripePeak)> {
    let c = camera.centre();
    peaks
        .iter()
        .filter_map(|pk| {
            let ray = camera.pixel_ray(pk.u, f64::from(pk.v) + 0.5);
            plane.intersect(&c, &ray).map(|p| (p, *pk))
        })
        .collect()
}

/// The best-fitting plane of `points` (metres) by total least squares (normal = direction of least
/// variance); `None` for fewer than 3 points or points on a line.
pub fn least_squares_plane(points: &[Vector3<f64>]) -> Option<Plane> {
    if points.len() < 3 {
        return None;
    }
    let mean = points.iter().sum::<Vector3<f64>>() / points.len() as f64;
    let mut cov = Matrix3::zeros();
    for p in points {
        let d = p - mean;
        cov += d * d.transpose();
    }
    let eig = SymmetricEigen::new(cov);
    let mut idx = [0usize, 1, 2];
    idx.sort_by(|&a, &b| eig.eigenvalues[a].total_cmp(&eig.eigenvalues[b]));
    // Points on a line: the two smallest variances both vanish next to the largest.
    if eig.eigenvalues[idx[1]] <= 1e-12 * eig.eigenvalues[idx[2]].max(1e-300) {
        return None;
    }
    let n = eig.eigenvectors.column(idx[0]).into_owned().try_normalize(1e-12)?;
    Some(Plane { normal: n.into(), offset_m: n.dot(&mean) })
}

/// Parameters of [`fit_plane`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlaneFitParams {
    /// A point within this distance of a candidate plane is its inlier, metres.
    pub inlier_m: f64,
    /// RANSAC candidates tried.
    pub iterations: u32,
    /// Seed of the deterministic sampler.
    pub seed: u64,
}

impl Default for PlaneFitParams {
    fn default() -> Self {
        PlaneFitParams { inlier_m: 0.5e-3, iterations: 400, seed: 1 }
    }
}

/// A fitted plane and how well it fits.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct PlaneFit {
    /// The plane (least squares over the inliers).
    pub plane: Plane,
    /// Points within `inlier_m` of the final plane.
    pub inliers: usize,
    /// Points given.
    pub points: usize,
    /// Root-mean-square distance of the inliers from the plane, metres.
    pub rms_m: f64,
}

/// Fit a plane to `points` (metres) robustly: RANSAC over random triples, the candidate with the most
/// inliers refitted by least squares over its inliers, twice. Needs at least 3 inliers not on a line.
pub fn fit_plane(points: &[Vector3<f64>], params: &PlaneFitParams) -> Result<PlaneFit, LaserError> {
    check_inlier_distance(params)?;
    let n = points.len();
    let fail = |inliers| LaserError::PlaneFit { points: n, inliers, needed: 3 };
    if n < 3 {
        return Err(fail(0));
    }
    let mut next = sample_indices(params.seed);
    let inliers_of = |plane: &Plane| -> Vec<Vector3<f64>> {
        points.iter().filter(|p| plane.distance(p).abs() <= params.inlier_m).copied().collect()
    };
    let mut best: Option<(usize, Plane)> = None;
    for _ in 0..params.iterations.max(1) {
        let (a, b, c) = (points[next(n)], points[next(n)], points[next(n)]);
        let normal = (b - a).cross(&(c - a));
        let Ok(plane) = Plane::through(a.into(), normal.into()) else { continue };
        let count = points.iter().filter(|p| plane.distance(p).abs() <= params.inlier_m).count();
        if best.is_none_or(|(k, _)| count > k) {
            best = Some((count, plane));
        }
    }
    let (_, mut plane) = best.ok_or_else(|| fail(0))?;
    for _ in 0..2 {
        let inl = inliers_of(&plane);
        plane = least_squares_plane(&inl).ok_or_else(|| fail(inl.len()))?;
    }
    let inl = inliers_of(&plane);
    if inl.len() < 3 {
        return Err(fail(inl.len()));
    }
    let rms_m = (inl.iter().map(|p| plane.distance(p).powi(2)).sum::<f64>() / inl.len() as f64).sqrt();
    Ok(PlaneFit { plane, inliers: inl.len(), points: n, rms_m })
}

/// A seeded stream of indices below `m` (splitmix64), so plane fits are repeatable.
fn sample_indices(seed: u64) -> impl FnMut(usize) -> usize {
    let mut state = seed ^ 0x9e37_79b9_7f4a_7c15;
    move |m: usize| {
        state = state.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = state;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        ((z ^ (z >> 31)) % m as u64) as usize
    }
}

/// The inlier distance must be a positive number of metres.
fn check_inlier_distance(params: &PlaneFitParams) -> Result<(), LaserError> {
    if params.inlier_m.is_finite() && params.inlier_m > 0.0 {
        Ok(())
    } else {
        Err(LaserError::Parameter { name: "inlier_m", value: params.inlier_m, expected: "positive metres" })
    }
}

/// The laser planes in stripe points of several target poses (`sets[k]`: the points of pose `k`, a
/// board's stripe points say): one pose's points lie on the target's surface (a board: one plane
/// holding every laser's line), so only a plane that two or more poses each give at least
/// `min_per_set` inliers is a laser plane. Planes are found one after another (RANSAC over triples
/// drawn from two or more poses, the best candidate refitted by least squares over its inliers,
/// twice; its inliers are then removed), at most `max_planes`, until no candidate has the support
/// of two poses.
pub fn fit_planes_across(
    sets: &[Vec<Vector3<f64>>],
    params: &PlaneFitParams,
    min_per_set: usize,
    max_planes: usize,
) -> Result<Vec<PlaneFit>, LaserError> {
    check_inlier_distance(params)?;
    let min_per_set = min_per_set.max(3);
    let mut left: Vec<(Vector3<f64>, usize)> =
        sets.iter().enumerate().flat_map(|(k, s)| s.iter().map(move |p| (*p, k))).collect();
    let total = left.len();
    let mut next = sample_indices(params.seed);
    // Inliers per set, and whether two sets give `min_per_set` each.
    let support = |plane: &Plane, pts: &[(Vector3<f64>, usize)]| {
        let mut per = vec![0usize; sets.len()];
        for (p, k) in pts {
            if plane.distance(p).abs() <= params.inlier_m {
                per[*k] += 1;
            }
        }
        let sum: usize = per.iter().sum();
        (sum, per.iter().filter(|&&c| c >= min_per_set).count() >= 2)
    };
    let mut fits = Vec::new();
    while fits.len() < max_planes && left.len() >= 3 {
        let mut best: Option<(usize, Plane)> = None;
        for _ in 0..params.iterations.max(1) {
            let a = left[next(left.len())];
            let b = left[next(left.len())];
            let c = left[next(left.len())];
            if a.1 == b.1 && b.1 == c.1 {
                continue;
            }
            let Ok(plane) = Plane::through(a.0.into(), (b.0 - a.0).cross(&(c.0 - a.0)).into()) else { continue };
            let (count, two) = support(&plane, &left);
            if two && best.is_none_or(|(k, _)| count > k) {
                best = Some((count, plane));
            }
        }
        let Some((_, mut plane)) = best else { break };
        let inliers_of = |plane: &Plane, pts: &[(Vector3<f64>, usize)]| -> Vec<Vector3<f64>> {
            pts.iter().filter(|(p, _)| plane.distance(p).abs() <= params.inlier_m).map(|(p, _)| *p).collect()
        };
        for _ in 0..2 {
            let inl = inliers_of(&plane, &left);
            match least_squares_plane(&inl) {
                Some(p) => plane = p,
                None => break,
            }
        }
        let (_, two) = support(&plane, &left);
        let inl = inliers_of(&plane, &left);
        if !two || inl.len() < 3 {
            break;
        }
        let rms_m = (inl.iter().map(|p| plane.distance(p).powi(2)).sum::<f64>() / inl.len() as f64).sqrt();
        fits.push(PlaneFit { plane, inliers: inl.len(), points: total, rms_m });
        left.retain(|(p, _)| plane.distance(p).abs() > params.inlier_m);
    }
    if fits.is_empty() {
        let most = sets.iter().map(Vec::len).max().unwrap_or(0);
        return Err(LaserError::PlaneAcrossPoses {
            poses: sets.len(),
            points: total,
            largest: most,
            needed: min_per_set,
        });
    }
    Ok(fits)
}

/// Where the ray `origin + t·dir` (t > 0) first meets the box `target` (same frame), if it does.
pub fn ray_box(target: &Aabb, origin: &Vector3<f64>, dir: &Vector3<f64>) -> Option<Vector3<f64>> {
    let (mut t0, mut t1) = (0.0f64, f64::INFINITY);
    for a in 0..3 {
        if dir[a].abs() < 1e-15 {
            if origin[a] < target.min[a] || origin[a] > target.max[a] {
                return None;
            }
            continue;
        }
        let (ta, tb) = ((target.min[a] - origin[a]) / dir[a], (target.max[a] - origin[a]) / dir[a]);
        t0 = t0.max(ta.min(tb));
        t1 = t1.min(ta.max(tb));
    }
    (t0 <= t1 && t0 > 0.0).then(|| origin + dir * t0)
}

/// One capture of the calibration target: the turntable angle (degrees) and the laser-off and
/// laser-on frames.
#[derive(Debug, Clone, Copy)]
pub struct CalibrationView<'a> {
    /// Turntable angle, degrees.
    pub angle_deg: f64,
    /// Laser off.
    pub off: &'a RgbImage,
    /// Laser on.
    pub on: &'a RgbImage,
}

/// Estimate a laser plane (rig frame) from captures of a known target: a box `target` standing on
/// the turntable (object frame, metres). Each stripe peak's camera ray is turned into the object
/// frame, met with the box (its first face along the ray: the point the camera sees), and the point
/// turned back into the rig frame; the plane is [`fit_plane`] of all points. The views must show the
/// stripe on at least two non-parallel faces in total (e.g. two turntable angles), or the points lie
/// on one line.
pub fn calibrate_laser_plane(
    camera: &CameraModel,
    target: &Aabb,
    views: &[CalibrationView<'_>],
    colour: [u8; 3],
    stripe: &StripeParams,
    fit: &PlaneFitParams,
) -> Result<PlaneFit, LaserError> {
    let mut points = Vec::new();
    let c = camera.centre();
    for view in views {
        if view.off.dimensions() != (camera.width, camera.height) {
            return Err(LaserError::FrameSize {
                off: view.off.dimensions(),
                on: view.on.dimensions(),
                camera: (camera.width, camera.height),
            });
        }
        let to_obj = turntable_rotation(-view.angle_deg);
        let to_rig = turntable_rotation(view.angle_deg);
        for pk in detect_stripe(view.off, view.on, colour, stripe)? {
            let ray = camera.pixel_ray(pk.u, f64::from(pk.v) + 0.5);
            if let Some(hit) = ray_box(target, &(to_obj * c), &(to_obj * ray)) {
                points.push(to_rig * hit);
            }
        }
    }
    fit_plane(&points, fit)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A row with a Gaussian stripe of peak `a` levels and sigma `s` px centred at `c` (continuous
    /// coordinates), integrated over each pixel (as a camera does), plus an offset.
    fn gaussian_row(n: usize, c: f64, s: f64, a: f64) -> Vec<f32> {
        (0..n)
            .map(|i| {
                // Midpoint rule over 20 sub-samples of the pixel.
                let v: f64 = (0..20)
                    .map(|k| {
                        let x = i as f64 + (k as f64 + 0.5) / 20.0;
                        a * (-(x - c).powi(2) / (2.0 * s * s)).exp()
                    })
                    .sum::<f64>()
                    / 20.0;
                v as f32
            })
            .collect()
    }

    /// Two lasers' stripes on a board at two poses: four lines, each pose's two on its board
    /// plane. The fit finds the two laser planes, never a board plane.
    #[test]
    fn laser_planes_come_from_two_poses_not_from_one_board() {
        let lasers = [
            Plane::through([0.0, 0.0, 0.3], [-0.87, 0.0, 0.49]).expect("plane"),
            Plane::through([0.0, 0.0, 0.3], [0.85, 0.0, 0.53]).expect("plane"),
        ];
        // Vertical boards (normal in the x-z plane) at 260 mm and 280 mm, turned by 0 and 25 degrees.
        let boards = [(0.26, 0.0f64), (0.28, 25.0f64)];
        let mut sets = Vec::new();
        for (z, turn) in boards {
            let n = Vector3::new(turn.to_radians().sin(), 0.0, -turn.to_radians().cos());
            let board = Plane::through([0.0, 0.0, z], n.into()).expect("board");
            let mut pts = Vec::new();
            for l in &lasers {
                // The line board ∩ laser, sampled along y with 0.05 mm of noise.
                let d = Vector3::from(board.normal).cross(&Vector3::from(l.normal)).normalize();
                let (a, b) = (Vector3::from(board.normal), Vector3::from(l.normal));
                // A point on both planes with y = 0: solve the 2x2 system in x, z.
                let det = a[0] * b[2] - a[2] * b[0];
                let x = (board.offset_m * b[2] - a[2] * l.offset_m) / det;
                let zz = (a[0] * l.offset_m - board.offset_m * b[0]) / det;
                let p0 = Vector3::new(x, 0.0, zz);
                for k in 0..200 {
                    let t = -0.03 + 0.08 * k as f64 / 200.0;
                    let noise = 5e-5 * ((k * 7919 % 13) as f64 / 6.0 - 1.0);
                    pts.push(p0 + d * (t / d[1]) + Vector3::from(l.normal) * noise);
                }
            }
            sets.push(pts);
        }
        let fits = fit_planes_across(&sets, &PlaneFitParams { inlier_m: 5e-4, iterations: 2000, seed: 3 }, 20, 4)
            .expect("fits");
        assert_eq!(fits.len(), 2, "{fits:?}");
        for l in &lasers {
            let f = fits.iter().min_by(|a, b| a.plane.angle_deg(l).total_cmp(&b.plane.angle_deg(l))).expect("fit");
            assert!(f.plane.angle_deg(l) < 0.1 && f.inliers == 400, "{f:?} for {l:?}");
        }
        // One pose alone is only lines on one board: refused.
        let e = fit_planes_across(&sets[..1], &PlaneFitParams::default(), 20, 4).expect_err("one pose");
        assert!(e.to_string().contains("two target poses"), "{e}");
    }

    #[test]
    fn gaussian_stripe_peaks_are_sub_pixel() {
        let params = StripeParams { min_peak: 20.0, max_width_px: 10, half_window_px: 4 };
        let mut worst: f64 = 0.0;
        for k in 0..40 {
            let c = 30.0 + k as f64 * 0.137;
            for s in [0.8, 1.2, 1.8] {
                let mut out = Vec::new();
                row_peaks(&gaussian_row(80, c, s, 180.0), 7, &params, &mut out);
                assert_eq!(out.len(), 1, "{c} {s}: {out:?}");
                assert_eq!(out[0].v, 7);
                worst = worst.max((out[0].u - c).abs());
            }
        }
        // Nearest-pixel detection would be off by up to 0.5 px.
        assert!(worst < 0.05, "worst sub-pixel error {worst} px");
    }

    #[test]
    fn rows_keep_separate_runs_and_reject_wide_ones() {
        let params = StripeParams { min_peak: 20.0, max_width_px: 5, half_window_px: 2 };
        let mut row = gaussian_row(100, 20.5, 1.0, 200.0);
        for (x, y) in row.iter_mut().zip(gaussian_row(100, 60.5, 1.0, 120.0)) {
            *x += y;
        }
        // A lit patch 12 px wide: not a line.
        for x in &mut row[80..92] {
            *x += 150.0;
        }
        let mut out = Vec::new();
        row_peaks(&row, 0, &params, &mut out);
        assert_eq!(out.len(), 2, "{out:?}");
        assert!((out[0].u - 20.5).abs() < 0.01 && (out[1].u - 60.5).abs() < 0.01, "{out:?}");
        assert!(out[0].strength > out[1].strength);
        // Noise below the threshold gives nothing.
        out.clear();
        row_peaks(&[5.0, -3.0, 19.0, 2.0], 0, &params, &mut out);
        assert!(out.is_empty());
    }

    #[test]
    fn stripe_in_the_laser_colour_only() {
        let (w, h) = (40, 6);
        let off = RgbImage::from_pixel(w, h, image::Rgb([50, 50, 50]));
        let mut on = off.clone();
        for v in 0..h {
            on.put_pixel(12, v, image::Rgb([250, 50, 50]));
            // A green flash elsewhere is not a red laser.
            on.put_pixel(30, v, image::Rgb([50, 250, 50]));
        }
        let peaks = detect_stripe(&off, &on, [255, 0, 0], &StripeParams::default()).expect("detect");
        assert_eq!(peaks.len(), h as usize);
        assert!(peaks.iter().all(|p| (p.u - 12.5).abs() < 1e-9 && p.strength == 200.0), "{peaks:?}");
        assert!(matches!(
            detect_stripe(&off, &RgbImage::new(3, 3), [255, 0, 0], &StripeParams::default()),
            Err(LaserError::FrameSize { .. })
        ));
        assert!(matches!(
            detect_stripe(&off, &on, [0, 0, 0], &StripeParams::default()),
            Err(LaserError::BlackLaser { .. })
        ));
        let bad = StripeParams { min_peak: f32::NAN, ..StripeParams::default() };
        assert!(matches!(
            detect_stripe(&off, &on, [255, 0, 0], &bad),
            Err(LaserError::Parameter { name: "min_peak", .. })
        ));
    }

    #[test]
    fn ransac_plane_ignores_outliers() {
        let truth = Plane::through([0.01, 0.02, 0.03], [0.3, -0.8, 0.2]).expect("plane");
        let n = Vector3::from(truth.normal);
        let a = n.cross(&Vector3::z()).normalize();
        let b = n.cross(&a);
        let p0 = Vector3::new(0.01, 0.02, 0.03);
        let mut pts = Vec::new();
        for i in 0..30 {
            for j in 0..20 {
                // +-0.1 mm of deterministic "noise" along the normal.
                let e = 1e-4 * (((i * 7 + j * 13) % 11) as f64 / 5.0 - 1.0);
                pts.push(p0 + a * (i as f64 * 0.002) + b * (j as f64 * 0.003) + n * e);
            }
        }
        for k in 0..150 {
            pts.push(Vector3::new((k % 7) as f64 * 0.01, (k % 5) as f64 * 0.013, (k % 3) as f64 * 0.02 + 0.05));
        }
        let fit = fit_plane(&pts, &PlaneFitParams::default()).expect("fit");
        assert!(fit.plane.angle_deg(&truth) < 0.05, "{fit:?}");
        assert!(fit.plane.offset_at(&truth, &p0).expect("not parallel") < 2e-5, "{fit:?}");
        assert!(fit.inliers >= 600 && fit.inliers < 620, "{fit:?}");
        let line: Vec<Vector3<f64>> = (0..10).map(|i| Vector3::new(i as f64, 0.0, 0.0)).collect();
        assert!(matches!(fit_plane(&line, &PlaneFitParams::default()), Err(LaserError::PlaneFit { .. })));
    }

    #[test]
    fn rays_meet_planes_and_boxes() {
        let plane = Plane::through([0.0, 0.0, 0.5], [0.0, 0.0, 2.0]).expect("plane");
        let hit = plane.intersect(&Vector3::zeros(), &Vector3::new(0.0, 0.6, 0.8)).expect("hit");
        assert!((hit - Vector3::new(0.0, 0.375, 0.5)).norm() < 1e-12);
        assert!(plane.intersect(&Vector3::zeros(), &Vector3::new(0.0, 0.0, -1.0)).is_none());
        assert!(Plane::through([0.0; 3], [0.0; 3]).is_err());
        let b = Aabb { min: [-1.0, -1.0, 0.0], max: [1.0, 1.0, 2.0] };
        let hit = ray_box(&b, &Vector3::new(0.0, -5.0, 1.0), &Vector3::new(0.0, 1.0, 0.0)).expect("hit");
        assert!((hit - Vector3::new(0.0, -1.0, 1.0)).norm() < 1e-12);
        assert!(ray_box(&b, &Vector3::new(3.0, -5.0, 1.0), &Vector3::new(0.0, 1.0, 0.0)).is_none());
    }
}

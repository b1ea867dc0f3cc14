//! Triangulation of decoded structured light into a range image: one 3-D point per camera pixel
//! with a projector coordinate, with its colour, a normal from its range-image neighbours, and an
//! outlier test against those neighbours.
//!
//! Frames: the camera and the projector are [`CameraModel`]s posed in one reference frame (the
//! object frame at the view's turntable angle, from `for_turntable_angle`, or the rig frame); the
//! points and normals come out in that frame, metres. Both models include radial distortion.
//!
//! - Camera ray: the undistorted ray through the pixel centre `(x + 0.5, y + 0.5)` from the camera
//!   centre.
//! - Column only: the surface point is where the camera ray meets the set of points the projector
//!   maps to column `c` (a plane through the projector centre without distortion, a slightly curved
//!   surface with it). It is found exactly: start from the distortion-free column plane, then a few
//!   secant steps along the ray on the projector's distorted column `u(t) - c = 0`; a point whose
//!   residual stays above 0.01 projector pixel is rejected.
//! - Column and row: the midpoint of the closest points of the camera ray and the projector ray
//!   through `(c, r)` (undistorted through the projector's model), rejected when the rays pass further
//!   than `max_ray_gap_m` apart.
//!
//! Projector coordinates are continuous (see [`super::coords`]): a code's centre `i + 0.5`, or a
//! sub-pixel value from stripe-edge interpolation ([`super::subpixel`]) or a phase decoder.

use nalgebra::Vector3;
use rayon::prelude::*;

use super::coords::ProjectorCoords;
use super::decode::{ProjectorMap, INVALID};
use crate::geometry::CameraModel;
use crate::pipeline::simd::{has_avx2, run_simd};
use crate::pipeline::PointCloud;

/// Parameters of [`Triangulator::triangulate`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TriangulationParams {
    /// Column+row triangulation: largest distance between the camera and projector rays, metres.
    pub max_ray_gap_m: f64,
    /// A point is kept only if at least this many of its 8 range-image neighbours are valid and lie
    /// within `neighbour_tolerance_m` of it along the camera axis (0 keeps every point).
    pub min_neighbours: u8,
    /// Depth difference to a neighbour that still counts as the same surface, metres.
    pub neighbour_tolerance_m: f64,
}

impl Default for TriangulationParams {
    fn default() -> Self {
        TriangulationParams { max_ray_gap_m: 0.002, min_neighbours: 5, neighbour_tolerance_m: 0.002 }
    }
}

/// Why [`Triangulator`] refused its input.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TriangulateError {
    /// The projector coordinates are not the camera's size.
    #[error("projector coordinates of {found_width}x{found_height} pixels for a {width}x{height} camera")]
    CoordsSize {
        /// Camera width, pixels.
        width: u32,
        /// Camera height, pixels.
        height: u32,
        /// Width of the coordinates, pixels.
        found_width: usize,
        /// Height of the coordinates, pixels.
        found_height: usize,
    },
    /// The colour image is not the camera's size.
    #[error("colour image of {found_width}x{found_height} pixels for a {width}x{height} camera")]
    ColourSize {
        /// Camera width, pixels.
        width: u32,
        /// Camera height, pixels.
        height: u32,
        /// Width of the image, pixels.
        found_width: u32,
        /// Height of the image, pixels.
        found_height: u32,
    },
    /// A camera or projector model holds a non-finite value.
    #[error("the {which} model is not finite")]
    Model {
        /// `"camera"` or `"projector"`.
        which: &'static str,
    },
}

/// One view's triangulated surface: per camera pixel (row-major, `width * height`), the point, its
/// depth along the camera axis, normal and colour. Invalid pixels have a `NaN` point, depth 0 and a
/// zero normal.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RangeImage {
    /// Camera width, pixels.
    pub width: u32,
    /// Camera height, pixels.
    pub height: u32,
    /// Points in the models' reference frame, metres (`NaN` where none).
    pub points: Vec<[f32; 3]>,
    /// Depth along the camera's optical axis, metres (0 where none): the depth map of the view.
    pub depth_m: Vec<f32>,
    /// Unit surface normals, reference frame, facing the camera (zero where none).
    pub normals: Vec<[f32; 3]>,
    /// 8-bit RGB colour from the fully lit frame (black without one).
    pub colours: Vec<[u8; 3]>,
    /// Pixels with a projector coordinate.
    pub decoded: usize,
    /// Pixels triangulated (before the outlier test).
    pub triangulated: usize,
    /// Points removed by the neighbour test.
    pub outliers: usize,
}

impl RangeImage {
    /// Valid points.
    pub fn valid_count(&self) -> usize {
        self.depth_m.iter().filter(|&&d| d > 0.0).count()
    }

    /// The valid points with their normals and colours, reference frame.
    pub fn valid_points(&self) -> impl Iterator<Item = ([f32; 3], [f32; 3], [u8; 3])> + '_ {
        (0..self.depth_m.len())
            .filter(|&i| self.depth_m[i] > 0.0)
            .map(|i| (self.points[i], self.normals[i], self.colours[i]))
    }

    /// The valid points (reference frame, metres) with their normals and colours as one cloud, in
    /// [`RangeImage::valid_points`]' order: each camera row counted, then copied into its place,
    /// rows in parallel.
    pub fn valid_cloud(&self) -> PointCloud {
        let w = (self.width as usize).max(1);
        let n = self.depth_m.len().min(self.points.len()).min(self.normals.len()).min(self.colours.len());
        let rows = n / w;
        let counts: Vec<usize> =
            self.depth_m[..rows * w].par_chunks(w).map(|r| r.iter().filter(|&&d| d > 0.0).count()).collect();
        let total: usize = counts.iter().sum();
        let mut points = vec![[0.0f32; 3]; total];
        let mut normals = vec![[0.0f32; 3]; total];
        let mut colours = vec![[0u8; 3]; total];
        // Each row's share of the three outputs, split off in order.
        let mut parts = Vec::with_capacity(rows);
        let (mut p, mut nr, mut c) = (&mut points[..], &mut normals[..], &mut colours[..]);
        for &k in &counts {
            let (p0, p1) = p.split_at_mut(k);
            let (n0, n1) = nr.split_at_mut(k);
            let (c0, c1) = c.split_at_mut(k);
            parts.push((p0, n0, c0));
            (p, nr, c) = (p1, n1, c1);
        }
        parts.into_par_iter().enumerate().for_each(|(y, (p, nr, c))| {
            let range = y * w..(y + 1) * w;
            let valid = self.depth_m[range.clone()].iter().enumerate().filter(|(_, &d)| d > 0.0);
            for (k, (x, _)) in valid.enumerate() {
                let i = range.start + x;
                (p[k], nr[k], c[k]) = (self.points[i], self.normals[i], self.colours[i]);
            }
        });
        PointCloud::from_parts(points, Some(normals), Some(colours)).expect("one normal and colour per point")
    }
}

/// The distortion-free plane of projector column `c` (continuous pixels) in the reference frame:
/// `(n, d)` with `n·x + d = 0`.
fn column_plane(projector: &CameraModel, c: f64) -> (Vector3<f64>, f64) {
    let k = &projector.intrinsics;
    let xn = (c - k.cx) / k.fx;
    let r = &projector.pose.rotation;
    let t = &projector.pose.translation;
    // In projector coordinates the plane is X - xn Z = 0.
    let np = Vector3::new(1.0, 0.0, -xn);
    (r.transpose() * np, np.dot(t))
}

/// The point on the camera ray `o + s·d` (s > 0) that the projector maps to column `c`.
fn ray_column(projector: &CameraModel, o: &Vector3<f64>, d: &Vector3<f64>, c: f64) -> Option<Vector3<f64>> {
    let (n, off) = column_plane(projector, c);
    let denom = n.dot(d);
    if denom.abs() < 1e-12 {
        return None;
    }
    let mut s = -(n.dot(o) + off) / denom;
    if !(s.is_finite() && s > 0.0) {
        return None;
    }
    let u = |s: f64| projector.project(&(o + d * s)).map(|p| p.x - c);
    if projector.intrinsics.has_distortion() || projector.intrinsics.skew != 0.0 {
        // Secant steps on the distorted column; the plane's solution is the first guess.
        let mut f0 = u(s)?;
        let mut s_prev = s * (1.0 + 1e-4);
        let mut f_prev = u(s_prev)?;
        for _ in 0..8 {
            if f0.abs() < 1e-6 {
                break;
            }
            let slope = (f0 - f_prev) / (s - s_prev);
            if !(slope.is_finite() && slope != 0.0) {
                return None;
            }
            let next = s - f0 / slope;
            (s_prev, f_prev) = (s, f0);
            s = next;
            if !(s.is_finite() && s > 0.0) {
                return None;
            }
            f0 = u(s)?;
        }
        if f0.abs() > 0.01 {
            return None;
        }
    } else {
        // Must be in front of the projector.
        u(s)?;
    }
    Some(o + d * s)
}

/// Midpoint of the closest points of rays `o1 + s d1` and `o2 + t d2` (unit directions), both in
/// front of their origins, if they pass within `max_gap` of each other.
fn ray_ray(
    o1: &Vector3<f64>,
    d1: &Vector3<f64>,
    o2: &Vector3<f64>,
    d2: &Vector3<f64>,
    max_gap: f64,
) -> Option<Vector3<f64>> {
    let w = o1 - o2;
    let b = d1.dot(d2);
    let (dd, e) = (d1.dot(&w), d2.dot(&w));
    let den = 1.0 - b * b;
    if den < 1e-12 {
        return None;
    }
    let s = (b * e - dd) / den;
    let t = (e - b * dd) / den;
    if s <= 0.0 || t <= 0.0 {
        return None;
    }
    let p1 = o1 + d1 * s;
    let p2 = o2 + d2 * t;
    ((p1 - p2).norm() <= max_gap).then(|| (p1 + p2) * 0.5)
}

/// A camera and projector pair prepared for triangulating many views.
///
/// Built once per pair: the camera's undistorted pixel rays (reference frame, through pixel
/// centres, `f32`, scaled so that their camera-frame `z` is 1: a point's distance along its ray is
/// its depth) and the projector's plane and ray coefficients, so that each view costs a few
/// multiply-adds and one division per pixel. The per-view buffers are reused: the outlier-test
/// mask lives here and [`Triangulator::triangulate_into`] writes into a caller's [`RangeImage`],
/// so that a stream of views allocates nothing once the first is done.
///
/// Work per view, each pass parallel over camera rows (rayon) and reading only the rows it needs:
/// 1. triangulate every decoded pixel (point and depth), counting decoded and triangulated pixels;
/// 2. the neighbour test on the 8-neighbourhood in the image grid (depths only), into a byte mask;
/// 3. normals from the kept image-grid neighbours, and colours;
/// 4. the points and depths of removed pixels cleared.
///
/// Passes 1-3 compute every pixel of a row (or of a block of one) and mask the failed ones instead
/// of branching per pixel, so that the compiler vectorises them, and run compiled for AVX2 when the
/// CPU has it (`f64` points, `f32` normals; no FMA, so every CPU rounds the same). Pass 1 takes this
/// path for a projector without distortion; a distorting projector's column surface or pixel rays
/// are solved pixel by pixel.
#[derive(Debug, Clone)]
pub struct Triangulator {
    camera: CameraModel,
    projector: CameraModel,
    /// Per pixel, row-major: the camera ray at unit camera depth, reference frame.
    rays: Vec<[f32; 3]>,
    /// Per pixel: 1 where the point passed the neighbour test (scratch, reused across views).
    keep: Vec<u8>,
    /// Wall seconds of the last view's four passes.
    pass_s: [f64; 4],
    /// The row kernels run compiled for AVX2 (the CPU has it).
    simd: bool,
}

/// Where a pixel's projector coordinates come from: continuous coordinates, or the integer codes of
/// a Gray/binary [`ProjectorMap`] taken at their centres (`i + 0.5`, as
/// [`ProjectorCoords::from_map`] gives them) without building the coordinates.
#[derive(Clone, Copy)]
enum Source<'a> {
    Coords(&'a ProjectorCoords),
    Map { map: &'a ProjectorMap, rows: bool },
}

impl Source<'_> {
    fn has_rows(&self) -> bool {
        match self {
            Source::Coords(c) => c.row.is_some(),
            Source::Map { rows, .. } => *rows,
        }
    }

    /// Column and row (`NaN` row without rows) of pixel `i`, or `None` when it has none.
    #[inline(always)]
    fn at(&self, i: usize) -> Option<(f32, f32)> {
        match self {
            Source::Coords(c) => {
                let col = c.column[i];
                let row = c.row.as_ref().map_or(f32::NAN, |r| r[i]);
                (col.is_finite() && (c.row.is_none() || row.is_finite())).then_some((col, row))
            }
            Source::Map { map, rows } => {
                let col = map.columns()[i];
                let row = map.rows().get(i).copied().unwrap_or(INVALID);
                let centre = |v: u16| f32::from(v) + 0.5;
                (col != INVALID && (!rows || row != INVALID))
                    .then(|| (centre(col), if *rows { centre(row) } else { f32::NAN }))
            }
        }
    }
}

/// The per-view constants of pass 1, `f64`.
struct Geometry<'a> {
    projector: &'a CameraModel,
    /// Camera centre.
    o: Vector3<f64>,
    /// Camera optical axis (row 2 of its rotation): depth of `p` is `axis · (p - o)`.
    axis: Vector3<f64>,
    /// Projector centre.
    po: Vector3<f64>,
    /// Projector rotation rows: `x_proj = R p + t`.
    pr: [Vector3<f64>; 3],
    pt: Vector3<f64>,
    /// The projector has neither distortion nor skew (the column surface is a plane).
    plane: bool,
    /// The projector has no distortion (its pixel rays are linear in the pixel).
    linear: bool,
    max_gap: f64,
}

impl Geometry<'_> {
    /// The point of camera ray `o + s d` (`d` at unit depth) lit by projector column `c` (and row
    /// `r` when finite), with its depth, for a projector that [`Linear`] does not take (distortion,
    /// or skew without rows): the distorted column surface by secant steps, or the projector's
    /// undistorted pixel ray.
    #[inline(always)]
    fn point(&self, d: Vector3<f64>, c: f64, r: f64) -> Option<(Vector3<f64>, f64)> {
        let o = &self.o;
        // The projector without distortion (the column plane, ray-ray) goes through [`Linear`].
        let p = if r.is_nan() {
            ray_column(self.projector, o, &d.normalize(), c)?
        } else {
            let pd = self.projector.pixel_ray(c, r);
            ray_ray(o, &d.normalize(), &self.po, &pd, self.max_gap)?
        };
        let z = self.axis.dot(&(p - o));
        (z > 0.0 && p.iter().all(|v| v.is_finite())).then_some((p, z))
    }
}

impl Triangulator {
    /// Checks both models and precomputes the camera's pixel rays.
    pub fn new(camera: &CameraModel, projector: &CameraModel) -> Result<Triangulator, TriangulateError> {
        if !camera.is_finite() {
            return Err(TriangulateError::Model { which: "camera" });
        }
        if !projector.is_finite() {
            return Err(TriangulateError::Model { which: "projector" });
        }
        let w = camera.width as usize;
        let mut rays = vec![[0.0f32; 3]; w * camera.height as usize];
        let rt = camera.pose.rotation.transpose();
        rays.par_chunks_mut(w.max(1)).enumerate().for_each(|(y, row)| {
            for (x, r) in row.iter_mut().enumerate() {
                let (xn, yn) = camera.intrinsics.pixel_to_normalised(x as f64 + 0.5, y as f64 + 0.5);
                let d = rt * Vector3::new(xn, yn, 1.0);
                *r = [d.x as f32, d.y as f32, d.z as f32];
            }
        });
        Ok(Triangulator {
            camera: *camera,
            projector: *projector,
            rays,
            keep: Vec::new(),
            pass_s: [0.0; 4],
            simd: has_avx2(),
        })
    }

    /// Triangulates `coords` (the projector coordinates seen by the camera's pixels), colours the
    /// points from `white` (the fully lit frame, optional), estimates normals from the range-image
    /// neighbours and removes the points without enough neighbours on the same surface.
    /// Uses ray-ray triangulation when `coords` has rows, the column surface otherwise.
    pub fn triangulate(
        &mut self,
        coords: &ProjectorCoords,
        white: Option<&image::RgbImage>,
        params: &TriangulationParams,
    ) -> Result<RangeImage, TriangulateError> {
        let mut out = RangeImage::default();
        self.triangulate_into(coords, white, params, &mut out)?;
        Ok(out)
    }

    /// [`Triangulator::triangulate`] into `out`, reusing its buffers (a view of the same camera
    /// allocates nothing).
    pub fn triangulate_into(
        &mut self,
        coords: &ProjectorCoords,
        white: Option<&image::RgbImage>,
        params: &TriangulationParams,
        out: &mut RangeImage,
    ) -> Result<(), TriangulateError> {
        self.check(coords.width, coords.height, white)?;
        self.run(Source::Coords(coords), white, params, out);
        Ok(())
    }

    /// Triangulates a decoded Gray/binary map at its code centres, as
    /// `triangulate_into(&ProjectorCoords::from_map(map, rows), ..)` does, without building the
    /// coordinates: decode output goes straight into points.
    pub fn triangulate_map_into(
        &mut self,
        map: &ProjectorMap,
        rows: bool,
        white: Option<&image::RgbImage>,
        params: &TriangulationParams,
        out: &mut RangeImage,
    ) -> Result<(), TriangulateError> {
        self.check(map.width(), map.height(), white)?;
        self.run(Source::Map { map, rows }, white, params, out);
        Ok(())
    }

    /// Wall seconds of the last view's passes: triangulation, neighbour test, normals and colours,
    /// clearing the removed points (for benchmarks and logs).
    pub fn last_pass_seconds(&self) -> [f64; 4] {
        self.pass_s
    }

    fn check(&self, width: usize, height: usize, white: Option<&image::RgbImage>) -> Result<(), TriangulateError> {
        let (w, h) = (self.camera.width, self.camera.height);
        if width != w as usize || height != h as usize {
            return Err(TriangulateError::CoordsSize { width: w, height: h, found_width: width, found_height: height });
        }
        if let Some(img) = white {
            if img.width() != w || img.height() != h {
                return Err(TriangulateError::ColourSize {
                    width: w,
                    height: h,
                    found_width: img.width(),
                    found_height: img.height(),
                });
            }
        }
        Ok(())
    }

    /// The per-view work, sizes already checked.
    fn run(
        &mut self,
        src: Source<'_>,
        white: Option<&image::RgbImage>,
        params: &TriangulationParams,
        out: &mut RangeImage,
    ) {
        let (camera, projector) = (&self.camera, &self.projector);
        let w = camera.width as usize;
        let n = w * camera.height as usize;
        out.width = camera.width;
        out.height = camera.height;
        for v in [&mut out.points, &mut out.normals] {
            v.resize(n, [0.0; 3]);
        }
        out.depth_m.resize(n, 0.0);
        out.colours.resize(n, [0; 3]);
        self.keep.resize(n, 0);
        if n == 0 {
            (out.decoded, out.triangulated, out.outliers) = (0, 0, 0);
            return;
        }
        let k = &projector.intrinsics;
        let linear = !k.has_distortion();
        let r = &projector.pose.rotation;
        let geo = Geometry {
            projector,
            o: camera.centre(),
            axis: camera.pose.rotation.row(2).transpose(),
            po: projector.centre(),
            pr: [r.row(0).transpose(), r.row(1).transpose(), r.row(2).transpose()],
            pt: projector.pose.translation,
            plane: linear && k.skew == 0.0,
            linear,
            max_gap: params.max_ray_gap_m,
        };
        let rows = src.has_rows();
        let mut lap = {
            let mut t = std::time::Instant::now();
            move || {
                let now = std::time::Instant::now();
                let s = (now - t).as_secs_f64();
                t = now;
                s
            }
        };
        let (decoded, triangulated) = triangulate_pass(&geo, &self.rays, src, rows, w, self.simd, out);
        self.pass_s[0] = lap();
        let kept = neighbour_pass(&out.depth_m, w, params, &mut self.keep, self.simd);
        self.pass_s[1] = lap();
        normal_pass(
            &geo.o,
            &out.points,
            &out.depth_m,
            &self.keep,
            w,
            params,
            white,
            self.simd,
            &mut out.normals,
            &mut out.colours,
        );
        self.pass_s[2] = lap();
        clear_pass(&self.keep, w, &mut out.points, &mut out.depth_m);
        self.pass_s[3] = lap();
        (out.decoded, out.triangulated, out.outliers) = (decoded, triangulated, triangulated - kept);
    }
}

/// Pass 1: point and depth per pixel (`NaN` and 0 where none); returns (decoded, triangulated).
/// A projector without distortion (ray-ray with rows, the column plane without skew) takes the
/// branch-free row kernel of [`Linear`], compiled for AVX2 when `simd`; anything else the per-pixel
/// [`Geometry::point`].
#[inline(never)]
fn triangulate_pass(
    geo: &Geometry<'_>,
    rays: &[[f32; 3]],
    src: Source<'_>,
    rows: bool,
    w: usize,
    simd: bool,
    out: &mut RangeImage,
) -> (usize, usize) {
    let linear = Linear::of(geo, rows);
    out.points
        .par_chunks_mut(w)
        .zip(out.depth_m.par_chunks_mut(w))
        .enumerate()
        .map(|(y, (pr, dr))| {
            let base = y * w;
            let ray_row = &rays[base..base + w];
            if let Some(k) = &linear {
                return match src {
                    Source::Map { map, .. } => {
                        let rws = if rows { &map.rows()[base..base + w] } else { &[][..] };
                        let row = MapRow { cols: &map.columns()[base..base + w], rows: rws };
                        k.row(&row, ray_row, pr, dr, simd)
                    }
                    Source::Coords(c) => {
                        let rws = c.row.as_ref().map_or(&[][..], |r| &r[base..base + w]);
                        let row = CoordsRow { cols: &c.column[base..base + w], rows: rws };
                        k.row(&row, ray_row, pr, dr, simd)
                    }
                };
            }
            let (mut decoded, mut triangulated) = (0, 0);
            for (x, (p, z)) in pr.iter_mut().zip(dr.iter_mut()).enumerate() {
                *p = [f32::NAN; 3];
                *z = 0.0;
                let Some((c, r)) = src.at(base + x) else { continue };
                decoded += 1;
                let d = ray_row[x];
                let d = Vector3::new(f64::from(d[0]), f64::from(d[1]), f64::from(d[2]));
                let r = if rows { f64::from(r) } else { f64::NAN };
                if let Some((q, depth)) = geo.point(d, f64::from(c), r) {
                    *p = [q.x as f32, q.y as f32, q.z as f32];
                    *z = depth as f32;
                    triangulated += 1;
                }
            }
            (decoded, triangulated)
        })
        .reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1))
}

/// One camera row of projector coordinates for [`Linear::row`].
trait RowCoords {
    /// Whether pixel `x` has coordinates, and its column and row (`f64`; the row is unused
    /// without rows).
    fn at(&self, x: usize) -> (bool, f64, f64);
}

/// A row of a Gray/binary map, taken at code centres (`i + 0.5`).
struct MapRow<'a> {
    cols: &'a [u16],
    /// Empty without rows.
    rows: &'a [u16],
}

impl RowCoords for MapRow<'_> {
    #[inline(always)]
    fn at(&self, x: usize) -> (bool, f64, f64) {
        let c = self.cols[x];
        let r = self.rows.get(x).copied().unwrap_or(0);
        let ok = (c != INVALID) & (r != INVALID);
        (ok, f64::from(f32::from(c) + 0.5), f64::from(f32::from(r) + 0.5))
    }
}

/// A row of continuous coordinates (`NaN` invalid).
struct CoordsRow<'a> {
    cols: &'a [f32],
    /// Empty without rows.
    rows: &'a [f32],
}

impl RowCoords for CoordsRow<'_> {
    #[inline(always)]
    fn at(&self, x: usize) -> (bool, f64, f64) {
        let c = self.cols[x];
        let r = self.rows.get(x).copied().unwrap_or(0.0);
        (c.is_finite() & r.is_finite(), f64::from(c), f64::from(r))
    }
}

/// Pass 1 for a projector without distortion: the column plane `n · x + off = 0` with
/// `n = R^T (1, 0, -xn)`, `off = t_x - xn t_z` (columns only, no skew), or the closest points of the
/// camera ray and the projector ray `R^T (xn, yn, 1)` (columns and rows), without a branch per
/// pixel: every pixel of a block is computed and the failed ones masked, so that the compiler
/// vectorises it (`f64`, reference frame, metres).
#[derive(Debug, Clone, Copy)]
struct Linear {
    /// Ray-ray (columns and rows) or the column plane (columns only, no skew).
    rays: bool,
    o: [f64; 3],
    axis: [f64; 3],
    po: [f64; 3],
    /// `o - po`.
    w: [f64; 3],
    pr: [[f64; 3]; 3],
    pt: [f64; 3],
    cx: f64,
    cy: f64,
    /// `1 / fx`, `1 / fy`: the kernels multiply by them instead of dividing.
    inv_fx: f64,
    inv_fy: f64,
    skew: f64,
    max_gap2: f64,
}

impl Linear {
    /// The kernel for `geo`, or `None` when the projector needs the per-pixel path (distortion, or
    /// skew without rows).
    fn of(geo: &Geometry<'_>, rows: bool) -> Option<Linear> {
        if !(geo.linear && (rows || geo.plane)) {
            return None;
        }
        let v = |x: &Vector3<f64>| [x.x, x.y, x.z];
        let k = &geo.projector.intrinsics;
        Some(Linear {
            rays: rows,
            o: v(&geo.o),
            axis: v(&geo.axis),
            po: v(&geo.po),
            w: v(&(geo.o - geo.po)),
            pr: geo.pr.each_ref().map(v),
            pt: v(&geo.pt),
            cx: k.cx,
            cy: k.cy,
            inv_fx: 1.0 / k.fx,
            inv_fy: 1.0 / k.fy,
            skew: k.skew,
            max_gap2: geo.max_gap * geo.max_gap,
        })
    }

    /// Ray-ray points of one block: `lanes.c`, `lanes.r` and the ray `lanes.d` in, the point, depth
    /// and whether it holds out (rays closer than `max_ray_gap_m`, both in front of their centres;
    /// every test folded into the flag).
    #[inline(always)]
    fn ray_ray_block(&self, lanes: &mut Lanes) {
        let [ox, oy, oz] = self.o;
        let [wx, wy, wz] = self.w;
        let [r0, r1, r2] = self.pr;
        for l in 0..BLOCK {
            let (dx, dy, dz) = (lanes.d[0][l], lanes.d[1][l], lanes.d[2][l]);
            let yn = (lanes.r[l] - self.cy) * self.inv_fy;
            let xn = (lanes.c[l] - self.cx - self.skew * yn) * self.inv_fx;
            let (ex, ey, ez) =
                (r2[0] + r0[0] * xn + r1[0] * yn, r2[1] + r0[1] * xn + r1[1] * yn, r2[2] + r0[2] * xn + r1[2] * yn);
            let a = dx * dx + dy * dy + dz * dz;
            let b = dx * ex + dy * ey + dz * ez;
            let cc = ex * ex + ey * ey + ez * ez;
            let dd = dx * wx + dy * wy + dz * wz;
            let e = ex * wx + ey * wy + ez * wz;
            let den = a * cc - b * b;
            let inv = 1.0 / den;
            let s = (b * e - cc * dd) * inv;
            let t = (a * e - b * dd) * inv;
            let (p1x, p1y, p1z) = (ox + dx * s, oy + dy * s, oz + dz * s);
            let (p2x, p2y, p2z) = (self.po[0] + ex * t, self.po[1] + ey * t, self.po[2] + ez * t);
            let (gx, gy, gz) = (p1x - p2x, p1y - p2y, p1z - p2z);
            let ok = (den >= 1e-12 * a * cc) & (s > 0.0) & (t > 0.0) & (gx * gx + gy * gy + gz * gz <= self.max_gap2);
            let (px, py, pz) = ((p1x + p2x) * 0.5, (p1y + p2y) * 0.5, (p1z + p2z) * 0.5);
            self.finish(lanes, l, [px, py, pz], ok);
        }
    }

    /// Column-plane points of one block (columns only, no skew), as [`Linear::ray_ray_block`].
    #[inline(always)]
    fn plane_block(&self, lanes: &mut Lanes) {
        let [ox, oy, oz] = self.o;
        let [r0, _, r2] = self.pr;
        for l in 0..BLOCK {
            let (dx, dy, dz) = (lanes.d[0][l], lanes.d[1][l], lanes.d[2][l]);
            let xn = (lanes.c[l] - self.cx) * self.inv_fx;
            let (nx, ny, nz) = (r0[0] - r2[0] * xn, r0[1] - r2[1] * xn, r0[2] - r2[2] * xn);
            let den = nx * dx + ny * dy + nz * dz;
            let s = -(nx * ox + ny * oy + nz * oz + self.pt[0] - xn * self.pt[2]) / den;
            let (px, py, pz) = (ox + dx * s, oy + dy * s, oz + dz * s);
            let front = r2[0] * px + r2[1] * py + r2[2] * pz + self.pt[2] > 0.0;
            let ok = (den.abs() >= 1e-12) & s.is_finite() & (s > 0.0) & front;
            self.finish(lanes, l, [px, py, pz], ok);
        }
    }

    /// Depth along the camera axis and the last tests (in front, finite) of lane `l`'s point.
    #[inline(always)]
    fn finish(&self, lanes: &mut Lanes, l: usize, p: [f64; 3], ok: bool) {
        let [ax, ay, az] = self.axis;
        let z = ax * (p[0] - self.o[0]) + ay * (p[1] - self.o[1]) + az * (p[2] - self.o[2]);
        let ok = ok & lanes.has[l] & (z > 0.0) & p[0].is_finite() & p[1].is_finite() & p[2].is_finite();
        for (k, &v) in p.iter().enumerate() {
            lanes.p[k][l] = if ok { v as f32 } else { f32::NAN };
        }
        lanes.z[l] = if ok { z as f32 } else { 0.0 };
        lanes.ok[l] = ok;
    }

    /// One camera row: points and depths written (`NaN` and 0 where none); returns (decoded,
    /// triangulated).
    fn row(
        &self,
        src: &impl RowCoords,
        rays: &[[f32; 3]],
        points: &mut [[f32; 3]],
        depth: &mut [f32],
        simd: bool,
    ) -> (usize, usize) {
        run_simd(
            simd,
            #[inline(always)]
            || self.row_kernel(src, rays, points, depth),
        )
    }

    /// The row in blocks of [`BLOCK`] pixels: coordinates and rays gathered into lanes, the block
    /// computed lane by lane without a branch (so it vectorises), the results scattered back.
    #[inline(always)]
    fn row_kernel(
        &self,
        src: &impl RowCoords,
        rays: &[[f32; 3]],
        points: &mut [[f32; 3]],
        depth: &mut [f32],
    ) -> (usize, usize) {
        let n = points.len().min(depth.len()).min(rays.len());
        let (mut decoded, mut triangulated) = (0usize, 0usize);
        let mut lanes = Lanes::default();
        let mut start = 0;
        while start < n {
            let m = (n - start).min(BLOCK);
            for l in 0..m {
                let (has, c, r) = src.at(start + l);
                lanes.has[l] = has;
                (lanes.c[l], lanes.r[l]) = (c, r);
                for (lane, &v) in lanes.d.iter_mut().zip(&rays[start + l]) {
                    lane[l] = f64::from(v);
                }
                decoded += usize::from(has);
            }
            for l in m..BLOCK {
                lanes.has[l] = false;
            }
            if self.rays {
                self.ray_ray_block(&mut lanes);
            } else {
                self.plane_block(&mut lanes);
            }
            for l in 0..m {
                points[start + l] = [lanes.p[0][l], lanes.p[1][l], lanes.p[2][l]];
                depth[start + l] = lanes.z[l];
                triangulated += usize::from(lanes.ok[l]);
            }
            start += m;
        }
        (decoded, triangulated)
    }
}

/// Pixels per block of [`Linear::row_kernel`].
const BLOCK: usize = 128;

/// One block of pixels for [`Linear`], one array per quantity (structure of arrays).
struct Lanes {
    has: [bool; BLOCK],
    c: [f64; BLOCK],
    r: [f64; BLOCK],
    /// The camera ray, `x`, `y`, `z`.
    d: [[f64; BLOCK]; 3],
    p: [[f32; BLOCK]; 3],
    z: [f32; BLOCK],
    ok: [bool; BLOCK],
}

impl Default for Lanes {
    fn default() -> Lanes {
        Lanes {
            has: [false; BLOCK],
            c: [0.0; BLOCK],
            r: [0.0; BLOCK],
            d: [[0.0; BLOCK]; 3],
            p: [[0.0; BLOCK]; 3],
            z: [0.0; BLOCK],
            ok: [false; BLOCK],
        }
    }
}

/// Pass 2: `keep[i] = 1` where pixel `i` has a point and at least `min_neighbours` of its 8
/// image-grid neighbours have points within `neighbour_tolerance_m` in depth; returns the kept count.
/// The interior of each row runs branch-free ([`neighbour_interior`], AVX2 when `simd`), the two end
/// pixels one by one; a missing row above or below reads as depth 0 (no point).
#[inline(never)]
fn neighbour_pass(depth: &[f32], w: usize, params: &TriangulationParams, keep: &mut [u8], simd: bool) -> usize {
    let tol = params.neighbour_tolerance_m as f32;
    let min = params.min_neighbours;
    let h = depth.len() / w;
    let none = vec![0.0f32; w];
    keep.par_chunks_mut(w)
        .enumerate()
        .map(|(y, kr)| {
            let cur = &depth[y * w..(y + 1) * w];
            let up = if y > 0 { &depth[(y - 1) * w..y * w] } else { &none[..] };
            let down = if y + 1 < h { &depth[(y + 1) * w..(y + 2) * w] } else { &none[..] };
            let rows = [up, cur, down];
            let mut kept = run_simd(
                simd,
                #[inline(always)]
                || neighbour_interior(rows, tol, min, kr),
            );
            let ends: &[usize] = if w == 1 { &[0] } else { &[0, w - 1] };
            for &x in ends {
                let d0 = cur[x];
                let close = |v: f32| u8::from(v > 0.0 && (v - d0).abs() <= tol);
                let cols = [x.checked_sub(1), (x + 1 < w).then_some(x + 1)];
                let mut near = close(up[x]) + close(down[x]);
                for row in rows {
                    near += cols.iter().flatten().map(|&c| close(row[c])).sum::<u8>();
                }
                let ok = d0 > 0.0 && near >= min;
                kr[x] = u8::from(ok);
                kept += usize::from(ok);
            }
            kept
        })
        .sum()
}

/// Pass 2 on pixels `1..w - 1` of a row (`rows`: above, the row, below): the flags written to
/// `keep`, the kept count returned.
#[inline(always)]
fn neighbour_interior(rows: [&[f32]; 3], tol: f32, min: u8, keep: &mut [u8]) -> usize {
    let w = keep.len();
    if w < 3 || rows.iter().any(|r| r.len() != w) {
        return 0;
    }
    let n = w - 2;
    let [up, cur, down] = rows;
    let (ul, uc, ur) = (&up[..n], &up[1..n + 1], &up[2..]);
    let (cl, cc, cr) = (&cur[..n], &cur[1..n + 1], &cur[2..]);
    let (dl, dc, dr) = (&down[..n], &down[1..n + 1], &down[2..]);
    let k = &mut keep[1..n + 1];
    let mut kept = 0u32;
    for i in 0..n {
        let d0 = cc[i];
        let close = |v: f32| u8::from((v > 0.0) & ((v - d0).abs() <= tol));
        let near = close(ul[i])
            + close(uc[i])
            + close(ur[i])
            + close(cl[i])
            + close(cr[i])
            + close(dl[i])
            + close(dc[i])
            + close(dr[i]);
        let ok = (d0 > 0.0) & (near >= min);
        k[i] = u8::from(ok);
        kept += u32::from(ok);
    }
    kept as usize
}

/// Pass 3: unit normals (facing the camera centre `o`) from the kept image-grid neighbours on the
/// same surface, central differences where both are, one-sided otherwise (zero where neither); and
/// colours from `white` (black without it). Inner pixels run branch-free ([`normal_interior`], AVX2
/// when `simd`), the image's border one by one ([`normal_at`]).
#[inline(never)]
#[allow(clippy::too_many_arguments)]
fn normal_pass(
    o: &Vector3<f64>,
    points: &[[f32; 3]],
    depth: &[f32],
    keep: &[u8],
    w: usize,
    params: &TriangulationParams,
    white: Option<&image::RgbImage>,
    simd: bool,
    normals: &mut [[f32; 3]],
    colours: &mut [[u8; 3]],
) {
    let tol = params.neighbour_tolerance_m as f32;
    let h = depth.len() / w;
    let o = [o.x as f32, o.y as f32, o.z as f32];
    normals.par_chunks_mut(w).zip(colours.par_chunks_mut(w)).enumerate().for_each(|(y, (nr, cr))| {
        match white {
            Some(img) => {
                for (c, px) in cr.iter_mut().zip(img.as_raw()[3 * y * w..3 * (y + 1) * w].chunks_exact(3)) {
                    *c = [px[0], px[1], px[2]];
                }
            }
            None => cr.fill([0; 3]),
        }
        let inner = y > 0 && y + 1 < h && w >= 3;
        if inner {
            let rows = |k: usize| k * w..(k + 1) * w;
            let three = |r: [usize; 3]| r.map(&rows);
            let [ru, rc, rd] = three([y - 1, y, y + 1]);
            let view = NormalRows {
                points: [&points[ru.clone()], &points[rc.clone()], &points[rd.clone()]],
                depth: [&depth[ru.clone()], &depth[rc.clone()], &depth[rd.clone()]],
                keep: [&keep[ru], &keep[rc], &keep[rd]],
            };
            run_simd(
                simd,
                #[inline(always)]
                || normal_interior(&view, o, tol, nr),
            );
        }
        for (x, n) in nr.iter_mut().enumerate() {
            if inner && x > 0 && x + 1 < w {
                continue;
            }
            *n = normal_at(o, points, depth, keep, w, h, tol, x, y);
        }
    });
}

/// The rows above, at and below an inner camera row, for [`normal_interior`].
struct NormalRows<'a> {
    points: [&'a [[f32; 3]]; 3],
    depth: [&'a [f32]; 3],
    keep: [&'a [u8]; 3],
}

#[inline(always)]
fn sub3(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

/// Pass 3 on pixels `1..w - 1` of an inner row, every pixel computed and masked (the same
/// arithmetic as [`normal_at`]).
#[inline(always)]
fn normal_interior(rows: &NormalRows<'_>, o: [f32; 3], tol: f32, normals: &mut [[f32; 3]]) {
    let w = normals.len();
    let ok_len = rows.points.iter().all(|r| r.len() == w)
        && rows.depth.iter().all(|r| r.len() == w)
        && rows.keep.iter().all(|r| r.len() == w);
    if w < 3 || !ok_len {
        return;
    }
    let n = w - 2;
    let [pu, pc, pd] = rows.points;
    let [du, dc, dd] = rows.depth;
    let [ku, kc, kd] = rows.keep;
    let (pl, pm, pr, pu, pd) = (&pc[..n], &pc[1..n + 1], &pc[2..], &pu[1..n + 1], &pd[1..n + 1]);
    let (dl, dm, dr, du, dd) = (&dc[..n], &dc[1..n + 1], &dc[2..], &du[1..n + 1], &dd[1..n + 1]);
    let (kl, km, kr, ku, kd) = (&kc[..n], &kc[1..n + 1], &kc[2..], &ku[1..n + 1], &kd[1..n + 1]);
    let out = &mut normals[1..n + 1];
    for i in 0..n {
        let d0 = dm[i];
        let on = |k: u8, d: f32| (k != 0) & ((d - d0).abs() <= tol);
        let (l, r, u, b) = (on(kl[i], dl[i]), on(kr[i], dr[i]), on(ku[i], du[i]), on(kd[i], dd[i]));
        let p = pm[i];
        let pick = |ok: bool, q: [f32; 3]| if ok { q } else { p };
        let eu = sub3(pick(r, pr[i]), pick(l, pl[i]));
        let ev = sub3(pick(b, pd[i]), pick(u, pu[i]));
        let v = [eu[1] * ev[2] - eu[2] * ev[1], eu[2] * ev[0] - eu[0] * ev[2], eu[0] * ev[1] - eu[1] * ev[0]];
        let len = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        let v = v.map(|c| c / len);
        let t = sub3(o, p);
        let flip = v[0] * t[0] + v[1] * t[1] + v[2] * t[2] < 0.0;
        let v = if flip { v.map(|c| -c) } else { v };
        let ok = (km[i] != 0) & (l | r) & (u | b) & (len > 0.0) & len.is_finite();
        out[i] = if ok { v } else { [0.0; 3] };
    }
}

/// Pass 3 at one pixel `(x, y)`, any pixel of the image (borders included).
#[allow(clippy::too_many_arguments)]
fn normal_at(
    o: [f32; 3],
    points: &[[f32; 3]],
    depth: &[f32],
    keep: &[u8],
    w: usize,
    h: usize,
    tol: f32,
    x: usize,
    y: usize,
) -> [f32; 3] {
    let i = y * w + x;
    if keep[i] == 0 {
        return [0.0; 3];
    }
    let p = |j: usize| Vector3::from(points[j]);
    let d0 = depth[i];
    // A kept neighbour on the same surface.
    let on = |j: usize| keep[j] != 0 && (depth[j] - d0).abs() <= tol;
    let pick = |ok: bool, j: usize| (ok && on(j)).then_some(j);
    let diff = |a: Option<usize>, b: Option<usize>| match (a, b) {
        (Some(a), Some(b)) => Some(p(b) - p(a)),
        (Some(a), None) => Some(p(i) - p(a)),
        (None, Some(b)) => Some(p(b) - p(i)),
        (None, None) => None,
    };
    let du = diff(pick(x > 0, i.wrapping_sub(1)), pick(x + 1 < w, i + 1));
    let dv = diff(pick(y > 0, i.wrapping_sub(w)), pick(y + 1 < h, i + w));
    let (Some(du), Some(dv)) = (du, dv) else { return [0.0; 3] };
    let mut v = du.cross(&dv);
    let len = v.norm();
    if !(len > 0.0 && len.is_finite()) {
        return [0.0; 3];
    }
    v /= len;
    if v.dot(&(Vector3::from(o) - p(i))) < 0.0 {
        v = -v;
    }
    [v.x, v.y, v.z]
}

/// Pass 4: the points and depths of pixels that failed the neighbour test cleared.
#[inline(never)]
fn clear_pass(keep: &[u8], w: usize, points: &mut [[f32; 3]], depth: &mut [f32]) {
    points.par_chunks_mut(w).zip(depth.par_chunks_mut(w)).zip(keep.par_chunks(w)).for_each(|((pr, dr), kr)| {
        for ((p, d), &k) in pr.iter_mut().zip(dr.iter_mut()).zip(kr) {
            if k == 0 {
                *p = [f32::NAN; 3];
                *d = 0.0;
            }
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{Intrinsics, Pose};

    fn model(eye: [f64; 3], target: [f64; 3], w: u32, h: u32, f: f64, k1: f64) -> CameraModel {
        CameraModel {
            width: w,
            height: h,
            intrinsics: Intrinsics {
                fx: f,
                fy: f,
                cx: w as f64 / 2.0,
                cy: h as f64 / 2.0,
                skew: 0.0,
                k1,
                k2: 0.0,
                ..Intrinsics::default()
            },
            pose: Pose::look_at(Vector3::from(eye), Vector3::from(target), Vector3::z()),
        }
    }

    /// Exact projector coordinates for each camera pixel from a surface `hit(origin, dir) -> point`.
    fn coords_of(
        camera: &CameraModel,
        projector: &CameraModel,
        rows: bool,
        hit: impl Fn(&Vector3<f64>, &Vector3<f64>) -> Option<Vector3<f64>>,
    ) -> ProjectorCoords {
        let (w, h) = (camera.width as usize, camera.height as usize);
        let mut col = vec![f32::NAN; w * h];
        let mut row = vec![f32::NAN; w * h];
        for y in 0..h {
            for x in 0..w {
                let d = camera.pixel_ray(x as f64 + 0.5, y as f64 + 0.5);
                if let Some(p) = hit(&camera.centre(), &d).and_then(|p| projector.project(&p)) {
                    col[y * w + x] = p.x as f32;
                    row[y * w + x] = p.y as f32;
                }
            }
        }
        ProjectorCoords { width: w, height: h, column: col, row: rows.then_some(row) }
    }

    fn rig(k1: f64) -> (CameraModel, CameraModel) {
        let target = [0.0, 0.0, 0.03];
        (model([0.0, -0.4, 0.2], target, 96, 72, 200.0, k1), model([0.12, -0.38, 0.2], target, 200, 150, 260.0, k1))
    }

    fn plane_hit(o: &Vector3<f64>, d: &Vector3<f64>) -> Option<Vector3<f64>> {
        // The plane y = 0.01 (facing the camera).
        let s = (0.01 - o.y) / d.y;
        (s > 0.0).then(|| o + d * s)
    }

    fn sphere_hit(o: &Vector3<f64>, d: &Vector3<f64>) -> Option<Vector3<f64>> {
        let c = Vector3::new(0.0, 0.0, 0.03);
        let oc = o - c;
        let b = oc.dot(d);
        let disc = b * b - (oc.norm_squared() - 0.03 * 0.03);
        (disc >= 0.0).then(|| o + d * (-b - disc.sqrt()))
    }

    #[test]
    fn a_plane_is_recovered_with_distortion_by_column_plane_and_by_ray_ray() {
        for k1 in [0.0, -0.08] {
            let (cam, proj) = rig(k1);
            for rows in [false, true] {
                let coords = coords_of(&cam, &proj, rows, plane_hit);
                let params = TriangulationParams { min_neighbours: 0, ..Default::default() };
                let r = Triangulator::new(&cam, &proj)
                    .expect("models")
                    .triangulate(&coords, None, &params)
                    .expect("triangulate");
                assert!(r.valid_count() > 96 * 72 / 2, "k1 {k1} rows {rows}: {} points", r.valid_count());
                for (p, n, _) in r.valid_points() {
                    assert!((p[1] - 0.01).abs() < 2e-6, "k1 {k1} rows {rows}: point {p:?} off the plane");
                    if n != [0.0; 3] {
                        assert!(n[1] < -0.999, "normal {n:?} should face the camera (-y)");
                    }
                }
            }
        }
    }

    #[test]
    fn a_sphere_is_recovered_and_its_normals_point_outwards() {
        let (cam, proj) = rig(-0.05);
        let coords = coords_of(&cam, &proj, false, sphere_hit);
        let r = Triangulator::new(&cam, &proj)
            .expect("models")
            .triangulate(&coords, None, &TriangulationParams::default())
            .expect("triangulate");
        assert!(r.valid_count() > 300, "{} points", r.valid_count());
        let c = Vector3::new(0.0f32, 0.0, 0.03);
        let mut with_normal = 0;
        for (p, n, _) in r.valid_points() {
            let v = Vector3::from(p) - c;
            assert!((v.norm() - 0.03).abs() < 1e-5, "point {p:?} off the sphere");
            if n != [0.0; 3] {
                with_normal += 1;
                assert!(Vector3::from(n).dot(&v.normalize()) > 0.98, "normal {n:?} at {p:?}");
            }
        }
        assert!(with_normal > 250, "{with_normal} normals");
    }

    #[test]
    fn quantised_columns_and_outliers() {
        // Columns rounded to code centres: the error is bounded by half a projector pixel's depth.
        let (cam, proj) = rig(0.0);
        let mut coords = coords_of(&cam, &proj, false, plane_hit);
        for c in coords.column.iter_mut() {
            *c = c.floor() + 0.5;
        }
        // One wild pixel in the middle: 40 projector columns off.
        let mid = 36 * 96 + 48;
        coords.column[mid] += 40.0;
        let r = Triangulator::new(&cam, &proj)
            .expect("models")
            .triangulate(&coords, None, &TriangulationParams::default())
            .expect("triangulate");
        assert_eq!(r.depth_m[mid], 0.0, "the wild pixel is removed");
        assert!(r.outliers >= 1);
        let worst = r.valid_points().map(|(p, _, _)| (p[1] - 0.01).abs()).fold(0.0f32, f32::max);
        // Half a projector pixel is 0.5 / 260 rad, about 0.8 mm across at 0.4 m; the camera and
        // projector rays meet at about 17 degrees, so depth moves up to 0.8 mm / tan(17°) ≈ 2.6 mm,
        // a little more on the slanted plane.
        assert!(worst > 1e-4 && worst < 3.5e-3, "worst error {worst} m");
    }

    #[test]
    fn mismatched_sizes_are_errors() {
        let (cam, proj) = rig(0.0);
        let coords = ProjectorCoords { width: 3, height: 3, column: vec![0.0; 9], row: None };
        let e = Triangulator::new(&cam, &proj)
            .expect("models")
            .triangulate(&coords, None, &TriangulationParams::default())
            .expect_err("size");
        assert!(matches!(e, TriangulateError::CoordsSize { found_width: 3, .. }));
        let coords = coords_of(&cam, &proj, false, plane_hit);
        let img = image::RgbImage::new(4, 4);
        let e = Triangulator::new(&cam, &proj)
            .expect("models")
            .triangulate(&coords, Some(&img), &TriangulationParams::default())
            .expect_err("size");
        assert!(matches!(e, TriangulateError::ColourSize { found_width: 4, .. }));
    }
    /// The per-pixel triangulation this module had before the passes were fused and moved to `f32`
    /// rays and projector coefficients (`f64` unit rays, `Option` per neighbour): the reference the
    /// fast path is compared against.
    fn reference(
        camera: &CameraModel,
        projector: &CameraModel,
        rays: &[[f64; 3]],
        coords: &ProjectorCoords,
        white: Option<&image::RgbImage>,
        params: &TriangulationParams,
    ) -> Result<RangeImage, TriangulateError> {
        let (w, h) = (camera.width, camera.height);
        let n = w as usize * h as usize;
        let o = camera.centre();
        let po = projector.centre();
        let mut points = vec![[f32::NAN; 3]; n];
        let mut depth = vec![0.0f32; n];
        let decoded = (0..h as usize)
            .into_par_iter()
            .map(|y| (0..w as usize).filter(|&x| coords.get(x, y).is_some()).count())
            .sum();
        points.par_chunks_mut(w as usize).zip(depth.par_chunks_mut(w as usize)).enumerate().for_each(
            |(y, (pr, dr))| {
                for x in 0..w as usize {
                    let Some((c, r)) = coords.get(x, y) else { continue };
                    let d = Vector3::from(rays[y * w as usize + x]);
                    let p = match r {
                        None => ray_column(projector, &o, &d, f64::from(c)),
                        Some(r) => {
                            let pd = projector.pixel_ray(f64::from(c), f64::from(r));
                            ray_ray(&o, &d, &po, &pd, params.max_ray_gap_m)
                        }
                    };
                    if let Some(p) = p {
                        let z = camera.pose.apply(&p).z;
                        if z > 0.0 && p.iter().all(|v| v.is_finite()) {
                            pr[x] = [p.x as f32, p.y as f32, p.z as f32];
                            dr[x] = z as f32;
                        }
                    }
                }
            },
        );
        let triangulated = depth.iter().filter(|&&d| d > 0.0).count();

        // Outlier test and normals, from the 8-neighbourhood in the range image.
        let (wi, hi) = (w as i64, h as i64);
        let tol = params.neighbour_tolerance_m as f32;
        let at = |x: i64, y: i64| -> Option<usize> {
            (x >= 0 && y >= 0 && x < wi && y < hi).then(|| (y * wi + x) as usize).filter(|&i| depth[i] > 0.0)
        };
        let keep: Vec<bool> = (0..n)
            .into_par_iter()
            .map(|i| {
                if depth[i] <= 0.0 {
                    return false;
                }
                let (x, y) = ((i % w as usize) as i64, (i / w as usize) as i64);
                let mut near = 0u8;
                for (dx, dy) in [(-1, -1), (0, -1), (1, -1), (-1, 0), (1, 0), (-1, 1), (0, 1), (1, 1)] {
                    if let Some(j) = at(x + dx, y + dy) {
                        near += u8::from((depth[j] - depth[i]).abs() <= tol);
                    }
                }
                near >= params.min_neighbours
            })
            .collect();
        let outliers = triangulated - keep.iter().filter(|&&k| k).count();
        let kept = |x: i64, y: i64| at(x, y).filter(|&j| keep[j]);
        let normals: Vec<[f32; 3]> = (0..n)
            .into_par_iter()
            .map(|i| {
                if !keep[i] {
                    return [0.0; 3];
                }
                let (x, y) = ((i % w as usize) as i64, (i / w as usize) as i64);
                let p = |j: usize| Vector3::new(points[j][0], points[j][1], points[j][2]);
                let close = |j: usize| (depth[j] - depth[i]).abs() <= tol;
                // Central differences where both neighbours are on the surface, else one-sided.
                let diff = |a: Option<usize>, b: Option<usize>| match (a.filter(|&j| close(j)), b.filter(|&j| close(j)))
                {
                    (Some(a), Some(b)) => Some(p(b) - p(a)),
                    (Some(a), None) => Some(p(i) - p(a)),
                    (None, Some(b)) => Some(p(b) - p(i)),
                    (None, None) => None,
                };
                let (Some(du), Some(dv)) = (diff(kept(x - 1, y), kept(x + 1, y)), diff(kept(x, y - 1), kept(x, y + 1)))
                else {
                    return [0.0; 3];
                };
                let mut nrm = du.cross(&dv);
                let len = nrm.norm();
                if !(len > 0.0 && len.is_finite()) {
                    return [0.0; 3];
                }
                nrm /= len;
                let to_camera = Vector3::new(o.x as f32, o.y as f32, o.z as f32) - p(i);
                if nrm.dot(&to_camera) < 0.0 {
                    nrm = -nrm;
                }
                [nrm.x, nrm.y, nrm.z]
            })
            .collect();
        let colours: Vec<[u8; 3]> = (0..n)
            .into_par_iter()
            .map(|i| white.map_or([0; 3], |img| img.as_raw()[3 * i..3 * i + 3].try_into().unwrap_or([0; 3])))
            .collect();
        for (i, k) in keep.iter().enumerate() {
            if !k {
                points[i] = [f32::NAN; 3];
                depth[i] = 0.0;
            }
        }
        Ok(RangeImage {
            width: w,
            height: h,
            points,
            depth_m: depth,
            normals,
            colours,
            decoded,
            triangulated,
            outliers,
        })
    }

    fn reference_of(
        camera: &CameraModel,
        projector: &CameraModel,
        coords: &ProjectorCoords,
        white: Option<&image::RgbImage>,
        params: &TriangulationParams,
    ) -> RangeImage {
        let rays: Vec<[f64; 3]> = (0..camera.height as usize)
            .flat_map(|y| (0..camera.width as usize).map(move |x| (x, y)))
            .map(|(x, y)| {
                let d = camera.pixel_ray(x as f64 + 0.5, y as f64 + 0.5);
                [d.x, d.y, d.z]
            })
            .collect();
        reference(camera, projector, &rays, coords, white, params).expect("reference")
    }

    /// Same counts, same valid pixels, points within `tol_m`, normals within 1e-3, same colours.
    fn assert_same(a: &RangeImage, b: &RangeImage, tol_m: f32, what: &str) {
        assert_eq!((a.decoded, a.triangulated, a.outliers), (b.decoded, b.triangulated, b.outliers), "{what}");
        assert_eq!(a.colours, b.colours, "{what}");
        for i in 0..a.depth_m.len() {
            assert_eq!(a.depth_m[i] > 0.0, b.depth_m[i] > 0.0, "{what}: pixel {i} valid in one only");
            if a.depth_m[i] > 0.0 {
                assert!((a.depth_m[i] - b.depth_m[i]).abs() <= tol_m, "{what}: depth {i}");
                for k in 0..3 {
                    assert!((a.points[i][k] - b.points[i][k]).abs() <= tol_m, "{what}: point {i}");
                    assert!((a.normals[i][k] - b.normals[i][k]).abs() <= 1e-3, "{what}: normal {i}");
                }
            }
        }
    }

    #[test]
    fn the_fused_passes_equal_the_per_pixel_reference() {
        let white = image::RgbImage::from_fn(96, 72, |x, y| image::Rgb([x as u8, y as u8, (x ^ y) as u8]));
        let mut cases = 0;
        // The row kernels both generic and, where the CPU has it, compiled for AVX2.
        for (k1, simd) in [(0.0, false), (0.0, has_avx2()), (-0.08, false)] {
            let (cam, proj) = rig(k1);
            let mut tri = Triangulator::new(&cam, &proj).expect("models");
            tri.simd = simd;
            // One output reused across every case: stale values must not survive.
            let mut out = RangeImage::default();
            for rows in [false, true] {
                for (name, hit) in [
                    ("plane", plane_hit as fn(&Vector3<f64>, &Vector3<f64>) -> Option<Vector3<f64>>),
                    ("sphere", sphere_hit),
                ] {
                    let mut coords = coords_of(&cam, &proj, rows, hit);
                    // Code centres (steps in depth) and a wild pixel, so the outlier test and the
                    // one-sided normals have work.
                    for c in coords.column.iter_mut() {
                        *c = c.floor() + 0.5;
                    }
                    coords.column[36 * 96 + 48] += 40.0;
                    for params in [
                        TriangulationParams::default(),
                        TriangulationParams { min_neighbours: 0, ..Default::default() },
                    ] {
                        let what =
                            format!("k1 {k1} simd {simd} rows {rows} {name} min_neighbours {}", params.min_neighbours);
                        let want = reference_of(&cam, &proj, &coords, Some(&white), &params);
                        assert!(want.valid_count() > 150, "{what}: {} points", want.valid_count());
                        tri.triangulate_into(&coords, Some(&white), &params, &mut out).expect("triangulates");
                        assert_same(&out, &want, 2e-6, &what);
                        // The cloud gathered row by row holds the valid points in order.
                        let cloud = out.valid_cloud();
                        let (p, n, c): (Vec<_>, Vec<_>, (Vec<_>, ())) =
                            out.valid_points().map(|(p, n, c)| (p, n, (c, ()))).collect();
                        assert_eq!(cloud.points(), p.as_slice(), "{what}");
                        assert_eq!(cloud.normals(), Some(n.as_slice()), "{what}");
                        assert_eq!(cloud.colors(), Some(c.0.as_slice()), "{what}");
                        cases += 1;
                    }
                }
            }
        }
        assert_eq!(cases, 24);
    }

    #[test]
    fn a_decoded_map_triangulates_as_its_centre_coordinates() {
        let (cam, proj) = rig(0.0);
        let coords = coords_of(&cam, &proj, true, sphere_hit);
        let (w, h) = (coords.width, coords.height);
        let code = |v: f32| if v.is_finite() && v >= 0.0 { v.floor() as u16 } else { INVALID };
        let row = coords.row.as_ref().expect("rows");
        let (cols, rws): (Vec<u16>, Vec<u16>) = (0..w * h)
            .map(|i| match (code(coords.column[i]), code(row[i])) {
                (c, r) if c == INVALID || r == INVALID => (INVALID, INVALID),
                cr => cr,
            })
            .unzip();
        let map = ProjectorMap::from_parts(w, h, cols, rws);
        let mut tri = Triangulator::new(&cam, &proj).expect("models");
        for (rows, simd) in [(false, false), (true, false), (false, has_avx2()), (true, has_avx2())] {
            tri.simd = simd;
            let params = TriangulationParams::default();
            let want = tri.triangulate(&ProjectorCoords::from_map(&map, rows), None, &params).expect("coords");
            let mut got = RangeImage::default();
            tri.triangulate_map_into(&map, rows, None, &params, &mut got).expect("map");
            assert!(got.valid_count() > 150, "rows {rows}: {} points", got.valid_count());
            assert_same(&got, &want, 0.0, &format!("rows {rows}"));
        }
    }
}

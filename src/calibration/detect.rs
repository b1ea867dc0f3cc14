//! Chessboard inner-corner detection.
//!
//! 1. The grey image is smoothed (Gaussian, [`DetectOptions::sigma_px`]) and every pixel scored by a
//!    saddle response `Ixy² - Ixx·Iyy` (positive where the intensity curves up one way and down the
//!    other, as at the point where four squares meet; about zero along straight edges).
//! 2. Local maxima above a fraction of the strongest are kept if a circle around them crosses the
//!    mid-grey level exactly four times (two dark and two light sectors), which rejects the
//!    L-shaped outer corners of the board, text and texture.
//! 3. Each survivor is refined to sub-pixel accuracy by the gradient-orthogonality condition: at the
//!    true corner `q` every gradient `g_i` at a nearby point `p_i` is orthogonal to `p_i - q`, so `q`
//!    solves `Σ g gᵀ q = Σ g gᵀ p` (iterated with re-centred windows).
//! 4. A grid is grown from a seed corner and two neighbours, predicting each next corner from the
//!    last two in line (which follows perspective), until no prediction finds a corner. The grid must
//!    be complete and exactly `cols` x `rows`; otherwise the image is rejected with the reason.
//! 5. The grid is ordered into the board frame: handedness from the image (board `x` right, `y`
//!    down as seen), origin so that the first square is dark when the board's colouring tells the
//!    two 180° orientations apart (`cols + rows` odd), else the corner nearest the image's top-left.
//!
//! Why not the `calib-targets` crate: it needs Rust 1.91 while this project builds with 1.85, and it
//! brings a family of crates for target types (ChArUco, ArUco, PuzzleBoard) the rig does not use.

use std::collections::{HashMap, VecDeque};

use image::GrayImage;
use nalgebra::{Matrix2, Point2, Vector2};

use super::BoardSpec;

/// Tunables of [`detect_chessboard`]. The defaults suit squares from about 12 pixels across up
/// (the four-sector ring must fit inside the squares around a corner).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DetectOptions {
    /// Gaussian smoothing before the saddle response, pixels (standard deviation).
    pub sigma_px: f64,
    /// Radius of the circle sampled to check a candidate has four alternating sectors, pixels.
    pub ring_radius_px: f64,
    /// Smallest difference between the light and dark sectors of a corner, 8-bit grey levels.
    pub min_contrast: f64,
    /// Half-size of the sub-pixel refinement window, pixels.
    pub refine_half_window_px: i32,
}

impl Default for DetectOptions {
    fn default() -> Self {
        DetectOptions { sigma_px: 1.5, ring_radius_px: 5.0, min_contrast: 20.0, refine_half_window_px: 5 }
    }
}

/// A detected board: the inner corners in board order.
#[derive(Debug, Clone, PartialEq)]
pub struct ChessboardDetection {
    /// Sub-pixel corner positions, pixels (top-left origin), row-major in board order: index
    /// `j·cols + i` is inner corner `(i, j)`, matching [`BoardSpec::object_points`].
    pub corners: Vec<Point2<f64>>,
    /// Number of saddle-point candidates found in the image (board corners and clutter).
    pub candidates: usize,
}

/// Why an image was rejected.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DetectError {
    /// The board asked for has fewer than 3 inner corners along a side.
    #[error("a chessboard needs at least 3x3 inner corners, got {cols}x{rows}")]
    BoardTooSmall {
        /// Inner corners along x.
        cols: usize,
        /// Inner corners along y.
        rows: usize,
    },
    /// The image is smaller than the detector's windows.
    #[error("image is {width}x{height} pixels, too small to search")]
    ImageTooSmall {
        /// Width, pixels.
        width: u32,
        /// Height, pixels.
        height: u32,
    },
    /// No corner candidates at all (no board, or too blurred or too dark).
    #[error("no chessboard found: {candidates} corner candidates (board missing, blurred, or too little contrast)")]
    NoBoard {
        /// Candidates found.
        candidates: usize,
    },
    /// The largest grid found is smaller than the board: part of it is out of view, occluded or
    /// too blurred.
    #[error("partial board: found a {found_cols}x{found_rows} grid of corners, expected {cols}x{rows} (board cut off, occluded or blurred)")]
    PartialBoard {
        /// Corners along the grid's first axis.
        found_cols: usize,
        /// Corners along the second axis.
        found_rows: usize,
        /// Expected inner corners along x.
        cols: usize,
        /// Expected inner corners along y.
        rows: usize,
    },
    /// The grid found is larger than the board: the board size given is wrong, or clutter lines up.
    #[error("found a {found_cols}x{found_rows} grid of corners, larger than the {cols}x{rows} board given")]
    GridTooLarge {
        /// Corners along the grid's first axis.
        found_cols: usize,
        /// Corners along the second axis.
        found_rows: usize,
        /// Expected inner corners along x.
        cols: usize,
        /// Expected inner corners along y.
        rows: usize,
    },
}

/// A grey image as `f32`, row-major.
#[derive(Debug, Clone)]
struct Plane {
    w: usize,
    h: usize,
    data: Vec<f32>,
}

impl Plane {
    fn from_gray(img: &GrayImage) -> Plane {
        Plane {
            w: img.width() as usize,
            h: img.height() as usize,
            data: img.as_raw().iter().map(|&v| v as f32).collect(),
        }
    }

    #[inline]
    fn at(&self, x: usize, y: usize) -> f32 {
        self.data[y * self.w + x]
    }

    /// Bilinear sample, clamped to the image.
    fn sample(&self, x: f64, y: f64) -> f32 {
        let x = x.clamp(0.0, (self.w - 1) as f64);
        let y = y.clamp(0.0, (self.h - 1) as f64);
        let (x0, y0) = (x.floor() as usize, y.floor() as usize);
        let (x1, y1) = ((x0 + 1).min(self.w - 1), (y0 + 1).min(self.h - 1));
        let (fx, fy) = ((x - x0 as f64) as f32, (y - y0 as f64) as f32);
        let top = self.at(x0, y0) * (1.0 - fx) + self.at(x1, y0) * fx;
        let bot = self.at(x0, y1) * (1.0 - fx) + self.at(x1, y1) * fx;
        top * (1.0 - fy) + bot * fy
    }

    /// Separable Gaussian blur with standard deviation `sigma` pixels (edges clamped).
    fn blurred(&self, sigma: f64) -> Plane {
        if sigma <= 0.0 {
            return self.clone();
        }
        let r = (3.0 * sigma).ceil() as i64;
        let mut k: Vec<f32> = (-r..=r).map(|i| (-(i * i) as f64 / (2.0 * sigma * sigma)).exp() as f32).collect();
        let s: f32 = k.iter().sum();
        k.iter_mut().for_each(|v| *v /= s);
        let (w, h) = (self.w as i64, self.h as i64);
        let mut tmp = vec![0.0f32; self.data.len()];
        for y in 0..h {
            for x in 0..w {
                let mut acc = 0.0;
                for (i, kv) in k.iter().enumerate() {
                    let xx = (x + i as i64 - r).clamp(0, w - 1);
                    acc += kv * self.data[(y * w + xx) as usize];
                }
                tmp[(y * w + x) as usize] = acc;
            }
        }
        let mut out = vec![0.0f32; self.data.len()];
        for y in 0..h {
            for x in 0..w {
                let mut acc = 0.0;
                for (i, kv) in k.iter().enumerate() {
                    let yy = (y + i as i64 - r).clamp(0, h - 1);
                    acc += kv * tmp[(yy * w + x) as usize];
                }
                out[(y * w + x) as usize] = acc;
            }
        }
        Plane { w: self.w, h: self.h, data: out }
    }
}

/// Saddle response `Ixy² - Ixx·Iyy` (0 on the one-pixel border).
fn saddle_response(p: &Plane) -> Vec<f32> {
    let (w, h) = (p.w, p.h);
    let mut out = vec![0.0f32; w * h];
    for y in 1..h - 1 {
        for x in 1..w - 1 {
            let c = p.at(x, y);
            let ixx = p.at(x + 1, y) - 2.0 * c + p.at(x - 1, y);
            let iyy = p.at(x, y + 1) - 2.0 * c + p.at(x, y - 1);
            let ixy = 0.25 * (p.at(x + 1, y + 1) - p.at(x + 1, y - 1) - p.at(x - 1, y + 1) + p.at(x - 1, y - 1));
            out[y * w + x] = ixy * ixy - ixx * iyy;
        }
    }
    out
}

/// True when a circle of radius `r` around `(x, y)` has four alternating sectors with at least
/// `min_contrast` between light and dark.
fn has_four_sectors(p: &Plane, x: f64, y: f64, r: f64, min_contrast: f64) -> bool {
    const N: usize = 32;
    let samples: Vec<f32> = (0..N)
        .map(|k| {
            let a = k as f64 * std::f64::consts::TAU / N as f64;
            p.sample(x + r * a.cos(), y + r * a.sin())
        })
        .collect();
    let (lo, hi) = samples.iter().fold((f32::MAX, f32::MIN), |(a, b), &v| (a.min(v), b.max(v)));
    if ((hi - lo) as f64) < min_contrast {
        return false;
    }
    let mid = 0.5 * (lo + hi);
    let signs: Vec<bool> = samples.iter().map(|&v| v > mid).collect();
    let changes = (0..N).filter(|&k| signs[k] != signs[(k + 1) % N]).count();
    changes == 4
}

/// Gradient-orthogonality sub-pixel refinement of a corner near `(x, y)`; `None` if it wanders
/// off by more than the window.
fn refine(p: &Plane, x: f64, y: f64, half: i32) -> Option<Point2<f64>> {
    let (mut qx, mut qy) = (x, y);
    let sigma_w = half as f64 * 0.6;
    for _ in 0..20 {
        let mut a = Matrix2::zeros();
        let mut b = Vector2::zeros();
        for dy in -half..=half {
            for dx in -half..=half {
                let (px, py) = (qx + dx as f64, qy + dy as f64);
                if px < 1.0 || py < 1.0 || px > (p.w - 2) as f64 || py > (p.h - 2) as f64 {
                    continue;
                }
                let gx = 0.5 * (p.sample(px + 1.0, py) - p.sample(px - 1.0, py)) as f64;
                let gy = 0.5 * (p.sample(px, py + 1.0) - p.sample(px, py - 1.0)) as f64;
                let wgt = (-((dx * dx + dy * dy) as f64) / (2.0 * sigma_w * sigma_w)).exp();
                let g = Vector2::new(gx, gy);
                let ggt = g * g.transpose() * wgt;
                a += ggt;
                b += ggt * Vector2::new(px, py);
            }
        }
        let q = a.try_inverse()? * b;
        let shift = ((q.x - qx).powi(2) + (q.y - qy).powi(2)).sqrt();
        qx = q.x;
        qy = q.y;
        if ((qx - x).powi(2) + (qy - y).powi(2)).sqrt() > half as f64 {
            return None;
        }
        if shift < 1e-3 {
            break;
        }
    }
    Some(Point2::new(qx, qy))
}

/// Corner candidates: refined saddle points with four alternating sectors.
fn candidates(raw: &Plane, opts: &DetectOptions) -> Vec<Point2<f64>> {
    let smooth = raw.blurred(opts.sigma_px);
    let resp = saddle_response(&smooth);
    let max = resp.iter().copied().fold(0.0f32, f32::max);
    if max <= 0.0 {
        return Vec::new();
    }
    let thr = 0.03 * max;
    let (w, h) = (raw.w, raw.h);
    let nms = 3usize;
    let margin = (opts.ring_radius_px.ceil() as usize + 1).max(nms + 1);
    let mut peaks: Vec<(f32, usize, usize)> = Vec::new();
    for y in margin..h.saturating_sub(margin) {
        for x in margin..w.saturating_sub(margin) {
            let v = resp[y * w + x];
            if v <= thr {
                continue;
            }
            let mut is_max = true;
            'n: for yy in y - nms..=y + nms {
                for xx in x - nms..=x + nms {
                    let o = resp[yy * w + xx];
                    if o > v || (o == v && (yy, xx) < (y, x)) {
                        is_max = false;
                        break 'n;
                    }
                }
            }
            if is_max {
                peaks.push((v, x, y));
            }
        }
    }
    peaks.sort_by(|a, b| b.0.total_cmp(&a.0));
    peaks.truncate(4000);
    let lightly = raw.blurred(0.7);
    let mut out: Vec<Point2<f64>> = Vec::new();
    for (_, x, y) in peaks {
        if !has_four_sectors(&smooth, x as f64, y as f64, opts.ring_radius_px, opts.min_contrast) {
            continue;
        }
        let Some(q) = refine(&lightly, x as f64, y as f64, opts.refine_half_window_px) else { continue };
        // Two peaks refining onto one corner keep the first (stronger) one.
        if out.iter().any(|o| (o - q).norm() < 2.0) {
            continue;
        }
        out.push(q);
    }
    out
}

/// A grid of candidate indices keyed by integer grid coordinates.
type Grid = HashMap<(i32, i32), usize>;

/// Inclusive grid index ranges `(i_min, i_max, j_min, j_max)`.
type GridRange = (i32, i32, i32, i32);

/// Grow a grid from `seed` and its neighbours `a` (grid +i) and `b` (grid +j).
fn grow(pts: &[Point2<f64>], seed: usize, a: usize, b: usize) -> Grid {
    let mut grid: Grid = HashMap::new();
    let mut used = vec![false; pts.len()];
    for (k, idx) in [((0, 0), seed), ((1, 0), a), ((0, 1), b)] {
        grid.insert(k, idx);
        used[idx] = true;
    }
    let mut queue: VecDeque<(i32, i32)> = [(0, 0), (1, 0), (0, 1)].into_iter().collect();
    let dirs = [(1, 0), (-1, 0), (0, 1), (0, -1)];
    while let Some((i, j)) = queue.pop_front() {
        let pc = pts[grid[&(i, j)]];
        for (di, dj) in dirs {
            let target = (i + di, j + dj);
            if grid.contains_key(&target) {
                continue;
            }
            // Step along (di, dj): from the corner behind this one, else from a neighbour's step,
            // else from the seed's axes.
            let step = if let Some(&back) = grid.get(&(i - di, j - dj)) {
                pc - pts[back]
            } else {
                let perp = [(dj, di), (-dj, -di)];
                let mut s = None;
                for (pi, pj) in perp {
                    if let (Some(&n0), Some(&n1)) = (grid.get(&(i + pi, j + pj)), grid.get(&(i + pi + di, j + pj + dj)))
                    {
                        s = Some(pts[n1] - pts[n0]);
                        break;
                    }
                }
                match s {
                    Some(s) => s,
                    None => {
                        let e = if di != 0 { pts[a] - pts[seed] } else { pts[b] - pts[seed] };
                        e * (di + dj) as f64
                    }
                }
            };
            let pred = pc + step;
            let tol = 0.3 * step.norm();
            let mut best: Option<(f64, usize)> = None;
            for (k, q) in pts.iter().enumerate() {
                if used[k] {
                    continue;
                }
                let d = (q - pred).norm();
                if d < tol && best.is_none_or(|(bd, _)| d < bd) {
                    best = Some((d, k));
                }
            }
            if let Some((_, k)) = best {
                used[k] = true;
                grid.insert(target, k);
                queue.push_back(target);
            }
        }
    }
    grid
}

/// The one `w` x `h` (or `h` x `w`) window of `grid` whose every cell is filled, restricted to it,
/// when there is exactly one: the board, with clutter that happened to line up with its grid (an
/// edge of the stand, a tile joint) left outside.
fn board_window(grid: &Grid, (i0, i1, j0, j1): GridRange, w: i32, h: i32) -> Option<(Grid, GridRange)> {
    let mut found = None;
    let mut count = 0;
    let sizes = if w == h { vec![(w, h)] } else { vec![(w, h), (h, w)] };
    for (a, b) in sizes {
        for si in i0..=i1 - a + 1 {
            for sj in j0..=j1 - b + 1 {
                if (si..si + a).all(|i| (sj..sj + b).all(|j| grid.contains_key(&(i, j)))) {
                    count += 1;
                    found = Some((si, si + a - 1, sj, sj + b - 1));
                }
            }
        }
    }
    let (a0, a1, b0, b1) = found.filter(|_| count == 1)?;
    let sub: Grid = grid
        .iter()
        .filter(|((i, j), _)| (a0..=a1).contains(i) && (b0..=b1).contains(j))
        .map(|(k, v)| (*k, *v))
        .collect();
    Some((sub, (a0, a1, b0, b1)))
}

/// Grids grown from several seeds; the largest complete rectangle wins. A grid with holes (clutter
/// grown onto the board's grid) counts when it holds exactly one complete `cols` x `rows` window.
fn best_grid(pts: &[Point2<f64>], cols: usize, rows: usize) -> Option<(Grid, GridRange)> {
    let n = pts.len();
    if n < 4 {
        return None;
    }
    // Seeds: the candidates nearest their centroid first (the board usually fills the middle).
    let c = pts.iter().fold(Vector2::zeros(), |acc, p| acc + p.coords) / n as f64;
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by(|&x, &y| (pts[x].coords - c).norm().total_cmp(&(pts[y].coords - c).norm()));
    let mut best: Option<(Grid, GridRange, usize)> = None;
    for &seed in order.iter().take(12) {
        let mut near: Vec<(f64, usize)> =
            (0..n).filter(|&k| k != seed).map(|k| ((pts[k] - pts[seed]).norm(), k)).collect();
        near.sort_by(|x, y| x.0.total_cmp(&y.0));
        near.truncate(6);
        let Some(&(d0, a)) = near.first() else { continue };
        let ea = pts[a] - pts[seed];
        // The second axis: the nearest neighbour roughly perpendicular to the first.
        let Some(&(_, b)) = near.iter().skip(1).find(|(d, k)| {
            let eb = pts[*k] - pts[seed];
            let cos = ea.dot(&eb) / (ea.norm() * eb.norm());
            cos.abs() < 0.6 && *d < 2.0 * d0
        }) else {
            continue;
        };
        let grid = grow(pts, seed, a, b);
        let (mut i0, mut i1, mut j0, mut j1) = (i32::MAX, i32::MIN, i32::MAX, i32::MIN);
        for &(i, j) in grid.keys() {
            i0 = i0.min(i);
            i1 = i1.max(i);
            j0 = j0.min(j);
            j1 = j1.max(j);
        }
        // Keep the largest fully filled rectangle (a hole means a mismatch, unless the board's
        // window inside is complete and unique).
        let complete = grid.len() == ((i1 - i0 + 1) * (j1 - j0 + 1)) as usize;
        let (grid, range, size) = if complete {
            let n = grid.len();
            (grid, (i0, i1, j0, j1), n)
        } else {
            match board_window(&grid, (i0, i1, j0, j1), cols as i32, rows as i32) {
                Some((sub, r)) => (sub, r, cols * rows),
                None => (grid, (i0, i1, j0, j1), 0),
            }
        };
        if best.as_ref().is_none_or(|b| size > b.2) {
            best = Some((grid, range, size));
        }
    }
    best.filter(|b| b.2 > 0).map(|(g, r, _)| (g, r))
}

/// Find a `board.cols` x `board.rows` chessboard in a grey image and return its inner corners in
/// board order (see the module docs), or the reason it is not usable.
pub fn detect_chessboard(
    image: &GrayImage,
    board: &BoardSpec,
    opts: &DetectOptions,
) -> Result<ChessboardDetection, DetectError> {
    if board.cols < 3 || board.rows < 3 {
        return Err(DetectError::BoardTooSmall { cols: board.cols, rows: board.rows });
    }
    let (width, height) = image.dimensions();
    let min_side = 4 * (opts.ring_radius_px.ceil() as u32 + 4);
    if width < min_side || height < min_side {
        return Err(DetectError::ImageTooSmall { width, height });
    }
    let plane = Plane::from_gray(image);
    let pts = candidates(&plane, opts);
    let ncand = pts.len();
    let Some((grid, (i0, i1, j0, j1))) = best_grid(&pts, board.cols, board.rows) else {
        return Err(DetectError::NoBoard { candidates: ncand });
    };
    let (gi, gj) = ((i1 - i0 + 1) as usize, (j1 - j0 + 1) as usize);
    let (cols, rows) = (board.cols, board.rows);
    let fits = (gi == cols && gj == rows) || (gi == rows && gj == cols);
    if !fits {
        if gi * gj > cols * rows && gi >= cols.min(rows) && gj >= cols.min(rows) {
            return Err(DetectError::GridTooLarge { found_cols: gi, found_rows: gj, cols, rows });
        }
        if gi < 2 || gj < 2 {
            return Err(DetectError::NoBoard { candidates: ncand });
        }
        return Err(DetectError::PartialBoard { found_cols: gi, found_rows: gj, cols, rows });
    }
    // Grid coordinates (0-based) -> point.
    let at = |i: usize, j: usize| pts[grid[&(i0 + i as i32, j0 + j as i32)]];
    // Put the grid's first axis along the board's columns.
    let mut m: Vec<Vec<Point2<f64>>> = if gi == cols && gj == rows {
        (0..rows).map(|j| (0..cols).map(|i| at(i, j)).collect()).collect()
    } else {
        (0..rows).map(|j| (0..cols).map(|i| at(j, i)).collect()).collect()
    };
    // Handedness: board x to the right and y downwards as seen (positive image-plane cross product).
    let ex = m[0][1] - m[0][0];
    let ey = m[1][0] - m[0][0];
    if ex.x * ey.y - ex.y * ey.x < 0.0 {
        m.reverse();
    }
    // 180° ambiguity.
    let rotate = if (cols + rows) % 2 == 1 {
        let cell = |j: usize, i: usize| {
            let c = (m[j][i].coords + m[j][i + 1].coords + m[j + 1][i].coords + m[j + 1][i + 1].coords) / 4.0;
            plane.sample(c.x, c.y)
        };
        cell(0, 0) > cell(0, 1)
    } else {
        let first = m[0][0];
        let last = m[rows - 1][cols - 1];
        last.x + last.y < first.x + first.y
    };
    if rotate {
        m.reverse();
        m.iter_mut().for_each(|r| r.reverse());
    }
    // Sample (array) coordinates have pixel centres at integers; the project's pixel centres are at
    // `u + 0.5` (see `crate::geometry`).
    let corners = m.into_iter().flatten().map(|p| Point2::new(p.x + 0.5, p.y + 0.5)).collect();
    Ok(ChessboardDetection { corners, candidates: ncand })
}

/// Convert an RGB frame to grey (Rec. 601 luma), for [`detect_chessboard`].
pub fn to_gray(rgb: &image::RgbImage) -> GrayImage {
    image::DynamicImage::ImageRgb8(rgb.clone()).to_luma8()
}

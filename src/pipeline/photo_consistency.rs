//! Photo-consistency of voxels: footprints, per-view item buffers and the consistency tests shared by
//! voxel colouring and generalized space carving ([`super::voxel_coloring`]).
//!
//! # Footprint
//! A voxel's footprint in a view is the set of pixels whose centres fall inside the bounding rectangle
//! of its eight projected corners (at least the pixel its centre falls in). A voxel with a corner
//! behind the camera (camera-frame `z <= 0`) has no footprint in that view. Projection uses the full
//! camera model (pinhole, skew, the five-term lens model k1 k2 p1 p2 k3 of
//! [`crate::geometry::Intrinsics`]) in `f32`.
//!
//! # Visibility
//! An [`ItemBuffer`] holds, per pixel of a view, the nearest (smallest camera depth of the voxel
//! centre) surface voxel whose footprint covers the pixel. A voxel is *visible* in a pixel of its
//! footprint iff the item buffer names it there, so occluded views and occluded parts of footprints
//! are never consulted. Pixels outside the view's silhouette (when a mask is given) are not sampled.
//!
//! # Consistency
//! For each view in which the voxel is visible (and which faces the voxel's estimated outward normal
//! with a cosine of at least `min_cos`), the mean colour of its visible footprint pixels is taken.
//! - **Colour standard deviation**: the count-weighted standard deviation of those per-view means,
//!   RMS over the three channels, in 8-bit levels (0..255), must not exceed `threshold`. Using the
//!   per-view means (not every pixel pooled) keeps a voxel on a texture edge consistent: every view
//!   sees the same mix of the two colours, while pooled pixels would vary by the texture's contrast.
//! - **Normalised cross-correlation** (optional, `min_ncc`): the eight sub-voxel points at ±¼ voxel
//!   are projected into each view in which all of them are visible; each view's 24 values (8 points ×
//!   RGB) are correlated with the mean over those views. When the mean pattern has a standard
//!   deviation above [`NCC_MIN_SIGMA`] levels (a textured patch), the mean correlation must reach
//!   `min_ncc`; flat patches are left to the standard deviation test.
//!
//! Fewer than `min_views` views seeing a voxel leave it undecided: it is kept (consistent).
//!
//! The test assumes Lambertian surfaces under lighting that changes little between views: shading
//! differences between views count as colour differences, so `threshold` must exceed them.

use image::RgbImage;
use rayon::prelude::*;

use super::silhouette::Mask;
use crate::geometry::round::{ceil_f32, floor_f32};
use crate::geometry::{CameraModel, VoxelGrid};

/// A calibrated colour view: a camera (in the grid's frame), its image and optionally its silhouette.
#[derive(Debug, Clone, Copy)]
pub struct PhotoView<'a> {
    /// The camera, in the grid's frame.
    pub camera: CameraModel,
    /// The image; must be the camera's image size.
    pub image: &'a RgbImage,
    /// The silhouette; pixels outside it are never sampled. Must be the camera's image size.
    pub mask: Option<&'a Mask>,
}

/// Parameters of the photo-consistency test and of the carving loops.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PhotoParams {
    /// Largest colour standard deviation between views of a consistent voxel, 8-bit levels (0..255).
    pub threshold: f32,
    /// Smallest mean normalised cross-correlation of a textured consistent voxel (-1..1); `None` skips
    /// the test.
    pub min_ncc: Option<f32>,
    /// Views needed to judge a voxel (at least 2); fewer leave it kept.
    pub min_views: usize,
    /// Views whose direction makes a cosine below this with the voxel's estimated outward normal are
    /// not consulted (grazing views mix neighbouring surfaces); -1 consults every view.
    pub min_cos: f32,
    /// Cap on generalized space carving iterations (each visits every surface voxel once).
    pub max_iterations: usize,
}

/// The defaults (threshold 22 levels, `min_cos` 0.4) carve both the simulated cup under near-ambient
/// light and the Middlebury dino (lights fixed while the object turns) without tunnelling; see the
/// README's method table for the figures.
impl Default for PhotoParams {
    fn default() -> Self {
        PhotoParams { threshold: 22.0, min_ncc: None, min_views: 2, min_cos: 0.4, max_iterations: 500 }
    }
}

impl PhotoParams {
    /// These parameters with `threshold` derived from the measured noise of the data
    /// ([`PhotoNoise::threshold`]) instead of a fixed number.
    pub fn with_measured_noise(self, noise: &PhotoNoise) -> PhotoParams {
        PhotoParams { threshold: noise.threshold(), ..self }
    }
}

/// The measured noise of a photo data set (see [`super::voxel_coloring::measure_noise`]), 8-bit levels.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct PhotoNoise {
    /// Image noise: the median over views of Immerkær's estimate of the standard deviation of the
    /// pixel noise (RMS over channels), over pixels inside the masks.
    pub image_sigma: f32,
    /// Median over the start's seen surface voxels of their colour spread between views (the
    /// statistic [`PhotoParams::threshold`] bounds).
    pub spread_median: f32,
    /// Median absolute deviation of those spreads from their median.
    pub spread_mad: f32,
    /// Surface voxels the spreads were measured on.
    pub voxels: usize,
}

impl PhotoNoise {
    /// Multiples of the spread's robust standard deviation (1.4826 MAD) above its median, and of the
    /// image noise, that the derived threshold allows.
    pub const K: f32 = 3.0;

    /// The consistency threshold this noise calls for, 8-bit levels: the start's surface is mostly
    /// on or near the true surface, so its spreads are mostly what view-to-view differences of
    /// consistent voxels are (sensor noise, shading, sampling); a voxel counts as inconsistent
    /// when its spread is an outlier of that distribution, `median + K * 1.4826 * MAD`, and never
    /// below `K` times the image noise.
    pub fn threshold(&self) -> f32 {
        let robust = self.spread_median + Self::K * 1.4826 * self.spread_mad;
        robust.max(Self::K * self.image_sigma).max(1.0)
    }
}

/// Immerkær's fast estimate of the standard deviation of additive pixel noise (8-bit levels, RMS
/// over channels) of one view: the mean absolute response of the 3x3 Laplacian-difference mask
/// `[1 -2 1; -2 4 -2; 1 -2 1]` times `sqrt(pi/2) / 6`, over the pixels whose 3x3 neighbourhood is
/// inside the mask (every interior pixel without one). `None` without such pixels.
pub fn image_noise_sigma(view: &PhotoView<'_>) -> Option<f32> {
    let (w, h) = view.image.dimensions();
    let (w, h) = (w as usize, h as usize);
    if w < 3 || h < 3 {
        return None;
    }
    let img = view.image.as_raw();
    let inside = |x: usize, y: usize| view.mask.is_none_or(|m| m.get(x as u32, y as u32));
    let (sum, n) = (1..h - 1)
        .into_par_iter()
        .map(|y| {
            let mut sum = [0f64; 3];
            let mut n = 0u64;
            for x in 1..w - 1 {
                if !(inside(x - 1, y - 1) && inside(x + 1, y - 1) && inside(x - 1, y + 1) && inside(x + 1, y + 1)) {
                    continue;
                }
                for (c, acc) in sum.iter_mut().enumerate() {
                    let at = |dx: usize, dy: usize| img[3 * ((y + dy - 1) * w + x + dx - 1) + c] as i32;
                    let r = at(0, 0) - 2 * at(1, 0) + at(2, 0) - 2 * at(0, 1) + 4 * at(1, 1) - 2 * at(2, 1) + at(0, 2)
                        - 2 * at(1, 2)
                        + at(2, 2);
                    *acc += r.unsigned_abs() as f64;
                }
                n += 1;
            }
            (sum, n)
        })
        .reduce(|| ([0f64; 3], 0), |a, b| ([a.0[0] + b.0[0], a.0[1] + b.0[1], a.0[2] + b.0[2]], a.1 + b.1));
    if n == 0 {
        return None;
    }
    let k = (std::f64::consts::PI / 2.0).sqrt() / 6.0 / n as f64;
    let var = sum.iter().map(|s| (s * k).powi(2)).sum::<f64>() / 3.0;
    Some(var.sqrt() as f32)
}

/// Standard deviation (8-bit levels) below which a patch counts as untextured for the NCC test.
pub const NCC_MIN_SIGMA: f32 = 6.0;

/// Colour of surface voxels no view sees.
pub const UNSEEN_COLOUR: [u8; 3] = [128, 128, 128];

/// Errors of photo-consistency reconstruction.
#[derive(Debug, thiserror::Error)]
pub enum PhotoError {
    /// The grid has no voxels or an unusable voxel size.
    #[error("the voxel grid is unusable: dims {dims:?}, voxel size {voxel_size} m")]
    BadGrid {
        /// Voxels along x, y, z.
        dims: [usize; 3],
        /// Voxel edge, metres.
        voxel_size: f64,
    },
    /// A view's image or mask is not the camera's image size.
    #[error("view {view}: image or mask size differs from the camera's {width}x{height} px")]
    ImageSize {
        /// Index of the view.
        view: usize,
        /// Camera width, px.
        width: u32,
        /// Camera height, px.
        height: u32,
    },
    /// A camera has non-finite parameters.
    #[error("view {view}: the camera has non-finite parameters")]
    BadCamera {
        /// Index of the view.
        view: usize,
    },
    /// Parameters out of range.
    #[error("photo-consistency parameters out of range: {what}")]
    BadParams {
        /// Which one.
        what: &'static str,
    },
    /// Voxel colouring needs every camera on the near side of a plane in front of the volume.
    #[error("no ordinal visibility order: camera {view} is not in front of the working volume along the sweep direction {direction:?}")]
    NoOrdinalOrder {
        /// The first camera that breaks the order.
        view: usize,
        /// The sweep direction tried (unit vector, grid frame).
        direction: [f64; 3],
    },
}

pub(crate) fn check_inputs(grid: &VoxelGrid, views: &[PhotoView<'_>], params: &PhotoParams) -> Result<(), PhotoError> {
    if grid.is_empty() || !(grid.voxel_size.is_finite() && grid.voxel_size > 0.0) {
        return Err(PhotoError::BadGrid { dims: grid.dims, voxel_size: grid.voxel_size });
    }
    if !(params.threshold.is_finite() && params.threshold > 0.0) {
        return Err(PhotoError::BadParams { what: "threshold must be positive" });
    }
    if params.min_views < 2 {
        return Err(PhotoError::BadParams { what: "min_views must be at least 2" });
    }
    if !(-1.0..=1.0).contains(&params.min_cos) {
        return Err(PhotoError::BadParams { what: "min_cos must be in -1..1" });
    }
    if params.min_ncc.is_some_and(|n| !(-1.0..=1.0).contains(&n)) {
        return Err(PhotoError::BadParams { what: "min_ncc must be in -1..1" });
    }
    for (n, v) in views.iter().enumerate() {
        let c = &v.camera;
        let size = (c.width, c.height);
        if v.image.dimensions() != size || v.mask.is_some_and(|m| (m.width(), m.height()) != size) {
            return Err(PhotoError::ImageSize { view: n, width: c.width, height: c.height });
        }
        if !c.is_finite() {
            return Err(PhotoError::BadCamera { view: n });
        }
    }
    Ok(())
}

/// A camera prepared for projecting voxels of one grid (`f32`, see the module docs).
#[derive(Debug, Clone)]
pub(crate) struct VoxelCamera {
    r: [[f32; 3]; 3],
    t: [f32; 3],
    fx: f32,
    fy: f32,
    cx: f32,
    cy: f32,
    skew: f32,
    k1: f32,
    k2: f32,
    k3: f32,
    p1: f32,
    p2: f32,
    pub(crate) width: usize,
    pub(crate) height: usize,
    /// Camera centre, grid frame, metres.
    pub(crate) centre: [f32; 3],
    origin: [f32; 3],
    size: f32,
    /// Whether any lens term is non-zero (without one, projection skips the lens polynomial, which
    /// would leave every coordinate unchanged).
    distorted: bool,
    /// Camera-frame centre of voxel (0, 0, 0), metres.
    base: [f32; 3],
    /// Camera-frame step of one voxel along grid axis `a` (`axis[a]`), metres.
    axis: [[f32; 3]; 3],
}

/// A footprint: the voxel centre's camera depth (metres) and the pixel rectangle `[x0, x1) x [y0, y1)`.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Footprint {
    pub(crate) depth: f32,
    pub(crate) x0: usize,
    pub(crate) x1: usize,
    pub(crate) y0: usize,
    pub(crate) y1: usize,
}

impl VoxelCamera {
    pub(crate) fn new(camera: &CameraModel, grid: &VoxelGrid) -> VoxelCamera {
        let rot = &camera.pose.rotation;
        let r = [0, 1, 2].map(|a| [0, 1, 2].map(|b| rot[(a, b)] as f32));
        let t = [0, 1, 2].map(|a| camera.pose.translation[a] as f32);
        let c = camera.centre();
        let i = &camera.intrinsics;
        VoxelCamera {
            r,
            t,
            fx: i.fx as f32,
            fy: i.fy as f32,
            cx: i.cx as f32,
            cy: i.cy as f32,
            skew: i.skew as f32,
            k1: i.k1 as f32,
            k2: i.k2 as f32,
            k3: i.k3 as f32,
            p1: i.p1 as f32,
            p2: i.p2 as f32,
            width: camera.width as usize,
            height: camera.height as usize,
            centre: [c.x as f32, c.y as f32, c.z as f32],
            origin: grid.origin.map(|x| x as f32),
            size: grid.voxel_size as f32,
            distorted: [i.k1, i.k2, i.k3, i.p1, i.p2].iter().any(|&k| k != 0.0),
            base: {
                let p = [0, 1, 2].map(|a| grid.origin[a] + 0.5 * grid.voxel_size);
                [0, 1, 2]
                    .map(|a| (0..3).map(|b| rot[(a, b)] * p[b]).sum::<f64>() + camera.pose.translation[a])
                    .map(|x| x as f32)
            },
            axis: [0, 1, 2].map(|b| [0, 1, 2].map(|a| (rot[(a, b)] * grid.voxel_size) as f32)),
        }
    }

    /// Camera-frame coordinates (metres) of voxel `v`'s centre, from the per-axis steps.
    #[inline]
    fn camera_frame(&self, v: [u32; 3]) -> [f32; 3] {
        let f = v.map(|x| x as f32);
        [0, 1, 2].map(|a| self.base[a] + f[0] * self.axis[0][a] + f[1] * self.axis[1][a] + f[2] * self.axis[2][a])
    }

    /// Continuous pixel coordinates of camera-frame point `(x, y, z)` (`z > 0`).
    #[inline]
    fn image_of(&self, x: f32, y: f32, z: f32) -> (f32, f32) {
        let (x, y) = (x / z, y / z);
        if self.distorted {
            return self.lens(x, y);
        }
        (self.fx * x + self.skew * y + self.cx, self.fy * y + self.cy)
    }

    /// Centre of voxel `v` at fractional offset `f` (voxel units, 0 = centre), grid frame, metres.
    #[inline]
    pub(crate) fn point(&self, v: [u32; 3], f: [f32; 3]) -> [f32; 3] {
        [0, 1, 2].map(|a| self.origin[a] + (v[a] as f32 + 0.5 + f[a]) * self.size)
    }

    /// Camera depth and continuous pixel coordinates of grid-frame point `p`.
    #[inline]
    pub(crate) fn project(&self, p: [f32; 3]) -> (f32, f32, f32) {
        let c = [0, 1, 2].map(|a| self.r[a][0] * p[0] + self.r[a][1] * p[1] + self.r[a][2] * p[2] + self.t[a]);
        let (u, w) = self.lens(c[0] / c[2], c[1] / c[2]);
        (c[2], u, w)
    }

    /// Continuous pixel coordinates of normalised image point `(x, y)` (`x/z`, `y/z` of a
    /// camera-frame point), through every lens term (also when all are zero).
    #[inline]
    fn lens(&self, x: f32, y: f32) -> (f32, f32) {
        let r2 = x * x + y * y;
        // As `Intrinsics::distort`: radial k1 k2 k3, tangential p1 p2.
        let f = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        let xd = x * f + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x);
        let yd = y * f + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y;
        (self.fx * xd + self.skew * yd + self.cx, self.fy * yd + self.cy)
    }

    /// The pixel a continuous image point falls in, if inside the image.
    #[inline]
    pub(crate) fn pixel(&self, u: f32, v: f32) -> Option<(usize, usize)> {
        (u >= 0.0 && v >= 0.0 && u < self.width as f32 && v < self.height as f32).then_some((u as usize, v as usize))
    }

    /// The pixels `[x0, x1) x [y0, y1)` that hold every footprint of a voxel inside the box of voxels
    /// `lo..hi` (voxel indices, `hi` exclusive), clipped to the image (possibly empty); `None` when
    /// a corner of the box is behind the camera.
    ///
    /// The pinhole image of the box (normalised coordinates `x/z`, `y/z`) is the convex hull of its
    /// corners' images, so it lies in their bounding rectangle. Without lens terms that rectangle
    /// maps to pixels directly. With them, the lens polynomial is bounded over the rectangle by
    /// interval arithmetic (every term is monotone in `r²` or a product of intervals), which holds
    /// every distorted point of the box however the lens bends the box's edges; over a brick a few
    /// pixels wide the bound is within a fraction of a pixel of the corners' rectangle.
    pub(crate) fn box_pixels(&self, lo: [u32; 3], hi: [u32; 3]) -> Option<[usize; 4]> {
        let (mut xa, mut xb, mut ya, mut yb) = (f32::INFINITY, f32::NEG_INFINITY, f32::INFINITY, f32::NEG_INFINITY);
        let (mut u0, mut u1, mut v0, mut v1) = (f32::INFINITY, f32::NEG_INFINITY, f32::INFINITY, f32::NEG_INFINITY);
        for corner in 0..8 {
            let p = [0, 1, 2].map(|a| {
                let i = if corner >> a & 1 == 1 { hi[a] } else { lo[a] };
                self.origin[a] + i as f32 * self.size
            });
            let c = [0, 1, 2].map(|a| self.r[a][0] * p[0] + self.r[a][1] * p[1] + self.r[a][2] * p[2] + self.t[a]);
            let (z, x, y) = (c[2], c[0] / c[2], c[1] / c[2]);
            let (u, w) = self.lens(x, y);
            if z.is_nan() || z <= 0.0 || !u.is_finite() || !w.is_finite() {
                return None;
            }
            xa = xa.min(x);
            xb = xb.max(x);
            ya = ya.min(y);
            yb = yb.max(y);
            u0 = u0.min(u);
            u1 = u1.max(u);
            v0 = v0.min(w);
            v1 = v1.max(w);
        }
        if self.distorted {
            [u0, u1, v0, v1] = self.distorted_bound([xa, xb], [ya, yb])?;
        }
        // A footprint is the pixels whose centres lie in its voxel's rectangle, or the pixel its
        // centre falls in: all within one pixel of the box's rectangle.
        let clip = |lo: f32, hi: f32, n: usize| {
            let a = (floor_f32(lo) - 1.0).clamp(0.0, n as f32) as usize;
            let b = (floor_f32(hi) + 2.0).clamp(0.0, n as f32) as usize;
            (a, b.max(a))
        };
        let (x0, x1) = clip(u0, u1, self.width);
        let (y0, y1) = clip(v0, v1, self.height);
        Some([x0, x1, y0, y1])
    }

    /// Bounds `[u0, u1, v0, v1]` (continuous pixels) of the distorted images of the normalised
    /// points `[xa, xb] x [ya, yb]`, by interval arithmetic in `f64`; `None` when not finite.
    fn distorted_bound(&self, [xa, xb]: [f32; 2], [ya, yb]: [f32; 2]) -> Option<[f32; 4]> {
        type I = [f64; 2];
        let mul = |a: I, b: I| {
            let p = [a[0] * b[0], a[0] * b[1], a[1] * b[0], a[1] * b[1]];
            [p.iter().copied().fold(f64::INFINITY, f64::min), p.iter().copied().fold(f64::NEG_INFINITY, f64::max)]
        };
        let add = |a: I, b: I| [a[0] + b[0], a[1] + b[1]];
        let scale = |a: I, k: f32| mul(a, [f64::from(k); 2]);
        let square = |a: I| {
            let (l, h) = (a[0] * a[0], a[1] * a[1]);
            if a[0] <= 0.0 && a[1] >= 0.0 {
                [0.0, l.max(h)]
            } else {
                [l.min(h), l.max(h)]
            }
        };
        let x = [f64::from(xa), f64::from(xb)];
        let y = [f64::from(ya), f64::from(yb)];
        let (x2, y2) = (square(x), square(y));
        let r2 = add(x2, y2);
        // k r2^n is monotone in r2 >= 0: its interval is spanned by the ends'.
        let term = |k: f32, n: i32| {
            let (a, b) = (f64::from(k) * r2[0].powi(n), f64::from(k) * r2[1].powi(n));
            [a.min(b), a.max(b)]
        };
        let f = add(add(add([1.0; 2], term(self.k1, 1)), term(self.k2, 2)), term(self.k3, 3));
        let xy = mul(x, y);
        // As `project`: xd = x f + 2 p1 x y + p2 (r2 + 2 x^2), yd = y f + p1 (r2 + 2 y^2) + 2 p2 x y.
        let xd = add(add(mul(x, f), scale(xy, 2.0 * self.p1)), scale(add(r2, scale(x2, 2.0)), self.p2));
        let yd = add(add(mul(y, f), scale(add(r2, scale(y2, 2.0)), self.p1)), scale(xy, 2.0 * self.p2));
        let u = add(add(scale(xd, self.fx), scale(yd, self.skew)), [f64::from(self.cx); 2]);
        let v = add(scale(yd, self.fy), [f64::from(self.cy); 2]);
        let out = [u[0], u[1], v[0], v[1]];
        out.iter().all(|b| b.is_finite()).then(|| out.map(|b| b as f32))
    }

    /// The footprint of voxel `v` (see the module docs); `None` when a corner is behind the camera or
    /// the footprint misses the image.
    pub(crate) fn footprint(&self, v: [u32; 3]) -> Option<Footprint> {
        self.footprint_of_cube(v, 0.5)
    }

    /// The camera depth (metres) and continuous pixel coordinates of the centre of voxel `v`, and
    /// the bounding rectangle `[u0, u1] x [v0, v1]` (continuous pixels) of the corners of the cube
    /// of half-edge `half` (voxel units) centred on it, with the centre's image; `None` when a
    /// corner is behind the camera.
    ///
    /// The corners are the centre's camera-frame point plus or minus `half` of each axis step
    /// (computed once per camera), so one voxel costs one small affine map and nine divisions.
    #[inline]
    fn cube_rect(&self, v: [u32; 3], half: f32) -> Option<(f32, f32, f32, [f32; 4])> {
        // Corner n is the centre plus or minus half a step along each grid axis (bit a of n: +).
        const SIGN: [[f32; 8]; 3] = [
            [-1.0, 1.0, -1.0, 1.0, -1.0, 1.0, -1.0, 1.0],
            [-1.0, -1.0, 1.0, 1.0, -1.0, -1.0, 1.0, 1.0],
            [-1.0, -1.0, -1.0, -1.0, 1.0, 1.0, 1.0, 1.0],
        ];
        let c = self.camera_frame(v);
        let d = self.axis.map(|a| a.map(|x| x * half));
        let corner = |k: usize| -> [f32; 8] {
            std::array::from_fn(|n| c[k] + SIGN[0][n] * d[0][k] + SIGN[1][n] * d[1][k] + SIGN[2][n] * d[2][k])
        };
        let (xs, ys, zs) = (corner(0), corner(1), corner(2));
        // NaN depths fail `z > 0` too.
        if !(zs.iter().all(|&z| z > 0.0) && c[2] > 0.0) {
            return None;
        }
        let (uc, vc) = self.image_of(c[0], c[1], c[2]);
        let (us, ws): ([f32; 8], [f32; 8]) = if self.distorted {
            let mut us = [0f32; 8];
            let mut ws = [0f32; 8];
            for n in 0..8 {
                (us[n], ws[n]) = self.image_of(xs[n], ys[n], zs[n]);
            }
            (us, ws)
        } else {
            // The pinhole map, written so the eight corners go through it together.
            let inv: [f32; 8] = std::array::from_fn(|n| 1.0 / zs[n]);
            (
                std::array::from_fn(|n| (self.fx * xs[n] + self.skew * ys[n]) * inv[n] + self.cx),
                std::array::from_fn(|n| self.fy * ys[n] * inv[n] + self.cy),
            )
        };
        let (mut u0, mut u1, mut v0, mut v1) = (uc, uc, vc, vc);
        for n in 0..8 {
            u0 = u0.min(us[n]);
            u1 = u1.max(us[n]);
            v0 = v0.min(ws[n]);
            v1 = v1.max(ws[n]);
        }
        Some((c[2], uc, vc, [u0, u1, v0, v1]))
    }

    /// The footprint of the cube of half-edge `half` (voxel units, 0.5 = the voxel) centred on voxel
    /// `v`, as [`Self::footprint`].
    pub(crate) fn footprint_of_cube(&self, v: [u32; 3], half: f32) -> Option<Footprint> {
        let (depth, uc, vc, [u0, u1, v0, v1]) = self.cube_rect(v, half)?;
        let on_image = u1 >= 0.0 && v1 >= 0.0 && u0 < self.width as f32 && v0 < self.height as f32;
        if depth.is_nan() || depth <= 0.0 || !on_image {
            return None;
        }
        // Pixels whose centre x + 0.5 lies in [u0, u1].
        let range = |lo: f32, hi: f32, c: f32, n: usize| {
            let a = ceil_f32(lo - 0.5).max(0.0);
            let b = (floor_f32(hi - 0.5) + 1.0).min(n as f32);
            if a < b {
                (a as usize, b as usize)
            } else {
                let p = floor_f32(c).clamp(0.0, n as f32 - 1.0) as usize;
                (p, p + 1)
            }
        };
        let (x0, x1) = range(u0, u1, uc, self.width);
        let (y0, y1) = range(v0, v1, vc, self.height);
        Some(Footprint { depth, x0, x1, y0, y1 })
    }

    /// The pixels voxel `v` covers the way [`super::space_carving::reproject`] splats voxels: the
    /// inclusive pixel rectangle `[x0, x1] x [y0, y1]` whose centres lie in the bounding rectangle
    /// of the voxel's projected corners (when any does), and the pixel its centre falls in (when it
    /// is on the image); nothing when a corner is behind the camera. Computed in `f32`.
    #[inline]
    fn cover_of(&self, v: [u32; 3]) -> (Option<[usize; 4]>, Option<(usize, usize)>) {
        let (w, h) = (self.width, self.height);
        let Some((_, uc, vc, [u0, u1, v0, v1])) = self.cube_rect(v, 0.5) else { return (None, None) };
        if !(u0.is_finite() && u1.is_finite() && v0.is_finite() && v1.is_finite()) {
            return (None, None);
        }
        let ua = ceil_f32(u0 - 0.5).max(0.0);
        let ub = floor_f32(u1 - 0.5).min(w as f32 - 1.0);
        let va = ceil_f32(v0 - 0.5).max(0.0);
        let vb = floor_f32(v1 - 0.5).min(h as f32 - 1.0);
        let rect = (ua <= ub && va <= vb).then_some([ua as usize, ub as usize, va as usize, vb as usize]);
        (rect, self.pixel(floor_f32(uc), floor_f32(vc)))
    }

    /// Whether voxel `v` covers pixel `(x, y)` (as [`Self::cover`] counts it).
    pub(crate) fn covers(&self, v: [u32; 3], x: usize, y: usize) -> bool {
        let (rect, centre) = self.cover_of(v);
        rect.is_some_and(|[x0, x1, y0, y1]| (x0..=x1).contains(&x) && (y0..=y1).contains(&y)) || centre == Some((x, y))
    }

    /// Per pixel (row-major), whether one of `voxels` covers it (see [`Self::covers`]).
    ///
    /// The voxels are taken in runs of consecutive ones in the same [`COVER_RUN_BRICK`]³ brick (the
    /// order `Occupancy::boundary_voxels` gives makes them long; any order gives the same answer):
    /// a run of at least [`COVER_RUN_MIN`] whose pixel rectangle (`box_pixels` of the box around
    /// its voxels, which holds each of their footprints) is already all covered adds nothing, and
    /// none of its voxels is projected.
    pub(crate) fn cover(&self, voxels: &[[u32; 3]]) -> Vec<bool> {
        self.cover_counting(voxels).0
    }

    /// [`Self::cover`], with how many voxels it did not project (their run's rectangle was covered).
    fn cover_counting(&self, voxels: &[[u32; 3]]) -> (Vec<bool>, usize) {
        let w = self.width;
        let mut skipped = 0;
        let mut out = vec![false; w * self.height];
        let brick = |v: &[u32; 3]| v.map(|x| x / COVER_RUN_BRICK);
        // Nearest runs first: those behind them are then the likelier to find their pixels covered.
        let mut runs: Vec<(f32, &[[u32; 3]])> =
            voxels.chunk_by(|a, b| brick(a) == brick(b)).map(|r| (self.camera_frame(r[0])[2], r)).collect();
        runs.sort_by(|a, b| a.0.total_cmp(&b.0));
        for (_, run) in runs {
            if run.len() >= COVER_RUN_MIN {
                let lo = run.iter().fold([u32::MAX; 3], |m, v| [0, 1, 2].map(|a| m[a].min(v[a])));
                let hi = run.iter().fold([0; 3], |m, v| [0, 1, 2].map(|a| m[a].max(v[a] + 1)));
                let covered = self
                    .box_pixels(lo, hi)
                    .is_some_and(|[x0, x1, y0, y1]| (y0..y1).all(|y| out[y * w + x0..y * w + x1].iter().all(|&c| c)));
                if covered {
                    skipped += run.len();
                    continue;
                }
            }
            for &v in run {
                self.splat(v, &mut out);
            }
        }
        (out, skipped)
    }

    /// Mark the pixels voxel `v` covers (see [`Self::covers`]) in `out` (row-major, this camera's size).
    fn splat(&self, v: [u32; 3], out: &mut [bool]) {
        let w = self.width;
        let (rect, centre) = self.cover_of(v);
        if let Some([x0, x1, y0, y1]) = rect {
            for y in y0..=y1 {
                out[y * w + x0..=y * w + x1].fill(true);
            }
        }
        if let Some((x, y)) = centre {
            out[y * w + x] = true;
        }
    }
}

/// Edge, voxels, of the bricks [`VoxelCamera::cover`] groups its voxels by.
const COVER_RUN_BRICK: u32 = 8;
/// The fewest voxels in a run of [`VoxelCamera::cover`] worth checking its pixel rectangle for.
const COVER_RUN_MIN: usize = 8;

/// Per pixel of one view, the nearest surface voxel covering it (by index into a voxel list).
#[derive(Debug, Clone)]
pub struct ItemBuffer {
    width: usize,
    depth: Vec<f32>,
    id: Vec<u32>,
}

impl ItemBuffer {
    /// No voxel.
    pub const NONE: u32 = u32::MAX;

    /// The voxel (index into the list it was rendered from) nearest in pixel `(x, y)`, or [`Self::NONE`].
    pub fn get(&self, x: usize, y: usize) -> u32 {
        self.id.get(y * self.width + x).copied().unwrap_or(Self::NONE)
    }

    /// The voxel nearest in pixel `p = y * width + x`, or [`Self::NONE`].
    #[inline]
    pub(crate) fn at(&self, p: usize) -> u32 {
        self.id.get(p).copied().unwrap_or(Self::NONE)
    }

    /// Per pixel (row-major), the voxel nearest there or [`Self::NONE`].
    pub(crate) fn ids(&self) -> &[u32] {
        &self.id
    }

    pub(crate) fn render(cam: &VoxelCamera, voxels: &[[u32; 3]]) -> ItemBuffer {
        let n = cam.width * cam.height;
        let mut buf = ItemBuffer { width: cam.width, depth: vec![f32::INFINITY; n], id: vec![Self::NONE; n] };
        for (idx, &v) in voxels.iter().enumerate() {
            let Some(fp) = cam.footprint(v) else { continue };
            for y in fp.y0..fp.y1 {
                let row = y * cam.width;
                for x in fp.x0..fp.x1 {
                    let p = row + x;
                    if fp.depth < buf.depth[p] {
                        buf.depth[p] = fp.depth;
                        buf.id[p] = idx as u32;
                    }
                }
            }
        }
        buf
    }
}

/// Render item buffers of `voxels` for every camera, in parallel.
pub(crate) fn render_item_buffers(cams: &[VoxelCamera], voxels: &[[u32; 3]]) -> Vec<ItemBuffer> {
    cams.par_iter().map(|c| ItemBuffer::render(c, voxels)).collect()
}

/// One view's visible samples of a voxel.
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct ViewSample {
    pub(crate) count: u32,
    /// Mean colour, 8-bit levels.
    pub(crate) mean: [f32; 3],
    /// Colour of the pixel the voxel's centre projects into, when the voxel is visible there (and it
    /// is inside the mask); only gathered for colouring.
    pub(crate) centre: Option<[u8; 3]>,
}

/// Outward normal estimate of voxel `v`: the normalised sum of the offsets to its empty
/// 26-neighbours (out-of-grid counts as empty). Zero when it has none or they cancel.
pub(crate) fn normal_estimate(occupied: &impl Fn(i64, i64, i64) -> bool, v: [u32; 3]) -> [f32; 3] {
    let mut n = [0f32; 3];
    for dz in -1i64..=1 {
        for dy in -1i64..=1 {
            for dx in -1i64..=1 {
                if (dx, dy, dz) != (0, 0, 0) && !occupied(v[0] as i64 + dx, v[1] as i64 + dy, v[2] as i64 + dz) {
                    n[0] += dx as f32;
                    n[1] += dy as f32;
                    n[2] += dz as f32;
                }
            }
        }
    }
    let l = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
    if l > 1e-6 {
        n.map(|x| x / l)
    } else {
        [0.0; 3]
    }
}

/// Cosine between `normal` and the direction from voxel centre `p` to `cam`'s centre (1 without a normal).
pub(crate) fn facing(cam: &VoxelCamera, p: [f32; 3], normal: [f32; 3]) -> f32 {
    if normal == [0.0; 3] {
        return 1.0;
    }
    let d = [0, 1, 2].map(|a| cam.centre[a] - p[a]);
    let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(1e-12);
    (d[0] * normal[0] + d[1] * normal[1] + d[2] * normal[2]) / l
}

/// Width of the silhouette contour band (see [`ViewPixels`]), pixels.
pub const CONTOUR_BAND_PX: usize = 2;

/// Bit of [`ViewPixels`]' per-pixel class: inside the silhouette (every pixel without a mask).
const INSIDE: u8 = 1;
/// Bit of [`ViewPixels`]' per-pixel class: inside the silhouette and on its contour band.
const RIM: u8 = 2;

/// One view's visible footprint pixels, summed in one pass by [`ViewPixels::sample`].
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub(crate) struct FootprintSample {
    /// Visible pixels inside the silhouette.
    pub(crate) count: u32,
    /// Their mean colour, 8-bit levels (zero without pixels).
    pub(crate) mean: [f32; 3],
    /// Whether one of them lies on the silhouette's contour band.
    pub(crate) rim: bool,
}

/// A view's pixels prepared for sampling footprints: its image and, per pixel, whether it is inside
/// the silhouette and whether it lies on the silhouette's *contour band*: inside the mask with a
/// pixel outside it within [`CONTOUR_BAND_PX`] along its row or column (the image border is no
/// contour: the object may go on beyond it). Without a mask every pixel is inside and none is on a
/// contour.
///
/// The carvers keep voxels seen on a contour band: the visual hull touches the object along its
/// rims, so a voxel that a view sees on its silhouette's outline lies on the surface (up to the
/// silhouettes' accuracy), and carving it would shrink that view's silhouette of the result below
/// the hull's.
#[derive(Clone)]
pub(crate) struct ViewPixels<'a> {
    image: &'a [u8],
    width: usize,
    class: Vec<u8>,
}

impl<'a> ViewPixels<'a> {
    /// Classify `view`'s pixels (its image and mask sizes must match, see `check_inputs`).
    pub(crate) fn new(view: &PhotoView<'a>) -> ViewPixels<'a> {
        let (w, h) = (view.image.width() as usize, view.image.height() as usize);
        let class = match view.mask {
            None => vec![INSIDE; w * h],
            Some(m) => {
                let data = m.data();
                let outside = |x: usize, y: usize| data[y * w + x] == 0;
                let mut class = vec![0u8; w * h];
                for y in 0..h {
                    for x in 0..w {
                        if outside(x, y) {
                            continue;
                        }
                        let b = CONTOUR_BAND_PX;
                        let near = (x.saturating_sub(b)..(x + b + 1).min(w)).any(|u| outside(u, y))
                            || (y.saturating_sub(b)..(y + b + 1).min(h)).any(|v| outside(x, v));
                        class[y * w + x] = if near { INSIDE | RIM } else { INSIDE };
                    }
                }
                class
            }
        };
        ViewPixels { image: view.image.as_raw(), width: w, class }
    }

    /// Every view of `views`, in parallel.
    pub(crate) fn all(views: &[PhotoView<'a>]) -> Vec<ViewPixels<'a>> {
        views.par_iter().map(ViewPixels::new).collect()
    }

    /// Whether pixel `(x, y)` is inside the silhouette.
    #[inline]
    pub(crate) fn inside(&self, x: usize, y: usize) -> bool {
        self.class[y * self.width + x] & INSIDE != 0
    }

    /// The first pixel, in row-major order from number `from` on (numbered row by row within the
    /// rectangle `[x0, x1, y0, y1]`, i.e. `[x0, x1) x [y0, y1)` inside the image), that is inside
    /// the silhouette and not set in `marks` (row-major, one flag a pixel); `None` when there is
    /// none: no footprint sample can then take a pixel of the rest of the rectangle that `marks`
    /// hides. Marks only being added, a caller can resume from the number returned last time.
    pub(crate) fn first_unsettled(&self, marks: &[bool], [x0, x1, y0, y1]: [usize; 4], from: usize) -> Option<usize> {
        let w = x1 - x0;
        if w == 0 {
            return None;
        }
        for y in y0 + from / w..y1 {
            let skip = if y == y0 + from / w { from % w } else { 0 };
            let row = y * self.width;
            let (a, b) = (row + x0 + skip, row + x1);
            if let Some(k) = marks[a..b].iter().zip(&self.class[a..b]).position(|(&m, &c)| !m && c != 0) {
                return Some((y - y0) * w + skip + k);
            }
        }
        None
    }

    /// The colour of pixel `(x, y)`.
    #[inline]
    pub(crate) fn colour(&self, x: usize, y: usize) -> [u8; 3] {
        let p = 3 * (y * self.width + x);
        [self.image[p], self.image[p + 1], self.image[p + 2]]
    }

    /// The pixels of footprint `fp` for which `visible(p)` holds (`p = y * width + x`) and that lie
    /// inside the silhouette: their count, mean colour and whether one is on the contour band.
    #[inline]
    pub(crate) fn sample(&self, fp: &Footprint, visible: impl Fn(usize) -> bool) -> FootprintSample {
        let mut sum = [0u32; 3];
        let mut count = 0u32;
        let mut rim = 0u8;
        for y in fp.y0..fp.y1 {
            let row = y * self.width;
            for p in row + fp.x0..row + fp.x1 {
                let c = self.class[p];
                if c == 0 || !visible(p) {
                    continue;
                }
                rim |= c;
                let px = &self.image[3 * p..3 * p + 3];
                sum[0] += px[0] as u32;
                sum[1] += px[1] as u32;
                sum[2] += px[2] as u32;
                count += 1;
            }
        }
        let mean = if count == 0 { [0.0; 3] } else { sum.map(|s| s as f32 / count as f32) };
        FootprintSample { count, mean, rim: rim & RIM != 0 }
    }
}

/// The colour of the pixel voxel `v`'s centre projects into, if `visible(p)` holds there (`p = y *
/// width + x`) and the pixel is inside the silhouette.
pub(crate) fn centre_sample(
    cam: &VoxelCamera,
    px: &ViewPixels<'_>,
    v: [u32; 3],
    visible: impl Fn(usize) -> bool,
) -> Option<[u8; 3]> {
    let (z, u, w) = cam.project(cam.point(v, [0.0; 3]));
    if z.is_nan() || z <= 0.0 {
        return None;
    }
    let (x, y) = cam.pixel(u, w)?;
    if !px.inside(x, y) || !visible(y * px.width + x) {
        return None;
    }
    Some(px.colour(x, y))
}

/// Count-weighted standard deviation of per-view mean colours, RMS over channels, 8-bit levels.
pub(crate) fn colour_spread(samples: &[ViewSample]) -> f32 {
    let total: f32 = samples.iter().map(|s| s.count as f32).sum();
    if total <= 0.0 {
        return 0.0;
    }
    let mut var = 0f32;
    for c in 0..3 {
        let mean = samples.iter().map(|s| s.count as f32 * s.mean[c]).sum::<f32>() / total;
        var += samples.iter().map(|s| s.count as f32 * (s.mean[c] - mean).powi(2)).sum::<f32>() / total;
    }
    (var / 3.0).sqrt()
}

/// Mean NCC of each view's pattern with the mean pattern; `None` when fewer than two patterns or the
/// mean pattern is untextured (see [`NCC_MIN_SIGMA`]).
pub(crate) fn mean_ncc(patterns: &[[f32; 24]]) -> Option<f32> {
    if patterns.len() < 2 {
        return None;
    }
    let mut mean = [0f32; 24];
    for p in patterns {
        for (m, x) in mean.iter_mut().zip(p) {
            *m += x / patterns.len() as f32;
        }
    }
    let centred = |p: &[f32; 24]| {
        let mu = p.iter().sum::<f32>() / 24.0;
        p.map(|x| x - mu)
    };
    let m = centred(&mean);
    let mnorm = m.iter().map(|x| x * x).sum::<f32>().sqrt();
    if mnorm / 24f32.sqrt() < NCC_MIN_SIGMA {
        return None;
    }
    let mut acc = 0f32;
    for p in patterns {
        let q = centred(p);
        let qn = q.iter().map(|x| x * x).sum::<f32>().sqrt().max(1e-6);
        acc += q.iter().zip(&m).map(|(a, b)| a * b).sum::<f32>() / (qn * mnorm);
    }
    Some(acc / patterns.len() as f32)
}

/// The 24-value pattern (8 sub-voxel points × RGB) of voxel `v` in a view, if every point is visible.
pub(crate) fn ncc_pattern(
    cam: &VoxelCamera,
    px: &ViewPixels<'_>,
    v: [u32; 3],
    visible: impl Fn(usize) -> bool,
) -> Option<[f32; 24]> {
    let mut out = [0f32; 24];
    for s in 0..8 {
        let f = [0, 1, 2].map(|a| if s >> a & 1 == 1 { 0.25 } else { -0.25 });
        let (z, u, w) = cam.project(cam.point(v, f));
        if z.is_nan() || z <= 0.0 {
            return None;
        }
        let (x, y) = cam.pixel(u, w)?;
        if !visible(y * px.width + x) {
            return None;
        }
        let rgb = px.colour(x, y);
        for c in 0..3 {
            out[3 * s + c] = rgb[c] as f32;
        }
    }
    Some(out)
}

/// The verdict on one voxel from its per-view samples (views below `min_cos` already removed) and
/// NCC patterns: `true` = consistent (or undecided).
pub(crate) fn is_consistent(samples: &[ViewSample], patterns: &[[f32; 24]], params: &PhotoParams) -> bool {
    if samples.len() < params.min_views {
        return true;
    }
    if colour_spread(samples) > params.threshold {
        return false;
    }
    match (params.min_ncc, mean_ncc(patterns)) {
        (Some(min), Some(ncc)) => ncc >= min,
        _ => true,
    }
}

/// The colour of a voxel from its per-view samples (the unoccluded views that face it, cosine >=
/// `min_cos`): the mean of their centre pixels ([`ViewSample::centre`]) where any has one, else the
/// count-weighted mean of their footprint means; [`UNSEEN_COLOUR`] without samples.
///
/// The centre pixel is sharper than the footprint (which spans up to twice the voxel and blurs texture
/// edges). Averaging over every facing view rather than taking the most frontal one cancels much of
/// the view-dependent shading: on a turntable the lights stay with the camera, so the most frontal
/// view is also the most brightly lit (on the shipped cup rig, colouring from the views within 0.05
/// of the best cosine gives a mean colour error of about 12/255, the mean over all facing views 7.9).
pub(crate) fn surface_colour(samples: &[ViewSample]) -> [u8; 3] {
    let mut acc = [0f32; 3];
    let mut n = 0f32;
    for c in samples.iter().filter_map(|s| s.centre) {
        for (a, x) in acc.iter_mut().zip(c) {
            *a += x as f32;
        }
        n += 1.0;
    }
    if n == 0.0 {
        for s in samples {
            for (a, m) in acc.iter_mut().zip(&s.mean) {
                *a += s.count as f32 * m;
            }
            n += s.count as f32;
        }
    }
    if n > 0.0 {
        acc.map(|x| (x / n).round().clamp(0.0, 255.0) as u8)
    } else {
        UNSEEN_COLOUR
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn s(count: u32, mean: [f32; 3], _cos: f32) -> ViewSample {
        ViewSample { count, mean, centre: None }
    }

    /// A 640x480 camera with every lens term and skew, looking at the origin from 0.34 m.
    fn lens_camera() -> CameraModel {
        use crate::geometry::{Intrinsics, Pose};
        use nalgebra::Vector3;
        CameraModel {
            intrinsics: Intrinsics {
                k1: -0.21,
                k2: 0.09,
                p1: 0.004,
                p2: -0.003,
                k3: -0.02,
                skew: 0.5,
                ..Intrinsics::new(800.0, 790.0, 321.0, 238.0)
            },
            pose: Pose::look_at(Vector3::new(0.05, -0.3, 0.15), Vector3::zeros(), Vector3::z()),
            width: 640,
            height: 480,
        }
    }

    #[test]
    fn voxel_camera_projects_like_the_camera_model_with_every_lens_term() {
        use crate::geometry::Aabb;
        use nalgebra::Vector3;
        let camera = lens_camera();
        let grid = VoxelGrid::from_resolution(&Aabb { min: [-0.05; 3], max: [0.05; 3] }, 16);
        let vc = VoxelCamera::new(&camera, &grid);
        let mut checked = 0;
        for v in [[0, 0, 0], [15, 15, 15], [0, 15, 7], [15, 0, 3], [8, 8, 8]] {
            let p = vc.point(v, [0.0; 3]);
            let (_, u, w) = vc.project(p);
            let want = camera
                .project(&Vector3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2])))
                .expect("in front of the camera");
            assert!((f64::from(u) - want.x).abs() < 1e-2 && (f64::from(w) - want.y).abs() < 1e-2, "{u},{w} vs {want}");
            checked += 1;
        }
        assert_eq!(checked, 5);
    }

    #[test]
    fn box_rectangles_hold_every_footprint_of_their_voxels_through_a_distorting_lens() {
        use crate::geometry::{Aabb, Intrinsics};
        let CameraModel { intrinsics: lens, pose, .. } = lens_camera();
        // The grid reaches the image corners, where the lens bends most.
        let grid = VoxelGrid::from_resolution(&Aabb { min: [-0.12; 3], max: [0.12; 3] }, 48);
        let strong = Intrinsics { k1: 0.3, k2: -0.2, p1: -0.02, p2: 0.015, ..lens };
        let tangential = Intrinsics { p1: 0.01, ..Intrinsics::new(800.0, 800.0, 320.0, 240.0) };
        let mut boxes = 0;
        for intrinsics in [lens, strong, tangential, Intrinsics::new(800.0, 790.0, 321.0, 238.0)] {
            let vc = VoxelCamera::new(&CameraModel { intrinsics, pose, width: 640, height: 480 }, &grid);
            for lo in [[0, 0, 0], [44, 44, 44], [0, 44, 20], [44, 0, 8], [22, 22, 22], [5, 30, 40]] {
                let hi = lo.map(|x| x + 4);
                let [x0, x1, y0, y1] = vc.box_pixels(lo, hi).expect("every corner in front");
                let mut union = [usize::MAX, 0, usize::MAX, 0];
                for k in lo[2]..hi[2] {
                    for j in lo[1]..hi[1] {
                        for i in lo[0]..hi[0] {
                            let Some(fp) = vc.footprint([i, j, k]) else { continue };
                            assert!(
                                fp.x0 >= x0 && fp.x1 <= x1 && fp.y0 >= y0 && fp.y1 <= y1,
                                "{fp:?} outside {:?} for {intrinsics:?}",
                                [x0, x1, y0, y1]
                            );
                            union =
                                [union[0].min(fp.x0), union[1].max(fp.x1), union[2].min(fp.y0), union[3].max(fp.y1)];
                        }
                    }
                }
                // Tight: within a few pixels (and a fraction of its size, for a strong lens near the
                // image's edge) of the footprints' own bounding rectangle.
                if union[0] >= union[1] {
                    continue; // off the image
                }
                let slack = (union[0] - x0) + (x1 - union[1]) + (union[2] - y0) + (y1 - union[3]);
                assert!(
                    slack <= 8 + (union[1] - union[0] + union[3] - union[2]) / 4,
                    "{:?} around {union:?} for {intrinsics:?}",
                    [x0, x1, y0, y1]
                );
                boxes += 1;
            }
        }
        assert!(boxes >= 12, "{boxes} boxes seen");
    }

    #[test]
    fn covering_by_runs_projects_fewer_voxels_and_changes_no_pixel() {
        use crate::geometry::{Aabb, Intrinsics};
        use crate::pipeline::occupancy::Occupancy;
        let CameraModel { intrinsics: lens, pose, .. } = lens_camera();
        let grid = VoxelGrid::from_resolution(&Aabb { min: [-0.05; 3], max: [0.05; 3] }, 64);
        let solid = Occupancy::from_fn(grid, |p| p.norm() < 0.04 && p.z < 0.025);
        // Brick by brick (runs of up to a brick's boundary voxels) and row by row (runs of a few).
        let bricks = solid.boundary_voxels();
        let mut rows = bricks.clone();
        rows.sort_unstable_by_key(|v| [v[2], v[1], v[0]]);
        for intrinsics in [lens, Intrinsics::new(800.0, 790.0, 321.0, 238.0)] {
            let vc = VoxelCamera::new(&CameraModel { intrinsics, pose, width: 640, height: 480 }, &grid);
            // Every voxel's footprint splatted, one by one.
            let mut want = vec![false; 640 * 480];
            for &v in &bricks {
                vc.splat(v, &mut want);
            }
            assert!(want.iter().filter(|&&c| c).count() > 20_000);
            let (by_bricks, skipped) = vc.cover_counting(&bricks);
            let (by_rows, _) = vc.cover_counting(&rows);
            for got in [by_bricks, by_rows] {
                let differ = got.iter().zip(&want).filter(|(a, b)| a != b).count();
                assert_eq!(differ, 0, "{differ} pixels differ for {intrinsics:?}");
            }
            // Runs behind the front are left out (a fifth or more of the voxels here, whose bricks are
            // some 30 pixels wide).
            assert!(skipped * 5 > bricks.len(), "{skipped} of {} skipped for {intrinsics:?}", bricks.len());
        }
    }

    #[test]
    fn cube_rectangles_and_covers_match_projecting_every_corner() {
        use crate::geometry::{Aabb, Intrinsics};
        let CameraModel { intrinsics: lens, pose, .. } = lens_camera();
        let grid = VoxelGrid::from_resolution(&Aabb { min: [-0.05; 3], max: [0.05; 3] }, 24);
        for intrinsics in [lens, Intrinsics::new(800.0, 790.0, 321.0, 238.0)] {
            let camera = CameraModel { intrinsics, pose, width: 640, height: 480 };
            let vc = VoxelCamera::new(&camera, &grid);
            let mut checked = 0;
            for v in [[0, 0, 0], [23, 23, 23], [0, 23, 7], [23, 0, 3], [12, 12, 12], [5, 17, 20]] {
                for half in [0.5, 0.6, 0.25] {
                    let (depth, _, _, rect) = vc.cube_rect(v, half).expect("in front");
                    let (dc, mut u0, mut v0) = vc.project(vc.point(v, [0.0; 3]));
                    let (mut u1, mut v1) = (u0, v0);
                    for n in 0..8 {
                        let f = [0, 1, 2].map(|a| if n >> a & 1 == 1 { half } else { -half });
                        let (_, u, w) = vc.project(vc.point(v, f));
                        (u0, u1, v0, v1) = (u0.min(u), u1.max(u), v0.min(w), v1.max(w));
                    }
                    assert!((depth - dc).abs() < 1e-5, "{depth} vs {dc}");
                    for (a, b) in rect.iter().zip([u0, u1, v0, v1]) {
                        assert!((a - b).abs() < 2e-3, "{rect:?} vs {:?}", [u0, u1, v0, v1]);
                    }
                    checked += 1;
                }
            }
            assert_eq!(checked, 18);
        }
    }

    #[test]
    fn footprint_samples_follow_visibility_and_the_contour_band() {
        use crate::geometry::{Intrinsics, Pose};
        use nalgebra::Vector3;
        let (w, h) = (64u32, 48u32);
        // A disc silhouette with a notch, and a textured image.
        let mask = Mask::from_fn(w, h, |x, y| {
            let (dx, dy) = (x as f32 - 30.0, y as f32 - 24.0);
            dx * dx + dy * dy < 300.0 && !(x > 38 && (20..23).contains(&y))
        });
        let image = RgbImage::from_fn(w, h, |x, y| image::Rgb([(x * 4) as u8, (y * 5) as u8, ((x * y) % 251) as u8]));
        let camera = CameraModel {
            intrinsics: Intrinsics::new(50.0, 50.0, 32.0, 24.0),
            pose: Pose::look_at(Vector3::new(0.0, -1.0, 0.0), Vector3::zeros(), Vector3::z()),
            width: w,
            height: h,
        };
        let visible = |p: usize| (p * 7919) % 5 != 0;
        for masked in [true, false] {
            let view = PhotoView { camera, image: &image, mask: masked.then_some(&mask) };
            let px = ViewPixels::new(&view);
            let inside = |x: i64, y: i64| !masked || mask.get(x as u32, y as u32);
            let outside = |x: i64, y: i64| x >= 0 && y >= 0 && x < w as i64 && y < h as i64 && !inside(x, y);
            let mut rims = 0;
            for (x0, y0) in [(0, 0), (5, 10), (12, 20), (20, 5), (28, 20), (36, 18), (40, 30), (60, 44)] {
                let fp = Footprint { depth: 1.0, x0, x1: (x0 + 4).min(64), y0, y1: (y0 + 4).min(48) };
                // By the definition, pixel by pixel.
                let (mut count, mut sum, mut rim) = (0u32, [0f32; 3], false);
                for y in fp.y0..fp.y1 {
                    for x in fp.x0..fp.x1 {
                        let (xi, yi) = (x as i64, y as i64);
                        if !visible(y * 64 + x) || !inside(xi, yi) {
                            continue;
                        }
                        count += 1;
                        for (acc, v) in sum.iter_mut().zip(image.get_pixel(x as u32, y as u32).0) {
                            *acc += v as f32;
                        }
                        rim |= (1..=CONTOUR_BAND_PX as i64).any(|d| {
                            outside(xi - d, yi) || outside(xi + d, yi) || outside(xi, yi - d) || outside(xi, yi + d)
                        });
                    }
                }
                let got = px.sample(&fp, visible);
                assert_eq!((got.count, got.rim), (count, rim), "footprint at {x0},{y0}, masked {masked}");
                for (got, sum) in got.mean.iter().zip(sum) {
                    let want = if count == 0 { 0.0 } else { sum / count as f32 };
                    assert!((got - want).abs() < 1e-3, "{got} vs {want}");
                }
                rims += usize::from(rim);
            }
            // The cases reach both sides of the contour band when there is a mask.
            assert_eq!(rims > 0, masked);
        }
    }

    #[test]
    fn the_first_unsettled_pixel_is_found_and_resumed_from() {
        use crate::geometry::{Intrinsics, Pose};
        use nalgebra::Vector3;
        let (w, h) = (40u32, 30u32);
        let mask = Mask::from_fn(w, h, |x, y| (x + 2 * y) % 7 != 0 && x > 3);
        let image = RgbImage::new(w, h);
        let camera = CameraModel {
            intrinsics: Intrinsics::new(40.0, 40.0, 20.0, 15.0),
            pose: Pose::look_at(Vector3::new(0.0, -1.0, 0.0), Vector3::zeros(), Vector3::z()),
            width: w,
            height: h,
        };
        let px = ViewPixels::new(&PhotoView { camera, image: &image, mask: Some(&mask) });
        let mut marks = vec![false; (w * h) as usize];
        let rect = [2, 12, 5, 11];
        let brute = |marks: &[bool], from: usize| {
            (from..60).find(|&k| {
                let (x, y) = (2 + k % 10, 5 + k / 10);
                !marks[y * 40 + x] && mask.get(x as u32, y as u32)
            })
        };
        let mut from = 0;
        for step in 0..200usize {
            let got = px.first_unsettled(&marks, rect, from);
            assert_eq!(got, brute(&marks, 0), "step {step}");
            let Some(k) = got else { break };
            from = k;
            // Claim a few pixels, the first unsettled one among them.
            for p in [(2 + k % 10) + (5 + k / 10) * 40, (step * 37) % 1200] {
                marks[p] = true;
            }
        }
        assert_eq!(px.first_unsettled(&marks, rect, from), None);
        assert_eq!(px.first_unsettled(&marks, [3, 3, 0, 30], 0), None, "an empty rectangle is settled");
    }

    #[test]
    fn spread_is_zero_for_equal_means_and_grows_with_disagreement() {
        assert_eq!(colour_spread(&[s(4, [100.0; 3], 1.0), s(2, [100.0; 3], 1.0)]), 0.0);
        let d = colour_spread(&[s(1, [90.0; 3], 1.0), s(1, [110.0; 3], 1.0)]);
        assert!((d - 10.0).abs() < 1e-4, "{d}");
        let p = PhotoParams::default();
        assert!(is_consistent(&[s(1, [90.0; 3], 1.0), s(1, [110.0; 3], 1.0)], &[], &p));
        assert!(!is_consistent(&[s(1, [50.0; 3], 1.0), s(1, [150.0; 3], 1.0)], &[], &p));
        // One view cannot judge.
        assert!(is_consistent(&[s(1, [50.0; 3], 1.0)], &[], &p));
    }

    #[test]
    fn ncc_separates_matching_and_mismatched_patterns() {
        let mut a = [0f32; 24];
        for (n, x) in a.iter_mut().enumerate() {
            *x = if n % 6 < 3 { 200.0 } else { 40.0 };
        }
        let brighter = a.map(|x| x * 1.2 + 5.0);
        let ncc = mean_ncc(&[a, brighter]).expect("textured");
        assert!(ncc > 0.99, "{ncc}");
        let inverted = a.map(|x| 240.0 - x);
        let third = a.map(|x| x * 0.9);
        let ncc = mean_ncc(&[a, inverted, third]).expect("textured");
        assert!(ncc < 0.9, "{ncc}");
        assert!(mean_ncc(&[[50.0; 24], [51.0; 24]]).is_none());
    }

    #[test]
    fn immerkaer_estimate_recovers_the_added_noise_and_ignores_smooth_shading() {
        use crate::geometry::{CameraModel, Intrinsics, Pose};
        use nalgebra::Vector3;
        let camera = CameraModel {
            width: 200,
            height: 150,
            intrinsics: Intrinsics { fx: 200.0, fy: 200.0, cx: 100.0, cy: 75.0, ..Intrinsics::default() },
            pose: Pose::look_at(Vector3::new(0.0, -1.0, 0.0), Vector3::zeros(), Vector3::z()),
        };
        // A linear ramp (the mask's Laplacian cancels it) plus uniform noise of +-6 levels (sd 3.46).
        let mut seed = 12345u64;
        let mut noise = || {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((seed >> 33) % 13) as i32 - 6
        };
        let img = RgbImage::from_fn(200, 150, |x, y| {
            let base = 60 + x as i32 / 2 + y as i32 / 3;
            image::Rgb([0, 1, 2].map(|_| (base + noise()).clamp(0, 255) as u8))
        });
        let sd = (((13 * 13 - 1) as f32) / 12.0).sqrt();
        let view = PhotoView { camera, image: &img, mask: None };
        let sigma = image_noise_sigma(&view).expect("interior pixels");
        assert!((sigma - sd).abs() < 0.15 * sd, "estimated {sigma}, added {sd}");
        let clean = RgbImage::from_fn(200, 150, |x, y| image::Rgb([(60 + x / 2 + y / 3) as u8; 3]));
        let clean_view = PhotoView { image: &clean, ..view };
        assert!(image_noise_sigma(&clean_view).expect("interior pixels") < 0.5);
        // The derived threshold follows the spread's outliers and never falls below K x image noise.
        let n = PhotoNoise { image_sigma: sigma, spread_median: 9.0, spread_mad: 2.0, voxels: 100 };
        assert!((n.threshold() - (9.0 + PhotoNoise::K * 1.4826 * 2.0)).abs() < 1e-4);
        let quiet = PhotoNoise { spread_median: 1.0, spread_mad: 0.0, ..n };
        assert!((quiet.threshold() - PhotoNoise::K * sigma).abs() < 1e-4);
        assert_eq!(PhotoParams::default().with_measured_noise(&n).threshold, n.threshold());
    }

    #[test]
    fn surface_colour_averages_centre_pixels_and_falls_back_to_footprints() {
        let with_centre = |c: [u8; 3]| ViewSample { centre: Some(c), ..s(3, [0.0; 3], 0.9) };
        // Centre pixels win over footprint means (which blur edges).
        let c = surface_colour(&[with_centre([200, 10, 10]), with_centre([180, 30, 10]), s(9, [0.0; 3], 1.0)]);
        assert_eq!(c, [190, 20, 10]);
        // Without centre pixels, the count-weighted footprint means.
        assert_eq!(surface_colour(&[s(3, [100.0; 3], 0.9), s(1, [20.0; 3], 0.5)]), [80, 80, 80]);
        assert_eq!(surface_colour(&[]), UNSEEN_COLOUR);
    }
}

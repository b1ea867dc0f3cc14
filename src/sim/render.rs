//! The renderer: ray casting of the [`Scene`] through a calibrated pinhole camera with radial
//! distortion, with Lambertian point lights and cast shadows, ambient light, the projector's pattern,
//! line lasers, optional seeded Gaussian noise, and a metric depth render.
//!
//! Conventions: cameras, lights, lasers and the projector are posed in the **rig frame**; the scene is
//! in the **object frame**, turned by the turntable angle `θ` (a point `p_obj` is at `Rz(θ)·p_obj` in
//! the rig frame). Rather than moving the scene, each frame rotates the rays, lights, lasers and the
//! projector into the object frame by `Rz(-θ)`. Pixel `(u, v)` is sampled by one ray through its
//! centre `(u + 0.5, v + 0.5)`. Intensities are linear, 0..1 of full scale, then scaled to 8 bits.
//!
//! Light model, per channel with reflectance `a`:
//! `a · (ambient + Σ_lights level·intensity·cosθ·(0.5 m / d)²)
//!  + a · projector.intensity · pattern/255 · cosθ · (0.5 m / d)²  + Σ_lasers colour/255`,
//! each light/projector term only if the point faces it and the segment to it is free (cast shadows,
//! including self-shadows). A laser lights a point that faces the laser's origin, sees it unoccluded,
//! and lies within a half-width of the laser plane; the half-width is half the change of plane
//! distance from one pixel to the next on the surface (so the line is about one pixel wide as seen by
//! the camera), clamped to [`LASER_MIN_HALF_WIDTH_M`]..[`LASER_MAX_HALF_WIDTH_M`].

use image::RgbImage;
use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;

use super::rng::gaussian3;
use super::scene::Scene;
use super::world::WorldState;
use crate::devices::Pattern;
use crate::geometry::{turntable_rotation, CameraModel};

/// Smallest half-width of a laser line on the surface, metres (the line is at least 0.5 mm wide).
pub const LASER_MIN_HALF_WIDTH_M: f64 = 0.25e-3;
/// Largest half-width of a laser line, metres (caps the widening at grazing views).
pub const LASER_MAX_HALF_WIDTH_M: f64 = 2.0e-3;
/// Distance at which a light of intensity 1 makes a white surface facing it fully bright, metres.
pub const REFERENCE_DISTANCE_M: f64 = 0.5;
/// Offset of shadow-ray origins along the surface normal, metres.
const SHADOW_EPS_M: f64 = 1e-7;

/// A white point light, rig frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PointLight {
    /// Position, rig frame, metres.
    pub position_m: Vector3<f64>,
    /// Relative intensity (1 = full brightness on a white surface facing it at 0.5 m).
    pub intensity: f64,
}

/// A line laser: a plane of light fanned out from `origin_m`, rig frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LineLaser {
    /// Exit point, rig frame, metres.
    pub origin_m: Vector3<f64>,
    /// Unit normal of the light plane, rig frame.
    pub normal: Vector3<f64>,
    /// Colour added where the line falls, 8-bit RGB.
    pub colour: [u8; 3],
}

/// A projector modelled as an inverse pinhole camera, posed in the rig frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProjectorModel {
    /// Its camera model (size = projector resolution), rig frame.
    pub model: CameraModel,
    /// Brightness of a full-white pixel on a white surface, relative to a light of intensity 1.
    pub intensity: f64,
}

/// The fixed light sources and surroundings of the rig.
#[derive(Debug, Clone, PartialEq)]
pub struct Lighting {
    /// White point lights, by index.
    pub lights: Vec<PointLight>,
    /// Line lasers, by index.
    pub lasers: Vec<LineLaser>,
    /// The projector, if any.
    pub projector: Option<ProjectorModel>,
    /// Ambient level, 0..1 of full brightness (reaches every point, no shadows).
    pub ambient: f64,
    /// Colour where no object is, 8-bit RGB.
    pub background: [u8; 3],
}

/// Per-pixel ray directions of one camera, computed once (undistortion is iterative), stored as
/// unit vectors in the rig frame in `f32` (direction error ~1e-7 rad, far below a pixel).
#[derive(Debug, Clone)]
pub struct RayTable {
    model: CameraModel,
    dirs: Vec<[f32; 3]>,
}

impl RayTable {
    /// Rays through every pixel centre of `model` (rig frame).
    pub fn new(model: CameraModel) -> RayTable {
        let (w, h) = (model.width as usize, model.height as usize);
        let mut dirs = vec![[0.0f32; 3]; w * h];
        dirs.par_chunks_mut(w.max(1)).enumerate().for_each(|(v, row)| {
            for (u, d) in row.iter_mut().enumerate() {
                let r = model.pixel_ray(u as f64 + 0.5, v as f64 + 0.5);
                *d = [r.x as f32, r.y as f32, r.z as f32];
            }
        });
        RayTable { model, dirs }
    }

    /// The camera model, rig frame.
    pub fn model(&self) -> &CameraModel {
        &self.model
    }

    /// Unit direction through the centre of pixel `(u, v)`, rig frame (zero vector outside the image).
    #[inline]
    pub fn dir(&self, u: u32, v: u32) -> Vector3<f64> {
        if u >= self.model.width || v >= self.model.height {
            return Vector3::zeros();
        }
        let d = self.dirs[v as usize * self.model.width as usize + u as usize];
        Vector3::new(d[0] as f64, d[1] as f64, d[2] as f64)
    }
}

/// Noise settings of one rendered frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameNoise {
    /// Standard deviation, 8-bit levels (0 = none).
    pub sigma: f64,
    /// Generator seed.
    pub seed: u64,
    /// Frame sequence number (each frame gets its own noise).
    pub sequence: u64,
}

impl FrameNoise {
    /// No noise.
    pub const NONE: FrameNoise = FrameNoise { sigma: 0.0, seed: 0, sequence: 0 };
}

/// Everything of one frame expressed in the object frame.
struct FrameSetup<'a> {
    to_obj: Matrix3<f64>,
    origin: Vector3<f64>,
    lights: Vec<(Vector3<f64>, f64)>,
    lasers: Vec<(Vector3<f64>, Vector3<f64>, [f32; 3])>,
    projector: Option<(CameraModel, Vector3<f64>, f64, &'a Pattern)>,
}

/// Renders the scene under the rig's lighting.
#[derive(Debug, Clone)]
pub struct Renderer {
    scene: Scene,
    lighting: Lighting,
}

impl Renderer {
    /// A renderer for `scene` under `lighting`.
    pub fn new(scene: Scene, lighting: Lighting) -> Renderer {
        Renderer { scene, lighting }
    }

    /// The scene (object frame).
    pub fn scene(&self) -> &Scene {
        &self.scene
    }

    /// The rig's light sources.
    pub fn lighting(&self) -> &Lighting {
        &self.lighting
    }

    fn setup<'a>(&self, camera: &CameraModel, state: &'a WorldState) -> FrameSetup<'a> {
        let to_obj = turntable_rotation(-state.turntable_deg);
        let lights = self
            .lighting
            .lights
            .iter()
            .zip(&state.light_levels)
            .filter(|(l, &level)| level > 0.0 && l.intensity > 0.0)
            .map(|(l, &level)| (to_obj * l.position_m, l.intensity * level as f64))
            .collect();
        let lasers = self
            .lighting
            .lasers
            .iter()
            .zip(&state.lasers_on)
            .filter(|(_, &on)| on)
            .map(|(l, _)| (to_obj * l.origin_m, to_obj * l.normal, l.colour.map(|c| c as f32 / 255.0)))
            .collect();
        let projector = match (&self.lighting.projector, &state.pattern) {
            // A pattern of the wrong size (possible in a hand-made state) is not shown rather than
            // indexed out of bounds.
            (Some(p), Some(pattern))
                if pattern.width == p.model.width
                    && pattern.height == p.model.height
                    && pattern.rgb.len() == 3 * pattern.width as usize * pattern.height as usize =>
            {
                let m = p.model.for_turntable_angle(state.turntable_deg);
                Some((m, m.centre(), p.intensity, pattern))
            }
            _ => None,
        };
        FrameSetup { to_obj, origin: to_obj * camera.centre(), lights, lasers, projector }
    }

    /// The linear colour (0..1 per channel, no noise) of pixel `(u, v)` of the camera `rays` in the
    /// world state `state`.
    pub fn pixel(&self, rays: &RayTable, state: &WorldState, u: u32, v: u32) -> [f32; 3] {
        let f = self.setup(rays.model(), state);
        self.shade(&f, rays, u, v)
    }

    /// Render an 8-bit RGB image of the camera `rays` in the world state `state` (parallel over rows).
    pub fn render_rgb(&self, rays: &RayTable, state: &WorldState, noise: FrameNoise) -> RgbImage {
        let (w, h) = (rays.model().width, rays.model().height);
        let f = self.setup(rays.model(), state);
        let row_len = 3 * w as usize;
        let mut buf = vec![0u8; row_len * h as usize];
        let sigma = noise.sigma as f32;
        buf.par_chunks_mut(row_len.max(1)).enumerate().for_each(|(v, row)| {
            for u in 0..w {
                let c = self.shade(&f, rays, u, v as u32);
                let g = if sigma > 0.0 {
                    gaussian3(noise.seed, noise.sequence, v as u64 * w as u64 + u as u64)
                } else {
                    [0.0; 3]
                };
                for ch in 0..3 {
                    let x = c[ch] * 255.0 + sigma * g[ch];
                    row[3 * u as usize + ch] = x.round().clamp(0.0, 255.0) as u8;
                }
            }
        });
        RgbImage::from_raw(w, h, buf).unwrap_or_else(|| RgbImage::new(w, h))
    }

    /// Depth along the optical axis (camera-frame `z`, metres) of every pixel of the camera `rays`
    /// with the turntable at `turntable_deg`; 0 where the ray meets no object. Row-major.
    pub fn render_depth(&self, rays: &RayTable, turntable_deg: f64) -> Vec<f32> {
        let m = rays.model();
        let (w, h) = (m.width as usize, m.height as usize);
        let to_obj = turntable_rotation(-turntable_deg);
        let origin = to_obj * m.centre();
        let axis = m.pose.rotation.row(2).transpose();
        let mut out = vec![0.0f32; w * h];
        out.par_chunks_mut(w.max(1)).enumerate().for_each(|(v, row)| {
            for (u, z) in row.iter_mut().enumerate() {
                let d = rays.dir(u as u32, v as u32);
                if let Some(hit) = self.scene.intersect(&origin, &(to_obj * d), 0.0, f64::INFINITY) {
                    *z = (hit.t * d.dot(&axis)) as f32;
                }
            }
        });
        out
    }

    fn shade(&self, f: &FrameSetup<'_>, rays: &RayTable, u: u32, v: u32) -> [f32; 3] {
        let bg = self.lighting.background.map(|c| c as f32 / 255.0);
        let d = f.to_obj * rays.dir(u, v);
        let Some(hit) = self.scene.intersect(&f.origin, &d, 0.0, f64::INFINITY) else { return bg };
        let (p, n) = (hit.point, hit.normal);
        let a = self.scene.albedo(hit.solid, &p);
        let lifted = p + n * SHADOW_EPS_M;
        let r2 = REFERENCE_DISTANCE_M * REFERENCE_DISTANCE_M;
        // The factor of a source at `at` (cos / d², with shadow test); 0 when facing away or occluded.
        let lit = |at: &Vector3<f64>| -> f64 {
            let l = at - p;
            let d2 = l.norm_squared();
            let dist = d2.sqrt();
            if dist == 0.0 {
                return 0.0;
            }
            let ld = l / dist;
            let cos = n.dot(&ld);
            if cos <= 0.0 || self.scene.occluded(&lifted, &ld, 0.0, dist) {
                return 0.0;
            }
            cos * r2 / d2
        };
        let mut white = self.lighting.ambient;
        for (pos, power) in &f.lights {
            white += power * lit(pos);
        }
        let mut rgb = [a[0] * white as f32, a[1] * white as f32, a[2] * white as f32];
        if let Some((model, centre, intensity, pattern)) = &f.projector {
            if let Some((pu, pv)) = model.pixel_of(&p) {
                let k = (intensity * lit(centre)) as f32;
                if k > 0.0 {
                    let c = pattern.at(pu, pv);
                    for ch in 0..3 {
                        rgb[ch] += a[ch] * c[ch] as f32 / 255.0 * k;
                    }
                }
            }
        }
        for (origin, normal, colour) in &f.lasers {
            let s = normal.dot(&(p - origin)).abs();
            if s > LASER_MAX_HALF_WIDTH_M {
                continue;
            }
            let half =
                (0.5 * plane_step(f, rays, u, v, &p, &n, normal)).clamp(LASER_MIN_HALF_WIDTH_M, LASER_MAX_HALF_WIDTH_M);
            if s <= half && lit(origin) > 0.0 {
                for ch in 0..3 {
                    rgb[ch] += colour[ch];
                }
            }
        }
        rgb.map(|c| c.clamp(0.0, 1.0))
    }
}

/// How much the distance to a plane of normal `plane` changes from pixel `(u, v)` to its neighbour
/// (larger of the horizontal and vertical steps), measured on the surface's tangent plane at `p`.
fn plane_step(
    f: &FrameSetup<'_>,
    rays: &RayTable,
    u: u32,
    v: u32,
    p: &Vector3<f64>,
    n: &Vector3<f64>,
    plane: &Vector3<f64>,
) -> f64 {
    let (w, h) = (rays.model().width, rays.model().height);
    let mut step: f64 = 0.0;
    let neighbours = [
        (if u + 1 < w { u + 1 } else { u.saturating_sub(1) }, v),
        (u, if v + 1 < h { v + 1 } else { v.saturating_sub(1) }),
    ];
    for (uu, vv) in neighbours {
        if (uu, vv) == (u, v) {
            continue;
        }
        let d = f.to_obj * rays.dir(uu, vv);
        let denom = n.dot(&d);
        if denom.abs() < 1e-9 {
            return f64::INFINITY;
        }
        let t = n.dot(&(p - f.origin)) / denom;
        let q = f.origin + d * t;
        step = step.max(plane.dot(&(q - p)).abs());
    }
    step
}

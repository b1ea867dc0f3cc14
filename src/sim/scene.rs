//! The scene on the turntable: solids built by constructive solid geometry from analytic primitives,
//! with exact ray-interval intersection, outward normals, surface colour, and ground truth (inside test,
//! bounds, surface samples, volume).
//!
//! Everything here is in the **object frame** (metres, `+z` up the turntable axis, the table top at
//! `z = 0`). A [`Solid`] is one primitive minus a few holes; a [`Scene`] is the union of its solids.
//! Geometry is kept in `f64`: the scene is the ground truth that reconstructions are measured against,
//! and the intersection code is cheap next to shading.

use nalgebra::Vector3;

use super::rng::SplitMix64;
use super::SimError;
use crate::geometry::Aabb;

/// Holes per solid. Each hole can split a span in two, so a ray meets at most `MAX_HOLES + 1` spans.
pub const MAX_HOLES: usize = 6;

/// An analytic solid primitive in the object frame, metres.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Primitive {
    /// Axis-aligned box between two corners.
    Box {
        /// Minimum corner, metres.
        min: Vector3<f64>,
        /// Maximum corner, metres.
        max: Vector3<f64>,
    },
    /// A ball.
    Sphere {
        /// Centre, metres.
        centre: Vector3<f64>,
        /// Radius, metres.
        radius: f64,
    },
    /// A solid cylinder with its axis parallel to `z`, closed by two flat caps.
    ZCylinder {
        /// Axis position `(x, y)`, metres.
        centre_xy: [f64; 2],
        /// Radius, metres.
        radius: f64,
        /// Bottom cap height, metres.
        z_min: f64,
        /// Top cap height, metres.
        z_max: f64,
    },
}

/// The part of a ray inside a solid: from parameter `t0` (entering, outward normal `n0`) to `t1`
/// (leaving, outward normal `n1`). Normals are unit vectors pointing out of the solid the span
/// belongs to.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Span {
    /// Ray parameter where the ray enters, metres along a unit direction.
    pub t0: f64,
    /// Outward normal at the entry point.
    pub n0: Vector3<f64>,
    /// Ray parameter where the ray leaves.
    pub t1: f64,
    /// Outward normal at the exit point.
    pub n1: Vector3<f64>,
}

/// The spans of one ray through one solid, sorted by `t0`, at most `MAX_HOLES + 1` (no allocation).
#[derive(Debug, Clone, Copy)]
pub struct Spans {
    items: [Span; MAX_HOLES + 1],
    len: usize,
}

impl Spans {
    fn empty() -> Self {
        let z = Span { t0: 0.0, n0: Vector3::zeros(), t1: 0.0, n1: Vector3::zeros() };
        Spans { items: [z; MAX_HOLES + 1], len: 0 }
    }

    fn push(&mut self, s: Span) {
        if self.len < self.items.len() && s.t0 < s.t1 {
            self.items[self.len] = s;
            self.len += 1;
        }
    }

    /// The spans as a slice, sorted by entry parameter.
    pub fn as_slice(&self) -> &[Span] {
        &self.items[..self.len]
    }
}

impl Primitive {
    /// The parameter interval where the ray `origin + t·dir` is inside the primitive (any `t`, also
    /// negative), with outward normals; `None` when the line misses it.
    pub fn span(&self, origin: &Vector3<f64>, dir: &Vector3<f64>) -> Option<Span> {
        match *self {
            Primitive::Box { min, max } => box_span(&min, &max, origin, dir),
            Primitive::Sphere { centre, radius } => {
                let oc = origin - centre;
                let a = dir.norm_squared();
                let b = oc.dot(dir);
                let c = oc.norm_squared() - radius * radius;
                let disc = b * b - a * c;
                if disc <= 0.0 || a == 0.0 {
                    return None;
                }
                let s = disc.sqrt();
                let (t0, t1) = ((-b - s) / a, (-b + s) / a);
                let n0 = (origin + dir * t0 - centre) / radius;
                let n1 = (origin + dir * t1 - centre) / radius;
                Some(Span { t0, n0, t1, n1 })
            }
            Primitive::ZCylinder { centre_xy, radius, z_min, z_max } => {
                let (ox, oy) = (origin.x - centre_xy[0], origin.y - centre_xy[1]);
                let a = dir.x * dir.x + dir.y * dir.y;
                let (mut t0, mut n0, mut t1, mut n1);
                if a < 1e-24 {
                    if ox * ox + oy * oy > radius * radius {
                        return None;
                    }
                    (t0, t1) = (f64::NEG_INFINITY, f64::INFINITY);
                    (n0, n1) = (Vector3::zeros(), Vector3::zeros());
                } else {
                    let b = ox * dir.x + oy * dir.y;
                    let c = ox * ox + oy * oy - radius * radius;
                    let disc = b * b - a * c;
                    if disc <= 0.0 {
                        return None;
                    }
                    let s = disc.sqrt();
                    t0 = (-b - s) / a;
                    t1 = (-b + s) / a;
                    n0 = Vector3::new(ox + t0 * dir.x, oy + t0 * dir.y, 0.0) / radius;
                    n1 = Vector3::new(ox + t1 * dir.x, oy + t1 * dir.y, 0.0) / radius;
                }
                if dir.z.abs() < 1e-300 {
                    if origin.z < z_min || origin.z > z_max {
                        return None;
                    }
                } else {
                    let ta = (z_min - origin.z) / dir.z;
                    let tb = (z_max - origin.z) / dir.z;
                    let (tn, tf, nn, nf) = if dir.z > 0.0 {
                        (ta, tb, -Vector3::z(), Vector3::z())
                    } else {
                        (tb, ta, Vector3::z(), -Vector3::z())
                    };
                    if tn > t0 {
                        t0 = tn;
                        n0 = nn;
                    }
                    if tf < t1 {
                        t1 = tf;
                        n1 = nf;
                    }
                }
                (t0 < t1).then_some(Span { t0, n0, t1, n1 })
            }
        }
    }

    /// True when `p` (object frame, metres) is inside or on the primitive.
    pub fn contains(&self, p: &Vector3<f64>) -> bool {
        match *self {
            Primitive::Box { min, max } => (0..3).all(|a| p[a] >= min[a] && p[a] <= max[a]),
            Primitive::Sphere { centre, radius } => (p - centre).norm_squared() <= radius * radius,
            Primitive::ZCylinder { centre_xy, radius, z_min, z_max } => {
                let (dx, dy) = (p.x - centre_xy[0], p.y - centre_xy[1]);
                dx * dx + dy * dy <= radius * radius && p.z >= z_min && p.z <= z_max
            }
        }
    }

    /// The bounding box, metres.
    pub fn bounds(&self) -> Aabb {
        match *self {
            Primitive::Box { min, max } => Aabb { min: min.into(), max: max.into() },
            Primitive::Sphere { centre, radius } => Aabb {
                min: [centre.x - radius, centre.y - radius, centre.z - radius],
                max: [centre.x + radius, centre.y + radius, centre.z + radius],
            },
            Primitive::ZCylinder { centre_xy: [x, y], radius, z_min, z_max } => {
                Aabb { min: [x - radius, y - radius, z_min], max: [x + radius, y + radius, z_max] }
            }
        }
    }

    /// Exact volume, m³.
    pub fn volume(&self) -> f64 {
        match *self {
            Primitive::Box { min, max } => (max - min).iter().map(|e| e.max(0.0)).product(),
            Primitive::Sphere { radius, .. } => 4.0 / 3.0 * std::f64::consts::PI * radius.powi(3),
            Primitive::ZCylinder { radius, z_min, z_max, .. } => {
                std::f64::consts::PI * radius * radius * (z_max - z_min).max(0.0)
            }
        }
    }

    /// Exact surface area, m².
    pub fn area(&self) -> f64 {
        match *self {
            Primitive::Box { min, max } => {
                let e = max - min;
                2.0 * (e.x * e.y + e.y * e.z + e.z * e.x)
            }
            Primitive::Sphere { radius, .. } => 4.0 * std::f64::consts::PI * radius * radius,
            Primitive::ZCylinder { radius, z_min, z_max, .. } => {
                2.0 * std::f64::consts::PI * radius * (radius + (z_max - z_min))
            }
        }
    }

    /// A point uniformly distributed over the surface by area, with its outward normal.
    fn sample_surface(&self, rng: &mut SplitMix64) -> (Vector3<f64>, Vector3<f64>) {
        match *self {
            Primitive::Box { min, max } => {
                let e = max - min;
                let faces = [e.y * e.z, e.y * e.z, e.x * e.z, e.x * e.z, e.x * e.y, e.x * e.y];
                let f = pick_weighted(&faces, rng.next_f64());
                let axis = f / 2;
                let mut p = Vector3::new(
                    min.x + rng.next_f64() * e.x,
                    min.y + rng.next_f64() * e.y,
                    min.z + rng.next_f64() * e.z,
                );
                let mut n = Vector3::zeros();
                if f % 2 == 0 {
                    p[axis] = min[axis];
                    n[axis] = -1.0;
                } else {
                    p[axis] = max[axis];
                    n[axis] = 1.0;
                }
                (p, n)
            }
            Primitive::Sphere { centre, radius } => {
                let z = 2.0 * rng.next_f64() - 1.0;
                let phi = 2.0 * std::f64::consts::PI * rng.next_f64();
                let r = (1.0 - z * z).max(0.0).sqrt();
                let n = Vector3::new(r * phi.cos(), r * phi.sin(), z);
                (centre + n * radius, n)
            }
            Primitive::ZCylinder { centre_xy: [cx, cy], radius, z_min, z_max } => {
                let side = 2.0 * std::f64::consts::PI * radius * (z_max - z_min);
                let cap = std::f64::consts::PI * radius * radius;
                let f = pick_weighted(&[side, cap, cap], rng.next_f64());
                let phi = 2.0 * std::f64::consts::PI * rng.next_f64();
                if f == 0 {
                    let n = Vector3::new(phi.cos(), phi.sin(), 0.0);
                    let z = z_min + rng.next_f64() * (z_max - z_min);
                    (Vector3::new(cx + radius * n.x, cy + radius * n.y, z), n)
                } else {
                    let r = radius * rng.next_f64().sqrt();
                    let (z, nz) = if f == 1 { (z_min, -1.0) } else { (z_max, 1.0) };
                    (Vector3::new(cx + r * phi.cos(), cy + r * phi.sin(), z), Vector3::new(0.0, 0.0, nz))
                }
            }
        }
    }

    fn scaled(&self, s: f64) -> Primitive {
        match *self {
            Primitive::Box { min, max } => Primitive::Box { min: min * s, max: max * s },
            Primitive::Sphere { centre, radius } => Primitive::Sphere { centre: centre * s, radius: radius * s },
            Primitive::ZCylinder { centre_xy: [x, y], radius, z_min, z_max } => Primitive::ZCylinder {
                centre_xy: [x * s, y * s],
                radius: radius * s,
                z_min: z_min * s,
                z_max: z_max * s,
            },
        }
    }
}

fn pick_weighted(weights: &[f64], u: f64) -> usize {
    let total: f64 = weights.iter().sum();
    let mut acc = 0.0;
    for (i, w) in weights.iter().enumerate() {
        acc += w;
        if u * total < acc {
            return i;
        }
    }
    weights.len() - 1
}

fn box_span(min: &Vector3<f64>, max: &Vector3<f64>, o: &Vector3<f64>, d: &Vector3<f64>) -> Option<Span> {
    let (mut t0, mut t1) = (f64::NEG_INFINITY, f64::INFINITY);
    let (mut n0, mut n1) = (Vector3::zeros(), Vector3::zeros());
    for a in 0..3 {
        if d[a].abs() < 1e-300 {
            if o[a] < min[a] || o[a] > max[a] {
                return None;
            }
            continue;
        }
        let ta = (min[a] - o[a]) / d[a];
        let tb = (max[a] - o[a]) / d[a];
        let (tn, tf, sn) = if d[a] > 0.0 { (ta, tb, -1.0) } else { (tb, ta, 1.0) };
        if tn > t0 {
            t0 = tn;
            n0 = Vector3::zeros();
            n0[a] = sn;
        }
        if tf < t1 {
            t1 = tf;
            n1 = Vector3::zeros();
            n1[a] = -sn;
        }
    }
    (t0 < t1).then_some(Span { t0, n0, t1, n1 })
}

/// Surface colour of a solid as a function of the object-frame point: linear reflectance 0..1 per
/// channel (RGB).
#[derive(Debug, Clone, PartialEq)]
pub enum Material {
    /// One colour everywhere.
    Uniform([f32; 3]),
    /// A 3-D checkerboard of cubic cells of edge `cell_m` metres; the cell `(i, j, k)` takes
    /// `palette[(i + j + k) mod len]`, so each flat face shows a pattern of distinct colours.
    Checker {
        /// Colours, at least one.
        palette: Vec<[f32; 3]>,
        /// Cell edge, metres.
        cell_m: f64,
    },
    /// Horizontal bands of height `band_m` metres: band `floor(z / band_m)` takes
    /// `palette[band mod len]`.
    Bands {
        /// Colours, at least one.
        palette: Vec<[f32; 3]>,
        /// Band height, metres.
        band_m: f64,
    },
}

impl Material {
    /// Reflectance at object-frame point `p`, 0..1 per channel.
    pub fn albedo(&self, p: &Vector3<f64>) -> [f32; 3] {
        let pick = |palette: &[[f32; 3]], idx: i64| -> [f32; 3] {
            if palette.is_empty() {
                return [1.0; 3];
            }
            palette[idx.rem_euclid(palette.len() as i64) as usize]
        };
        match self {
            Material::Uniform(c) => *c,
            Material::Checker { palette, cell_m } => {
                let c = |x: f64| (x / cell_m).floor() as i64;
                pick(palette, c(p.x) + c(p.y) + c(p.z))
            }
            Material::Bands { palette, band_m } => pick(palette, (p.z / band_m).floor() as i64),
        }
    }

    /// The darkest channel maximum over the palette: the faintest a point of this material can look
    /// against a black background at a given light level.
    pub fn dimmest_max_channel(&self) -> f32 {
        let max3 = |c: &[f32; 3]| c[0].max(c[1]).max(c[2]);
        match self {
            Material::Uniform(c) => max3(c),
            Material::Checker { palette, .. } | Material::Bands { palette, .. } => {
                palette.iter().map(max3).fold(f32::INFINITY, f32::min)
            }
        }
    }

    fn scaled(&self, s: f64) -> Material {
        match self {
            Material::Uniform(c) => Material::Uniform(*c),
            Material::Checker { palette, cell_m } => Material::Checker { palette: palette.clone(), cell_m: cell_m * s },
            Material::Bands { palette, band_m } => Material::Bands { palette: palette.clone(), band_m: band_m * s },
        }
    }
}

/// One solid: a primitive minus up to [`MAX_HOLES`] primitive holes, with a material.
#[derive(Debug, Clone, PartialEq)]
pub struct Solid {
    base: Primitive,
    holes: Vec<Primitive>,
    material: Material,
}

impl Solid {
    /// `base` minus every hole. Errors when there are more than [`MAX_HOLES`] holes.
    pub fn new(base: Primitive, holes: Vec<Primitive>, material: Material) -> Result<Solid, SimError> {
        if holes.len() > MAX_HOLES {
            return Err(SimError::TooManyHoles { holes: holes.len(), max: MAX_HOLES });
        }
        Ok(Solid { base, holes, material })
    }

    /// The primitive the holes are cut from.
    pub fn base(&self) -> &Primitive {
        &self.base
    }

    /// The holes.
    pub fn holes(&self) -> &[Primitive] {
        &self.holes
    }

    /// The material.
    pub fn material(&self) -> &Material {
        &self.material
    }

    /// Every interval of the line `origin + t·dir` inside the solid, sorted, with outward normals.
    pub fn spans(&self, origin: &Vector3<f64>, dir: &Vector3<f64>) -> Spans {
        let mut out = Spans::empty();
        let Some(base) = self.base.span(origin, dir) else { return out };
        out.push(base);
        for hole in &self.holes {
            let Some(h) = hole.span(origin, dir) else { continue };
            let mut next = Spans::empty();
            for s in out.as_slice() {
                if h.t1 <= s.t0 || h.t0 >= s.t1 {
                    next.push(*s);
                    continue;
                }
                // Before the hole: the solid's surface where the ray enters the hole faces into it.
                if s.t0 < h.t0 {
                    next.push(Span { t0: s.t0, n0: s.n0, t1: h.t0, n1: -h.n0 });
                }
                // After the hole.
                if h.t1 < s.t1 {
                    next.push(Span { t0: h.t1, n0: -h.n1, t1: s.t1, n1: s.n1 });
                }
            }
            out = next;
        }
        out
    }

    /// True when `p` is inside the solid (in the base and in no hole).
    pub fn contains(&self, p: &Vector3<f64>) -> bool {
        self.base.contains(p) && !self.holes.iter().any(|h| h.contains(p))
    }

    /// Volume, m³: exact when every hole is a box inside a box, or a coaxial cylinder or a box in a
    /// z-cylinder whose disc contains it; otherwise by integrating exact span lengths along a dense
    /// grid of vertical rays (relative error about 1e-5).
    pub fn volume(&self) -> f64 {
        let mut v = self.base.volume();
        for (i, hole) in self.holes.iter().enumerate() {
            // Holes that overlap each other need the numeric path.
            let overlaps_other = self.holes.iter().enumerate().any(|(j, other)| j != i && aabb_overlap(hole, other));
            match (!overlaps_other).then(|| clipped_volume(&self.base, hole)).flatten() {
                Some(cut) => v -= cut,
                None => return numeric_volume(std::slice::from_ref(self), 1024),
            }
        }
        v
    }

    fn scaled(&self, s: f64) -> Solid {
        Solid {
            base: self.base.scaled(s),
            holes: self.holes.iter().map(|h| h.scaled(s)).collect(),
            material: self.material.scaled(s),
        }
    }
}

fn aabb_overlap(a: &Primitive, b: &Primitive) -> bool {
    let (a, b) = (a.bounds(), b.bounds());
    (0..3).all(|k| a.min[k] < b.max[k] && b.min[k] < a.max[k])
}

/// Volume of `hole ∩ base` when it is simple to get exactly.
fn clipped_volume(base: &Primitive, hole: &Primitive) -> Option<f64> {
    let z_overlap = |lo: f64, hi: f64, blo: f64, bhi: f64| (hi.min(bhi) - lo.max(blo)).max(0.0);
    match (*base, *hole) {
        (Primitive::Box { min, max }, Primitive::Box { min: hmin, max: hmax }) => {
            Some((0..3).map(|a| z_overlap(hmin[a], hmax[a], min[a], max[a])).product())
        }
        (
            Primitive::ZCylinder { centre_xy: c, radius: r, z_min, z_max },
            Primitive::ZCylinder { centre_xy: hc, radius: hr, z_min: hz0, z_max: hz1 },
        ) => {
            let d = ((c[0] - hc[0]).powi(2) + (c[1] - hc[1]).powi(2)).sqrt();
            (d + hr <= r).then(|| std::f64::consts::PI * hr * hr * z_overlap(hz0, hz1, z_min, z_max))
        }
        (Primitive::ZCylinder { centre_xy: c, radius: r, z_min, z_max }, Primitive::Box { min, max }) => {
            let far = [min.x, max.x]
                .iter()
                .flat_map(|x| [min.y, max.y].map(|y| ((x - c[0]).powi(2) + (y - c[1]).powi(2)).sqrt()))
                .fold(0.0, f64::max);
            (far <= r).then(|| (max.x - min.x) * (max.y - min.y) * z_overlap(min.z, max.z, z_min, z_max))
        }
        (_, _) if !aabb_overlap(base, hole) => Some(0.0),
        _ => None,
    }
}

/// Volume of the union of `solids` by integrating exact span lengths along an `n x n` grid of
/// vertical rays (midpoint rule) over their bounds.
fn numeric_volume(solids: &[Solid], n: usize) -> f64 {
    let Some(b) = union_bounds(solids) else { return 0.0 };
    let (dx, dy) = ((b.max[0] - b.min[0]) / n as f64, (b.max[1] - b.min[1]) / n as f64);
    let dir = Vector3::z();
    let mut total = 0.0;
    let mut ivals: Vec<(f64, f64)> = Vec::new();
    for i in 0..n {
        for j in 0..n {
            let o = Vector3::new(b.min[0] + (i as f64 + 0.5) * dx, b.min[1] + (j as f64 + 0.5) * dy, b.min[2] - 1.0);
            ivals.clear();
            for s in solids {
                ivals.extend(s.spans(&o, &dir).as_slice().iter().map(|s| (s.t0, s.t1)));
            }
            total += union_length(&mut ivals);
        }
    }
    total * dx * dy
}

fn union_length(ivals: &mut [(f64, f64)]) -> f64 {
    ivals.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut len = 0.0;
    let mut cur: Option<(f64, f64)> = None;
    for &(a, b) in ivals.iter() {
        cur = match cur {
            Some((s, e)) if a <= e => Some((s, e.max(b))),
            Some((s, e)) => {
                len += e - s;
                Some((a, b))
            }
            None => Some((a, b)),
        };
    }
    if let Some((s, e)) = cur {
        len += e - s;
    }
    len
}

fn union_bounds(solids: &[Solid]) -> Option<Aabb> {
    let mut it = solids.iter().map(|s| s.base.bounds());
    let first = it.next()?;
    Some(it.fold(first, |a, b| Aabb {
        min: [0, 1, 2].map(|k| a.min[k].min(b.min[k])),
        max: [0, 1, 2].map(|k| a.max[k].max(b.max[k])),
    }))
}

/// A ray hit on the scene.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hit {
    /// Ray parameter, metres along the unit direction.
    pub t: f64,
    /// The surface point, object frame, metres.
    pub point: Vector3<f64>,
    /// Outward unit normal there, object frame.
    pub normal: Vector3<f64>,
    /// Index of the solid that was hit.
    pub solid: usize,
}

/// The objects on the turntable: a union of solids, in the object frame.
#[derive(Debug, Clone, PartialEq)]
pub struct Scene {
    name: String,
    solids: Vec<Solid>,
    bounds: Aabb,
}

impl Scene {
    /// A scene from solids (at least one).
    pub fn new(name: impl Into<String>, solids: Vec<Solid>) -> Result<Scene, SimError> {
        let bounds = union_bounds(&solids).ok_or(SimError::EmptyScene)?;
        Ok(Scene { name: name.into(), solids, bounds })
    }

    /// A preset scene by name (one of [`super::SCENE_NAMES`]), scaled uniformly by `scale` about the
    /// origin (so it still rests on the table). At scale 1 every preset is 6-7 cm across.
    pub fn preset(name: &str, scale: f64) -> Result<Scene, SimError> {
        if !(scale.is_finite() && scale > 0.0) {
            return Err(SimError::InvalidScale { scale });
        }
        let v = Vector3::new;
        let solid = match name {
            "sphere" => Solid::new(
                Primitive::Sphere { centre: v(0.0, 0.0, 0.035), radius: 0.035 },
                vec![],
                Material::Uniform([0.85, 0.75, 0.6]),
            )?,
            "box" => Solid::new(
                Primitive::Box { min: v(-0.025, -0.02, 0.0), max: v(0.025, 0.02, 0.06) },
                vec![],
                Material::Uniform([0.6, 0.7, 0.85]),
            )?,
            "cup" => Solid::new(
                Primitive::ZCylinder { centre_xy: [0.0, 0.0], radius: 0.03, z_min: 0.0, z_max: 0.07 },
                // The pit reaches past the rim so the cup is open at the top.
                vec![Primitive::ZCylinder { centre_xy: [0.0, 0.0], radius: 0.022, z_min: 0.015, z_max: 0.08 }],
                Material::Bands { palette: vec![[0.9, 0.8, 0.55], [0.75, 0.35, 0.3]], band_m: 0.01 },
            )?,
            "pit-block" => Solid::new(
                Primitive::Box { min: v(-0.03, -0.03, 0.0), max: v(0.03, 0.03, 0.05) },
                vec![Primitive::Box { min: v(-0.015, -0.012, 0.02), max: v(0.015, 0.012, 0.06) }],
                Material::Checker { palette: vec![[0.8, 0.8, 0.75], [0.45, 0.6, 0.4]], cell_m: 0.01 },
            )?,
            "textured-box" => Solid::new(
                Primitive::Box { min: v(-0.03, -0.025, 0.0), max: v(0.03, 0.025, 0.06) },
                vec![],
                Material::Checker {
                    palette: vec![[0.9, 0.2, 0.2], [0.2, 0.8, 0.25], [0.25, 0.35, 0.9], [0.9, 0.85, 0.2]],
                    cell_m: 0.01,
                },
            )?,
            other => return Err(SimError::UnknownScene { name: other.to_owned() }),
        };
        Scene::new(name, vec![solid.scaled(scale)])
    }

    /// The scene's name.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// The solids.
    pub fn solids(&self) -> &[Solid] {
        &self.solids
    }

    /// Axis-aligned bounds of the scene, object frame, metres.
    pub fn bounds(&self) -> Aabb {
        self.bounds
    }

    /// True when the object-frame point `p` (metres) is inside some solid.
    pub fn contains(&self, p: &Vector3<f64>) -> bool {
        self.solids.iter().any(|s| s.contains(p))
    }

    /// The first surface the ray `origin + t·dir` (object frame, `dir` a unit vector) enters with
    /// `t_min <= t < t_max`. The ray must start outside every solid.
    pub fn intersect(&self, origin: &Vector3<f64>, dir: &Vector3<f64>, t_min: f64, t_max: f64) -> Option<Hit> {
        let (lo, hi) = self.bounds_range(origin, dir)?;
        if hi < t_min || lo >= t_max {
            return None;
        }
        let mut best: Option<(f64, Vector3<f64>, usize)> = None;
        for (i, solid) in self.solids.iter().enumerate() {
            let limit = best.map_or(t_max, |b| b.0);
            if let Some(s) = solid.spans(origin, dir).as_slice().iter().find(|s| s.t0 >= t_min) {
                if s.t0 < limit {
                    best = Some((s.t0, s.n0, i));
                }
            }
        }
        best.map(|(t, normal, solid)| Hit { t, point: origin + dir * t, normal, solid })
    }

    /// True when any solid lies on the ray between `t_min` and `t_max` (shadow rays).
    pub fn occluded(&self, origin: &Vector3<f64>, dir: &Vector3<f64>, t_min: f64, t_max: f64) -> bool {
        let Some((lo, hi)) = self.bounds_range(origin, dir) else { return false };
        if hi < t_min || lo > t_max {
            return false;
        }
        self.solids.iter().any(|s| s.spans(origin, dir).as_slice().iter().any(|s| s.t1 > t_min && s.t0 < t_max))
    }

    /// The ray parameter range inside the (slightly padded) scene bounds.
    fn bounds_range(&self, origin: &Vector3<f64>, dir: &Vector3<f64>) -> Option<(f64, f64)> {
        let pad = 1e-6;
        let min = Vector3::from(self.bounds.min).add_scalar(-pad);
        let max = Vector3::from(self.bounds.max).add_scalar(pad);
        box_span(&min, &max, origin, dir).map(|s| (s.t0, s.t1))
    }

    /// Reflectance (0..1 per channel) at a surface point of solid `solid`.
    pub fn albedo(&self, solid: usize, p: &Vector3<f64>) -> [f32; 3] {
        self.solids.get(solid).map_or([1.0; 3], |s| s.material.albedo(p))
    }

    /// The true 8-bit surface colour (reflectance) at object-frame point `p`: the material of the
    /// solid whose surface is nearest, as judged by which solid contains the point or is closest to
    /// containing it (for points on a shared surface, the first solid).
    pub fn colour_at(&self, p: &Vector3<f64>) -> [u8; 3] {
        let solid = self.solids.iter().position(|s| s.contains(p)).unwrap_or(0);
        self.albedo(solid, p).map(|c| (c.clamp(0.0, 1.0) * 255.0).round() as u8)
    }

    /// The faintest a surface point can look: the smallest per-point maximum channel of any
    /// material's reflectance.
    pub fn dimmest_max_channel(&self) -> f32 {
        self.solids.iter().map(|s| s.material.dimmest_max_channel()).fold(f32::INFINITY, f32::min)
    }

    /// `n` points on the scene's surface, roughly uniform by area, with outward unit normals,
    /// object frame, metres. Deterministic given `seed`.
    pub fn sample_surface(&self, n: usize, seed: u64) -> Vec<(Vector3<f64>, Vector3<f64>)> {
        // Candidate pieces: every solid's base (kept outside its holes) and every hole's wall (kept
        // inside the base); rejection keeps the distribution uniform on what remains.
        let mut pieces: Vec<(usize, Option<usize>, f64)> = Vec::new();
        for (i, s) in self.solids.iter().enumerate() {
            pieces.push((i, None, s.base.area()));
            for (h, hole) in s.holes.iter().enumerate() {
                pieces.push((i, Some(h), hole.area()));
            }
        }
        let weights: Vec<f64> = pieces.iter().map(|p| p.2).collect();
        let mut rng = SplitMix64::new(seed);
        let mut out = Vec::with_capacity(n);
        let mut attempts = 0usize;
        while out.len() < n && attempts < 1000 * (n + 10) {
            attempts += 1;
            let (si, hole, _) = pieces[pick_weighted(&weights, rng.next_f64())];
            let solid = &self.solids[si];
            let (p, normal) = match hole {
                None => solid.base.sample_surface(&mut rng),
                Some(h) => {
                    let (p, n) = solid.holes[h].sample_surface(&mut rng);
                    (p, -n)
                }
            };
            let on_boundary = match hole {
                None => !solid.holes.iter().any(|h| strictly_inside(h, &p)),
                Some(h) => {
                    strictly_inside(&solid.base, &p)
                        && !solid.holes.iter().enumerate().any(|(k, o)| k != h && strictly_inside(o, &p))
                }
            };
            let in_other = self.solids.iter().enumerate().any(|(k, o)| k != si && o.contains(&p));
            if on_boundary && !in_other {
                out.push((p, normal));
            }
        }
        out
    }

    /// Volume of the scene, m³ (exact for the presets; see [`Solid::volume`]). Overlapping solids
    /// are integrated numerically.
    pub fn volume(&self) -> f64 {
        let overlap = self
            .solids
            .iter()
            .enumerate()
            .any(|(i, a)| self.solids[i + 1..].iter().any(|b| aabb_overlap(&a.base, &b.base)));
        if overlap {
            numeric_volume(&self.solids, 1024)
        } else {
            self.solids.iter().map(Solid::volume).sum()
        }
    }
}

/// Inside by more than a hair (points on a shared boundary count as outside).
fn strictly_inside(p: &Primitive, x: &Vector3<f64>) -> bool {
    const EPS: f64 = 1e-9;
    match *p {
        Primitive::Box { min, max } => (0..3).all(|a| x[a] > min[a] + EPS && x[a] < max[a] - EPS),
        Primitive::Sphere { centre, radius } => (x - centre).norm() < radius - EPS,
        Primitive::ZCylinder { centre_xy, radius, z_min, z_max } => {
            let r = ((x.x - centre_xy[0]).powi(2) + (x.y - centre_xy[1]).powi(2)).sqrt();
            r < radius - EPS && x.z > z_min + EPS && x.z < z_max - EPS
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn all_presets() -> Vec<Scene> {
        super::super::SCENE_NAMES.iter().map(|n| Scene::preset(n, 1.0).expect("preset")).collect()
    }

    #[test]
    fn unknown_scene_and_bad_scale_are_typed_errors() {
        assert!(matches!(Scene::preset("teapot", 1.0), Err(SimError::UnknownScene { .. })));
        assert!(matches!(Scene::preset("cup", 0.0), Err(SimError::InvalidScale { .. })));
        assert!(matches!(Scene::preset("cup", f64::NAN), Err(SimError::InvalidScale { .. })));
    }

    #[test]
    fn presets_rest_on_the_table_centred_and_6_to_8_cm_across() {
        for s in all_presets() {
            let b = s.bounds();
            assert!(b.min[2].abs() < 1e-12, "{} does not rest on z = 0", s.name());
            let across = (b.max[0] - b.min[0]).max(b.max[1] - b.min[1]).max(b.max[2] - b.min[2]);
            assert!((0.055..=0.085).contains(&across), "{}: {across}", s.name());
            assert!((b.max[0] + b.min[0]).abs() < 1e-9 && (b.max[1] + b.min[1]).abs() < 1e-9);
        }
    }

    #[test]
    fn rays_into_the_cup_pit_hit_the_pit_floor_with_an_upward_normal() {
        let cup = Scene::preset("cup", 1.0).expect("cup");
        for (x, y) in [(0.0, 0.0), (0.01, -0.015), (-0.02, 0.005)] {
            let o = Vector3::new(x, y, 0.3);
            let hit = cup.intersect(&o, &-Vector3::z(), 0.0, f64::INFINITY).expect("hits the floor");
            assert!((hit.point.z - 0.015).abs() < 1e-12, "hit at {}", hit.point);
            assert!((hit.normal - Vector3::z()).norm() < 1e-12);
        }
        // Outside the pit, straight down: the rim.
        let hit = cup.intersect(&Vector3::new(0.026, 0.0, 0.3), &-Vector3::z(), 0.0, 1.0).expect("rim");
        assert!((hit.point.z - 0.07).abs() < 1e-12);
        // A slanting ray through the opening hits the pit wall, whose normal points to the axis.
        let o = Vector3::new(-0.015, 0.0, 0.1);
        let d = Vector3::new(1.0, 0.0, -1.0).normalize();
        let hit = cup.intersect(&o, &d, 0.0, 1.0).expect("wall");
        assert!((hit.point.x - 0.022).abs() < 1e-12, "{}", hit.point);
        assert!((hit.normal - Vector3::new(-1.0, 0.0, 0.0)).norm() < 1e-12);
    }

    #[test]
    fn contains_agrees_with_intersection_parity() {
        let mut rng = SplitMix64::new(7);
        for s in all_presets() {
            let b = s.bounds();
            for _ in 0..2000 {
                let p = Vector3::new(
                    b.min[0] - 0.01 + rng.next_f64() * (b.max[0] - b.min[0] + 0.02),
                    b.min[1] - 0.01 + rng.next_f64() * (b.max[1] - b.min[1] + 0.02),
                    b.min[2] - 0.01 + rng.next_f64() * (b.max[2] - b.min[2] + 0.02),
                );
                let d = Vector3::new(rng.next_f64() - 0.5, rng.next_f64() - 0.5, rng.next_f64() - 0.5).normalize();
                // Count boundary crossings ahead of p.
                let crossings: usize = s
                    .solids()
                    .iter()
                    .flat_map(|so| so.spans(&p, &d).as_slice().to_vec())
                    .map(|sp| usize::from(sp.t0 > 0.0) + usize::from(sp.t1 > 0.0))
                    .sum();
                assert_eq!(crossings % 2 == 1, s.contains(&p), "{} at {p} dir {d}", s.name());
            }
        }
    }

    #[test]
    fn hits_lie_on_the_surface_with_normals_facing_the_ray() {
        let mut rng = SplitMix64::new(11);
        for s in all_presets() {
            let mut hits = 0;
            for _ in 0..500 {
                let o = Vector3::new(rng.next_f64() - 0.5, rng.next_f64() - 0.5, rng.next_f64() * 0.4 - 0.1) * 0.5;
                let target =
                    Vector3::new(rng.next_f64() * 0.06 - 0.03, rng.next_f64() * 0.06 - 0.03, rng.next_f64() * 0.07);
                let d = (target - o).normalize();
                if s.contains(&o) {
                    continue;
                }
                if let Some(h) = s.intersect(&o, &d, 0.0, 10.0) {
                    hits += 1;
                    assert!(h.normal.dot(&d) <= 1e-12, "{}: normal faces away", s.name());
                    assert!(!s.contains(&(h.point - d * 1e-7)), "{}: inside before the hit", s.name());
                    assert!(s.contains(&(h.point + d * 1e-7)), "{}: not inside after the hit", s.name());
                }
            }
            assert!(hits > 100, "{}: only {hits} hits", s.name());
        }
    }

    #[test]
    fn volumes_match_a_numeric_integral() {
        for s in all_presets() {
            let exact = s.volume();
            let numeric = numeric_volume(s.solids(), 400);
            assert!(((exact - numeric) / exact).abs() < 2e-3, "{}: {exact} vs {numeric}", s.name());
        }
        let cup = Scene::preset("cup", 1.0).expect("cup");
        let pi = std::f64::consts::PI;
        let expected = pi * 0.03f64.powi(2) * 0.07 - pi * 0.022f64.powi(2) * 0.055;
        assert!((cup.volume() - expected).abs() < 1e-15);
        // Scale multiplies volume by scale³.
        let big = Scene::preset("cup", 2.0).expect("cup");
        assert!((big.volume() / cup.volume() - 8.0).abs() < 1e-9);
    }

    #[test]
    fn surface_samples_are_on_the_surface_with_outward_normals() {
        for s in all_presets() {
            let pts = s.sample_surface(3000, 3);
            assert_eq!(pts.len(), 3000);
            for (p, n) in &pts {
                assert!((n.norm() - 1.0).abs() < 1e-9);
                assert!(s.contains(&(p - n * 1e-6)), "{}: {p} not inside below the surface", s.name());
                assert!(!s.contains(&(p + n * 1e-6)), "{}: {p} inside above the surface", s.name());
            }
        }
        // Roughly uniform by area: the cup's pit floor gets its share.
        let cup = Scene::preset("cup", 1.0).expect("cup");
        let pts = cup.sample_surface(20_000, 5);
        let floor = pts.iter().filter(|(p, n)| (p.z - 0.015).abs() < 1e-12 && n.z > 0.5).count() as f64;
        let pi = std::f64::consts::PI;
        let total = 2.0 * pi * 0.03 * 0.07
            + pi * 0.03f64.powi(2)
            + (pi * 0.03f64.powi(2) - pi * 0.022f64.powi(2))
            + 2.0 * pi * 0.022 * 0.055
            + pi * 0.022f64.powi(2);
        let share = pi * 0.022f64.powi(2) / total;
        let got = floor / pts.len() as f64;
        assert!((got - share).abs() < 0.2 * share, "floor share {got} vs {share}");
    }

    #[test]
    fn colours_follow_the_materials() {
        let tb = Scene::preset("textured-box", 1.0).expect("textured-box");
        let a = tb.colour_at(&Vector3::new(0.005, -0.025, 0.005));
        let b = tb.colour_at(&Vector3::new(0.015, -0.025, 0.005));
        assert_ne!(a, b, "neighbouring checker cells must differ");
        let cup = Scene::preset("cup", 1.0).expect("cup");
        assert_ne!(cup.colour_at(&Vector3::new(0.03, 0.0, 0.005)), cup.colour_at(&Vector3::new(0.03, 0.0, 0.015)));
        assert!(tb.dimmest_max_channel() >= 0.5);
    }
}

//! Point-light calibration from a Lambertian sphere of known centre and radius: fit a light's position
//! (and its power) to the shading the sphere shows under that light alone.
//!
//! # Model
//! For a pixel whose ray (through the pixel centre) meets the sphere at `P` with outward normal `n`,
//! the light's direct term (light frame minus ambient frame, `R + G + B`, 8-bit levels) is
//!
//! `d = k · max(0, n·ℓ) · (r₀ / |L − P|)²`,  `ℓ = (L − P) / |L − P|`,  `r₀ = 0.5 m`,
//!
//! with `L` the light's position and `k` its power times the sphere's albedo (levels). Only pixels
//! clearly lit (`d >= min_direct`) and not saturated are used, so the `max` never clips at the solution.
//! `L` and `k` are found by Levenberg-Marquardt on the squared residuals, started from a nominal
//! position (the rig's design, a tape measure) with `k` from linear least squares. Several observations
//! (the sphere at different turntable angles, or placed off the turntable axis) pin down the distance
//! of the light, which the shading of one sphere alone constrains only weakly.
//!
//! Frames: everything (camera, sphere, result) in one reference frame, e.g. the rig frame.

use image::RgbImage;
use nalgebra::{Matrix4, Vector3, Vector4};

use crate::geometry::CameraModel;

/// Distance at which the model's inverse-square factor is 1, metres.
pub const REFERENCE_DISTANCE_M: f64 = 0.5;

/// A calibration sphere in the reference frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sphere {
    /// Centre, metres.
    pub centre_m: Vector3<f64>,
    /// Radius, metres.
    pub radius_m: f64,
}

/// One view of the sphere under the light being calibrated.
#[derive(Debug, Clone, Copy)]
pub struct SphereObservation<'a> {
    /// The camera, reference frame.
    pub camera: CameraModel,
    /// The sphere as it stood for this view, reference frame.
    pub sphere: Sphere,
    /// Frame with every light off.
    pub ambient: &'a RgbImage,
    /// Frame with only the light being calibrated on.
    pub lit: &'a RgbImage,
}

/// Parameters of [`calibrate_point_light`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LightFitParams {
    /// Starting position, reference frame, metres.
    pub initial_m: Vector3<f64>,
    /// Smallest direct term used, `R + G + B` levels.
    pub min_direct: f64,
    /// Pixels with a channel at or above this level in either frame are not used.
    pub saturation: u8,
    /// Levenberg-Marquardt iterations at most.
    pub max_iterations: u32,
}

impl LightFitParams {
    /// Defaults around a nominal starting position.
    pub fn new(initial_m: Vector3<f64>) -> LightFitParams {
        LightFitParams { initial_m, min_direct: 30.0, saturation: 250, max_iterations: 100 }
    }
}

/// A fitted light.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LightEstimate {
    /// Position, reference frame, metres.
    pub position_m: Vector3<f64>,
    /// Power times albedo, `R + G + B` levels at 0.5 m, facing the light.
    pub power: f64,
    /// Root mean square residual, levels.
    pub rms_levels: f64,
    /// Pixels used.
    pub pixels: usize,
    /// Iterations run.
    pub iterations: u32,
}

/// Why a light could not be calibrated.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LightCalibrationError {
    /// An observation's frames are not the camera's image size.
    #[error("observation {index}: frames do not match the camera's image size")]
    FrameSize {
        /// Observation index.
        index: usize,
    },
    /// A sphere with a non-positive or non-finite radius, or a non-finite centre or start.
    #[error("observation {index}: invalid sphere or starting position")]
    BadInput {
        /// Observation index (or the number of observations for the starting position).
        index: usize,
    },
    /// Too few lit sphere pixels to fit four parameters.
    #[error("only {pixels} lit sphere pixels; the light does not light the sphere the camera sees")]
    TooFewPixels {
        /// Pixels found.
        pixels: usize,
    },
    /// The fit left the valid region (light inside the sphere, no lit samples).
    #[error("the fit diverged")]
    Diverged,
}

/// One lit sphere pixel: surface point, normal, observed direct term.
#[derive(Debug, Clone, Copy)]
struct Sample {
    p: Vector3<f64>,
    n: Vector3<f64>,
    d: f64,
}

/// The geometric factor `max(0, n·ℓ)·(r₀/|L−P|)²`.
fn geometry(s: &Sample, light: &Vector3<f64>) -> f64 {
    let l = light - s.p;
    let d2 = l.norm_squared();
    if d2 <= 0.0 {
        return 0.0;
    }
    let cos = s.n.dot(&l) / d2.sqrt();
    cos.max(0.0) * REFERENCE_DISTANCE_M * REFERENCE_DISTANCE_M / d2
}

fn samples(obs: &[SphereObservation<'_>], params: &LightFitParams) -> Result<Vec<Sample>, LightCalibrationError> {
    let mut out = Vec::new();
    for (index, o) in obs.iter().enumerate() {
        let (w, h) = (o.camera.width, o.camera.height);
        if o.ambient.dimensions() != (w, h) || o.lit.dimensions() != (w, h) {
            return Err(LightCalibrationError::FrameSize { index });
        }
        let s = &o.sphere;
        if !(s.radius_m.is_finite() && s.radius_m > 0.0 && s.centre_m.iter().all(|x| x.is_finite())) {
            return Err(LightCalibrationError::BadInput { index });
        }
        let c = o.camera.centre();
        let oc = c - s.centre_m;
        for v in 0..h {
            for u in 0..w {
                let dir = o.camera.pixel_ray(u as f64 + 0.5, v as f64 + 0.5);
                let b = oc.dot(&dir);
                let disc = b * b - (oc.norm_squared() - s.radius_m * s.radius_m);
                if disc <= 0.0 {
                    continue;
                }
                let t = -b - disc.sqrt();
                if t <= 0.0 {
                    continue;
                }
                let a = o.ambient.get_pixel(u, v).0;
                let l = o.lit.get_pixel(u, v).0;
                if a.iter().chain(l.iter()).any(|&x| x >= params.saturation) {
                    continue;
                }
                let sum = |x: [u8; 3]| x.iter().map(|&c| c as f64).sum::<f64>();
                let d = sum(l) - sum(a);
                if d < params.min_direct {
                    continue;
                }
                let p = c + dir * t;
                out.push(Sample { p, n: (p - s.centre_m) / s.radius_m, d });
            }
        }
    }
    Ok(out)
}

/// Fit one point light to views of a calibration sphere (see the module documentation).
pub fn calibrate_point_light(
    observations: &[SphereObservation<'_>],
    params: &LightFitParams,
) -> Result<LightEstimate, LightCalibrationError> {
    if !params.initial_m.iter().all(|x| x.is_finite()) {
        return Err(LightCalibrationError::BadInput { index: observations.len() });
    }
    let samples = samples(observations, params)?;
    if samples.len() < 8 {
        return Err(LightCalibrationError::TooFewPixels { pixels: samples.len() });
    }
    // Parameters x = (Lx, Ly, Lz, k). k from linear least squares at the start.
    let k0 = {
        let (mut num, mut den) = (0.0, 0.0);
        for s in &samples {
            let g = geometry(s, &params.initial_m);
            num += g * s.d;
            den += g * g;
        }
        if den > 0.0 {
            num / den
        } else {
            samples.iter().map(|s| s.d).fold(0.0, f64::max)
        }
    };
    let mut x = Vector4::new(params.initial_m.x, params.initial_m.y, params.initial_m.z, k0);
    let cost = |x: &Vector4<f64>| -> f64 {
        let l = Vector3::new(x[0], x[1], x[2]);
        samples.iter().map(|s| (x[3] * geometry(s, &l) - s.d).powi(2)).sum()
    };
    let mut current = cost(&x);
    let mut lambda = 1e-3;
    let mut iterations = 0;
    for _ in 0..params.max_iterations {
        iterations += 1;
        let l = Vector3::new(x[0], x[1], x[2]);
        let mut jtj = Matrix4::zeros();
        let mut jtr = Vector4::zeros();
        let h = 1e-6;
        for s in &samples {
            let g = geometry(s, &l);
            let r = x[3] * g - s.d;
            let mut j = Vector4::zeros();
            for a in 0..3 {
                let mut lp = l;
                lp[a] += h;
                let mut lm = l;
                lm[a] -= h;
                j[a] = x[3] * (geometry(s, &lp) - geometry(s, &lm)) / (2.0 * h);
            }
            j[3] = g;
            jtj += j * j.transpose();
            jtr += j * r;
        }
        let mut improved = false;
        for _ in 0..20 {
            let mut a = jtj;
            for i in 0..4 {
                a[(i, i)] += lambda * jtj[(i, i)].max(1e-12);
            }
            let Some(step) = a.lu().solve(&(-jtr)) else {
                lambda *= 10.0;
                continue;
            };
            let candidate = x + step;
            let c = cost(&candidate);
            if c.is_finite() && c < current {
                let rel = (current - c) / current.max(1e-30);
                x = candidate;
                current = c;
                lambda = (lambda * 0.3).max(1e-12);
                improved = rel > 1e-12 && step.fixed_rows::<3>(0).norm() > 1e-9;
                break;
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
    }
    let position_m = Vector3::new(x[0], x[1], x[2]);
    if !(x.iter().all(|v| v.is_finite()) && x[3] > 0.0) {
        return Err(LightCalibrationError::Diverged);
    }
    if observations.iter().any(|o| (position_m - o.sphere.centre_m).norm() <= o.sphere.radius_m) {
        return Err(LightCalibrationError::Diverged);
    }
    Ok(LightEstimate {
        position_m,
        power: x[3],
        rms_levels: (current / samples.len() as f64).sqrt(),
        pixels: samples.len(),
        iterations,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{Intrinsics, Pose};

    fn camera() -> CameraModel {
        CameraModel {
            width: 160,
            height: 120,
            intrinsics: Intrinsics {
                fx: 400.0,
                fy: 400.0,
                cx: 80.0,
                cy: 60.0,
                skew: 0.0,
                k1: 0.0,
                k2: 0.0,
                ..Intrinsics::default()
            },
            pose: Pose::look_at(Vector3::new(0.0, -0.4, 0.2), Vector3::new(0.0, 0.0, 0.03), Vector3::z()),
        }
    }

    /// Render the model itself (no noise) and check the fit returns the light.
    #[test]
    fn recovers_a_light_from_its_own_model() {
        let cam = camera();
        let light = Vector3::new(0.15, -0.3, 0.35);
        let k = 400.0;
        let ambient = RgbImage::from_pixel(160, 120, image::Rgb([40, 40, 40]));
        let spheres = [Vector3::new(0.03, 0.0, 0.03), Vector3::new(-0.03, 0.0, 0.03), Vector3::new(0.0, 0.03, 0.03)];
        let frames: Vec<RgbImage> = spheres
            .iter()
            .map(|c| {
                let sphere = Sphere { centre_m: *c, radius_m: 0.025 };
                RgbImage::from_fn(160, 120, |u, v| {
                    let dir = cam.pixel_ray(u as f64 + 0.5, v as f64 + 0.5);
                    let oc = cam.centre() - sphere.centre_m;
                    let b = oc.dot(&dir);
                    let disc = b * b - (oc.norm_squared() - 0.025 * 0.025);
                    if disc <= 0.0 {
                        return image::Rgb([40, 40, 40]);
                    }
                    let p = cam.centre() + dir * (-b - disc.sqrt());
                    let s = Sample { p, n: (p - sphere.centre_m) / 0.025, d: 0.0 };
                    let per = (k * geometry(&s, &light) / 3.0).round();
                    let c = (40.0 + per).min(249.0) as u8;
                    image::Rgb([c, c, c])
                })
            })
            .collect();
        let obs: Vec<SphereObservation<'_>> = spheres
            .iter()
            .zip(&frames)
            .map(|(c, f)| SphereObservation {
                camera: cam,
                sphere: Sphere { centre_m: *c, radius_m: 0.025 },
                ambient: &ambient,
                lit: f,
            })
            .collect();
        let start = light + Vector3::new(-0.05, 0.04, -0.03);
        let est = calibrate_point_light(&obs, &LightFitParams::new(start)).expect("fit");
        let err = (est.position_m - light).norm();
        assert!(err < 0.01, "error {err} m, estimate {:?}", est.position_m);
        assert!(est.rms_levels < 2.0);
    }

    #[test]
    fn a_dark_sphere_is_too_few_pixels() {
        let cam = camera();
        let black = RgbImage::new(160, 120);
        let obs = [SphereObservation {
            camera: cam,
            sphere: Sphere { centre_m: Vector3::new(0.0, 0.0, 0.03), radius_m: 0.025 },
            ambient: &black,
            lit: &black,
        }];
        let r = calibrate_point_light(&obs, &LightFitParams::new(Vector3::new(0.0, -0.3, 0.3)));
        assert!(matches!(r, Err(LightCalibrationError::TooFewPixels { .. })));
        let small = RgbImage::new(10, 10);
        let obs = [SphereObservation { ambient: &small, ..obs[0] }];
        let r = calibrate_point_light(&obs, &LightFitParams::new(Vector3::new(0.0, -0.3, 0.3)));
        assert!(matches!(r, Err(LightCalibrationError::FrameSize { index: 0 })));
    }
}
